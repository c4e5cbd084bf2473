"""sim_robot_node through sim_robot.launch: a differential-drive base in a simulator scene that
follows cmd_vel, publishes the stereo pair, camera_info, wheel odometry, tf, ground truth and
/clock (it owns sim time), and stops at a wall, counting the collision.

Waits are on events (a message, a count) with generous timeouts: the node renders as fast as a
loaded 2-core machine lets it, capped at real time.
"""
from __future__ import annotations

import threading

import numpy as np
import pytest

from conftest import wait_for
from mdr_slam import conversions as cv
from mdr_slam.geometry import inv_T

pytestmark = [pytest.mark.ros, pytest.mark.slow]

PERIOD = 0.1     # s of sim time per frame (the launch's rate 10)


class Recorder:
    """Every message of the robot's topics, by name, thread-safe."""

    def __init__(self, rospy, ns=""):
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2
        from std_msgs.msg import UInt32
        from tf2_msgs.msg import TFMessage
        self.lock = threading.Lock()
        self.msgs = {}
        topics = {"left": ("stereo/left/image_raw", Image),
                  "right": ("stereo/right/image_raw", Image),
                  "left_info": ("stereo/left/camera_info", CameraInfo),
                  "right_info": ("stereo/right/camera_info", CameraInfo),
                  "odom": ("odom", Odometry), "gt": ("ground_truth/pose", PoseStamped),
                  "gt_odom": ("ground_truth/odom", Odometry),
                  "collisions": ("collisions", UInt32),
                  "bumper": ("bumper/points", PointCloud2),
                  "clock": ("/clock", Clock), "tf": ("/tf", TFMessage),
                  "tf_static": ("/tf_static", TFMessage)}
        self.subs = []
        for key, (topic, typ) in topics.items():
            name = topic if topic.startswith("/") else ns + "/" + topic
            self.msgs[key] = []
            self.subs.append(rospy.Subscriber(name, typ, self._cb(key), queue_size=500))

    def _cb(self, key):
        def cb(msg):
            with self.lock:
                self.msgs[key].append(msg)
        return cb

    def get(self, key):
        with self.lock:
            return list(self.msgs[key])

    def n(self, key):
        with self.lock:
            return len(self.msgs[key])

    def close(self):
        for s in self.subs:
            s.unregister()


def _launch(start_process, *args):
    return start_process(["roslaunch", "mdr_slam", "sim_robot.launch"] + list(args), "sim_robot")


def _stamp(m):
    return m.header.stamp.to_sec()


def _drive(rospy, pub, rec, vx, seconds_sim, vy=0.0, until=None, timeout=120.0):
    """Publish (vx, vy) at 20 Hz wall until ``seconds_sim`` of sim time have passed on /clock
    (or ``until()`` holds); returns the sim time reached."""
    from geometry_msgs.msg import Twist
    t_start = rec.get("clock")[-1].clock.to_sec()
    msg = Twist()
    msg.linear.x, msg.linear.y = vx, vy

    def done():
        pub.publish(msg)
        t = rec.get("clock")[-1].clock.to_sec()
        return (until is not None and until()) or t - t_start >= seconds_sim
    assert wait_for(done, timeout, 0.05), "sim time did not advance"
    return rec.get("clock")[-1].clock.to_sec()


def test_sim_robot_streams_like_a_driver_and_follows_cmd_vel(rospy_client, start_process):
    rospy = rospy_client
    from geometry_msgs.msg import Twist
    rec = Recorder(rospy)
    pub = rospy.Publisher("/cmd_vel", Twist, queue_size=10)
    # the office's middle, facing +x: 3.7 m of floor ahead
    node = _launch(start_process, "start_pose:=4 3 0", "scale:=0.5")
    try:
        assert wait_for(lambda: all(rec.n(k) >= 3 for k in
                                    ("left", "right", "left_info", "right_info", "odom", "gt",
                                     "gt_odom", "clock")) and
                        rec.n("collisions") and rec.n("tf_static"), 120, 0.2), \
            ({k: rec.n(k) for k in rec.msgs}, node.output()[-3000:])
        assert wait_for(lambda: pub.get_num_connections() > 0, 30)
        # a lateral command (a holonomic planner's) moves nothing sideways
        _drive(rospy, pub, rec, 0.3, 3.0, vy=0.2)
        t_end = _drive(rospy, pub, rec, 0.0, 1.0)
        assert wait_for(lambda: rec.get("gt") and _stamp(rec.get("gt")[-1]) >= t_end, 30)
    finally:
        rec.close()
    out = node.output()
    assert node.proc.poll() is None, out[-3000:]
    assert "Traceback" not in out, out[-3000:]

    # images as a driver publishes them: half resolution mono8, camera_info with their stamp and
    # frame, the rectified pair's baseline in the right P
    left, right = rec.get("left"), rec.get("right")
    li, ri = rec.get("left_info"), rec.get("right_info")
    im = left[-1]
    assert (im.width, im.height, im.encoding) == (376, 240, "mono8")
    assert im.header.frame_id == "camera_left_optical_frame"
    assert right[-1].header.frame_id == ri[-1].header.frame_id == "camera_right_optical_frame"
    assert li[-1].header.frame_id == "camera_left_optical_frame"
    fx = li[-1].P[0]
    assert ri[-1].P[3] == pytest.approx(-fx * 0.11)
    # the same stamps on the four topics (each from when its subscription was connected)
    stamps = [[round(_stamp(m), 6) for m in ms] for ms in (left, right, li, ri)]
    lo, hi = max(s[0] for s in stamps), min(s[-1] for s in stamps)
    sets = [{t for t in s if lo <= t <= hi} for s in stamps]
    assert len(sets[0]) > 30 and all(x == sets[0] for x in sets)
    img = np.frombuffer(im.data, np.uint8).reshape(240, 376)
    assert img.std() > 5

    # /clock: advanced one frame period at a time, and every frame is stamped at a clock tick
    clock = np.array([m.clock.to_sec() for m in rec.get("clock")])
    steps = np.diff(clock)
    assert np.all(steps > 0) and np.allclose(steps / PERIOD, np.round(steps / PERIOD), atol=1e-6)
    assert np.mean(np.isclose(steps, PERIOD)) > 0.9
    assert all(m.clock.nsecs % 100000000 == 0 for m in rec.get("clock"))   # on the frame grid
    ticks = set(np.round(clock, 6))
    frames = [round(_stamp(m), 6) for m in left if clock[0] <= _stamp(m) <= clock[-1]]
    assert len(frames) > 30 and np.mean([t in ticks for t in frames]) > 0.9

    # tf_static: base_link -> camera_link -> both optical frames; REP-103: the optical z is the
    # robot's x (pitched down a little), the optical x its right
    edges = {}
    for m in rec.get("tf_static"):
        for tr in m.transforms:
            edges[tr.child_frame_id] = (tr.header.frame_id, cv.transform_stamped_to_matrix(tr))

    def chain(child):
        T = np.eye(4)
        while child in edges:
            parent, Tpc = edges[child]
            T = Tpc @ T
            child = parent
        return child, T
    root, T_base_left = chain("camera_left_optical_frame")
    assert root == "base_link"
    z, x = T_base_left[:3, 2], T_base_left[:3, 0]
    assert z[0] > 0.99 and -0.1 < z[2] < 0 and x == pytest.approx([0, -1, 0], abs=1e-9)
    assert 1.25 < T_base_left[2, 3] < 1.4
    root, T_base_right = chain("camera_right_optical_frame")
    assert root == "base_link"
    assert (inv_T(T_base_left) @ T_base_right)[:3, 3] == pytest.approx([0.11, 0, 0], abs=1e-9)

    # ground truth: the left optical frame in map (as the simulator's bags), = the true base
    # pose x the mounting; the base went ahead along +x, not sideways
    gt = {round(_stamp(m), 6): cv.pose_stamped_to_matrix(m) for m in rec.get("gt")}
    assert all(m.header.frame_id == "map" for m in rec.get("gt"))
    gto = rec.get("gt_odom")
    assert gto[-1].header.frame_id == "map" and gto[-1].child_frame_id == "base_link"
    # the two topics are recorded by separate subscribers: on a loaded machine the last
    # ground-truth odometry can arrive before the camera pose of the same stamp
    both = [m for m in gto if round(_stamp(m), 6) in gt][-5:]
    assert len(both) == 5, (sorted(gt)[-3:], [_stamp(m) for m in gto[-3:]])
    for m in both:
        T_map_base = cv.pose_to_matrix(m.pose.pose)
        np.testing.assert_allclose(gt[round(_stamp(m), 6)], T_map_base @ T_base_left, atol=1e-6)
    base0 = cv.pose_to_matrix(gto[0].pose.pose)
    base1 = cv.pose_to_matrix(gto[-1].pose.pose)
    assert base0[:3, 3] == pytest.approx([4, 3, 0], abs=1e-6)
    moved = base1[:3, 3] - base0[:3, 3]
    assert 0.5 < moved[0] < 1.0 and abs(moved[1]) < 0.02, moved     # ~0.3 m/s x 3 s
    assert abs(gto[-1].twist.twist.linear.x) < 1e-9                  # stopped again

    # wheel odometry: odom -> base_link from the start pose, close to the truth but drifting
    od = rec.get("odom")
    assert all(m.header.frame_id == "odom" and m.child_frame_id == "base_link" for m in od)
    assert od[0].pose.pose.position.x == 0.0
    ox = od[-1].pose.pose.position.x
    assert ox == pytest.approx(moved[0], rel=0.1) and ox != pytest.approx(moved[0], abs=1e-4)
    assert np.median(np.diff([_stamp(m) for m in od])) == pytest.approx(0.02)    # 50 Hz
    odom_tf = [tr for m in rec.get("tf") for tr in m.transforms
               if (tr.header.frame_id, tr.child_frame_id) == ("odom", "base_link")]
    # the same poses on tf, at the same stamps (from when each subscription was connected)
    tf_at = {round(_stamp(tr), 6): cv.transform_stamped_to_matrix(tr) for tr in odom_tf}
    lo, hi = min(tf_at), max(tf_at)
    common = [m for m in od if lo <= round(_stamp(m), 6) <= hi]
    assert len(common) > 100 and hi - lo > 2.0
    for m in common:
        np.testing.assert_allclose(tf_at[round(_stamp(m), 6)], cv.pose_to_matrix(m.pose.pose),
                                   atol=1e-9)
    assert rec.get("collisions")[-1].data == 0


def test_a_drive_into_a_wall_is_counted_the_base_stops_and_backs_off(rospy_client, start_process):
    rospy = rospy_client
    from geometry_msgs.msg import Twist
    rec = Recorder(rospy, ns="/robot1")
    pub = rospy.Publisher("/robot1/cmd_vel", Twist, queue_size=10)
    # 1 m before the office's east wall (x = 8), facing it; in a namespace, as a fleet would be
    node = start_process(["roslaunch", "mdr_slam", "sim_robot.launch", "start_pose:=7 2.5 0", "scale:=0.5",
                          "__ns:=robot1"], "sim_robot")
    try:
        assert wait_for(lambda: rec.n("collisions") >= 1 and rec.n("gt_odom") >= 3 and
                        rec.n("clock") >= 3, 120, 0.2), node.output()[-3000:]
        assert wait_for(lambda: pub.get_num_connections() > 0, 30)
        assert rec.get("collisions")[-1].data == 0
        _drive(rospy, pub, rec, 0.4, 20.0, until=lambda: rec.get("collisions")[-1].data >= 1)
        assert rec.get("collisions")[-1].data == 1, node.output()[-3000:]
        t_hit = rec.get("clock")[-1].clock.to_sec()
        # pushing on for 4 s of sim time: the base backs off 0.15 m regardless, then the
        # commands drive it into the wall again
        t_end = _drive(rospy, pub, rec, 0.4, 4.0)
        assert wait_for(lambda: _stamp(rec.get("gt_odom")[-1]) >= t_end, 30)
    finally:
        rec.close()
    out = node.output()
    assert node.proc.poll() is None and "Traceback" not in out, out[-3000:]
    assert rec.get("collisions")[-1].data == 2, out[-3000:]
    xs = [(_stamp(m), cv.pose_to_matrix(m.pose.pose)[0, 3]) for m in rec.get("gt_odom")]
    assert max(x for _, x in xs) <= 8.0 - 0.2 + 1e-6          # the footprint never entered
    after = [x for t, x in xs if t >= t_hit - 0.05]
    assert 8.0 - 0.2 - max(after) < 0.01                      # stopped at the wall
    assert max(after) - min(after) == pytest.approx(0.15, abs=0.02), (max(after), min(after))
    assert "collision 1 at" in out and "collision 2 at" in out and "office_wall_x1" in out
    # the bumper: nothing before the contact, then points at the wall ahead, in base_link
    bumps = rec.get("bumper")
    assert bumps and min(_stamp(m) for m in bumps) >= t_hit - 0.2, [_stamp(m) for m in bumps[:3]]
    x_at = dict((round(t, 2), x) for t, x in xs)
    for m in bumps:
        P = cv.pointcloud2_to_xyz(m)
        assert m.header.frame_id == "base_link" and len(P) >= 3
        x = x_at.get(round(_stamp(m), 2))
        if x is not None:        # at x = 8 in the map, from wherever the base is
            assert np.all(np.abs(x + P[:, 0] - 8.0) < 0.06), (x, P)


def test_wait_for_topic_holds_the_clock_until_the_consumer_caught_up(rospy_client,
                                                                     start_process):
    """Lockstep: the node starts once the consumer is connected and, after each frame, waits
    for a message stamped at it on ~wait_for_topic (here the test plays the consumer) before
    advancing /clock."""
    rospy = rospy_client
    from geometry_msgs.msg import PoseStamped
    rec = Recorder(rospy, ns="/lock")
    pub = rospy.Publisher("/lock/consumer", PoseStamped, queue_size=10)
    node = start_process(["roslaunch", "mdr_slam", "sim_robot.launch", "scale:=0.25",
                          "wait_for_topic:=consumer", "wait_timeout:=30", "__ns:=lock"],
                         "sim_robot")
    try:
        assert wait_for(lambda: rec.n("left") >= 1 and pub.get_num_connections() > 0 and
                        rec.n("clock") >= 1, 120, 0.2), node.output()[-3000:]
        # no consumer output: the first frame's time is where the clock stays (and is re-sent)
        rospy.sleep(3.0)
        first = _stamp(rec.get("left")[0])
        assert rec.n("left") == 1 and rec.get("clock")[-1].clock.to_sec() == pytest.approx(first)
        # the consumer answers each frame: the clock follows, one frame per answer
        for k in range(5):
            t = _stamp(rec.get("left")[-1])
            pub.publish(cv.matrix_to_pose_stamped(np.eye(4), rospy.Time.from_sec(t), "map"))
            assert wait_for(lambda: rec.n("left") >= k + 2, 60, 0.02), node.output()[-3000:]
            assert _stamp(rec.get("left")[-1]) == pytest.approx(t + PERIOD)
        rospy.sleep(1.0)
        assert rec.n("left") == 6
    finally:
        rec.close()
    assert node.proc.poll() is None and "Traceback" not in node.output()
