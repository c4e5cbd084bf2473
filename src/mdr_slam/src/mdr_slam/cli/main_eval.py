"""``mdr eval ate|rpe|map|depth``: the paper's metrics on files, printed as JSON.

    mdr eval ate EST GT [--format tum|kitti|euroc] [--align se3|sim3|scale|none] [--plot out.png]
    mdr eval rpe EST GT [--delta 10 --delta-unit m] [--align none]
    mdr eval map EST.ply GT.ply [--threshold 0.05] [--plot out.png]
    mdr eval depth EST GT [--est-scale 1 --gt-scale 1] [--depth]   (files or folders of frames)
"""
from __future__ import annotations

import json
import os
import sys

import numpy as np

from ..eval.depth import (MIDDLEBURY, depth_error_metrics, depth_metrics, load_middlebury,
                          read_disparity)
from ..eval.map import map_metrics
from ..eval.plot import plot_ate, plot_map_errors
from ..eval.trajectory import alignment_matrix, ate, read_for_eval, rpe, transform_trajectory
from ..io.atomic import atomic_write
from ..io.pointcloud import cloud_xyz, read_cloud


def add_parser(subparsers, name, help_text):
    p = subparsers.add_parser(name, help=help_text, description=help_text)
    sub = p.add_subparsers(dest="metric", metavar="METRIC")

    for metric, h in (("ate", "absolute trajectory error after Umeyama alignment (evo APE)"),
                      ("rpe", "relative pose error over a distance or frame delta (evo RPE)")):
        q = sub.add_parser(metric, help=h, description=h)
        q.add_argument("est", help="estimated trajectory")
        q.add_argument("gt", help="ground-truth trajectory")
        q.add_argument("--format", choices=["tum", "kitti", "euroc"], default=None,
                       help="format of both files (default: guessed from each file)")
        q.add_argument("--est-format", choices=["tum", "kitti", "euroc"], default=None)
        q.add_argument("--gt-format", choices=["tum", "kitti", "euroc"], default=None)
        q.add_argument("--est-times", default=None, help="stamps for a KITTI estimate (times.txt)")
        q.add_argument("--gt-times", default=None, help="stamps for a KITTI ground truth (times.txt)")
        q.add_argument("--max-diff", type=float, default=0.01,
                       help="max stamp difference for association, s (default 0.01)")
        q.add_argument("--offset", type=float, default=0.0, help="time offset added to the estimate")
        q.add_argument("--json", default=None, help="also write the summary to this file")
        q.set_defaults(func=run_ate if metric == "ate" else run_rpe)
        if metric == "ate":
            q.add_argument("--align", choices=["se3", "sim3", "scale", "none"], default="se3")
            q.add_argument("--align-as", metavar="EST0", default=None,
                           help="align with the SE(3) transform that aligns EST0 (an earlier run "
                                "whose map this one was localized in) to the ground truth: the "
                                "estimate is scored in that run's map frame")
            q.add_argument("--n-to-align", type=int, default=-1,
                           help="align on the first N poses only (default all)")
            q.add_argument("--plot", default=None, help="save the Fig. 6 style plot (PNG/PDF)")
            q.add_argument("--plane", choices=["xy", "xz", "yz", "auto"], default="xy",
                           help="plane of the trajectory plot (auto: the two widest axes)")
        else:
            q.add_argument("--align", choices=["se3", "sim3", "scale", "none"], default="none")
            q.add_argument("--delta", type=float, default=10.0)
            q.add_argument("--delta-unit", choices=["m", "frames"], default="m")
            q.add_argument("--all-pairs", action="store_true")
            q.add_argument("--rotation", action="store_true", help="rotation error (deg)")

    h = "dense map accuracy (RMSE) and completeness against a ground-truth cloud"
    m = sub.add_parser("map", help=h, description=h)
    m.add_argument("est", help="estimated map (PLY or PCD)")
    m.add_argument("gt", help="ground-truth cloud (PLY or PCD; optional per-point 'surface' label)")
    m.add_argument("--threshold", type=float, default=0.05, help="completeness threshold, m")
    m.add_argument("--thresholds", default="0.01,0.02,0.05,0.10",
                   help="comma-separated thresholds to report as well")
    m.add_argument("--label-field", default="surface", help="per-point label field of the GT cloud")
    m.add_argument("--plot", default=None, help="save a distance histogram / curves figure")
    m.add_argument("--json", default=None)
    m.set_defaults(func=run_map)

    h = "per-frame disparity or depth errors against ground truth"
    d = sub.add_parser("depth", help=h, description=h)
    d.add_argument("est", help="estimated disparity/depth image (.png .pgm .pfm .tiff .npy) or folder")
    d.add_argument("gt", help="ground-truth image or folder (paired by file name stem), or a "
                              "Middlebury folder / name (tsukuba, venus, teddy, cones)")
    d.add_argument("--est-scale", type=float, default=1.0, help="stored value / scale = px (or m)")
    d.add_argument("--gt-scale", type=float, default=1.0)
    d.add_argument("--depth", action="store_true", help="inputs are depths in metres, not disparities")
    d.add_argument("--max-error", type=float, default=0.05, help="depth: 'bad' above this, m")
    d.add_argument("--json", default=None)
    d.set_defaults(func=run_depth)

    p.set_defaults(func=_usage(p))
    return p


def _usage(p):
    def run(args):
        p.print_help()
        return 2
    return run


def _emit(stats, path=None):
    text = json.dumps(stats, indent=2, sort_keys=True, default=float)
    print(text)
    if path:
        atomic_write(path, text + "\n", "w")


def _read_pair(args):
    est = read_for_eval(args.est, args.est_format or args.format, args.est_times)
    gt = read_for_eval(args.gt, args.gt_format or args.format, args.gt_times)
    return est, gt


def run_ate(args):
    try:
        est, gt = _read_pair(args)
        align_mode = args.align
        if args.align_as:
            first = read_for_eval(args.align_as, args.est_format or args.format, args.est_times)
            est = transform_trajectory(est, alignment_matrix(
                ate(first, gt, "se3", args.max_diff, args.offset).alignment))
            align_mode = "none"
        res = ate(est, gt, align_mode, args.max_diff, args.offset, args.n_to_align)
    except (ValueError, OSError) as e:
        print("mdr eval ate: %s" % e, file=sys.stderr)
        return 1
    if args.plot:
        plot_ate(res, args.plot, args.plane)
        res.stats["plot"] = os.path.abspath(args.plot)
    _emit(res.stats, args.json)
    return 0


def run_rpe(args):
    try:
        est, gt = _read_pair(args)
        res = rpe(est, gt, args.delta, args.delta_unit, args.align, args.max_diff, args.offset,
                  args.all_pairs, args.rotation)
    except (ValueError, OSError) as e:
        print("mdr eval rpe: %s" % e, file=sys.stderr)
        return 1
    _emit(res.stats, args.json)
    return 0


def run_map(args):
    try:
        thresholds = [float(t) for t in args.thresholds.split(",") if t.strip()]
        est = read_cloud(args.est)
        gt = read_cloud(args.gt)
        labels = gt.get(args.label_field) if args.label_field else None
        res = map_metrics(cloud_xyz(est), cloud_xyz(gt), args.threshold, thresholds, labels,
                          return_distances=bool(args.plot))
    except (ValueError, OSError, KeyError) as e:
        print("mdr eval map: %s" % e, file=sys.stderr)
        return 1
    if args.plot:
        plot_map_errors(res.pop("_d_acc"), res.pop("_d_comp"), args.plot, thresholds)
        res["plot"] = os.path.abspath(args.plot)
    _emit(res, args.json)
    return 0


def _frames(path):
    """{stem: file} of a folder of images, or {'': path} for one file."""
    if os.path.isdir(path):
        exts = (".png", ".pgm", ".pfm", ".tif", ".tiff", ".npy", ".exr")
        return {os.path.splitext(f)[0]: os.path.join(path, f) for f in sorted(os.listdir(path))
                if f.lower().endswith(exts)}
    return {"": path}


def run_depth(args):
    try:
        key = os.path.basename(os.path.normpath(args.gt)).lower()
        if key in MIDDLEBURY and (os.path.isdir(args.gt) or not os.path.exists(args.gt)):
            gts = {"": load_middlebury(args.gt)[2]}
        else:
            gts = {k: read_disparity(v, args.gt_scale) for k, v in _frames(args.gt).items()}
        ests = _frames(args.est)
        if list(ests) == [""] or list(gts) == [""]:
            if len(ests) != 1 or len(gts) != 1:
                raise ValueError("give two files or two folders")
            pairs = [("frame", list(ests.values())[0], list(gts.values())[0])]
        else:
            common = sorted(set(ests) & set(gts))
            if not common:
                raise ValueError("no frame names in common between %s and %s" % (args.est, args.gt))
            pairs = [(k, ests[k], gts[k]) for k in common]
        per = {}
        for name, ep, g in pairs:
            e = read_disparity(ep, args.est_scale)
            if args.depth:
                per[name] = depth_error_metrics(e, g, max_error=args.max_error)
            else:
                per[name] = depth_metrics(e, g)
    except (ValueError, OSError) as e:
        print("mdr eval depth: %s" % e, file=sys.stderr)
        return 1
    keys = [k for k in next(iter(per.values())) if not k.startswith("n_") and k != "max_error"]
    mean = {k: float(np.nanmean([v[k] for v in per.values()])) for k in keys}
    _emit({"frames": per, "mean": mean, "n_frames": len(per),
           "kind": "depth_m" if args.depth else "disparity_px"}, args.json)
    return 0
