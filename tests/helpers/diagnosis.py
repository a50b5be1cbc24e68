"""The calibration requests the diagnosis tests make on the 180:1 / 360:1 bench, and the wait for a
diagnosis to end."""

from __future__ import annotations

from tests.helpers.waiting import eventually

# 7 x 7 points 2.4 deg apart: the 180:1 upper worm (2-deg period) and the 360:1 lower one (1 deg)
# are each sampled at five phases
GRID = {"x_deg": [-7.2, 7.2], "y_deg": [-7.2, 7.2], "n_x": 7, "n_y": 7}
BODY = {
    "procedure": "stage-grid",
    "method": "kinematic",
    "grid": GRID,
    "samples_per_point": 8,
    "validation": {"n_points": 4},
    "settle": {"tolerance_deg": 0.005, "window_s": 0.5, "timeout_s": 60},
}
# A record to refer to, quickly made: 3 x 3 points
SMALL_BODY = {**BODY, "grid": {"x_deg": [-2, 2], "y_deg": [-2, 2], "n_x": 3, "n_y": 3}}


def wait_diagnosis(client, h, diagnosis_id: int, timeout_s: float = 300.0) -> dict:
    """The diagnosis once it has succeeded or failed."""
    return eventually(
        lambda: client.get(f"/diagnoses/{diagnosis_id}", headers=h).json(),
        until=lambda d: d["state"] in ("succeeded", "failed"),
        timeout_s=timeout_s,
        every_s=0.2,
        what=f"diagnosis {diagnosis_id} ended",
    )


# A diagnosis names an effect when its test passes at a family-wise 1 % a selection step, so on a
# bench that holds nothing more it names a second, chance effect in about one diagnosis in a
# hundred (and a test that asks for "nothing else" fails as often). An effect the bench really holds
# is named with a far smaller p-value (the hidden effects of these tests: 1e-20 and below). So the
# tests ask that nothing else is named beyond chance: any other effect's p-value at least this.
CHANCE_P = 1e-4


def named_beyond_chance(d: dict, planted: tuple[str, ...] = ()) -> list[tuple[str, float]]:
    """The effects a diagnosis named, other than `planted`, with a p-value below CHANCE_P: what a
    test that hid only `planted` must not see."""
    return [
        (effect["effect"], effect["evidence"]["p_value"])
        for effect in d["effects"]
        if effect["effect"] not in planted and effect["evidence"]["p_value"] < CHANCE_P
    ]
