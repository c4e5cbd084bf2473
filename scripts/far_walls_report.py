#!/usr/bin/env python3
"""Far walls: map and grid figures of simulated scenes, the default system against the ELAS-only
baseline, with true and with tracked poses.

    python scripts/far_walls_report.py [--scenes office,corridor,garage,atrium] [--seed 7]
        [--work /tmp/mdr_far_walls] [--out FILE.json] [--duration S] [--rate HZ] [--scale F]
        [--workers N] [--max-frames N] [--max-range 4] [--grid-range 5]
        [--set NODE.KEY=VALUE ...]

For each scene: render the sequence with ``mdr sim`` (into ``WORK/sim_<scene>_seed<seed>...``; a
folder that already holds its ``gt_map.ply`` is reused), then run ``mdr run`` on it three times,
one after the other (into ``WORK/<scene>_seed<seed>..._<variant>``, its output in ``.log``):

- ``default``: the default configuration with the ground-truth poses (``--pose-source
  groundtruth``);
- ``elas_only``: the ELAS-only baseline (``--temporal off``) with the ground-truth poses;
- ``tracked``: the default configuration with the tracker's poses (``--pose-source orb``).

``--set`` options go to ``default`` and ``tracked``, not to the baseline. Every map is scored
as ``mdr eval map MAP gt_map.ply --trajectory groundtruth.tum`` scores it (``map_metrics``
with the true camera path and its default ``--max-range``, 4 m): precision at 5 cm, RMSE,
completeness and F-score of the points within range of the path; and its occupancy grid as
``mdr eval grid ... --max-range 5`` (``grid_metrics``, the fusion node's grid parameters, with
``--set fusion.grid_*`` applied): obstacle-cell recall and precision, one cell of tolerance,
within ``--grid-range`` (5 m) of the path. ``tracked``'s map is first moved into the
simulator's frame by the SE(3) alignment of its trajectory (as ``mdr bench --ablation``), and
its ATE (``mdr eval ate``, se3) is reported. With ``--max-frames`` the camera path is the
ground truth over the frames the run used.

Prints a markdown table per scene (F ratio: the variant's F-score over the baseline's) and
writes every figure (also the whole-map ones and the in-range low-texture ones) as JSON to
``--out`` (default ``WORK/far_walls.json``).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from collections import OrderedDict

HERE = os.path.dirname(os.path.abspath(__file__))
SRC = os.path.join(os.path.dirname(HERE), "src", "mdr_slam", "src")
sys.path.insert(0, SRC)

VARIANTS = OrderedDict([
    ("default", {"pose_source": "groundtruth", "argv": [], "sets": True}),
    ("elas_only", {"pose_source": "groundtruth", "argv": ["--temporal", "off"], "sets": False}),
    ("tracked", {"pose_source": "orb", "argv": [], "sets": True}),
])
BASELINE = "elas_only"


def _tag(args) -> str:
    """The sequence's name: scene options that change it are part of it."""
    out = "seed%d" % args.seed
    for key, flag in (("duration", "d"), ("rate", "r"), ("scale", "x")):
        v = getattr(args, key)
        if v is not None:
            out += "_%s%g" % (flag, v)
    return out


def _child_env() -> dict:
    """The children import this checkout's mdr_slam, as this script does."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([SRC] + [p for p in env.get("PYTHONPATH", "").split(
        os.pathsep) if p])
    return env


def _call(argv, log: str) -> int:
    t0 = time.time()
    with open(log, "w") as f:
        f.write(" ".join(argv) + "\n")
        f.flush()
        code = subprocess.call(argv, stdout=f, stderr=subprocess.STDOUT, env=_child_env())
    print("    %.0f s, exit %d (log %s)" % (time.time() - t0, code, log), file=sys.stderr,
          flush=True)
    return code


def simulate(scene: str, args) -> str:
    from mdr_slam.cli import mdr_command
    d = os.path.join(args.work, "sim_%s_%s" % (scene, _tag(args)))
    if os.path.exists(os.path.join(d, "gt_map.ply")):
        print("  %s: reusing %s" % (scene, d), file=sys.stderr, flush=True)
        return d
    argv = mdr_command() + ["sim", "--scene", scene, "--seed", str(args.seed), "--out", d,
                            "--quiet"]
    for key in ("duration", "rate", "scale", "workers"):
        if getattr(args, key) is not None:
            argv += ["--" + key, str(getattr(args, key))]
    print("  %s: mdr sim -> %s" % (scene, d), file=sys.stderr, flush=True)
    if _call(argv, d + ".log") != 0:
        raise RuntimeError("mdr sim failed for %s, see %s.log" % (scene, d))
    return d


def run_variant(scene: str, variant: str, sim_dir: str, args) -> str:
    from mdr_slam.cli import mdr_command
    v = VARIANTS[variant]
    sets = "_set" + hashlib.sha1(" ".join(args.set).encode()).hexdigest()[:6] \
        if v["sets"] and args.set else ""
    d = os.path.join(args.work, "%s_%s%s_%s" % (scene, _tag(args), sets, variant))
    if args.reuse_runs and os.path.exists(os.path.join(d, "summary.json")):
        print("  %s: reusing %s" % (scene, d), file=sys.stderr, flush=True)
        return d
    shutil.rmtree(d, ignore_errors=True)
    argv = mdr_command() + ["run", os.path.join(sim_dir, "sequence.bag"), "--out", d,
                            "--pose-source", v["pose_source"], "--quiet"] + v["argv"]
    if args.max_frames:
        argv += ["--max-frames", str(args.max_frames)]
    if v["sets"]:
        for s in args.set:
            argv += ["--set", s]
    print("  %s: mdr run %s" % (scene, variant), file=sys.stderr, flush=True)
    if _call(argv, d + ".log") != 0:
        raise RuntimeError("mdr run failed, see %s.log" % d)
    return d


def score(run_dir: str, sim_dir: str, variant: str, gt, args) -> dict:
    """The figures of one run's map and grid (and ATE with the tracker's poses)."""
    import numpy as np
    from mdr_slam.cli.main_bench import _grid_params
    from mdr_slam.cli.main_eval import map_grid_confidence
    from mdr_slam.eval import ate, grid_metrics, map_alignment, map_metrics
    from mdr_slam.eval.trajectory import read_for_eval
    from mdr_slam.io import cloud_xyz, read_cloud
    from mdr_slam.nav import map_views

    v = VARIANTS[variant]
    gt_xyz, labels, gt_traj = gt
    est_traj = read_for_eval(os.path.join(run_dir, "trajectory.tum"))
    out = OrderedDict([("pose_source", v["pose_source"]), ("run", run_dir),
                       ("n_poses", int(len(est_traj)))])
    summ = json.load(open(os.path.join(run_dir, "summary.json")))
    out["frames_in"] = summ.get("frames_in")
    out["frames_lost"] = summ.get("frames_lost")
    # the true camera path over the frames the run used (all of them without --max-frames)
    st = gt_traj.stamps
    if len(est_traj):
        keep = (st >= est_traj.stamps.min() - 1e-3) & (st <= est_traj.stamps.max() + 1e-3)
    else:
        keep = np.ones(len(st), bool)
    path = gt_traj.positions[keep]
    map_path = os.path.join(run_dir, "map.ply")
    cloud = read_cloud(map_path)
    est = cloud_xyz(cloud)
    gparams = _grid_params(args.set if v["sets"] else [])
    views = map_views(cloud) if gparams["raytrace"] else None
    if v["pose_source"] == "orb":
        res = ate(est_traj, gt_traj, "se3")
        out["ate_m"] = res.stats["rmse"]
        out["ate_max_m"] = res.stats["max"]
        # the map is in the tracker's frame: into the simulator's by the trajectory alignment
        al = map_alignment(est_traj, gt_traj)
        R, t = np.asarray(al["rotation"]), np.asarray(al["translation"])
        est = est @ R.T + t
        if views is not None:
            views = views @ R.T + t
    out["n_points"] = int(len(est))
    try:
        m = map_metrics(est, gt_xyz, threshold=args.threshold, gt_labels=labels, path=path,
                        max_range=args.max_range)
        r = m["in_range"]
        low = r.get("per_label", {}).get("low_texture", {})
        out["map"] = OrderedDict([
            ("max_range_m", args.max_range), ("precision", r.get("accuracy")),
            ("rmse_m", r.get("accuracy_rmse")), ("completeness", r.get("completeness")),
            ("fscore", r.get("fscore")),
            ("low_texture", OrderedDict([("precision", low.get("accuracy")),
                                         ("completeness", low.get("completeness")),
                                         ("fscore", low.get("fscore"))])),
            ("whole_map", OrderedDict([("precision", m.get("accuracy")),
                                       ("rmse_m", m.get("accuracy_rmse")),
                                       ("completeness", m.get("completeness")),
                                       ("fscore", m.get("fscore"))]))])
    except ValueError as e:        # an empty map: nothing to score
        out["map"] = {"error": str(e)}
    try:
        mc = map_grid_confidence(map_path, cloud, gparams["min_confidence"])
        g = grid_metrics(est, gt_xyz, labels, path, cloud.get("confidence"), mc,
                         gparams["resolution"], gparams["z_min"], gparams["z_max"],
                         gparams["up_axis"], gparams["free_band"], 1, args.grid_range,
                         est_views=views, max_gap=gparams["max_gap"],
                         raytrace_range=gparams["raytrace_range"])
        gr = g["in_range"]
        out["grid"] = OrderedDict([
            ("max_range_m", args.grid_range), ("recall", gr["recall"]),
            ("precision", gr["precision"]), ("n_true_cells", gr["n_true_cells"]),
            ("n_est_cells", gr["n_est_cells"]), ("min_confidence", g["min_confidence"]),
            ("route_occupied_est", g["route"]["occupied_est"]),
            ("whole_grid", OrderedDict([("recall", g["recall"]), ("precision", g["precision"])]))])
    except ValueError as e:
        out["grid"] = {"error": str(e)}
    return out


def _f(x, fmt="%.3f"):
    return "-" if x is None else fmt % x


def _pct(x):
    return "-" if x is None else "%.1f %%" % (100.0 * x)


def markdown(scene: str, res: dict, args) -> str:
    base_f = res.get(BASELINE, {}).get("map", {}).get("fscore")
    lines = ["### %s (seed %d)" % (scene, args.seed), "",
             "| variant | poses | precision | RMSE (m) | completeness | F | F / baseline | "
             "grid recall <= %g m | grid precision <= %g m | ATE (m) |"
             % (args.grid_range, args.grid_range),
             "|---|---|---|---|---|---|---|---|---|---|"]
    for variant, r in res.items():
        if "error" in r and "map" not in r:
            lines.append("| %s | %s | %s |" % (variant, VARIANTS[variant]["pose_source"],
                                               r["error"]))
            continue
        m, g = r.get("map", {}), r.get("grid", {})
        f = m.get("fscore")
        ratio = f / base_f if f is not None and base_f else None
        lines.append("| %s | %s | %s | %s | %s | %s | %s | %s | %s | %s |" % (
            variant, r["pose_source"], _pct(m.get("precision")), _f(m.get("rmse_m")),
            _pct(m.get("completeness")), _pct(f), _f(ratio, "%.2f"), _pct(g.get("recall")),
            _pct(g.get("precision")), _f(r.get("ate_m"))))
        if "error" in m:
            lines.append("| | | map not scored: %s | | | | | | | |" % m["error"])
    lines += ["", "Map figures: points within %g m of the true camera path, precision and "
              "completeness at %g cm (mdr eval map); grid: obstacle cells, one cell of "
              "tolerance, within %g m of the path (mdr eval grid)."
              % (args.max_range, 100 * args.threshold, args.grid_range), ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    from mdr_slam.eval import DEFAULT_MAX_RANGE
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="office,corridor,garage,atrium",
                    help="comma-separated scenes (default office,corridor,garage,atrium)")
    ap.add_argument("--seed", type=int, default=7, help="mdr sim --seed (default 7)")
    ap.add_argument("--work", default="/tmp/mdr_far_walls",
                    help="folder of the sequences and runs (a sequence there is reused)")
    ap.add_argument("--out", default=None, metavar="FILE",
                    help="JSON report (default WORK/far_walls.json)")
    ap.add_argument("--duration", type=float, default=None,
                    help="mdr sim --duration (default: its own, 30 s per lap)")
    ap.add_argument("--rate", type=float, default=None, help="mdr sim --rate (default 20 Hz)")
    ap.add_argument("--scale", type=float, default=None,
                    help="mdr sim --scale (default 1; 0.5 for quick looks: the filter converges "
                         "on little at half resolution)")
    ap.add_argument("--workers", type=int, default=None, help="mdr sim --workers")
    ap.add_argument("--max-frames", type=int, default=None, help="mdr run --max-frames")
    ap.add_argument("--max-range", type=float, default=DEFAULT_MAX_RANGE,
                    help="map figures within this many metres of the path (default %g, as "
                         "mdr eval map)" % DEFAULT_MAX_RANGE)
    ap.add_argument("--grid-range", type=float, default=5.0,
                    help="grid figures within this many metres of the path (default 5)")
    ap.add_argument("--threshold", type=float, default=0.05,
                    help="precision/completeness distance, m (default 0.05)")
    ap.add_argument("--set", action="append", default=[], metavar="NODE.KEY=VALUE",
                    help="mdr run --set for the default and tracked runs (not the baseline); "
                         "repeatable")
    ap.add_argument("--variants", default=",".join(VARIANTS),
                    help="comma-separated variants to run (default all: %s)" % ",".join(VARIANTS))
    ap.add_argument("--reuse-runs", action="store_true",
                    help="score a run folder that already holds a finished run instead of "
                         "running it again (its folder name carries the --set options)")
    args = ap.parse_args(argv)
    from mdr_slam.eval.trajectory import read_for_eval
    from mdr_slam.io import cloud_xyz, read_cloud
    from mdr_slam.sim import SCENES

    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    bad = [s for s in scenes if s not in SCENES]
    if bad:
        ap.error("unknown scene(s) %s (known: %s)" % (", ".join(bad), ", ".join(SCENES)))
    os.makedirs(args.work, exist_ok=True)
    out_path = args.out or os.path.join(args.work, "far_walls.json")
    report = OrderedDict([
        ("scenes", scenes), ("seed", args.seed), ("sets", list(args.set)),
        ("options", OrderedDict((k, getattr(args, k)) for k in (
            "duration", "rate", "scale", "max_frames", "max_range", "grid_range", "threshold"))),
        ("variants", OrderedDict((k, {"pose_source": v["pose_source"], "argv": v["argv"],
                                      "sets": v["sets"]}) for k, v in VARIANTS.items())),
        ("results", OrderedDict())])
    code = 0
    tables = []
    for scene in scenes:
        res = report["results"][scene] = OrderedDict()
        try:
            sim_dir = simulate(scene, args)
        except RuntimeError as e:
            print("far_walls_report: %s" % e, file=sys.stderr)
            res["error"] = str(e)
            code = 1
            continue
        gt_cloud = read_cloud(os.path.join(sim_dir, "gt_map.ply"))
        gt = (cloud_xyz(gt_cloud), gt_cloud.get("surface"),
              read_for_eval(os.path.join(sim_dir, "groundtruth.tum")))
        for variant in [v for v in args.variants.split(",") if v in VARIANTS]:
            try:
                d = run_variant(scene, variant, sim_dir, args)
                res[variant] = score(d, sim_dir, variant, gt, args)
            except (RuntimeError, OSError, ValueError) as e:
                print("far_walls_report: %s %s: %s" % (scene, variant, e), file=sys.stderr)
                res[variant] = {"pose_source": VARIANTS[variant]["pose_source"], "error": str(e)}
                code = 1
        base_f = res.get(BASELINE, {}).get("map", {}).get("fscore")
        for r in res.values():
            f = r.get("map", {}).get("fscore") if isinstance(r, dict) else None
            if isinstance(r, dict) and "map" in r:
                r["map"]["f_ratio"] = f / base_f if f is not None and base_f else None
        tables.append(markdown(scene, res, args))
        print(tables[-1], flush=True)
        with open(out_path, "w") as f:      # after every scene: a long run keeps what it has
            json.dump(report, f, indent=2, default=float)
    with open(out_path, "w") as f:
        json.dump(report, f, indent=2, default=float)
    print("far_walls_report: wrote %s" % out_path, file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
