"""Node 3's core (paper section 3.4): confidence-based global map fusion, occupancy grid, mesh.

``VoxelMap`` is the fuse-update-clean map (its parameters: ``VoxelMapConfig``); ``mesh`` turns a
map (or depth frames) into a TSDF triangle mesh. ROS-free: the node (mdr_slam.nodes.fusion_node)
and the offline runner call these.
"""
from __future__ import annotations

import os
import sys

from .config import VoxelMapConfig
from .grid import GridExtent, free_footprint, grid_axes, grid_origin_T, occupancy_grid
from .voxel_map import IntegrationStats, VoxelMap, normal_bins, voxel_downsample
from .mesh import (auto_views, mesh_from_map, render_depth, tsdf_mesh, views_from_trajectory,
                   write_mesh)

__all__ = ["limit_openmp_threads", "VoxelMap", "VoxelMapConfig", "IntegrationStats", "normal_bins",
           "voxel_downsample", "GridExtent", "free_footprint", "grid_axes", "grid_origin_T",
           "occupancy_grid", "render_depth", "auto_views", "views_from_trajectory", "tsdf_mesh", "mesh_from_map",
           "write_mesh"]


def limit_openmp_threads(n: int = 1) -> bool:
    """Ask Open3D's OpenMP runtime for ``n`` threads (must run before ``open3d`` is imported).

    Open3D runs only for the mesh (TSDF integration and extraction); its OpenMP worker threads
    spin idle on a CPU shared with the pose and depth nodes (the paper's nodes each get about one
    core), and each of its small calls then costs milliseconds.
    Returns False when Open3D was already loaded (then the setting has no effect); an
    OMP_NUM_THREADS set by the user is kept.
    """
    if "open3d" in sys.modules:
        return False
    os.environ.setdefault("OMP_NUM_THREADS", str(int(n)))
    return True
