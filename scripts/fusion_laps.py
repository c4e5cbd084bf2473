#!/usr/bin/env python3
"""Map growth on a repeated room ("memory bounded by the mapped surface"), offline.

The depth node's clouds of the sample bag (ground-truth poses) are computed once and cached, then
integrated into one ``VoxelMap`` lap after lap, as a looped bag would feed the fusion node. Lap 1
uses the depth filter's first pass over the bag, later laps its second pass (the filter state
carries over, as in a live loop) with a random ~2/3 of the clouds per lap (the live depth node
publishes ~13 of 20 Hz). Per lap: map size, confident points, accuracy RMSE / completeness against
the simulator's ``gt_map.ply``, integration time; at the end, what the points added after lap 1 are.

    python scripts/fusion_laps.py --laps 20                       # cache in output/fusion_laps/
    python scripts/fusion_laps.py --laps 20 --set min_span=1      # ablation of one VoxelMap parameter
"""
from __future__ import annotations

import argparse
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "src", "mdr_slam", "src"))

from mdr_slam.fusion import limit_openmp_threads  # noqa: E402

limit_openmp_threads(1)

import numpy as np  # noqa: E402


def build_cache(bag, path, passes=6, keep=0.65, seed=0):
    """Depth clouds of ``passes`` passes over the bag through one depth filter (state carried over):
    pass 1 every frame, later passes a random ``keep`` share of the frames (the live depth node
    drops the rest), so every pass gives different clouds, as a live loop does."""
    from mdr_slam.config import split_known
    from mdr_slam.depth import StereoDepth
    from mdr_slam.nodes import node_configs
    from mdr_slam.pipeline import frames_from_bag, load_params
    cam, frames = frames_from_bag(bag, ground_truth=True)
    frames = [f for f in frames if f.T_map_cam_gt is not None]
    _, dp = split_known(load_params("depth", "sample"), *node_configs("depth"))  # not the node's
    sd = StereoDepth(cam, dp)
    dur = frames[-1].stamp - frames[0].stamp + 0.05
    P, I, S, T, L = [], [], [], [], []
    t0 = time.time()
    rng = np.random.default_rng(seed)
    for lap in range(passes):
        for f in frames:
            if lap > 0 and rng.random() >= keep:
                continue
            left, right = cam.rectify(f.left, f.right)
            o = sd.process(f.stamp + lap * dur, left, right, f.T_map_cam_gt, rectified=True)
            if len(o.points):
                P.append(o.points.astype(np.float32))
                I.append(o.intensity.astype(np.float32))
                S.append(f.stamp)
                T.append(f.T_map_cam_gt)
                L.append(lap)
        print("depth pass %d: %d clouds, %.0f s" % (lap + 1, len(P), time.time() - t0), flush=True)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    np.savez(path, points=np.concatenate(P), intensity=np.concatenate(I),
             n=np.array([len(p) for p in P]), stamps=np.array(S), T=np.stack(T), lap=np.array(L),
             duration=dur)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bag", default=os.path.join(ROOT, "output", "sample", "sequence.bag"))
    ap.add_argument("--gt-map", default=None, help="default: gt_map.ply beside the bag")
    ap.add_argument("--cache", default=os.path.join(ROOT, "output", "fusion_laps", "clouds.npz"))
    ap.add_argument("--laps", type=int, default=20)
    ap.add_argument("--passes", type=int, default=6,
                    help="depth passes over the bag when the cache is built (later laps cycle "
                         "through passes 2..N with a random --keep share of their clouds)")
    ap.add_argument("--keep", type=float, default=0.65, help="share of clouds integrated per lap")
    ap.add_argument("--wrap", action="store_true",
                    help="stamps jump back each lap (a looping bag) instead of increasing")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--save", default="", help="write the final map here (PLY/PCD, VoxelMap.save)")
    ap.add_argument("--minutes", type=float, default=0.0,
                    help="stop after the lap that ends past this wall-clock budget (0 = run all laps)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="VoxelMap parameter over config/fusion.yaml (repeatable)")
    args = ap.parse_args()
    import yaml
    from mdr_slam.eval.map import map_metrics
    from mdr_slam.fusion import VoxelMap
    from mdr_slam.io import read_cloud
    from mdr_slam.pipeline import load_params
    if not os.path.exists(args.cache):
        build_cache(args.bag, args.cache, passes=args.passes)
    with np.load(args.cache) as z:
        d = {k: z[k] for k in z.files}  # an NpzFile re-reads an array on every access
    off = np.concatenate([[0], np.cumsum(d["n"])])
    laps_src = d["lap"]
    dur = float(d["duration"])
    gt = read_cloud(args.gt_map or os.path.join(os.path.dirname(args.bag), "gt_map.ply"))
    gt = np.stack([gt["x"], gt["y"], gt["z"]], 1)
    sets = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    m = VoxelMap(load_params("fusion", "sample"), **sets)   # the node's own keys are skipped
    print("VoxelMap:", {k: getattr(m, k) for k in ("voxel_size", "min_confidence", "grace",
                                                    "min_span")}, "sets:", args.set)
    rng = np.random.default_rng(args.seed)
    print("%4s %8s %8s %8s %8s %9s %9s %8s %8s %8s %8s" % ("lap", "points", "conf>=3", "removed", "folded",
                                                       "rmse mm", "compl %", "acc %", "med ms", "cpu ms",
                                                       "rss MB"))
    import psutil
    proc = psutil.Process()
    t_start = time.time()
    ms_all = []
    for lap in range(args.laps):
        npass = int(laps_src.max()) + 1
        src = np.nonzero(laps_src == (lap if lap < npass else 1 + (lap - 1) % (npass - 1)))[0]
        if lap > 0:
            src = src[rng.random(len(src)) < args.keep]
        t_lap = time.process_time()
        ms = []
        for i in src:
            stamp = float(d["stamps"][i]) + (0.0 if args.wrap else lap * dur)
            t = time.perf_counter()
            m.integrate(d["points"][off[i]:off[i + 1]], d["T"][i], stamp,
                        intensity=d["intensity"][off[i]:off[i + 1]])
            ms.append(1e3 * (time.perf_counter() - t))
        cpu = 1e3 * (time.process_time() - t_lap) / max(1, len(src))
        ms_all += ms
        mm = map_metrics(m.points(0), gt, threshold=0.05)
        print("%4d %8d %8d %8d %8d %9.1f %9.1f %8.1f %8.1f %8.1f %8.1f" % (
            lap + 1, len(m), len(m.points(m.min_confidence)), m.n_removed,
            getattr(m, "n_duplicates", 0),
            1e3 * mm["accuracy_rmse"], 100 * mm["completeness"], 100 * mm["accuracy"],
            np.median(ms), cpu, proc.memory_info().rss / 2**20), flush=True)
        if lap == 0:
            lap1_end = float(d["stamps"][src].max()) + (0.0 if args.wrap else 0.0)
        if args.minutes > 0 and time.time() - t_start > 60 * args.minutes:
            print("stopped after lap %d: %.1f min budget" % (lap + 1, args.minutes))
            break
    print("integration over all laps: median %.1f ms, p90 %.1f ms (wall)" % (
        np.median(ms_all), np.percentile(ms_all, 90)))
    print("points re-keyed (mean left its voxel): %d, folded into their new voxel's point: %d" % (
        getattr(m, "n_rekeyed", 0), getattr(m, "n_cell_folds", 0)))
    # what are the points that came after lap 1?
    c = m.to_cloud(0)
    P = np.stack([c["x"], c["y"], c["z"]], 1)
    from mdr_slam.eval.map import nearest_distances
    dgt, _ = nearest_distances(P, gt)
    late = c["first_seen"] > lap1_end + 1.0 if not args.wrap else np.zeros(len(P), bool)
    old = ~late
    print("points first seen in lap 1: %d, later: %d" % (old.sum(), late.sum()))
    for name, s in (("lap-1 points", old), ("later points", late)):
        if s.sum() == 0:
            continue
        dd = dgt[s]
        print("  %-13s dist to GT median %.1f mm, p90 %.1f mm, >5 cm %.1f %%; confidence median %d" % (
            name, 1e3 * np.median(dd), 1e3 * np.percentile(dd, 90), 100 * np.mean(dd > 0.05),
            np.median(c["confidence"][s])))
    if late.sum() and old.sum():
        dn, j = nearest_distances(P[late], P[old])
        Nl = np.stack([c["nx"], c["ny"], c["nz"]], 1)
        cosn = np.einsum("ij,ij->i", Nl[late], Nl[old][j])
        print("  later points: nearest lap-1 point median %.1f mm (p10 %.1f, p90 %.1f); normals "
              "agree (<45 deg) %.0f %%, opposite (>135 deg) %.0f %%" % (
                  1e3 * np.median(dn), 1e3 * np.percentile(dn, 10), 1e3 * np.percentile(dn, 90),
                  100 * np.mean(cosn > np.cos(np.radians(45))), 100 * np.mean(cosn < -0.7)))
    if args.save:
        m.save(args.save)
    m.close()


if __name__ == "__main__":
    main()
