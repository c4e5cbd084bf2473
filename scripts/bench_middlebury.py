#!/usr/bin/env python3
"""Single-frame stereo on Middlebury: libelas (what node 2 runs) next to OpenCV StereoSGBM.

    python scripts/bench_middlebury.py [--root DIR]

Bad-pixel rates (> 2 px and > 1 px, over pixels with both ground truth and an estimate, the way
the shared data README scores SGBM), density (share of ground-truth pixels with an estimate), and
bad > 2 px over all ground-truth pixels (a missing estimate counts as bad). SGBM uses the settings
that reproduce the README's published figures (block 5, HH, 64 disparities); ELAS uses libelas's
Middlebury preset with the same 64-disparity range, full resolution (no subsampling).
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "src", "mdr_slam",
                                "src"))

from mdr_slam.depth import ElasMatcher  # noqa: E402
from mdr_slam.eval import depth_metrics, load_middlebury  # noqa: E402

PAIRS = ("cones", "teddy", "tsukuba", "venus")


def sgbm(left, right):
    import cv2
    s = cv2.StereoSGBM_create(minDisparity=0, numDisparities=64, blockSize=5, P1=8 * 25, P2=32 * 25,
                              disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100,
                              speckleRange=2, mode=cv2.STEREO_SGBM_MODE_HH)
    return s.compute(left, right).astype(np.float32) / 16.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", default=None, help="Middlebury folder (default: ../shared/data/middlebury)")
    args = ap.parse_args()
    elas = ElasMatcher({"preset": "middlebury", "disp_min": 0, "disp_max": 63, "subsampling": False})
    rows = []
    for name in PAIRS:
        try:
            left, right, gt = load_middlebury(name, args.root)
        except (OSError, ValueError) as e:
            print("skipping %s: %s" % (name, e))
            continue
        for method, fn in (("ELAS", elas.compute), ("SGBM", sgbm)):
            m = depth_metrics(fn(left, right), gt)
            rows.append((name, method, 100 * m["bad2"], 100 * m["bad1"], 100 * m["density"],
                         100 * m.get("bad2_all", float("nan")), m["mae"]))
    print("| pair | method | bad > 2 px | bad > 1 px | density | bad > 2 px, holes count as bad | MAE (px) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print("| %s | %s | %.2f %% | %.2f %% | %.1f %% | %.2f %% | %.3f |" % r)
    for method in ("ELAS", "SGBM"):
        sel = [r for r in rows if r[1] == method]
        if sel:
            print("| mean | %s | %.2f %% | %.2f %% | %.1f %% | %.2f %% | %.3f |" % (
                (method,) + tuple(float(np.mean([r[i] for r in sel])) for i in range(2, 7))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
