#!/usr/bin/env python3
"""Node 2 accuracy on the simulator: keyframe Kalman temporal filter vs ELAS-only, with ground truth.

    python scripts/eval_depth_sim.py [--scenes office corridor] [--frames 80] [--rate 10] [--duration 30]
        [--set tau=0.02 --set stride=2 ...] [--sweep tau=0.01,0.02,0.03] [--cache /tmp/mdr_depth_eval]
        [--correlation]   # frame-to-frame correlation of ELAS's disparity error per surface label

For each scene: render ``--frames`` stereo pairs along the scene's ground-truth trajectory, run
ELAS and the weak-texture matcher once per pair (cached in ``--cache``, so sweeps re-run only
the filter), then run the filter (ground-truth poses) and the ELAS-only baseline and compare every published point with the true
depth at its pixel in the current frame. Reported per surface label (low_texture, textured,
specular) and overall:

- RMSE (m) of the depth error, and the share of points with |error| > 5 cm;
- density: published points per pixel of the filter grid that sees a surface, averaged over
  frames (both methods on the same ``stride`` grid, so the numbers compare).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from collections import OrderedDict

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src", "mdr_slam", "src"))

LABEL_NAMES = OrderedDict([(1, "low_texture"), (2, "textured"), (3, "specular")])
FAR = 3.5   # m: beyond it one frame of the rig's stereo does not pass tau (reported apart)


def _parse_value(v: str):
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(v.lower(), v)


def measurements(scene_name: str, frames: int, rate: float, params, cache: str, scale: float,
                 duration: float = 30.0):
    """Per frame: (T, disparity, grey, gt_depth, surface, weak-texture disparity); the matchers'
    results cached on disk."""
    from mdr_slam.depth import StereoDepth
    from mdr_slam.sim import Simulator, make_scene, make_trajectory, sim_camera
    cam = sim_camera(scale=scale)
    sd = StereoDepth(cam, params)
    import hashlib
    from mdr_slam.depth.weak_texture import BLOCK, WeakTextureMatcher
    weak_matcher = WeakTextureMatcher(sd.matcher.cfg.disp_max)
    elas_key = hashlib.sha1((repr(sorted(sd.matcher.params.items())) + "weak%d" % BLOCK).encode()
                            ).hexdigest()[:10]
    key = "%s_n%d_r%g_d%g_s%g_elas%s" % (scene_name, frames, rate, duration, scale, elas_key)
    path = os.path.join(cache, key + ".npz")
    names = ("T", "disp", "grey", "gt", "surface", "weak")
    if os.path.exists(path):
        with np.load(path) as z:
            d = {k: z[k] for k in names}     # each z[k] decompresses the whole array: once
        return cam, [tuple(d[k][i] for k in names) for i in range(len(d["T"]))]
    scene = make_scene(scene_name)
    stamps, Ts = make_trajectory(scene, duration=duration, rate=rate)
    sim = Simulator(scene, cam, seed=0)
    out = []
    t0 = time.time()
    for i, T in enumerate(Ts[:frames]):
        f = sim.render(T, index=i)
        disp = sd.matcher.compute(f["left"], f["right"])
        weak = weak_matcher.compute(f["left"], f["right"])
        out.append((T, disp, f["left"], f["depth"], f["surface"], weak))
    print("  %s: rendered + matched %d frames in %.0f s" % (scene_name, len(out), time.time() - t0),
          flush=True)
    os.makedirs(cache, exist_ok=True)
    np.savez(path, **{k: np.stack([o[j] for o in out]) for j, k in enumerate(names)})
    return cam, out


def evaluate(cam, frames, params, rate: float) -> dict:
    """Run the filter (or ELAS-only) over the frames; error/density per label."""
    from mdr_slam.depth import DepthFilter, StereoDepth
    f = DepthFilter(cam, params)
    sd = StereoDepth(cam, params)
    use_weak = sd.weak_matcher is not None
    w, h = cam.size
    s = f.cfg.stride
    errs = {k: [] for k in LABEL_NAMES}
    npts = {k: 0 for k in LABEL_NAMES}
    ngrid = {k: 0 for k in LABEL_NAMES}
    far_err, far_n, far_grid = [], 0, 0
    t_filter = []
    motion_ms = []
    kfs = set()
    for i, (T, disp, grey, gt, surf, weak) in enumerate(frames):
        Z, var = sd.measurement(disp, grey, weak if use_weak else None)
        t0 = time.perf_counter()
        out = f.process(i / rate, T, Z, var, grey)
        t_filter.append(time.perf_counter() - t0)
        kfs.add(out.keyframe_id)
        if "motion_ms" in out.stats:
            motion_ms.append(out.stats["motion_ms"])
        gsurf = surf[::s, ::s]
        ggt = gt[::s, ::s]
        for k in LABEL_NAMES:
            ngrid[k] += int(np.count_nonzero((gsurf == k) & (ggt > 0)))
        far_grid += int(np.count_nonzero(ggt > FAR))
        if len(out) == 0:
            continue
        u, v, z = cam.project(out.points)
        ui = np.clip(np.rint(u).astype(int), 0, w - 1)
        vi = np.clip(np.rint(v).astype(int), 0, h - 1)
        zt = gt[vi, ui]
        lab = surf[vi, ui]
        ok = zt > 0
        for k in LABEL_NAMES:
            m = ok & (lab == k)
            errs[k].append(z[m] - zt[m])
            npts[k] += int(np.count_nonzero(m))
        m = ok & (zt > FAR)
        far_err.append(z[m] - zt[m])
        far_n += int(np.count_nonzero(m))
    res = OrderedDict()
    allerr = np.concatenate([np.concatenate(e) if e else np.zeros(0) for e in errs.values()])
    res["all"] = _summ(allerr, sum(npts.values()), sum(ngrid.values()))
    for k, name in LABEL_NAMES.items():
        e = np.concatenate(errs[k]) if errs[k] else np.zeros(0)
        res[name] = _summ(e, npts[k], ngrid[k])
    res["far"] = _summ(np.concatenate(far_err) if far_err else np.zeros(0), far_n, far_grid)
    res["filter_ms_median"] = 1e3 * float(np.median(t_filter[1:])) if len(t_filter) > 1 else 0.0
    res["keyframes"] = len(kfs)
    res["motion_ms"] = motion_ms
    return res


def error_correlation(cam, frames, label: int = 1, lags=(1, 2, 5, 10, 20, 40), starts=(0, 30),
                      stride: int = 2):
    """How much of ELAS's disparity error repeats from frame to frame on one surface label.

    For a start frame i and a lag k: every pixel of frame i with that label, a match and a true
    depth is moved (true depth, true poses) into frame i+k; where it lands on the same surface
    (true depth within 3 cm) with a match, the two disparity errors are paired. Returns rows
    (start, lag, pairs, correlation, rms error of one frame, rms of the two-frame mean). A
    Kalman filter assumes independent errors (correlation 0: averaging n frames divides the rms
    by sqrt(n)); correlated errors are a bias that no temporal averaging removes."""
    fB = cam.fx * cam.baseline
    w, h = cam.size
    T = [f[0] for f in frames]
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    rows = []
    for i0 in starts:
        if i0 >= len(frames):
            continue
        _, disp, _, gt, surf = frames[i0][:5]
        zi = gt[::stride, ::stride]
        m = (zi > 0) & (surf[::stride, ::stride] == label) & (disp[::stride, ::stride] > 0)
        ei = (disp[::stride, ::stride] - fB / np.where(zi > 0, zi, 1.0))[m]
        P = np.stack([(u[m] - cam.cx) / cam.fx * zi[m], (v[m] - cam.cy) / cam.fy * zi[m], zi[m]], 1)
        Pw = P @ T[i0][:3, :3].T + T[i0][:3, 3]
        for k in lags:
            j = i0 + k
            if j >= len(frames):
                break
            _, dj, _, gj, _ = frames[j][:5]
            Tj = np.linalg.inv(T[j])
            Pc = Pw @ Tj[:3, :3].T + Tj[:3, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                uj = np.rint(cam.fx * Pc[:, 0] / Pc[:, 2] + cam.cx)
                vj = np.rint(cam.fy * Pc[:, 1] / Pc[:, 2] + cam.cy)
                ok = (Pc[:, 2] > 0.1) & (uj >= 0) & (uj < w) & (vj >= 0) & (vj < h)
            uj, vj = uj[ok].astype(np.int64), vj[ok].astype(np.int64)
            same = (np.abs(gj[vj, uj] - Pc[ok, 2]) < 0.03) & (dj[vj, uj] > 0)
            a = ei[ok][same]
            b = dj[vj[same], uj[same]] - fB / Pc[ok, 2][same]
            if len(a) < 100:
                continue
            rows.append((i0, k, len(a), float(np.corrcoef(a, b)[0, 1]), float(np.sqrt(np.mean(a * a))),
                         float(np.sqrt(np.mean(((a + b) / 2) ** 2)))))
    return rows


def _summ(e, n, ng):
    e = np.asarray(e, dtype=float)
    if len(e) == 0:
        return {"rmse": float("nan"), "gt5cm": float("nan"), "density": 0.0, "n": 0}
    return {"rmse": float(np.sqrt(np.mean(e * e))), "gt5cm": float(np.mean(np.abs(e) > 0.05)),
            "density": n / max(1, ng), "n": int(n)}


def _row(scene, name, r):
    cells = ["%-9s" % scene, "%-34s" % name]
    for k in ["all"] + list(LABEL_NAMES.values()) + ["far"]:
        x = r[k]
        cells.append("%6.3f %5.1f%% %5.1f%%" % (x["rmse"], 100 * x["gt5cm"], 100 * x["density"]))
    cells.append("%5.1f" % r["filter_ms_median"])
    return " | ".join(cells)


def main(argv=None):
    from mdr_slam.config import split_known
    from mdr_slam.depth import DepthConfig
    from mdr_slam.nodes import node_configs
    from mdr_slam.pipeline import load_params
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["office", "corridor"])
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--rate", type=float, default=10.0, help="frames per second of trajectory")
    ap.add_argument("--duration", type=float, default=30.0,
                    help="the scene trajectory's duration (s): it sets the speed; the first "
                         "--frames frames of it are used")
    ap.add_argument("--scale", type=float, default=1.0, help="camera scale (1 = 752x480)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a depth parameter (config/depth.yaml name)")
    ap.add_argument("--sweep", default="", metavar="KEY=V1,V2,...",
                    help="also run the filter with each value of one parameter")
    ap.add_argument("--cache", default="/tmp/mdr_depth_eval")
    ap.add_argument("--correlation", action="store_true",
                    help="also print the frame-to-frame correlation of ELAS's disparity error on "
                         "low-texture surfaces (is it noise a filter averages, or a bias?)")
    a = ap.parse_args(argv)
    _, shipped = split_known(load_params("depth"), *node_configs("depth"))  # not the node's keys
    params = DepthConfig.from_dict(shipped)

    def with_value(cfg, k, v):   # elas.disp_max=64: a field of the nested ElasConfig
        head, _, sub = k.partition(".")
        return cfg.replace(**({head: {sub: v}} if sub else {k: v}))
    for kv in a.set:
        k, v = kv.split("=", 1)
        params = with_value(params, k, _parse_value(v))
    configs = [("ELAS-only", params.replace(temporal=False)),
               ("temporal", params.replace(temporal=True))]
    if a.sweep:
        k, vals = a.sweep.split("=", 1)
        for v in vals.split(","):
            configs.append(("temporal %s=%s" % (k, v),
                            with_value(params.replace(temporal=True), k, _parse_value(v))))
    print("params: %s" % {k: getattr(params, k) for k in (
        "stride", "tau", "min_obs", "init_var_scale", "chi2_threshold", "sigma_d", "sigma_d_texture",
        "kf_max_frames", "kf_translation", "carry_tau", "fill_holes")})
    head = ["scene    ", "%-34s" % "method"] + ["%-19s" % ("%s rmse >5cm dens" % k[:8])
                                                for k in ["all"] + list(LABEL_NAMES.values()) + ["far"]] + ["ms"]
    rows = []
    for scene in a.scenes:
        cam, frames = measurements(scene, a.frames, a.rate, params, a.cache, a.scale,
                                    a.duration)
        if a.correlation:
            for lab, name in LABEL_NAMES.items():
                for r in error_correlation(cam, frames, lab):
                    print("  %s %-11s start %2d lag %2d: %6d pairs, disparity error correlation "
                          "%5.2f, rms %.2f px one frame, %.2f px mean of two" % ((scene, name) + r))
        for name, p in configs:
            r = evaluate(cam, frames, p, a.rate)
            rows.append(_row(scene, name + (" (%d kf)" % r["keyframes"] if p.temporal else ""), r))
            print(rows[-1], flush=True)
            if r["motion_ms"]:
                print("  %s %s: motion stereo %.0f ms median, %.0f ms max per keyframe (%d)" % (
                    scene, name, np.median(r["motion_ms"]), max(r["motion_ms"]),
                    len(r["motion_ms"])), flush=True)
    print()
    print("columns per label (far: true depth > %.1f m): depth RMSE (m), share |err| > 5 cm, density "
          "(published / grid pixels with a surface); ms = filter median per frame" % FAR)
    print(" | ".join(head))
    for r in rows:
        print(r)
    return 0


if __name__ == "__main__":
    sys.exit(main())
