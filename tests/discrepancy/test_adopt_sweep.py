"""Adopting never fails after the diagnosis said it could, over the hidden-effect sweep.

The cases of benchmarks/sweep_discrepancy.py (every candidate alone and every pair, each at 5 times
the noise, on seed 000's bench with its mounting drawn per seed; serpentine and random order), one
seed per case instead of fifty: the kinematic diagnosis runs, the adoption of each named effect is
decided as the daemon decides it (by the refit adopting makes), and for every effect said adoptable
the adopting refit succeeds. A named effect said not adoptable carries its reason and the
measurement that would tell.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from benchmarks.hidden_effects import VARIANTS, bench_with_hidden
from benchmarks.sweep_discrepancy import PAIR_EFFECTS
from service.discrepancy.adopt import adopted_model, adoption, seen_labels_of, worm_axes_of
from service.discrepancy.stage import analyse_stage
from service.discrepancy.workflow import to_report
from service.physics.stage import StageBench

CASES = (
    [{v: 5.0} for v in VARIANTS]
    + [{a: 5.0, b: 5.0} for a, b in itertools.combinations(PAIR_EFFECTS, 2)]
    + [{}]
)


def _case_id(hidden: dict) -> str:
    return "+".join(hidden) or "nothing"


@pytest.mark.parametrize("index,hidden", list(enumerate(CASES)), ids=[_case_id(h) for h in CASES])
def test_an_effect_said_adoptable_is_adopted(index, hidden):
    design = "random" if index % 2 else "serpentine"
    hb = bench_with_hidden(100 + index, hidden, design)
    bench = StageBench(**hb.scenario["bench"])
    res, fam = analyse_stage(hb.columns, "ref", "kinematic", hb.sigma_deg, bench)
    named = list(res.named_effects)
    verdicts = adoption(
        hb.columns, named, "ref", bench, "the sweep's bench", frozenset(), seen_labels_of(res.steps)
    )
    assert [v.effect for v in verdicts] == named
    for v in verdicts:
        if not v.adoptable:
            assert v.reason and v.measurement, v
    ok = [v.effect for v in verdicts if v.adoptable]
    if ok:  # what the daemon's adopt does with them: never a failure after the diagnosis said yes
        model = adopted_model(
            hb.columns,
            ok,
            "ref",
            bench,
            "the sweep's bench",
            {"what": "the sweep"},
            worm_axes=worm_axes_of([v.as_dict() for v in verdicts]),
        )
        assert model.state["added_effects"] == ok
        assert np.isfinite(model.covariance).all()
        for effect in ok:
            assert any(
                n.startswith(f"{effect}.") and not p.fixed for n, p in model.parameters.items()
            ), effect
    report = to_report(res, fam)
    assert report["named_effects"] == named
