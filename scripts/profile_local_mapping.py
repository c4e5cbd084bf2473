#!/usr/bin/env python3
"""CPU cost per keyframe of each LocalMapping step (and LoopClosing), offline and deterministic.

    python scripts/profile_local_mapping.py [--bag output/sample/sequence.bag --frames 600]
    python scripts/profile_local_mapping.py --kitti [DIR]       # the KITTI 06 clip
    python scripts/profile_local_mapping.py --set n_features=1000 local_ba=false

Runs mdr_slam.pose.System(threads=False) so mapping runs synchronously after each frame; every
step is timed with time.thread_time (CPU of the calling thread: far less inflated by a loaded
machine than wall time). Prints keyframes made, ATE, per-step mean/median/p90 ms per keyframe and
the process CPU. Set OPENBLAS_NUM_THREADS=1 to measure the one-core cost without BLAS helper
threads (as the pose node runs with blas_threads: 1).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "src", "mdr_slam", "src"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

STEPS = ("process_new_keyframe", "map_point_culling", "create_new_map_points", "local_ba",
         "keyframe_culling", "run_once", "loop_closing")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bag", default=os.path.join(ROOT, "output", "sample", "sequence.bag"))
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--kitti", nargs="?", const=os.path.join(os.path.dirname(ROOT), "shared",
                                                             "data", "kitti06_clip"))
    ap.add_argument("--set", nargs="*", default=[], help="pose parameters KEY=JSON")
    args = ap.parse_args(argv)
    from bench_pose import bag_frames, kitti
    from mdr_slam.pose import System
    from mdr_slam.pose.evaluate import ate_rmse
    from mdr_slam.pose.optimizer import Optimizer
    params = {}
    if args.kitti:
        cam, frames, stamps, gt, _ = kitti(args.kitti)
        params["max_frames"] = 10          # as bench_pose
    else:
        cam, frames, stamps, gt, _ = bag_frames(args.bag, args.frames)
    for kv in args.set:
        k, v = kv.split("=", 1)
        params[k] = json.loads(v)
    acc = {}

    def timed(name, fn):
        def w(*a, **k):
            c0 = time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                acc.setdefault(name, []).append(1000.0 * (time.thread_time() - c0))
        return w

    orig = Optimizer.local_bundle_adjustment
    Optimizer.local_bundle_adjustment = staticmethod(timed("local_ba", orig))
    try:
        s = System(cam, config=params, threads=False)
        lm = s.local_mapping
        for name in STEPS[:3] + STEPS[4:6]:
            setattr(lm, name, timed(name, getattr(lm, name)))
        if s.loop_closing is not None:
            s.loop_closing.process = timed("loop_closing", s.loop_closing.process)
        p0, c_main = time.process_time(), 0.0
        for t, (l, r) in zip(stamps, frames):
            c0 = time.thread_time()
            s.track(float(t), l, r)
            c_main += time.thread_time() - c0
        cpu = time.process_time() - p0
        s.shutdown()
    finally:
        Optimizer.local_bundle_adjustment = orig
    traj = s.trajectory()
    mapping = (sum(acc.get("run_once", [])) + sum(acc.get("loop_closing", []))) / 1000.0
    print("params %s | frames %d posed %d | ATE %.3f m | keyframes made %d, alive %d | map points "
          "%d | loops %s | process CPU %.1f s (main thread %.1f s: mapping+loop %.1f s, tracking "
          "%.1f ms/frame) | load %.1f" % (
              params, len(frames), len(traj), ate_rmse(traj, gt), s.map.next_kf_id,
              len(s.map.good_keyframes()), s.map.n_points,
              s.loop_closing.loops if s.loop_closing else "-", cpu, c_main, mapping,
              1000.0 * (c_main - mapping) / max(1, len(frames)), os.getloadavg()[0]))
    for k in STEPS:
        v = np.array(acc.get(k, [0.0]))
        print("  %-22s calls %4d  CPU ms mean %7.1f  median %7.1f  p90 %7.1f  total %6.2f s" % (
            k, len(acc.get(k, [])), v.mean(), np.median(v), np.percentile(v, 90), v.sum() / 1e3))
    return 0


if __name__ == "__main__":
    sys.exit(main())
