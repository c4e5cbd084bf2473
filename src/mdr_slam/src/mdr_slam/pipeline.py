"""The offline pipeline behind ``mdr run``: the three nodes' core stages, in one process, on every
frame of a sequence, in order (no drops, deterministic), so accuracy is measured without transport.

It calls exactly the core classes the nodes call (``mdr_slam.pose.System``,
``mdr_slam.depth.StereoDepth``, ``mdr_slam.fusion.VoxelMap``) with the nodes' parameter files
(``config/*.yaml``), so an offline figure describes what the live system computes:

    frame -> rectify -> pose (ORB tracking, or the bag's ground truth)
          -> depth (ELAS + keyframe Kalman filter, or ELAS only)     [node 2]
          -> fusion (confidence-based voxel map, or a plain voxel grid) [node 3]

Frames come from a bag (:func:`frames_from_bag`: the nodes' topics, approximate-time stereo
pairing and camera_info handling, raw or compressed images) or an EuRoC/KITTI folder
(:func:`frames_from_dataset`). A frame whose pose is unknown (tracking LOST, no ground truth at
that stamp) is not integrated: a smeared map is worse than a gap.
"""
from __future__ import annotations

import itertools
import json
import os
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Callable, Dict, Iterable, Iterator, List, Optional

import numpy as np

from .camera import CalibrationError, StereoCamera
from .geometry import is_valid_T

__all__ = ["PipelineConfig", "Pipeline", "StageTimer", "config_dir", "load_params",
           "frames_from_bag", "frames_from_dataset", "InputFrame"]


def config_dir() -> str:
    """The package's ``config/`` folder (source or devel space; install space through rospkg)."""
    here = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "config")
    if os.path.isdir(here):
        return os.path.normpath(here)
    import rospkg  # install space: the share folder
    return os.path.join(rospkg.RosPack().get_path("mdr_slam"), "config")


def load_params(name: str, preset: Optional[str] = None) -> dict:
    """A node's parameter file ``config/<name>.yaml``, overlaid with ``config/<preset>/<name>.yaml``
    when a dataset preset (sample, euroc, kitti) has one: the same files the launch file loads."""
    import yaml
    out: dict = {}
    paths = [os.path.join(config_dir(), name + ".yaml")]
    if preset:
        paths.append(os.path.join(config_dir(), preset, name + ".yaml"))
    for p in paths:
        if os.path.exists(p):
            with open(p) as f:
                out.update(yaml.safe_load(f) or {})
    return out


class StageTimer:
    """Wall time per stage and frame; summarized as median and p90 milliseconds."""

    def __init__(self):
        self.ms: "OrderedDict[str, List[float]]" = OrderedDict()

    def add(self, stage: str, ms: float) -> None:
        self.ms.setdefault(stage, []).append(float(ms))

    def time(self, stage: str, fn: Callable, *args, **kwargs):
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        self.add(stage, 1e3 * (time.perf_counter() - t0))
        return out

    def summary(self) -> Dict[str, Dict[str, float]]:
        out = OrderedDict()
        for k, v in self.ms.items():
            a = np.asarray(v)
            out[k] = {"median_ms": round(float(np.median(a)), 3),
                      "p90_ms": round(float(np.percentile(a, 90)), 3),
                      "mean_ms": round(float(a.mean()), 3), "n": int(len(a))}
        return out


@dataclass
class InputFrame:
    """One stereo pair as the pipeline takes it (raw or rectified, grey)."""

    index: int
    stamp: float
    left: np.ndarray
    right: np.ndarray
    T_map_cam_gt: Optional[np.ndarray] = None


@dataclass
class PipelineConfig:
    pose_source: str = "groundtruth"     # "orb" or "groundtruth"
    temporal: bool = True                 # False: ELAS-only baseline (every valid pixel)
    confidence: bool = True               # False: plain voxel-grid accumulation
    preset: Optional[str] = None          # config/<preset>/*.yaml overlays
    pose_params: dict = field(default_factory=dict)    # overrides of config/pose.yaml
    depth_params: dict = field(default_factory=dict)   # overrides of config/depth.yaml
    fusion_params: dict = field(default_factory=dict)  # overrides of config/fusion.yaml


class Pipeline:
    """Pose -> depth -> fusion for one frame at a time (see the module docstring)."""

    def __init__(self, camera: StereoCamera, config: Optional[PipelineConfig] = None):
        from .depth import StereoDepth
        from .fusion import VoxelMap
        self.camera = camera
        self.config = cfg = config or PipelineConfig()
        if cfg.pose_source not in ("orb", "groundtruth"):
            raise ValueError("pose source must be 'orb' or 'groundtruth', got %r" % cfg.pose_source)
        dp = load_params("depth", cfg.preset)
        dp.update(cfg.depth_params)
        dp["temporal"] = bool(cfg.temporal)
        fp = load_params("fusion", cfg.preset)
        fp.update(cfg.fusion_params)
        fp["confidence"] = bool(cfg.confidence)
        self.depth = StereoDepth(camera, dp)
        self.map = VoxelMap(fp)
        self.tracker = None
        if cfg.pose_source == "orb":
            from .pose import make_system
            pp = load_params("pose", cfg.preset)
            pp.update(cfg.pose_params)
            # map is base_link where tracking starts, as the pose node publishes (REP-105)
            from .geometry import parse_transform
            self.tracker = make_system(camera, pp, threads=False,
                                       T_map_cam0=parse_transform(pp.get("base_to_camera", "")))
        self.timer = StageTimer()
        self.counts = OrderedDict([("frames_in", 0), ("frames_posed", 0), ("frames_integrated", 0),
                                   ("frames_lost", 0), ("points_published", 0),
                                   ("local_ba_corrections", 0), ("loop_closures", 0)])
        self._anchor = (None, None)           # (reference keyframe id, T_map_kf) of this frame
        self._late_ref = -1                   # newest keyframe of a backend without references
        self.poses: List[tuple] = []          # (stamp, T_map_cam) of every posed frame
        self.states: List[tuple] = []         # (stamp, state)

    # ------------------------------------------------------------------ one frame
    def process(self, frame: InputFrame) -> dict:
        """Run the three stages on one frame; returns what happened to it."""
        t_frame = time.perf_counter()
        self.counts["frames_in"] += 1
        left, right = self.timer.time("rectify", self.camera.rectify, frame.left, frame.right)
        T, state, kf = self._pose(frame, left, right)
        self.states.append((frame.stamp, state))
        rec = {"index": frame.index, "stamp": frame.stamp, "state": state, "points": 0}
        if T is None:
            self.counts["frames_lost"] += 1
            self.timer.add("frame", 1e3 * (time.perf_counter() - t_frame))
            return rec
        self.counts["frames_posed"] += 1
        self.poses.append((frame.stamp, T))
        out = self.timer.time("depth", self.depth.process, frame.stamp, left, right, T,
                              rectified=True, new_keyframe=kf)
        for stage, ms in getattr(out, "timings", {}).items():
            self.timer.add("depth." + stage, ms)
        n = len(out.points)
        rec["points"] = n
        if n:
            self.counts["points_published"] += n
            # Points are anchored to the pose node's reference keyframe, so a later loop closure or
            # bundle adjustment that moves the keyframe moves them too (no depth re-run).
            kf_id, T_map_kf = self._anchor
            self.timer.time("fusion", self.map.integrate, out.points, T, frame.stamp,
                            intensity=out.intensity, anchor_id=kf_id, T_map_anchor=T_map_kf)
            self.counts["frames_integrated"] += 1
        self.timer.add("frame", 1e3 * (time.perf_counter() - t_frame))
        return rec

    def _pose(self, frame: InputFrame, left, right):
        """(T_map_cam or None, state, keyframe flag or None)."""
        if self.tracker is None:
            T = frame.T_map_cam_gt
            if T is None or not is_valid_T(T):
                return None, "NO_GROUND_TRUTH", None
            return T, "OK", None
        res = self.timer.time("pose", self.tracker.track, frame.stamp, left, right)
        if res.corrections:
            reason, _, kfs = res.corrections
            key = "loop_closures" if reason == "loop_closure" else "local_ba_corrections"
            self.counts[key] += 1
            self.timer.time("fusion.corrections", self.map.apply_corrections,
                            {k: v[1] for k, v in kfs.items()})
        T = res.T_map_cam if res.T_map_cam is not None and is_valid_T(res.T_map_cam) else None
        ref = res.keyframe_id if res.is_keyframe and res.keyframe_id >= 0 else res.ref_keyframe_id
        new = getattr(res, "new_keyframes", None)
        if ref < 0 and new:           # orbslam3: keyframes learnt a frame late, no reference
            self._late_ref = max(new)     # keyframe per frame: the newest one anchors the points
        if ref < 0:
            ref = self._late_ref
        if T is not None and ref is not None and ref >= 0:
            kf_poses = self.tracker.keyframe_poses()
            self._anchor = (int(ref), kf_poses[ref][1]) if ref in kf_poses else (None, None)
        else:
            self._anchor = (None, None)
        return T, res.state, bool(res.is_keyframe or new)

    # ------------------------------------------------------------------ outputs
    def trajectory(self):
        """Estimated trajectory: the tracker's (loop-corrected) one, or the ground truth used."""
        from .io import Trajectory
        if self.tracker is not None:
            return self.tracker.trajectory()
        if not self.poses:
            return Trajectory(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)))
        return Trajectory.from_matrices([s for s, _ in self.poses], [T for _, T in self.poses])

    def finish(self, out_dir: str, extra: Optional[dict] = None) -> dict:
        """Write ``map.ply``, ``trajectory.tum`` and ``summary.json`` into ``out_dir``."""
        from .io import atomic_write, write_tum
        os.makedirs(out_dir, exist_ok=True)
        if self.tracker is not None:
            self.tracker.shutdown()
        n_map = self.map.save(os.path.join(out_dir, "map.ply"))
        traj = self.trajectory()
        write_tum(os.path.join(out_dir, "trajectory.tum"), traj)
        summary = OrderedDict()
        summary["pose_source"] = self.config.pose_source
        summary["temporal"] = self.config.temporal
        summary["confidence"] = self.config.confidence
        summary["camera"] = {"width": self.camera.size[0], "height": self.camera.size[1],
                             "fx": self.camera.fx, "baseline": self.camera.baseline}
        summary.update(self.counts)
        summary["map_points"] = int(n_map if n_map is not None else len(self.map))
        summary["trajectory_poses"] = len(traj)
        summary["timing"] = self.timer.summary()
        if extra:
            summary.update(extra)
        atomic_write(os.path.join(out_dir, "summary.json"), json.dumps(summary, indent=2) + "\n",
                     mode="w")
        return summary


# ---------------------------------------------------------------------- frame sources
def frames_from_bag(path: str, topics: Optional[dict] = None, max_frames: Optional[int] = None,
                    calib: Optional[str] = None, on_skip=None, ground_truth: bool = False,
                    image_transport: str = "raw", sync_tolerance: float = 0.0,
                    rectified: str = "auto"):
    """(StereoCamera, iterator of InputFrame) for a bag, read as :func:`bagio.read_stereo_frames`
    reads it (``topics``, ``image_transport``, ``sync_tolerance``: as the nodes take them).

    The camera comes from the first pair's camera_info (wherever the bag has it), or from
    ``calib`` (any format mdr_slam.calib reads) when given. ``rectified`` ("auto", "true",
    "false"): whether the images are rectified already (:func:`camera.images_are_rectified`;
    auto: an ``image_rect*`` topic, as stereo_image_proc publishes with the raw camera_info, or
    a calibration that says so); then they are not rectified again. ``ground_truth``: attach the
    bag's ground-truth pose to each frame (``--pose-source groundtruth``); without it frames
    carry none.
    """
    from . import bagio
    from .camera import images_are_rectified
    topics = dict(bagio.DEFAULT_TOPICS, **(topics or {}))
    if not isinstance(rectified, bool) and \
            str(rectified).strip().lower() not in ("auto", "true", "false"):   # before reading
        raise ValueError("rectified must be 'auto', 'true' or 'false', not %r" % (rectified,))
    camera = None
    if calib:
        from .calib import load_stereo_calibration
        camera = load_stereo_calibration(calib)
    it = bagio.read_stereo_frames(path, topics=topics, max_frames=max_frames,
                                  with_ground_truth=ground_truth, on_skip=on_skip,
                                  image_transport=image_transport, sync_tolerance=sync_tolerance)
    first = next(it, None)
    if first is None:
        found = bagio.bag_image_topics(path)
        want = bagio.image_topics(topics, image_transport)
        raise ValueError("%s: no stereo pair on %s and %s (image topics in the bag: %s)" % (
            path, want["left"], want["right"],
            ", ".join("%s [%s]" % kv for kv in found.items()) or "none"))
    if camera is None:
        if first.left_info is None or first.right_info is None:
            raise CalibrationError("%s has no usable camera_info on %s and %s; give a calibration "
                                   "file (--calib)" % (path, topics["left_info"],
                                                       topics["right_info"]))
        camera = StereoCamera(first.left_info, first.right_info)
    if images_are_rectified(rectified, topics["left_image"], camera):
        camera = camera.assume_rectified()

    def gen() -> Iterator[InputFrame]:
        for f in itertools.chain([first], it):
            yield InputFrame(f.index, f.stamp, f.left, f.right, f.T_map_cam_gt)
    return camera, gen()


def frames_from_dataset(kind: str, path: str, max_frames: Optional[int] = None):
    """(StereoCamera, iterator of InputFrame) for an EuRoC (ASL) or KITTI odometry folder, with
    the folder's ground truth (interpolated to the image stamps) when it has one."""
    from .io import datasets
    seq = datasets.load_euroc(path) if kind == "euroc" else datasets.load_kitti(path)
    gt = dict(seq.ground_truth_at())

    def gen() -> Iterator[InputFrame]:
        for i, (stamp, left, right) in enumerate(seq):
            if max_frames is not None and i >= max_frames:
                return
            yield InputFrame(i, stamp, left, right, gt.get(float(stamp)))
    return seq.camera, gen()
