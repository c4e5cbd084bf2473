"""pose_node with source:=groundtruth relays a ground-truth pose as pose, odometry, path and tf."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import wait_for
from mdr_slam import conversions as cv
from mdr_slam.geometry import make_T, quat_to_R

pytestmark = pytest.mark.ros


def test_groundtruth_relay_publishes_pose_path_and_tf(rospy_client, start_process):
    rospy = rospy_client
    import tf2_ros
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path
    node = start_process(["rosrun", "mdr_slam", "pose_node", "_source:=groundtruth",
                          "__name:=relay_test", "ground_truth_pose:=/gt_test"], "relay")
    got, paths = [], []
    subs = [rospy.Subscriber("/mdr/pose", PoseStamped, got.append),
            rospy.Subscriber("/mdr/path", Path, paths.append)]
    pub = rospy.Publisher("/gt_test", PoseStamped, queue_size=10)
    assert wait_for(lambda: pub.get_num_connections() > 0 and
                    all(s.get_num_connections() > 0 for s in subs), 20), node.output()
    buf = tf2_ros.Buffer()
    tf2_ros.TransformListener(buf)
    T = make_T(quat_to_R([0.2, 0.1, -0.3, 0.9]), [1.0, 2.0, 0.5])
    base = rospy.Time.now()
    for i in range(5):   # 10 cm apart: every pose joins the path
        Ti = T.copy()
        Ti[0, 3] += 0.1 * i
        pub.publish(cv.matrix_to_pose_stamped(Ti, base + rospy.Duration(0.1 * i), "map"))
        rospy.sleep(0.05)
    T = Ti
    Tn = T.copy()
    Tn[0, 3] += 0.001   # 1 mm on: on /mdr/pose, not a new path pose (path_min_translation)
    pub.publish(cv.matrix_to_pose_stamped(Tn, base + rospy.Duration(0.5), "map"))
    rospy.sleep(0.05)
    bad = cv.matrix_to_pose_stamped(T, base + rospy.Duration(1.0), "map")
    bad.pose.position.x = float("nan")
    pub.publish(bad)  # must be skipped, not crash the node
    assert wait_for(lambda: len(got) >= 6, 10), node.output()
    np.testing.assert_allclose(cv.pose_stamped_to_matrix(got[-1]), Tn, atol=1e-9)
    assert len(got) == 6
    assert wait_for(lambda: paths and len(paths[-1].poses) == 5, 5)
    rospy.sleep(1.0)   # two path periods: still the 5 poses 10 cm apart
    assert len(paths[-1].poses) == 5
    tf = wait_for(lambda: buf.can_transform("map", "camera_left_optical_frame",
                                            base + rospy.Duration(0.4)), 5)
    assert tf
    ts = buf.lookup_transform("map", "camera_left_optical_frame", base + rospy.Duration(0.4))
    np.testing.assert_allclose(cv.transform_stamped_to_matrix(ts), T, atol=1e-6)
    assert node.proc.poll() is None, "pose_node died:\n" + node.output()
