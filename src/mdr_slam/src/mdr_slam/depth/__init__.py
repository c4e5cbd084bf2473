"""Node 2 core: ELAS stereo depth + keyframe-guided Kalman temporal filter (paper section 3.3).

- :class:`ElasMatcher` / :func:`measurement_from_disparity`: single-frame depth with libelas.
- :class:`DepthFilter`: per-pixel inverse-depth Kalman filter anchored to keyframes.
- :class:`StereoDepth`: rectify -> ELAS -> measurement -> filter, what the node and ``mdr run`` call.
"""
from __future__ import annotations

from .elas_matcher import (ELAS_DEFAULTS, ElasMatcher, disparity_sigma, measurement_from_disparity,
                           to_gray8)
from .filter import FILTER_DEFAULTS, DepthFilter, DepthOutput, KeyFrameDepth, render_depth
from .pose_cache import PoseCache
from .stereo_depth import DEPTH_DEFAULTS, StereoDepth, split_params

__all__ = ["ElasMatcher", "ELAS_DEFAULTS", "measurement_from_disparity", "disparity_sigma",
           "to_gray8",
           "DepthFilter", "DepthOutput", "KeyFrameDepth", "FILTER_DEFAULTS", "render_depth",
           "StereoDepth", "DEPTH_DEFAULTS", "split_params", "PoseCache"]
