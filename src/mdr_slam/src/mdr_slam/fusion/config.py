"""The voxel map's configuration (paper 3.4.2: fuse-update-clean). The fusion node's own parameters
(topics, publishing, the occupancy grid, files) are nodes.fusion_node.FusionNodeConfig;
config/fusion.yaml overrides both. Every default of the map lives here and nowhere else.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..config import Config, ConfigError

__all__ = ["VoxelMapConfig"]


@dataclass
class VoxelMapConfig(Config):
    """:class:`~mdr_slam.fusion.VoxelMap`'s parameters (its docstring says what each step does).
    A 0 for ``radius``, ``normal_radius`` and ``dup_*`` means the default derived from the voxel."""
    voxel_size: float = 0.02        # m, map resolution
    radius: float = 0.0             # m, association radius (at most voxel_size); 0: voxel_size
    normal_angle_deg: float = 45.0  # deg: a sample merges into a map point when their normals agree
    normal_radius: float = 0.0      # m, normals by PCA over the grid cells within this radius; 0: 4 voxels
    merge_duplicates: bool = True   # fold a point coming of age into an older point of the same surface
    dup_normal: float = 0.0         # m, ... when within this along the normal; 0: 1.5 voxels
    dup_lateral: float = 0.0        # m, ... and this across it; 0: 1 voxel
    dup_radius: float = 0.0         # m, ... or closer than this in any direction; 0: half a voxel
    rekey: bool = True              # keys follow the running means: one point per voxel and normal bin
    confidence: bool = True         # false: plain voxel grid (ablation "Confidence OFF", no cleaning)
    min_confidence: int = 3         # clouds that must see a point ...
    grace: float = 5.0              # s, ... within this long after its first sighting, else it is removed
    min_span: float = 0.0           # s, ... and over at least this long (first to last sighting); 0: off
    clean_every: int = 10           # integrations between two cleaning passes; 0: only when clean() is called
    min_depth: float = 0.1          # m, cloud points nearer to the camera are dropped
    max_depth: float = 10.0         # m, cloud points farther from the camera are dropped

    def __post_init__(self):
        super().__post_init__()
        if not self.voxel_size > 0:
            raise ConfigError("VoxelMapConfig.voxel_size must be > 0, got %r" % self.voxel_size)
