"""MDR-SLAM: modular decoupled stereo dense mapping (ROS 1).

The algorithms live here, free of ROS: ``mdr_slam.pose`` (ORB-SLAM2-style tracking, local BA,
loop closure), ``mdr_slam.depth`` (ELAS + keyframe-guided Kalman temporal filter),
``mdr_slam.fusion`` (confidence-based global map), ``mdr_slam.camera`` and ``mdr_slam.geometry``,
``mdr_slam.io`` (maps, trajectories, bags), ``mdr_slam.sim`` (stereo simulator with exact ground
truth) and ``mdr_slam.eval`` (the paper's metrics). ``mdr_slam.conversions`` is the only bridge
between ROS messages and numpy, and ``mdr_slam.nodes`` holds the thin rospy shells.
"""
__version__ = "0.1.0"
