"""Node 1: pose estimation. Publishes /mdr/pose, /mdr/odom, /mdr/path and tf (REP-105).

``~source``: ``orb`` (ORB-SLAM2-style stereo tracking from mdr_slam.pose) or ``groundtruth``
(relay a ground-truth PoseStamped of the left camera optical frame in ``map``, e.g. the simulator's
``/ground_truth/pose``, so depth and fusion can be developed and measured without tracking error).
With ``orb``, a saved map can be loaded and reused (``~load_map``, ``~localization``; services
``~save_map``, ``~load_map``, ``~reset`` and ``/initialpose``: nodes/pose_map_services.py).
"""
from __future__ import annotations

import dataclasses
import os
import threading
import time
from collections import deque

import diagnostic_updater
import numpy as np
import rospy
import tf2_ros
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from mdr_slam_msgs.msg import KeyFrame, KeyFrameArray, TrackingState
from mdr_slam_msgs.srv import SaveTrajectory, SaveTrajectoryResponse
from nav_msgs.msg import Odometry, Path

from ..calib import load_stereo_calibration
from ..camera import CalibrationError, StereoCamera, images_are_rectified
from ..conversions import (ConversionError, camera_info_to_model, image_msg_to_mono8 as to_mono8,
                           matrix_to_pose, matrix_to_pose_stamped, matrix_to_transform_stamped,
                           pose_stamped_to_matrix, transform_stamped_to_matrix)
from ..geometry import base_to_camera, body_twist, inv_T, is_valid_T, rotation_angle
from ..io.map_dir import MapPathError, resolve_map_path
from ..io.trajectory import write_kitti_poses, write_tum
from ..pose import System, TrackerConfig, make_system
from ..pose.factory import limit_library_threads
from ..pose.map_io import PoseMapError
from ..pose.odometry_calibration import MIN_TRAVEL_M
from .common import (ClockWatch, StampGuard, Throttled, frame_root, read_config,
                     skip_future_stamp, transform_listener)
from .config import NODE_CONFIGS, PoseNodeConfig
from .health import ProcessHealth, RateWindow, update_diagnostics
from .pose_map_services import PoseMapServices
from .stereo_input import StereoInput

STAGE_WINDOW = 200           # frames the diagnostics' per-stage median times are taken over
# the pose node's stages: waiting for the wheel odometry at the image stamp, the Frame (ORB on
# both images, stereo matching), tracking proper, and its wait for the map lock (bundle
# adjustment, loop correction) within it
STAGES = ("odometry_wait", "frame", "tracking", "tracking_cpu", "map_lock_wait")
PATH_MAX_LENGTH = 100000    # /mdr/path keeps at most this many poses (the oldest go)
PATH_PERIOD = 0.5           # s: /mdr/path at most this often (its size grows with the run)
PATH_MIN_TRANSLATION = 0.05  # m: a pose joins /mdr/path once the camera moved this far ...
PATH_MIN_ROTATION_DEG = 5.0  # ... or turned this much since the last one
PIPELINE_FRAMES = True      # make frame N+1 (ORB, stereo) while frame N is being tracked
DEFAULT_CAMERA_FRAME = "camera_left_optical_frame"   # the simulator's; when nothing names one
BASE_TF_WAIT = 1.0        # s (wall) from the first result, waiting for tf base <- camera before a
                          # fallback (tracking goes on; its results are published once known) ...
BASE_TF_WAIT_GIVEN = 0.2  # ... and when ~base_to_camera gives one (then tf is only checked)
HELD_POLL = 0.05          # s: how often a tracking thread without frames looks for that transform
MAP_ODOM_RATE = 20.0      # Hz: map -> odom re-sent with wheel odometry, so tf stays valid while
                          # tracking is LOST or the camera stalls ...
MAP_ODOM_AHEAD = 0.25     # s: ... future-dated by this (amcl's transform_tolerance): more than a
                          # resend period plus one step of a stepping sim clock (a 10 Hz /clock)
ODOM_LOOKUP_TIMEOUT = 0.05  # s to wait for the robot's odom -> base_link at an image stamp
# /mdr/odom covariance (the README's topic table): the tracker's pose is good to about a
# centimetre and half a degree on the project's sequences (ATE 0.2-1 % of the path); twist from
# consecutive poses, whose difference doubles the variance over one frame period
POSE_STD_M = 0.02
POSE_STD_RAD = 0.01
TWIST_STD_MPS = 0.05
TWIST_STD_RADPS = 0.05


def _covariance(std_lin: float, std_ang: float):
    c = np.zeros((6, 6))
    c[:3, :3] = np.eye(3) * std_lin ** 2
    c[3:, 3:] = np.eye(3) * std_ang ** 2
    return c.ravel().tolist()


class PoseRelay:
    """Publishes a camera pose stream as pose, odometry, path and tf (map -> odom -> base_link).

    Frames follow REP-105 and the data: the camera frame is the image's frame_id, base -> camera
    comes from tf (a URDF, robot_state_publisher, a bag's /tf_static); only when tf has none is
    ``base_to_camera`` (else identity) published, attached to the root of the camera's tree so
    no frame gets a second parent. With a robot publishing odom -> base_link (wheel odometry),
    only map -> odom = T_map_base(t) T_odom_base(t)^-1 is published, at the image stamp and
    re-sent at MAP_ODOM_RATE; otherwise map -> odom (loop-closure jumps) and odom -> base_link.
    """

    def __init__(self, p: PoseNodeConfig):
        self.p = p
        self.T_base_cam = None             # known once the camera frame is resolved in tf
        self.camera_frame = None
        self._camera_deadline = None       # monotonic end of the wait for it in tf
        self.pub_pose = rospy.Publisher("mdr/pose", PoseStamped, queue_size=10)
        self.pub_odom = rospy.Publisher("mdr/odom", Odometry, queue_size=10)
        self.pub_path = rospy.Publisher("mdr/path", Path, queue_size=1, latch=True)
        self.tf = tf2_ros.TransformBroadcaster() if p.publish_tf else None
        self.static_tf = tf2_ros.StaticTransformBroadcaster() if p.publish_tf else None
        self.path = Path()
        self.path.header.frame_id = p.map_frame
        self._path_sent = -1e9             # monotonic time of the last /mdr/path
        self._path_dirty = False
        self._path_last = None             # T_map_cam of the last pose put on /mdr/path
        self._path_lock = threading.Lock()   # the timer thread publishes it too
        if PATH_PERIOD > 0:   # the last poses of a burst go out too
            self._path_timer = rospy.Timer(rospy.Duration(PATH_PERIOD),
                                           lambda _e: self._flush_path(), reset=True)
        self.guard = StampGuard()
        self.clock = ClockWatch()          # ROS time jumping back (bag loop): a new timeline
        self.warn = Throttled()
        mode = str(p.publish_odom_tf).lower()
        if mode not in ("auto", "true", "false"):
            rospy.logerr("pose_node: ~publish_odom_tf is auto, true or false, not %r: auto", mode)
            mode = "auto"
        self.odom_mode = mode
        self.wheel_odom = False            # the robot's odometry owns odom -> base_link
        self._last_odom_pose = None        # (stamp s, T_map_base) for the twist
        self._last_map_odom = None         # T_map_odom re-sent by the timer (wheel odometry)
        self._ahead_stamp = None           # stamp of the last future-dated map -> odom
        self.tf_buffer = tf2_ros.Buffer(cache_time=rospy.Duration(30.0))
        self.tf_listener = transform_listener(self.tf_buffer, float(p.max_future_stamp),
                                              self.warn, "pose_node", self._on_tf)
        if self.tf is not None:
            self._map_odom_timer = rospy.Timer(rospy.Duration(1.0 / MAP_ODOM_RATE),
                                               self._resend_map_odom, reset=True)
        self._init_diagnostics()

    # ------------------------------------------------------------------ frames
    def _on_tf(self, tr, authority: str) -> None:
        """The robot's odometry publishes odom -> base_link: leave it that transform."""
        if self.wheel_odom or self.odom_mode != "auto":
            return
        if tr.header.frame_id.lstrip("/") == self.p.odom_frame and \
                tr.child_frame_id.lstrip("/") == self.p.base_frame and \
                authority != rospy.get_name():
            self.wheel_odom = True
            rospy.loginfo("pose_node: %s publishes %s -> %s (wheel odometry): publishing only "
                          "%s -> %s", authority, self.p.odom_frame, self.p.base_frame,
                          self.p.map_frame, self.p.odom_frame)

    def resolve_camera(self, frame: str, wait: bool = True) -> bool:
        """Find T_base_cam for the camera frame ``frame`` (True once known). tf first, for up to
        BASE_TF_WAIT s from the first call (a bag's /tf_static, robot_state_publisher starting);
        without it the user's ``base_to_camera`` or identity is published, from base to the root
        of the camera's tree. ``wait`` False: one look, False while the wait lasts."""
        if self.T_base_cam is not None:
            if frame != self.camera_frame:
                self.warn("camframe", "pose_node: image frame_id %r differs from %r (the first "
                          "one's); kept %r" % (frame, self.camera_frame, self.camera_frame))
            return True
        p = self.p
        base = p.base_frame
        given = bool(str(p.base_to_camera).strip())
        if self._camera_deadline is None:
            self._camera_deadline = time.monotonic() + (BASE_TF_WAIT_GIVEN if given
                                                        else BASE_TF_WAIT)
        while True:
            try:
                ts = self.tf_buffer.lookup_transform(base, frame, rospy.Time(0))
                self.T_base_cam, self.camera_frame = transform_stamped_to_matrix(ts), frame
                rospy.loginfo("pose_node: %s -> %s from tf", base, frame)
                return True
            except (tf2_ros.TransformException, rospy.ROSTimeMovedBackwardsException):
                if time.monotonic() > self._camera_deadline or rospy.is_shutdown():
                    break
                if not wait:
                    return False
                time.sleep(0.05)
        T = base_to_camera(p.base_to_camera)
        root = frame_root(self.tf_buffer, frame)
        T_root = np.eye(4)
        if root != frame:   # the camera has a tree of its own (e.g. a driver's): attach its root
            try:
                T_root = transform_stamped_to_matrix(self.tf_buffer.lookup_transform(
                    root, frame, rospy.Time(0)))
            except tf2_ros.TransformException:
                pass
        self.T_base_cam, self.camera_frame = T, frame
        if self.static_tf is not None and root != base:
            self.static_tf.sendTransform(matrix_to_transform_stamped(
                T @ inv_T(T_root), rospy.Time(0), base, root))
        if given:
            rospy.loginfo("pose_node: no tf %s <- %s: publishing %s -> %s from ~base_to_camera",
                          base, frame, base, root)
        else:
            rospy.logwarn(
                "pose_node: no tf %s <- %s and no ~base_to_camera: assuming a level camera at %s's "
                "origin looking along its x (REP-103), published as %s -> %s. %s Give the mount "
                "(URDF, or ~base_to_camera \"x y z qx qy qz qw\") for the map's floor and the "
                "grid's obstacle heights.", base, frame, base, base, root,
                "map is the ground truth's frame." if p.source == "groundtruth" else
                "map is z-up at %s where tracking starts, i.e. at the camera's height." % base)
        return True

    def from_the_future(self, t: float, what: str) -> bool:
        """A message stamped ahead of the clock (the old lap's last ones after a bag loop): its
        pose would go out into the new lap's tf as a stale entry. Skipped."""
        return skip_future_stamp(t, float(self.p.max_future_stamp), self.warn, what)

    # ------------------------------------------------------------------ diagnostics
    def _init_diagnostics(self) -> None:
        """/diagnostics "pose_node: pose": rate, latency, drops, tracking state, CPU, RSS."""
        self.health = ProcessHealth()
        self.rate = RateWindow(10.0)
        self.n_published = 0
        self.last_latency = float("nan")
        # per-stage wall ms of the last STAGE_WINDOW frames (OrbNode): where a slow frame's time went
        self.stages = {k: deque(maxlen=STAGE_WINDOW) for k in STAGES}
        self.tracking = {"state": "GROUNDTRUTH" if self.p.source == "groundtruth"
                         else "NOT_INITIALIZED", "time_ms": float("nan"), "lost": 0,
                         "keyframes": 0, "loop_closures": 0, "visual_odometry": 0, "odom_refused": 0,
                         "last_ok": None}
        self.sparse_map_points = None      # OrbNode: () -> points of its sparse map, or None
        self._sparse_last = None
        self.diag = diagnostic_updater.Updater()
        self.diag.setHardwareID("mdr_slam")
        self.diag.add("pose", self.diagnostics)
        self.diag_timer = rospy.Timer(rospy.Duration(float(self.p.diagnostics_period)),
                                      lambda _e: update_diagnostics(self.diag), reset=True)

    def note_tracking(self, res) -> None:
        """Record one tracking result (OrbNode) for the diagnostics."""
        t = self.tracking
        track_ms = getattr(res, "track_ms", None)
        if track_ms is not None:
            frame_ms = float(getattr(res, "frame_ms", 0.0) or 0.0)
            self.note_stage("frame", frame_ms)
            self.note_stage("tracking", float(track_ms) - frame_ms)
            # CPU of the tracking thread: below the wall time, the thread waited (the GIL, a
            # loaded machine); as high, the work itself is slower
            self.note_stage("tracking_cpu", float(getattr(res, "track_cpu_ms", 0.0) or 0.0))
            self.note_stage("map_lock_wait", float(getattr(res, "lock_wait_ms", 0.0) or 0.0))
        t["state"], t["time_ms"] = str(res.state), float(res.time_ms)
        t["keyframes"], t["loop_closures"] = int(res.n_keyframes), int(res.n_loop_closures)
        t["visual_odometry"] = int(getattr(res, "n_visual_odometry", 0))
        t["odom_refused"] = int(getattr(res, "n_odom_refused", 0))
        refusal = getattr(res, "odom_refusal", None)
        if refusal is not None:
            self.warn("odomrefused", "pose_node: a pose %.2f m / %.0f deg from where the wheel "
                      "odometry puts the camera (%.2f m travelled since the last tracked frame, "
                      "%d points) was refused at %.3f (the %s check)"
                      % (*refusal[:4], res.stamp, refusal[4] if len(refusal) > 4 else "odometry"))
        if res.state == "LOST":
            t["lost"] += 1
        elif res.T_map_cam is not None:
            t["last_ok"] = rospy.Time.now()
        if getattr(res, "odometry_errors", None) is not None:
            before = t.get("odometry_errors")
            t["odometry_errors"] = res.odometry_errors
            if res.odometry_errors[3] >= MIN_TRAVEL_M and (before is None or
                                                           before[3] < MIN_TRAVEL_M):
                rospy.loginfo("pose_node: wheel odometry fitted over %.1f m tracked (scale %.4f, "
                              "rotation scale %+.4f, yaw drift %+.3f deg/m): while LOST, map -> "
                              "odom follows the corrected odometry", res.odometry_errors[3],
                              *res.odometry_errors[:3])

    def note_stage(self, stage: str, ms: float) -> None:
        """One frame's ms in ``stage`` (STAGES: wall time, but tracking_cpu) for the diagnostics'
        medians."""
        self.stages[stage].append(float(ms))

    def diagnostics(self, stat):
        t = self.tracking
        rate = self.rate.rate()
        level, text = DiagnosticStatus.OK, "tracking %s" % t["state"]
        if not self.n_published:
            level, text = DiagnosticStatus.WARN, "no pose published yet (%s)" % t["state"]
        elif t["state"] == "LOST":
            level = DiagnosticStatus.WARN
        elif rate == 0:
            level, text = DiagnosticStatus.WARN, "no pose in the last 10 s"
        stat.summary(level, text)
        stat.add("tracking_state", t["state"])
        stat.add("rate_hz", "%.2f" % rate)
        stat.add("latency_s", "%.3f" % self.last_latency)       # image (or input pose) stamp -> published
        stat.add("poses_published", str(self.n_published))
        stat.add("drops", str(sum(v for k, v in self.warn.counts.items()
                                  if k not in ("back", "calib_change", "odomrefused"))))
        stat.add("tracking_time_ms", "%.1f" % t["time_ms"])
        for k in STAGES:   # medians over the last STAGE_WINDOW frames
            ms = self.stages[k].copy()   # one C call: the other threads append meanwhile
            if ms:
                stat.add("median_ms: " + k, "%.1f" % float(np.median(ms)))
        stat.add("frames_dropped_busy", str(self.warn.counts.get("busy", 0)))   # newest kept
        stat.add("frames_lost", str(t["lost"]))
        stat.add("keyframes", str(t["keyframes"]))   # alive: culled ones are not counted
        stat.add("loop_closures", str(t["loop_closures"]))
        n = self.sparse_map_points() if self.sparse_map_points is not None else None
        self._sparse_last = n if n is not None else self._sparse_last
        if self._sparse_last is not None:
            stat.add("sparse_map_points", str(self._sparse_last))
        # tracked frame to frame where the map did not cover the view (fast turns, mapping behind)
        stat.add("frames_visual_odometry", str(t["visual_odometry"]))
        stat.add("poses_refused_by_odometry", str(t["odom_refused"]))
        stat.add("last_tracked_s_ago", "%.2f" % ((rospy.Time.now() - t["last_ok"]).to_sec()
                                                  if t["last_ok"] is not None else float("nan")))
        if t.get("odometry_errors") is not None:   # the wheel odometry's fitted errors
            sc, rs, dr, m = t["odometry_errors"]
            stat.add("wheel_odometry_fit", "scale %.4f, rotation scale %+.4f, yaw drift %+.3f "
                     "deg/m, over %.1f m tracked%s" % (sc, rs, dr, m, "" if m >= MIN_TRAVEL_M
                                                       else " (not applied yet)"))
        for k, v in sorted(self.warn.counts.items()):
            stat.add("skipped: " + k, str(v))
        self.health.add_to(stat)
        return stat

    def _flush_path(self, throttled: bool = False) -> None:
        """Publish /mdr/path when it changed, at most every ``PATH_PERIOD`` s when throttled
        (serializing thousands of poses on every frame would cost the tracker its CPU)."""
        with self._path_lock:
            now = time.monotonic()
            if not self._path_dirty or (throttled and now - self._path_sent <
                                        PATH_PERIOD):
                return
            self._path_dirty = False
            self._path_sent = now
            self.pub_path.publish(self.path)

    def _path_step(self, T: np.ndarray) -> bool:
        """True when ``T`` is far enough from the last pose of /mdr/path to join it: the message
        is re-sent whole, so one pose per frame would make it grow with time (a standing robot)
        instead of with the path (36 k poses after 30 min at 20 Hz, re-serialized every period)."""
        last = self._path_last
        if last is not None:
            moved = float(np.linalg.norm(T[:3, 3] - last[:3, 3]))
            turned = np.degrees(rotation_angle(last[:3, :3].T @ T[:3, :3]))
            if moved < PATH_MIN_TRANSLATION and \
                    turned < PATH_MIN_ROTATION_DEG:
                return False
        self._path_last = T.copy()
        return True

    def _odom_base_at(self, stamp, warn: bool = True):
        """The robot's T_odom_base at ``stamp`` (None, with a warning, when tf has none). Waits
        up to ODOM_LOOKUP_TIMEOUT s of wall time: a sim clock that stops (the bag ends) must not
        hold the tracking thread."""
        deadline = time.monotonic() + ODOM_LOOKUP_TIMEOUT
        while True:
            try:
                return transform_stamped_to_matrix(self.tf_buffer.lookup_transform(
                    self.p.odom_frame, self.p.base_frame, stamp))
            except (tf2_ros.TransformException, rospy.ROSTimeMovedBackwardsException) as e:
                if time.monotonic() > deadline or rospy.is_shutdown():
                    if not warn:
                        return None
                    self.warn("odomtf", "pose_node: no %s <- %s at %.3f (%s); map -> odom kept"
                              % (self.p.odom_frame, self.p.base_frame, stamp.to_sec(),
                                 str(e).splitlines()[0] if str(e) else type(e).__name__))
                    return None
            time.sleep(0.005)

    def odom_camera_at(self, stamp):
        """T_odom_cam at ``stamp`` from the robot's wheel odometry (the tracker's motion between
        frames), or None: no wheel odometry, camera not resolved yet, or tf has none there."""
        if not self.wheel_odom or self.T_base_cam is None:
            return None
        T = self._odom_base_at(stamp, warn=False)
        return None if T is None else T @ self.T_base_cam

    def _resend_map_odom(self, _event=None) -> None:
        """Wheel odometry: the last map -> odom again, future-dated by MAP_ODOM_AHEAD (as amcl
        does), so lookups at the current time succeed while no image is tracked. Not re-sent
        while the clock stands still (a stepping sim clock): tf2 refuses a repeated stamp."""
        T = self._last_map_odom
        if T is None or self.tf is None:
            return
        tr = self._map_odom_ahead(T)
        if tr is not None:
            self.tf.sendTransform(tr)

    def _map_odom_ahead(self, T_map_odom: np.ndarray):
        stamp = rospy.Time.now() + rospy.Duration(MAP_ODOM_AHEAD)
        if stamp == self._ahead_stamp:   # the sim clock has not moved since the last one
            return None
        self._ahead_stamp = stamp
        return matrix_to_transform_stamped(T_map_odom, stamp, self.p.map_frame, self.p.odom_frame)

    def _odometry(self, stamp, T_map_base, T_map_odom):
        """/mdr/odom: the visual pose of base_link with covariance and twist (robot_localization
        reads both). In odom (continuous) without wheel odometry; in map with it, where the
        visual pose is the information the wheels lack."""
        p = self.p
        odom = Odometry()
        odom.header.stamp = stamp
        odom.child_frame_id = p.base_frame
        if self.wheel_odom:
            odom.header.frame_id, T = p.map_frame, T_map_base
        else:
            odom.header.frame_id, T = p.odom_frame, inv_T(T_map_odom) @ T_map_base
        odom.pose.pose = matrix_to_pose(T)
        odom.pose.covariance = _covariance(POSE_STD_M, POSE_STD_RAD)
        t = stamp.to_sec()
        last = self._last_odom_pose
        if last is not None and 0 < t - last[0] < 1.0:
            v, w = body_twist(last[1], T_map_base, t - last[0])
            odom.twist.twist.linear.x, odom.twist.twist.linear.y, odom.twist.twist.linear.z = v
            odom.twist.twist.angular.x, odom.twist.twist.angular.y, odom.twist.twist.angular.z = w
            odom.twist.covariance = _covariance(TWIST_STD_MPS, TWIST_STD_RADPS)
        else:   # no previous pose close in time: the twist is unknown
            odom.twist.covariance = _covariance(1e3, 1e3)
        self._last_odom_pose = (t, T_map_base)
        self.pub_odom.publish(odom)

    def publish(self, stamp, T_map_cam: np.ndarray, T_map_odom: np.ndarray = None) -> None:
        """One camera pose ``T_map_cam`` at ``stamp``. ``T_map_odom``: the tracker's map -> odom
        (loop-closure jumps) when the pose node owns odom -> base_link."""
        p = self.p
        if not is_valid_T(T_map_cam):
            self.warn("nan", "pose at %.3f is not a finite rigid transform; skipped" % stamp.to_sec())
            return
        if self.T_base_cam is None:
            self.warn("nobase", "pose at %.3f before the camera frame is known; skipped"
                      % stamp.to_sec())
            return
        if self.from_the_future(stamp.to_sec(), "pose"):
            return
        state = self.guard.check(stamp.to_sec())
        jumped = self.clock.jumped()
        if state == "backwards" and not jumped:   # the clock goes on: one out-of-order pose
            self.warn("stale", "pose stamp %.3f is older than the last one; skipped" % stamp.to_sec())
            return
        if jumped:
            self.warn("back", "time went backwards (bag loop?); clearing the path")
            with self._path_lock:
                del self.path.poses[:]
            self._path_last = None
            self._last_odom_pose = None
        if state == "duplicate":
            self.warn("dup", "duplicate pose stamp %.3f; skipped" % stamp.to_sec())
            return
        if self.odom_mode == "auto" and not self.wheel_odom and self.tf is not None and \
                self.n_published == 0 and self.tf_buffer.can_transform(
                    p.odom_frame, p.base_frame, stamp):
            self.wheel_odom = True   # tf had it before this node published any: the robot's
        ps = matrix_to_pose_stamped(T_map_cam, stamp, p.map_frame)
        self.pub_pose.publish(ps)
        T_map_base = T_map_cam @ inv_T(self.T_base_cam)
        T_map_odom = np.eye(4) if T_map_odom is None else T_map_odom
        own_odom = not self.wheel_odom and self.odom_mode != "false"
        tfs = []
        if self.wheel_odom:
            T_odom_base = self._odom_base_at(stamp)
            if T_odom_base is not None:
                first = self._last_map_odom is None
                self._last_map_odom = T_map_base @ inv_T(T_odom_base)
                tfs.append(matrix_to_transform_stamped(self._last_map_odom, stamp,
                                                       p.map_frame, p.odom_frame))
                if first:   # valid at the current time now, not only from the timer's next tick
                    ahead = self._map_odom_ahead(self._last_map_odom)
                    if ahead is not None:
                        tfs.append(ahead)
        else:
            tfs.append(matrix_to_transform_stamped(T_map_odom, stamp, p.map_frame,
                                                   p.odom_frame))
            if own_odom:
                tfs.append(matrix_to_transform_stamped(inv_T(T_map_odom) @ T_map_base, stamp,
                                                       p.odom_frame, p.base_frame))
        self._odometry(stamp, T_map_base, T_map_odom)
        if self._path_step(T_map_cam):
            with self._path_lock:
                self.path.header.stamp = stamp
                self.path.poses.append(ps)
                if len(self.path.poses) > PATH_MAX_LENGTH:
                    del self.path.poses[: len(self.path.poses) - PATH_MAX_LENGTH]
                self._path_dirty = True
            self._flush_path(throttled=True)
        if self.tf is not None and tfs:
            self.tf.sendTransform(tfs)
        self.n_published += 1
        self.rate.tick()
        self.last_latency = (rospy.Time.now() - stamp).to_sec()

    def coast(self, stamp, T_map_cam: np.ndarray) -> bool:
        """Tracking LOST with wheel odometry: map -> odom from the pose the tracker carried on by
        the corrected odometry (TrackResult.T_map_cam_coasted), so that map -> base_link follows
        it rather than the raw odometry's drift. Nothing else is published (no pose, path or
        odometry message: the frame was not tracked). False when nothing was sent."""
        if not self.wheel_odom or self.tf is None or self.T_base_cam is None or \
                not is_valid_T(T_map_cam) or self._last_map_odom is None:
            return False
        if self.from_the_future(stamp.to_sec(), "pose"):
            return False
        T_odom_base = self._odom_base_at(stamp, warn=False)
        if T_odom_base is None:
            return False
        self._last_map_odom = T_map_cam @ inv_T(self.T_base_cam) @ inv_T(T_odom_base)
        self.tf.sendTransform([matrix_to_transform_stamped(self._last_map_odom, stamp,
                                                           self.p.map_frame, self.p.odom_frame)])
        return True


class LatestSlot:
    """A mailbox of ``capacity`` frames between the subscriber callbacks and the tracking thread:
    ``put`` on a full box drops the oldest waiting frame (counted), so the tracker never works
    through a backlog of stale frames. capacity 1 (default): always the newest frame; 2-3 absorb
    a slow frame (keyframe, map-lock wait) without a gap, at most that many frames late."""

    def __init__(self, capacity: int = 1):
        self._cv = threading.Condition()
        self._items = deque()
        self.capacity = max(1, int(capacity))
        self._closed = False
        self.dropped = 0

    def put(self, item) -> bool:
        """Store ``item``; True when a frame that was never taken had to go (a drop)."""
        with self._cv:
            dropped = len(self._items) >= self.capacity
            if dropped:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._cv.notify()
            return dropped

    def get(self, timeout=None):
        """The oldest waiting item (waiting up to ``timeout`` s for one), or None (timeout,
        closed)."""
        with self._cv:
            if not self._items and not self._closed:
                self._cv.wait(timeout)
            return self._items.popleft() if self._items else None

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed


_STATE_CODES = {"NOT_INITIALIZED": 0, "OK": 1, "LOST": 2, "RELOCALIZED": 3}
_REASON_CODES = {"new_keyframe": 0, "local_ba": 1, "loop_closure": 2, "full_map": 3}


def _moved(res, D: np.ndarray):
    """``res`` with its map-frame poses moved by ``D`` (a change of the map frame)."""
    def kfs(d):
        return None if d is None else {k: (s, D @ T) for k, (s, T) in d.items()}
    corr = res.corrections
    return dataclasses.replace(
        res, T_map_cam=None if res.T_map_cam is None else D @ res.T_map_cam,
        corrections=None if corr is None else (corr[0], corr[1], kfs(corr[2])),
        new_keyframes=kfs(res.new_keyframes))


class OrbNode(PoseMapServices):
    """``source: orb``: stereo images (+ camera_info or ``calib``) -> mdr_slam.pose.System ->
    PoseRelay (pose, odom, path, tf), /mdr/tracking_state, /mdr/keyframes, ~save_trajectory."""

    def __init__(self, p: PoseNodeConfig, tracker: TrackerConfig, relay: PoseRelay):
        self.p = p
        self.tracker_cfg = tracker
        self.relay = relay
        self.warn = relay.warn
        self.system = None
        relay.sparse_map_points = self._sparse_map_points
        self.camera = None
        self.info_key = None
        self.T_map_odom = np.eye(4)
        self.kf_poses = {}                 # last published T_map_kf per keyframe id
        self.last_stamp = None
        self.last_state = "NOT_INITIALIZED"
        self.n_loops_logged = 0                # loop closures the log has told of
        self.camera_frame_id = None
        # tracking starts before base -> camera is in tf: its results wait here (at most the
        # wait's frames), in a system whose world is the first camera until it is anchored
        self.held = []
        self.planar_logged = False         # planar motion last reported (on/off)
        self.unanchored = None
        self.clock = ClockWatch()          # ROS time jumping back (bag loop): a new timeline
        self.lock = threading.Lock()
        self.pub_state = rospy.Publisher("mdr/tracking_state", TrackingState, queue_size=10)
        self.pub_kfs = rospy.Publisher("mdr/keyframes", KeyFrameArray, queue_size=10, latch=True)
        self.srv = rospy.Service("~save_trajectory", SaveTrajectory, self.on_save)
        self._init_map_files()
        if p.calib:
            self.camera = load_stereo_calibration(p.calib)
            rospy.loginfo("pose_node: calibration from %s (baseline %.4f m)", p.calib,
                          self.camera.baseline)
        # the callbacks only hand the newest pairs to the frame thread (LatestSlot): a pair
        # arriving while it is busy replaces the oldest waiting one instead of queueing. With
        # pipeline_frames that thread makes the Frame (ORB on both images, stereo matching: no map
        # access) and a second slot hands it to the tracking thread, so frame N+1 is extracted
        # while frame N is tracked: the two stages overlap on two cores instead of adding up
        self.slot = LatestSlot(int(p.max_pending))
        self.frames = LatestSlot(int(p.max_pending)) if PIPELINE_FRAMES else None
        self.worker = threading.Thread(
            target=self._serve, name="frames", daemon=True,
            args=(self.slot, self.process, None if PIPELINE_FRAMES else self._idle))
        self.worker.start()
        self.tracker = None
        if self.frames is not None:
            self.tracker = threading.Thread(target=self._serve, name="tracking", daemon=True,
                                            args=(self.frames, self.track, self._idle))
            self.tracker.start()
        self.input = StereoInput("pose_node", self.on_stereo, self.warn,
                                 float(p.sync_tolerance), str(p.image_transport),
                                 with_info=not p.calib, queue_size=int(p.sync_queue_size))
        if self.camera is not None:
            self.camera = self._rectified(self.camera)
        rospy.loginfo("pose_node: ORB tracking on %s + %s", self.input.topics["left"],
                      self.input.topics["right"])

    def _sparse_map_points(self):
        """Points of the sparse map for the diagnostics (None without one: orbslam3's), read
        under the map's lock but not waiting long for it (bundle adjustment may hold it)."""
        mp = getattr(self.system, "map", None)
        lock = getattr(mp, "lock", None)
        if lock is None or not hasattr(mp, "n_points") or not lock.acquire(timeout=0.05):
            return None
        try:
            return int(mp.n_points)
        finally:
            lock.release()

    # ------------------------------------------------------------------ input
    def _rectified(self, cam):
        """``cam``, taken as rectified when the images already are (``rectified`` switch)."""
        if images_are_rectified(self.p.rectified, self.input.topics["left"], cam) and \
                not cam.is_rectified:
            rospy.loginfo("pose_node: %s is rectified already: its camera_info's distortion and "
                          "R are not applied again", self.input.topics["left"])
            return cam.assume_rectified()
        return cam

    def _camera_from_info(self, li, ri):
        key = (tuple(li.K), tuple(li.P), tuple(li.D), tuple(ri.P), li.width, li.height)
        if key != self.info_key:
            try:
                cam = StereoCamera(camera_info_to_model(li), camera_info_to_model(ri))
            except (CalibrationError, ValueError) as e:
                self.warn("calib", "unusable camera_info pair: %s; frame skipped" % e)
                return None
            if self.camera is not None and self.system is not None:
                self.warn("calib_change", "camera_info changed: restarting the tracker")
                with self.lock:   # not while the tracking thread is on a frame
                    self.system.shutdown()
                    self.system = None
            self.camera, self.info_key = self._rectified(cam), key
            if cam.doffs:
                rospy.loginfo("pose_node: the right principal point is %+.3f px from the left's "
                              "(doffs): disparities are measured from it", -cam.doffs)
        return self.camera

    def _to_mono8(self, msg):
        return to_mono8(msg)   # refuses 16UC1/32FC1 (depth images) and malformed data

    def on_stereo(self, left_msg, right_msg, left_info=None, right_info=None):
        if self.relay.from_the_future(left_msg.header.stamp.to_sec(), "stereo"):
            return
        if self.slot.put((left_msg, right_msg, left_info, right_info)):
            self.warn("busy", "tracking busy: the oldest waiting stereo pair was dropped",
                      level="info")

    def _serve(self, slot, handle, idle=None) -> None:
        """A worker thread: ``handle(*item)`` for each item of ``slot`` until it closes; ``idle()``
        when none came (within HELD_POLL s while results are held)."""
        while not slot.closed and not rospy.is_shutdown():
            item = slot.get(timeout=HELD_POLL if idle is not None and self.held else 0.5)
            if item is None:
                if idle is not None:
                    idle()
                continue
            try:
                handle(*item)
            except Exception as e:   # never die on input: log, drop this frame
                self.warn("track", "frame skipped: %r" % (e,), level="err")

    def process(self, left_msg, right_msg, left_info=None, right_info=None):
        """Check and convert one stereo pair and make its Frame (the frame thread); the frame
        goes to the tracking thread (pipeline_frames) or is tracked here."""
        stamp = left_msg.header.stamp
        cam = self.camera if left_info is None else self._camera_from_info(left_info, right_info)
        if cam is None:
            self.warn("nocalib", "no stereo calibration yet; frame skipped")
            return
        try:
            left, right = self._to_mono8(left_msg), self._to_mono8(right_msg)
        except ConversionError as e:
            self.warn("img", "image skipped: %s" % e)
            return
        w, h = cam.size
        if left.shape != (h, w) or right.shape != (h, w):
            self.warn("size", "image sizes %s/%s differ from the calibration %dx%d; skipped"
                      % (left.shape[::-1], right.shape[::-1], w, h))
            return
        frame_id = self.p.camera_frame or left_msg.header.frame_id or DEFAULT_CAMERA_FRAME
        if self.camera_frame_id is None:   # resolved in tf by the tracking thread (publish)
            self.camera_frame_id = frame_id
        t = stamp.to_sec()
        jumped = self.clock.jumped()
        if self.last_stamp is not None and t == self.last_stamp:
            self.warn("dup", "duplicate stereo stamp %.3f; skipped" % t)
            return
        if self.last_stamp is not None and t < self.last_stamp and not jumped:
            self.warn("stale", "stereo stamp %.3f is older than the last one; skipped" % t)
            return   # the clock goes on: one out-of-order pair
        if jumped and self.system is not None:   # ROS time went back: a new timeline
            self.warn("back", "time went backwards (bag loop?): starting a new map")
            with self.lock:   # frames of the old map still waiting are dropped by track()
                self._save_on_exit()
                self._new_session()   # the old timeline's map stays in its session's folder
                self.system.shutdown()
                self.system = None
                self.T_map_odom = np.eye(4)
                self.kf_poses = {}
        self.last_stamp = t
        if self.system is None:
            with self.lock:
                # REP-105: map is base_link where tracking starts (z up for a level robot);
                # without any base -> camera transform, map is the first camera's frame
                args = dict(threads=bool(self.p.threads), T_map_cam0=self.relay.T_base_cam)
                try:
                    self.system = make_system(cam, self.tracker_cfg, **args)
                except (ImportError, OSError, ValueError, RuntimeError) as e:
                    # an optional backend that cannot start must not stop the robot
                    rospy.logerr("pose_node: backend %r unavailable (%s): using the built-in "
                                 "tracker", self.tracker_cfg.backend, e)
                    self.tracker_cfg = self.tracker_cfg.replace(backend="mdr")
                    self.system = System(cam, self.tracker_cfg, **args)
                self._load_start_map(self.system)
                self.unanchored = self.system if self.relay.T_base_cam is None else None
        system = self.system
        left, right = cam.rectify(left, right)
        try:
            frame = system.make_frame(t, left, right)
        except Exception as e:   # never die on input: log, drop this frame
            self.warn("track", "tracking failed on frame %.3f: %r" % (t, e), level="err")
            return
        if hasattr(frame, "T_odom_cam"):   # wheel odometry: the motion model (not ORB-SLAM3's)
            t0 = time.perf_counter()
            frame.T_odom_cam = self.relay.odom_camera_at(stamp)
            if self.relay.wheel_odom:
                self.relay.note_stage("odometry_wait", 1000.0 * (time.perf_counter() - t0))
        if self.frames is None:
            self.track(stamp, system, frame)
        elif self.frames.put((stamp, system, frame)):
            self.warn("busy", "tracking busy: the oldest waiting stereo pair was dropped",
                      level="info")

    def track(self, stamp, system, frame) -> None:
        """Track a made Frame and publish the result (the tracking thread)."""
        with self.lock:
            if system is not self.system:   # a new map began while this frame waited
                return
            try:
                res = system.track(frame.stamp, frame=frame)
            except Exception as e:   # never die on input: log, drop this frame
                self.warn("track", "tracking failed on frame %.3f: %r" % (frame.stamp, e),
                          level="err")
                return
            planar = getattr(getattr(system, "map", None), "planar", None) is not None
            if planar != self.planar_logged:
                rospy.loginfo("pose_node: planar motion %s (planar_motion: %s)" % (
                    "on: base_link's height, roll and pitch held in map" if planar else "off",
                    self.tracker_cfg.planar_motion))
                self.planar_logged = planar
            self.publish(stamp, res)

    # ------------------------------------------------------------------ output
    def publish(self, stamp, res) -> None:
        """Publish a result, or hold it while base -> camera is not yet known (the tracking
        thread, under ``lock``)."""
        if self.held or self.unanchored is not None or self.relay.T_base_cam is None:
            self.held.append((self.system, stamp, res))
            self._release_held()
            return
        self._publish(stamp, res)

    def _release_held(self) -> bool:
        """Once base -> camera is known (or its wait is over): anchor the map and publish the
        held results, moved into it (under ``lock``)."""
        if self.relay.T_base_cam is None and \
                not self.relay.resolve_camera(self.camera_frame_id, wait=False):
            return False
        D = self._anchor()
        held, self.held = self.held, []
        for system, stamp, res in held:
            if system is self.system:   # not those of a map restarted meanwhile
                self._publish(stamp, _moved(res, D))
        return True

    def _idle(self) -> None:
        """The tracking thread without frames: results held for tf go out when its wait ends."""
        if self.held:
            with self.lock:
                if self.held:
                    self._release_held()

    def _anchor(self) -> np.ndarray:
        """Put the map frame where REP-105 wants it once base -> camera is known: the system
        started with its world at the first camera. Returns the change applied to the poses it
        already returned (identity when a loaded map gave the frame)."""
        system, self.unanchored = self.unanchored, None
        if system is None or system is not self.system or getattr(system, "map_loaded", False):
            return np.eye(4)
        old = np.asarray(system.T_map_world, float)
        T = np.asarray(self.relay.T_base_cam, float).copy()
        if hasattr(system, "set_map_frame"):
            system.set_map_frame(T)
        else:
            system.T_map_world = T
        return system.T_map_world @ inv_T(old)

    def _publish(self, stamp, res) -> None:
        st = TrackingState()
        st.header.stamp = stamp
        st.header.frame_id = self.p.map_frame
        st.state = _STATE_CODES.get(res.state, 2)
        st.n_tracked_points = res.n_tracked
        st.n_map_points = res.n_map_points
        st.n_keyframes = res.n_keyframes
        st.current_keyframe_id = res.ref_keyframe_id
        st.n_loop_closures = res.n_loop_closures
        st.tracking_time_ms = res.time_ms
        self.pub_state.publish(st)
        self.relay.note_tracking(res)
        if res.state == "RELOCALIZED" and self.relocalized_at is None and \
                getattr(self.system, "map_loaded", False):
            self.relocalized_at = stamp.to_sec()
            rospy.loginfo("pose_node: relocalized in the loaded map at %.3f", self.relocalized_at)
        self._log_transition(res, stamp.to_sec())
        if res.corrections is not None:
            reason, cid, kfs = res.corrections
            if reason == "loop_closure":
                self._log_loops()
            if reason == "loop_closure" and res.ref_keyframe_id in kfs and \
                    res.ref_keyframe_id in self.kf_poses:
                # the jump goes into map -> odom so odom -> base_link stays continuous (REP-105)
                new = kfs[res.ref_keyframe_id][1]
                self.T_map_odom = new @ inv_T(self.kf_poses[res.ref_keyframe_id]) @ self.T_map_odom
            self.publish_keyframes(stamp, _REASON_CODES.get(reason, 1), cid, kfs)
        if res.is_keyframe and res.T_map_cam is not None:
            self.publish_keyframes(stamp, 0, self.system.correction_id,
                                   {res.keyframe_id: (res.stamp, res.T_map_cam)})
        if getattr(res, "new_keyframes", None):   # orbslam3: keyframes known a frame late
            self.publish_keyframes(stamp, 0, self.system.correction_id, res.new_keyframes)
        if res.T_map_cam is not None:
            self.relay.publish(stamp, res.T_map_cam, self.T_map_odom)
        elif getattr(res, "T_map_cam_coasted", None) is not None:
            self.relay.coast(stamp, res.T_map_cam_coasted)

    def _log_transition(self, res, stamp: float) -> None:
        """One line per change of the tracking state: at most a few per run."""
        if res.state == self.last_state:
            return
        log = rospy.logwarn if res.state == "LOST" else rospy.loginfo
        log("tracking %s -> %s at %.3f (%d points tracked, %d keyframes, %d frames skipped "
            "while busy so far)", self.last_state, res.state, stamp, res.n_tracked,
            res.n_keyframes, self.relay.warn.counts.get("busy", 0))
        self.last_state = res.state

    def _log_loops(self):
        """One line per loop closure (ORB-SLAM2 prints "Loop detected!"): which keyframes and how
        they were found, how far apart along the map's keyframe path, how far the correction
        moved and turned the current keyframe, its checks' figures, and how long tracking
        waited for it."""
        closed = getattr(getattr(self.system, "loop_closing", None), "closed", None)
        if not closed:
            return
        if len(closed) < self.n_loops_logged:   # a new map (reset, load) started a new list
            self.n_loops_logged = 0
        for c in closed[self.n_loops_logged:]:
            checks = ""
            if c["map_check"] is not None:
                checks += "; the loop keyframe's points matched %d -> %d times, moved %.1f px" \
                    % c["map_check"]
            if c["odometry_check"] is not None:
                e0, e1, path = c["odometry_check"][:3]
                a0, a1 = (tuple(c["odometry_check"][3:5]) + (None, None))[:2]
                checks += "; %.2f -> %.2f m%s off the wheel odometry over %.1f m" \
                    % (e0, e1, "" if a0 is None else " (%.1f -> %.1f deg)" % (a0, a1), path)
            if c.get("held_ms") is not None:
                checks += "; tracking waited %.2f s for it (pose graph of %d edges: %.2f s)" \
                    % (c["held_ms"] / 1000.0, c["graph_edges"], c["graph_ms"] / 1000.0)
            rospy.loginfo("pose_node: loop closed at %.3f (%s): keyframe %d with keyframe %d, "
                          "%.1f m of keyframe path apart; the correction moved it %.2f m and "
                          "turned it %.1f deg%s", c["stamp"], c.get("source", "bow"), c["kf"],
                          c["cand"], c["path_m"], c["moved_m"], c["turned_deg"], checks)
        self.n_loops_logged = len(closed)

    def publish_keyframes(self, stamp, reason: int, cid: int, kfs: dict) -> None:
        msg = KeyFrameArray()
        msg.header.stamp = stamp
        msg.header.frame_id = self.p.map_frame
        msg.reason = reason
        msg.correction_id = cid
        for k in sorted(kfs):
            s, T = kfs[k]
            kf = KeyFrame()
            kf.id = int(k)
            kf.stamp = rospy.Time.from_sec(s)
            kf.pose = matrix_to_pose(T)
            msg.keyframes.append(kf)
            self.kf_poses[int(k)] = T
        self.pub_kfs.publish(msg)

    def save_trajectory(self, path: str, fmt: str = ""):
        if self.system is None:
            raise RuntimeError("nothing tracked yet")
        traj = self.system.trajectory()
        fmt = (fmt or ("kitti" if os.path.splitext(path)[1].lower() == ".kitti" else "tum")).lower()
        if fmt not in ("tum", "kitti"):
            raise ValueError("format must be tum or kitti, got %r" % fmt)
        n = (write_kitti_poses if fmt == "kitti" else write_tum)(path, traj)
        return n

    def on_save(self, req):
        """``~save_trajectory``: a path given by the caller resolves inside ``map_dir`` (one
        outside is refused unless ``allow_any_map_path``, as for the map services); none: the
        ``trajectory_path`` parameter (the operator's), else ``trajectory.txt`` in ``map_dir``."""
        try:
            if req.path.strip():
                path = resolve_map_path(req.path, self.map_dir, self.p.allow_any_map_path)
            else:
                path = resolve_map_path(self.p.trajectory_path or "trajectory.txt", self.map_dir,
                                        True)
        except MapPathError as e:
            return SaveTrajectoryResponse(False, str(e), req.path, 0)
        with self.lock:
            try:
                n = self.save_trajectory(path, req.format)
            except Exception as e:
                return SaveTrajectoryResponse(False, str(e), path, 0)
        return SaveTrajectoryResponse(True, "wrote %d poses" % n, path, n)

    def _save_on_exit(self) -> None:
        if self.autosaving and getattr(self.system, "map", None) is not None and \
                self.system.map.keyframes:
            try:
                folder, info, _ = self._autosave(self.system)
                rospy.loginfo("pose_node: saved %d keyframes to %s", info["keyframes"], folder)
            except (PoseMapError, IOError, OSError, ValueError) as e:
                rospy.logerr("pose_node: could not save the sparse map: %s", e)
        if self.p.trajectory_path and self.system is not None:
            try:
                n = self.save_trajectory(self.p.trajectory_path, self.p.trajectory_format)
                rospy.loginfo("pose_node: wrote %d poses to %s", n, self.p.trajectory_path)
            except Exception as e:
                rospy.logerr("pose_node: could not write the trajectory: %s", e)

    def shutdown(self) -> None:
        if self.autosave_timer is not None:
            self.autosave_timer.shutdown()
        self.slot.close()
        self.worker.join(timeout=10.0)
        if self.frames is not None:
            self.frames.close()
            self.tracker.join(timeout=10.0)
        with self.lock:
            self._save_on_exit()
            if self.system is not None:
                self.system.shutdown()
        if self.autosaving:
            self.marker.clear()


def main():
    rospy.init_node("pose_node")
    p, tracker = read_config("pose_node", *NODE_CONFIGS["pose"])
    # one BLAS and one OpenCV thread (mdr_slam.pose.factory says why)
    why = limit_library_threads()
    if why:
        rospy.logwarn("pose_node: BLAS threads not limited: %s", why)
    relay = PoseRelay(p)
    if p.source == "groundtruth":
        def on_gt(msg):
            try:
                T = pose_stamped_to_matrix(msg)
            except ConversionError as e:
                relay.warn("bad", "ground-truth pose skipped: %s" % e)
                return
            if relay.resolve_camera(p.camera_frame or DEFAULT_CAMERA_FRAME):
                relay.publish(msg.header.stamp, T)
        rospy.Subscriber("ground_truth_pose", PoseStamped, on_gt, queue_size=100)
        rospy.loginfo("pose_node: relaying ground truth from %s",
                      rospy.resolve_name("ground_truth_pose"))
    elif p.source == "orb":
        node = OrbNode(p, tracker, relay)
        rospy.on_shutdown(node.shutdown)
    else:
        rospy.logerr("pose_node: unknown ~source %r (orb or groundtruth)", p.source)
    rospy.spin()
