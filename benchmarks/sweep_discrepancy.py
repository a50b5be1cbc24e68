"""Many-seed sweep of the discrepancy workflow on simulated benches with hidden effects.

For each baseline (linear, kinematic) and grid design (serpentine: seed 000's single
serpentine pass; random: the same 81 points in random order; grid10: the serpentine 9 x 9 with each
point a mean of 10 readings, as today's job records it; adaptive: the adaptive job's 4 x 4 spread,
each point a mean of 50 readings; adaptive3: a 3 x 3 spread, 90 readings a point;
benchmarks/hidden_effects.py):

* no hidden effect (coupling and mounting effects only): how often an effect that is not in
  the data is named (target: at most 2 % of runs, all candidates together);
* every candidate alone and every pair, each at 5 times the noise level: how often it is
  named (target: at least 95 %), and whether the final residual reaches the noise level;
* a magnitude ladder per candidate: the detection limit, the smallest multiple of the noise
  named in at least 95 % of runs.

Sizes are defined in benchmarks/hidden_effects.py (largest mean-free change of a reading over
the grid; amplitude for the periodic error). The noise level is given to the workflow as
the instrument's specification (1-sigma of one reading), except in the `null-residual` case.

    python benchmarks/sweep_discrepancy.py                      # everything, 50 seeds, 2 workers
    python benchmarks/sweep_discrepancy.py --seeds 10 --baselines linear --designs serpentine
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.hidden_effects import VARIANTS, bench_with_hidden  # noqa: E402
from service.discrepancy.stage import stage_report  # noqa: E402
from service.errors import InputError  # noqa: E402

PAIR_EFFECTS = (
    "backlash",
    "periodic_error",
    "sensor_nonlinearity",
    "temperature_drift",
    "time_drift",
)
LADDER = (0.3, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 7.0, 10.0, 15.0, 20.0, 30.0, 40.0)
TARGET_RATE = 0.95
# variant -> label of the fitted parameter that carries it, and how to read the truth
TRUE_PARAM = {
    "backlash": ("x_deg", lambda p, s: p["backlash"]["x_deg"]),
    "periodic_error": ("x_amp_deg", lambda p, s: p["periodic_error"]["x_amp_deg"]),
    "periodic_error_y": ("y_amp_deg", lambda p, s: p["periodic_error"]["y_amp_deg"]),
    "sensor_nonlinearity": (
        "{s}_x_per_deg",
        lambda p, s: p["sensor_nonlinearity"][f"{s}_x_per_deg"],
    ),
    "sensor_nonlinearity_y": (
        "{s}_y_per_deg",
        lambda p, s: p["sensor_nonlinearity"][f"{s}_y_per_deg"],
    ),
    "temperature_drift": (
        "{s}_x_deg_per_k",
        lambda p, s: p["temperature_drift"][f"{s}_x_deg_per_k"],
    ),
    "time_drift": ("{s}_x_deg_per_h", lambda p, s: p["time_drift"][f"{s}_x_deg_per_h"]),
}


def effect_of(variant: str) -> str:
    return VARIANTS[variant][0]


def one_run(task: dict) -> dict:
    """One simulated bench, one workflow run: what was named, and how close the end came to the
    noise."""
    hidden = task["hidden"]
    sensor = task.get("sensor", "ref")
    try:
        hb = bench_with_hidden(task["seed"], hidden, task["design"], sensor)
    except InputError as exc:
        # the size asks for a parameter the bench description does not allow (a time drift fast
        # enough to show on a short record): not a run, said as such
        return {**task, "unrepresentable": str(exc), "named": [], "hit": False, "false": []}
    noise = None if task.get("noise") == "residual" else hb.sigma_deg
    t0 = time.perf_counter()
    rep, _, _ = stage_report(hb.columns, sensor, task["baseline"], noise)
    dt = time.perf_counter() - t0
    named = [e for e in rep["named_effects"] if e != "offaxis_coupling"]
    want = {effect_of(v) for v in hidden}
    out = {
        **task,
        "named": named,
        "hit": want <= set(named),
        "false": sorted(set(named) - want),
        "final_over_noise": rep["final_vs_noise"]["rms_over_noise"],
        "chi2_p": rep["final_vs_noise"]["p_value"],
        "seconds": dt,
        "coupling_named": "offaxis_coupling" in rep["named_effects"]
        or task["baseline"] != "linear",
    }
    if len(hidden) == 1:
        (variant,) = hidden
        label, truth = TRUE_PARAM[variant]
        label = label.format(s=sensor)
        true_value = truth(hb.params, sensor)
        for st in rep["steps"]:
            if st["effect"] == effect_of(variant) and label in st["magnitude"]:
                m = st["magnitude"][label]
                out["estimate"] = {
                    "value": m["value"],
                    "uncertainty": m["uncertainty"],
                    "true": true_value,
                }
    return out


def run_tasks(pool, tasks: list[dict]) -> list[dict]:
    return list(pool.imap_unordered(one_run, tasks, chunksize=4))


def rate(rows, key="hit") -> float:
    return sum(bool(r[key]) for r in rows) / max(len(rows), 1)


def summarise_gap(rows) -> str:
    ratios = np.array([r["final_over_noise"] for r in rows], dtype=float)
    ps = [r["chi2_p"] for r in rows if r["chi2_p"] is not None]
    ok = sum(p >= 0.01 for p in ps) / max(len(ps), 1)
    return (
        f"final RMS/noise median {np.median(ratios[:, 0]):.2f}, {np.median(ratios[:, 1]):.2f} "
        f"(95th pct {np.percentile(ratios.max(axis=1), 95):.2f}); chi2 p >= 0.01 in "
        f"{100 * ok:.0f} %"
    )


def pct(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:.0f} %"


NOT_REPRESENTABLE = "not representable"  # the size asks for a parameter outside the bench's bounds


def _single(block: dict, variant: str, key: str) -> str:
    """One single-effect figure of a block for the tables."""
    if "singles_5x" not in block:
        return "—"
    one = block["singles_5x"][variant]
    return NOT_REPRESENTABLE if "unrepresentable" in one else pct(one[key])


def ladder(pool, base_task: dict, seeds, variants, singles: dict) -> dict:
    """Smallest multiple of the noise named in >= 95 % of runs, per variant (None if not within the
    ladder)."""
    state = {}
    for v in variants:
        r5 = rate(singles[v])
        state[v] = {"rates": {5.0: r5}, "dir": -1 if r5 >= TARGET_RATE else +1, "done": False}
    while True:
        todo = {}
        for v, st in state.items():
            if st["done"]:
                continue
            tried = sorted(st["rates"])
            if st["dir"] < 0:
                lower = [m for m in LADDER if m < min(tried)]
                nxt = lower[-1] if lower else None
            else:
                higher = [m for m in LADDER if m > max(tried)]
                nxt = higher[0] if higher else None
            if nxt is None:
                st["done"] = True
            else:
                todo[v] = nxt
        if not todo:
            break
        tasks = [
            {**base_task, "hidden": {v: m}, "seed": s}
            for v, m in todo.items()
            for s in range(seeds)
        ]
        res = run_tasks(pool, tasks)
        for v, m in todo.items():
            rows = [x for x in res if x["hidden"] == {v: m}]
            st = state[v]
            if any("unrepresentable" in x for x in rows):
                st["done"], st["unrepresentable_from"] = True, m
                continue
            r = rate(rows)
            st["rates"][m] = r
            if st["dir"] < 0 and r < TARGET_RATE:
                st["done"] = True
            if st["dir"] > 0 and r >= TARGET_RATE:
                st["done"] = True
        print(f"    ladder round: {', '.join(f'{v} x{m:g}' for v, m in todo.items())}", flush=True)
    limits = {}
    for v, st in state.items():
        passing = sorted(m for m, r in st["rates"].items() if r >= TARGET_RATE)
        if st["dir"] < 0:
            # going down: the limit is the smallest passing level above the first failure
            failing = [m for m, r in st["rates"].items() if r < TARGET_RATE]
            floor = max(failing) if failing else 0.0
            limits[v] = min(m for m in passing if m > floor)
        else:
            limits[v] = passing[0] if passing else None
        st.pop("done")
    return {
        "limits": limits,
        "unrepresentable_from": {
            v: st["unrepresentable_from"] for v, st in state.items() if "unrepresentable_from" in st
        },
        "rates": {
            v: {str(k): r for k, r in sorted(st["rates"].items())} for v, st in state.items()
        },
    }


def timing_cli() -> dict:
    """Wall time of `tiltlab discrepancy` on an 81-point grid with every candidate testable."""
    from service.io.datasets import write_dataset

    hb = bench_with_hidden(0, {"backlash": 5.0}, "serpentine")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "bench.csv"
        write_dataset(data, hb.columns)
        for baseline in ("linear", "kinematic"):
            walls = []
            for _ in range(3):
                t0 = time.perf_counter()
                r = subprocess.run(
                    [
                        sys.executable,
                        "-m",
                        "service",
                        "discrepancy",
                        "--kind",
                        "stage",
                        "--input",
                        str(data),
                        "--out",
                        str(Path(tmp) / "r.json"),
                        "--baseline",
                        baseline,
                    ],
                    capture_output=True,
                    text=True,
                    cwd=ROOT,
                )
                walls.append(time.perf_counter() - t0)
                if r.returncode != 0:
                    raise RuntimeError(r.stderr)
            rep = json.loads((Path(tmp) / "r.json").read_text())
            out[baseline] = {
                "wall_s": walls,
                "median_s": statistics.median(walls),
                "chain": rep["chain"],
                "candidates_tested": len(rep["steps"][0]["evidence"]["candidates"])
                if rep["steps"]
                else None,
                "skipped": rep["skipped"],
            }
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--null-seeds", type=int, default=300)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--baselines", default="linear,kinematic")
    ap.add_argument("--designs", default="serpentine,random")
    ap.add_argument("--no-ladder", action="store_true")
    ap.add_argument(
        "--sensor",
        default="ref",
        choices=["ref", "meas"],
        help="sensor whose readings are compared",
    )
    ap.add_argument("--null-only", action="store_true", help="only the no-hidden-effect runs")
    ap.add_argument("--no-timing", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "docs/examples/discrepancy/sweep_results.json"))
    ap.add_argument(
        "--markdown", metavar="RESULTS.json", help="print the tables of a finished sweep and exit"
    )
    args = ap.parse_args(argv)
    if args.markdown:
        print(markdown(args.markdown))
        return 0
    workers = max(1, min(args.workers, 2))
    results: dict = {
        "seeds": args.seeds,
        "null_seeds": args.null_seeds,
        "target_rate": TARGET_RATE,
        "runs": {},
    }
    t_start = time.time()
    results["sensor"] = args.sensor
    if not args.no_timing:
        print(
            "timing of one 81-point run with all candidates (tiltlab discrepancy, wall clock, "
            f"{os.cpu_count()} cores shared):",
            flush=True,
        )
        results["timing"] = timing_cli()
        for b, t in results["timing"].items():
            print(
                f"  {b}: median {t['median_s']:.2f} s of "
                f"{', '.join(f'{w:.2f}' for w in t['wall_s'])}; chain {' -> '.join(t['chain'])}",
                flush=True,
            )
    with Pool(workers) as pool:
        for baseline, design in itertools.product(
            args.baselines.split(","), args.designs.split(",")
        ):
            key = f"{baseline}/{design}"
            print(f"\n=== baseline {baseline}, design {design} ===", flush=True)
            block: dict = {}
            # no hidden effect
            base_task = {"baseline": baseline, "design": design, "sensor": args.sensor}
            null = run_tasks(
                pool, [{**base_task, "hidden": {}, "seed": s} for s in range(args.null_seeds)]
            )
            fp = sum(bool(r["false"]) for r in null)
            per = {}
            for r in null:
                for e in r["false"]:
                    per[e] = per.get(e, 0) + 1
            block["null"] = {
                "runs": len(null),
                "false_named": fp,
                "rate": fp / len(null),
                "by_effect": per,
                "coupling_named": rate(null, "coupling_named"),
                "gap": summarise_gap(null),
                "mean_seconds": float(np.mean([r["seconds"] for r in null])),
            }
            print(
                f"no hidden effect: false effect named in {fp}/{len(null)} runs "
                f"({100 * fp / len(null):.1f} %) {per or ''}; off-axis coupling named first in "
                f"{100 * rate(null, 'coupling_named'):.0f} %; {block['null']['gap']}; "
                f"{block['null']['mean_seconds']:.2f} s/run",
                flush=True,
            )
            if baseline == "linear" and design == "serpentine":
                nr = run_tasks(
                    pool,
                    [
                        {**base_task, "hidden": {}, "seed": s, "noise": "residual"}
                        for s in range(args.null_seeds)
                    ],
                )
                fpr = sum(bool(r["false"]) for r in nr)
                block["null_residual_noise"] = {
                    "runs": len(nr),
                    "false_named": fpr,
                    "rate": fpr / len(nr),
                }
                print(
                    "no hidden effect, noise from the final residual (F-tests): false effect "
                    f"named in {fpr}/{len(nr)} runs ({100 * fpr / len(nr):.1f} %)",
                    flush=True,
                )
            if args.null_only:
                results["runs"][key] = block
                continue
            # singles at 5x
            singles_rows = run_tasks(
                pool,
                [
                    {**base_task, "hidden": {v: 5.0}, "seed": s}
                    for v in VARIANTS
                    for s in range(args.seeds)
                ],
            )
            singles = {v: [r for r in singles_rows if r["hidden"] == {v: 5.0}] for v in VARIANTS}
            block["singles_5x"] = {}
            print("one hidden effect at 5 x noise:", flush=True)
            for v, rows in singles.items():
                if any("unrepresentable" in r for r in rows):
                    reason = next(r["unrepresentable"] for r in rows if "unrepresentable" in r)
                    block["singles_5x"][v] = {"named_rate": 0.0, "unrepresentable": reason}
                    print(f"  {v:24s} not representable at this size: {reason}", flush=True)
                    continue
                est = [r["estimate"] for r in rows if "estimate" in r]
                z = [
                    (e["value"] - e["true"]) / e["uncertainty"] for e in est if e["uncertainty"] > 0
                ]
                cover = sum(abs(x) <= 2 for x in z) / max(len(z), 1)
                bias = (
                    float(np.median([(e["value"] - e["true"]) / e["true"] for e in est]))
                    if est
                    else None
                )
                block["singles_5x"][v] = {
                    "named_rate": rate(rows),
                    "false_rate": sum(bool(r["false"]) for r in rows) / len(rows),
                    "false_by_effect": _count(rows),
                    "gap": summarise_gap(rows),
                    "estimate_within_2u": cover,
                    "median_relative_bias": bias,
                }
                print(
                    f"  {v:24s} named {100 * rate(rows):5.1f} %  other effect named "
                    f"{100 * block['singles_5x'][v]['false_rate']:4.1f} %  magnitude within ±2u "
                    f"{100 * cover:5.1f} % (median rel. bias "
                    f"{bias if bias is None else f'{bias:+.3f}'})  "
                    f"{block['singles_5x'][v]['gap']}",
                    flush=True,
                )
            # pairs at 5x
            pair_rows = run_tasks(
                pool,
                [
                    {**base_task, "hidden": {a: 5.0, b: 5.0}, "seed": s}
                    for a, b in itertools.combinations(PAIR_EFFECTS, 2)
                    for s in range(args.seeds)
                ],
            )
            block["pairs_5x"] = {}
            print("two hidden effects, each at 5 x noise:", flush=True)
            for a, b in itertools.combinations(PAIR_EFFECTS, 2):
                rows = [r for r in pair_rows if r["hidden"] == {a: 5.0, b: 5.0}]
                if any("unrepresentable" in r for r in rows):
                    block["pairs_5x"][f"{a}+{b}"] = {"both_named": 0.0, "unrepresentable": True}
                    print(f"  {a + ' + ' + b:40s} not representable at this size", flush=True)
                    continue
                each = {e: sum(e in r["named"] for r in rows) / len(rows) for e in (a, b)}
                block["pairs_5x"][f"{a}+{b}"] = {
                    "both_named": rate(rows),
                    "each_named": each,
                    "false_rate": sum(bool(r["false"]) for r in rows) / len(rows),
                    "gap": summarise_gap(rows),
                }
                print(
                    f"  {a + ' + ' + b:40s} both {100 * rate(rows):5.1f} %  ({a} "
                    f"{100 * each[a]:.0f} %, {b} {100 * each[b]:.0f} %)  other effect named "
                    f"{100 * block['pairs_5x'][f'{a}+{b}']['false_rate']:4.1f} %  "
                    f"{summarise_gap(rows)}",
                    flush=True,
                )
            if not args.no_ladder:
                print(
                    "detection limits (smallest multiple of the noise named in >= 95 % of runs):",
                    flush=True,
                )
                lad = ladder(pool, base_task, args.seeds, list(VARIANTS), singles)
                block["ladder"] = lad
                for v in VARIANTS:
                    lim = lad["limits"][v]
                    rates = ", ".join(f"x{k}: {100 * r:.0f} %" for k, r in lad["rates"][v].items())
                    print(
                        f"  {v:24s} limit {'> ' + str(LADDER[-1]) if lim is None else f'{lim:g}'} "
                        "x noise  "
                        f"[{rates}]",
                        flush=True,
                    )
            results["runs"][key] = block
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out).write_text(json.dumps(results, indent=1))
    results["elapsed_s"] = time.time() - t_start
    Path(args.out).write_text(json.dumps(results, indent=1))
    print(f"\nwrote {args.out}; {results['elapsed_s'] / 60:.1f} min", flush=True)
    return 0


def markdown(path: str) -> str:
    """The sweep's figures as the Markdown tables of docs/discrepancy.md."""
    res = json.loads(Path(path).read_text())
    out = []
    keys = list(res["runs"])
    out.append(
        f"Seeds per case: {res['seeds']} (no hidden effect: {res['null_seeds']}); target rate "
        f"{100 * res['target_rate']:.0f} %; sensor {res.get('sensor', 'ref')}.\n"
    )
    out.append("| case | " + " | ".join(keys) + " |")
    out.append("| --- |" + " --- |" * len(keys))
    row = lambda name, f: out.append(
        f"| {name} | " + " | ".join(f(res["runs"][k]) for k in keys) + " |"
    )  # noqa: E731
    row(
        "no hidden effect: a false effect named",
        lambda b: (
            f"{b['null']['false_named']}/{b['null']['runs']} ({100 * b['null']['rate']:.1f} %)"
        ),
    )
    row(
        "no hidden effect, noise from the final residual",
        lambda b: (
            f"{b['null_residual_noise']['false_named']}/{b['null_residual_noise']['runs']}"
            if "null_residual_noise" in b
            else "—"
        ),
    )
    row(
        "no hidden effect: final χ² p ≥ 0.01",
        lambda b: b["null"]["gap"].split("; ")[-1].replace("chi2 p >= 0.01 in ", ""),
    )
    variants = list(next(iter(res["runs"].values())).get("singles_5x", {}))
    for v in variants:
        row(
            f"`{v}` at 5×: named",
            lambda b, v=v: _single(b, v, "named_rate"),
        )
    for v in variants:
        row(
            f"`{v}` at 5×: other effect named",
            lambda b, v=v: _single(b, v, "false_rate"),
        )
    for v in variants:
        row(
            f"`{v}`: magnitude within ±2u of truth",
            lambda b, v=v: (
                pct(b["singles_5x"][v]["estimate_within_2u"])
                if "singles_5x" in b
                and b["singles_5x"][v].get("estimate_within_2u") is not None
                and b["singles_5x"][v]["named_rate"] > 0
                else "—"
            ),
        )
    pairs = list(next(iter(res["runs"].values())).get("pairs_5x", {}))
    for pr in pairs:
        row(
            f"pair `{pr}` at 5×: both named",
            lambda b, pr=pr: (
                "—"
                if "pairs_5x" not in b
                else NOT_REPRESENTABLE
                if "unrepresentable" in b["pairs_5x"][pr]
                else pct(b["pairs_5x"][pr]["both_named"])
            ),
        )
    row(
        "pairs: other effect named (worst pair)",
        lambda b: (
            pct(max(x.get("false_rate", 0.0) for x in b["pairs_5x"].values()))
            if "pairs_5x" in b
            else "—"
        ),
    )
    for v in variants:

        def lim(b, v=v):
            if "ladder" not in b:
                return "—"
            m = b["ladder"]["limits"][v]
            beyond = b["ladder"].get("unrepresentable_from", {}).get(v)
            if m is None and beyond is not None:
                tried = max(float(k) for k in b["ladder"]["rates"][v])
                return f"> {tried:g}× ({NOT_REPRESENTABLE} from {beyond:g}×)"
            return f"> {LADDER[-1]:g}×" if m is None else f"{m:g}×"

        row(f"`{v}`: detection limit", lim)
    return "\n".join(out)


def _count(rows) -> dict:
    per: dict = {}
    for r in rows:
        for e in r["false"]:
            per[e] = per.get(e, 0) + 1
    return per


if __name__ == "__main__":
    raise SystemExit(main())
