#!/usr/bin/env python3
"""Memory against the area mapped, per window of an ``mdr run --window S`` output folder.

Area mapped by the end of a window: the cells (``--cell``, default 0.5 m) of the run's final
dense map, projected on the plane of the camera path, that lie within ``--range`` (default 4 m)
of the path driven so far. Printed beside each window's process RSS, dense map points, keyframes
alive and tracking time, then the RSS growth per 100 m2 between the first and the last window.

    mdr run BAG --out R --window 16
    python scripts/map_area_timeline.py R
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
from scipy.spatial import cKDTree


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", help="an `mdr run --window S` output folder")
    ap.add_argument("--cell", type=float, default=0.5, help="cell size, m (default 0.5)")
    ap.add_argument("--range", type=float, default=4.0, dest="max_range",
                    help="cells within this distance of the path count, m (default 4)")
    a = ap.parse_args(argv)
    import open3d as o3d
    pts = np.asarray(o3d.io.read_point_cloud(os.path.join(a.run, "map", "dense_map.ply")).points)
    tum = np.loadtxt(os.path.join(a.run, "trajectory.tum"), ndmin=2)
    with open(os.path.join(a.run, "timeline.json")) as f:
        windows = json.load(f)["windows"]
    if len(pts) == 0 or len(tum) < 3:
        print("%s: no dense map or too short a path" % a.run)
        return 1
    stamps, P = tum[:, 0] - tum[0, 0], tum[:, 1:4]
    c = P.mean(axis=0)
    e = np.linalg.svd(P - c)[2][:2]                # the path's plane (a level robot's floor)
    cells = np.unique(np.floor((pts - c) @ e.T / a.cell).astype(np.int64), axis=0)
    centres = (cells + 0.5) * a.cell
    first = np.full(len(centres), np.inf)          # when each cell first comes within range
    tree = cKDTree(centres)
    for t, p in zip(stamps, (P - c) @ e.T):
        near = np.asarray(tree.query_ball_point(p, a.max_range), np.int64)
        if len(near):
            first[near] = np.minimum(first[near], t)
    cell_m2 = a.cell * a.cell
    rows = []
    print("| bag s | area mapped m2 | process RSS MB | dense map points | keyframes alive | "
          "tracking ms median / p90 |")
    print("|---|---|---|---|---|---|")
    for w in windows:
        area = float(np.count_nonzero(first <= w["t1"]) * cell_m2)
        rows.append((area, w.get("rss_mb")))
        tm = w.get("tracking_ms") or {}
        print("| %.0f-%.0f | %.0f | %s | %s | %s | %s / %s |" % (
            w["t0"], w["t1"], area, w.get("rss_mb"), w.get("dense_map_points"),
            w.get("keyframes"), tm.get("median"), tm.get("p90")))
    (a0, r0), (a1, r1) = rows[0], rows[-1]
    if r0 is not None and r1 is not None and a1 > a0:
        print("RSS %.0f -> %.0f MB from %.0f to %.0f m2: %.0f MB per 100 m2 mapped" % (
            r0, r1, a0, a1, 100.0 * (r1 - r0) / (a1 - a0)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
