"""A peer map to score beside ours: OpenCV StereoSGBM depth fused in Open3D's scalable TSDF.

The usual robotics baseline of a dense stereo map: semi-global matching on every rectified pair
(``numDisparities`` 128, ``blockSize`` 5, ``P1``/``P2`` = 8/32 * blockSize^2, ``uniquenessRatio``
10, speckle filtering, ``SGBM_3WAY``), depth ``Z = f*B / (d - doffs)`` kept within the depth
node's ``min_depth``/``max_depth`` (config/depth.yaml), integrated with the frame's pose into
``o3d.pipelines.integration.ScalableTSDFVolume`` (2 cm voxels, 8 cm truncation, no colour: the
grey image is fed as colour); the map is the volume's ``extract_point_cloud``. It reads the frames
and poses exactly as ``mdr run --pose-source groundtruth`` does (:func:`mdr_slam.pipeline.
frames_from_bag` with ``ground_truth=True``, the camera's rectification), so both see the same
frames.

    python -m mdr_slam.eval.peer BAG --out DIR [--max-frames N]

writes ``DIR/map.ply`` and ``DIR/summary.json`` (frames, points, per-frame wall time as ``mdr run``
reports it: ``timing.frame`` median/p90 ms, and its stages ``sgbm`` and ``tsdf``).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import OrderedDict
from typing import Optional

import cv2
import numpy as np

__all__ = ["sgbm_matcher", "sgbm_depth", "sgbm_tsdf_map", "main"]


def sgbm_matcher(num_disparities: int = 128, block_size: int = 5):
    """cv2.StereoSGBM with the parameters of the module docstring (grey images)."""
    if num_disparities <= 0 or num_disparities % 16:
        raise ValueError("num_disparities must be a positive multiple of 16, got %r"
                         % (num_disparities,))
    bs = int(block_size)
    return cv2.StereoSGBM_create(minDisparity=0, numDisparities=int(num_disparities),
                                 blockSize=bs, P1=8 * bs * bs, P2=32 * bs * bs, disp12MaxDiff=1,
                                 uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


def sgbm_depth(matcher, camera, left: np.ndarray, right: np.ndarray, min_depth: float,
               max_depth: float) -> np.ndarray:
    """float32 depth (m) of a rectified grey pair; 0 where SGBM found no match or the depth is
    outside ``[min_depth, max_depth]`` (Open3D's "no depth")."""
    disp = matcher.compute(left, right).astype(np.float32) / 16.0   # fixed point, 4 fraction bits
    Z = camera.disparity_to_depth(disp)                              # NaN where no match
    ok = np.isfinite(Z) & (Z >= min_depth) & (Z <= max_depth)
    return np.where(ok, Z, 0.0).astype(np.float32)


def _grey(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:   # 16-bit sensors: SGBM takes 8 bits
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return np.ascontiguousarray(img)


def sgbm_tsdf_map(bag: str, out_ply: Optional[str] = None, max_frames: Optional[int] = None,
                  num_disparities: int = 128, block_size: int = 5, voxel: float = 0.02,
                  sdf_trunc: float = 0.08, min_depth: Optional[float] = None,
                  max_depth: Optional[float] = None, **bag_options) -> dict:
    """Build the peer map of ``bag`` (see the module docstring) and write it to ``out_ply``.

    ``min_depth``/``max_depth`` default to config/depth.yaml's; ``bag_options`` go to
    :func:`mdr_slam.pipeline.frames_from_bag` (topics, image_transport, sync_tolerance,
    rectified, calib). Frames without a ground-truth pose are skipped, as ``mdr run`` skips them.
    Returns a summary dict (``xyz`` holds the (N, 3) points). Raises RuntimeError when the volume
    yields no points (Open3D builds whose legacy TSDF extracts nothing must not pass as an
    empty map).
    """
    import open3d as o3d
    from ..io import points_cloud, write_cloud
    from ..pipeline import StageTimer, frames_from_bag, load_params

    depth_cfg = load_params("depth")
    zmin = float(depth_cfg.get("min_depth", 0.2) if min_depth is None else min_depth)
    zmax = float(depth_cfg.get("max_depth", 8.0) if max_depth is None else max_depth)
    camera, frames = frames_from_bag(bag, max_frames=max_frames, ground_truth=True, **bag_options)
    W, H = camera.size
    intrinsic = o3d.camera.PinholeCameraIntrinsic(int(W), int(H), camera.fx, camera.fy,
                                                  camera.cx, camera.cy)
    volume = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=float(voxel), sdf_trunc=float(sdf_trunc),
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor)
    matcher = sgbm_matcher(num_disparities, block_size)
    timer = StageTimer()
    counts = OrderedDict([("frames_in", 0), ("frames_posed", 0), ("frames_integrated", 0)])
    t_run = time.perf_counter()
    for f in frames:
        t0 = time.perf_counter()
        counts["frames_in"] += 1
        T = f.T_map_cam_gt
        if T is None or not np.all(np.isfinite(T)):
            continue
        counts["frames_posed"] += 1
        left, right = timer.time("rectify", camera.rectify, _grey(f.left), _grey(f.right))
        Z = timer.time("sgbm", sgbm_depth, matcher, camera, left, right, zmin, zmax)
        t1 = time.perf_counter()
        if Z.any():
            rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
                o3d.geometry.Image(np.ascontiguousarray(left)), o3d.geometry.Image(Z),
                depth_scale=1.0, depth_trunc=zmax, convert_rgb_to_intensity=False)
            volume.integrate(rgbd, intrinsic, np.linalg.inv(T))   # extrinsic: map -> camera
            counts["frames_integrated"] += 1
        timer.add("tsdf", 1e3 * (time.perf_counter() - t1))
        timer.add("frame", 1e3 * (time.perf_counter() - t0))
    if counts["frames_in"] == 0:
        raise ValueError("%s: no frames" % bag)
    t1 = time.perf_counter()
    xyz = np.asarray(volume.extract_point_cloud().points, dtype=np.float64).reshape(-1, 3)
    extract_ms = 1e3 * (time.perf_counter() - t1)
    if len(xyz) == 0:
        raise RuntimeError("ScalableTSDFVolume.extract_point_cloud returned no points after %d "
                           "integrated frames (open3d %s)" % (counts["frames_integrated"],
                                                              o3d.__version__))
    summary = OrderedDict([("method", "sgbm_tsdf"), ("input", bag)])
    summary.update(counts)
    summary["map_points"] = int(len(xyz))
    summary["camera"] = {"width": int(W), "height": int(H), "fx": camera.fx,
                         "baseline": camera.baseline}
    summary["params"] = {"num_disparities": int(num_disparities), "block_size": int(block_size),
                         "voxel": float(voxel), "sdf_trunc": float(sdf_trunc),
                         "min_depth": zmin, "max_depth": zmax, "open3d": o3d.__version__,
                         "opencv": cv2.__version__}
    summary["timing"] = timer.summary()
    summary["extract_ms"] = round(extract_ms, 3)
    summary["wall_s"] = round(time.perf_counter() - t_run, 3)
    if out_ply:
        write_cloud(out_ply, points_cloud(xyz.astype(np.float32)))
    summary["xyz"] = xyz
    return summary


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m mdr_slam.eval.peer", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag")
    p.add_argument("--out", required=True, help="folder for map.ply and summary.json")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--num-disparities", type=int, default=128)
    p.add_argument("--block-size", type=int, default=5)
    p.add_argument("--voxel", type=float, default=0.02)
    p.add_argument("--sdf-trunc", type=float, default=0.08)
    from ..cli.main_run import add_bag_input_arguments, bag_topics
    add_bag_input_arguments(p)
    args = p.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    try:
        s = sgbm_tsdf_map(args.bag, os.path.join(args.out, "map.ply"), args.max_frames,
                          args.num_disparities, args.block_size, args.voxel, args.sdf_trunc,
                          topics=bag_topics(args), image_transport=args.image_transport,
                          sync_tolerance=args.sync_tolerance, rectified=args.rectified)
    except (ValueError, OSError, RuntimeError) as e:
        print("sgbm_tsdf: %s" % e, file=sys.stderr)
        return 1
    s.pop("xyz")
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(s, f, indent=2)
        f.write("\n")
    print("sgbm_tsdf: %d frames, map %d points -> %s" % (s["frames_in"], s["map_points"], args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
