"""``mdr eval ate|rpe|map|grid|depth``: the paper's metrics on files, printed as JSON.

    mdr eval ate EST GT [--format tum|kitti|euroc] [--align se3|sim3|scale|none] [--plot out.png]
    mdr eval rpe EST GT [--delta 10 --delta-unit m] [--align none]
    mdr eval map EST.ply GT.ply [--threshold 0.05] [--plot out.png] [--trajectory TUM --max-range 4]
    mdr eval grid MAP.ply GT_MAP.ply [--trajectory TUM] [--min-confidence N] [--tolerance 1]
        [--raytrace on|off] [--max-gap 0.5]
    mdr eval depth EST GT [--est-scale 1 --gt-scale 1] [--depth]   (files or folders of frames)
"""
from __future__ import annotations

import json
import os
import sys

import numpy as np

from ..eval.depth import (MIDDLEBURY, depth_error_metrics, depth_metrics, load_middlebury,
                          read_disparity)
from ..eval.grid import grid_metrics, grid_params
from ..eval.map import DEFAULT_MAX_RANGE, map_metrics
from ..eval.plot import plot_ate, plot_map_errors
from ..eval.trajectory import (alignment_matrix, ate, read_for_eval, rpe,
                               transform_trajectory)
from ..io.atomic import atomic_write
from ..io.pointcloud import cloud_xyz, read_cloud
from ..nav import map_views


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
    m.add_argument("--trajectory", default=None, metavar="TRAJ",
                   help="camera path in the clouds' frame (TUM, KITTI or EuRoC): also score the "
                        "points within --max-range of it (block in_range)")
    m.add_argument("--max-range", type=float, default=DEFAULT_MAX_RANGE,
                   help="with --trajectory: metres from the path (default %g)" % DEFAULT_MAX_RANGE)
    m.add_argument("--json", default=None)
    m.set_defaults(func=run_map)

    gp = grid_params()
    h = "the occupancy grid of a map against the true one of a ground-truth cloud"
    g = sub.add_parser("grid", help=h, description=h + ": obstacle-cell recall and precision "
                       "with a tolerance in cells, and occupied cells on the camera's route. Both "
                       "grids are the fusion node's /mdr/map/grid rules (mdr_slam.fusion."
                       "occupancy_grid) with its parameters (defaults: FusionNodeConfig).")
    g.add_argument("est", help="estimated map (PLY or PCD; its 'confidence' field is used)")
    g.add_argument("gt", help="ground-truth cloud (optional per-point 'surface' label)")
    g.add_argument("--trajectory", default=None, metavar="TRAJ",
                   help="camera path in the map frame (TUM, KITTI or EuRoC): route cells, and "
                        "recall and precision within --max-range")
    g.add_argument("--max-range", type=float, default=DEFAULT_MAX_RANGE,
                   help="with --trajectory: metres from the path (default %g)" % DEFAULT_MAX_RANGE)
    g.add_argument("--min-confidence", type=int, default=None,
                   help="map points of at least this confidence mark cells (default: "
                        "grid_min_confidence %d; 0, i.e. all points, for a map without a "
                        "confidence field or whose summary.json beside it says confidence "
                        "false)" % gp["min_confidence"])
    g.add_argument("--tolerance", type=int, default=1, help="cells (Chebyshev), default 1")
    g.add_argument("--resolution", type=float, default=gp["resolution"])
    g.add_argument("--z-min", type=float, default=gp["z_min"])
    g.add_argument("--z-max", type=float, default=gp["z_max"])
    g.add_argument("--up-axis", default=gp["up_axis"])
    g.add_argument("--free-band", type=float, default=gp["free_band"])
    g.add_argument("--raytrace", choices=("on", "off"), default="on" if gp["raytrace"] else "off",
                   help="free space along the rays from the map's views (view_x, view_y, view_z "
                        "fields; a map without them has no rays), as grid_raytrace (default %s)"
                        % ("on" if gp["raytrace"] else "off"))
    g.add_argument("--raytrace-range", type=float, default=gp["raytrace_range"],
                   help="m of each ray traced, 0 = whole ray (grid_raytrace_range)")
    g.add_argument("--max-gap", type=float, default=gp["max_gap"],
                   help="m, wall gaps no ray looked through closed up to this, 0 = off "
                        "(grid_max_gap, default %g)" % gp["max_gap"])
    g.add_argument("--label-field", default="surface", help="per-point label field of the GT cloud")
    g.add_argument("--json", default=None)
    g.set_defaults(func=run_grid)

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
        path = read_for_eval(args.trajectory) if args.trajectory else None
        res = map_metrics(cloud_xyz(est), cloud_xyz(gt), args.threshold, thresholds, labels,
                          return_distances=bool(args.plot), path=path, max_range=args.max_range)
    except (ValueError, OSError, KeyError) as e:
        print("mdr eval map: %s" % e, file=sys.stderr)
        return 1
    if args.plot:
        plot_map_errors(res.pop("_d_acc"), res.pop("_d_comp"), args.plot, thresholds)
        res["plot"] = os.path.abspath(args.plot)
    _emit(res, args.json)
    return 0


def map_grid_confidence(path: str, cloud, default: int) -> int:
    """Minimum confidence of a map's grid points: ``default`` (grid_min_confidence), or 0 (all
    points) for a map without a confidence field or one that ``mdr run --confidence off`` wrote
    (its summary.json beside map.ply says so): the plain voxel grid has no confidence to filter
    on, as the fusion node's grid of such a map has none (mdr_slam.nav.map_min_confidence)."""
    if "confidence" not in cloud:
        return 0
    summ = os.path.join(os.path.dirname(os.path.abspath(path)), "summary.json")
    if os.path.exists(summ):
        try:
            with open(summ) as f:
                if json.load(f).get("confidence") is False:
                    return 0
        except (ValueError, OSError):
            pass   # not mdr run's summary: keep the default
    return int(default)


def run_grid(args):
    try:
        est = read_cloud(args.est)
        gt = read_cloud(args.gt)
        labels = gt.get(args.label_field) if args.label_field else None
        path = read_for_eval(args.trajectory) if args.trajectory else None
        mc = args.min_confidence
        if mc is None:
            mc = map_grid_confidence(args.est, est, grid_params()["min_confidence"])
        views = map_views(est) if args.raytrace == "on" else None
        res = grid_metrics(cloud_xyz(est), cloud_xyz(gt), labels, path,
                           est.get("confidence"), mc, args.resolution,
                           args.z_min, args.z_max, args.up_axis, args.free_band, args.tolerance,
                           args.max_range if path is not None else None, est_views=views,
                           max_gap=args.max_gap, raytrace_range=args.raytrace_range)
    except (ValueError, OSError, KeyError) as e:
        print("mdr eval grid: %s" % e, file=sys.stderr)
        return 1
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
