"""``mdr bench``: the live system's rates and resources (paper Table 4), and the paper's ablation
(Table 2) on simulated sequences with exact ground truth.

    mdr bench BAG --out DIR [--duration S] [--loop] [--rate 1] [--pose-source orb|groundtruth]
        [--left-image TOPIC ... --image-transport compressed --sync-tolerance S --rectified auto]
    mdr bench --ablation --out DIR [--scenes office,corridor] [--duration 30] [--pose-source groundtruth]
        [--max-range 4] [--configs elas_only,temporal,confidence,full,full_elas,sgbm_tsdf]
    mdr bench BAG --out DIR --compare [--runs 3] [--no-live] [--max-frames N]
    mdr bench --compare --kitti DIR | --euroc DIR --out DIR [--runs 3] [--max-frames N]
    mdr bench --navigate --out DIR [--scenes office,corridor,garage] [--seed N] [--goals 10]
        (the simulated robot driven by move_base on the map: mdr_slam.cli.bench_navigate)

Live (``mdr bench BAG``): starts a private roscore, ``roslaunch mdr_slam mdr.launch bag:=BAG`` (the
three nodes and ``rosbag play --clock``), samples every node's CPU % and RSS once a second (psutil),
listens to the nodes' topics and ``/diagnostics``, and writes ``DIR/bench.json`` (map_integration_hz,
depth_hz, pose_hz, frames_in, frames_tracked, latency_ms, cpu_percent and rss_mb per node and in
total, median and max), ``DIR/report.md`` and ``DIR/resources.png``. The bag input options
(``--left-image``, ``--right-image``, ``--left-info``, ``--right-info``, ``--ground-truth-pose``,
``--image-transport``, ``--sync-tolerance``, ``--rectified``) go to the launch file as its
arguments of the same names (``left_image:=...``); live poses default to ``orb`` (the launch
file's default), ``groundtruth`` relays the bag's ground-truth topic. Long runs (``--loop
--live-duration 1800``): bench.json's ``timeline``, report.md's table and ``DIR/timeline.png``
give per window (``--window S``) RSS per node and in total, tracking ms median and p90, the
share of stereo pairs tracked, keyframes alive, sparse and dense map points, loop closures and
the map rate.

For each scene: render the sequence (``mdr sim``, skipped when ``DIR/sim_<scene>`` exists), run the
offline pipeline (``mdr run``) five times -- ELAS-only baseline (temporal off, confidence off),
temporal only, confidence only, full, and full with ELAS on every pixel as the paper
(``full_elas``: no weak-texture matcher) -- plus a peer, ``sgbm_tsdf`` (OpenCV StereoSGBM depth
fused in Open3D's ScalableTSDFVolume, mdr_slam.eval.peer, on the same frames with the true
poses), and score each map against the simulator's ground-truth map (``mdr eval map``: RMSE of
estimated-to-truth distances, completeness at 5 cm over the whole map; and completeness,
precision and F-score, overall and per surface label, within ``--max-range`` of the camera path:
what a stereo rig can see) and its occupancy grid against the true one (``mdr eval grid``:
obstacle-cell recall and precision with one cell of tolerance, occupied cells on the camera's
route, free-cell precision; the grid the fusion node publishes, rays from map.ply's views
included). The runs place the frames with the simulator's true poses unless ``--pose-source orb``
(``mdr run`` is given ``--pose-source`` explicitly: its own default is orb; the peer always uses
the true poses). Writes ``DIR/ablation.json``, ``DIR/ablation.md`` and ``DIR/ablation.png``.

Tracker comparison (``--compare``): the built-in tracker (``mdr``) and ORB-SLAM3 (``orbslam3``,
pyorbslam3) on the same input. ``--runs`` times, alternating, the live benchmark with each
backend (``--set pose.backend=...``; into ``DIR/live_<backend>_<i>/``, its output in
``DIR/live_<backend>_<i>.log``), then the offline tracker benchmark (mdr_slam.eval.tracker: the
frames rectified in memory, CPU per frame, track time, tracked/LOST, ATE as published and
final) ``--runs`` times per backend. ``--no-live``, ``--kitti DIR`` and ``--euroc DIR``: offline
only. Writes ``DIR/compare.json`` and ``DIR/compare.md``: both tables (median and min-max over
the runs), the live ATE against the same backend's offline ATE, and the built-in tracker's
targets, each with yes/no. Without pyorbslam3 only ``mdr`` runs, and the report says so.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections import OrderedDict

import numpy as np

from ..eval import DEFAULT_MAX_RANGE, ate, grid_metrics, grid_params, map_alignment, map_metrics
from ..io import cloud_xyz, read_cloud, read_tum
from ..nav import map_min_confidence, map_views
from . import mdr_command
from .main_run import _overrides, _seconds, add_bag_input_arguments, bag_input_argv, bag_topics

SURFACE_LABELS_ORDER = ("low_texture", "textured", "specular")
CONFIGS = OrderedDict([
    ("elas_only", {"temporal": False, "confidence": False}),
    ("temporal", {"temporal": True, "confidence": False}),
    ("confidence", {"temporal": False, "confidence": True}),
    ("full", {"temporal": True, "confidence": True}),
    # the full system with ELAS on every pixel, as the paper (no weak-texture matcher)
    ("full_elas", {"temporal": True, "confidence": True, "set": ["depth.weak_texture=off"]}),
])
# peers: other mapping methods run on the same frames (python -m MODULE BAG --out DIR ...)
PEERS = OrderedDict([
    ("sgbm_tsdf", "mdr_slam.eval.peer"),
])


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", nargs="?", help="bag to play live (omit with --ablation)")
    p.add_argument("--ablation", action="store_true", help="run the offline map ablation")
    p.add_argument("--navigate", action="store_true",
                   help="the robot in the loop: simulated robot, mdr.launch and move_base, "
                        "seeded goals per scene (default scenes office,corridor,garage)")
    p.add_argument("--goals", type=int, default=10, help="--navigate: goals per scene")
    p.add_argument("--navigate-scene", default=None, help=argparse.SUPPRESS)
    p.add_argument("--record", action="store_true",
                   help="--navigate: record the robot's topics (images, camera_info, odom, tf, ground "
                        "truth) and what the planners saw (the depth cloud, the grid, the map "
                        "points, keyframes, plans) to DIR/SCENE/robot.bag, for "
                        "scripts/replay_robot_bag.py")
    p.add_argument("--robot-arg", action="append", default=[], metavar="NAME:=VALUE",
                   help="--navigate: an argument for sim_robot.launch (e.g. scale:=1.0)")
    p.add_argument("--compare", action="store_true",
                   help="compare the built-in tracker (mdr) with ORB-SLAM3 (orbslam3): live and "
                        "offline, --runs times each")
    p.add_argument("--runs", type=int, default=3,
                   help="--compare: runs per backend, live and offline (default 3)")
    p.add_argument("--no-live", action="store_true", help="--compare: the offline comparison only")
    p.add_argument("--kitti", metavar="DIR",
                   help="--compare: a KITTI odometry folder instead of a BAG (offline only)")
    p.add_argument("--euroc", metavar="DIR",
                   help="--compare: an EuRoC (ASL) folder instead of a BAG (offline only)")
    p.add_argument("--out", required=True)
    p.add_argument("--loop", action="store_true", help="live: play the bag in a loop")
    p.add_argument("--rate", type=float, default=1.0, help="live: rosbag play rate")
    p.add_argument("--live-duration", type=float, default=None,
                   help="live: seconds to run (default: the bag's length / rate + 15 s)")
    p.add_argument("--window", type=_seconds, default=None, metavar="S",
                   help="live: the report's time windows, s (default: 60 for runs of 5 minutes "
                        "or more, else about a sixth of the run), e.g. --window 300")
    p.add_argument("--scenes", default=None,
                   help="--ablation: default office,corridor; --navigate: office,corridor,garage")
    p.add_argument("--duration", type=float, default=30.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--pose-source", choices=("groundtruth", "orb"), default=None,
                   help="default: groundtruth for --ablation (map quality of depth and fusion "
                        "alone), orb live (as on a robot)")
    p.add_argument("--configs", default=",".join(list(CONFIGS) + list(PEERS)),
                   help="subset of %s" % ", ".join(list(CONFIGS) + list(PEERS)))
    p.add_argument("--jobs", type=int, default=2, help="runs in parallel (one per core)")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--threshold", type=float, default=0.05, help="completeness threshold (m)")
    p.add_argument("--max-range", type=float, default=DEFAULT_MAX_RANGE,
                   help="ablation: also score the maps within this many metres of the camera "
                        "path (default %g)" % DEFAULT_MAX_RANGE)
    p.add_argument("--launch-arg", action="append", default=[], metavar="NAME:=VALUE",
                   help="live: extra mdr.launch argument (repeatable), e.g. depth_prefix:=")
    p.add_argument("--set", action="append", default=[], metavar="NODE.KEY=VALUE",
                   help="parameter override passed to every mdr run, or to the live nodes")
    add_bag_input_arguments(p)
    p.set_defaults(func=run)
    return p


def _input_launch_args(args) -> list:
    """The bag input options as mdr.launch arguments of the same names."""
    return ["%s:=%s" % (k, getattr(args, k)) for k in (
        "left_image", "right_image", "left_info", "right_info", "ground_truth_pose",
        "image_transport", "sync_tolerance", "rectified")]



def _run_parallel(cmds, jobs):
    """Run (name, argv, log) commands, at most ``jobs`` at a time; returns {name: returncode}."""
    pending, running, codes = list(cmds), [], {}
    while pending or running:
        while pending and len(running) < jobs:
            name, argv, log = pending.pop(0)
            running.append((name, subprocess.Popen(argv, stdout=open(log, "wb"),
                                                   stderr=subprocess.STDOUT)))
        time.sleep(0.5)
        for item in list(running):
            if item[1].poll() is not None:
                codes[item[0]] = item[1].returncode
                running.remove(item)
    return codes


def run(args) -> int:
    if args.navigate:
        from .bench_navigate import run_navigate
        return run_navigate(args)
    if args.compare:
        return run_compare(args)
    if args.kitti or args.euroc:
        raise SystemExit("mdr bench: --kitti and --euroc go with --compare")
    if not args.ablation:
        if not args.bag:
            raise SystemExit("mdr bench: give a BAG for the live benchmark, or --ablation")
        # the live benchmark when it runs: `mdr --help` imports this module
        from .bench_live import run_live
        # before --launch-arg's, so those still win (roslaunch keeps an argument's last value)
        args.launch_arg = _input_launch_args(args) + list(args.launch_arg or [])
        return run_live(args)
    return run_ablation(args)


def _fell_back(run_dir: str) -> bool:
    """Whether a live run's pose node logged that it could not start its backend and tracked
    with the built-in one (its ROS log under ``run_dir/roslog``)."""
    for root, _, files in os.walk(os.path.join(run_dir, "roslog")):
        for f in files:
            if f.startswith("pose_node") and f.endswith(".log"):
                with open(os.path.join(root, f), errors="replace") as fh:
                    if "using the built-in tracker" in fh.read():
                        return True
    return False


def _live_compare_run(args, backend: str, run_dir: str, log: str):
    """One live benchmark (``mdr bench BAG``, a process of its own: a process is one ROS node
    for good) with ``pose.backend=backend``; ``(bench.json dict or None, error or None)``."""
    argv = mdr_command() + ["bench", os.path.abspath(args.bag), "--out", run_dir,
                            "--rate", str(args.rate)]
    if args.loop:
        argv.append("--loop")
    if args.live_duration:
        argv += ["--live-duration", str(args.live_duration)]
    if getattr(args, "window", None):
        argv += ["--window", str(args.window)]
    for a in args.launch_arg or []:
        argv += ["--launch-arg", a]
    for it in list(args.set or []) + ["pose.backend=" + backend]:   # the last value wins
        argv += ["--set", it]
    argv += bag_input_argv(args)
    with open(log, "wb") as f:
        code = subprocess.call(argv, stdout=f, stderr=subprocess.STDOUT)
    path = os.path.join(run_dir, "bench.json")
    if code != 0 or not os.path.exists(path):
        print(open(log, errors="replace").read()[-2000:], file=sys.stderr)
        return None, "the live benchmark failed (exit %d), see %s" % (code, log)
    if backend != "mdr" and _fell_back(run_dir):
        return None, ("the pose node could not start %s and tracked with the built-in tracker, "
                      "see %s" % (backend, os.path.join(run_dir, "roslog")))
    with open(path) as f:
        return json.load(f), None


def run_compare(args) -> int:
    """``--compare``: the module docstring's tracker comparison."""
    sources = [x for x in (args.bag, args.kitti, args.euroc) if x]
    if len(sources) != 1:
        raise SystemExit("mdr bench --compare: give one input: a BAG, --kitti DIR or --euroc DIR")
    if args.ablation:
        raise SystemExit("mdr bench: --compare and --ablation are separate benchmarks")
    if args.runs < 1:
        raise SystemExit("mdr bench --compare: --runs must be at least 1")
    if args.pose_source == "groundtruth":
        raise SystemExit("mdr bench --compare compares trackers: not with --pose-source groundtruth")
    if not os.path.exists(sources[0]):
        raise SystemExit("mdr bench --compare: %s does not exist" % sources[0])
    # the offline tracker benchmark (pose backends, evo) when it runs: `mdr --help` imports this
    from ..eval.tracker import (BACKENDS, available_backends, compare_report_markdown,
                                compare_targets, compare_trackers, live_summary)
    pose_params = _overrides(args.set)["pose"]   # refuses a bad --set before anything runs
    kind = "bag" if args.bag else ("kitti" if args.kitti else "euroc")
    source = os.path.abspath(sources[0])
    os.makedirs(args.out, exist_ok=True)
    backends, notes = available_backends(BACKENDS)
    for n in notes:
        print("mdr bench --compare: %s" % n, file=sys.stderr)
    live = kind == "bag" and not args.no_live
    if live and args.max_frames:
        notes.append("offline on the first %d frames, live on the whole bag: the live / offline "
                     "ATE ratios compare different stretches" % args.max_frames)
    live_runs = OrderedDict((b, []) for b in backends)
    entries = []
    code = 0
    if live:
        for i in range(1, args.runs + 1):
            for b in backends:   # alternating: a load spike on a shared machine falls on both
                d = os.path.join(args.out, "live_%s_%d" % (b, i))
                log = d + ".log"
                print("mdr bench --compare: live run %d/%d, %s -> %s" % (i, args.runs, b, d),
                      file=sys.stderr)
                bench, err = _live_compare_run(args, b, d, log)
                live_runs[b].append(bench)
                entries.append(OrderedDict([("backend", b), ("run", i), ("dir", d),
                                            ("error", err)]))
                if err:
                    print("mdr bench --compare: %s" % err, file=sys.stderr)
                    notes.append("live run %d of %s: %s" % (i, b, err))
                    code = 1
    print("mdr bench --compare: offline, %d run(s) per backend of %s" % (args.runs, source),
          file=sys.stderr)
    offline = None
    bag_options = None
    if kind == "bag":
        bag_options = {"topics": bag_topics(args), "image_transport": args.image_transport,
                       "sync_tolerance": args.sync_tolerance, "rectified": args.rectified}
    try:
        offline = compare_trackers(source, kind, backends, args.runs, args.max_frames,
                                   params=pose_params, bag_options=bag_options,
                                   log=lambda m: print(m, file=sys.stderr))
    except Exception as e:   # noqa: BLE001 - the live part is reported all the same
        notes.append("the offline comparison failed: %s: %s" % (type(e).__name__, e))
        print("mdr bench --compare: %s" % notes[-1], file=sys.stderr)
        code = 1
    summary = live_summary(live_runs, offline) if live else None
    report = OrderedDict()
    report["source"] = source
    report["kind"] = kind
    report["runs"] = args.runs
    report["backends"] = backends
    report["notes"] = notes
    report["live_skipped"] = None if live else (
        "--no-live" if kind == "bag" else "a %s folder is not a bag: offline only" % kind)
    report["live_runs"] = entries
    report["live"] = summary
    report["offline"] = offline
    report["targets"] = compare_targets(summary, offline)
    with open(os.path.join(args.out, "compare.json"), "w") as f:
        json.dump(report, f, indent=2, default=str)
    md = compare_report_markdown(report)
    with open(os.path.join(args.out, "compare.md"), "w") as f:
        f.write(md)
    print(md)
    return code


def run_ablation(args) -> int:
    os.makedirs(args.out, exist_ok=True)
    scenes = [s for s in (args.scenes or "office,corridor").split(",") if s]
    configs = [c for c in args.configs.split(",") if c]
    for c in configs:
        if c not in CONFIGS and c not in PEERS:
            raise SystemExit("unknown config %r (known: %s)" % (c, ", ".join(list(CONFIGS) +
                                                                              list(PEERS))))
    gparams = _grid_params(args.set)
    # 1. sequences
    sims = []
    for scene in scenes:
        d = os.path.join(args.out, "sim_" + scene)
        if not os.path.exists(os.path.join(d, "gt_map.ply")):
            sims.append(("sim_" + scene, mdr_command() + ["sim", "--scene", scene, "--duration",
                                                   str(args.duration), "--seed", str(args.seed),
                                                   "--out", d, "--quiet"],
                         os.path.join(args.out, "sim_%s.log" % scene)))
    for name, argv, log in sims:  # the simulator uses both cores itself
        print("mdr bench: rendering %s" % name, file=sys.stderr)
        if _run_parallel([(name, argv, log)], 1)[name] != 0:
            print(open(log, errors="replace").read()[-2000:], file=sys.stderr)
            return 1
    # 2. the four runs (and the peers) per scene
    runs = []
    for scene in scenes:
        for c in configs:
            d = os.path.join(args.out, "%s_%s" % (scene, c))
            if c in PEERS:
                argv = [sys.executable, "-m", PEERS[c],
                        os.path.join(args.out, "sim_" + scene, "sequence.bag"), "--out", d]
                argv += bag_input_argv(args)
                if args.max_frames:
                    argv += ["--max-frames", str(args.max_frames)]
                runs.append(("%s_%s" % (scene, c), argv, d + ".log"))
                continue
            argv = mdr_command() + ["run", os.path.join(args.out, "sim_" + scene, "sequence.bag"),
                             "--out", d, "--pose-source", args.pose_source or "groundtruth", "--quiet",
                             "--temporal", "on" if CONFIGS[c]["temporal"] else "off",
                             "--confidence", "on" if CONFIGS[c]["confidence"] else "off"]
            argv += bag_input_argv(args)
            if args.max_frames:
                argv += ["--max-frames", str(args.max_frames)]
            for s in CONFIGS[c].get("set", []) + list(args.set):
                argv += ["--set", s]
            runs.append(("%s_%s" % (scene, c), argv, d + ".log"))
    print("mdr bench: %d runs, %d at a time" % (len(runs), args.jobs), file=sys.stderr)
    t0 = time.time()
    codes = _run_parallel(runs, args.jobs)
    print("mdr bench: runs took %.0f s" % (time.time() - t0), file=sys.stderr)
    # 3. scores
    results = OrderedDict()
    for scene in scenes:
        gt = read_cloud(os.path.join(args.out, "sim_" + scene, "gt_map.ply"))
        gt_xyz = cloud_xyz(gt)
        gt_path = read_tum(os.path.join(args.out, "sim_" + scene, "groundtruth.tum"))
        results[scene] = OrderedDict()
        for c in configs:
            name = "%s_%s" % (scene, c)
            d = os.path.join(args.out, name)
            if codes.get(name) != 0:
                results[scene][c] = {"error": "%s failed, see %s.log" % (
                    "the peer" if c in PEERS else "mdr run", d)}
                continue
            cloud = read_cloud(os.path.join(d, "map.ply"))
            est = cloud_xyz(cloud)
            # the views of mdr run's map (a peer's cloud has none: no rays), as the node uses them
            views = map_views(cloud) if gparams["raytrace"] else None
            summ = json.load(open(os.path.join(d, "summary.json")))
            traj = None
            if (args.pose_source or "groundtruth") == "orb" and c not in PEERS:
                # estimated poses: the map is in the tracker's frame; move it into the ground
                # truth's by the trajectory's SE(3) alignment (as evo aligns trajectories)
                est_traj = read_tum(os.path.join(d, "trajectory.tum"))
                gt_traj = read_tum(os.path.join(args.out, "sim_" + scene, "groundtruth.tum"))
                traj = ate(est_traj, gt_traj, "se3")
                al = map_alignment(est_traj, gt_traj)
                est = est @ np.asarray(al["rotation"]).T + np.asarray(al["translation"])
                if views is not None:   # the rays move with their points
                    views = views @ np.asarray(al["rotation"]).T + np.asarray(al["translation"])
            # the maps are in the simulator's map frame (true poses, or aligned above), so the
            # true camera path is their path too
            try:
                m = map_metrics(est, gt_xyz, threshold=args.threshold, gt_labels=gt.get("surface"),
                                path=gt_path, max_range=args.max_range)
                # the fusion node's grid: confident points of a confidence map, all points
                # otherwise; rays from the points' views, wall gaps closed
                mc = map_min_confidence({"confidence": CONFIGS.get(c, {}).get("confidence", False),
                                         "display_min_confidence": gparams["min_confidence"],
                                         "grid_min_confidence": gparams["min_confidence"]})[1]
                g = grid_metrics(est, gt_xyz, gt.get("surface"), gt_path, cloud.get("confidence"),
                                 mc, gparams["resolution"], gparams["z_min"], gparams["z_max"],
                                 gparams["up_axis"], gparams["free_band"], 1, args.max_range,
                                 est_views=views, max_gap=gparams["max_gap"],
                                 raytrace_range=gparams["raytrace_range"])
            except ValueError as e:   # e.g. an empty map: one row says so, the others are scored
                results[scene][c] = {"error": "not scored: %s" % e}
                codes[name] = 1
                continue
            prec, comp = m["accuracy"], m["completeness"]
            results[scene][c] = OrderedDict([
                ("rmse_m", m["accuracy_rmse"]), ("completeness", comp),
                ("accuracy_5cm", prec), ("fscore", 2 * prec * comp / max(prec + comp, 1e-12)),
                ("n_points", int(len(est))),
                ("per_label", {k: {"rmse_m": v.get("accuracy_rmse"),
                                   "completeness": v.get("completeness"),
                                   "n": v.get("n_estimate")}
                               for k, v in m.get("per_label", {}).items()}),
                ("in_range", _in_range_row(m["in_range"])),
                ("grid", _grid_row(g)),
                ("frames", summ["frames_in"]), ("frames_posed", summ.get("frames_posed")),
                ("timing", summ["timing"].get("frame"))])
            if traj is not None:
                results[scene][c]["ate_m"] = traj.stats["rmse"]
                results[scene][c]["path_length_m"] = traj.stats["path_length"]
    report = {"scenes": scenes, "configs": configs, "duration_s": args.duration,
              "pose_source": args.pose_source or "groundtruth", "threshold_m": args.threshold,
              "max_range_m": args.max_range, "grid": dict(gparams), "results": results}
    with open(os.path.join(args.out, "ablation.json"), "w") as f:
        json.dump(report, f, indent=2)
    md = _markdown(report)
    with open(os.path.join(args.out, "ablation.md"), "w") as f:
        f.write(md)
    _plot(report, os.path.join(args.out, "ablation.png"))
    print(md)
    return 0 if all(v == 0 for v in codes.values()) else 1


def _grid_params(sets) -> dict:
    """The fusion node's grid parameters, with the ``--set fusion.grid_*=V`` overrides the runs
    get too (so the grid is scored as the node would publish it with them)."""
    over = {}
    names = {"grid_resolution": "resolution", "grid_z_min": "z_min", "grid_z_max": "z_max",
             "grid_up_axis": "up_axis", "grid_free_band": "free_band",
             "grid_min_confidence": "min_confidence", "grid_raytrace": "raytrace",
             "grid_raytrace_range": "raytrace_range", "grid_max_gap": "max_gap"}
    for it in sets or []:
        key, _, val = it.partition("=")
        node, _, k = key.partition(".")
        if node == "fusion" and k in names:
            over[names[k]] = val
    return grid_params(**over)


def _in_range_row(r) -> dict:
    """The table's figures of map_metrics' in_range block."""
    def row(b):
        return OrderedDict([("completeness", b.get("completeness")), ("precision", b.get("accuracy")),
                            ("fscore", b.get("fscore")), ("rmse_m", b.get("accuracy_rmse")),
                            ("n_ground_truth", b["n_ground_truth"]), ("n_estimate", b["n_estimate"])])
    out = row(r)
    out["max_range_m"] = r["max_range_m"]
    out["per_label"] = OrderedDict((k, row(v)) for k, v in r.get("per_label", {}).items())
    return out


def _grid_row(g) -> dict:
    """The table's figures of grid_metrics."""
    out = OrderedDict([("recall", g["recall"]), ("precision", g["precision"]),
                       ("n_true_cells", g["n_true_cells"]), ("n_est_cells", g["n_est_cells"]),
                       ("min_confidence", g["min_confidence"]),
                       ("free_precision", g["free_precision"]),
                       ("n_free_cells", g["n_est_free_cells"]), ("raytrace", g["raytrace"])])
    out["recall_per_label"] = OrderedDict((k, v["recall"]) for k, v in g.get("per_label", {}).items())
    rng = g.get("in_range", {})
    out["recall_in_range"] = rng.get("recall")
    out["recall_in_range_per_label"] = OrderedDict(
        (k, v["recall"]) for k, v in rng.get("per_label", {}).items())
    out["route_cells"] = g["route"]["n_cells"]
    out["route_occupied"] = g["route"]["occupied_est"]
    out["route_occupied_true"] = g["route"]["occupied_true"]
    return out


def _markdown(report) -> str:
    lines = ["# Map ablation (paper Table 2), %s poses, completeness at %.0f cm" % (
        report["pose_source"], 100 * report["threshold_m"]), "",
        "Precision: share of map points within that distance of a true surface; F-score: harmonic "
        "mean of precision and completeness.", "",
        "| scene | config | map RMSE (m) | completeness | precision | F-score | points "
        "| RMSE low-texture | RMSE textured | RMSE specular | RMSE vs ELAS-only | ATE |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for scene, res in report["results"].items():
        base = res.get("elas_only", {}).get("rmse_m")
        for c, r in res.items():
            if "error" in r:
                lines.append("| %s | %s | %s |" % (scene, c, r["error"]))
                continue
            pl = r["per_label"]
            cell = lambda k: ("%.4f" % pl[k]["rmse_m"]) if pl.get(k, {}).get("rmse_m") is not None \
                else "-"
            rel = ("%+.1f %%" % (100 * (r["rmse_m"] / base - 1))) if base else "-"
            at = ("%.3f m (%.2f %%)" % (r["ate_m"], 100 * r["ate_m"] / max(r["path_length_m"], 1e-9))
                  if "ate_m" in r else "-")
            lines.append("| %s | %s | %.4f | %.1f %% | %.1f %% | %.3f | %d | %s | %s | %s | %s | %s |" % (
                scene, c, r["rmse_m"], 100 * r["completeness"], 100 * r["accuracy_5cm"],
                r.get("fscore", float("nan")), r["n_points"],
                cell("low_texture"), cell("textured"), cell("specular"), rel, at))
    lines += _markdown_in_range(report)
    return "\n".join(lines) + "\n"


def _pct(v) -> str:
    return "-" if v is None else "%.1f %%" % (100 * v)


def _f3(v) -> str:
    return "-" if v is None else "%.3f" % v


def _markdown_in_range(report) -> list:
    """The second table: what the rig can see (within max_range of the path) and the grid."""
    if not any("in_range" in r for res in report["results"].values() for r in res.values()):
        return []
    g = report.get("grid", {})
    lines = ["", "## Within %g m of the camera path, and the occupancy grid" % report["max_range_m"],
             "",
             "Map: completeness (C), precision (P) and F-score at %.0f cm of the ground-truth and "
             "estimated points within %g m of the true camera path (per label: ground-truth points "
             "of that surface; estimated points labelled by their nearest ground-truth point). "
             "Grid: the fusion node's obstacle grid (%g m cells, band %g-%g m along %s; points of "
             "confidence >= %s for confidence maps, all points otherwise) of the map against the one "
             "of the ground-truth map: obstacle-cell recall and precision with one cell of "
             "tolerance (recall of all true cells, and of those of the true points within range); "
             "route: occupied estimated cells on the camera's ground track, of all its cells "
             "(must be 0); free precision: share of the grid's free cells (rays from the points' "
             "views when the map has them, mapped floor) that are no true obstacle cell, and "
             "their number; wall gaps up to %g m closed. Time: wall time per frame, median / "
             "p90." % (
                 100 * report["threshold_m"], report["max_range_m"], g.get("resolution", 0.05),
                 g.get("z_min", 0.1), g.get("z_max", 1.5), g.get("up_axis", "z"),
                 g.get("min_confidence", 3), g.get("max_gap", 0.0)),
             "",
             "| scene | config | C | P | F-score | F low-texture | C low-texture | F textured "
             "| F specular | grid recall (all / in range) | grid recall low-texture (in range) "
             "| grid precision | grid free precision (cells) | route cells occupied | ms/frame |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for scene, res in report["results"].items():
        for c, r in res.items():
            if "in_range" not in r:
                continue
            ir, gr = r["in_range"], r["grid"]
            pl = ir["per_label"]
            lab = lambda k, f: pl.get(k, {}).get(f)
            t = r.get("timing") or {}
            ms = ("%.0f / %.0f" % (t["median_ms"], t["p90_ms"])) if "median_ms" in t else "-"
            lines.append("| %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s (%s) "
                         "| %d / %d | %s |" % (
                scene, c, _pct(ir["completeness"]), _pct(ir["precision"]), _f3(ir["fscore"]),
                _f3(lab("low_texture", "fscore")), _pct(lab("low_texture", "completeness")),
                _f3(lab("textured", "fscore")), _f3(lab("specular", "fscore")),
                "%s / %s" % (_pct(gr["recall"]), _pct(gr["recall_in_range"])),
                _pct(gr["recall_in_range_per_label"].get("low_texture")),
                _pct(gr["precision"]), _pct(gr.get("free_precision")), gr.get("n_free_cells", "-"),
                gr["route_occupied"], gr["route_cells"], ms))
    labels = [k for k in SURFACE_LABELS_ORDER
              if any(k in r.get("in_range", {}).get("per_label", {})
                     for res in report["results"].values() for r in res.values())]
    if not labels:
        return lines
    lines += ["", "Per surface label within %.0f m of the path: F-score, precision, completeness "
              "and RMSE; x ELAS: the F-score over the ELAS-only baseline's of the same run." % (
                  report["max_range_m"]),
              "", "| scene | config | " + " | ".join(
                  "%s F (x ELAS) | P | C | RMSE" % k.replace("_", "-") for k in labels) + " |",
              "|---|---|" + "---|---|---|---|" * len(labels)]
    for scene, res in report["results"].items():
        base = res.get("elas_only", {}).get("in_range", {}).get("per_label", {})
        for c, r in res.items():
            if "in_range" not in r:
                continue
            pl = r["in_range"]["per_label"]
            cells = []
            for k in labels:
                b = pl.get(k, {})
                f0 = base.get(k, {}).get("fscore")
                ratio = (" (%.2f)" % (b["fscore"] / f0)) if b.get("fscore") is not None and f0 \
                    else ""
                cells += [_f3(b.get("fscore")) + ratio, _pct(b.get("precision")),
                          _pct(b.get("completeness")),
                          "-" if b.get("rmse_m") is None else "%.3f" % b["rmse_m"]]
            lines.append("| %s | %s | %s |" % (scene, c, " | ".join(cells)))
    return lines


def _plot(report, path):
    # matplotlib: 0.3 s to import and it must get the Agg backend first; only the plot needs it
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    scenes = list(report["results"])
    configs = report["configs"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), dpi=100)
    w = 0.8 / max(len(configs), 1)
    for j, c in enumerate(configs):
        x = np.arange(len(scenes)) + j * w
        rm = [report["results"][s].get(c, {}).get("rmse_m", np.nan) for s in scenes]
        co = [100 * report["results"][s].get(c, {}).get("completeness", np.nan) for s in scenes]
        axes[0].bar(x, rm, w, label=c)
        axes[1].bar(x, co, w, label=c)
    for ax, t in zip(axes, ("map RMSE (m)", "completeness (%)")):
        ax.set_xticks(np.arange(len(scenes)) + 0.4 - w / 2)
        ax.set_xticklabels(scenes)
        ax.set_title(t)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
