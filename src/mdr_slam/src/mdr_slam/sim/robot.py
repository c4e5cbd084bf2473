"""A simulated differential-drive robot in a simulator scene: the ROS-free core of sim_robot_node.

:class:`SimRobot` drives a base on the scene's floor from velocity commands and renders the stereo
pair of the camera on its mast:

- **kinematics** (:class:`DiffDrive`): a unicycle whose commanded velocities are clamped to the
  velocity limits, then approached within the acceleration limits, integrated exactly along arcs
  in physics sub-steps; a command older than ``cmd_timeout`` counts as zero (as
  diff_drive_controller does), a lateral velocity is ignored and counted;
- **collisions** (:class:`ObstacleMap`, :class:`Footprint`): the 2-D footprint (circle or polygon)
  against the footprint of every scene rectangle between ``floor_clearance`` and ``body_height``
  (walls and box sides project to segments, horizontal faces to areas). A sub-step that would
  overlap one is not taken: the base stops where it was (a bumper stop) and a collision is counted
  once per contact, which ends when the base is ``CONTACT_MARGIN`` clear again;
- **bumper** (:meth:`SimRobot.bumper_points`) and **safety back-off**: the contact as points just
  outside the footprint (as kobuki_bumper2pc's cloud), and the base reversing ``backoff_distance``
  straight away from it, velocity commands ignored meanwhile (as kobuki_safety_controller);
- **wheel odometry** (:class:`WheelOdometry`): the true increments with systematic errors
  (translation scale, rotation scale, yaw drift per metre, as :mod:`.driver`'s bags) and a seeded
  random walk proportional to the square root of the wheels' travel, so the drift's statistics do
  not depend on the sub-step;
- **camera** (:func:`mount_transform`, :func:`camera_pose`): the camera body frame ``forward`` m
  ahead of base_link at the mast height, tilted down by the pitch (the scene's trajectory's median
  height and pitch by default, as the driver bags' mounting), its optical frame per REP-103 (z
  forward = the robot's x); topic and frame layouts are the simulator bags' or a driver's.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import yaml

from ..config import Config, ConfigError
from ..geometry import make_T
from .driver import (ODOM_POSE_COV, ODOM_TWIST_COV, PROFILES, R_OPTICAL, _Ry, compose_static,
                     mount_from_trajectory, raw_calibration, static_transforms)
from .render import Simulator, _clip_polygon, sim_camera
from .scene import SCENES, Scene, make_scene
from .trajectory import build_trajectory

__all__ = ["RobotConfig", "DiffDrive", "WheelOdometry", "Footprint", "ObstacleMap", "SimRobot",
           "CameraLayout", "camera_layout", "mount_transform", "camera_pose", "base_matrix",
           "base_from_camera", "scene_start", "parse_footprint", "CONTACT_MARGIN", "LAYOUTS",
           "ODOM_POSE_COV", "ODOM_TWIST_COV"]

CONTACT_MARGIN = 0.02   # m of clearance that ends a contact (a new collision is then counted)
BUMPER_SPREAD = np.radians([-40.0, -20.0, 0.0, 20.0, 40.0])   # bumper points either side of the
BUMPER_OUT = 0.05       # ... blocked motion's direction, this far outside the footprint (m) ...
BUMPER_Z = 0.3          # ... at this height: inside move_base's obstacle band (0.1-1.5 m)
LAYOUTS = ("stereo",) + tuple(PROFILES)   # stereo: the simulator bags' topics and frames
_EPS = 1e-9


@dataclass
class RobotConfig(Config):
    """sim_robot_node's parameters (all ROS-free)."""
    scene: str = "office"              # office | corridor | garage | floor | atrium
    seed: int = 0                      # scene layout and texture, image noise, odometry noise
    contrast: float = 4.0              # texture amplitude of the low-texture surfaces (grey levels)
    specular: bool = True              # the scene's glossy band
    noise: float = 2.0                 # image noise sigma (grey levels)
    scale: float = 1.0                 # camera resolution as a fraction of 752x480
    rate: float = 10.0                 # Hz of stereo frames; sim time advances 1/rate per frame
    real_time_factor: float = 1.0      # cap: sim s per wall s (<= 1; 0: as fast as it renders)
    physics_rate: float = 100.0        # Hz of kinematics and collision sub-steps
    layout: str = "stereo"             # topics, frames: stereo (sim bags') or a driver (LAYOUTS)
    camera_name: str = "camera"        # stereo: <name>_link, <name>_{left,right}_optical_frame
    map_frame: str = "map"             # frame of the ground truth (the scene's, z up)
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    camera_height: Any = "auto"        # m above the floor; auto: the scene trajectory's
    camera_pitch: Any = "auto"         # rad, down; auto: the scene trajectory's
    camera_forward: float = 0.10       # m from base_link to the camera, forward
    max_vel_x: float = 0.5             # m/s forward
    min_vel_x: float = -0.3            # m/s (negative: reverse allowed)
    max_vel_theta: float = 1.5         # rad/s
    acc_lim_x: float = 1.0             # m/s^2
    acc_lim_theta: float = 2.0         # rad/s^2
    cmd_timeout: float = 0.5           # s (sim) without cmd_vel: the command is zero
    footprint_radius: float = 0.2      # m, a circular footprint centred on base_link ...
    footprint: Any = ""                # ... or a polygon "[[x, y], ...]" in base_link (move_base's)
    backoff_distance: float = 0.15     # m the base reverses after a contact (0: it stays pressed)
    backoff_speed: float = 0.1         # m/s of that reversing
    body_height: float = 1.5           # m: obstacles up to this height collide (mast included)
    floor_clearance: float = 0.03      # m: surfaces below (mats, lines) do not
    wheel_separation: float = 0.36     # m: the wheels' travel in turns (odometry noise)
    odom_rate: float = 50.0            # Hz of odom and odom -> base_link (at most physics_rate)
    odom_scale_error: float = 0.02     # odometry translation reads this fraction long
    odom_rot_scale_error: float = 0.01  # odometry rotation reads this fraction large
    odom_yaw_drift: float = 1.0        # deg of counter-clockwise yaw error per metre travelled
    odom_noise_lin: float = 0.01       # m per sqrt(m) of wheel travel (random walk)
    odom_noise_yaw: float = 0.5        # deg per sqrt(m) of wheel travel (random walk)
    start_pose: str = ""               # "x y yaw" of base_link in map; "": the scene trajectory's
    publish_tf: bool = True            # odom -> base_link on /tf
    ground_truth_frame: str = "ground_truth_camera"  # tf map -> it per frame (bags'); "": none
    wait_for_topic: str = ""           # after a frame, wait for a message stamped at it here
    wait_timeout: float = 1.0          # s (wall) of that wait
    diagnostics_period: float = 1.0    # s (wall) between /diagnostics messages

    def validate(self) -> None:
        """Cross-field checks (raises ConfigError)."""
        def need(ok, text):
            if not ok:
                raise ConfigError(text)
        need(self.scene in SCENES, "scene must be one of %s, got %r" % (", ".join(SCENES),
                                                                       self.scene))
        need(self.layout in LAYOUTS, "layout must be one of %s, got %r" % (", ".join(LAYOUTS),
                                                                          self.layout))
        need(0.05 <= self.scale <= 2.0, "scale must be in [0.05, 2], got %r" % self.scale)
        need(self.rate > 0, "rate must be > 0 Hz, got %r" % self.rate)
        need(self.real_time_factor <= 1.0, "real_time_factor caps the sim at real time: it must "
             "be <= 1 (0: no cap), got %r" % self.real_time_factor)
        need(self.physics_rate >= self.rate, "physics_rate must be >= rate")
        need(0 < self.odom_rate <= self.physics_rate, "odom_rate must be in (0, physics_rate]")
        need(self.max_vel_x >= 0 >= self.min_vel_x, "need min_vel_x <= 0 <= max_vel_x")
        for k in ("max_vel_theta", "acc_lim_x", "acc_lim_theta", "cmd_timeout", "body_height",
                  "wheel_separation", "odom_noise_lin", "odom_noise_yaw", "wait_timeout"):
            need(getattr(self, k) >= 0 and np.isfinite(getattr(self, k)),
                 "%s must be finite and >= 0" % k)
        need(self.odom_scale_error > -1 and self.odom_rot_scale_error > -1,
             "odometry scale errors must be > -1")
        fp = parse_footprint(self.footprint, self.footprint_radius)
        reach = fp.radius if fp.is_circle else float(_point_segment_distance(
            np.zeros(2), fp.shape, np.roll(fp.shape, -1, axis=0)).min())
        # a sub-step shorter than a quarter of the footprint: no wall is stepped over
        need(max(self.max_vel_x, -self.min_vel_x) / self.physics_rate < 0.25 * reach,
             "physics_rate is too low for max_vel_x and the footprint")
        for k in ("camera_height", "camera_pitch"):
            v = getattr(self, k)
            need(v == "auto" or (isinstance(v, (int, float)) and not isinstance(v, bool)
                                 and np.isfinite(v)), "%s must be a number or auto" % k)
        if self.start_pose:
            parse_start(self.start_pose)


def parse_start(text: str) -> Tuple[float, float, float]:
    try:
        v = [float(x) for x in str(text).replace(",", " ").split()]
    except ValueError:
        v = []
    if len(v) != 3 or not np.all(np.isfinite(v)):
        raise ConfigError("start_pose must be 'x y yaw', got %r" % (text,))
    return v[0], v[1], v[2]


# ------------------------------------------------------------------------------- geometry
def base_matrix(x: float, y: float, yaw: float) -> np.ndarray:
    """T_map_base of a base on the floor (z = 0, no roll or pitch)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return make_T(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), [x, y, 0.0])


def mount_transform(height: float, pitch: float, forward: float) -> np.ndarray:
    """T_base_center: the camera body frame (x forward, z up) ``forward`` m ahead of base_link,
    ``height`` m up, tilted down by ``pitch`` rad."""
    return make_T(_Ry(pitch), [forward, 0.0, height])


def camera_pose(T_map_base: np.ndarray, T_base_cam: np.ndarray) -> np.ndarray:
    """T_map_cam of a camera mounted at ``T_base_cam`` (e.g. the left optical frame)."""
    return np.asarray(T_map_base, float) @ np.asarray(T_base_cam, float)


def base_from_camera(T_map_cam: np.ndarray, forward: float) -> Tuple[float, float, float]:
    """(x, y, yaw) of the base under a forward-looking optical frame mounted ``forward`` m ahead
    of base_link: yaw from the optical z axis on the floor."""
    T = np.asarray(T_map_cam, float)
    yaw = float(np.arctan2(T[1, 2], T[0, 2]))
    return (float(T[0, 3] - forward * np.cos(yaw)), float(T[1, 3] - forward * np.sin(yaw)), yaw)


def scene_start(scene, forward: float = 0.10):
    """``(height, pitch, (x, y, yaw))``: the scene's default trajectory's median camera height
    and pitch (as the driver bags mount the camera) and its start as a base pose."""
    traj = build_trajectory(scene, None if scene.default_trajectory == "route" else 30.0,
                            scene.seed, scene=scene)
    Ts = traj.poses(np.arange(0.0, traj.duration, 0.1))
    height, pitch, _ = mount_from_trajectory(Ts, forward)
    return height, pitch, base_from_camera(Ts[0], forward)


@dataclass
class CameraLayout:
    """Topics (relative names), frames and tf_static of the published camera."""
    name: str
    left_image: str
    right_image: str
    left_info: str
    right_info: str
    left_frame: str
    right_frame: str
    encoding: str
    raw_info: bool
    static: List[Tuple[str, str, np.ndarray]]   # (parent, child, T_parent_child), from base

    def T_base(self, frame: str, base_frame: str) -> np.ndarray:
        return compose_static(self.static, base_frame, frame)


def camera_layout(layout: str, T_base_center: np.ndarray, baseline: float,
                  base_frame: str = "base_link", camera_name: str = "camera") -> CameraLayout:
    """``stereo``: the simulator bags' topics (``stereo/{left,right}/image_raw``, camera_info)
    and frames (``<camera_name>_{left,right}_optical_frame`` under ``<camera_name>_link``); a
    driver's name: that driver's topics, encoding and tf tree (:mod:`.driver`), relative."""
    opt = make_T(R_OPTICAL, [0.0, 0.0, 0.0])
    if layout == "stereo":
        link = camera_name + "_link"
        lf, rf = camera_name + "_left_optical_frame", camera_name + "_right_optical_frame"
        static = [(base_frame, link, T_base_center), (link, lf, opt),
                  (link, rf, make_T(np.eye(3), [0.0, -float(baseline), 0.0]) @ opt)]
        return CameraLayout("stereo", "stereo/left/image_raw", "stereo/right/image_raw",
                            "stereo/left/camera_info", "stereo/right/camera_info", lf, rf,
                            "mono8", False, static)
    if layout not in PROFILES:
        raise ConfigError("layout must be one of %s, got %r" % (", ".join(LAYOUTS), layout))
    p = PROFILES[layout]
    static = [(base_frame if pa == "base_link" else pa, ch, T)
              for pa, ch, T in static_transforms(layout, T_base_center, baseline)]
    return CameraLayout(layout, p.left_image.lstrip("/"), p.right_image.lstrip("/"),
                        p.left_info.lstrip("/"), p.right_info.lstrip("/"), p.left_frame,
                        p.right_frame, p.encoding, p.raw_info, static)


# ----------------------------------------------------------------------------- kinematics
class DiffDrive:
    """Velocity- and acceleration-limited differential-drive (unicycle) kinematics."""

    def __init__(self, max_vel_x: float, min_vel_x: float, max_vel_theta: float,
                 acc_lim_x: float, acc_lim_theta: float):
        self.max_v, self.min_v = float(max_vel_x), float(min_vel_x)
        self.max_w = float(max_vel_theta)
        self.acc_v, self.acc_w = float(acc_lim_x), float(acc_lim_theta)
        self.v = 0.0
        self.w = 0.0

    def limited(self, v_cmd: float, w_cmd: float, dt: float) -> Tuple[float, float]:
        """The velocities after ``dt`` towards the command: clamped to the velocity limits,
        changed by at most the acceleration limits times ``dt``."""
        v_t = min(max(float(v_cmd), self.min_v), self.max_v)
        w_t = min(max(float(w_cmd), -self.max_w), self.max_w)
        dv, dw = self.acc_v * dt, self.acc_w * dt
        return (self.v + min(max(v_t - self.v, -dv), dv),
                self.w + min(max(w_t - self.w, -dw), dw))

    @staticmethod
    def increment(v: float, w: float, dt: float) -> Tuple[float, float, float]:
        """(dx, dy, dyaw) in the base frame at the step's start: the exact arc."""
        th = w * dt
        if abs(th) < 1e-9:
            return v * dt, 0.0, th
        r = v / w
        return r * np.sin(th), r * (1.0 - np.cos(th)), th


def compose2d(x: float, y: float, yaw: float, dx: float, dy: float, dyaw: float):
    c, s = np.cos(yaw), np.sin(yaw)
    return x + c * dx - s * dy, y + s * dx + c * dy, _wrap(yaw + dyaw)


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


# ------------------------------------------------------------------------------- odometry
class WheelOdometry:
    """Dead reckoning from the true increments with a systematic error and a seeded random walk.

    Per increment of true translation ``d`` (m, along the arc's chord) and rotation ``a`` (rad),
    with the wheels' travel ``s = |d| + wheel_separation / 2 * |a|``: the measured translation is
    ``d * (1 + scale_error) + N(0, noise_lin^2 * s)`` along the chord, the measured rotation
    ``a * (1 + rot_scale_error) + yaw_drift * |d| + N(0, noise_yaw^2 * s)``. The pose starts at
    the identity (the odom frame is the base's start pose).
    """

    def __init__(self, scale_error: float = 0.02, rot_scale_error: float = 0.01,
                 yaw_drift_deg_per_m: float = 1.0, noise_lin: float = 0.01,
                 noise_yaw_deg: float = 0.5, wheel_separation: float = 0.36, seed: int = 0):
        self.scale = 1.0 + float(scale_error)
        self.rot_scale = 1.0 + float(rot_scale_error)
        self.drift = np.deg2rad(float(yaw_drift_deg_per_m))
        self.noise_lin = float(noise_lin)
        self.noise_yaw = np.deg2rad(float(noise_yaw_deg))
        self.half_sep = 0.5 * float(wheel_separation)
        self.rng = np.random.default_rng([int(seed), 4711])
        self.x = self.y = self.yaw = 0.0
        self.v = self.w = 0.0           # measured velocities of the last increment

    def update(self, dx: float, dy: float, dyaw: float, dt: float) -> None:
        d = float(np.hypot(dx, dy))
        s = d + self.half_sep * abs(dyaw)
        n_lin, n_yaw = self.rng.standard_normal(2)   # drawn every step: one stream per seed
        if s <= 0.0:
            self.v = self.w = 0.0
            return
        if d > 0:
            ux, uy = dx / d, dy / d
        else:     # turning in place: wheel noise moves the base along its heading
            ux, uy = np.cos(0.5 * dyaw), np.sin(0.5 * dyaw)
        m = d * self.scale + self.noise_lin * np.sqrt(s) * n_lin
        a = dyaw * self.rot_scale + self.drift * d + self.noise_yaw * np.sqrt(s) * n_yaw
        self.x, self.y, self.yaw = compose2d(self.x, self.y, self.yaw, m * ux, m * uy, a)
        if dt > 0:
            self.v, self.w = (-m if dx < 0 else m) / dt, a / dt

    def matrix(self) -> np.ndarray:
        """T_odom_base."""
        return base_matrix(self.x, self.y, self.yaw)


# ----------------------------------------------------------------------------- collisions
class Footprint:
    """A circle of ``radius`` round base_link, or a polygon (K, 2) in base_link (any simple
    polygon, as move_base's ``footprint``). ``radius`` is then the polygon's bounding radius."""

    def __init__(self, shape):
        if isinstance(shape, (int, float)):
            if not shape > 0:
                raise ConfigError("footprint_radius must be > 0, got %r" % (shape,))
            self.shape = float(shape)
            self.radius = float(shape)
        else:
            P = np.asarray(shape, float)
            if P.ndim != 2 or P.shape[1] != 2 or len(P) < 3 or not np.all(np.isfinite(P)):
                raise ConfigError("footprint must be a list of at least 3 [x, y] points")
            if abs(_signed_area(P)) < 1e-6:
                raise ConfigError("footprint polygon has no area")
            self.shape = P
            self.radius = float(np.linalg.norm(P, axis=1).max())

    @property
    def is_circle(self) -> bool:
        return isinstance(self.shape, float)

    def distance(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """(M,) distances from the footprint to segments A-B ((M, 2) each, in base_link);
        0 where they touch or overlap."""
        if self.is_circle:
            return np.maximum(_point_segment_distance(np.zeros(2), A, B) - self.shape, 0.0)
        V = self.shape
        E0, E1 = V, np.roll(V, -1, axis=0)
        a, b = A[:, None, :], B[:, None, :]
        d = np.minimum.reduce([
            _point_segment_distance(a, E0[None], E1[None]).min(axis=1),
            _point_segment_distance(b, E0[None], E1[None]).min(axis=1),
            _point_segment_distance(V[None], a, b).min(axis=1)])
        cross = _segments_cross(a, b, E0[None], E1[None]).any(axis=1)
        inside = _inside_polygon(A, V) | _inside_polygon(B, V)
        return np.where(cross | inside, 0.0, d)


def parse_footprint(footprint, radius: float) -> Footprint:
    """A :class:`Footprint` from the ``footprint`` parameter (a polygon as a list or its YAML
    text; empty: the circle of ``radius``)."""
    fp = footprint
    if isinstance(fp, str):
        fp = fp.strip()
        if not fp:
            return Footprint(float(radius))
        try:
            fp = yaml.safe_load(fp)
        except yaml.YAMLError as e:
            raise ConfigError("footprint is not a list of [x, y] points: %s" % e)
    if fp is None or (isinstance(fp, (list, tuple)) and len(fp) == 0):
        return Footprint(float(radius))
    try:
        P = np.asarray(fp, float)
    except (TypeError, ValueError):
        raise ConfigError("footprint is not a list of [x, y] points: %r" % (footprint,))
    return Footprint(P)


def _signed_area(P: np.ndarray) -> float:
    return 0.5 * float(np.sum(P[:, 0] * np.roll(P[:, 1], -1) - np.roll(P[:, 0], -1) * P[:, 1]))


def _point_segment_distance(P, A, B) -> np.ndarray:
    """Distances of points P to segments A-B (broadcast over leading axes, last axis 2)."""
    AB = B - A
    AP = P - A
    L2 = np.sum(AB * AB, axis=-1)
    t = np.clip(np.sum(AP * AB, axis=-1) / np.maximum(L2, 1e-18), 0.0, 1.0)
    return np.linalg.norm(AP - t[..., None] * AB, axis=-1)


def _cross2(u, v):
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _segments_cross(A, B, C, D) -> np.ndarray:
    """Segments A-B and C-D cross properly (touching is left to the distances)."""
    d1 = _cross2(D - C, A - C)
    d2 = _cross2(D - C, B - C)
    d3 = _cross2(B - A, C - A)
    d4 = _cross2(B - A, D - A)
    return (d1 * d2 < 0) & (d3 * d4 < 0)


def _inside_polygon(P: np.ndarray, V: np.ndarray) -> np.ndarray:
    """(M,) points P (M, 2) inside the polygon V (K, 2) (crossing number, any simple polygon)."""
    x, y = P[:, 0:1], P[:, 1:2]
    x1, y1 = V[None, :, 0], V[None, :, 1]
    x2, y2 = np.roll(V[:, 0], -1)[None], np.roll(V[:, 1], -1)[None]
    straddle = (y1 > y) != (y2 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
    return (np.count_nonzero(straddle & (x < xi), axis=1) % 2) == 1


class ObstacleMap:
    """The 2-D footprint of a scene's rectangles between ``z_min`` and ``z_max``: each rectangle,
    clipped to that band and projected on the floor, is a segment (walls, box sides, panels) or,
    with an area, a polygon (box tops) whose edges are segments too."""

    def __init__(self, scene: Scene, z_min: float, z_max: float):
        A, B, seg_names, areas = [], [], [], []
        planes = [np.array([0.0, 0.0, 1.0, -float(z_min)]),
                  np.array([0.0, 0.0, -1.0, float(z_max)])]
        for rc in scene.rects:
            poly = _clip_polygon(list(rc.corners()), planes)
            if len(poly) < 2:
                continue
            P = np.array(poly)[:, :2]
            area = abs(_signed_area(P))
            if area > 1e-6:
                areas.append((P, rc.name))
                A.extend(P)
                B.extend(np.roll(P, -1, axis=0))
                seg_names.extend([rc.name] * len(P))
            else:   # vertical: the two points farthest apart
                D = np.linalg.norm(P[:, None] - P[None], axis=-1)
                i, j = np.unravel_index(np.argmax(D), D.shape)
                if D[i, j] < 1e-6:
                    continue
                A.append(P[i])
                B.append(P[j])
                seg_names.append(rc.name)
        self.A = np.array(A, float).reshape(-1, 2)
        self.B = np.array(B, float).reshape(-1, 2)
        self.names = seg_names
        self.areas = areas
        self.lo = np.minimum(self.A, self.B)
        self.hi = np.maximum(self.A, self.B)
        self.area_lo = np.array([P.min(axis=0) for P, _ in areas]).reshape(-1, 2)
        self.area_hi = np.array([P.max(axis=0) for P, _ in areas]).reshape(-1, 2)
        self.z_range = (float(z_min), float(z_max))

    def __len__(self) -> int:
        return len(self.A)

    def nearest(self, footprint: Footprint, x: float, y: float, yaw: float,
                reach: float = np.inf) -> Tuple[float, str]:
        """(distance, name) of the nearest obstacle to the footprint at (x, y, yaw): 0 when it
        overlaps one; ``(inf, "")`` when none is within ``reach`` m of the footprint."""
        r = footprint.radius + (reach if np.isfinite(reach) else 1e9)
        near = np.flatnonzero((self.lo[:, 0] <= x + r) & (self.hi[:, 0] >= x - r) &
                              (self.lo[:, 1] <= y + r) & (self.hi[:, 1] >= y - r))
        for k in np.flatnonzero((self.area_lo[:, 0] <= x) & (self.area_hi[:, 0] >= x) &
                                (self.area_lo[:, 1] <= y) & (self.area_hi[:, 1] >= y)):
            P, name = self.areas[k]
            if _inside_polygon(np.array([[x, y]]), P)[0]:
                return 0.0, name
        if len(near) == 0:
            return np.inf, ""
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, s], [-s, c]])     # map -> base rotation
        o = np.array([x, y])
        d = footprint.distance((self.A[near] - o) @ R.T, (self.B[near] - o) @ R.T)
        k = int(np.argmin(d))
        if d[k] > reach:
            return np.inf, ""
        return float(d[k]), self.names[near[k]]

    def collides(self, footprint: Footprint, x: float, y: float, yaw: float) -> Optional[str]:
        """The name of an obstacle the footprint overlaps at (x, y, yaw), or None."""
        d, name = self.nearest(footprint, x, y, yaw, reach=_EPS)
        return name if d <= _EPS else None

    def clearance(self, footprint: Footprint, x: float, y: float, yaw: float) -> float:
        """Distance from the footprint to the nearest obstacle (0: touching or overlapping)."""
        return self.nearest(footprint, x, y, yaw)[0]


# ---------------------------------------------------------------------------------- robot
@dataclass
class Collision:
    t: float
    x: float
    y: float
    yaw: float
    obstacle: str


class SimRobot:
    """A differential-drive base with a stereo camera on its mast in a simulator scene.

    ``command(vx, vy, wz, t)`` sets the velocity command, ``advance(duration)`` runs the physics
    sub-steps and returns the odometry samples due, ``render(index)`` renders the pair at the
    current pose. Times are seconds of sim time from ``t0``.
    """

    def __init__(self, cfg: Optional[RobotConfig] = None, scene: Optional[Scene] = None,
                 t0: float = 0.0):
        cfg = RobotConfig.of(cfg)
        cfg.validate()
        self.cfg = cfg
        self.scene = scene if scene is not None else make_scene(
            cfg.scene, contrast=cfg.contrast, specular=cfg.specular, seed=cfg.seed)
        height, pitch, start = scene_start(self.scene, cfg.camera_forward)
        self.height = height if cfg.camera_height == "auto" else float(cfg.camera_height)
        self.pitch = pitch if cfg.camera_pitch == "auto" else float(cfg.camera_pitch)
        self.camera = sim_camera(scale=cfg.scale)
        self.T_base_center = mount_transform(self.height, self.pitch, cfg.camera_forward)
        self.layout = camera_layout(cfg.layout, self.T_base_center, self.camera.baseline,
                                    cfg.base_frame, cfg.camera_name)
        self.T_base_cam = self.layout.T_base(self.layout.left_frame, cfg.base_frame)
        self.info_models = raw_calibration(self.camera) if self.layout.raw_info else (
            self.camera.left, self.camera.right)
        self.sim = Simulator(self.scene, self.camera, seed=cfg.seed, noise=cfg.noise)
        self.footprint = parse_footprint(cfg.footprint, cfg.footprint_radius)
        self.obstacles = ObstacleMap(self.scene, cfg.floor_clearance, cfg.body_height)
        self.drive = DiffDrive(cfg.max_vel_x, cfg.min_vel_x, cfg.max_vel_theta, cfg.acc_lim_x,
                               cfg.acc_lim_theta)
        self.odom = WheelOdometry(cfg.odom_scale_error, cfg.odom_rot_scale_error,
                                  cfg.odom_yaw_drift, cfg.odom_noise_lin, cfg.odom_noise_yaw,
                                  cfg.wheel_separation, cfg.seed)
        self.x, self.y, self.yaw = parse_start(cfg.start_pose) if cfg.start_pose else start
        self.yaw = _wrap(self.yaw)
        hit = self.obstacles.collides(self.footprint, self.x, self.y, self.yaw)
        if hit is not None:
            raise ConfigError("the start pose (%.2f, %.2f, %.2f) overlaps %s"
                              % (self.x, self.y, self.yaw, hit))
        self.t = float(t0)
        self.cmd = (0.0, 0.0)
        self.cmd_t = -np.inf
        self.lateral_commands = 0
        self.collisions: List[Collision] = []
        self.in_contact = False
        self.contact_heading = 0.0   # rad in base_link: the direction of the blocked motion
        self.T_odom_contact = np.eye(4)   # the wheel odometry's base pose at the contact
        self.backoff_left = 0.0      # m still to reverse (the safety back-off)
        self.backoff_dir = 0.0       # -1 backwards, +1 forwards
        self.distance = 0.0             # m travelled (true)
        self.n_steps = 0
        self.odom_every = max(1, int(round(cfg.physics_rate / cfg.odom_rate)))

    # --- input
    def command(self, vx: float, vy: float = 0.0, wz: float = 0.0,
                t: Optional[float] = None) -> None:
        """A velocity command (cmd_vel) received at sim time ``t`` (default: now). A
        differential drive cannot move sideways: ``vy`` is ignored, and counted when not 0."""
        vals = (float(vx), float(vy), float(wz))
        if not all(np.isfinite(vals)):
            raise ValueError("velocity command is not finite: %r" % (vals,))
        if abs(vals[1]) > 1e-6:
            self.lateral_commands += 1
        self.cmd = (vals[0], vals[2])
        self.cmd_t = self.t if t is None else float(t)

    # --- physics
    def step(self, dt: float) -> None:
        """One physics sub-step of ``dt`` s."""
        if self.backoff_left > 0:
            v_cmd, w_cmd = self.backoff_dir * self.cfg.backoff_speed, 0.0
        elif self.t - self.cmd_t <= self.cfg.cmd_timeout + 1e-9:
            v_cmd, w_cmd = self.cmd
        else:
            v_cmd, w_cmd = 0.0, 0.0
        v, w = self.drive.limited(v_cmd, w_cmd, dt)
        dx, dy, dyaw = DiffDrive.increment(v, w, dt)
        if dx or dy or dyaw:
            nx, ny, nyaw = compose2d(self.x, self.y, self.yaw, dx, dy, dyaw)
            hit = self.obstacles.collides(self.footprint, nx, ny, nyaw)
            if hit is not None:
                # a bumper stop: the base stays where it was, at rest
                backing = self.backoff_left > 0
                self.backoff_left = 0.0   # a back-off that hits something ends there
                if not self.in_contact:
                    self.collisions.append(Collision(self.t + dt, self.x, self.y, self.yaw, hit))
                    self.in_contact = True
                    if dx or dy:
                        self.contact_heading = float(np.arctan2(dy, dx))
                    self.T_odom_contact = self.odom.matrix()
                    if self.cfg.backoff_distance > 0 and not backing and (dx or dy):
                        self.backoff_left = float(self.cfg.backoff_distance)
                        self.backoff_dir = -1.0 if dx >= 0 else 1.0
                v = w = dx = dy = dyaw = 0.0
            else:
                self.x, self.y, self.yaw = nx, ny, nyaw
                self.distance += float(np.hypot(dx, dy))
                if self.backoff_left > 0:
                    self.backoff_left -= float(np.hypot(dx, dy))
                if self.in_contact and self.obstacles.nearest(
                        self.footprint, nx, ny, nyaw, CONTACT_MARGIN)[0] > CONTACT_MARGIN:
                    self.in_contact = False
        self.drive.v, self.drive.w = v, w
        self.odom.update(dx, dy, dyaw, dt)
        self.t += dt
        self.n_steps += 1

    def advance(self, duration: float) -> List[Tuple[float, np.ndarray, float, float]]:
        """Run ``duration`` s of physics in sub-steps of about 1 / physics_rate; returns the
        odometry due at odom_rate as ``(t, T_odom_base, v, w)`` (measured velocities)."""
        n = max(1, int(round(duration * self.cfg.physics_rate)))
        dt = duration / n
        t0 = self.t
        out = []
        for i in range(n):
            self.step(dt)
            self.t = t0 + (i + 1) * dt     # not a running sum: stamps stay on the frame grid
            if self.n_steps % self.odom_every == 0:
                out.append((self.t, self.odom.matrix(), self.odom.v, self.odom.w))
        return out

    # --- state
    @property
    def velocity(self) -> Tuple[float, float]:
        """True (v, w) of the base."""
        return self.drive.v, self.drive.w

    def bumper_points(self) -> np.ndarray:
        """(N, 3) points in base_link where the base touched something, while it is pressed
        against it or backing off from it (none otherwise): a fan round the blocked motion's
        direction just outside the footprint at the contact, as
        kobuki_bumper2pc turns a bumper press into a cloud for move_base's obstacle layer, which
        then keeps a wall the cameras cannot see (blank, specular) out of the robot's plans."""
        if not (self.in_contact or self.backoff_left > 0):
            return np.zeros((0, 3))
        a = self.contact_heading + BUMPER_SPREAD
        r = self.footprint.radius + BUMPER_OUT
        p = np.column_stack([r * np.cos(a), r * np.sin(a), np.full(len(a), BUMPER_Z),
                             np.ones(len(a))])
        # where the contact was, seen from where the wheels now say the base is
        T = np.linalg.solve(self.odom.matrix(), self.T_odom_contact)
        return (p @ T.T)[:, :3]

    @property
    def n_collisions(self) -> int:
        return len(self.collisions)

    def T_map_base(self) -> np.ndarray:
        return base_matrix(self.x, self.y, self.yaw)

    def T_map_cam(self) -> np.ndarray:
        """The left (rectified) optical frame in map: the simulator bags' ground truth."""
        return camera_pose(self.T_map_base(), self.T_base_cam)

    def clearance(self) -> float:
        return self.obstacles.clearance(self.footprint, self.x, self.y, self.yaw)

    def render(self, index: int) -> Dict[str, np.ndarray]:
        """``left``, ``right`` (uint8) at the current pose; ``index`` seeds the image noise."""
        return self.sim.render(self.T_map_cam(), index=int(index), depth=False)

    def describe(self) -> dict:
        W, H = self.camera.size
        return {"scene": self.scene.name, "seed": self.cfg.seed, "width": W, "height": H,
                "rate": self.cfg.rate, "height_m": self.height, "pitch_rad": self.pitch,
                "start": (self.x, self.y, self.yaw), "layout": self.layout.name,
                "footprint": ("circle r=%.2f" % self.footprint.shape if self.footprint.is_circle
                              else "polygon %d points" % len(self.footprint.shape)),
                "obstacle_segments": len(self.obstacles)}
