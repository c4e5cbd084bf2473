"""``mdr run``: the whole pipeline offline on every frame of a bag (or an EuRoC/KITTI folder).

    mdr run BAG --out DIR [--pose-source groundtruth|orb] [--temporal on|off] [--confidence on|off]
    mdr run --euroc DIR --out DIR        mdr run --kitti DIR --out DIR

Writes ``DIR/map.ply`` (the fused global map), ``DIR/trajectory.tum`` (left camera optical frame in
``map``, one line per posed frame) and ``DIR/summary.json`` (frame counts, per-stage median and p90
milliseconds). The four runs of the paper's ablation (Table 2) differ only in --temporal and
--confidence.
"""
from __future__ import annotations

import argparse
import itertools
import sys
import time


def _onoff(text: str) -> bool:
    t = text.lower()
    if t in ("on", "true", "1", "yes"):
        return True
    if t in ("off", "false", "0", "no"):
        return False
    raise argparse.ArgumentTypeError("expected on or off, got %r" % text)


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("bag", nargs="?", help="input bag (stereo images + camera_info)")
    src.add_argument("--euroc", metavar="DIR", help="EuRoC/ASL folder (mav0/cam0, mav0/cam1)")
    src.add_argument("--kitti", metavar="DIR", help="KITTI odometry folder (image_0/1, calib.txt)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--pose-source", choices=("orb", "groundtruth"), default=None,
                   help="orb: track with mdr_slam.pose; groundtruth: the bag's /ground_truth/pose "
                        "(default: groundtruth when the input has ground truth, else orb)")
    p.add_argument("--temporal", type=_onoff, default=True, metavar="on|off",
                   help="keyframe Kalman temporal filter (off: ELAS-only baseline)")
    p.add_argument("--confidence", type=_onoff, default=True, metavar="on|off",
                   help="confidence-based fusion (off: plain voxel-grid accumulation)")
    p.add_argument("--calib", help="calibration file for inputs without camera_info")
    p.add_argument("--preset", choices=("sample", "euroc", "kitti"), default=None,
                   help="dataset preset of config/<preset>/*.yaml (default: from the input)")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--blas-threads", type=int, default=1,
                   help="BLAS threads (0: the library's default). One, as in pose_node: OpenBLAS's "
                        "second thread mostly spins on the small BA/PnP products (300 sample "
                        "frames: 41.5 s of CPU with one thread, 49.6 s with two, same result)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.KEY=VALUE",
                   help="override a parameter, e.g. depth.tau=0.02 (repeatable)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.set_defaults(func=run)
    return p


def _overrides(items):
    import yaml
    out = {"pose": {}, "depth": {}, "fusion": {}}
    for it in items:
        key, sep, val = it.partition("=")
        node, dot, k = key.partition(".")
        if not sep or not dot or node not in out:
            raise SystemExit("--set wants NODE.KEY=VALUE with NODE in pose, depth, fusion: %r" % it)
        out[node][k] = yaml.safe_load(val)
    return out


def run(args) -> int:
    from ..pipeline import Pipeline, PipelineConfig, frames_from_bag, frames_from_dataset
    if getattr(args, "blas_threads", 0) and args.blas_threads > 0:
        try:
            from threadpoolctl import threadpool_limits
            threadpool_limits(args.blas_threads, user_api="blas")
        except ImportError:
            pass
    ov = _overrides(args.set)
    skipped = []
    try:
        if args.bag:
            camera, frames = frames_from_bag(args.bag, max_frames=args.max_frames,
                                             calib=args.calib, on_skip=skipped.append)
            preset = args.preset
        else:
            kind = "euroc" if args.euroc else "kitti"
            camera, frames = frames_from_dataset(kind, args.euroc or args.kitti, args.max_frames)
            preset = args.preset or kind
        frames = iter(frames)
        first = next(frames, None)
    except Exception as e:  # missing file, not a bag (ROSBagException), no calibration...
        print("mdr run: cannot read the input: %s: %s" % (type(e).__name__, e), file=sys.stderr)
        return 1
    if first is None:
        print("mdr run: no frames in the input", file=sys.stderr)
        return 1
    pose_source = args.pose_source or ("groundtruth" if first.T_map_cam_gt is not None else "orb")
    cfg = PipelineConfig(pose_source=pose_source, temporal=args.temporal,
                         confidence=args.confidence, preset=preset, pose_params=ov["pose"],
                         depth_params=ov["depth"], fusion_params=ov["fusion"])
    pipe = Pipeline(camera, cfg)
    t0 = time.perf_counter()
    n = 0
    for f in itertools.chain([first], frames):
        pipe.process(f)
        n += 1
        if not args.quiet and (n % 20 == 0):
            el = time.perf_counter() - t0
            print("\rmdr run: %d frames, %.1f frames/s, map %d points" % (
                n, n / el, len(pipe.map)), end="", file=sys.stderr, flush=True)
    if not args.quiet:
        print("", file=sys.stderr)
    summary = pipe.finish(args.out, extra={
        "input": args.bag or args.euroc or args.kitti, "skipped_inputs": len(skipped),
        "wall_s": round(time.perf_counter() - t0, 3)})
    print("mdr run: %d frames (%d posed, %d integrated), map %d points -> %s" % (
        summary["frames_in"], summary["frames_posed"], summary["frames_integrated"],
        summary["map_points"], args.out))
    return 0

