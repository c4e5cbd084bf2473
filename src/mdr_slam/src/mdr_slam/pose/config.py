"""The pose tracker's configuration (ORB-SLAM2's settings file): the parameters a user tunes,
shared by both backends (System and ORBSLAM3System) and the factory that picks one
(mdr_slam.pose.factory). The pose node's own parameters are nodes.pose_node.PoseNodeConfig;
config/pose.yaml overrides both. The tracker's tuned internals are named constants in the
modules that use them (tracking.py, local_mapping.py, loop_closing.py, system.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..config import Config

__all__ = ["TrackerConfig"]


@dataclass
class TrackerConfig(Config):
    backend: str = "mdr"            # mdr (this tracker) or orbslam3 (ORB-SLAM3's C++ tracker, pyorbslam3)
    orbslam3_vocabulary: str = ""   # orbslam3: DBoW2 text vocabulary (ORBvoc.txt); empty: ours, exported
    vocabulary: str = ""            # ORB vocabulary npz (mdr vocab); empty: the package's data/orb_vocab.npz
    n_features: int = 1500          # ORB features per image (ORB-SLAM2 EuRoC/KITTI: 1200-2000)
    scale_factor: float = 1.2       # scale between ORB pyramid levels (ORB-SLAM2: 1.2)
    n_levels: int = 8               # ORB pyramid levels (ORB-SLAM2: 8)
    fast_threshold: int = 12        # FAST corner threshold, grey levels (ORB-SLAM2 iniThFAST: 20)
    min_fast_threshold: int = 5     # poor grid cells re-detected at this threshold (ORB-SLAM2 minThFAST; 0: off)
    th_depth: float = 35.0          # close points: depth < th_depth x baseline (ORB-SLAM2 ThDepth)
    max_frames: int = 20            # a keyframe at least every max_frames frames (ORB-SLAM2: camera fps)
    local_ba: bool = True           # local bundle adjustment after each keyframe (LocalMapping)
    ba_process: bool = False        # threads: local BA in a child process (worth it with a spare core)
    loop_closing: bool = True       # detect and close loops (false: odometry with a local map only)
    global_ba: bool = True          # global bundle adjustment after each loop correction
    planar_motion: Any = "false"    # a ground robot on a flat floor: base_link's height, roll and pitch held in
    #                                 map, x, y and yaw solved (RTAB-Map Reg/Force3DoF): true; auto (when the
    #                                 frames carry wheel odometry); false (a camera that bobs or pitches, ramps)
