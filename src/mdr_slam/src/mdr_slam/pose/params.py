"""The pose tracker's parameters: every one with its default and a comment (config/pose.yaml
overrides only the few a user usually tunes), and the pose parameters that belong to the ROS node
instead. Shared by both backends (System and ORBSLAM3System) and the factory that picks one
(mdr_slam.pose.factory).
"""
from __future__ import annotations

__all__ = ["DEFAULT_PARAMS", "NODE_KEYS"]

DEFAULT_PARAMS = {
    "backend": "mdr",            # mdr (this tracker) or orbslam3 (ORB-SLAM3's C++ tracker via pyorbslam3)
    "orbslam3_vocabulary": "",   # orbslam3: DBoW2 text vocabulary (ORBvoc.txt); empty: ours, exported
    "orbslam3_keyframe_poll": 1,   # orbslam3: read its keyframes back every N frames for
                                   # /mdr/keyframes (0: never; ~1 ms each)
    "n_features": 1500,          # ORB features per image (ORB-SLAM2 EuRoC/KITTI: 1200-2000)
    "scale_factor": 1.2,         # scale between ORB pyramid levels (ORB-SLAM2: 1.2)
    "n_levels": 8,               # ORB pyramid levels (ORB-SLAM2: 8)
    "fast_threshold": 12,        # FAST corner threshold, grey levels (ORB-SLAM2 iniThFAST: 20)
    "min_fast_threshold": 5,     # poor grid cells re-detected at this FAST threshold (ORB-SLAM2
                                 # minThFAST; 0: off)
    "th_depth": 35.0,            # close/far threshold in baselines (ORB-SLAM2 ThDepth)
    "min_init_points": 100,      # stereo points needed to initialise (ORB-SLAM2: 500)
    "max_frames": 20,            # keyframe at least every max_frames frames (ORB-SLAM2: fps)
    "min_frames": 0,             # frames after a keyframe before an idle LocalMapping may take one
    "th_ref_ratio": 0.75,        # keyframe when inliers < this x the reference keyframe's points
    "min_close_points": 100,     # a new keyframe adds far stereo points only past this many close ones
    "close_tracked_ratio": 0.45, # also a keyframe (when LocalMapping is idle) when fewer than this
                                 # share of the close stereo points is tracked (0: off, ORB-SLAM2)
    "max_local_keyframes": 60,   # keyframes of the local map that frames are tracked against
    "reset_if_lost_below_kfs": 3,  # LOST with at most this many keyframes: the map is reset
    "local_ba": True,            # local bundle adjustment after each keyframe (LocalMapping)
    "ba_covisible": 10,          # covisible keyframes optimised with the new one in local BA
    "ba_iterations": 8,          # local BA iterations per round
    "ba_process": False,         # threads: local BA in a child process (helps with spare cores)
    "triangulation_neighbours": 10,  # best covisible keyframes a new keyframe triangulates with
    "triangulation_bow_depth": 0,  # > 0: vocabulary-node prefilter of triangulation pairs (0: all)
    "ba_tol": 1e-3,              # a local BA round ends once a step lowers the robust cost by less
                                 # than this share of it (0: full iterations)
    "loop_closing": True,        # detect and close loops (false: odometry with a local map only)
    "vocabulary": "",            # ORB vocabulary npz; empty = src/mdr_slam/data/orb_vocab.npz
    "loop_consistency": 2,       # consecutive keyframes a loop candidate must recur (ORB-SLAM2: 3)
    "global_ba": True,           # global bundle adjustment after each loop correction
    "global_ba_iterations": 20,  # iterations of each global BA
    "global_ba_min_kf_points": 20,   # keyframes seeing fewer points follow their parent in the global BA
                                     # (unconstrained otherwise; 0: off)
    "global_ba_process": True,   # threads: the global BA solved in a child process (GIL)
    "global_ba_nice": 10,        # ... at this nice increment (it yields the CPU to tracking)
    "pose_graph_weights": True,  # loop pose graph: edge information from shared points (false: all equal)
    "loop_min_age": 3.0,         # s; younger keyframes are never loop candidates
    "loop_max_drift": 0.3,       # a loop may move the keyframe <= this x the path since the match
    "loop_max_rotation_deg": 45.0,  # ... and turn it at most this much (false-loop gate)
    "loop_proximity": True,      # proximity loop candidates (estimated pose near, LK + PnP check) for
                                 # places the BoW misses (blank walls); keeps 112 kB of image per keyframe
    "loop_proximity_radius": 0.5,       # m, + loop_max_drift x keyframe path since the candidate
    "loop_proximity_max_radius": 2.0,   # m, cap of that radius
    "loop_proximity_min_path": 2.0,     # m of keyframe path since the candidate, at least (a
                                        # stop-and-sweep revisits its own views)
    "loop_proximity_angle_deg": 45.0,   # optical axes at most this far apart
    "loop_proximity_min_response": 0.3,  # phase-correlation response of the quarter images
    "loop_proximity_candidates": 2,     # verified per keyframe (best responses)
    "loop_proximity_min_inliers": 40,   # PnP inliers of the LK tracks (and >= 60 % of them)
    "loop_proximity_weak_inliers": 15,  # > 0: fewer inliers (down to this) when consistent ...
    "loop_proximity_weak_consistency": 2,  # ... with this many previous weak verifications
    "loop_proximity_two_way": True,     # cand's keypoints tracked into kf too: the two poses must agree ...
    "loop_proximity_two_way_deg": 2.0,  # ... within this rotation ...
    "loop_proximity_two_way_m": 0.5,    # ... and translation (m)
    "loop_max_rot_sigma_deg": 1.0,  # a BoW loop whose inliers leave its rotation more uncertain than this ...
    "loop_rot_significance": 5.0,   # ... is accepted only when it turns the map by this many sigmas (0: off)
    "loop_reprojection_refine": True,  # BoW loop correction refined by kf's pixels (ORB-SLAM2 OptimizeSim3)
    "loop_rot_sigma_cap_deg": 4.0,  # ... and never when that sigma exceeds this (0: no cap)
    "reloc_candidates": 10,      # LOST: keyframes tried for relocalization per frame
    "lost_coast_s": 0.5,         # LOST: motion-model / wide / frame-to-frame tracking from the last
                                 # tracked frame goes on this long before only relocalization (0: ORB-SLAM2)
    "motion_prior_acc": 4.0,     # pose-only optimization pulled toward the constant-velocity prediction:
    "motion_prior_ang_acc": 120.0, # sigmas acc * dt^2 (m/s^2) and ang_acc * dt^2 (deg/s^2) (0: off)
    "texture_tau": 10.0,         # a keypoint's x (u, u_R) and y residuals weigh min(1, gradient energy / tau)
                                 # (grey levels^2, 7x7 patch; 0: off, ORB-SLAM2)
    "shading_max_spread": 0.3,   # inliers spanning less of the image width: the last frame's shading joins
    "shading_max_close": 0.2,    # ... and at most this share of them is within th_depth (a far view)
    "shading_cell": 32,          # ... one point per cell of this many px (Tracking.refine_on_one_patch)
    "shading_min_eig": 6e-5,     # ... where the structure tensor's smaller eigenvalue exceeds this
    "shading_weight": 4.0,       # ... their information (1/px^2) in the pose-only optimization (0 spread: off)
    "trajectory_blend": True,    # trajectory(): frames between two keyframes follow both (System.trajectory;
                                 # false: ORB-SLAM2, the reference keyframe only)
    "reloc_max_ms": 60.0,        # LOST: no further relocalization candidate after this (wall ms per frame)
    "yield_max_ms": 60.0,        # threads: mapping waits at most this long for a frame's tracking, so
                                 # their share of the GIL does not slow it (0: off)
    "backpressure_inliers": 80,  # threads: wait for LocalMapping when tracking gets this weak
    "min_inliers": 30,           # local-map inliers for OK (ORB-SLAM2: 30)
    "low_texture_points": 150,   # frames needing the FAST fallback or with fewer stereo keypoints are
                                 # low-texture ...
    "min_inliers_low_texture": 15,  # ... and are tracked OK with this many inliers
    "flow_tracking": True,       # optical-flow fallback when the motion model fails (blank walls)
    "flow_window": 21,           # Lucas-Kanade window (px) ...
    "flow_levels": 3,            # ... pyramid levels above full resolution ...
    "flow_fb_px": 1.0,           # ... and forward-backward disagreement allowed (px)
    "flow_pnp_min_texture": 10.0,  # PnP on the tracks whose patch has this x and y gradient energy ...
    "flow_pnp_min_tracks": 15,   # ... when at least this many (0 texture: all tracks, as before)
    "wide_search_th": 6.0,       # local-map projection window (x4 px x scale) when both the
                                 # motion model and the reference keyframe fail
}

# pose parameters (config/pose.yaml, pose_node.DEFAULTS) that belong to the ROS node, not the
# tracker (System ignores them, so the runner can pass the whole file)
NODE_KEYS = {"source", "map_frame", "odom_frame", "base_frame", "camera_frame", "base_to_camera",
             "publish_tf", "publish_odom_tf", "path_max_length", "calib", "trajectory_path",
             "trajectory_format", "sync_queue_size", "sync_tolerance", "image_transport",
             "rectified", "threads", "path_period",
             "max_pending", "blas_threads", "cv_threads", "diagnostics_period", "path_min_translation",
             "path_min_rotation_deg", "pipeline_frames", "max_future_stamp"}
