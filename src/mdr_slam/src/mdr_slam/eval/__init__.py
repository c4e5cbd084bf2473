"""The paper's metrics as functions of arrays (evo's shape): trajectories (ATE, RPE via evo),
dense maps (accuracy RMSE, completeness, per surface label) and per-frame disparity/depth errors.
``mdr eval`` (mdr_slam.cli.main_eval) is the command-line face of this package.
"""
from __future__ import annotations

from .depth import (MIDDLEBURY, depth_error_metrics, depth_metrics, load_middlebury,
                    read_disparity)
from .map import DEFAULT_THRESHOLDS, SURFACE_LABELS, map_metrics, nearest_distances
from .trajectory import (ALIGNMENTS, TrajectoryErrors, associate, ate, map_alignment, read_for_eval, rpe,
                         summary_json)

__all__ = ["ate", "rpe", "map_alignment", "associate", "read_for_eval", "summary_json", "TrajectoryErrors",
           "ALIGNMENTS", "map_metrics", "nearest_distances", "SURFACE_LABELS",
           "DEFAULT_THRESHOLDS", "depth_metrics", "depth_error_metrics", "load_middlebury",
           "read_disparity", "MIDDLEBURY"]
