"""Node 2 core: ELAS stereo depth + keyframe-guided Kalman temporal filter (paper section 3.3).

- :class:`DepthConfig` / :class:`ElasConfig`: every parameter of this package, with its default.
- :class:`ElasMatcher` / :func:`measurement_from_disparity`: single-frame depth with libelas.
- :class:`DepthFilter`: per-pixel inverse-depth Kalman filter anchored to keyframes.
- :class:`StereoDepth`: rectify -> ELAS -> measurement -> filter, what the node and ``mdr run`` call.
"""
from __future__ import annotations

from .config import DepthConfig, ElasConfig
from .elas_matcher import (ELAS_PRESETS, ElasMatcher, disparity_sigma, measurement_from_disparity,
                           to_gray8)
from .filter import DepthFilter, DepthOutput, KeyFrameDepth, render_depth
from .pose_cache import PoseCache
from .stereo_depth import StereoDepth

__all__ = ["DepthConfig", "ElasConfig", "ElasMatcher", "ELAS_PRESETS",
           "measurement_from_disparity", "disparity_sigma", "to_gray8",
           "DepthFilter", "DepthOutput", "KeyFrameDepth", "render_depth",
           "StereoDepth", "PoseCache"]
