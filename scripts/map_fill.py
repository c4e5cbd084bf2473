#!/usr/bin/env python3
"""How full is a map's lattice? Map points against the true surface's voxels ("memory bounded
by the mapped surface").

Per map: points within ``--near`` of the ground-truth surface (``gt_map.ply`` of a simulated
sequence) and farther; the true surface's voxels (``--voxel``, the map's resolution) that have a map
point within ``--near`` ("covered"); near points per covered surface voxel. One point per surface
voxel is what a complete 2 cm map of the seen surfaces holds; a map that grows past that with
time is growing a shell of noise, not the surface.

    python scripts/map_fill.py output/sample/gt_map.ply ~/.ros/mdr_map.ply [more maps...]
"""
from __future__ import annotations

import argparse
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src", "mdr_slam", "src"))

import numpy as np  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("gt_map")
    ap.add_argument("maps", nargs="+")
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--near", type=float, default=0.03)
    args = ap.parse_args()
    from scipy.spatial import cKDTree
    from mdr_slam.io import read_cloud
    gt = read_cloud(args.gt_map)
    G = np.column_stack([gt["x"], gt["y"], gt["z"]])
    vox = np.unique(np.floor(G / args.voxel).astype(np.int64), axis=0)
    C = (vox + 0.5) * args.voxel
    tg = cKDTree(G)
    print("true surface: %d voxels of %.0f cm" % (len(vox), 100 * args.voxel))
    for f in args.maps:
        c = read_cloud(f)
        P = np.column_stack([c["x"], c["y"], c["z"]])
        d, _ = tg.query(P)
        near = d <= args.near
        dc, _ = cKDTree(P[near]).query(C, distance_upper_bound=args.near)
        cov = np.isfinite(dc)
        print("%-28s points %6d  near %6d  far %5d (%.1f %%)  covered surface voxels %6d (%.1f %%)  "
              "near points per covered voxel %.3f" % (
                  os.path.basename(f), len(P), near.sum(), (~near).sum(), 100 * (~near).mean(),
                  cov.sum(), 100 * cov.mean(), near.sum() / max(1, cov.sum())))


if __name__ == "__main__":
    main()
