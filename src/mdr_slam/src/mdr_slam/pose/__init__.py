"""Node 1 core: ORB-SLAM2-style stereo visual SLAM (Frame, KeyFrame, MapPoint, Map, Tracking,
LocalMapping, LoopClosing, ORBmatcher, Optimizer, KeyFrameDatabase, System).

Entry point: :class:`System` (see mdr_slam.pose.system), or :func:`make_system`
(mdr_slam.pose.factory) for the tracker the ``backend`` parameter names (``orbslam3``: ORB-SLAM3's
C++ tracker, mdr_slam.pose.orbslam3). ROS-free.
"""
from __future__ import annotations

from .config import TrackerConfig
from .factory import make_system
from .frame import Frame, compute_stereo_matches
from .local_mapping import LocalMapping
from .map import KeyFrame, Map, MapPoint
from .matcher import ORBmatcher
from .optimizer import Optimizer
from .orb import ORBextractor
from .result import TrackResult
from .system import System
from .tracking import LOST, NOT_INITIALIZED, OK, RELOCALIZED, Tracking

__all__ = ["Frame", "KeyFrame", "Map", "MapPoint", "ORBmatcher", "Optimizer", "ORBextractor",
           "System", "TrackResult", "TrackerConfig", "make_system", "Tracking", "LocalMapping",
           "compute_stereo_matches", "NOT_INITIALIZED", "OK", "LOST", "RELOCALIZED"]
