"""A simulated robot: a differential-drive base in a simulator scene, with a stereo camera.

Thin shell around :class:`mdr_slam.sim.robot.SimRobot` (kinematics, collisions, odometry and the
camera are there). The node owns sim time: it runs one frame period of physics with the latest
``cmd_vel``, renders the pair at the new pose, publishes everything stamped with that time and
only then advances ``/clock`` to it, so the simulation runs as fast as the CPU renders, capped at
``~real_time_factor`` (sim seconds per wall second; consumers must set ``/use_sim_time``, as
sim_robot.launch does). ``~wait_for_topic`` makes it also wait (up to ``~wait_timeout`` wall s)
for a consumer's output stamped at the frame, e.g. ``mdr/pose``: lockstep with the tracker
(starting once the left image has a subscriber and that topic a publisher).

Topics (relative names; ``~layout`` stereo, else a driver's, see mdr_slam.sim.driver):

- in ``cmd_vel`` (geometry_msgs/Twist): linear.x and angular.z; linear.y is ignored (a
  differential drive) and counted; no command for ``~cmd_timeout`` s: stop;
- ``stereo/{left,right}/image_raw`` (mono8), ``stereo/{left,right}/camera_info``, frames
  ``camera_{left,right}_optical_frame``;
- ``odom`` (nav_msgs/Odometry) and tf ``odom -> base_link`` at ``~odom_rate``: wheel odometry
  with a seeded drift; tf_static ``base_link -> camera_link -> camera_*_optical_frame``;
- ``ground_truth/pose`` (PoseStamped, the left optical frame in ``map``, as the simulator's bags)
  and tf ``map -> ground_truth_camera``; ``ground_truth/odom`` (base_link in ``map``, true twist);
- ``collisions`` (std_msgs/UInt32, latched): contacts of the footprint with the scene so far; each
  one stops the base and is logged;
- ``bumper/points`` (sensor_msgs/PointCloud2 in base_link): while the base is pressed against
  something or backing off from it (``backoff_distance``), points just outside the footprint
  where it touched (a bumper, as kobuki_bumper2pc);
- ``/clock``; ``/diagnostics`` (frames per wall second, render time, real-time factor, collisions).
"""
from __future__ import annotations

import struct
import sys
import threading
import time

import numpy as np
import rospy
import tf2_ros
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, Twist
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import UInt32

from ..config import ConfigError
from ..conversions import (arrays_to_pointcloud2, make_header, matrix_to_pose,
                           matrix_to_pose_stamped, matrix_to_transform_stamped,
                           model_to_camera_info, numpy_to_image)
from ..sim.generate import STAMP0
from ..sim.robot import ODOM_POSE_COV, ODOM_TWIST_COV, RobotConfig, SimRobot
from .common import Throttled
from .health import ProcessHealth, RateWindow

NODE = "sim_robot_node"
CLOCK_RESEND_S = 0.2    # s between re-sends of a held /clock (late subscribers get it)
_POSE_COV = [float(v) for v in np.diag(ODOM_POSE_COV).ravel()]
_TWIST_COV = [float(v) for v in np.diag(ODOM_TWIST_COV).ravel()]


def _time(t: float):
    """rospy.Time of ``t`` s, rounded to the nanosecond (from_sec truncates: 81.9 would be
    stamped 81.899999999)."""
    return rospy.Time(0, int(round(float(t) * 1e9)))


def read_params() -> RobotConfig:
    """The private parameters as a RobotConfig: unknown names and values of the wrong type are
    logged (the default is used); inconsistent values raise ConfigError."""
    defaults = RobotConfig.defaults()
    base = rospy.get_name()
    have = {n[len(base) + 1:].split("/", 1)[0] for n in rospy.get_param_names()
            if n.startswith(base + "/")}
    bad = sorted(have - set(defaults))
    if bad:
        rospy.logerr("%s: unknown parameters %s are not read (typo?)", NODE,
                     ", ".join("~" + k for k in bad))
    values = {}
    for k, v in defaults.items():
        val = rospy.get_param("~" + k, v)
        try:
            RobotConfig.from_dict({k: val})
            values[k] = val
        except ConfigError as e:
            rospy.logerr("%s: ~%s: %s; using the default %r", NODE, k, e, v)
    cfg = RobotConfig.from_dict(values)
    cfg.validate()
    return cfg


def header_stamp(msg) -> float:
    """The header stamp (s) of a rospy.AnyMsg whose type starts with a std_msgs/Header; None
    for other types."""
    import genpy.message
    cls = genpy.message.get_message_class(msg._connection_header.get("type", ""))
    if cls is None or not cls._slot_types or cls._slot_types[0] != "std_msgs/Header":
        return None
    secs, nsecs = struct.unpack_from("<II", msg._buff, 4)   # after the uint32 seq
    return secs + 1e-9 * nsecs


class SimRobotNode:
    def __init__(self, cfg: RobotConfig):
        self.cfg = cfg
        self.robot = SimRobot(cfg, t0=STAMP0)
        self.lay = self.robot.layout
        self.warn = Throttled()
        self.lock = threading.Lock()         # the robot: cmd_vel callbacks vs the sim loop
        self.cv = threading.Condition()      # the consumer's newest stamp
        self.consumer_stamp = -np.inf
        self.consumer_timeouts = 0
        self.health = ProcessHealth()
        self.fps = RateWindow(10.0)
        self.render_cpu_ms = 0.0             # running mean
        self.frames = 0
        self.wall_start = None
        self.sim_start = self.robot.t
        lay = self.lay
        self.pub_img = (rospy.Publisher(lay.left_image, Image, queue_size=2),
                        rospy.Publisher(lay.right_image, Image, queue_size=2))
        self.pub_info = (rospy.Publisher(lay.left_info, CameraInfo, queue_size=2),
                         rospy.Publisher(lay.right_info, CameraInfo, queue_size=2))
        self.pub_odom = rospy.Publisher("odom", Odometry, queue_size=50)
        self.pub_gt = rospy.Publisher("ground_truth/pose", PoseStamped, queue_size=10)
        self.pub_gt_odom = rospy.Publisher("ground_truth/odom", Odometry, queue_size=10)
        self.pub_collisions = rospy.Publisher("collisions", UInt32, queue_size=1, latch=True)
        self.pub_bumper = rospy.Publisher("bumper/points", PointCloud2, queue_size=2)
        self.pub_clock = rospy.Publisher("/clock", Clock, queue_size=10)
        self.pub_diag = rospy.Publisher("/diagnostics", DiagnosticArray, queue_size=5)
        self.tf = tf2_ros.TransformBroadcaster()
        self.tf_static = tf2_ros.StaticTransformBroadcaster()
        rospy.Subscriber("cmd_vel", Twist, self.on_cmd, queue_size=10)
        self.consumer = None
        if cfg.wait_for_topic:
            self.consumer = rospy.Subscriber(cfg.wait_for_topic, rospy.AnyMsg, self.on_consumer,
                                             queue_size=10)
        if not rospy.get_param("/use_sim_time", False):
            rospy.logwarn("%s: /use_sim_time is not set: nodes on wall time do not follow this "
                          "node's /clock (sim_robot.launch sets it)", NODE)
        d = self.robot.describe()
        rospy.loginfo("%s: %s (seed %d), %dx%d pair at %.3g Hz on %s, camera %.2f m up, %.2f rad "
                      "down; base at (%.2f, %.2f, %.2f rad), footprint %s; real-time factor cap "
                      "%s", NODE, d["scene"], d["seed"], d["width"], d["height"], d["rate"],
                      rospy.resolve_name(lay.left_image), d["height_m"], d["pitch_rad"],
                      *d["start"], d["footprint"],
                      "none" if cfg.real_time_factor <= 0 else "%.3g" % cfg.real_time_factor)

    # --- input
    def on_cmd(self, msg: Twist) -> None:
        try:
            with self.lock:
                self.robot.command(msg.linear.x, msg.linear.y, msg.angular.z)
        except ValueError as e:
            self.warn("cmd", "%s: cmd_vel ignored: %s" % (NODE, e))

    def on_consumer(self, msg) -> None:
        t = header_stamp(msg)
        if t is None:
            self.warn("consumer", "%s: ~wait_for_topic %s has no header stamp: not waited for"
                      % (NODE, self.cfg.wait_for_topic))
            return
        with self.cv:
            if t > self.consumer_stamp:
                self.consumer_stamp = t
                self.cv.notify_all()

    # --- output
    def publish_static(self) -> None:
        stamp = _time(self.robot.t)
        self.tf_static.sendTransform([matrix_to_transform_stamped(T, stamp, p, c)
                                      for p, c, T in self.lay.static])

    def publish_frame(self, t: float, pair, odometry) -> None:
        cfg, r, lay = self.cfg, self.robot, self.lay
        stamp = _time(t)
        if pair is not None:
            for side, frame in ((0, lay.left_frame), (1, lay.right_frame)):
                img = pair["left" if side == 0 else "right"]
                if lay.encoding == "bgr8":   # equal channels: consumers' grey is the rendered one
                    img = np.repeat(img[:, :, None], 3, axis=2)
                self.pub_img[side].publish(numpy_to_image(img, lay.encoding, stamp, frame))
                self.pub_info[side].publish(model_to_camera_info(r.info_models[side], stamp,
                                                                 frame))
        tfs = []
        for ts, T, v, w in odometry:
            st = _time(ts)
            msg = Odometry()
            msg.header = make_header(st, cfg.odom_frame)
            msg.child_frame_id = cfg.base_frame
            msg.pose.pose = matrix_to_pose(T)
            msg.pose.covariance = _POSE_COV
            msg.twist.twist.linear.x = float(v)
            msg.twist.twist.angular.z = float(w)
            msg.twist.covariance = _TWIST_COV
            self.pub_odom.publish(msg)
            if cfg.publish_tf:
                tfs.append(matrix_to_transform_stamped(T, st, cfg.odom_frame, cfg.base_frame))
        T_cam = r.T_map_cam()
        self.pub_gt.publish(matrix_to_pose_stamped(T_cam, stamp, cfg.map_frame))
        if cfg.ground_truth_frame:
            tfs.append(matrix_to_transform_stamped(T_cam, stamp, cfg.map_frame,
                                                   cfg.ground_truth_frame))
        if tfs:
            self.tf.sendTransform(tfs)
        gt = Odometry()
        gt.header = make_header(stamp, cfg.map_frame)
        gt.child_frame_id = cfg.base_frame
        gt.pose.pose = matrix_to_pose(r.T_map_base())
        gt.twist.twist.linear.x, gt.twist.twist.angular.z = (float(x) for x in r.velocity)
        self.pub_gt_odom.publish(gt)

    def publish_collisions(self) -> None:
        self.pub_collisions.publish(UInt32(self.robot.n_collisions))

    def publish_diagnostics(self) -> None:
        r = self.robot
        wall = max(time.monotonic() - self.wall_start, 1e-6)
        st = DiagnosticStatus(name="%s: robot" % rospy.get_name().lstrip("/"),
                              hardware_id=r.scene.name)
        st.level = DiagnosticStatus.WARN if r.in_contact else DiagnosticStatus.OK
        st.message = "in contact with %s" % r.collisions[-1].obstacle if r.in_contact else \
            "%d collisions" % r.n_collisions
        vals = {"frames": str(self.frames),
                "frames_per_wall_s": "%.2f" % self.fps.rate(),
                "render_cpu_ms": "%.1f" % self.render_cpu_ms,
                "real_time_factor": "%.3f" % ((r.t - self.sim_start) / wall),
                "sim_time": "%.3f" % r.t,
                "collisions": str(r.n_collisions),
                "in_contact": str(r.in_contact).lower(),
                "lateral_commands": str(r.lateral_commands),
                "distance_m": "%.3f" % r.distance,
                "x": "%.3f" % r.x, "y": "%.3f" % r.y, "yaw": "%.4f" % r.yaw,
                "consumer_timeouts": str(self.consumer_timeouts),
                "cpu_percent": "%.1f" % self.health.cpu_percent(),
                "rss_mb": "%.1f" % self.health.rss_mb()}
        st.values = [KeyValue(k, v) for k, v in vals.items()]
        arr = DiagnosticArray()
        arr.header = make_header(_time(r.t))
        arr.status = [st]
        self.pub_diag.publish(arr)

    def wait_for_connections(self) -> None:
        """Lockstep starts once the consumer is there: it subscribes to the left image and
        publishes ~wait_for_topic (no frame is lost before it listens). The clock is re-sent
        meanwhile for nodes that start later."""
        t0 = time.monotonic()
        told = False
        while not rospy.is_shutdown() and not (self.pub_img[0].get_num_connections() > 0 and
                                               self.consumer.get_num_connections() > 0):
            if not told and time.monotonic() - t0 > 5.0:
                told = True
                rospy.loginfo("%s: waiting for a subscriber of %s and a publisher of %s", NODE,
                              rospy.resolve_name(self.lay.left_image), self.consumer.name)
            self.pub_clock.publish(Clock(_time(self.robot.t)))
            time.sleep(CLOCK_RESEND_S)

    def wait_for_consumer(self, t: float) -> None:
        """Hold the clock at ``t`` until the consumer has answered the frame stamped ``t``,
        re-sending it (as rosbag play does while paused) for subscribers that connect now."""
        deadline = time.monotonic() + self.cfg.wait_timeout
        resend = time.monotonic() + CLOCK_RESEND_S
        with self.cv:
            while self.consumer_stamp < t - 1e-6 and not rospy.is_shutdown():
                now = time.monotonic()
                rest = deadline - now
                if rest <= 0:
                    self.consumer_timeouts += 1
                    return
                if now >= resend:
                    resend = now + CLOCK_RESEND_S
                    self.pub_clock.publish(Clock(_time(t)))
                self.cv.wait(min(rest, 0.1))

    # --- the loop
    def run(self) -> None:
        cfg, r = self.cfg, self.robot
        period = 1.0 / cfg.rate
        wall_step = period / cfg.real_time_factor if cfg.real_time_factor > 0 else 0.0
        self.publish_static()
        self.publish_collisions()
        self.pub_clock.publish(Clock(_time(r.t)))
        self.publish_frame(r.t, None, [(r.t, r.odom.matrix(), 0.0, 0.0)])
        if self.consumer is not None:
            self.wait_for_connections()
        self.wall_start = deadline = last_diag = last_log = time.monotonic()
        n_coll = 0
        while not rospy.is_shutdown():
            with self.lock:
                odometry = r.advance(period)
            c0 = time.process_time()
            pair = r.render(self.frames)
            cpu = (time.process_time() - c0) * 1e3
            self.frames += 1
            self.render_cpu_ms += (cpu - self.render_cpu_ms) / min(self.frames, 50)
            self.publish_frame(r.t, pair, odometry)
            bump = r.bumper_points()
            if len(bump):
                self.pub_bumper.publish(arrays_to_pointcloud2({}, _time(r.t), cfg.base_frame,
                                                              xyz=bump))
            # sim time reaches the frame only once it is out
            self.pub_clock.publish(Clock(_time(r.t)))
            self.fps.tick()
            if r.n_collisions != n_coll:
                for i, c in enumerate(r.collisions[n_coll:], n_coll + 1):
                    rospy.logwarn("%s: collision %d at t=%.2f s: the base at (%.2f, %.2f, %.2f "
                                  "rad) hit %s and stopped", NODE, i, c.t, c.x, c.y, c.yaw,
                                  c.obstacle)
                n_coll = r.n_collisions
                self.publish_collisions()
            if cfg.wait_for_topic:
                self.wait_for_consumer(r.t)
            now = time.monotonic()
            if now - last_diag >= cfg.diagnostics_period:
                last_diag = now
                self.publish_diagnostics()
            if now - last_log >= 30.0:
                last_log = now
                rospy.loginfo("%s: %d frames, %.1f frames per wall s (render %.0f ms CPU), "
                              "sim/wall %.2f, %d collisions", NODE, self.frames, self.fps.rate(),
                              self.render_cpu_ms, (r.t - self.sim_start) / (now - self.wall_start),
                              r.n_collisions)
            if wall_step > 0:   # never faster than the cap; no catch-up burst after a stall
                deadline += wall_step
                if deadline > now:
                    time.sleep(deadline - now)
                else:
                    deadline = now
        wall = max(time.monotonic() - self.wall_start, 1e-6)
        rospy.loginfo("%s: stopped after %d frames in %.1f wall s (%.2f frames per wall s, "
                      "sim/wall %.2f), %.2f m driven, %d collisions, %d lateral commands ignored",
                      NODE, self.frames, wall, self.frames / wall, (r.t - self.sim_start) / wall,
                      r.distance, r.n_collisions, r.lateral_commands)


def main():
    rospy.init_node("sim_robot")
    try:
        node = SimRobotNode(read_params())
    except (ConfigError, ValueError) as e:
        rospy.logfatal("%s: cannot start: %s", NODE, e)
        sys.exit(2)
    node.run()
