"""A looping bag's lap boundary: the last messages of a lap delivered
after the clock jumped back to the start.

Found in 10-minute looped runs of the sample under bursty CPU load: the map jumped by up to 15 k
points at lap starts (all eight jumps of four runs came within 35 frames of a lap boundary).
With a debug hook comparing every pose the nodes used with the same stamp's pose on the first lap,
the fusion node integrated the old lap's last cloud 0.65 m / 34 deg off: the clock had jumped
back, tf2_ros had cleared its buffer, a late tf of the old lap's end went into the new buffer,
and the lookup at the cloud's (old) stamp interpolated between the new lap's first poses and that
stale one. Now a message stamped more than ``max_future_stamp`` ahead of the clock is dropped by
the pose node (pose, stereo pair), the depth node (stereo pair, tf) and the fusion node (cloud,
tf). This test replays that order of events under a test-driven /clock.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from conftest import wait_for
from mdr_slam import conversions as cv
from mdr_slam.geometry import make_T, transform_points
from scipy.spatial.transform import Rotation

pytestmark = pytest.mark.ros

T0 = 100.0          # the lap's first stamp; a lap is 4 s
WALL_Z = 3.0        # the wall: the plane z = 3 m of map


def _pose(t):
    """map <- camera: a camera at the origin turning back and forth about its y axis
    (0, +40, 0, -40, 0 deg over the lap): tf's interpolation across the lap is wrong."""
    yaw = 40.0 * np.sin(np.pi * (t - T0) / 2.0)
    return make_T(Rotation.from_euler("y", yaw, degrees=True).as_matrix(), [0.0, 0.0, 0.0])


def _cloud(t, rng):
    """Points of the wall z = WALL_Z (map) seen from the camera at time t, in the camera frame."""
    Pw = np.column_stack([rng.uniform(-1.5, 1.5, (3000, 2)), np.full(3000, WALL_Z)])
    return transform_points(np.linalg.inv(_pose(t)), Pw).astype(np.float32)


class SimClock:
    """Publishes /clock every 10 ms (rospy's sim-time waits need it to keep coming)."""

    def __init__(self, rospy, t):
        from rosgraph_msgs.msg import Clock
        self.rospy, self.Clock, self.t = rospy, Clock, t
        self.pub = rospy.Publisher("/clock", Clock, queue_size=10)
        self.stop = False
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self.stop:
            self.pub.publish(self.Clock(clock=self.rospy.Time.from_sec(self.t)))
            time.sleep(0.01)


def test_old_lap_messages_after_the_clock_jumped_back_are_dropped(rospy_client, start_process,
                                                                  tmp_path):
    rospy = rospy_client   # a wall-clock client; the nodes run on the /clock it publishes
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import PointCloud2
    from tf2_msgs.msg import TFMessage
    from mdr_slam_msgs.srv import SaveMap
    from mdr_slam.io import read_cloud
    clock = SimClock(rospy, T0)
    rospy.set_param("/use_sim_time", True)
    try:
        name = "fusion_tj"
        fusion = start_process(
            ["rosrun", "mdr_slam", "fusion_node", "__name:=" + name,
             "_map_path:=%s" % (tmp_path / "auto.ply"), "_autosave_period:=0.0",
             "_map_dir:=%s" % tmp_path,
             "_voxel_size:=0.05", "_clean_every:=0", "_tf_timeout:=0.3", "_publish_rate:=0.0",
             "_tracking_state_topic:=", "/mdr/depth/points:=/tj/cloud", "/mdr/keyframes:=/tj/kf",
             "/mdr/map/points:=/tj/map", "/mdr/map/grid:=/tj/grid"], name)
        pose = start_process(
            ["rosrun", "mdr_slam", "pose_node", "__name:=pose_tj", "_source:=groundtruth",
             "_publish_tf:=false", "ground_truth_pose:=/tj/gt", "/mdr/pose:=/tj/pose",
             "/mdr/odom:=/tj/odom", "/mdr/path:=/tj/path"], "pose_tj")
        from test_depth_node import StereoPublisher, _node_cmd, _pair
        depth = start_process(_node_cmd("depth_tj", "/tj/", "_camera_frame:=cam_tj",
                                         "_tracking_state_topic:=", "/mdr/depth/points:=/tj/depth"),
                              "depth_tj")
        depth_stamps = []
        rospy.Subscriber("/tj/depth", PointCloud2,
                         lambda m: depth_stamps.append(m.header.stamp.to_sec()))
        sp = StereoPublisher(rospy, "/tj/")
        left, right = _pair()
        relayed = []
        rospy.Subscriber("/tj/pose", PoseStamped, lambda m: relayed.append(m.header.stamp.to_sec()))
        pub_gt = rospy.Publisher("/tj/gt", PoseStamped, queue_size=50)
        pub_cloud = rospy.Publisher("/tj/cloud", PointCloud2, queue_size=50)
        pub_tf = rospy.Publisher("/tf", TFMessage, queue_size=50)
        assert wait_for(lambda: pub_cloud.get_num_connections() > 0
                        and pub_gt.get_num_connections() > 0
                        and pub_tf.get_num_connections() > 0 and sp.connected(), 60), \
            fusion.output() + depth.output()
        rospy.wait_for_service("/%s/save_map" % name, 30)
        rng = np.random.default_rng(0)

        def at(t):
            return rospy.Time.from_sec(t)

        def tf(t):
            pub_tf.publish(TFMessage([cv.matrix_to_transform_stamped(_pose(t), at(t), "map",
                                                                     "cam_tj")]))

        def cloud(t):
            pub_cloud.publish(cv.arrays_to_pointcloud2({}, at(t), "cam_tj", xyz=_cloud(t, rng)))

        def gt(t):
            pub_gt.publish(cv.matrix_to_pose_stamped(_pose(t), at(t), "map"))

        def pair(t):
            sp.publish(at(t), left, right)

        def step_to(t):   # the clock runs a little ahead of the stamps, as under rosbag play
            clock.t = t + 0.02
            time.sleep(0.06)

        # lap 1: tf every 0.1 s, a cloud every 0.5 s, a ground-truth pose for the relay
        for k in range(41):
            t = T0 + 0.1 * k
            step_to(t)
            tf(t)
            gt(t)
            if k % 5 == 0 and k < 40:
                time.sleep(0.05)
                cloud(t)
                pair(t)
        assert wait_for(lambda: len(relayed) >= 41, 20), pose.output()
        assert wait_for(lambda: len(depth_stamps) >= 6, 20), depth.output()
        time.sleep(1.0)
        # the bag loops: the clock jumps back; the new lap's first poses arrive
        step_to(T0)
        time.sleep(0.3)
        for k in range(4):
            step_to(T0 + 0.1 * k)
            tf(T0 + 0.1 * k)
        n_relayed = len(relayed)
        # ... then the old lap's end, late: its last tf, its last ground-truth pose and a cloud
        tf(T0 + 4.0)
        gt(T0 + 3.95)
        time.sleep(0.1)
        pair(T0 + 3.3)
        cloud(T0 + 3.3)   # true yaw -32 deg; interpolated between 100.3 s and 104 s: +3 deg
        time.sleep(1.0)
        # the new lap goes on normally
        for k in range(4, 11):
            t = T0 + 0.1 * k
            step_to(t)
            tf(t)
            if k % 5 == 0:
                time.sleep(0.05)
                cloud(t)
        time.sleep(1.5)
        r = rospy.ServiceProxy("/%s/save_map" % name, SaveMap)(str(tmp_path / "map.ply"), "")
        assert r.success, r.message
        c = read_cloud(r.path)
        P = np.column_stack([c["x"], c["y"], c["z"]])
        off = np.abs(P[:, 2] - WALL_Z)
        log = fusion.output()
        # every map point is on the wall: the old lap's cloud was not placed with a pose
        # interpolated across the jump (without the check: hundreds of points 0.1-1 m off)
        assert len(P) > 500, log
        assert off.max() < 0.06, (np.sort(off)[-10:], log)
        assert "ahead of the clock" in log, log
        # the depth node did not match and publish the old lap's pair in the new lap
        assert not any(abs(t - (T0 + 3.3)) < 1e-3 for t in depth_stamps), (depth_stamps,
                                                                              depth.output())
        assert "ahead of the clock" in depth.output(), depth.output()
        # the relay did not put the old lap's pose into the new lap's tf and /mdr/pose
        assert len(relayed) == n_relayed, (relayed[n_relayed:], pose.output())
        assert "ahead of the clock" in pose.output(), pose.output()
    finally:
        clock.stop = True
        clock.thread.join(1.0)
        clock.pub.unregister()
        rospy.delete_param("/use_sim_time")
