#!/usr/bin/env python3
"""Check a stereo calibration's disparity offset against ground truth (mdr_slam.pose.stereo_offset).

    python scripts/check_stereo_offset.py BAG | --kitti DIR | --euroc DIR
        [--preset kitti] [--doffs PX] [--max-frames N] [--shift PX]

Tracks the sequence with the built-in tracker (every frame, loop closing off), replaces the
keyframes' poses by the ground truth (moved into the tracker's first camera frame), triangulates
the map points seen by >= 3 keyframes from their left-image observations alone and fits
``measured disparity = a * f*B/Z + e``. A calibration whose right principal point is right gives
``e`` ~ 0; otherwise put ``doffs + e`` into it (the right camera's cx = left cx - (doffs + e)):
every node reads ``doffs`` from the right camera's P (and K for rectified images).
``--doffs`` tries a correction without editing the calibration; ``--shift`` moves the right
image by that many pixels first (a known offset, to see the check find it).
"""
from __future__ import annotations

import argparse
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "src", "mdr_slam", "src"))

import mdr_slam  # noqa: E402,F401
import numpy as np  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bag", nargs="?", help="stereo bag with /ground_truth/pose")
    ap.add_argument("--kitti", help="KITTI odometry folder (poses.txt)")
    ap.add_argument("--euroc", help="EuRoC folder")
    ap.add_argument("--preset", default=None, help="parameter preset (kitti, euroc, sample)")
    ap.add_argument("--doffs", type=float, default=None,
                    help="principal point difference to use instead of the calibration's (px)")
    ap.add_argument("--shift", type=float, default=0.0,
                    help="move the right image right by this many px first (offset -shift)")
    ap.add_argument("--max-frames", type=int, default=None)
    a = ap.parse_args(argv)
    from mdr_slam.pipeline import frames_from_bag, frames_from_dataset, load_params
    from mdr_slam.pose import System, TrackerConfig
    from mdr_slam.pose.stereo_offset import estimate_disparity_offset
    if a.kitti or a.euroc:
        cam, frames = frames_from_dataset("kitti" if a.kitti else "euroc", a.kitti or a.euroc,
                                          max_frames=a.max_frames)
    elif a.bag:
        cam, frames = frames_from_bag(a.bag, max_frames=a.max_frames, ground_truth=True)
    else:
        ap.error("give a bag, --kitti or --euroc")
    if a.doffs is not None:
        cam = cam.with_doffs(a.doffs)
    params = TrackerConfig.pick(load_params("pose", a.preset)).replace(loop_closing=False, backend="mdr")
    system = System(cam, params, threads=False)
    gt = {}
    n = 0
    import cv2
    for f in frames:
        left, right = cam.rectify(f.left, f.right)
        if a.shift:
            h, w = right.shape[:2]
            right = cv2.warpAffine(right, np.float32([[1, 0, a.shift], [0, 1, 0]]), (w, h),
                                   flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        system.track(f.stamp, left, right)
        if f.T_map_cam_gt is not None:
            gt[round(f.stamp, 6)] = f.T_map_cam_gt
        n += 1
    system.shutdown()
    kfs = system.map.good_keyframes()
    first = min(kfs, key=lambda k: k.id, default=None)
    if first is None or round(first.stamp, 6) not in gt:
        print("no ground truth at the first keyframe: nothing to check against", file=sys.stderr)
        return 1
    G0 = gt[round(first.stamp, 6)]
    poses = {k.id: np.linalg.inv(gt[round(k.stamp, 6)]) @ G0 for k in kfs
             if round(k.stamp, 6) in gt}
    print("%d frames, %d keyframes (%d with ground truth), doffs in use %+.3f px"
          % (n, len(kfs), len(poses), cam.doffs))
    for name, ref in (("ground truth", poses), ("tracker's own (biased)", None)):
        fit = estimate_disparity_offset(system.map, ref)
        if fit is None:
            print("%-24s too few multi-view points" % name)
            continue
        print("%-24s offset %+.3f +- %.3f px with scale %.4f (%+.3f +- %.3f px at scale 1), %d "
              "points, %d stereo observations, residual MAD %.3f px"
              % (name, fit.offset, fit.offset_sigma, fit.scale, fit.offset_unit_scale,
                 fit.offset_unit_scale_sigma, fit.n_points, fit.n_obs, fit.residual_mad))
        if ref is not None:
            print("  -> doffs %+.3f px: right cx = %.4f (left cx %.4f)"
                  % (cam.doffs + fit.offset, cam.cx - (cam.doffs + fit.offset), cam.cx))
    return 0


if __name__ == "__main__":
    sys.exit(main())
