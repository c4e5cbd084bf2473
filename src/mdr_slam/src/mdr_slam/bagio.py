"""Bags in and out: stereo sequences, camera_info, ground-truth poses, tf.

ROS side (uses rosbag and mdr_slam.conversions), like the nodes: the simulator and the importers
write bags through :class:`StereoBagWriter`; the offline runners (``mdr run``, ``mdr bench
--ablation``, ``mdr demo``) read them with :func:`read_stereo_frames`, which reads bags as robots
record them: messages in receive order (not stamp order), raw or compressed images of any
intensity encoding, left/right paired by approximate time with the nodes' policy
(:class:`mdr_slam.stereo_sync.StereoSync`), camera_info before, after or once beside the images,
and, when asked, the ground-truth pose at the frame's stamp (interpolated).
"""
from __future__ import annotations

import bisect
import struct
from dataclasses import dataclass
from typing import Dict, Iterator, List, Optional

import numpy as np

import genpy
from tf2_msgs.msg import TFMessage

from . import conversions as cv
from .camera import CameraModel, StereoCamera
from .geometry import interpolate_pose
from .stereo_sync import StereoSync

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
IMAGE_TRANSPORTS = ("raw", "compressed")
_IMAGE_TYPES = ("sensor_msgs/Image", "sensor_msgs/CompressedImage")
_SIDES = ("left", "right")
_TIME_JUMP_NS = 1000000000        # a stamp this far behind its side's newest: a new timeline


class StereoBagWriter:
    """Writes a stereo sequence on the default input topics (mono8 images + camera_info)."""

    def __init__(self, path: str, topics: Optional[Dict[str, str]] = None, compression: str = "none"):
        # rosbag (it imports rospy: 0.1-0.25 s) only where a bag is opened: `mdr --help`
        # imports this module for DEFAULT_TOPICS and IMAGE_TRANSPORTS
        import rosbag
        self.topics = dict(DEFAULT_TOPICS, **(topics or {}))
        self.bag = rosbag.Bag(path, "w", compression=compression)
        self.seq = 0

    def write_stereo(self, stamp: float, left: np.ndarray, right: np.ndarray,
                     camera: Optional[StereoCamera] = None, encoding: Optional[str] = None) -> None:
        """One stereo pair (and, when given, the pair's camera_info) at ``stamp`` seconds."""
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
    stamp: float                     # the left image's header stamp
    left: np.ndarray                 # as in the bag (raw or rectified), grey uint8
    right: np.ndarray
    left_info: Optional[CameraModel]
    right_info: Optional[CameraModel]
    T_map_cam_gt: Optional[np.ndarray] = None   # ground truth at the stamp, when asked and known
    right_stamp: Optional[float] = None         # the right image's header stamp


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


def image_topics(topics: Optional[Dict[str, str]] = None,
                 image_transport: str = "raw") -> Dict[str, str]:
    """``{"left": topic, "right": topic}`` the images are read from: the image topics, with
    image_transport's ``/compressed`` suffix for the compressed transport (as a subscriber
    appends it to the remapped name)."""
    if image_transport not in IMAGE_TRANSPORTS:
        raise ValueError("image_transport must be one of %s, got %r"
                         % (", ".join(IMAGE_TRANSPORTS), image_transport))
    topics = dict(DEFAULT_TOPICS, **(topics or {}))
    suffix = "/compressed" if image_transport == "compressed" else ""
    return {side: topics[side + "_image"] + suffix for side in _SIDES}


def bag_image_topics(bag_path: str) -> Dict[str, str]:
    """``{topic: type}`` of the bag's Image and CompressedImage topics (for error messages)."""
    import rosbag
    with rosbag.Bag(bag_path) as bag:
        info = bag.get_type_and_topic_info().topics
    return {t: v.msg_type for t, v in sorted(info.items()) if v.msg_type in _IMAGE_TYPES}


def _stamp_ns(data) -> Optional[int]:
    """Header stamp (ns) of a serialized message that starts with a std_msgs/Header
    (uint32 seq, uint32 secs, uint32 nsecs, ...), without deserializing the rest (the image)."""
    if len(data) < 12:
        return None
    secs, nsecs = struct.unpack_from("<II", data, 4)
    return secs * 1000000000 + nsecs


def _fmt(ns: int) -> str:
    return "%d.%09d" % divmod(int(ns), 1000000000)


def _deserialize(pytype, data):
    """The message of serialized ``data``; ConversionError when it is cut short or corrupt."""
    msg = pytype()
    try:
        msg.deserialize(data)
    except genpy.DeserializationError as e:
        raise cv.ConversionError("cannot deserialize %s: %s" % (pytype._type, e)) from e
    return msg


class _Infos:
    """The camera_infos of one side by stamp; identical calibrations are kept once (a driver
    publishes the same one with every image)."""

    def __init__(self):
        self.stamps: List[int] = []
        self.which: List[int] = []
        self.models: List[CameraModel] = []
        self._keys: Dict[tuple, int] = {}

    def add(self, ns: int, model: CameraModel) -> None:
        key = (model.width, model.height, model.distortion_model, model.frame_id,
               model.K.tobytes(), model.D.tobytes(), model.R.tobytes(), model.P.tobytes())
        if key not in self._keys:
            self._keys[key] = len(self.models)
            self.models.append(model)
        self.stamps.append(ns)
        self.which.append(self._keys[key])

    def freeze(self) -> None:
        order = np.argsort(np.asarray(self.stamps, dtype=np.int64), kind="stable")
        self._st = np.asarray(self.stamps, dtype=np.int64)[order]
        self._wh = np.asarray(self.which, dtype=np.int64)[order]

    def at(self, ns: int) -> Optional[CameraModel]:
        """The info stamped at or before ``ns`` (the latest such), else the earliest one."""
        if not self.models:
            return None
        i = int(np.searchsorted(self._st, ns, side="right")) - 1
        return self.models[int(self._wh[max(i, 0)])]


def _scan(bag, img_topics: Dict[str, str], info_topics: Dict[str, str], skip):
    """First pass over the serialized messages: per side the image header stamps in the bag's
    order (None for a message that is not an image) with a timeline number (an image stamped more
    than ``_TIME_JUMP_NS`` before the newest one starts a new timeline, for both sides: a bag
    recorded from a looping source, where StereoSync resets live), and the camera_infos."""
    want = {}
    for side in _SIDES:
        want[img_topics[side]] = ("image", side)
        want[info_topics[side]] = ("info", side)
    stamps = {side: [] for side in _SIDES}
    timeline = {side: [] for side in _SIDES}
    infos = {side: _Infos() for side in _SIDES}
    newest, current = None, 0
    for topic, raw, _ in bag.read_messages(topics=list(want), raw=True):
        datatype, data, _, _, pytype = raw
        kind, side = want[topic]
        ns = _stamp_ns(data)
        if kind == "info":
            if datatype != "sensor_msgs/CameraInfo":
                skip("%s on %s is not a camera_info" % (datatype, topic))
                continue
            try:
                infos[side].add(ns, cv.camera_info_to_model(_deserialize(pytype, data)))
            except cv.ConversionError as e:
                skip("camera_info on %s at %s: %s" % (topic, _fmt(ns or 0), e))
            continue
        if datatype not in _IMAGE_TYPES or ns is None:
            skip("%s on %s is not an image (sensor_msgs/Image or CompressedImage)"
                 % (datatype, topic))
            ns = None
        elif newest is not None and ns < newest - _TIME_JUMP_NS:
            current, newest = current + 1, ns
        else:
            newest = ns if newest is None else max(ns, newest)
        stamps[side].append(ns)
        timeline[side].append(current)
    for side in _SIDES:
        infos[side].freeze()
    return stamps, timeline, infos


def _pair(stamps, timeline, tolerance: float):
    """The pairs (left index, right index) of :class:`StereoSync` fed with both sides' images
    in stamp order (per timeline), as a live subscriber receives them; and the sync."""
    order = sorted((timeline[side][k], ns, i, k) for i, side in enumerate(_SIDES)
                   for k, ns in enumerate(stamps[side]) if ns is not None)
    sync = StereoSync(tolerance=tolerance)
    pairs = []
    for _, ns, i, k in order:
        for _, lk, _, rk in sync.add(_SIDES[i], 1e-9 * ns, k):
            pairs.append((lk, rk))
    return pairs, sync


def read_stereo_frames(bag_path: str, topics: Optional[Dict[str, str]] = None,
                       max_frames: Optional[int] = None, with_ground_truth: bool = False,
                       on_skip=None, image_transport: str = "raw",
                       sync_tolerance: float = 0.0) -> Iterator[StereoFrame]:
    """Stereo pairs of a bag in stamp order, as the nodes pair them live.

    ``topics``: overrides of :data:`DEFAULT_TOPICS`. Images are sensor_msgs/Image of any
    intensity encoding, or, with ``image_transport="compressed"``, sensor_msgs/CompressedImage
    (png, jpeg) on ``<image topic>/compressed``; each is turned into grey uint8.

    The bag's order is the order messages were received, not their stamps': a first pass reads the
    header stamps from the serialized messages (and the camera_infos), :class:`StereoSync` pairs
    the images by approximate time (``sync_tolerance`` s, 0 = auto: a fraction of the frame
    period) fed in stamp order, and a second pass decodes the paired images only. Images are held
    only until their pair is complete and every earlier pair is out, so the memory follows how far
    the bag's order strays from the stamps' (a few frames), not the bag's length.

    Each image takes its side's camera_info stamped at or before it (the latest), else the
    earliest in the bag (an info recorded after the images, or once anywhere); None when the bag
    has none (give a calibration file then). The frame's stamp is the left image's. Images that
    do not pair, do not convert or differ in size from their partner are reported through
    ``on_skip(reason)`` and skipped. ``with_ground_truth``: attach the ground-truth pose
    (``topics["ground_truth"]``) interpolated at the stamp.
    """
    import rosbag
    topics = dict(DEFAULT_TOPICS, **(topics or {}))
    img_topics = image_topics(topics, image_transport)
    info_topics = {side: topics[side + "_info"] for side in _SIDES}
    if not sync_tolerance >= 0:
        raise ValueError("sync_tolerance must be >= 0 s (0: auto), got %r" % (sync_tolerance,))
    skip = on_skip or (lambda reason: None)
    gt = read_ground_truth(bag_path, topics["ground_truth"]) if with_ground_truth else None
    with rosbag.Bag(bag_path) as bag:
        stamps, timeline, infos = _scan(bag, img_topics, info_topics, skip)
        pairs, sync = _pair(stamps, timeline, float(sync_tolerance))
        partner = {side: np.full(len(stamps[side]), -1, dtype=np.int64) for side in _SIDES}
        for p, (lk, rk) in enumerate(pairs):
            partner["left"][lk] = p
            partner["right"][rk] = p
        sorted_ns = {side: np.sort(np.asarray([s for s in stamps[side] if s is not None],
                                              dtype=np.int64)) for side in _SIDES}

        def unpaired(side: str, ns: int) -> str:
            other = "right" if side == "left" else "left"
            o = sorted_ns[other]
            near = ""
            if len(o):
                j = int(np.searchsorted(o, ns))
                c = [o[i] for i in (j - 1, j) if 0 <= i < len(o)]
                d = min((x - ns for x in c), key=abs)
                near = " (nearest %s %+.1f ms)" % (other, 1e-6 * d)
            return "%s image at %s on %s has no %s partner within %.1f ms%s" % (
                side, _fmt(ns), img_topics[side], other, 1e3 * sync.tolerance, near)

        pending: Dict[int, Dict[str, Optional[np.ndarray]]] = {}
        next_pair, n = 0, 0
        seen = {side: 0 for side in _SIDES}
        side_of = {img_topics[side]: side for side in _SIDES}
        for topic, raw, _ in bag.read_messages(topics=list(side_of), raw=True):
            side = side_of[topic]
            k = seen[side]
            seen[side] += 1
            ns = stamps[side][k]
            if ns is None:
                continue                                   # reported by the scan
            p = int(partner[side][k])
            if p < 0:
                skip(unpaired(side, ns))
                continue
            _, data, _, _, pytype = raw
            try:
                img = cv.image_msg_to_mono8(_deserialize(pytype, data))
            except cv.ConversionError as e:
                skip("%s image at %s on %s: %s" % (side, _fmt(ns), topic, e))
                img = None
            pending.setdefault(p, {})[side] = img
            while len(pending.get(next_pair, ())) == 2:
                got = pending.pop(next_pair)
                lk, rk = pairs[next_pair]
                next_pair += 1
                l_ns, r_ns = stamps["left"][lk], stamps["right"][rk]
                left, right = got["left"], got["right"]
                if left is None or right is None:
                    ok = "left" if left is not None else "right"
                    if left is not None or right is not None:
                        skip("%s image at %s dropped: its partner could not be read"
                             % (ok, _fmt(l_ns if ok == "left" else r_ns)))
                    continue
                if left.shape != right.shape:
                    skip("left %s and right %s image sizes differ at %s"
                         % (left.shape, right.shape, _fmt(l_ns)))
                    continue
                stamp = 1e-9 * l_ns
                T = gt.at(stamp) if gt is not None and len(gt) else None
                yield StereoFrame(n, stamp, left, right, infos["left"].at(l_ns),
                                  infos["right"].at(r_ns), T, 1e-9 * r_ns)
                n += 1
                if max_frames is not None and n >= max_frames:
                    return
