"""The nodes' own parameters, one Config per node (ROS-free, so ``mdr run`` and the tests read
them without rospy). Each node also drives a core component with its own configuration:
:func:`node_configs` lists both; config/<node>.yaml overrides their fields.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..config import Config
from ..depth.config import DepthConfig
from ..fusion.config import VoxelMapConfig
from ..pose.config import TrackerConfig

__all__ = ["PoseNodeConfig", "DepthNodeConfig", "FusionNodeConfig", "NODE_CONFIGS"]


@dataclass
class PoseNodeConfig(Config):
    """The pose node's own parameters; the tracker's are mdr_slam.pose.TrackerConfig."""
    source: str = "orb"                # orb (stereo tracking) or groundtruth (relay a ground-truth pose)
    map_frame: str = "map"             # tf frames (REP-105)
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    camera_frame: str = ""             # empty: the left image's frame_id (groundtruth: DEFAULT_CAMERA_FRAME)
    base_to_camera: str = ""           # T_base_camera "x y z qx qy qz qw", published only when tf has none
    publish_tf: bool = True            # map -> odom -> base_link (false: topics only)
    publish_odom_tf: Any = "auto"      # auto: odom -> base_link unless the robot's odometry publishes it; true/false
    calib: str = ""                    # calibration file(s) instead of camera_info
    image_transport: str = "raw"       # raw (sensor_msgs/Image) or compressed (<image topic>/compressed)
    rectified: Any = "auto"            # auto: image_rect* topics and distortion-free camera_info are rectified
    sync_queue_size: int = 10          # images kept per side while waiting for the other one
    sync_tolerance: float = 0.0        # s between the stamps of a stereo pair; 0 = 0.4 of the frame period
    max_pending: int = 2               # stereo pairs waiting for the tracker; older ones are dropped
    threads: bool = True               # LocalMapping/LoopClosing in background threads
    trajectory_path: str = ""          # written on shutdown when set (.txt = TUM, .kitti = KITTI)
    trajectory_format: str = ""        # tum or kitti; empty = from the extension (default tum)
    diagnostics_period: float = 1.0    # s between /diagnostics messages
    max_future_stamp: float = 1.0      # s (sim time): pairs and poses stamped further ahead of the clock are
                                       # dropped (a looping bag's clock jumps back; 0 = no check)
    load_map: str = ""                 # map folder to start from (its pose_map.npz); empty: a new map
    localization: bool = False         # with load_map: track against it only (no new keyframes, files unchanged)
    map_dir: str = ""                  # the map services' paths resolve inside it; "": $ROS_HOME/mdr_maps
    map_path: str = "last"             # map folder (in map_dir) of the autosave; a respawned node resumes it
    session_id: str = ""               # mapping session written into the map files (mdr.launch: one per launch); "": /run_id
    allow_any_map_path: bool = False   # the services may also read and write outside map_dir
    resume: bool = True                # reload map_path's autosave after an unclean exit, and relocalize
    autosave: bool = True              # save the sparse map to map_path on shutdown ...
    autosave_period: float = 60.0      # ... and every this many s (0: only on shutdown)


@dataclass
class DepthNodeConfig(Config):
    """The depth node's own parameters; StereoDepth's are mdr_slam.depth.DepthConfig."""
    map_frame: str = "map"              # tf frame of the poses
    camera_frame: str = ""              # tf frame of the left camera; empty: the image's frame_id
    use_tf: bool = True                 # pose at the image stamp from tf2; false: pose_source_topic
    pose_source_topic: str = "mdr/pose"  # PoseStamped of the left optical frame in map (use_tf false)
    tf_timeout: float = 0.1             # s to wait for tf / for the pose of an image stamp
    max_future_stamp: float = 1.0       # s (sim time): drop pairs and tf further ahead of the clock; 0: off
    max_rate: float = 12.0              # Hz of stereo pairs matched, chosen by stamp; 0: every pair
    tracking_state_topic: str = "mdr/tracking_state"  # no filtering while the tracker is LOST; "": always
    # Hz of single-frame clouds on mdr/depth/raw_points while the tracker is LOST (no pose for the
    # filter), so that costmaps keep sensing obstacles; 0: nothing is matched while LOST
    lost_cloud_rate: float = 2.0
    pose_max_gap: float = 0.25          # s between two cached poses to interpolate between them
    keyframe_topic: str = "mdr/keyframes"  # the pose node's keyframe events and corrections
    use_keyframe_events: bool = True    # follow the pose node's keyframes once it publishes any
    sync_tolerance: float = 0.0         # s between a stereo pair's stamps; 0: 0.4 of the frame period
    sync_queue_size: int = 10           # images kept per side while waiting for the other one
    image_transport: str = "raw"        # raw (sensor_msgs/Image) or compressed (<image topic>/compressed)
    rectified: Any = "auto"             # auto: image_rect* topics, distortion-free camera_info; true/false
    calib: str = ""                     # calibration file(s) for inputs without camera_info
    publish_depth_image: bool = False   # also /mdr/depth/image (32FC1, m) of the published points
    diagnostics_period: float = 1.0     # s between /diagnostics messages
    # bytes: fixed glibc mmap threshold (1048576: flat RSS in long runs, but +60 % CPU per frame
    # from page faults); 0: glibc's dynamic threshold. See the docstring (memory in long runs).
    malloc_mmap_threshold: int = 0


@dataclass
class FusionNodeConfig(Config):
    """The fusion node's own parameters; the map's are mdr_slam.fusion.VoxelMapConfig."""
    map_frame: str = "map"          # frame of the map, its topics and the poses
    cloud_topic: str = "mdr/depth/points"   # PointCloud2 in the camera frame (the depth node's)
    pose_topic: str = "mdr/pose"    # PoseStamped of the camera in map_frame (pose_source topic)
    keyframes_topic: str = "mdr/keyframes"  # keyframe poses: corrections move their points
    tracking_state_topic: str = "mdr/tracking_state"  # clouds stamped while LOST are skipped; "": no check
    pose_source: str = "tf"         # tf: tf2 map <- cloud frame at its stamp; topic: pose_topic
    tf_timeout: float = 0.1         # s to wait for the transform at the cloud's stamp
    max_future_stamp: float = 1.0   # s (sim time): drop clouds and tf further ahead of the clock; 0: off
    sync_tolerance: float = 0.05    # s between a cloud and its pose (pose_source topic)
    sync_queue_size: int = 30       # messages per topic the ApproximateTime synchroniser keeps
    cloud_queue: int = 10           # clouds waiting while the node is busy; rospy drops the oldest beyond
    anchor_keyframes: bool = True   # anchor points to keyframes so corrections move them
    intensity_field: str = "intensity"  # per-point intensity field of the cloud, if present
    weight_field: str = "weight"    # per-point weight field of the cloud, if present (e.g. inverse variance)
    # output
    publish_rate: float = 1.0       # Hz of /mdr/map/points and /mdr/map/grid (when changed); 0: never
    display_voxel: float = 0.05     # m, display downsampling of /mdr/map/points; 0: every point
    display_min_confidence: int = 3  # /mdr/map/points; keep >= grid_min_confidence (shows the grid's obstacles)
    publish_grid: bool = True       # /mdr/map/grid (nav_msgs/OccupancyGrid) for move_base
    publish_nav_grid: bool = True   # /mdr/map/nav_grid: the same grid for move_base's static layer
                                    # (config/navigation/costmap_common_params.yaml), unknown cells ...
    nav_grid_unknown: int = 10      # ... at this value (0-99): a cost the planner pays to cross them
    grid_resolution: float = 0.05   # m per grid cell
    grid_z_min: float = 0.1         # m, obstacle band along grid_up_axis ...
    grid_z_max: float = 1.5         # m, ... up to this
    grid_free_band: float = 0.3     # m below grid_z_min: floor points there mark a cell free
    grid_up_axis: str = "z"         # z for a REP-105 map; -y if map is the first camera's optical frame
    grid_min_confidence: int = 3    # map points of at least this confidence mark grid cells
    grid_raytrace: bool = True      # free cells along the ray from each point's camera to the point
    grid_raytrace_range: float = 0.0  # m, free only the first this many metres of a ray; 0: whole ray
    grid_max_gap: float = 0.5       # m, close gaps up to this in straight walls where no ray passed; 0: off
    grid_extent_step: float = 5.0   # m: the grid's extent grows in steps of this (fewer move_base
                                    # costmap resizes, each blank until its next update); 0: bounding box
    grid_margin: float = 2.0        # m kept around the camera inside the grid (move_base's robot and
                                    # depth sensor must lie in the global costmap)
    goal_topic: str = "move_base/current_goal"   # PoseStamped goals kept inside the grid too; "": none
    base_frame: str = "base_link"   # tf frame of the robot's base (move_base's robot_base_frame) ...
    grid_footprint_radius: float = 0.3  # m: ... grid cells within this of it are free (the robot
                                    # stands there); above the costmap's inscribed radius; 0: off
    # files (writes are atomic: temporary file + rename)
    map_dir: str = ""               # the services' paths resolve inside it; "": $ROS_HOME/mdr_maps
    map_path: str = "last"          # map folder (in map_dir; or a .ply/.pcd file) of autosave and ~save_map
    session_id: str = ""            # mapping session written into the map files (mdr.launch: one per launch); "": /run_id
    load_map: str = ""              # map folder (or .ply/.pcd file) to start from; "": empty
    localization: bool = False      # with load_map: its files are never written (no autosave)
    allow_any_map_path: bool = False  # the services may also read and write outside map_dir
    pose_node: str = "pose_node"    # whose ~save_map / ~load_map the map services call too; "": none
    resume: bool = True             # reload map_path after an unclean exit (see the module doc)
    autosave: bool = True           # save to map_path on shutdown
    autosave_period: float = 60.0   # s, also save periodically; 0: only on shutdown
    mesh_path: str = "mdr_mesh.ply"  # ~export_mesh default target (relative: in map_dir)
    mesh_voxel: float = 0.02        # m, TSDF voxel of ~export_mesh
    mesh_width: int = 640           # px, depth images rendered for the TSDF ...
    mesh_height: int = 480          # px
    mesh_hfov_deg: float = 90.0     # deg, ... and their horizontal field of view
    mesh_min_confidence: int = 2    # map points of at least this confidence are meshed
    mesh_max_views: int = 100       # camera poses of the run used as TSDF views (auto views if none)
    diagnostics_period: float = 1.0  # s between /diagnostics messages
    omp_threads: int = 1            # Open3D OpenMP threads of the mesh export; 0: all cores


# node: (the node's own parameters, the core component's)
NODE_CONFIGS = {"pose": (PoseNodeConfig, TrackerConfig),
                "depth": (DepthNodeConfig, DepthConfig),
                "fusion": (FusionNodeConfig, VoxelMapConfig)}
