"""``mdr run``: the whole pipeline offline on every frame of a bag (or an EuRoC/KITTI folder).

    mdr run BAG --out DIR [--pose-source orb|groundtruth] [--temporal on|off] [--confidence on|off]
    mdr run BAG --out DIR --left-image /cam/left/image_rect --right-image /cam/right/image_rect \
        --left-info /cam/left/camera_info --right-info /cam/right/camera_info \
        [--image-transport raw|compressed] [--sync-tolerance S] [--rectified auto|true|false]
    mdr run --euroc DIR --out DIR        mdr run --kitti DIR --out DIR

The bag is read as the nodes read their topics (the options are named as mdr.launch's
arguments): images of any intensity encoding, raw or compressed (``<topic>/compressed``), in the
order they were recorded, left and right paired by approximate time (``--sync-tolerance``, 0 =
auto), camera_info before, after or once beside the images (or ``--calib``). The frames are
tracked by the ORB tracker (``--pose-source orb``, the default, as on a robot);
``--pose-source groundtruth`` places them with the bag's ground-truth poses
(``--ground-truth-pose``) or the dataset's ground truth instead.

Writes the map folder ``DIR/map/`` (the fused dense map and the tracker's sparse map, for
``--map`` and the nodes' ``load_map``), ``DIR/map.ply`` (a link to the dense map),
``DIR/trajectory.tum`` (left camera optical frame in ``map``, one line per posed frame) and
``DIR/summary.json`` (frame counts, keyframes created, the first relocalization in a loaded map,
per-stage median and p90 milliseconds). With ``--window S``: also ``DIR/timeline.json`` and
``DIR/timeline.png``, the run per S seconds of bag time (memory, tracking time and share,
sparse and dense map size, loop closures: a long-run report).

    mdr run BAG --out A                                    # map once
    mdr run BAG --out B --map A/map --localization --start 6   # then localize in it The four runs of the paper's ablation (Table 2) differ only in --temporal and
--confidence.
"""
from __future__ import annotations

import argparse
import itertools
import os
import sys
import time

import yaml

from ..bagio import DEFAULT_TOPICS, IMAGE_TRANSPORTS
from ..config import ConfigError
from ..nodes import node_configs, node_defaults


def _onoff(text: str) -> bool:
    t = text.lower()
    if t in ("on", "true", "1", "yes"):
        return True
    if t in ("off", "false", "0", "no"):
        return False
    raise argparse.ArgumentTypeError("expected on or off, got %r" % text)


def _seconds(text: str) -> float:
    """A window length: seconds > 0."""
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError("expected seconds > 0, got %r" % text)
    return v


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("bag", nargs="?", help="input bag (stereo images + camera_info)")
    src.add_argument("--euroc", metavar="DIR", help="EuRoC/ASL folder (mav0/cam0, mav0/cam1)")
    src.add_argument("--kitti", metavar="DIR", help="KITTI odometry folder (image_0/1, calib.txt)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--pose-source", choices=("orb", "groundtruth"), default="orb",
                   help="orb (default): track with mdr_slam.pose, as on a robot; groundtruth: the "
                        "bag's ground-truth poses (--ground-truth-pose) or the dataset's")
    p.add_argument("--temporal", type=_onoff, default=True, metavar="on|off",
                   help="keyframe Kalman temporal filter (off: ELAS-only baseline)")
    p.add_argument("--confidence", type=_onoff, default=True, metavar="on|off",
                   help="confidence-based fusion (off: plain voxel-grid accumulation)")
    p.add_argument("--calib", help="calibration file for inputs without camera_info")
    add_bag_input_arguments(p)
    p.add_argument("--preset", choices=("sample", "euroc", "kitti"), default=None,
                   help="dataset preset of config/<preset>/*.yaml (default: from the input)")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--start", type=float, default=0.0, metavar="S",
                   help="skip the first S seconds of the input (as rosbag play --start)")
    p.add_argument("--map", metavar="FOLDER", default="",
                   help="start from a saved map folder (e.g. an earlier run's DIR/map): the "
                        "tracker relocalizes in it and the poses are in its map frame")
    p.add_argument("--localization", action="store_true",
                   help="with --map: track against the saved map only (no new keyframes)")
    p.add_argument("--blas-threads", type=int, default=1,
                   help="BLAS threads (0: the library's default). One, as in pose_node: OpenBLAS's "
                        "second thread mostly spins on the small BA/PnP products (300 sample "
                        "frames: 41.5 s of CPU with one thread, 49.6 s with two, same result)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.KEY=VALUE",
                   help="override a parameter, e.g. depth.tau=0.02 (repeatable)")
    p.add_argument("--window", type=_seconds, default=None, metavar="S",
                   help="also write DIR/timeline.json and timeline.png: per S seconds of bag "
                        "time the process's RSS, tracking ms median / p90, frames tracked, "
                        "keyframes alive, sparse and dense map points, loop closures (a long-run "
                        "report, e.g. --window 60)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.set_defaults(func=run)
    return p


def add_bag_input_arguments(p) -> None:
    """The bag's topics and how to read them, named as mdr.launch's arguments (also used by
    ``mdr bench`` and ``mdr demo``, which pass them on)."""
    g = p.add_argument_group("bag input (as mdr.launch's arguments)")
    for name, key in (("left-image", "left_image"), ("right-image", "right_image"),
                      ("left-info", "left_info"), ("right-info", "right_info")):
        g.add_argument("--" + name, default=DEFAULT_TOPICS[key], metavar="TOPIC",
                       help="default %s" % DEFAULT_TOPICS[key])
    g.add_argument("--ground-truth-pose", default=DEFAULT_TOPICS["ground_truth"], metavar="TOPIC",
                   help="geometry_msgs/PoseStamped ground truth, read with --pose-source "
                        "groundtruth (default %s)" % DEFAULT_TOPICS["ground_truth"])
    g.add_argument("--image-transport", choices=IMAGE_TRANSPORTS, default="raw",
                   help="raw: sensor_msgs/Image on the image topics; compressed: "
                        "sensor_msgs/CompressedImage (png, jpeg) on <image topic>/compressed")
    g.add_argument("--sync-tolerance", type=float, default=0.0, metavar="S",
                   help="largest left/right stamp difference of a stereo pair, s (default 0: "
                        "auto, 0.4 of the frame period)")
    g.add_argument("--rectified", choices=("auto", "true", "false"), default="auto",
                   help="whether the images are rectified already (auto: image_rect* topics, "
                        "which come with the raw camera_info, or a calibration without "
                        "distortion); rectified images are not rectified again")


def bag_topics(args) -> dict:
    """bagio's topics dict of the parsed bag input arguments."""
    return {"left_image": args.left_image, "right_image": args.right_image,
            "left_info": args.left_info, "right_info": args.right_info,
            "ground_truth": args.ground_truth_pose}


def bag_input_argv(args) -> list:
    """The bag input arguments again, for an ``mdr run`` started as a subprocess."""
    out = []
    for name in ("left_image", "right_image", "left_info", "right_info", "ground_truth_pose",
                 "image_transport", "sync_tolerance", "rectified"):
        out += ["--" + name.replace("_", "-"), str(getattr(args, name))]
    return out


def _overrides(items):
    out = {"pose": {}, "depth": {}, "fusion": {}}
    for it in items:
        key, sep, val = it.partition("=")
        node, dot, k = key.partition(".")
        if not sep or not dot or node not in out:
            raise SystemExit("--set wants NODE.KEY=VALUE with NODE in pose, depth, fusion: %r" % it)
        top, _, sub = k.partition(".")
        if top not in node_defaults(node):
            raise SystemExit("--set: the %s node has no parameter %r (see config/%s.yaml)"
                             % (node, k, node))
        v = yaml.safe_load(val)
        for c in node_configs(node):
            if top in c.keys():
                try:
                    c.from_dict({top: {sub: v} if sub else v})
                except ConfigError as e:
                    try:   # YAML reads a bare off/on/no/yes as a bool: a word field keeps it
                        if not isinstance(v, bool):
                            raise
                        c.from_dict({top: {sub: val} if sub else val})
                        v = val
                    except ConfigError:
                        raise SystemExit("--set %s: %s" % (it, e))
        out[node][k] = v
    return out


def run(args) -> int:
    # the pipeline (pose, depth, fusion) when the command runs: `mdr --help` imports this module
    from ..pipeline import Pipeline, PipelineConfig, frames_from_bag, frames_from_dataset
    if getattr(args, "blas_threads", 0) and args.blas_threads > 0:
        try:   # threadpoolctl is optional
            from threadpoolctl import threadpool_limits
            threadpool_limits(args.blas_threads, user_api="blas")
        except ImportError:
            pass
    ov = _overrides(args.set)
    skipped = {"n": 0, "examples": []}

    def on_skip(reason: str) -> None:        # a count and a few reasons, not one per message
        skipped["n"] += 1
        if len(skipped["examples"]) < 5:
            skipped["examples"].append(reason)
    # --max-frames counts the frames after --start
    max_frames = None if args.start > 0 else args.max_frames
    try:
        if args.bag:
            camera, frames = frames_from_bag(
                args.bag, topics=bag_topics(args), max_frames=max_frames, calib=args.calib,
                on_skip=on_skip, ground_truth=args.pose_source == "groundtruth",
                image_transport=args.image_transport, sync_tolerance=args.sync_tolerance,
                rectified=args.rectified)
            preset = args.preset
        else:
            kind = "euroc" if args.euroc else "kitti"
            camera, frames = frames_from_dataset(kind, args.euroc or args.kitti, max_frames)
            preset = args.preset or kind
        frames = iter(frames)
        first = next(frames, None)
    except Exception as e:  # missing file, not a bag (ROSBagException), no calibration...
        print("mdr run: cannot read the input: %s: %s" % (type(e).__name__, e), file=sys.stderr)
        return 1
    if args.start > 0 and first is not None:
        t_skip = first.stamp + args.start
        frames = itertools.dropwhile(lambda f: f.stamp < t_skip, itertools.chain([first], frames))
        if args.max_frames:
            frames = itertools.islice(frames, args.max_frames)
        first = next(frames, None)
    if first is None:
        print("mdr run: no frames in the input%s" % (" after --start" if args.start else ""),
              file=sys.stderr)
        return 1
    if args.localization and not args.map:
        print("mdr run: --localization needs --map FOLDER", file=sys.stderr)
        return 1
    if args.map and not os.path.isdir(args.map):
        print("mdr run: --map %s is not a folder" % args.map, file=sys.stderr)
        return 1
    if args.pose_source == "groundtruth" and first.T_map_cam_gt is None:
        print("mdr run: warning: no ground-truth pose at the first frame (%s); frames without "
              "one are not mapped" % (("topic %s" % args.ground_truth_pose) if args.bag
                                      else "the dataset's ground truth"), file=sys.stderr)
    cfg = PipelineConfig(pose_source=args.pose_source, temporal=args.temporal,
                         confidence=args.confidence, preset=preset, pose_params=ov["pose"],
                         depth_params=ov["depth"], fusion_params=ov["fusion"],
                         map_folder=args.map, localization=args.localization)
    pipe = Pipeline(camera, cfg)
    if args.map and not pipe.map_loaded:
        print("mdr run: could not load the map %s: %s (starting empty)"
              % (args.map, pipe.map_load_error), file=sys.stderr)
    timeline = None
    if getattr(args, "window", None):
        from ..eval.timeline import RunTimeline, pipeline_gauges
        timeline = RunTimeline(args.window, lambda: pipeline_gauges(pipe))
    t0 = time.perf_counter()
    n = 0
    for f in itertools.chain([first], frames):
        if timeline is not None:
            timeline.before_frame(f.stamp)
        rec = pipe.process(f)
        if timeline is not None:
            timeline.frame(f.stamp, rec["state"], rec.get("tracking_ms"))
        n += 1
        if not args.quiet and (n % 20 == 0):
            el = time.perf_counter() - t0
            print("\rmdr run: %d frames, %.1f frames/s, map %d points" % (
                n, n / el, len(pipe.map)), end="", file=sys.stderr, flush=True)
    if not args.quiet:
        print("", file=sys.stderr)
    rows = timeline.rows() if timeline is not None else None   # before finish ends the tracker
    summary = pipe.finish(args.out, extra={
        "input": args.bag or args.euroc or args.kitti, "skipped_inputs": skipped["n"],
        "skipped_examples": skipped["examples"], "wall_s": round(time.perf_counter() - t0, 3)})
    if timeline is not None:
        from ..eval.timeline import write_timeline
        write_timeline(args.out, rows, args.window, extra={
            "input": args.bag or args.euroc or args.kitti, "pose_source": args.pose_source,
            "time": "bag seconds since the first frame"},
            title="mdr run %s" % os.path.basename(os.path.normpath(
                args.bag or args.euroc or args.kitti)))
    if skipped["n"] and not args.quiet:
        print("mdr run: %d input messages skipped, e.g. %s" % (
            skipped["n"], "; ".join(skipped["examples"][:3])), file=sys.stderr)
    print("mdr run: %d frames (%d posed, %d integrated), map %d points -> %s" % (
        summary["frames_in"], summary["frames_posed"], summary["frames_integrated"],
        summary["map_points"], args.out))
    return 0

