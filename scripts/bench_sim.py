#!/usr/bin/env python3
"""Benchmark ``mdr_slam.sim.generate``: wall time of the default 30 s office sequence.

Prints the wall time of every run, then median and spread, plus the per-frame render time the
workers measured. The machine may be shared: figures are indicative, compare on one machine.

    python scripts/bench_sim.py [--runs 3] [--duration 30] [--scene office] [--workers 2]
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src", "mdr_slam", "src"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--scene", default="office")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--distort", action="store_true")
    ap.add_argument("--keep", default=None, help="keep the last output in this folder")
    args = ap.parse_args(argv)

    import numpy as np
    from mdr_slam.sim import generate

    walls, med_ms, mean_ms = [], [], []
    for i in range(args.runs):
        out = tempfile.mkdtemp(prefix="bench_sim_")
        try:
            cpu0 = os.times()
            t0 = time.perf_counter()
            s = generate(out, scene=args.scene, duration=args.duration, workers=args.workers,
                         scale=args.scale, distort=args.distort)
            wall = time.perf_counter() - t0
            cpu1 = os.times()
            cpu = (cpu1.user - cpu0.user) + (cpu1.system - cpu0.system) + \
                (cpu1.children_user - cpu0.children_user) + \
                (cpu1.children_system - cpu0.children_system)
            tm = s["timing"]
            walls.append(wall)
            med_ms.append(tm["render_ms_per_frame_median"])
            mean_ms.append(tm["render_ms_per_frame_mean"])
            print("run %d: %s %d frames %dx%d -> wall %.1f s, CPU %.1f s, render %.1f ms/frame "
                  "median (%.1f mean), bag write %.1f s, load avg %.1f" % (
                      i + 1, args.scene, s["n_frames"], s["camera"]["width"],
                      s["camera"]["height"], wall, cpu, tm["render_ms_per_frame_median"],
                      tm["render_ms_per_frame_mean"], tm["bag_write_s"], os.getloadavg()[0]),
                  flush=True)
            if args.keep and i == args.runs - 1:
                shutil.rmtree(args.keep, ignore_errors=True)
                shutil.copytree(out, args.keep)
        finally:
            shutil.rmtree(out, ignore_errors=True)
    w = np.array(walls)
    print("generate %s %.0f s: wall median %.1f s (min %.1f, max %.1f, n=%d); render median "
          "%.1f ms/frame (per-run medians %s)" % (
              args.scene, args.duration, np.median(w), w.min(), w.max(), len(w),
              float(np.median(med_ms)), ", ".join("%.1f" % m for m in med_ms)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
