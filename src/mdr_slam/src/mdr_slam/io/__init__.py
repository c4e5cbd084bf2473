"""Files: point clouds (PLY, PCD) with arbitrary per-point fields, trajectories, atomic writes."""
from .atomic import atomic_write, atomic_path
from .pointcloud import (read_ply, write_ply, read_pcd, write_pcd, read_cloud, write_cloud,
                         points_cloud, cloud_xyz)
from .trajectory import (Trajectory, read_tum, write_tum, read_kitti_poses, write_kitti_poses,
                         read_euroc_csv, read_trajectory)
from .datasets import (StereoDataset, DatasetError, load_euroc, load_kitti, iter_euroc, iter_kitti,
                       interpolate_poses)

__all__ = ["atomic_write", "atomic_path", "read_ply", "write_ply", "read_pcd", "write_pcd",
           "read_cloud", "write_cloud", "points_cloud", "cloud_xyz", "Trajectory", "read_tum", "write_tum", "read_kitti_poses",
           "write_kitti_poses", "read_euroc_csv", "read_trajectory",
           "StereoDataset", "DatasetError", "load_euroc", "load_kitti", "iter_euroc", "iter_kitti",
           "interpolate_poses"]
