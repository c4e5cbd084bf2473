"""The paper's metrics as functions of arrays (evo's shape): trajectories (ATE, RPE via evo),
dense maps (accuracy RMSE, completeness, per surface label, also within range of the camera path),
the planner's occupancy grid against the true occupancy (eval.grid) and per-frame disparity/depth
errors. eval.peer builds a peer map (OpenCV SGBM depth fused in an Open3D TSDF) to score alongside.
``mdr eval`` (mdr_slam.cli.main_eval) is the command-line face of this package.
"""
from __future__ import annotations

from .depth import (MIDDLEBURY, depth_error_metrics, depth_metrics, load_middlebury,
                    read_disparity)
from .grid import cells_near, grid_metrics, grid_params, obstacle_cells, route_cells
from .map import (DEFAULT_MAX_RANGE, DEFAULT_THRESHOLDS, SURFACE_LABELS, map_metrics,
                  nearest_distances, path_positions, within_range)
from .trajectory import (ALIGNMENTS, TrajectoryErrors, associate, ate, map_alignment, read_for_eval, rpe,
                         summary_json)

__all__ = ["ate", "rpe", "map_alignment", "associate", "read_for_eval", "summary_json", "TrajectoryErrors",
           "ALIGNMENTS", "map_metrics", "nearest_distances", "SURFACE_LABELS",
           "DEFAULT_THRESHOLDS", "DEFAULT_MAX_RANGE", "within_range", "path_positions",
           "grid_metrics", "grid_params", "obstacle_cells", "route_cells", "cells_near", "depth_metrics", "depth_error_metrics", "load_middlebury",
           "read_disparity", "MIDDLEBURY"]
