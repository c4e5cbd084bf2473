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
from typing import Callable, Dict, Iterator, List, Optional

import numpy as np
import yaml
from scipy.spatial import cKDTree

from . import bagio
from .calib import load_stereo_calibration
from .camera import CalibrationError, StereoCamera, images_are_rectified
from .config import split_known
from .depth import DepthConfig, StereoDepth
from .fusion import VoxelMap, VoxelMapConfig
from .fusion.map_io import load_dense_map, save_dense_map
from .geometry import base_to_camera, is_valid_T
from .io import Trajectory, atomic_write, datasets, write_tum
from .io.map_dir import DENSE_MAP_FILE, map_files
from .nodes import node_configs
from .pose import TrackerConfig, make_system
from .pose.map_io import PoseMapError, load_pose_map, save_pose_map

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


LOADED_DISTANCE_SAMPLES = 2000   # points per cloud measured against a loaded map ...
LOADED_SURFACE_RADIUS = 0.25     # ... those with a loaded point this close (m) saw a saved surface


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
    map_folder: str = ""                  # a saved map folder to start from (mdr_slam.io.map_dir)
    localization: bool = False            # with map_folder: track against it only, no new keyframes


class Pipeline:
    """Pose -> depth -> fusion for one frame at a time (see the module docstring)."""

    def __init__(self, camera: StereoCamera, config: Optional[PipelineConfig] = None):
        self.camera = camera
        self.config = cfg = config or PipelineConfig()
        if cfg.pose_source not in ("orb", "groundtruth"):
            raise ValueError("pose source must be 'orb' or 'groundtruth', got %r" % cfg.pose_source)
        # the YAML files hold the nodes' own parameters too: only the core classes' are used here
        _, dp = split_known(load_params("depth", cfg.preset), *node_configs("depth"))
        dov = {}
        for k, v in cfg.depth_params.items():   # "elas.disp_max" (mdr run --set): a nested field
            head, _, sub = k.partition(".")
            if sub:
                dov[head] = dict(dov.get(head) or {}, **{sub: v})
            else:
                dov[k] = v
        _, dov = split_known(dov, *node_configs("depth"))
        dov["temporal"] = bool(cfg.temporal)
        self.depth = StereoDepth(camera, DepthConfig.from_dict(dp).replace(**dov))
        _, fp = split_known(load_params("fusion", cfg.preset), *node_configs("fusion"))
        _, fov = split_known(cfg.fusion_params, *node_configs("fusion"))
        fp.update(fov)
        fp["confidence"] = bool(cfg.confidence)
        self.map = VoxelMap(VoxelMapConfig.from_dict(fp))
        self.tracker = None
        if cfg.pose_source == "orb":
            pp = load_params("pose", cfg.preset)
            pp.update(cfg.pose_params)
            # pose.yaml also holds the pose node's parameters; the node's config checks those
            tracker = TrackerConfig.pick(pp)
            # map is base_link where tracking starts, as the pose node publishes (REP-105)
            self.tracker = make_system(camera, tracker, threads=False,
                                       T_map_cam0=base_to_camera(pp.get("base_to_camera", "")))
        self.map_loaded = False
        self.map_load_error = ""
        self.relocalized_at = None            # stamp of the first frame relocalized in the loaded map
        self._loaded_tree = None              # the loaded dense map's points (distances of new clouds)
        self.loaded_distances: List[np.ndarray] = []   # new points' distances to the loaded map
        self.loaded_seen = [0, 0]             # new points near a loaded surface, all new points
        if cfg.map_folder:
            self._load_map_folder(cfg.map_folder, cfg.localization)
        self.timer = StageTimer()
        self.counts = OrderedDict([("frames_in", 0), ("frames_posed", 0), ("frames_integrated", 0),
                                   ("frames_lost", 0), ("points_published", 0),
                                   ("local_ba_corrections", 0), ("loop_closures", 0)])
        self._anchor = (None, None)           # (reference keyframe id, T_map_kf) of this frame
        self._late_ref = -1                   # newest keyframe of a backend without references
        self.poses: List[tuple] = []          # (stamp, T_map_cam) of every posed frame
        self.states: List[tuple] = []         # (stamp, state)

    def _load_map_folder(self, folder: str, localization: bool) -> None:
        """Both maps of a saved folder; a bad one is reported and the run starts empty."""
        try:
            load_dense_map(self.map, folder)
            if self.tracker is not None:
                load_pose_map(self.tracker, map_files(folder)["pose"])
                self.tracker.localization = bool(localization)
        except (ValueError, PoseMapError, IOError, OSError) as e:
            self.map_load_error = str(e)
            self.map.reset()
            if self.tracker is not None and getattr(self.tracker, "map_loaded", False):
                self.tracker.reset()
            return
        self.map_loaded = True
        c = self.map.to_cloud()
        if len(c["x"]):
            self._loaded_tree = cKDTree(np.stack([c["x"], c["y"], c["z"]], 1))

    # ------------------------------------------------------------------ one frame
    def process(self, frame: InputFrame) -> dict:
        """Run the three stages on one frame; returns what happened to it."""
        t_frame = time.perf_counter()
        self.counts["frames_in"] += 1
        left, right = self.timer.time("rectify", self.camera.rectify, frame.left, frame.right)
        T, state, kf = self._pose(frame, left, right)
        self.states.append((frame.stamp, state))
        rec = {"index": frame.index, "stamp": frame.stamp, "state": state, "points": 0,
               "tracking_ms": self._tracking_ms}
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
        if n and self._loaded_tree is not None:
            P = out.points[:: max(1, n // LOADED_DISTANCE_SAMPLES)]
            d, _ = self._loaded_tree.query(P @ T[:3, :3].T + T[:3, 3],
                                           distance_upper_bound=LOADED_SURFACE_RADIUS)
            near = d[np.isfinite(d)]
            self.loaded_distances.append(near)
            self.loaded_seen[0] += len(near)
            self.loaded_seen[1] += len(d)
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
        self._tracking_ms = None              # the tracker's own time, as the pose node reports
        if self.tracker is None:
            T = frame.T_map_cam_gt
            if T is None or not is_valid_T(T):
                return None, "NO_GROUND_TRUTH", None
            return T, "OK", None
        res = self.timer.time("pose", self.tracker.track, frame.stamp, left, right)
        self._tracking_ms = float(res.time_ms)
        if res.state == "RELOCALIZED" and self.map_loaded and self.relocalized_at is None:
            self.relocalized_at = float(frame.stamp)
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
        if self.tracker is not None:
            return self.tracker.trajectory()
        if not self.poses:
            return Trajectory(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)))
        return Trajectory.from_matrices([s for s, _ in self.poses], [T for _, T in self.poses])

    def finish(self, out_dir: str, extra: Optional[dict] = None) -> dict:
        """Write the map folder ``map/`` (dense and sparse map), ``map.ply`` (a link to the dense
        map), ``trajectory.tum`` and ``summary.json`` into ``out_dir``."""
        os.makedirs(out_dir, exist_ok=True)
        folder = os.path.join(out_dir, "map")
        if self.tracker is not None:
            self.tracker.shutdown()
            if self.tracker.map.keyframes and hasattr(self.tracker, "n_keyframes_created"):
                os.makedirs(folder, exist_ok=True)
                save_pose_map(self.tracker, map_files(folder)["pose"])
        n_map = save_dense_map(self.map, folder)
        _link(os.path.join("map", DENSE_MAP_FILE), os.path.join(out_dir, "map.ply"))
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
        summary["map_folder"] = folder
        summary["map_loaded"] = self.map_loaded
        if self.config.map_folder:
            summary["map_loaded_from"] = self.config.map_folder
            summary["map_load_error"] = self.map_load_error
            summary["localization"] = bool(self.config.localization)
        summary["keyframes_created"] = int(getattr(self.tracker, "n_keyframes_created", 0))
        summary["relocalized_at"] = self.relocalized_at
        if self.loaded_seen[1]:   # new clouds against the loaded dense map
            d = np.concatenate(self.loaded_distances)
            summary["clouds_to_loaded_map_median_m"] = float(np.median(d)) if len(d) else None
            summary["clouds_on_loaded_surfaces"] = self.loaded_seen[0] / float(self.loaded_seen[1])
        summary["timing"] = self.timer.summary()
        if extra:
            summary.update(extra)
        atomic_write(os.path.join(out_dir, "summary.json"), json.dumps(summary, indent=2) + "\n",
                     mode="w")
        return summary


def _link(target: str, path: str) -> None:
    """``path`` -> ``target`` (relative) as a symbolic link, replacing an older file."""
    tmp = path + ".tmp-link"
    if os.path.lexists(tmp):
        os.unlink(tmp)
    os.symlink(target, tmp)
    os.replace(tmp, path)


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
    topics = dict(bagio.DEFAULT_TOPICS, **(topics or {}))
    if not isinstance(rectified, bool) and \
            str(rectified).strip().lower() not in ("auto", "true", "false"):   # before reading
        raise ValueError("rectified must be 'auto', 'true' or 'false', not %r" % (rectified,))
    camera = None
    if calib:
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
    seq = datasets.load_euroc(path) if kind == "euroc" else datasets.load_kitti(path)
    gt = dict(seq.ground_truth_at())

    def gen() -> Iterator[InputFrame]:
        for i, (stamp, left, right) in enumerate(seq):
            if max_frames is not None and i >= max_frames:
                return
            yield InputFrame(i, stamp, left, right, gt.get(float(stamp)))
    return seq.camera, gen()
