"""Node 1: pose estimation. Publishes /mdr/pose, /mdr/odom, /mdr/path and tf (REP-105).

``~source``: ``orb`` (ORB-SLAM2-style stereo tracking from mdr_slam.pose) or ``groundtruth``
(relay a ground-truth PoseStamped of the left camera optical frame in ``map``, e.g. the simulator's
``/ground_truth/pose``, so depth and fusion can be developed and measured without tracking error).
"""
from __future__ import annotations

import numpy as np

from .common import StampGuard, Throttled, get_params, parse_transform

DEFAULTS = {
    "source": "orb",
    "map_frame": "map",
    "odom_frame": "odom",
    "base_frame": "base_link",
    "camera_frame": "camera_left_optical_frame",
    "base_to_camera": "",          # T_base_camera "x y z qx qy qz qw"; empty = identity
    "publish_tf": True,
    "path_max_length": 100000,
}


class PoseRelay:
    """Publishes a camera pose stream as pose, odometry, path and tf (map -> odom -> base_link)."""

    def __init__(self, p: dict):
        import rospy
        import tf2_ros
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry, Path
        self.p = p
        self.T_base_cam = parse_transform(p["base_to_camera"])
        self.pub_pose = rospy.Publisher("/mdr/pose", PoseStamped, queue_size=10)
        self.pub_odom = rospy.Publisher("/mdr/odom", Odometry, queue_size=10)
        self.pub_path = rospy.Publisher("/mdr/path", Path, queue_size=1, latch=True)
        self.tf = tf2_ros.TransformBroadcaster() if p["publish_tf"] else None
        self.static_tf = tf2_ros.StaticTransformBroadcaster() if p["publish_tf"] else None
        self.path = Path()
        self.path.header.frame_id = p["map_frame"]
        self.guard = StampGuard()
        self.warn = Throttled()
        if self.static_tf is not None:
            from ..conversions import matrix_to_transform_stamped
            self.static_tf.sendTransform(matrix_to_transform_stamped(
                self.T_base_cam, rospy.Time(0), p["base_frame"], p["camera_frame"]))

    def publish(self, stamp, T_map_cam: np.ndarray) -> None:
        from nav_msgs.msg import Odometry
        from ..conversions import matrix_to_pose, matrix_to_pose_stamped, matrix_to_transform_stamped
        from ..geometry import inv_T, is_valid_T
        p = self.p
        if not is_valid_T(T_map_cam):
            self.warn("nan", "pose at %.3f is not a finite rigid transform; skipped" % stamp.to_sec())
            return
        state = self.guard.check(stamp.to_sec())
        if state == "backwards":
            self.warn("back", "time went backwards (bag loop?); clearing the path")
            del self.path.poses[:]
        elif state == "duplicate":
            self.warn("dup", "duplicate pose stamp %.3f; skipped" % stamp.to_sec())
            return
        ps = matrix_to_pose_stamped(T_map_cam, stamp, p["map_frame"])
        self.pub_pose.publish(ps)
        T_map_base = T_map_cam @ inv_T(self.T_base_cam)
        odom = Odometry()
        odom.header = ps.header
        odom.header.frame_id = p["odom_frame"]
        odom.child_frame_id = p["base_frame"]
        odom.pose.pose = matrix_to_pose(T_map_base)  # map -> odom is identity for the relay
        self.pub_odom.publish(odom)
        self.path.header.stamp = stamp
        self.path.poses.append(ps)
        if len(self.path.poses) > p["path_max_length"]:
            del self.path.poses[: len(self.path.poses) - p["path_max_length"]]
        self.pub_path.publish(self.path)
        if self.tf is not None:
            self.tf.sendTransform([
                matrix_to_transform_stamped(np.eye(4), stamp, p["map_frame"], p["odom_frame"]),
                matrix_to_transform_stamped(T_map_base, stamp, p["odom_frame"], p["base_frame"]),
            ])


def main():
    import rospy
    from geometry_msgs.msg import PoseStamped
    from ..conversions import ConversionError, pose_stamped_to_matrix
    rospy.init_node("pose_node")
    p = get_params(DEFAULTS)
    relay = PoseRelay(p)
    if p["source"] == "groundtruth":
        def on_gt(msg):
            try:
                T = pose_stamped_to_matrix(msg)
            except ConversionError as e:
                relay.warn("bad", "ground-truth pose skipped: %s" % e)
                return
            relay.publish(msg.header.stamp, T)
        rospy.Subscriber("ground_truth_pose", PoseStamped, on_gt, queue_size=100)
        rospy.loginfo("pose_node: relaying ground truth from %s",
                      rospy.resolve_name("ground_truth_pose"))
    elif p["source"] == "orb":
        rospy.logwarn("pose_node: ORB tracking (source:=orb) is not implemented yet; "
                      "use pose_source:=groundtruth. Publishing nothing.")
    else:
        rospy.logerr("pose_node: unknown ~source %r (orb or groundtruth)", p["source"])
    rospy.spin()
