"""Node 3: confidence-based global map fusion -> /mdr/map/points, /mdr/map/grid, map services."""
from __future__ import annotations


def main():
    import rospy
    rospy.init_node("fusion_node")
    rospy.logwarn("fusion_node: not implemented yet (issue [fusion]); publishing nothing.")
    rospy.spin()
