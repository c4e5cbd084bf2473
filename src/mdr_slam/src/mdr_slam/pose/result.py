"""TrackResult: what ``track`` returns, from either pose backend (System, ORBSLAM3System)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np

__all__ = ["TrackResult"]


@dataclass
class TrackResult:
    stamp: float
    state: str                                 # NOT_INITIALIZED, OK, LOST, RELOCALIZED
    T_map_cam: Optional[np.ndarray]            # 4x4, None unless OK/RELOCALIZED
    n_tracked: int
    is_keyframe: bool
    keyframe_id: int                           # new keyframe id, or -1
    corrections: Optional[Tuple[str, int, Dict[int, Tuple[float, np.ndarray]]]]
    time_ms: float
    ref_keyframe_id: int = -1
    n_map_points: int = 0
    n_keyframes: int = 0
    n_loop_closures: int = 0
    n_visual_odometry: int = 0                 # frames so far tracked frame to frame (map behind)
    n_odom_refused: int = 0                    # poses so far refused: the wheel odometry contradicted them
    odom_refusal: Optional[Tuple[float, float, float, int, str]] = None   # this frame's: m, deg
    #         off the odometry's prediction, m travelled since the last tracked frame, points, check
    track_ms: float = 0.0                      # tracking alone (time_ms adds sync-mode mapping)
    track_cpu_ms: float = 0.0                  # CPU of the threads making (left image) and tracking it
    lock_wait_ms: float = 0.0                  # waiting for the map lock (mapping threads)
    frame_ms: float = 0.0                      # Frame: ORB on both images and stereo matching
    # keyframes that appeared since the last result, with their own stamps and poses (backends
    # that learn of a keyframe after the frame it was made from: orbslam3); None for System
    new_keyframes: Optional[Dict[int, Tuple[float, np.ndarray]]] = None
    # not tracked, with wheel odometry: the last tracked pose carried on by the odometry (its
    # fitted errors taken out: pose.odometry_calibration), for map -> odom while LOST
    T_map_cam_coasted: Optional[np.ndarray] = None
    # with wheel odometry: its fitted errors (pose.odometry_calibration): translation scale,
    # rotation scale error, yaw drift in deg per metre, metres of tracked driving fitted on
    odometry_errors: Optional[Tuple[float, float, float, float]] = None
