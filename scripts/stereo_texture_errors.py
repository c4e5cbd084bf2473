#!/usr/bin/env python3
"""How wrong the pose tracker's stereo depths are, by the texture of the keypoint's patch.

    python scripts/stereo_texture_errors.py [--sequences office_loop_rotation@7,office_loop@1]
                                            [--every 1.0] [--json FILE]

Renders frames of simulated sequences with exact depth (``mdr_slam.sim``, 752x480, the
simulator's sensor noise sigma = 2 grey levels), makes the tracker's Frame on each (ORB on both
images, ORB-SLAM2's row search and 11x11 SAD refinement), and bins every stereo keypoint by the
texture of its 11x11 patch, the mean |dI/dx| in grey levels (the measure of cv2.StereoBM's
textureThreshold; sensor noise alone gives about 1.13 sigma = 2.3). Per bin: keypoints, the
share whose depth is off by more than 10 %, the median relative error. Also, per frame, the
share of stereo keypoints below 3 grey levels (blank walls, the specular band's highlight).

It measures the cause of the drift on office_loop_rotation seed 7 (docs/experiments.md):
on the band the corners are noise and so are their disparities. The tracker uses a related
measure (the mean squared x and y gradient of the 7x7 patch, ``pose.frame.gradient_energy``) to
weight each keypoint's x and y residuals (``texture_tau``) and to pick the optical-flow tracks
its PnP fits (``flow_pnp_min_texture``); the variants that dropped such stereo depths, tried and
not kept, are in docs/experiments.md.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "src", "mdr_slam", "src"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from eval_pose_sim import SEQUENCES  # noqa: E402  (the same sequences and seeds)
EDGES = (0.0, 2.5, 3.0, 3.5, 4.0, 5.0, 7.0, 10.0, np.inf)
_W = 5


def patch_texture(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Mean |dI/dx| over the 11x11 patch around each keypoint (nan where it leaves the image)."""
    h, w = image.shape[:2]
    u = np.round(uv[:, 0]).astype(int)
    v = np.round(uv[:, 1]).astype(int)
    out = np.full(len(uv), np.nan)
    inb = (v - _W >= 0) & (v + _W < h) & (u - _W - 1 >= 0) & (u + _W < w)
    win = np.lib.stride_tricks.sliding_window_view(image, (2 * _W + 1, 2 * _W + 2))
    p = win[v[inb] - _W, u[inb] - _W - 1].astype(np.int16)
    out[inb] = np.abs(np.diff(p, axis=2)).mean(axis=(1, 2))
    return out


def measure(name: str, every: float, n_features: int = 1500) -> dict:
    from mdr_slam.pose import Frame, ORBextractor
    from mdr_slam.sim.render import Simulator, sim_camera
    from mdr_slam.sim.scene import make_scene
    from mdr_slam.sim.trajectory import build_trajectory
    base, _, seed_arg = name.partition("@")
    scene_name, kind, duration, seed = SEQUENCES[base][:4]
    seed = int(seed_arg) if seed_arg else seed
    scene = make_scene(scene_name, seed=seed)
    cam = sim_camera(scale=1.0)
    stamps = np.arange(0.0, duration, every)
    poses = build_trajectory(kind, duration, seed, scene=scene).poses(stamps)
    sim = Simulator(scene, cam, seed=seed, noise=2.0)
    ex = ORBextractor(n_features, min_fast_threshold=5)
    ex_r = ORBextractor(n_features, min_fast_threshold=5)
    tex_all, err_all, per_frame = [], [], []
    for t, T in zip(stamps, poses):
        im = sim.render(T, index=int(round(t * 20)), depth=True)
        f = Frame(float(t), im["left"], im["right"], cam, ex, ex_r)
        idx = np.nonzero(f.depth > 0)[0]
        tex = patch_texture(im["left"], f.uv[idx])
        ok = np.isfinite(tex)
        idx, tex = idx[ok], tex[ok]
        u = np.round(f.uv[idx]).astype(int)
        z = im["depth"][u[:, 1], u[:, 0]]
        good = np.isfinite(z) & (z > 0)
        idx, tex, z = idx[good], tex[good], z[good]
        err = np.abs(f.depth[idx] - z) / z
        tex_all.append(tex)
        err_all.append(err)
        per_frame.append({"t": float(t), "stereo": int(len(idx)),
                          "weak_share": float(np.mean(tex < 3.0)) if len(idx) else 0.0,
                          "bad_share": float(np.mean(err > 0.1)) if len(idx) else 0.0})
    return {"sequence": name, "frames": len(stamps), "per_frame": per_frame,
            "texture": np.concatenate(tex_all), "rel_err": np.concatenate(err_all)}


def texture_bins(tex: np.ndarray, err: np.ndarray) -> list:
    """Per texture bin: keypoints, share with depth off by > 10 %, median relative error."""
    bins = []
    for lo, hi in zip(EDGES[:-1], EDGES[1:]):
        m = (tex >= lo) & (tex < hi)
        bins.append({"texture": [lo, hi if np.isfinite(hi) else None], "n": int(m.sum()),
                     "bad_share": float(np.mean(err[m] > 0.1)) if m.any() else None,
                     "median_rel_err": float(np.median(err[m])) if m.any() else None})
    return bins


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequences", default="office_loop_rotation@7,office_loop")
    ap.add_argument("--every", type=float, default=1.0, help="seconds between rendered frames")
    ap.add_argument("--json", default="")
    a = ap.parse_args(argv)
    names = [s.strip() for s in a.sequences.split(",") if s.strip()]
    bad = [n for n in names if n.partition("@")[0] not in SEQUENCES]
    if bad:
        ap.error("unknown sequences %s (known: %s)" % (bad, ", ".join(SEQUENCES)))
    out = [measure(n, a.every) for n in names]
    bins = texture_bins(np.concatenate([o["texture"] for o in out]),
                        np.concatenate([o["rel_err"] for o in out]))
    print("| texture (mean abs dI/dx, grey levels) | stereo keypoints | depth off > 10 % | "
          "median relative error |")
    print("|---|---|---|---|")
    for b in bins:
        if b["n"]:
            lo, hi = b["texture"]
            print("| %g-%s | %d | %.0f %% | %.3f |" % (lo, "inf" if hi is None else "%g" % hi,
                                                     b["n"], 100 * b["bad_share"],
                                                     b["median_rel_err"]))
    for o in out:
        weak = [p for p in o["per_frame"] if p["weak_share"] > 0.5]
        print("%s: %d frames, %d with most stereo keypoints below 3 grey levels (t = %s s)" % (
            o["sequence"], o["frames"], len(weak), ", ".join("%.0f" % p["t"] for p in weak)))
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"bins": bins, "sequences": [
                {k: v for k, v in o.items() if k not in ("texture", "rel_err")} for o in out]},
                f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
