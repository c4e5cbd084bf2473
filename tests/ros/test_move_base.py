"""The real move_base (ROS navigation) with MDR-SLAM's navigation configuration
(src/mdr_slam/config/navigation, started by launch/navigation.launch with the map nodes it does
not need switched off).

The robot is a kinematic base in this process (:class:`FakeRobot`): it integrates /cmd_vel as
given (a lateral velocity moves it sideways), publishes tf map -> odom -> base_link and its
wheel odometry on /odom, and can carry a depth camera (:class:`Room`: the wall points of a room
of straight walls it sees, as a PointCloud2 in its optical frame on /mdr/depth/points). Maps come
either as a published /mdr/map/grid or, in the closed loop, from the fusion node fed by that
camera while the robot explores, so the grid grows as the node publishes it.

Skipped when move_base is not found (Noetic: apt install ros-noetic-navigation; Debian:
MDR_BUILD_NAVIGATION=1 ./catkin_ws_setup.sh builds it from ../shared/thirdparty).
"""
from __future__ import annotations

import math
import os
import subprocess
import threading
import time

import numpy as np
import pytest
import yaml

from conftest import ROOT, wait_for

CONFIG = os.path.join(ROOT, "src", "mdr_slam", "config")
NAV_LAUNCH = os.path.join(ROOT, "launch", "navigation.launch")
RES = 0.05


def _move_base_found() -> bool:
    try:
        return subprocess.run(["rospack", "find", "move_base"], capture_output=True,
                              timeout=30).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


pytestmark = [pytest.mark.ros, pytest.mark.skipif(
    not _move_base_found(),
    reason="move_base not found (rospack find move_base): on Noetic apt install "
           "ros-noetic-navigation; on Debian MDR_BUILD_NAVIGATION=1 ./catkin_ws_setup.sh builds "
           "it from ../shared/thirdparty/ros-navigation-*.tar.gz")]


def _nav_yaml(name):
    return yaml.safe_load(open(os.path.join(CONFIG, "navigation", name)))


def _plan_topic():
    """move_base publishes its global planner's plans on ~<planner name>/plan."""
    return "/move_base/%s/plan" % _nav_yaml("move_base.yaml")["base_global_planner"].split("/")[-1]


# ---------------------------------------------------------------------- maps and a robot
def wall_grid(walls, lo, hi, fill=0, res=RES):
    """int8 grid (rows: y) over [lo, hi) with the cells along the wall segments occupied (100),
    the others ``fill``; returns (grid, origin)."""
    W, H = int(round((hi[0] - lo[0]) / res)), int(round((hi[1] - lo[1]) / res))
    g = np.full((H, W), fill, np.int8)
    for x0, y0, x1, y1 in walls:
        n = int(math.ceil(math.hypot(x1 - x0, y1 - y0) / (res / 4))) + 1
        c = np.floor((np.linspace(x0, x1, n) - lo[0]) / res).astype(int)
        r = np.floor((np.linspace(y0, y1, n) - lo[1]) / res).astype(int)
        ok = (c >= 0) & (c < W) & (r >= 0) & (r < H)
        g[r[ok], c[ok]] = 100
    return g, (float(lo[0]), float(lo[1]))


def grid_msg(g, origin, res=RES, frame="map"):
    import rospy
    from nav_msgs.msg import OccupancyGrid
    m = OccupancyGrid()
    m.header.stamp = rospy.Time.now()
    m.header.frame_id = frame
    m.info.map_load_time = m.header.stamp
    m.info.resolution = res
    m.info.height, m.info.width = g.shape
    m.info.origin.position.x, m.info.origin.position.y = origin
    m.info.origin.orientation.w = 1.0
    m.data = g.reshape(-1).tolist()
    return m


def msg_grid(m):
    """(grid (H, W) int8, origin (x, y), resolution) of an OccupancyGrid."""
    g = np.asarray(m.data, np.int8).reshape(m.info.height, m.info.width)
    return g, (m.info.origin.position.x, m.info.origin.position.y), m.info.resolution


def cells_of(xy, origin, res, shape):
    """(rows, cols, inside) of metric points in a grid."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    c = np.floor((xy[:, 0] - origin[0]) / res).astype(int)
    r = np.floor((xy[:, 1] - origin[1]) / res).astype(int)
    inside = (c >= 0) & (c < shape[1]) & (r >= 0) & (r < shape[0])
    return r, c, inside


CAMERA_FRAME = "test_camera_optical"
CAMERA_ON_BASE = (0.15, 0.0, 0.8)     # m: a camera on a mast, looking along base_link x


class Room:
    """Straight walls (x0, y0, x1, y1) from the floor to 2 m, sampled on a fixed 5 cm lattice, and
    what a camera sees of them: the lattice points within its field of view and range that no
    other wall hides."""

    def __init__(self, walls, spacing=0.05, height=2.0):
        cols, owner = [], []
        for k, (x0, y0, x1, y1) in enumerate(walls):
            n = max(2, int(round(math.hypot(x1 - x0, y1 - y0) / spacing)))
            t = (np.arange(n) + 0.5) / n
            cols.append(np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0)], 1))
            owner.append(np.full(n, k))
        self.walls = np.asarray(walls, np.float64)
        self.cols = np.vstack(cols)
        self.owner = np.concatenate(owner)
        self.z = np.arange(spacing / 2, height, spacing)

    def visible(self, cam, yaw, hfov=math.radians(90), vfov=math.radians(60), max_range=6.0):
        """(N, 3) map points the camera at ``cam`` (x, y, z), heading ``yaw``, sees."""
        d = self.cols - cam[:2]
        dist = np.hypot(d[:, 0], d[:, 1])
        bearing = np.arctan2(d[:, 1], d[:, 0]) - yaw
        bearing = (bearing + np.pi) % (2 * np.pi) - np.pi
        ok = (np.abs(bearing) <= hfov / 2) & (dist <= max_range) & (dist > 0.2)
        # hidden: the segment camera -> column crosses another wall before it
        p, r = cam[:2], d[ok]
        q = self.walls[:, :2]
        s = self.walls[:, 2:] - q
        den = r[:, None, 0] * s[None, :, 1] - r[:, None, 1] * s[None, :, 0]
        qp = q[None] - p
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (qp[..., 0] * s[None, :, 1] - qp[..., 1] * s[None, :, 0]) / den
            u = (qp[..., 0] * r[:, None, 1] - qp[..., 1] * r[:, None, 0]) / den
        other = self.owner[ok][:, None] != np.arange(len(self.walls))[None]
        hit = other & (np.abs(den) > 1e-12) & (t > 1e-6) & (t < 1 - 1e-6) & (u >= 0) & (u <= 1)
        idx = np.flatnonzero(ok)[~hit.any(1)]
        c, dd = self.cols[idx], dist[idx]
        elev = np.arctan2(self.z[None] - cam[2], dd[:, None])
        keep = np.abs(elev) <= vfov / 2
        n = keep.sum(1)
        return np.column_stack([np.repeat(c, n, 0), np.broadcast_to(self.z, keep.shape)[keep]])


class FakeRobot:
    """A kinematic base: integrates /cmd_vel (vx, vy, wz in base_link) as given, stops when the
    last command is older than 0.5 s; publishes tf map -> odom (``map_odom``: x, y, yaw; identity
    unless a test moves it, as a relocalization does), odom -> base_link and its wheel odometry on
    /odom (with the velocity) at 50 Hz, and with a ``room`` the camera's view of it on
    /mdr/depth/points at 5 Hz (the same stamp as the tf it was seen from)."""

    def __init__(self, rospy, pose, room=None, rate=50.0, cloud_rate=5.0):
        import tf2_ros
        from geometry_msgs.msg import Twist
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import PointCloud2
        self.rospy = rospy
        self.pose = np.array(pose, np.float64)
        self.map_odom = (0.0, 0.0, 0.0)
        self.cmd = np.zeros(3)
        self.cmd_time = -1e9
        self.cmds = []             # (ROS time s, vx, vy, wz) of every /cmd_vel
        self.track = []            # (ROS time s, x, y, yaw)
        self.lock = threading.Lock()
        self.room = room
        self.rate, self.cloud_period = rate, 1.0 / cloud_rate
        self.tfb = tf2_ros.TransformBroadcaster()
        self.pub_odom = rospy.Publisher("/odom", Odometry, queue_size=5)
        self.pub_cloud = (rospy.Publisher("/mdr/depth/points", PointCloud2, queue_size=2)
                          if room else None)
        if room is not None:
            from geometry_msgs.msg import TransformStamped
            self.static = tf2_ros.StaticTransformBroadcaster()
            t = TransformStamped()
            t.header.stamp = rospy.Time.now()
            t.header.frame_id, t.child_frame_id = "base_link", CAMERA_FRAME
            t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = \
                CAMERA_ON_BASE
            # optical axes: z forward (base x), x right (-base y), y down (-base z)
            (t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
             t.transform.rotation.w) = (-0.5, 0.5, -0.5, 0.5)
            self.static.sendTransform(t)
        self.sub = rospy.Subscriber("/cmd_vel", Twist, self._on_cmd, queue_size=20)
        self.running = True
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _on_cmd(self, m):
        t = self.rospy.get_time()
        with self.lock:
            self.cmd = np.array([m.linear.x, m.linear.y, m.angular.z])
            self.cmd_time = t
            self.cmds.append((t, m.linear.x, m.linear.y, m.angular.z))

    def xy_yaw(self):
        with self.lock:
            return self.pose.copy()

    def _run(self):
        from geometry_msgs.msg import TransformStamped
        from nav_msgs.msg import Odometry
        last = time.monotonic()
        next_cloud = last
        while self.running and not self.rospy.is_shutdown():
            now = time.monotonic()
            dt, last = now - last, now
            stamp = self.rospy.Time.now()
            with self.lock:
                v = self.cmd if stamp.to_sec() - self.cmd_time < 0.5 else np.zeros(3)
                x, y, th = self.pose
                self.pose = np.array([x + (v[0] * math.cos(th) - v[1] * math.sin(th)) * dt,
                                      y + (v[0] * math.sin(th) + v[1] * math.cos(th)) * dt,
                                      th + v[2] * dt])
                x, y, th = self.pose
                self.track.append((stamp.to_sec(), x, y, th))
                map_odom = self.map_odom
            tfs = []
            for parent, child, (tx, ty, yaw) in (("map", "odom", map_odom),
                                                 ("odom", "base_link", (x, y, th))):
                t = TransformStamped()
                t.header.stamp = stamp
                t.header.frame_id, t.child_frame_id = parent, child
                t.transform.translation.x, t.transform.translation.y = tx, ty
                t.transform.rotation.z = math.sin(yaw / 2)
                t.transform.rotation.w = math.cos(yaw / 2)
                tfs.append(t)
            self.tfb.sendTransform(tfs)
            o = Odometry()
            o.header.stamp, o.header.frame_id, o.child_frame_id = stamp, "odom", "base_link"
            o.pose.pose.position.x, o.pose.pose.position.y = x, y
            o.pose.pose.orientation.z = math.sin(th / 2)
            o.pose.pose.orientation.w = math.cos(th / 2)
            o.twist.twist.linear.x, o.twist.twist.linear.y, o.twist.twist.angular.z = v
            self.pub_odom.publish(o)
            if self.room is not None and now >= next_cloud:
                next_cloud = now + self.cloud_period
                self._publish_cloud(stamp, x, y, th)
            time.sleep(max(0.0, 1.0 / self.rate - (time.monotonic() - now)))

    def _publish_cloud(self, stamp, x, y, th):
        from mdr_slam.conversions import arrays_to_pointcloud2
        cx, cy, cz = CAMERA_ON_BASE
        cam = np.array([x + cx * math.cos(th) - cy * math.sin(th),
                        y + cx * math.sin(th) + cy * math.cos(th), cz])
        P = self.room.visible(cam, th)
        if not len(P):
            return
        rel = P - cam
        fwd = np.array([math.cos(th), math.sin(th), 0.0])
        right = np.array([math.sin(th), -math.cos(th), 0.0])
        opt = np.column_stack([rel @ right, -rel[:, 2], rel @ fwd]).astype(np.float32)
        self.pub_cloud.publish(arrays_to_pointcloud2({}, stamp, CAMERA_FRAME, xyz=opt))

    def pose_at(self, t):
        """(x, y) of the robot at ROS time ``t`` (the nearest recorded step)."""
        with self.lock:
            tr = np.asarray(self.track)
        i = int(np.clip(np.searchsorted(tr[:, 0], t), 0, len(tr) - 1))
        return tr[i, 1:3]

    def stop(self):
        self.running = False
        self.thread.join(5)
        self.sub.unregister()
        self.pub_odom.unregister()
        self.tfb.pub_tf.unregister()
        if self.pub_cloud is not None:
            self.pub_cloud.unregister()
            self.static.pub_tf.unregister()   # no latched camera frame left for later tests


# ---------------------------------------------------------------------- move_base
def start_move_base(start_process, name="move_base", fusion_params=None):
    """navigation.launch with move_base and, with ``fusion_params``, the fusion node (no pose or
    depth node: the test is the robot and its camera)."""
    args = ["roslaunch", NAV_LAUNCH, "move_base:=true", "start_pose:=false", "start_depth:=false",
            "respawn:=false", "start_fusion:=%s" % ("true" if fusion_params else "false")]
    if fusion_params:
        args += ["fusion_params:=%s" % fusion_params, "mapping_nice:=0"]
    return start_process(args, name)


def move_base_pids(launch):
    import psutil
    try:
        return [p for p in psutil.Process(launch.proc.pid).children(recursive=True)
                if p.name() == "move_base"]
    except psutil.Error:
        return []


class Recorder:
    """Messages of a topic with their arrival (ROS) time."""

    def __init__(self, rospy, topic, cls):
        self.msgs = []
        self.rospy = rospy
        self.sub = rospy.Subscriber(topic, cls, self._cb, queue_size=50, buff_size=1 << 24)

    def _cb(self, m):
        self.msgs.append((self.rospy.get_time(), m))

    def stop(self):
        self.sub.unregister()


def goal_client(rospy, timeout=60.0):
    import actionlib
    from move_base_msgs.msg import MoveBaseAction
    c = actionlib.SimpleActionClient("move_base", MoveBaseAction)
    assert c.wait_for_server(rospy.Duration(timeout)), "move_base's action server did not come up"
    return c


def goal(x, y, yaw=0.0):
    import rospy
    from move_base_msgs.msg import MoveBaseGoal
    g = MoveBaseGoal()
    g.target_pose.header.frame_id = "map"
    g.target_pose.header.stamp = rospy.Time.now()
    g.target_pose.pose.position.x, g.target_pose.pose.position.y = x, y
    g.target_pose.pose.orientation.z = math.sin(yaw / 2)
    g.target_pose.pose.orientation.w = math.cos(yaw / 2)
    return g


def state_name(s):
    from actionlib_msgs.msg import GoalStatus
    return {v: k for k, v in vars(GoalStatus).items() if isinstance(v, int)}.get(s, str(s))


def log_lines(launch, *needles):
    """move_base's output lines (without colour codes) that contain any of ``needles``."""
    import re
    text = re.sub(r"\x1b\[[0-9;]*m", "", launch.output())
    return [ln for ln in text.splitlines() if any(n in ln for n in needles)]


class GridPublisher:
    """Publishes a grid as the fusion node does: /mdr/map/grid, and /mdr/map/nav_grid with the
    unknown cells at fusion.yaml's nav_grid_unknown (or ``unknown``)."""

    def __init__(self, rospy, unknown=None):
        from nav_msgs.msg import OccupancyGrid
        self.pubs = [rospy.Publisher(t, OccupancyGrid, queue_size=1, latch=True)
                     for t in ("/mdr/map/grid", "/mdr/map/nav_grid")]
        self.unknown = unknown if unknown is not None else \
            yaml.safe_load(open(os.path.join(CONFIG, "fusion.yaml")))["nav_grid_unknown"]

    def publish(self, g, origin):
        self.pubs[0].publish(grid_msg(g, origin))
        self.pubs[1].publish(grid_msg(np.where(g < 0, self.unknown, g), origin))

    def stop(self):
        for p in self.pubs:
            p.unregister()


@pytest.fixture
def grid_publisher(rospy_client):
    pub = GridPublisher(rospy_client)
    yield pub
    pub.stop()


# ---------------------------------------------------------------------- DWA: a differential drive
ROOM = [(0, 0, 6, 0), (6, 0, 6, 4), (6, 4, 0, 4), (0, 4, 0, 0)]


def test_dwa_sends_no_lateral_velocity(rospy_client, start_process, grid_publisher):
    """The robot is a differential drive: every command DWA sends on the way to a goal has
    linear.y == 0 (DWA's own default samples y velocities of +-0.1 m/s)."""
    from actionlib_msgs.msg import GoalStatus
    rospy = rospy_client
    g, origin = wall_grid(ROOM, (-0.5, -0.5), (6.5, 4.5))
    grid_publisher.publish(g, origin)
    robot = FakeRobot(rospy, (1.0, 1.0, 0.0))
    launch = start_move_base(start_process)
    try:
        client = goal_client(rospy)
        # the goal 1.5 m to the robot's left: a sideways step is DWA's shortest way there when
        # it samples y velocities
        client.send_goal(goal(1.0, 2.5, math.pi / 2))
        # under a loaded suite DWA runs late and slower
        client.wait_for_result(rospy.Duration(240))
        state = client.get_state()
        end = robot.xy_yaw()
    finally:
        robot.stop()
        launch.stop()
    cmds = np.array([c[1:] for c in robot.cmds]).reshape(-1, 3)
    moving = np.abs(cmds).sum(1) > 0
    lateral = np.abs(cmds[:, 1]) > 1e-9
    print("DWA: %d commands (%d moving), %d with linear.y != 0 (largest |y| %.2f m/s); goal %s, "
          "robot at (%.2f, %.2f, %.0f deg)" % (len(cmds), moving.sum(), lateral.sum(),
                                              np.abs(cmds[:, 1]).max() if len(cmds) else 0,
                                              state_name(state), end[0], end[1],
                                              math.degrees(end[2])))
    assert moving.sum() >= 20
    assert lateral.sum() == 0
    assert state == GoalStatus.SUCCEEDED
    tol = _nav_yaml("move_base.yaml")["DWAPlannerROS"]["xy_goal_tolerance"]
    assert math.hypot(end[0] - 1.0, end[1] - 2.5) <= tol + 0.05


def test_dwa_turns_to_the_goal_while_the_tracker_is_silent(rospy_client, start_process,
                                                          grid_publisher):
    """A goal at the robot's place, turned 1.2 rad. The tracker's /mdr/odom went silent while the
    base was turning (tracking LOST), its last twist 0.5 rad/s. DWA reads the base's velocity
    from the wheel odometry (/odom), sees it stopped and turns it to the goal's heading; fed
    /mdr/odom it waited for the stale turn to stop and sent zeros until the goal timed out."""
    from actionlib_msgs.msg import GoalStatus
    from nav_msgs.msg import Odometry
    rospy = rospy_client
    g, origin = wall_grid(ROOM, (-0.5, -0.5), (6.5, 4.5))
    grid_publisher.publish(g, origin)
    robot = FakeRobot(rospy, (3.0, 2.0, 0.0))
    stale = rospy.Publisher("/mdr/odom", Odometry, queue_size=1, latch=True)
    m = Odometry()
    m.header.stamp, m.header.frame_id, m.child_frame_id = rospy.Time.now(), "map", "base_link"
    m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.orientation.w = 3.0, 2.0, 1.0
    m.twist.twist.angular.z = 0.5
    stale.publish(m)
    launch = start_move_base(start_process)
    try:
        client = goal_client(rospy)
        client.send_goal(goal(3.0, 2.0, 1.2))
        done = client.wait_for_result(rospy.Duration(60))
        state = client.get_state()
        end = robot.xy_yaw()
    finally:
        robot.stop()
        stale.unregister()
        launch.stop()
    print("goal %s (%s), robot at (%.2f, %.2f) yaw %.2f rad" % (state_name(state), done, *end))
    assert state == GoalStatus.SUCCEEDED
    assert abs(end[2] - 1.2) < 0.25 and np.hypot(end[0] - 3.0, end[1] - 2.0) < 0.2


# ---------------------------------------------------------------------- the global plan
def test_plans_start_at_the_robot_on_a_long_map(rospy_client, start_process, grid_publisher):
    """On a map much longer than wide (a corridor) every global plan runs from the robot to the
    goal. navfn's path extraction gives up after 4 x the map's width in steps and then returns
    the partial path anyway: a plan that starts next to the goal, not at the robot."""
    from nav_msgs.msg import Path
    rospy = rospy_client
    g, origin = wall_grid([(0, 0, 2, 0), (2, 0, 2, 20), (2, 20, 0, 20), (0, 20, 0, 0)],
                          (-0.5, -0.5), (2.5, 20.5), fill=-1)
    inner = g[10:410, 10:50]                 # the corridor: walls occupied, floor free
    inner[inner != 100] = 0
    grid_publisher.publish(g, origin)
    robot = FakeRobot(rospy, (1.0, 1.0, math.pi / 2))
    plans = Recorder(rospy, _plan_topic(), Path)
    launch = start_move_base(start_process)
    try:
        client = goal_client(rospy)
        client.send_goal(goal(1.0, 18.0, math.pi / 2))
        wait_for(lambda: len(plans.msgs) >= 4, 30, 0.2)
        client.cancel_all_goals()
    finally:
        plans.stop()
        robot.stop()
        launch.stop()
    assert plans.msgs, "no plan on %s\n%s" % (_plan_topic(), launch.output()[-3000:])
    bad = []
    for t, p in plans.msgs:
        if not p.poses:
            continue
        xy = np.array([(q.pose.position.x, q.pose.position.y) for q in p.poses])
        at = robot.pose_at(t)
        d_start = float(np.hypot(*(xy[0] - at)))
        d_goal = float(np.hypot(*(xy[-1] - (1.0, 18.0))))
        if d_start > 0.25 or d_goal > 0.25:
            bad.append((len(xy), round(d_start, 2), round(d_goal, 2)))
    print("%s on a 2 x 20 m corridor (%d x %d cells): %d plans, %d not from the robot to the goal "
          "(poses, m from the robot, m from the goal): %s" % (
              _plan_topic(), g.shape[1], g.shape[0], len(plans.msgs), len(bad), bad[:5]))
    assert len([1 for _, p in plans.msgs if p.poses]) >= 2
    assert not bad


def make_plan(rospy, start, target):
    """move_base's ~make_plan service: the (N, 2) plan from ``start`` to ``target`` (x, y)."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.srv import GetPlan
    rospy.wait_for_service("/move_base/make_plan", 30)
    s, t = PoseStamped(), PoseStamped()
    for p, (x, y) in ((s, start), (t, target)):
        p.header.frame_id = "map"
        p.pose.position.x, p.pose.position.y = x, y
        p.pose.orientation.w = 1.0
    plan = rospy.ServiceProxy("/move_base/make_plan", GetPlan)(s, t, 0.0).plan.poses
    return np.array([(q.pose.position.x, q.pose.position.y) for q in plan]).reshape(-1, 2)


def occupied_poses(xy, g, origin, res=RES):
    r, c, inside = cells_of(xy, origin, res, g.shape)
    return int((g[r[inside], c[inside]] == 100).sum())


def test_no_plan_through_a_wall_right_after_a_costmap_resize(rospy_client, start_process,
                                                             grid_publisher):
    """A grid of another extent resizes the global costmap, which stays blank until its next
    update (up to 1 / update_frequency later). A plan asked for meanwhile must not cross the
    walls of the map: none, or one around them. Once updated, the planner goes around the wall
    through the unmapped half of the room (unknown cells are crossed)."""
    rospy = rospy_client
    walls = [(0, 0, 10, 0), (10, 0, 10, 7), (10, 7, 0, 7), (0, 7, 0, 0), (5, 0, 5, 4.5)]
    start, target = (1.5, 1.5), (8.0, 1.5)

    def grid(k):
        """The room, its right half (behind the wall) unknown; k cells more to the east."""
        g, origin = wall_grid(walls, (-0.5, -0.5), (10.5 + k * RES, 7.5))
        right = g[:, int(5.5 / RES) + 1:]
        right[right != 100] = -1
        return g, origin
    g, origin = grid(0)
    grid_publisher.publish(g, origin)
    robot = FakeRobot(rospy, start + (0.0,))
    launch = start_move_base(start_process)
    crossing, empty, around = [], 0, []
    try:
        goal_client(rospy)
        time.sleep(2.0)
        for k in range(1, 9):
            g, origin = grid(k)
            grid_publisher.publish(g, origin)
            time.sleep(0.05)
            xy = make_plan(rospy, start, target)         # while the costmap is blank
            if not len(xy):
                empty += 1
            elif occupied_poses(xy, g, origin):
                crossing.append((k, len(xy), occupied_poses(xy, g, origin)))
            time.sleep(2.0)                               # updated: a plan around the wall
            xy = make_plan(rospy, start, target)
            around.append((len(xy), occupied_poses(xy, g, origin) if len(xy) else -1,
                           round(float(xy[:, 1].max()), 2) if len(xy) else None))
    finally:
        robot.stop()
        launch.stop()
    resized = log_lines(launch, "Resizing costmap")
    print("8 grids of another extent (%d costmap resizes): right after each, %d plans through "
          "walls (grid, poses, poses in occupied cells) %s, %d no plan; 2 s later (poses, in "
          "occupied cells, northmost y) %s"
          % (len(resized), len(crossing), crossing, empty, around))
    assert len(resized) >= 8
    assert not crossing
    # the updated costmap has a way round the wall (its end at y = 4.5) through unknown cells
    assert all(n > 0 and occ == 0 and y > 4.5 for n, occ, y in around)


# ---------------------------------------------------------------------- recovery
def test_recovery_clears_a_stale_obstacle(rospy_client, start_process, grid_publisher):
    """A phantom obstacle: a bumper's contacts in a doorway (someone stood there and left) stay
    marked in the obstacle layer (the bumper never clears, and no camera looks through). No plan
    gets through; move_base's recovery clears the obstacle layer (outside a 3 m square around
    the robot) and the robot then reaches the goal. A recovery that clears a layer of another name
    leaves it."""
    from actionlib_msgs.msg import GoalStatus
    from move_base_msgs.msg import RecoveryStatus
    from sensor_msgs.msg import PointCloud2
    from mdr_slam.conversions import arrays_to_pointcloud2
    rospy = rospy_client
    walls = [(0, 0, 8, 0), (8, 0, 8, 4), (8, 4, 0, 4), (0, 4, 0, 0),
             (4, 0, 4, 1.5), (4, 2.5, 4, 4)]                  # a partition with a 1 m doorway
    g, origin = wall_grid(walls, (-0.5, -0.5), (8.5, 4.5))
    grid_publisher.publish(g, origin)
    pub_bumper = rospy.Publisher("/bumper/points", PointCloud2, queue_size=1, latch=True)
    recoveries = Recorder(rospy, "/move_base/recovery_status", RecoveryStatus)
    start = (2.3, 2.0)     # the doorway 1.7 m ahead: in the bumper source's obstacle_range (2 m)
    robot = FakeRobot(rospy, (start[0], start[1], 0.0))
    launch = start_move_base(start_process)

    def plan_ok():
        return len(make_plan(rospy, start, (6.5, 2.0))) > 0

    # the contacts in base_link, the doorway across: x 1.7 m ahead, y -0.5..0.5
    yy, zz = np.meshgrid(np.arange(-0.5, 0.51, 0.025), np.arange(0.3, 1.01, 0.05))
    blob = np.column_stack([np.full(yy.size, 4.0 - start[0]), yy.ravel(), zz.ravel()])
    try:
        client = goal_client(rospy)
        assert wait_for(plan_ok, 20, 0.5), "no plan through the open doorway"
        pub_bumper.publish(arrays_to_pointcloud2({}, rospy.Time.now(), "base_link", xyz=blob))
        blocked = wait_for(lambda: not plan_ok(), 20, 0.5)
        # the bumper's next cloud has no contact; the layer keeps the old ones
        pub_bumper.publish(arrays_to_pointcloud2({}, rospy.Time.now(), "base_link",
                                                 xyz=np.zeros((0, 3))))
        time.sleep(3.0)
        still_blocked = not plan_ok()
        client.send_goal(goal(6.5, 2.0))
        client.wait_for_result(rospy.Duration(120))
        state = client.get_state()
        end = robot.xy_yaw()
    finally:
        recoveries.stop()
        robot.stop()
        pub_bumper.unregister()
        launch.stop()
    names = [m.recovery_behavior_name for _, m in recoveries.msgs]
    cleared = sorted({ln.split("clear layer")[-1].strip(" '") for ln in
                      log_lines(launch, "Recovery behavior will clear layer")})
    print("doorway blocked by bumper contacts: %s, still after the bumper let go: %s; "
          "recoveries run %s; goal %s, robot at (%.2f, %.2f); %s"
          % (blocked, still_blocked, names, state_name(state), end[0], end[1], cleared))
    assert blocked and still_blocked
    assert names and names[0] == "conservative_reset"
    assert state == GoalStatus.SUCCEEDED
    assert end[0] > 6.0


def test_global_costmap_follows_a_wall_the_map_moved(rospy_client, start_process, grid_publisher):
    """A loop correction moves a partition of the map 0.6 m: the fusion node republishes its grid
    and its cloud with the partition in the new place. The global costmap follows: the old place
    is no longer an obstacle. Marked from the map cloud, as the obstacle layer did, the old place
    stayed lethal (the layer keeps every mark of a cloud in ``map``, which cannot clear), and a
    robot beside it in a corridor of such remnants stood walled in with no plan out."""
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import PointCloud2
    from mdr_slam.conversions import arrays_to_pointcloud2
    rospy = rospy_client
    room = [(0, 0, 6, 0), (6, 0, 6, 4), (6, 4, 0, 4), (0, 4, 0, 0)]
    pub_pts = rospy.Publisher("/mdr/map/points", PointCloud2, queue_size=1, latch=True)
    costmaps = Recorder(rospy, "/move_base/global_costmap/costmap", OccupancyGrid)
    full = "/move_base/global_costmap/always_send_full_costmap"
    rospy.set_param(full, True)

    def publish_map(y):
        """The grid and the cloud of the room with the partition x 1-4 at y, as the node sends."""
        g, origin = wall_grid(room + [(1, y, 4, y)], (-0.5, -0.5), (6.5, 4.5))
        grid_publisher.publish(g, origin)
        xs, zs = np.meshgrid(np.arange(1.0, 4.0, 0.05), np.arange(0.3, 1.01, 0.1))
        pts = np.column_stack([xs.ravel(), np.full(xs.size, y), zs.ravel()])
        pub_pts.publish(arrays_to_pointcloud2({}, rospy.Time.now(), "map", xyz=pts))

    def cost_at(x, y):
        """The highest cost (0-100) of the latest global costmap within a cell of (x, y)."""
        if not costmaps.msgs:
            return None
        c, o, res = msg_grid(costmaps.msgs[-1][1])
        xx, yy = np.meshgrid(np.arange(x - res, x + res * 1.01, res / 2),
                             np.arange(y - res, y + res * 1.01, res / 2))
        r, cc, inside = cells_of(np.column_stack([xx.ravel(), yy.ravel()]), o, res, c.shape)
        return int(c[r[inside], cc[inside]].max()) if inside.any() else None

    publish_map(2.0)                              # latched: move_base starts on it
    robot = FakeRobot(rospy, (0.5, 0.5, 0.0))     # no camera: nothing clears but the map
    launch = start_move_base(start_process)
    try:
        goal_client(rospy)
        publish_map(2.0)                          # again, now that every layer listens
        before = wait_for(lambda: cost_at(2.5, 2.0) == 100, 60, 0.5)
        time.sleep(3.0)                           # the global costmap updates at 1 Hz
        publish_map(2.6)                          # the correction
        moved = wait_for(lambda: cost_at(2.5, 2.6) == 100, 60, 0.5)
        time.sleep(5.0)                           # a few more updates and publishes
        costmaps.msgs.clear()
        assert wait_for(lambda: costmaps.msgs, 30, 0.2)
        old, new = cost_at(2.5, 2.0), cost_at(2.5, 2.6)
    finally:
        costmaps.stop()
        robot.stop()
        pub_pts.unregister()
        launch.stop()
        rospy.delete_param(full)
    print("global costmap: partition at y 2.0 lethal %s; after it moved to y 2.6 (lethal %s): "
          "cost at the old place %s, at the new %s" % (before, moved, old, new))
    assert before and moved
    assert new == 100
    assert old is not None and old < 99                  # neither lethal nor inscribed


def test_local_costmap_keeps_the_seen_walls_through_a_map_to_odom_jump(rospy_client, start_process,
                                                                      grid_publisher):
    """A relocalization moves map -> odom by 0.5 m. The local costmap (in odom) keeps the
    corridor's walls where the camera saw them, beside the robot and out of its view now, and
    gets none where the map cloud lands through the new map -> odom: marked from the map cloud,
    the south wall stood 0.5 m inside the corridor beside the robot, and no camera ray there
    cleared it."""
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import PointCloud2
    from mdr_slam.conversions import arrays_to_pointcloud2
    rospy = rospy_client
    walls = [(-1, 0, 9, 0), (-1, 2, 9, 2)]          # a corridor 2 m wide along x
    g, origin = wall_grid(walls, (-1.5, -1.0), (9.5, 3.5))
    grid_publisher.publish(g, origin)
    xs, zs = np.meshgrid(np.arange(-1.0, 9.0, 0.05), np.arange(0.3, 1.01, 0.1))
    pts = np.vstack([np.column_stack([xs.ravel(), np.full(xs.size, y), zs.ravel()])
                     for y in (0.0, 2.0)])
    pub_pts = rospy.Publisher("/mdr/map/points", PointCloud2, queue_size=1, latch=True)
    costmaps = Recorder(rospy, "/move_base/local_costmap/costmap", OccupancyGrid)
    # the whole window at every publish (else only changed parts, as map_msgs updates)
    full = "/move_base/local_costmap/always_send_full_costmap"
    rospy.set_param(full, True)
    robot = FakeRobot(rospy, (0.3, 1.0, 0.0), room=Room(walls))
    launch = start_move_base(start_process)

    def worst(y0, y1):
        """The highest cost (0-100) of the latest local costmap in odom y [y0, y1], x [1.6, 2.2]."""
        if not costmaps.msgs:
            return None
        c, o, res = msg_grid(costmaps.msgs[-1][1])
        xx, yy = np.meshgrid(np.arange(1.6, 2.2, res / 2), np.arange(y0, y1, res / 2))
        r, cc, inside = cells_of(np.column_stack([xx.ravel(), yy.ravel()]), o, res, c.shape)
        return int(c[r[inside], cc[inside]].max()) if inside.any() else None
    try:
        goal_client(rospy)
        pub_pts.publish(arrays_to_pointcloud2({}, rospy.Time.now(), "map", xyz=pts))
        # seen from x = 0.3: both walls over x 1.6-2.2, within the 4 m window
        seen = wait_for(lambda: (worst(1.95, 2.05) or 0) == 100 and
                        (worst(-0.05, 0.05) or 0) == 100, 60, 0.5)
        with robot.lock:                              # then beside the robot, out of view
            robot.pose = np.array([1.9, 1.0, 0.0])
        time.sleep(2.0)
        robot.map_odom = (0.0, -0.5, 0.0)            # map now puts the walls at odom y 0.5, 2.5
        time.sleep(1.0)                               # tf has the new map -> odom at the stamp
        pub_pts.publish(arrays_to_pointcloud2({}, rospy.Time.now(), "map", xyz=pts))
        time.sleep(3.0)                               # a dozen updates of the costmap
        costmaps.msgs.clear()
        assert wait_for(lambda: costmaps.msgs, 30, 0.2)
        north, south = worst(1.95, 2.05), worst(-0.05, 0.05)
        inside = worst(0.45, 0.55)
    finally:
        costmaps.stop()
        robot.stop()
        pub_pts.unregister()
        launch.stop()
        rospy.delete_param(full)
    print("local costmap: walls seen %s; after the robot passed them and a 0.5 m map -> odom jump, "
          "the highest cost at the north wall %s, the south wall %s, 0.5 m inside: %s"
          % (seen, north, south, inside))
    assert seen
    assert north == 100 and south == 100
    assert inside is not None and inside < 99           # neither lethal nor inscribed


def test_local_costmap_marks_the_lost_cloud_until_the_stretch_ends(rospy_client, start_process,
                                                                   grid_publisher):
    """While tracking is LOST the depth node's single-frame cloud (/mdr/depth/raw_points) is the
    local costmap's only obstacle source: a box it shows 1 m ahead becomes lethal. costmap_2d
    re-marks a source's last cloud at every update, so the filtered cloud seeing through the
    box afterwards cannot clear it; the empty raw cloud that ends the LOST stretch lets it."""
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import PointCloud2
    from mdr_slam.conversions import arrays_to_pointcloud2
    rospy = rospy_client
    walls = [(0, 0, 8, 0), (8, 0, 8, 4), (8, 4, 0, 4), (0, 4, 0, 0)]
    g, origin = wall_grid(walls, (-0.5, -0.5), (8.5, 4.5))
    grid_publisher.publish(g, origin)
    pub_raw = rospy.Publisher("/mdr/depth/raw_points", PointCloud2, queue_size=1)
    pub_depth = rospy.Publisher("/mdr/depth/points", PointCloud2, queue_size=1)
    costmaps = Recorder(rospy, "/move_base/local_costmap/costmap", OccupancyGrid)
    full = "/move_base/local_costmap/always_send_full_costmap"
    rospy.set_param(full, True)
    robot = FakeRobot(rospy, (2.0, 2.0, 0.0))
    launch = start_move_base(start_process)
    yy, zz = np.meshgrid(np.arange(-0.2, 0.21, 0.025), np.arange(0.3, 1.01, 0.05))
    box = np.column_stack([np.full(yy.size, 1.0), yy.ravel(), zz.ravel()])     # base_link
    beyond = box * np.array([1.8, 1.8, 1.0])          # the same rays, 1.8 m ahead: through the box

    def box_cost():
        """The highest cost (0-100) of the latest local costmap at the box, in odom."""
        if not costmaps.msgs:
            return None
        c, o, res = msg_grid(costmaps.msgs[-1][1])
        xx, yb = np.meshgrid(np.arange(2.95, 3.05, res / 2), np.arange(1.85, 2.15, res / 2))
        r, cc, inside = cells_of(np.column_stack([xx.ravel(), yb.ravel()]), o, res, c.shape)
        return int(c[r[inside], cc[inside]].max()) if inside.any() else None

    def cloud(pub, xyz):
        pub.publish(arrays_to_pointcloud2({}, rospy.Time.now(), "base_link", xyz=xyz))

    def settled(expect_lethal, timeout=30):
        def ok():
            costmaps.msgs.clear()
            time.sleep(1.0)                         # updates at 5 Hz, published at 2 Hz
            b = box_cost()
            return b is not None and (b == 100) == expect_lethal
        return wait_for(ok, timeout, 0.1)
    try:
        goal_client(rospy)
        assert wait_for(lambda: pub_raw.get_num_connections() > 0 and
                        pub_depth.get_num_connections() > 0, 30), "move_base did not subscribe"
        assert settled(False), "the box's place is not free before any cloud"
        cloud(pub_raw, box)                           # LOST: the single-frame cloud shows the box
        marked = settled(True)
        for _ in range(5):                            # tracking back: the filtered cloud sees
            cloud(pub_depth, beyond)                  # through it
            time.sleep(0.5)
        kept = box_cost()
        cloud(pub_raw, np.zeros((0, 3)))              # the end of the LOST stretch
        for _ in range(5):
            cloud(pub_depth, beyond)
            time.sleep(0.5)
        cleared = settled(False)
    finally:
        costmaps.stop()
        robot.stop()
        pub_raw.unregister()
        pub_depth.unregister()
        launch.stop()
        rospy.delete_param(full)
    print("box from the LOST cloud lethal: %s; after the filtered cloud saw through it, cost %s; "
          "after the empty LOST cloud, cleared: %s" % (marked, kept, cleared))
    assert marked
    assert kept == 100       # re-marked from the last raw cloud at every update
    assert cleared


def test_plans_keep_to_mapped_floor_rather_than_cut_through_unmapped_space(
        rospy_client, start_process):
    """An L of mapped floor (a corridor the robot drove) round a block the map has nothing of: the
    cameras got no depth from its wall (blank), so the grid leaves it unknown. With the unknown
    cells of /mdr/map/nav_grid at ``nav_grid_unknown`` 10 (the static layer scales them: not
    trinary) the plan from the L's top to its far end takes the L (1.3 times the straight line)
    instead of the straight line through the unmapped block, into the blank wall; a goal inside
    unmapped space is still planned."""
    rospy = rospy_client
    grid_publisher = GridPublisher(rospy, unknown=10)
    g, origin = wall_grid([(0, 0, 10, 0), (10, 0, 10, 6)], (-0.5, -0.5), (10.5, 6.5), fill=-1)
    xx = origin[0] + (np.arange(g.shape[1]) + 0.5) * RES
    yy = origin[1] + (np.arange(g.shape[0]) + 0.5) * RES
    floor = ((yy[:, None] > 0.1) & (yy[:, None] < 1.5)) | ((xx[None] > 8.5) & (xx[None] < 9.9))
    g[floor & (g != 100)] = 0
    grid_publisher.publish(g, origin)
    start, target = (9.2, 5.0), (1.0, 0.8)
    robot = FakeRobot(rospy, (start[0], start[1], 0.0))
    launch = start_move_base(start_process)
    try:
        goal_client(rospy)
        grid_publisher.publish(g, origin)               # again, now that the static layer listens
        def plan_to(t):
            def get():
                p = make_plan(rospy, start, t)
                return [p] if len(p) else None
            got = wait_for(get, 30, 1.0)
            return got[0] if got else None
        xy = plan_to(target)
        into = plan_to((4.0, 4.0))
    finally:
        robot.stop()
        launch.stop()
        grid_publisher.stop()
    assert xy is not None and len(xy), "no plan"
    r, c, inside = cells_of(xy, origin, RES, g.shape)
    unknown = int((g[r[inside], c[inside]] < 0).sum())
    length = float(np.hypot(*np.diff(xy, axis=0).T).sum())
    print("plan of %.1f m (straight line %.1f m), %d of %d poses in unmapped cells; a goal in "
          "unmapped space planned: %s" % (length, math.hypot(start[0] - target[0],
                                                            start[1] - target[1]),
                                          unknown, len(xy), into is not None))
    assert unknown <= 3
    assert into is not None


def test_a_wall_mapped_under_the_base_leaves_it_a_plan(rospy_client, start_process, tmp_path):
    """A partition the fusion node mapped while the localization was off, 0.3 m thick, runs right
    under the base. move_base's recoveries never clear the static map, so with every cell around the base
    lethal or inscribed no plan would ever start ("Failed to get a plan"). The node frees the
    grid's cells within grid_footprint_radius of base_link (the default configuration): the
    base gets a plan out, and reaches the goal."""
    from actionlib_msgs.msg import GoalStatus
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import PointCloud2
    from mdr_slam.conversions import arrays_to_pointcloud2
    rospy = rospy_client
    fusion = yaml.safe_load(open(os.path.join(CONFIG, "fusion.yaml")))
    assert fusion["grid_footprint_radius"] > _nav_yaml("costmap_common_params.yaml")["robot_radius"]
    # the map's cloud on a topic of its own: move_base's costmaps read /mdr/depth/points as what
    # the camera sees now, and the camera does not see the misplaced partition
    fusion.update(map_path=str(tmp_path / "map"), autosave=False, resume=False,
                  tracking_state_topic="", pose_node="", goal_topic="",
                  cloud_topic="/mdr/test/map_cloud")
    (tmp_path / "fusion.yaml").write_text(yaml.safe_dump(fusion))
    # the misplaced partition: 0.3 m thick (a wall fused at several wrong poses), in mid-cells
    walls = [(0, 0, 6, 0), (6, 0, 6, 4), (6, 4, 0, 4), (0, 4, 0, 0)] + \
        [(1, y, 4, y) for y in np.arange(1.875, 2.18, 0.05)]
    cols = Room(walls).cols
    zs = np.arange(0.3, 1.01, 0.1)
    pts = np.column_stack([np.repeat(cols, len(zs), 0), np.tile(zs, len(cols))])
    start, target = (2.5, 2.025), (5.0, 1.0)
    pub = rospy.Publisher("/mdr/test/map_cloud", PointCloud2, queue_size=5)
    grids = Recorder(rospy, "/mdr/map/grid", OccupancyGrid)
    robot = FakeRobot(rospy, (start[0], start[1], 0.0))   # no camera: the map is the cloud below
    launch = start_move_base(start_process, fusion_params=str(tmp_path / "fusion.yaml"))

    def cell(m, x, y):
        g, o, res = msg_grid(m)
        r, c, inside = cells_of(np.array([[x, y]]), o, res, g.shape)
        return int(g[r[0], c[0]]) if inside[0] else None

    def partition_mapped():
        m = grids.msgs[-1][1] if grids.msgs else None
        return m is not None and cell(m, 1.5, start[1]) == 100 and m
    try:
        client = goal_client(rospy)
        assert wait_for(lambda: pub.get_num_connections() > 0, 30), "no fusion node"
        for _ in range(4):       # a cloud in map (camera at the map's origin), seen 4 times
            pub.publish(arrays_to_pointcloud2({}, rospy.Time.now(), "map", xyz=pts))
            time.sleep(0.5)
        m = wait_for(partition_mapped, 30, 0.2)
        assert m, launch.output()[-3000:]
        under, beside = cell(m, *start), cell(m, start[0] + 0.5, start[1])
        # (not ~make_plan: it clears a window around the robot in the global costmap, which
        # lasts until the static layer's next grid)
        client.send_goal(goal(*target))
        client.wait_for_result(rospy.Duration(120))
        state = client.get_state()
        end = robot.xy_yaw()
    finally:
        grids.stop()
        robot.stop()
        pub.unregister()
        launch.stop()
    failed = len(log_lines(launch, "Failed to get a plan"))
    print("grid under the base %s, 0.5 m along the partition %s; goal %s, robot at (%.2f, %.2f); "
          "%d times 'Failed to get a plan'" % (under, beside, state_name(state), end[0], end[1],
                                               failed))
    assert under == 0 and beside == 100
    assert state == GoalStatus.SUCCEEDED
    assert math.hypot(end[0] - target[0], end[1] - target[1]) < 0.3


# ---------------------------------------------------------------------- closed loop, fusion grid
# a 10 x 7 m room split by a wall with a 2.5 m opening at its far end; the robot starts facing
# the wall and is sent behind it
EXPLORE = [(0, 0, 10, 0), (10, 0, 10, 7), (10, 7, 0, 7), (0, 7, 0, 0), (5, 0, 5, 4.5)]
START, GOAL = (1.5, 1.5, 0.0), (8.0, 1.5)


@pytest.fixture(scope="module")
def explore_run(rospy_client, tmp_path_factory):
    """The fusion node maps the room from the robot's depth camera while move_base drives the
    robot to GOAL on the node's /mdr/map/grid and /mdr/map/points. Records the grids, plans,
    the robot's track, move_base's output and its CPU and RSS."""
    import psutil
    from conftest import NodeProcess
    from nav_msgs.msg import OccupancyGrid, Path
    rospy = rospy_client
    d = tmp_path_factory.mktemp("explore")
    fusion = yaml.safe_load(open(os.path.join(CONFIG, "fusion.yaml")))
    fusion.update(map_path=str(d / "map"), autosave=False, resume=False, tracking_state_topic="",
                  pose_node="")
    (d / "fusion.yaml").write_text(yaml.safe_dump(fusion))
    grids = Recorder(rospy, "/mdr/map/grid", OccupancyGrid)
    plans = Recorder(rospy, _plan_topic(), Path)
    robot = FakeRobot(rospy, START, room=Room(EXPLORE))
    launch = NodeProcess(["roslaunch", NAV_LAUNCH, "move_base:=true", "start_pose:=false",
                          "start_depth:=false", "respawn:=false", "mapping_nice:=0",
                          "fusion_params:=%s" % (d / "fusion.yaml")], log=str(d / "launch.log"))
    usage = []
    try:
        client = goal_client(rospy)
        assert wait_for(lambda: grids.msgs, 30, 0.2), launch.output()[-3000:]
        t0 = time.time()
        client.send_goal(goal(*GOAL))
        procs = []
        while time.time() - t0 < 150 and not client.wait_for_result(rospy.Duration(1.0)):
            procs = procs or move_base_pids(launch)
            for p in procs:
                try:
                    usage.append((p.cpu_percent(), p.memory_info().rss / 2 ** 20))
                except psutil.Error:
                    pass
        state = client.get_state()
        duration = time.time() - t0
        client.cancel_all_goals()
    finally:
        grids.stop()
        plans.stop()
        robot.stop()
        launch.stop()
    run = dict(grids=grids.msgs, plans=plans.msgs, robot=robot, launch=launch, state=state,
               duration=duration, usage=np.array(usage[1:]).reshape(-1, 2))
    shapes = [(m.info.width, m.info.height, m.info.origin.position.x, m.info.origin.position.y)
              for _, m in grids.msgs]
    run["resizes"] = sum(a != b for a, b in zip(shapes, shapes[1:]))
    # what the extent would have been without padding: the bounding box of the known cells
    boxes = []
    for _, m in grids.msgs:
        g, origin, res = msg_grid(m)
        r, c = np.nonzero(g >= 0)
        boxes.append((round(origin[0] / res) + c.min(), round(origin[1] / res) + r.min(),
                      round(origin[0] / res) + c.max(), round(origin[1] / res) + r.max())
                     if len(r) else None)
    run["bbox_changes"] = sum(a != b for a, b in zip(boxes, boxes[1:]))
    u = run["usage"]
    end = robot.xy_yaw()
    print("closed loop: goal %s after %.1f s, robot at (%.2f, %.2f); %d grids (%d resizes, the "
          "known cells' bounding box changed %d times; last %d x %d), %d plans; move_base CPU "
          "median %.1f %% max %.1f %% of a core, RSS median %.0f max %.0f MB"
          % (state_name(state), duration, end[0], end[1], len(grids.msgs), run["resizes"],
             run["bbox_changes"], shapes[-1][0] if shapes else 0, shapes[-1][1] if shapes else 0,
             len(plans.msgs), *(np.r_[np.median(u[:, 0]), u[:, 0].max(), np.median(u[:, 1]),
                                      u[:, 1].max()] if len(u) else np.zeros(4))))
    return run


def _grid_before(grids, t):
    """The latest grid that arrived at or before ``t`` (None before the first)."""
    best = None
    for ta, m in grids:
        if ta <= t:
            best = m
    return best


@pytest.mark.slow
def test_growing_grid_no_plan_crosses_an_occupied_cell(explore_run):
    """While the fusion node's grid grows, no global plan crosses a cell the grid has marked
    occupied for long enough for the global costmap to have it (in the grid that arrived 1.5 s
    before the plan, one costmap update period and some, and still in the latest), and every
    plan starts at the robot. The robot gets behind the wall."""
    from actionlib_msgs.msg import GoalStatus
    run = explore_run
    crossing, off_start, n = [], [], 0
    for t, p in run["plans"]:
        if not p.poses:
            continue
        n += 1
        old, new = _grid_before(run["grids"], t - 1.5), _grid_before(run["grids"], t)
        xy = np.array([(q.pose.position.x, q.pose.position.y) for q in p.poses])
        at = run["robot"].pose_at(t)
        if np.hypot(*(xy[0] - at)) > 0.25:
            off_start.append(round(float(np.hypot(*(xy[0] - at))), 2))
        if old is None:
            continue
        hits = 0
        for m in (old, new):
            g, origin, res = msg_grid(m)
            r, c, inside = cells_of(xy, origin, res, g.shape)
            occ = np.zeros(len(xy), bool)
            occ[inside] = g[r[inside], c[inside]] == 100
            hits = occ if m is old else hits & occ
        if hits.any():
            crossing.append((round(t, 1), int(hits.sum())))
    print("closed loop: %d plans, %d cross occupied cells (time, poses in occupied cells) %s; "
          "%d do not start at the robot %s; %d grid resizes" % (
              n, len(crossing), crossing[:5], len(off_start), off_start[:5], run["resizes"]))
    assert n >= 3
    assert run["resizes"] <= 3 < run["bbox_changes"]
    assert not crossing
    assert not off_start
    assert run["state"] == GoalStatus.SUCCEEDED
    end = run["robot"].xy_yaw()
    assert math.hypot(end[0] - GOAL[0], end[1] - GOAL[1]) < 0.3


@pytest.mark.slow
def test_robot_stays_inside_the_global_costmap(explore_run):
    """Every grid the fusion node publishes holds the robot with room for its radius (the global
    costmap is the grid's extent: a robot off it cannot plan, and a depth sensor off it clears
    nothing), and move_base never says otherwise."""
    run = explore_run
    radius = _nav_yaml("costmap_common_params.yaml")["robot_radius"]
    outside = []
    for t, m in run["grids"]:
        g, origin, res = msg_grid(m)
        at = run["robot"].pose_at(t)
        lo = np.array(origin) + radius
        hi = np.array(origin) + res * np.array([g.shape[1], g.shape[0]]) - radius
        if not ((at >= lo).all() and (at <= hi).all()):
            outside.append((round(t, 1), tuple(np.round(at, 2))))
    said = log_lines(run["launch"], "off the global costmap", "out of map bounds",
                     "out of bounds", "Sensor origin")
    print("closed loop: the robot outside %d of %d grids %s; move_base: %d lines %s" % (
        len(outside), len(run["grids"]), outside[:3], len(said), said[:3]))
    assert not outside
    assert not said


# ---------------------------------------------------------------------- live: tf age
TF_AGE_PLAY = 0.5   # play rate: 2 cores shared with the test's own process under CI load
TF_AGE_WALL_S = 35.0  # s of wall time sampled (the bag's first 17 s: start, a turn, keyframes)
@pytest.mark.slow
def test_live_tf_is_fresh_enough_for_move_base(rospy_client, start_process, sample_bag):
    """The whole stack on the sample bag (tracking, depth, fusion, move_base; no wheel odometry,
    so tf odom -> base_link comes from the tracker at the image stamps): the transform
    map -> base_link move_base looks up is older than the costmaps' transform_tolerance in less
    than 1 % of the samples, and move_base never reports a transform timeout (it stops planning
    and driving then). The bag plays at TF_AGE_PLAY: what is tested is that tf keeps coming
    (no stall in tracking, keyframes or relocalization); how old it is at full rate is the
    tracker's latency on the machine's load, a benchmark figure (README, Limitations)."""
    import psutil
    import tf2_ros
    rospy = rospy_client
    tol = _nav_yaml("costmap_common_params.yaml")["transform_tolerance"]
    buf = tf2_ros.Buffer(cache_time=rospy.Duration(10.0))
    listener = tf2_ros.TransformListener(buf)
    launch = start_process(["roslaunch", NAV_LAUNCH, "move_base:=true", "respawn:=false",
                            "delay:=3", "rate:=%g" % TF_AGE_PLAY,
                            "bag:=" + os.path.join(sample_bag, "sequence.bag")], "live")
    ages, usage, procs = [], [], []
    try:
        # the launch sets /use_sim_time: this process keeps wall time, so ages are measured
        # against the bag's /clock as move_base sees it
        from rosgraph_msgs.msg import Clock
        clock = []
        sub = rospy.Subscriber("/clock", Clock, lambda m: clock.append(m.clock.to_sec()),
                               queue_size=5)
        assert wait_for(lambda: clock, 60, 0.2), launch.output()[-3000:]
        t_end = time.time() + TF_AGE_WALL_S
        last, moved, t_usage = None, time.time(), 0.0
        while time.time() < t_end:
            time.sleep(0.05)
            if clock[-1] != last:
                last, moved = clock[-1], time.time()
            elif time.time() - moved > 1.0:
                break                                          # the bag has ended
            try:
                ts = buf.lookup_transform("map", "base_link", rospy.Time(0))
                ages.append(clock[-1] - ts.header.stamp.to_sec())
            except tf2_ros.TransformException:
                pass
            procs = procs or move_base_pids(launch)
            if time.time() - t_usage >= 1.0:                  # CPU over whole seconds
                t_usage = time.time()
                for p in procs:
                    try:
                        usage.append((p.cpu_percent(), p.memory_info().rss / 2 ** 20))
                    except psutil.Error:
                        pass
        sub.unregister()
    finally:
        listener.unregister()
        launch.stop()
    timeouts = log_lines(launch, "transform timeout")
    a, u = np.array(ages), np.array(usage[1:]).reshape(-1, 2)
    print("live: tf map -> base_link age over %d samples: median %.3f p90 %.3f p99 %.3f max %.3f s "
          "(transform_tolerance %.2f s); move_base transform timeouts: %d %s; move_base CPU median "
          "%.1f %% max %.1f %% of a core, RSS median %.0f max %.0f MB"
          % (len(a), np.median(a), np.percentile(a, 90), np.percentile(a, 99), a.max(), tol,
             len(timeouts), timeouts[:2], np.median(u[:, 0]), u[:, 0].max(), np.median(u[:, 1]),
             u[:, 1].max()))
    assert len(a) > 200
    # move_base looks 5 times a second: it meets the tail
    assert np.percentile(a, 99) < tol, "%d of %d samples older than %.2f s (largest %s); %s" % (
        (a >= tol).sum(), len(a), tol, np.sort(a)[-5:],
        log_lines(launch, "tracking ", "LOST", "reset")[-10:])
    assert not timeouts


# ---------------------------------------------------------------------- a driver bag replayed
REPLAY_S = 12.0     # s of the corridor drive (as tests/ros/test_robot_input_e2e.py)
REPLAY_PLAY = 0.5   # play rate: full-resolution pairs at 10 Hz wall on a 2-core machine


@pytest.mark.slow
def test_driver_bag_replay_plans_keep_clear_of_the_true_obstacles(rospy_client, start_process,
                                                                   tmp_path):
    """A driver bag (zed topics, the camera chain on /tf_static, wheel odometry; the corridor
    drive) through navigation.launch move_base:=true with the tracker's poses. The bag's robot
    does not obey move_base: the test is the plans move_base makes on the live grid, from where
    the recorded robot is to a point further along its drive, as it drives. Taken into the
    scene's frame (ground truth at the first tracked frame), every plan keeps the robot's radius,
    less the tracker's drift and a cell of each grid, from the true walls wherever the grid had
    mapped (unmapped cells are free to the planner and replanned once seen)."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import OccupancyGrid
    from mdr_slam.conversions import pose_stamped_to_matrix
    from mdr_slam.eval.navigation import true_grid
    from mdr_slam.geometry import quat_to_R
    from mdr_slam.nav import world_to_cell
    from mdr_slam.sim import make_scene
    from mdr_slam.sim.driver import generate_driver
    rospy = rospy_client
    d = str(tmp_path / "bag")
    generate_driver(d, scene="corridor", driver="zed", duration=REPLAY_S, rate=20.0,
                    map_cell=0.05)
    info = yaml.safe_load(open(os.path.join(d, "driver.yaml")))
    gt = np.loadtxt(os.path.join(d, "groundtruth.tum"))

    def T_world_cam(t):
        row = gt[np.argmin(np.abs(gt[:, 0] - t))]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = quat_to_R(row[4:8]), row[1:4]
        return T
    fusion = yaml.safe_load(open(os.path.join(CONFIG, "fusion.yaml")))
    fusion.update(map_path=str(tmp_path / "auto.ply"), autosave_period=0.0, resume=False)
    (tmp_path / "fusion.yaml").write_text(yaml.safe_dump(fusion))
    poses, asked = [], []     # /mdr/pose (stamp, T_map_cam); (time, plan) from make_plan
    n_refused = 0
    sub = rospy.Subscriber("/mdr/pose", PoseStamped, lambda m: poses.append(
        (m.header.stamp.to_sec(), pose_stamped_to_matrix(m))))
    grids = Recorder(rospy, "/mdr/map/grid", OccupancyGrid)
    t = info["topics"]
    # planar_motion false: this bag's camera follows the scene's path, which bobs 3 cm up and
    # down; a planar tracker cannot follow that, and its wheel odometry check then refuses the
    # poses (the closed-loop robot, whose base keeps to the floor, runs planar)
    launch = start_process(["roslaunch", NAV_LAUNCH, "move_base:=true", "respawn:=false",
                            "planar_motion:=false",
                            "bag:=" + os.path.join(d, "sequence.bag"), "delay:=3",
                            "rate:=%.2f" % REPLAY_PLAY, "left_image:=" + t["left_image"],
                            "right_image:=" + t["right_image"], "left_info:=" + t["left_info"],
                            "right_info:=" + t["right_info"],
                            "fusion_params:=%s" % (tmp_path / "fusion.yaml")], "replay")
    try:
        assert wait_for(lambda: poses, 90, 0.2), launch.output()[-3000:]
        # the map frame in the scene's: the ground truth and the tracker at its first pose
        t0, T0 = poses[0]
        W = T_world_cam(t0) @ np.linalg.inv(T0)
        ahead = T_world_cam(gt[0, 0] + 0.8 * REPLAY_S)[:3, 3]
        g_map = np.linalg.inv(W) @ np.r_[ahead, 1.0]
        # move_base's global plan from the tracked camera to the goal (~make_plan: the planner a
        # goal would run, on the same costmap) every half second (wall) while the bag plays
        t_end = time.time() + 60 + REPLAY_S / REPLAY_PLAY
        while poses[-1][0] < gt[-1, 0] - 0.2 and time.time() < t_end:
            try:
                asked.append((rospy.get_time(), make_plan(rospy, poses[-1][1][:2, 3],
                                                          g_map[:2])))
            except rospy.ServiceException:   # no plan (yet): a start outside the costmap
                n_refused += 1
            time.sleep(0.5)
    finally:
        sub.unregister()
        grids.stop()
        launch.stop()
    scene = make_scene("corridor", seed=0)
    tg = true_grid(scene)
    radius = _nav_yaml("costmap_common_params.yaml")["robot_radius"]
    worst = []
    n_known = n_unknown = 0
    for ta, xy in asked:
        xy = xy.reshape(-1, 2)
        if not len(xy):
            continue
        w = (W @ np.c_[xy, np.zeros(len(xy)), np.ones(len(xy))].T).T[:, :2]
        rc = world_to_cell(w, tg.origin, tg.resolution)
        inside = (rc >= 0).all(1) & (rc[:, 0] < tg.occ.shape[0]) & (rc[:, 1] < tg.occ.shape[1])
        assert inside.all(), "a plan leaves the scene"
        # unmapped space may be crossed (it is free in nav_grid and replanned once seen): only
        # the poses in cells the grid had seen when the plan was made count
        gm = _grid_before(grids.msgs, ta)
        if gm is None:
            continue
        g, origin, res = msg_grid(gm)
        gc = world_to_cell(xy, origin, res)
        ing = (gc >= 0).all(1) & (gc[:, 0] < g.shape[0]) & (gc[:, 1] < g.shape[1])
        known = np.zeros(len(xy), bool)
        known[ing] = g[gc[ing, 0], gc[ing, 1]] >= 0
        n_known += int(known.sum())
        n_unknown += int((~known).sum())
        if known.any():
            worst.append(float(tg.clearance(w[known]).min()))
    # the tracker's pose drift over the drive (live ATE 0.3-0.6 % of the path) and the grid's cells
    drift = np.linalg.norm((W @ poses[-1][1])[:3, 3] - T_world_cam(poses[-1][0])[:3, 3])
    print("replay: %d poses, %d plans (%d make_plan calls failed; %d poses in mapped cells, %d "
          "in unmapped ones), smallest true clearance of a plan's centre line in mapped cells %.3f m (robot radius %.2f m), "
          "tracker drift at the end %.3f m"
          % (len(poses), len(asked), n_refused, n_known, n_unknown,
             min(worst) if worst else float("nan"), radius, drift))
    # enough evidence, not a figure: how many plan poses fall in mapped cells depends on how far
    # the grid has come when each plan is made, which moves with the machine's load (400-600)
    assert len(worst) >= 10 and n_known >= 250, launch.output()[-3000:]
    assert min(worst) >= radius - drift - 2 * tg.resolution, sorted(worst)[:5]
