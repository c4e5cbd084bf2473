"""Driver-like recording of a simulated sequence: the bag a real stereo camera driver on a wheeled
base writes, with the simulator's exact ground truth kept OUT of the bag (groundtruth.tum,
gt_map.ply, scene.yaml as usual).

The rendering is :func:`~mdr_slam.sim.generate.generate`'s, unchanged; only the bag writer is
swapped (its ``frame_writer`` hook) for :class:`DriverBagWriter`, which writes what the driver
would publish:

- ``zed`` (zed_wrapper): bgr8 ``/zed/zed_node/{left,right}/image_rect_color``, rectified
  camera_info (D = 0, R = I), right stamps 3 ms after the left by default, tf_static
  ``base_link -> zed_camera_center -> zed_{left,right}_camera_frame -> *_optical_frame``;
- ``realsense`` (realsense2_camera): mono8 ``/camera/infra{1,2}/image_rect_raw``, rectified
  camera_info, tf_static ``base_link -> camera_link -> camera_infra{1,2}_frame -> *_optical_frame``;
- ``stereo_image_proc``: mono8 ``/stereo/{left,right}/image_rect`` next to camera_info that
  carries the RAW calibration (distortion D, rectification R != I) whose P is the rectified
  projection the images were rendered with, tf_static ``base_link -> stereo_left_optical``.
  Rectifying these images again warps them; trusting P gives the rendered geometry exactly.

Per frame: left image, left camera_info, right image, right camera_info, each camera_info with
its image's stamp; bag receive time = stamp + a few ms of transport latency. ``compressed``
puts the images on ``<topic>/compressed`` (sensor_msgs/CompressedImage, the format string of
compressed_image_transport) instead of the raw topics. Wheel odometry (``/odom`` and ``/tf``
odom -> base_link) integrates the true base motion with a systematic error
(:data:`ODOM_SCALE_ERROR`, :data:`ODOM_YAW_DRIFT`).

The camera's mounting on the base follows the trajectory: the camera centre sits
:data:`MOUNT_FORWARD` m ahead of base_link at the trajectory's median camera height and tilted
down by its median pitch, so base_link stays near the floor and near level. ``driver.yaml``
(written by :func:`generate_driver`) records topics, frames, ``T_base_cam``, lag and odometry.
"""
from __future__ import annotations

import heapq
import os
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from ..camera import CameraModel
from ..geometry import R_OPTICAL, inv_T, make_T, R_to_quat
from ..io.atomic import atomic_write
from .generate import generate
from .render import _EUROC_RAW

__all__ = ["DRIVERS", "DriverProfile", "PROFILES", "DriverConfig", "DriverBagWriter",
           "generate_driver", "static_transforms", "compose_static", "wheel_odometry",
           "mount_from_trajectory", "raw_calibration", "ODOM_SCALE_ERROR", "ODOM_YAW_DRIFT",
           "ODOM_RATE", "MOUNT_FORWARD", "JPEG_QUALITY", "R_OPTICAL"]

DRIVERS = ("zed", "realsense", "stereo_image_proc")

ODOM_SCALE_ERROR = 0.02     # odometry translation reads 2 % long (wheel radius calibration)
ODOM_YAW_DRIFT = 1.0        # deg of counter-clockwise yaw error per metre travelled (track width)
ODOM_RATE = 50.0            # Hz, its own clock (0: at the left image stamps)
ODOM_LATENCY = 0.001        # s from an odometry stamp to its bag receive time
IMAGE_LATENCY = (0.004, 0.002)   # s: image transport latency = base + uniform jitter
INFO_AFTER = 0.0001         # s: camera_info received right after its image
MOUNT_FORWARD = 0.10        # m: camera centre ahead of base_link
JPEG_QUALITY = 80           # compressed_image_transport's default jpeg_quality
# diff_drive_controller-like diagonals (x, y, z, roll, pitch, yaw), but finite for z/roll/pitch
# because this odometry integrates the base's full 3-D increments
ODOM_POSE_COV = (1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-2)
ODOM_TWIST_COV = (1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-2)

BASE_FRAME = "base_link"
ODOM_FRAME = "odom"


@dataclass(frozen=True)
class DriverProfile:
    """Topics and frames one camera driver publishes (the rectified stereo pair)."""

    name: str
    left_image: str
    right_image: str
    left_info: str
    right_info: str
    left_frame: str
    right_frame: str
    encoding: str            # mono8 | bgr8
    right_lag_ms: float      # default right stamp lag behind the left
    raw_info: bool           # camera_info holds the raw calibration (D, R) of rectified images


PROFILES: Dict[str, DriverProfile] = {
    "zed": DriverProfile(
        "zed", "/zed/zed_node/left/image_rect_color", "/zed/zed_node/right/image_rect_color",
        "/zed/zed_node/left/camera_info", "/zed/zed_node/right/camera_info",
        "zed_left_camera_optical_frame", "zed_right_camera_optical_frame", "bgr8", 3.0, False),
    "realsense": DriverProfile(
        "realsense", "/camera/infra1/image_rect_raw", "/camera/infra2/image_rect_raw",
        "/camera/infra1/camera_info", "/camera/infra2/camera_info",
        "camera_infra1_optical_frame", "camera_infra2_optical_frame", "mono8", 0.0, False),
    "stereo_image_proc": DriverProfile(
        "stereo_image_proc", "/stereo/left/image_rect", "/stereo/right/image_rect",
        "/stereo/left/camera_info", "/stereo/right/camera_info",
        "stereo_left_optical", "stereo_right_optical", "mono8", 0.0, True),
}


@dataclass
class DriverConfig:
    """What to record; ``None`` lag means the driver's default."""

    driver: str
    compressed: Optional[str] = None          # None (raw Image) | "jpeg" | "png"
    jpeg_quality: int = JPEG_QUALITY
    right_lag_ms: Optional[float] = None
    odom: bool = True
    odom_scale_error: float = ODOM_SCALE_ERROR
    odom_yaw_drift: float = ODOM_YAW_DRIFT    # deg per metre
    odom_rate: float = ODOM_RATE
    mount_forward: float = MOUNT_FORWARD
    seed: int = 0                             # latency jitter

    def __post_init__(self):
        if self.driver not in PROFILES:
            raise ValueError("unknown driver %r (drivers: %s)" % (self.driver, ", ".join(DRIVERS)))
        if self.compressed not in (None, "jpeg", "png"):
            raise ValueError("compressed must be jpeg or png, not %r" % (self.compressed,))
        if not 1 <= int(self.jpeg_quality) <= 100:
            raise ValueError("jpeg quality must be in 1..100, got %r" % (self.jpeg_quality,))
        if self.right_lag_ms is None:
            self.right_lag_ms = PROFILES[self.driver].right_lag_ms
        for name in ("right_lag_ms", "odom_rate"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v >= 0):
                raise ValueError("%s must be finite and >= 0, got %r" % (name, v))
        if not (np.isfinite(self.odom_scale_error) and self.odom_scale_error > -1.0):
            raise ValueError("odom scale error must be > -1, got %r" % (self.odom_scale_error,))
        if not np.isfinite(self.odom_yaw_drift):
            raise ValueError("odom yaw drift must be finite, got %r" % (self.odom_yaw_drift,))

    @property
    def profile(self) -> DriverProfile:
        return PROFILES[self.driver]


# -------------------------------------------------------------------------- geometry helpers
def _Ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _Rz(a) -> np.ndarray:
    """(3, 3) or, for an array of angles, (N, 3, 3) rotations about z."""
    a = np.asarray(a, float)
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1),
                     np.stack([z, z, o], -1)], -2)


def mount_from_trajectory(Ts: np.ndarray,
                          forward: float = MOUNT_FORWARD) -> Tuple[float, float, np.ndarray]:
    """``(height, pitch, T_base_center)``: the camera body frame (x forward, z up) in base_link,
    ``forward`` m ahead, at the median camera height and tilted down by the median pitch of the
    trajectory (rounded to cm and 0.01 rad, as a measured mounting would be)."""
    Ts = np.asarray(Ts, float).reshape(-1, 4, 4)
    height = round(float(np.median(Ts[:, 2, 3])), 2)
    fz = np.clip(Ts[:, 2, 2], -1.0, 1.0)          # optical z (forward) axis, map z component
    pitch = round(float(np.median(np.arcsin(-fz))), 2)
    return height, pitch, make_T(_Ry(pitch), [forward, 0.0, height])


def static_transforms(driver: str, T_base_center: np.ndarray,
                      baseline: float) -> List[Tuple[str, str, np.ndarray]]:
    """The driver's tf_static tree as ``(parent, child, T_parent_child)``, rooted at base_link.
    ``T_base_center`` places the camera body frame (x forward, z up) on the base."""
    opt = make_T(R_OPTICAL, [0.0, 0.0, 0.0])
    B = float(baseline)
    if driver == "zed":    # zed_wrapper: the two cameras B/2 left and right of the centre
        return [(BASE_FRAME, "zed_camera_center", T_base_center),
                ("zed_camera_center", "zed_left_camera_frame", make_T(np.eye(3), [0, B / 2, 0])),
                ("zed_left_camera_frame", "zed_left_camera_optical_frame", opt),
                ("zed_camera_center", "zed_right_camera_frame", make_T(np.eye(3), [0, -B / 2, 0])),
                ("zed_right_camera_frame", "zed_right_camera_optical_frame", opt)]
    if driver == "realsense":   # realsense2_camera: camera_link at infra1, infra2 B to its right
        return [(BASE_FRAME, "camera_link", T_base_center),
                ("camera_link", "camera_infra1_frame", np.eye(4)),
                ("camera_infra1_frame", "camera_infra1_optical_frame", opt),
                ("camera_link", "camera_infra2_frame", make_T(np.eye(3), [0, -B, 0])),
                ("camera_infra2_frame", "camera_infra2_optical_frame", opt)]
    if driver == "stereo_image_proc":
        # the rectified left optical frame, as stereo_image_proc's point clouds use the header
        # frame; the right camera B along its x
        return [(BASE_FRAME, "stereo_left_optical", T_base_center @ opt),
                ("stereo_left_optical", "stereo_right_optical", make_T(np.eye(3), [B, 0, 0]))]
    raise ValueError("unknown driver %r (drivers: %s)" % (driver, ", ".join(DRIVERS)))


def compose_static(transforms, parent: str, child: str) -> np.ndarray:
    """T_parent_child through a tree of ``(parent, child, T)`` edges (child -> root walk)."""
    up = {c: (p, T) for p, c, T in transforms}
    T = np.eye(4)
    frame = child
    while frame != parent:
        if frame not in up:
            raise ValueError("no static transform chain from %r to %r" % (parent, child))
        p, Tpc = up[frame]
        T = Tpc @ T
        frame = p
    return T


def wheel_odometry(T_map_base: np.ndarray, scale_error: float = ODOM_SCALE_ERROR,
                   yaw_drift_deg_per_m: float = ODOM_YAW_DRIFT):
    """``(T_odom_base (N, 4, 4), increments (N, 4, 4))`` integrated from the true base poses
    with a systematic error, from identity at the first pose:
    ``T_odom_base[k] = T_odom_base[k-1] @ noisy(inv(T_map_base[k-1]) @ T_map_base[k])``, where
    ``noisy`` scales the translation by ``1 + scale_error`` and adds a yaw of
    ``yaw_drift_deg_per_m`` per metre of the increment's true translation. ``increments[0]``
    is the identity."""
    Tb = np.asarray(T_map_base, float).reshape(-1, 4, 4)
    n = len(Tb)
    inc = np.tile(np.eye(4), (n, 1, 1))
    if n > 1:
        inc[1:] = np.einsum("nij,njk->nik", np.linalg.inv(Tb[:-1]), Tb[1:])
        dist = np.linalg.norm(inc[1:, :3, 3], axis=1)
        inc[1:, :3, 3] *= 1.0 + float(scale_error)
        inc[1:, :3, :3] = np.einsum("nij,njk->nik", inc[1:, :3, :3],
                                    _Rz(np.deg2rad(yaw_drift_deg_per_m) * dist))
    out = np.empty_like(inc)
    out[0] = np.eye(4)
    for k in range(1, n):     # a sequential product: N is the odometry rate x duration
        out[k] = out[k - 1] @ inc[k]
    return out, inc


def raw_calibration(camera):
    """(left, right) raw CameraModels for rectified images of ``camera``: EuRoC-like
    radial-tangential distortion and rectification rotations, scaled to the image width, with
    P = ``camera``'s rectified projections (what the images were rendered with)."""
    s = camera.left.width / 752.0
    out = []
    for (k, D, rv), m in zip(_EUROC_RAW, (camera.left, camera.right)):
        kfx, kfy, kcx, kcy = k
        K = np.array([[kfx * s, 0, (kcx + 0.5) * s - 0.5], [0, kfy * s, (kcy + 0.5) * s - 0.5],
                      [0, 0, 1.0]])
        out.append(CameraModel(m.width, m.height, K, D.copy(),
                               Rotation.from_rotvec(rv).as_matrix(), m.P.copy()))
    return out[0], out[1]


def _xyz_quat(T: np.ndarray) -> List[float]:
    return [round(float(v), 9) for v in list(T[:3, 3]) + list(R_to_quat(T[:3, :3]))]


# ------------------------------------------------------------------------------------ writer
class DriverBagWriter:
    """The ``frame_writer`` of :func:`~mdr_slam.sim.generate.generate` for one driver.

    Messages are queued with their bag receive time and written in that order (rosbag readers
    merge topics by receive time), so a frame's odometry, images and camera_info interleave as
    a recorder would have seen them.
    """

    def __init__(self, bag_path: str, camera, stamps: np.ndarray, Ts: np.ndarray, traj,
                 config: DriverConfig):
        # ROS (rosbag, genpy, messages, conversions) only in the bag writer's methods:
        # mdr_slam.sim imports without ROS
        import rosbag
        self.cfg = config
        self.prof = config.profile
        self.camera = camera
        self.stamps = np.asarray(stamps, float)
        self.lag = float(config.right_lag_ms) * 1e-3
        self.height, self.pitch, T_base_center = mount_from_trajectory(
            Ts, config.mount_forward)
        self.static = static_transforms(config.driver, T_base_center, camera.baseline)
        self.T_base_cam = compose_static(self.static, BASE_FRAME, self.prof.left_frame)
        if self.prof.raw_info:
            self.info = raw_calibration(camera)
        else:
            self.info = (camera.left, camera.right)
        self.rng = np.random.default_rng([int(config.seed), 5150])
        self.queue: list = []
        self.n_queued = 0
        self.seq: Dict[str, int] = {}
        self.counts: Dict[str, int] = {}
        self.bag = rosbag.Bag(bag_path, "w")
        self._odometry(traj)
        self._write_static()

    # --- odometry, precomputed from the analytic trajectory at its own rate
    def _odometry(self, traj) -> None:
        t0, t_end = float(self.stamps[0]), float(self.stamps[-1]) + self.lag
        self.next_odom = 0
        if not self.cfg.odom:
            self.odom_stamps = np.zeros(0)
            return
        if self.cfg.odom_rate > 0:
            n = int(np.floor((t_end - t0) * self.cfg.odom_rate + 1e-9)) + 1
            self.odom_stamps = t0 + np.arange(n) / float(self.cfg.odom_rate)
        else:
            self.odom_stamps = self.stamps.copy()
        T_map_base = traj.poses(self.odom_stamps - t0) @ inv_T(self.T_base_cam)
        self.T_odom_base, self.odom_inc = wheel_odometry(
            T_map_base, self.cfg.odom_scale_error, self.cfg.odom_yaw_drift)

    def _queue_odometry(self, until: float) -> None:
        """Queue the odometry stamped before ``until`` (inclusive at the end of the bag)."""
        import genpy
        from nav_msgs.msg import Odometry
        from tf2_msgs.msg import TFMessage
        from .. import conversions as cv
        k = self.next_odom
        while k < len(self.odom_stamps) and self.odom_stamps[k] < until:
            ts = float(self.odom_stamps[k])
            t = genpy.Time.from_sec(ts)
            T = self.T_odom_base[k]
            msg = Odometry()
            msg.header = self._header("/odom", t, ODOM_FRAME)
            msg.child_frame_id = BASE_FRAME
            msg.pose.pose = cv.matrix_to_pose(T)
            msg.pose.covariance = list(np.diag(ODOM_POSE_COV).ravel())
            if k > 0:   # the last increment over its time step, in the base frame at k-1
                dt = ts - float(self.odom_stamps[k - 1])
                inc = self.odom_inc[k]
                v = inc[:3, 3] / dt
                w = Rotation.from_matrix(inc[:3, :3]).as_rotvec() / dt
                tw = msg.twist.twist
                tw.linear.x, tw.linear.y, tw.linear.z = (float(x) for x in v)
                tw.angular.x, tw.angular.y, tw.angular.z = (float(x) for x in w)
            msg.twist.covariance = list(np.diag(ODOM_TWIST_COV).ravel())
            recv = ts + ODOM_LATENCY
            self._push(recv, "/odom", msg)
            self._push(recv, "/tf", TFMessage([cv.matrix_to_transform_stamped(
                T, t, ODOM_FRAME, BASE_FRAME)]))
            k += 1
        self.next_odom = k

    # --- static tf: once, latched, at the first stamp
    def _write_static(self) -> None:
        import genpy
        from tf2_msgs.msg import TFMessage
        from .. import conversions as cv
        t = genpy.Time.from_sec(float(self.stamps[0]))
        msg = TFMessage([cv.matrix_to_transform_stamped(T, t, p, c) for p, c, T in self.static])
        # what rosbag record stores for a latched topic: rosbag play republishes it latched
        header = {"topic": "/tf_static", "type": msg._type, "md5sum": msg._md5sum,
                  "message_definition": msg._full_text, "callerid": "/robot_state_publisher",
                  "latching": "1"}
        self.bag.write("/tf_static", msg, t, connection_header=header)
        self._count("/tf_static")

    # --- frames
    def _header(self, topic: str, t, frame: str):
        from .. import conversions as cv
        seq = self.seq.get(topic, 0)
        self.seq[topic] = seq + 1
        return cv.make_header(t, frame, seq)

    def _push(self, recv: float, topic: str, msg) -> None:
        heapq.heappush(self.queue, (recv, self.n_queued, topic, msg))
        self.n_queued += 1

    def _flush(self, until: Optional[float]) -> None:
        import genpy
        while self.queue and (until is None or self.queue[0][0] < until):
            recv, _, topic, msg = heapq.heappop(self.queue)
            self.bag.write(topic, msg, genpy.Time.from_sec(recv))
            self._count(topic)

    def _count(self, topic: str) -> None:
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _image_msg(self, topic: str, img: np.ndarray, t, frame: str):
        from .. import conversions as cv
        if self.prof.encoding == "bgr8":
            # equal channels: cv2's BGR2GRAY weights sum to exactly 1 in its fixed point, so
            # the grey a consumer converts back is the rendered one
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        if self.cfg.compressed:
            msg = cv.numpy_to_compressed_image(img, self.cfg.compressed, t, frame,
                                               int(self.cfg.jpeg_quality))
            topic = topic + "/compressed"
        else:
            msg = cv.numpy_to_image(img, self.prof.encoding, t, frame)
        msg.header = self._header(topic, t, frame)
        return topic, msg

    def image_topics(self) -> Tuple[str, str]:
        suffix = "/compressed" if self.cfg.compressed else ""
        return self.prof.left_image + suffix, self.prof.right_image + suffix

    def write(self, i: int, left: np.ndarray, right: np.ndarray) -> None:
        import genpy
        from .. import conversions as cv
        p = self.prof
        ts = float(self.stamps[i])
        recv = None
        for side, img, lag in (("left", left, 0.0), ("right", right, self.lag)):
            t = genpy.Time.from_sec(ts + lag)
            frame = p.left_frame if side == "left" else p.right_frame
            topic, msg = self._image_msg(getattr(p, side + "_image"), img, t, frame)
            lat = IMAGE_LATENCY[0] + IMAGE_LATENCY[1] * float(self.rng.random())
            r = ts + lag + lat
            if recv is not None:
                r = max(r, recv + INFO_AFTER)   # the right pair follows the left pair
            self._push(r, topic, msg)
            info_topic = getattr(p, side + "_info")
            info = cv.model_to_camera_info(self.info[0 if side == "left" else 1], t, frame)
            info.header = self._header(info_topic, t, frame)
            recv = r + INFO_AFTER
            self._push(recv, info_topic, info)
        nxt = float(self.stamps[i + 1]) if i + 1 < len(self.stamps) else None
        if nxt is not None:
            self._queue_odometry(nxt)
            # nothing queued later can be received before the next frame's stamp
            self._flush(nxt)

    def close(self, complete: bool = True) -> None:
        """Write what is queued (and, when ``complete``, the rest of the odometry) and close."""
        if self.bag is None:
            return
        try:
            if complete:
                self._queue_odometry(np.inf)
            self._flush(None)
        finally:
            self.bag.close()
            self.bag = None

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        self.close(complete=exc_type is None)

    # --- what was recorded
    def describe(self) -> dict:
        """driver.yaml's content."""
        p, c = self.prof, self.cfg
        left_bag, right_bag = self.image_topics()
        pose_cov = [float(v) for v in ODOM_POSE_COV]
        twist_cov = [float(v) for v in ODOM_TWIST_COV]
        return {
            "driver": p.name,
            # the launch file's argument names; with image_transport compressed the image
            # topics are the base topics the transport subscribes to
            "topics": {"left_image": p.left_image, "right_image": p.right_image,
                       "left_info": p.left_info, "right_info": p.right_info},
            "image_transport": "compressed" if c.compressed else "raw",
            "compressed_format": c.compressed,
            "jpeg_quality": int(c.jpeg_quality) if c.compressed == "jpeg" else None,
            "encoding": p.encoding,
            "bag_topics": {"left_image": left_bag, "right_image": right_bag,
                           "left_info": p.left_info, "right_info": p.right_info,
                           "tf_static": "/tf_static",
                           "tf": "/tf" if c.odom else None, "odom": "/odom" if c.odom else None},
            "camera_info": ("raw calibration (distortion D, rectification R) of the rectified "
                            "images; P is their projection" if p.raw_info else
                            "rectified (D = 0, R = I)"),
            "frames": {"base": BASE_FRAME, "left_optical": p.left_frame,
                       "right_optical": p.right_frame, "odom": ODOM_FRAME if c.odom else None},
            "T_base_cam": [[round(float(v), 12) for v in row] for row in self.T_base_cam],
            "base_to_camera": " ".join("%.9g" % v for v in _xyz_quat(self.T_base_cam)),
            "mount": {"forward": float(c.mount_forward), "height": self.height,
                      "pitch": self.pitch},
            "static_transforms": [{"parent": pa, "child": ch, "xyz_qxyzw": _xyz_quat(T)}
                                  for pa, ch, T in self.static],
            "baseline": float(self.camera.baseline),
            "right_lag_ms": float(c.right_lag_ms),
            "latency_ms": {"image": [IMAGE_LATENCY[0] * 1e3, sum(IMAGE_LATENCY) * 1e3],
                           "odom": ODOM_LATENCY * 1e3},
            "odometry": {"enabled": bool(c.odom), "topic": "/odom" if c.odom else None,
                         "rate_hz": float(c.odom_rate) if c.odom_rate > 0 else "image",
                         "scale_error": float(c.odom_scale_error),
                         "yaw_drift_deg_per_m": float(c.odom_yaw_drift),
                         "n_messages": int(len(self.odom_stamps)),
                         "pose_covariance_diagonal": pose_cov,
                         "twist_covariance_diagonal": twist_cov},
            "message_counts": dict(sorted(self.counts.items())),
            "ground_truth": {"in_bag": False, "file": "groundtruth.tum",
                             "frame": "rectified left optical frame (%s) in map" % p.left_frame},
        }

    def summary(self) -> dict:
        """scene.yaml entries: the driver, and ground truth only outside the bag."""
        return {"driver": {"name": self.prof.name, "file": "driver.yaml"},
                "ground_truth": {"topic": None, "frame": "map",
                                 "child": "rectified left camera optical frame (z fwd, x right, "
                                          "y down) = %s" % self.prof.left_frame,
                                 "depth": "Z along the rectified left optical axis, metres, "
                                          "0 = none"}}


def generate_driver(out_dir: str, driver: str, compressed: Optional[str] = None,
                    jpeg_quality: int = JPEG_QUALITY, right_lag_ms: Optional[float] = None,
                    odom: bool = True, odom_scale_error: float = ODOM_SCALE_ERROR,
                    odom_yaw_drift: float = ODOM_YAW_DRIFT, odom_rate: float = ODOM_RATE,
                    mount_forward: float = MOUNT_FORWARD, **kwargs) -> dict:
    """:func:`~mdr_slam.sim.generate.generate` with the bag written the way ``driver``
    records (see the module doc) plus ``driver.yaml``; ``kwargs`` go to generate (not
    ``distort``: drivers publish rectified images). Returns generate's summary with
    ``driver`` (driver.yaml's content) and ``driver_yaml`` (its path)."""
    if kwargs.get("distort"):
        raise ValueError("a driver bag holds rectified images: --distort does not apply")
    if kwargs.get("camera") is not None and not kwargs["camera"].is_rectified:
        raise ValueError("a driver bag holds rectified images: give a rectified camera")
    cfg = DriverConfig(driver=driver, compressed=compressed, jpeg_quality=jpeg_quality,
                       right_lag_ms=right_lag_ms, odom=odom, odom_scale_error=odom_scale_error,
                       odom_yaw_drift=odom_yaw_drift, odom_rate=odom_rate,
                       mount_forward=mount_forward, seed=int(kwargs.get("seed", 0)))
    rate = float(kwargs.get("rate", 20.0))
    if cfg.right_lag_ms * 1e-3 >= 0.5 / rate:
        raise ValueError("right lag %.3g ms must be under half the frame period (%.3g ms)"
                         % (cfg.right_lag_ms, 500.0 / rate))
    made: List[DriverBagWriter] = []

    def factory(bag_path, camera, stamps, Ts, traj):
        w = DriverBagWriter(bag_path, camera, stamps, Ts, traj, cfg)
        made.append(w)
        return w

    summary = generate(out_dir, frame_writer=factory, **kwargs)
    desc = made[0].describe()
    path = os.path.join(summary["out_dir"], "driver.yaml")
    atomic_write(path, yaml.safe_dump(desc, sort_keys=False, default_flow_style=None), "w")
    summary.update(driver=desc, driver_yaml=path)
    return summary
