#!/usr/bin/env python3
"""Benchmark of the evaluation code: map metrics on a few million points, ATE on KITTI 00.

    python scripts/bench_eval.py [--points 2000000] [--runs 5]

Prints the median and the spread (min-max) over ``--runs`` runs. Figures depend on the machine
and on its load (other processes on a shared 2-core machine make them indicative only).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src", "mdr_slam", "src"))


def _time(fn, runs):
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), float(min(ts)), float(max(ts))


def main(argv=None):
    from mdr_slam.eval import ate, map_metrics, read_for_eval
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=2000000, help="points in each cloud")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--data", default=os.path.join(os.path.dirname(os.path.dirname(HERE)), "shared", "data"))
    a = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    # a surface-like cloud: points on the faces of a 10 m room, like a fused map
    n = a.points
    P = rng.uniform(0, 10, (n, 3))
    face = rng.integers(0, 6, n)
    P[np.arange(n), face % 3] = np.where(face < 3, 0.0, 10.0)
    est = P + rng.normal(0, 0.01, P.shape)
    labels = (face % 3 + 1).astype(np.uint8)
    med, lo, hi = _time(lambda: map_metrics(est, P, gt_labels=labels), a.runs)
    print("map_metrics %d vs %d points (labels): median %.2f s (min %.2f, max %.2f) over %d runs"
          % (n, n, med, lo, hi, a.runs))
    gt = os.path.join(a.data, "trajectories", "evo", "KITTI_00_gt.txt")
    if os.path.exists(gt):
        e, g = read_for_eval(os.path.join(os.path.dirname(gt), "KITTI_00_ORB.txt")), read_for_eval(gt)
        med, lo, hi = _time(lambda: ate(e, g, "se3"), a.runs)
        print("ATE KITTI 00 (4541 poses, SE(3)): median %.3f s (min %.3f, max %.3f) over %d runs"
              % (med, lo, hi, a.runs))
    else:
        print("KITTI 00 trajectories not found under %s: ATE benchmark skipped" % a.data)
    return 0


if __name__ == "__main__":
    sys.exit(main())
