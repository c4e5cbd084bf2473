#!/usr/bin/env python3
"""Benchmark of node 3's core (mdr_slam.fusion.VoxelMap).

1. Integration time per cloud (median, p90) while the map already holds about 10k, 100k and 1M
   points elsewhere in the building: it should be flat (hash lookups, no global KD-tree). The
   hash work per cloud (``n_lookups``) is printed too: it depends on the cloud, not on the map.
2. Process RSS after integrating many clouds of a bounded scene (default 6000 clouds, the node's
   5 minutes at 20 Hz): memory follows the mapped surface, not the run time (the paper reports
   about 463 MB for its fusion node).

Synthetic scene: a 6 x 5 x 2.6 m room with a table and boxes; each cloud is the visible part of
its surfaces from a camera moving inside it (depth-dependent noise, a few outliers), like the
depth node's output. Figures depend on the machine and its load: run it on an idle machine.

    python scripts/bench_fusion.py                      # everything (several minutes)
    python scripts/bench_fusion.py --sizes 1e4 1e5 --rss-clouds 0
"""
from __future__ import annotations

import argparse
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src", "mdr_slam", "src"))

from mdr_slam.fusion import limit_openmp_threads  # noqa: E402

limit_openmp_threads(1)  # as fusion_node does (param omp_threads)

import numpy as np  # noqa: E402

from mdr_slam.fusion import VoxelMap  # noqa: E402
from mdr_slam.geometry import inv_T, make_T, transform_points  # noqa: E402


def room_surfaces(rng, density=4000.0):
    """Points (N, 3) and normals on a room's walls, floor, ceiling, a table and two boxes (z up)."""
    boxes = [((0, 0, 0), (6, 5, 2.6), -1.0),       # the room: normals point inwards
             ((2.0, 1.5, 0.0), (3.2, 2.3, 0.75), 1.0),   # table (solid box)
             ((4.5, 3.5, 0.0), (5.2, 4.3, 1.2), 1.0),
             ((0.5, 3.8, 0.0), (1.1, 4.6, 0.5), 1.0)]
    P, N = [], []
    for lo, hi, sign in boxes:
        lo, hi = np.array(lo, float), np.array(hi, float)
        for axis in range(3):
            for side, val in ((-1, lo[axis]), (1, hi[axis])):
                if sign > 0 and axis == 2 and side < 0:
                    continue  # a box's bottom touches the floor
                dims = [d for d in range(3) if d != axis]
                area = np.prod(hi[dims] - lo[dims])
                n = int(area * density)
                Q = rng.uniform(lo, hi, (n, 3))
                Q[:, axis] = val
                nn = np.zeros((n, 3))
                nn[:, axis] = side * sign
                P.append(Q)
                N.append(nn)
    return np.vstack(P), np.vstack(N)


def camera_path(n, rng):
    """T_map_cam (optical frame) moving around the room centre, looking outwards and around."""
    Ts = []
    for i in range(n):
        a = 2 * np.pi * i / 300.0
        c = np.array([3.0, 2.5, 1.2]) + 1.2 * np.array([np.cos(0.37 * a), np.sin(0.53 * a), 0.1 * np.sin(a)])
        yaw = a + 0.3 * np.sin(3 * a)
        f = np.array([np.cos(yaw), np.sin(yaw), -0.15])
        f /= np.linalg.norm(f)
        y = -np.array([0, 0, 1.0]) - np.dot(-np.array([0, 0, 1.0]), f) * f
        y /= np.linalg.norm(y)
        x = np.cross(y, f)
        Ts.append(make_T(np.stack([x, y, f], 1), c))
    return Ts


def visible_cloud(P, N, T_map_cam, rng, n_max=30000, hfov=1.0, vfov=0.8, max_depth=6.0):
    """Camera-frame points of the surfaces in the view (frustum + facing test), with noise."""
    Pc = transform_points(inv_T(T_map_cam), P)
    z = Pc[:, 2]
    keep = (z > 0.3) & (z < max_depth) & (np.abs(Pc[:, 0]) < np.tan(hfov / 2) * z) & \
        (np.abs(Pc[:, 1]) < np.tan(vfov / 2) * z)
    keep &= np.einsum("ij,j->i", N, T_map_cam[:3, 3]) - np.einsum("ij,ij->i", N, P) > 0
    idx = np.nonzero(keep)[0]
    if len(idx) > n_max:
        idx = rng.choice(idx, n_max, replace=False)
    Q = Pc[idx]
    Q = Q * (1.0 + rng.normal(0, 0.002, (len(Q), 1)) * Q[:, 2:3])  # depth noise ~ z^2
    out = rng.uniform([-2, -1.5, 0.5], [2, 1.5, 5], (len(Q) // 200, 3))  # stereo outliers
    return np.vstack([Q, out])


def filler(n_points, voxel):
    """A cloud dict of about ``n_points`` map points on far-away walls (another building part)."""
    side = int(np.sqrt(n_points)) + 1
    g = (np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n_points] + 0.5) * voxel
    z = np.full(len(g), 1.0)
    return {"x": 100.0 + g[:, 0], "y": 100.0 + g[:, 1], "z": z, "nx": np.zeros(len(g)),
            "ny": np.zeros(len(g)), "nz": np.ones(len(g)), "confidence": np.full(len(g), 5, np.int32)}


def rss_mb():
    try:
        import psutil
        return psutil.Process().memory_info().rss / 1e6
    except ImportError:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--sizes", type=float, nargs="*", default=[1e4, 1e5, 1e6],
                    help="map sizes (points) to measure integration time at")
    ap.add_argument("--clouds", type=int, default=20, help="timed clouds per map size")
    ap.add_argument("--points", type=int, default=30000, help="points per cloud")
    ap.add_argument("--rss-clouds", type=int, default=6000, help="clouds for the RSS run (0 = skip)")
    ap.add_argument("--rss-points", type=int, default=30000, help="points per cloud in the RSS run")
    ap.add_argument("--rss-unique", type=int, default=600, help="distinct views in the RSS run")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="VoxelMap parameter, e.g. min_span=1 (repeatable)")
    ap.add_argument("--rss-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    import yaml
    args.kw = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    if args.rss_only:
        return rss_run(args)
    rng = np.random.default_rng(0)
    P, N = room_surfaces(rng)
    Ts = camera_path(max(args.clouds, 300) + 20, rng)
    print("scene: %d surface samples; voxel %.3f m; %d points per cloud; OMP_NUM_THREADS=%s" % (
        len(P), args.voxel, args.points, os.environ.get("OMP_NUM_THREADS")))
    clouds = [visible_cloud(P, N, Ts[i], rng, args.points) for i in range(args.clouds + 10)]
    print("\n1) integration time vs map size (%d clouds each, after 10 warm-up clouds; the maps "
          "take turns on each cloud)" % args.clouds)
    print("%10s %10s %10s %10s %10s %10s %10s %12s" % ("filler", "map pts", "median ms", "p90 ms",
                                                     "min ms", "cpu ms", "lookups", "cloud->down"))
    # the maps take turns on every cloud, so the machine's load fluctuations hit all sizes alike
    maps = []
    for size in args.sizes:
        m = VoxelMap(voxel_size=args.voxel, **args.kw)
        m.load(filler(int(size), args.voxel))
        for i in range(10):
            m.integrate(clouds[i], Ts[i], 0.05 * i)
        maps.append(m)
    ts = np.zeros((len(maps), args.clouds))
    cpu = np.zeros((len(maps), args.clouds))
    look = np.zeros((len(maps), args.clouds))
    down = np.zeros((len(maps), args.clouds))
    for j, i in enumerate(range(10, 10 + args.clouds)):
        for k, m in enumerate(maps):
            t, c = time.perf_counter(), time.process_time()
            st = m.integrate(clouds[i], Ts[i], 0.05 * i)
            ts[k, j] = 1e3 * (time.perf_counter() - t)
            cpu[k, j] = 1e3 * (time.process_time() - c)
            look[k, j], down[k, j] = st.n_lookups, st.n_down
    for k, (size, m) in enumerate(zip(args.sizes, maps)):
        print("%10d %10d %10.1f %10.1f %10.1f %10.1f %10d %12s" % (
            int(size), len(m), np.median(ts[k]), np.percentile(ts[k], 90), ts[k].min(),
            np.median(cpu[k]),
            look[k].mean(), "%d->%d" % (args.points, down[k].mean())), flush=True)
    if args.rss_clouds > 0:
        # a fresh process, so the RSS is that of a fusion process and not of part 1's maps
        import subprocess
        sys.stdout.flush()
        subprocess.check_call([sys.executable, os.path.abspath(__file__), "--rss-only",
                               "--voxel", str(args.voxel), "--rss-clouds", str(args.rss_clouds),
                               "--rss-points", str(args.rss_points),
                               "--rss-unique", str(args.rss_unique)] +
                              sum([["--set", kv] for kv in args.set], []))


def rss_run(args):
    rng = np.random.default_rng(1)
    P, N = room_surfaces(rng)
    print("\n2) RSS after %d clouds of the bounded room (20 Hz stamps, %d points each, %d distinct "
          "views replayed), fresh process" % (args.rss_clouds, args.rss_points, args.rss_unique))
    m = VoxelMap(voxel_size=args.voxel, **args.kw)
    # the robot goes round the room again and again: clouds of the first `rss_unique` poses are
    # generated once and replayed (with new stamps), so the run measures the map, not the renderer
    n_u = min(args.rss_unique, args.rss_clouds)
    Ts = camera_path(n_u, rng)
    clouds = [visible_cloud(P, N, Ts[i], rng, args.rss_points) for i in range(n_u)]
    base = rss_mb()
    t0 = time.perf_counter()
    times = []
    for i in range(args.rss_clouds):
        c = clouds[i % n_u]
        t = time.perf_counter()
        m.integrate(c, Ts[i % n_u], 0.05 * i)
        times.append(time.perf_counter() - t)
        if (i + 1) % max(1, args.rss_clouds // 6) == 0:
            print("  %5d clouds  map %8d points  RSS %7.1f MB  map arrays+hash %6.1f MB  "
                  "median %.1f ms/cloud (last 200)" % (i + 1, len(m), rss_mb(), m.memory_bytes() / 1e6,
                                                       1e3 * np.median(times[-200:])), flush=True)
    print("  process RSS %.1f MB (%.1f MB with the scene before the run), %d clouds in %.0f s, "
          "%d points removed by cleaning" % (rss_mb(), base, args.rss_clouds,
                                             time.perf_counter() - t0, m.n_removed))

if __name__ == "__main__":
    main()
