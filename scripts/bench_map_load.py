#!/usr/bin/env python3
"""Load time, memory and relocalization time of a saved map folder.

    python scripts/bench_map_load.py MAP_FOLDER BAG [--frame 140] [--runs 5]

MAP_FOLDER is what ``mdr run BAG --out DIR`` writes (``DIR/map``). Each run builds a fresh
tracker (config/pose.yaml) and dense map (config/fusion.yaml), loads both maps, then tracks frame
``--frame`` of BAG: it must come back RELOCALIZED. Prints the median and the range over the runs
of the sparse and dense load times and the relocalization (first frame) time, the map sizes, and
the process's peak RSS before and after (one run: the memory of one loaded map).
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import resource
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "src", "mdr_slam", "src"))

from mdr_slam.fusion import VoxelMap, VoxelMapConfig  # noqa: E402
from mdr_slam.fusion.map_io import load_dense_map  # noqa: E402
from mdr_slam.io.map_dir import map_files  # noqa: E402
from mdr_slam.pipeline import frames_from_bag, load_params  # noqa: E402
from mdr_slam.pose import System, TrackerConfig  # noqa: E402
from mdr_slam.pose.map_io import load_pose_map  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder")
    ap.add_argument("bag")
    ap.add_argument("--frame", type=int, default=140, help="frame of BAG to relocalize")
    ap.add_argument("--runs", type=int, default=5)
    a = ap.parse_args(argv)
    cam, frames = frames_from_bag(a.bag)
    f = next(itertools.islice(frames, a.frame, None))
    left, right = cam.rectify(f.left, f.right)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    times = {"pose_load_s": [], "dense_load_s": [], "reloc_ms": []}
    for _ in range(a.runs):
        s = System(cam, TrackerConfig.pick(load_params("pose")), threads=False)
        t = time.perf_counter()
        info = load_pose_map(s, map_files(a.folder)["pose"])
        times["pose_load_s"].append(time.perf_counter() - t)
        m = VoxelMap(VoxelMapConfig.pick(load_params("fusion")))
        t = time.perf_counter()
        n = load_dense_map(m, a.folder)
        times["dense_load_s"].append(time.perf_counter() - t)
        t = time.perf_counter()
        r = s.track(f.stamp, left, right)
        times["reloc_ms"].append(1000.0 * (time.perf_counter() - t))
        s.shutdown()
        if r.state != "RELOCALIZED":
            print("frame %d came back %s, not RELOCALIZED" % (a.frame, r.state), file=sys.stderr)
            return 1
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(json.dumps({k: {"median": float(np.median(v)), "min": float(min(v)), "max": float(max(v))}
                      for k, v in times.items()}, indent=1))
    print("%d keyframes, %d map points (pose_map.npz %.1f MB); dense map %d points (%.1f MB); "
          "peak RSS %.0f MB before loading, %.0f MB after %d run(s)"
          % (info["keyframes"], info["points"], os.path.getsize(map_files(a.folder)["pose"]) / 1e6,
             n, os.path.getsize(map_files(a.folder)["dense"]) / 1e6, rss0, rss1, a.runs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
