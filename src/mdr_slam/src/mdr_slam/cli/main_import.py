"""``mdr import euroc|kitti DIR OUT.bag``: a dataset folder -> a bag the nodes and ``mdr run`` read.

The bag carries the images as stored (EuRoC: RAW, distorted; KITTI: already rectified), the
camera_info pair with D, K, R, P (EuRoC: the cv2.stereoRectify result, so the depth node
rectifies exactly as the calibration says) and, when there is ground truth, the left-camera pose
``T_map_cam`` on ``/ground_truth/pose`` (+ tf) at every image stamp it covers.
"""
from __future__ import annotations

import sys

from ..bagio import StereoBagWriter
from ..camera import CalibrationError
from ..io.datasets import DatasetError, load_euroc, load_kitti


def add_parser(subparsers, name, help_text):
    p = subparsers.add_parser(name, help=help_text, description=help_text)
    sub = p.add_subparsers(dest="dataset", metavar="DATASET")
    e = sub.add_parser("euroc", help="EuRoC / ASL folder (mav0/cam0, mav0/cam1, sensor.yaml)")
    e.add_argument("dir", help="sequence folder (containing mav0/) or the mav0 folder")
    e.add_argument("out", help="output bag")
    e.add_argument("--ground-truth", "--gt", dest="gt", default=None,
                   help="left-camera ground truth CSV (t[ns],x,y,z,qw,qx,qy,qz), e.g. "
                        "V101_GT_left_cam_ORB_SLAM3_clip.txt; default: the body pose of "
                        "state_groundtruth_estimate0/data.csv moved to cam0 with T_BS")
    k = sub.add_parser("kitti", help="KITTI odometry folder (image_0/1 or image_l/r, calib.txt)")
    k.add_argument("dir", help="sequence folder")
    k.add_argument("out", help="output bag")
    k.add_argument("--poses", default=None, help="ground-truth poses file (default DIR/poses.txt)")
    k.add_argument("--rate", type=float, default=10.0, help="frame rate when there is no times.txt")
    k.add_argument("--time-offset", type=float, default=1.0,
                   help="seconds added to times.txt (KITTI starts at 0, which ROS reads as "
                        "'no time'; default 1.0)")
    k.add_argument("--doffs", type=float, default=None,
                   help="principal point difference cx_left - cx_right (px) written into the "
                        "right camera_info instead of calib.txt's (0). On sequence 06 the "
                        "disparities measure -0.16 to -0.21 px against the ground truth "
                        "(scripts/check_stereo_offset.py); -0.2 takes the built-in tracker's "
                        "ATE on frames 0-50 from 0.21 to 0.06 m")
    for q in (e, k):
        q.add_argument("--max-frames", type=int, default=None, help="stop after N stereo pairs")
        q.add_argument("--no-ground-truth", action="store_true", help="do not write ground truth")
        q.add_argument("--compression", choices=["none", "bz2", "lz4"], default="none")
        q.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=run, _parser=p)
    return p


def import_dataset(dataset, out: str, max_frames=None, time_offset: float = 0.0,
                   ground_truth: bool = True, compression: str = "none", log=None) -> dict:
    """Write a :class:`~mdr_slam.io.datasets.StereoDataset` to ``out``; returns counts."""
    log = log or (lambda msg: None)
    gt = dict(dataset.ground_truth_at()) if ground_truth else {}
    n = n_gt = 0
    with StereoBagWriter(out, compression=compression) as w:
        for stamp, left, right in dataset:
            if max_frames is not None and n >= max_frames:
                break
            t = stamp + time_offset
            w.write_stereo(t, left, right, dataset.camera)
            T = gt.get(stamp)
            if T is not None:
                w.write_ground_truth(t, T)
                n_gt += 1
            n += 1
    log("%s: %d stereo pairs, %d ground-truth poses -> %s" % (dataset.name, n, n_gt, out))
    return {"frames": n, "ground_truth": n_gt, "skipped": list(dataset.skipped)}


def run(args):
    if not getattr(args, "dataset", None):
        args._parser.print_help()
        return 2
    log = (lambda msg: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr))
    try:
        if args.dataset == "euroc":
            ds = load_euroc(args.dir, ground_truth=args.gt, on_skip=log)
            offset = 0.0
        else:
            ds = load_kitti(args.dir, poses=args.poses, rate_hz=args.rate, on_skip=log,
                            doffs=args.doffs)
            offset = args.time_offset
    except (DatasetError, CalibrationError, OSError) as e:
        print("mdr import: %s" % e, file=sys.stderr)
        return 1
    if ds.ground_truth is None and not args.no_ground_truth:
        log("%s: no ground truth found; the bag has images and camera_info only" % ds.name)
    import_dataset(ds, args.out, args.max_frames, offset, not args.no_ground_truth,
                   args.compression, log)
    return 0
