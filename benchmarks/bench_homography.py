"""Benchmark of the seed 000 homography fit in-process, beside OpenCV's `findHomography`.

    python benchmarks/bench_homography.py [--repeats 200]

On seed 000's 81-point grid: one homography (H2, measurement -> reference, all 81 points:
normalised DLT and the refinement of the transfer error) by tiltlab and by
`cv2.findHomography(src, dst, 0)` (DLT then Levenberg-Marquardt) on the same points, their
largest difference on the grid, and the whole `homography` method (H1, H2, H2's covariance
and the model record). Runs are interleaved so that load hits all alike; the ratios to OpenCV
hold on a shared machine where the milliseconds do not. OpenCV is the yardstick only
(`pip install opencv-python-headless`); tiltlab does not need it.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import cv2
import numpy as np

from service.calibration.projective import apply_projective, fit_projective
from service.calibration.registry import FitOptions, get_method
from service.scenarios import load_scenario, run_scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=200)
    args = ap.parse_args()
    cols = run_scenario(load_scenario("seed000"), seed=0).columns
    mx, my, rx, ry = (
        np.asarray(cols[c], dtype=float)
        for c in ("meas_x_deg", "meas_y_deg", "ref_x_deg", "ref_y_deg")
    )
    src = np.column_stack([mx, my]).astype(np.float64)
    dst = np.column_stack([rx, ry]).astype(np.float64)
    method = get_method("stage", "homography")
    cases = {
        "cv2.findHomography, 81 points": lambda: cv2.findHomography(src, dst, 0),
        "tiltlab one homography (fit_projective)": lambda: fit_projective(mx, my, rx, ry),
        "tiltlab homography method (H1 + H2 + covariance)": lambda: method.fit(cols, FitOptions()),
    }
    for f in cases.values():  # warm-up (imports, caches)
        f()
    load_before = os.getloadavg()
    times: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(args.repeats):
        for name, f in cases.items():
            t0 = time.perf_counter()
            f()
            times[name].append(time.perf_counter() - t0)
    load_after = os.getloadavg()
    H_cv, _ = cv2.findHomography(src, dst, 0)
    H = fit_projective(mx, my, rx, ry)
    ours, theirs = apply_projective(H, mx, my), apply_projective(H_cv, mx, my)
    diff = max(float(np.abs(ours[0] - theirs[0]).max()), float(np.abs(ours[1] - theirs[1]).max()))
    yardstick = statistics.median(times["cv2.findHomography, 81 points"])
    print(
        f"load average (1, 5, 15 min): before {load_before[0]:.2f} {load_before[1]:.2f} "
        f"{load_before[2]:.2f}, after {load_after[0]:.2f} {load_after[1]:.2f} "
        f"{load_after[2]:.2f}; {os.cpu_count()} cores; numpy {np.__version__}, OpenCV "
        f"{cv2.__version__}"
    )
    for name, t in times.items():
        print(
            f"{name:50s} median {statistics.median(t) * 1e3:7.3f} ms of {args.repeats} "
            f"(min {min(t) * 1e3:.3f})  {statistics.median(t) / yardstick:6.2f} x OpenCV"
        )
    print(f"largest difference of the mapped grid, tiltlab vs OpenCV: {diff:.2e} deg")


if __name__ == "__main__":
    main()
