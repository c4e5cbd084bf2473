"""Node 2: ELAS stereo depth with the keyframe-guided Kalman temporal filter -> /mdr/depth/points."""
from __future__ import annotations


def main():
    import rospy
    rospy.init_node("depth_node")
    rospy.logwarn("depth_node: not implemented yet (issue [depth]); publishing nothing.")
    rospy.spin()
