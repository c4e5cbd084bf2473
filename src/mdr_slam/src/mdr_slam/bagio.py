"""Bags in and out: stereo sequences, camera_info, ground-truth poses, tf.

ROS side (uses rosbag and mdr_slam.conversions), like the nodes: the simulator and the importers
write bags through :class:`StereoBagWriter`; the offline runner (``mdr run``) reads them with
:func:`read_stereo_frames`, which pairs left/right images by exact stamp, as the depth node's
ExactTime synchronizer does, and attaches the latest camera_info and the ground-truth pose at
that stamp (interpolated) when the bag has one.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass
from typing import Dict, Iterator, List, Optional

import numpy as np

from . import conversions as cv
from .camera import CameraModel, StereoCamera
from .geometry import interpolate_pose, inv_T

DEFAULT_TOPICS = {
    "left_image": "/stereo/left/image_raw",
    "right_image": "/stereo/right/image_raw",
    "left_info": "/stereo/left/camera_info",
    "right_info": "/stereo/right/camera_info",
    "ground_truth": "/ground_truth/pose",
}
LEFT_FRAME = "camera_left_optical_frame"
RIGHT_FRAME = "camera_right_optical_frame"
GT_FRAME = "ground_truth_camera"   # tf child of `map` written by the simulator/importers


class StereoBagWriter:
    """Writes a stereo sequence on the default input topics (mono8 images + camera_info)."""

    def __init__(self, path: str, topics: Optional[Dict[str, str]] = None, compression: str = "none"):
        import rosbag
        self.topics = dict(DEFAULT_TOPICS, **(topics or {}))
        self.bag = rosbag.Bag(path, "w", compression=compression)
        self.seq = 0

    def write_stereo(self, stamp: float, left: np.ndarray, right: np.ndarray,
                     camera: Optional[StereoCamera] = None, encoding: Optional[str] = None) -> None:
        """One stereo pair (and, when given, the pair's camera_info) at ``stamp`` seconds."""
        import genpy
        t = genpy.Time.from_sec(stamp)
        for side, img, frame in (("left", left, LEFT_FRAME), ("right", right, RIGHT_FRAME)):
            if camera is not None:  # camera_info first, so a reader has it with the image
                model = camera.left if side == "left" else camera.right
                info = cv.model_to_camera_info(model, stamp=t, frame_id=frame)
                info.header.seq = self.seq
                self.bag.write(self.topics[side + "_info"], info, t)
            msg = cv.numpy_to_image(img, encoding, stamp=t, frame_id=frame)
            msg.header.seq = self.seq
            self.bag.write(self.topics[side + "_image"], msg, t)
        self.seq += 1

    def write_ground_truth(self, stamp: float, T_map_cam: np.ndarray, tf: bool = True) -> None:
        """Ground-truth pose of the left camera optical frame in ``map`` (PoseStamped + tf)."""
        import genpy
        from tf2_msgs.msg import TFMessage
        t = genpy.Time.from_sec(stamp)
        self.bag.write(self.topics["ground_truth"], cv.matrix_to_pose_stamped(T_map_cam, t, "map"), t)
        if tf:
            self.bag.write("/tf", TFMessage([cv.matrix_to_transform_stamped(
                T_map_cam, t, "map", GT_FRAME)]), t)

    def close(self) -> None:
        self.bag.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


@dataclass
class StereoFrame:
    """One synchronized stereo pair from a bag."""

    index: int
    stamp: float
    left: np.ndarray                 # as in the bag (raw or rectified), grey
    right: np.ndarray
    left_info: Optional[CameraModel]
    right_info: Optional[CameraModel]
    T_map_cam_gt: Optional[np.ndarray] = None   # ground truth at the stamp, when the bag has it


class PoseTimeline:
    """Stamped poses with interpolation (SLERP + linear) at arbitrary stamps."""

    def __init__(self, stamps, Ts):
        order = np.argsort(stamps)
        self.stamps = np.asarray(stamps, dtype=float)[order]
        self.Ts = np.asarray(Ts, dtype=float).reshape(-1, 4, 4)[order]

    def __len__(self):
        return len(self.stamps)

    def at(self, t: float, max_gap: float = 0.2) -> Optional[np.ndarray]:
        """Pose at ``t``; None outside the covered time or across a gap larger than ``max_gap``."""
        s = self.stamps
        if len(s) == 0 or t < s[0] - 1e-6 or t > s[-1] + 1e-6:
            return None
        i = bisect.bisect_left(s, t)
        if i < len(s) and abs(s[i] - t) < 1e-6:
            return self.Ts[i].copy()
        if i > 0 and abs(s[i - 1] - t) < 1e-6:
            return self.Ts[i - 1].copy()
        if i == 0 or i >= len(s) or s[i] - s[i - 1] > max_gap:
            return None
        a, b = self.Ts[i - 1], self.Ts[i]
        return interpolate_pose(a, b, (t - s[i - 1]) / (s[i] - s[i - 1]))


def read_ground_truth(bag_path: str, topic: str = DEFAULT_TOPICS["ground_truth"]) -> PoseTimeline:
    import rosbag
    stamps, Ts = [], []
    with rosbag.Bag(bag_path) as bag:
        for _, msg, _ in bag.read_messages(topics=[topic]):
            try:
                Ts.append(cv.pose_stamped_to_matrix(msg))
            except cv.ConversionError:
                continue
            stamps.append(cv.stamp_to_sec(msg.header.stamp))
    return PoseTimeline(stamps, Ts)


def read_stereo_frames(bag_path: str, topics: Optional[Dict[str, str]] = None,
                       max_frames: Optional[int] = None, with_ground_truth: bool = True,
                       on_skip=None) -> Iterator[StereoFrame]:
    """Stereo pairs of a bag in stamp order, paired by exact header stamp.

    Unpairable or unconvertible images are reported through ``on_skip(reason)`` and skipped; the
    camera_info used for a pair is the latest one received at or before it (None when the bag
    has none: give a calibration file then).
    """
    import rosbag
    topics = dict(DEFAULT_TOPICS, **(topics or {}))
    gt = read_ground_truth(bag_path, topics["ground_truth"]) if with_ground_truth else None
    skip = on_skip or (lambda reason: None)
    pending = {"left": {}, "right": {}}
    info = {"left": None, "right": None}
    want = {topics["left_image"]: "left", topics["right_image"]: "right",
            topics["left_info"]: "left_info", topics["right_info"]: "right_info"}
    n = 0
    with rosbag.Bag(bag_path) as bag:
        for topic, msg, _ in bag.read_messages(topics=list(want)):
            kind = want[topic]
            if kind.endswith("_info"):
                try:
                    info[kind[:-5]] = cv.camera_info_to_model(msg)
                except cv.ConversionError as e:
                    skip("camera_info on %s: %s" % (topic, e))
                continue
            key = (msg.header.stamp.secs, msg.header.stamp.nsecs)
            try:
                img = cv.image_to_numpy(msg, to_mono=True)
            except cv.ConversionError as e:
                skip("image on %s at %d.%09d: %s" % (topic, key[0], key[1], e))
                continue
            pending[kind][key] = (img, info[kind])
            other = "right" if kind == "left" else "left"
            if key in pending[other]:
                limg, linfo = pending["left"].pop(key)
                rimg, rinfo = pending["right"].pop(key)
                if limg.shape != rimg.shape:
                    skip("left %s and right %s image sizes differ at %d.%09d"
                         % (limg.shape, rimg.shape, key[0], key[1]))
                    continue
                stamp = key[0] + 1e-9 * key[1]
                T = gt.at(stamp) if gt is not None and len(gt) else None
                yield StereoFrame(n, stamp, limg, rimg, linfo or info["left"],
                                  rinfo or info["right"], T)
                n += 1
                if max_frames is not None and n >= max_frames:
                    return
                # drop unmatched images older than this pair (their partner never came)
                for side in ("left", "right"):
                    old = [k for k in pending[side] if k < key]
                    for k in old:
                        del pending[side][k]
                        skip("%s image at %d.%09d has no partner" % (side, k[0], k[1]))
