#!/usr/bin/env python3
"""Benchmark of node 2: ELAS, the weak-texture matcher and the temporal filter, timed separately,
at 752x480.

    python scripts/bench_depth.py [--runs 20] [--stride 2] [--disp-max 128] [--subsampling on|off]

ELAS runs on the same pair ``--runs`` times; the filter runs on a sequence of ``--runs``
measurements along a trajectory (so it fuses, gates, fills holes and switches keyframes as live).
Pairs come from the built-in simulator (office scene) when it is importable, else from a
textured synthetic pair. Prints median and p90 (ms) per stage and the rate both together allow
on one core. Figures depend on the machine and on its load (a shared 2-core machine makes them
indicative only).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src", "mdr_slam", "src"))


def _frames(n: int):
    """(camera, [(left, right, T_map_cam)]) at 752x480."""
    try:
        from mdr_slam.sim import Simulator, make_scene, make_trajectory, sim_camera
    except ImportError:
        return _synthetic_frames(n)
    cam = sim_camera()
    scene = make_scene("office")
    stamps, Ts = make_trajectory(scene, duration=max(30.0, n / 10.0), rate=10.0)  # ~0.3 m/s
    sim = Simulator(scene, cam, seed=0)
    out = []
    for i, T in enumerate(Ts[:n]):
        f = sim.render(T, index=i, depth=False)
        out.append((f["left"], f["right"], T))
    return cam, out, "simulator office scene"


def _synthetic_frames(n: int):
    import cv2
    from mdr_slam.camera import StereoCamera
    from mdr_slam.geometry import make_T
    cam = StereoCamera.from_rectified(752, 480, 458.0, 458.0, 367.0, 248.0, 0.11)
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur((rng.random((480, 752 + 80)) * 255).astype(np.uint8), (3, 3), 0)
    d = 25
    left, right = np.ascontiguousarray(tex[:, 40:792]), np.ascontiguousarray(tex[:, 40 + d:792 + d])
    return cam, [(left, right, make_T(np.eye(3), [0.0, 0.0, 0.0])) for _ in range(n)], \
        "synthetic textured fronto-parallel pair"


def _stats(ts):
    a = 1e3 * np.asarray(ts)
    return float(np.median(a)), float(np.percentile(a, 90)), float(a.min()), float(a.max())


def main(argv=None):
    from mdr_slam.config import split_known
    from mdr_slam.depth import DepthConfig, DepthFilter, ElasMatcher, StereoDepth
    from mdr_slam.nodes import node_configs
    from mdr_slam.pipeline import load_params
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--stride", type=int, default=None, help="filter stride (default: depth.yaml)")
    ap.add_argument("--disp-max", type=int, default=None)
    ap.add_argument("--subsampling", default=None, choices=("on", "off"),
                    help="ELAS every 2nd pixel (default: depth.yaml)")
    ap.add_argument("--weak-texture", default=None, choices=("sgbm", "off"),
                    help="matcher of the weak-texture pixels (default: depth.yaml)")
    a = ap.parse_args(argv)
    _, shipped = split_known(load_params("depth"), *node_configs("depth"))  # not the node's keys
    cfg = DepthConfig.from_dict(shipped)
    elas = {}
    if a.disp_max is not None:
        elas["disp_max"] = a.disp_max
    if a.subsampling is not None:
        elas["subsampling"] = a.subsampling == "on"
    cfg = cfg.replace(elas=elas)
    if a.stride is not None:
        cfg = cfg.replace(stride=a.stride)
    if a.weak_texture is not None:
        cfg = cfg.replace(weak_texture=a.weak_texture)
    cam, frames, source = _frames(a.runs)
    sd = StereoDepth(cam, cfg)
    print("input: %s, %dx%d, %d frames; ELAS %s; filter stride %d"
          % (source, cam.size[0], cam.size[1], len(frames),
             {k: v for k, v in sd.matcher.params.items() if k in ("preset", "disp_max", "subsampling")},
             sd.cfg.stride))
    # ELAS alone, several runs on one pair (plus one warm-up)
    matcher: ElasMatcher = sd.matcher
    left, right, _ = frames[0]
    matcher.compute(left, right)
    t_elas = []
    for _ in range(a.runs):
        t0 = time.perf_counter()
        matcher.compute(left, right)
        t_elas.append(time.perf_counter() - t0)
    t_weak = []
    if sd.weak_matcher is not None:   # SGBM on the weak-texture pixels (depth.weak_texture)
        sd.weak_matcher.compute(left, right)
        for _ in range(a.runs):
            t0 = time.perf_counter()
            sd.weak_matcher.compute(left, right)
            t_weak.append(time.perf_counter() - t0)
    # the measurements of the sequence, then the filter alone on them
    meas = [sd.measure(l, r, rectified=True)[:3] + (T,) for l, r, T in frames]
    filt: DepthFilter = sd.filter
    filt.reset()
    t_filt, n_pub = [], []
    for i, (Z, var, grey, T) in enumerate(meas):
        t0 = time.perf_counter()
        out = filt.process(0.1 * i, T, Z, var, grey)
        t_filt.append(time.perf_counter() - t0)
        n_pub.append(len(out))
    e = _stats(t_elas)
    f = _stats(t_filt[1:] if len(t_filt) > 1 else t_filt)   # frame 0 only initializes
    print("ELAS   : median %6.1f ms  p90 %6.1f ms  (min %.1f, max %.1f) over %d runs" % (e + (a.runs,)))
    print("filter : median %6.1f ms  p90 %6.1f ms  (min %.1f, max %.1f) over %d frames, "
          "median %d points published" % (f + (len(t_filt) - 1, int(np.median(n_pub)))))
    both = e[0] + f[0]
    if t_weak:
        w = _stats(t_weak)
        print("weak   : median %6.1f ms  p90 %6.1f ms  (min %.1f, max %.1f) over %d runs"
              % (w + (a.runs,)))
        both += w[0]
    print("matching + filter: %.1f ms median -> %.1f Hz on one core (target >= 10 Hz: %s)"
          % (both, 1e3 / both, "met" if both <= 100.0 else "NOT met"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
