"""Node 3: confidence-based global map fusion -> /mdr/map/points, /mdr/map/grid, map services.

A thin shell around :class:`mdr_slam.fusion.VoxelMap` (paper section 3.4):

* ``/mdr/depth/points`` (PointCloud2, camera frame) is paired with the camera pose at the cloud's
  stamp (the paper's time synchronisation): by default tf2 ``map <- cloud frame`` at that stamp
  (``~pose_source: tf``, waiting ``~tf_timeout`` s), or ``/mdr/pose`` through a message_filters
  ApproximateTime synchroniser (``~pose_source: topic``, ``~sync_tolerance`` s).
* each cloud is anchored to the latest keyframe (``/mdr/keyframes``) not newer than it; when the
  pose node publishes corrected keyframe poses (local BA, loop closure) the map points follow.
* ``/mdr/map/points`` (latched, ``~publish_rate`` Hz, voxel-downsampled for display: x, y, z,
  intensity, confidence) and ``/mdr/map/grid`` (nav_msgs/OccupancyGrid, latched) for move_base;
  ``/mdr/map/nav_grid`` is the same grid with its unknown cells at ``~nav_grid_unknown`` (move_base's
  static layer: unmapped space may be crossed, at a cost).
  The grid's extent grows in steps of ``~grid_extent_step`` m and holds the camera with a
  ``~grid_margin``, so move_base's global costmap is rarely resized and holds the robot.
* map folders (mdr_slam.io.map_dir): services ``~save_map``, ``~load_map`` (a folder name inside
  ``~map_dir``; a .ply/.pcd path names one file; with a folder they also call the pose node's
  ``~save_map``/``~load_map``, ``~pose_node``), ``~reset``, ``~export_mesh``; ``~load_map`` param
  at start; autosave to ``~map_path`` on shutdown and every ``~autosave_period`` s (atomic writes;
  none with ``~localization``, which never changes the loaded map's files).
* crash recovery (``~resume``): while running, the node keeps a marker
  (``<map_path>/fusion_node.running``, a file's ``<map_path>.running``); a clean shutdown saves
  and removes it. A node started while the marker is still there (the last one was killed, e.g.
  respawned by roslaunch) reloads ``map_path``: what is lost is bounded by the integrations of the
  last ``~autosave_period`` seconds before the crash (plus the clouds that arrive while it
  restarts).
* tracking LOST (``/mdr/tracking_state``): a cloud whose stamp falls where the pose node was LOST
  (or not initialised) is skipped, even when tf could interpolate a pose across the gap, so a
  lost tracker never smears the map; integration resumes with the first tracked frame.
* time going backwards (a looping bag): keyframe anchors and tracking states are forgotten with a
  warning (tf2 clears its own buffer), the map stays; timers survive the jump. Clouds and tf
  stamped more than ``~max_future_stamp`` ahead of the clock (the old lap's last ones, delivered
  after the jump) are dropped: looked up in the new lap, tf interpolated their pose across the
  jump (measured 0.65 m / 34 deg off; tests/ros/test_time_jump.py).
* bad input (malformed/empty clouds, NaN points, absurd depths, missing pose, time going
  backwards) is logged (throttled) and skipped; the node never dies on input.
"""
from __future__ import annotations

import os
import threading
import time

import message_filters
import numpy as np
import rospy
import tf2_ros
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from mdr_slam_msgs.msg import KeyFrameArray, TrackingState
from mdr_slam_msgs.srv import (ExportMesh, ExportMeshResponse, LoadMap, LoadMapResponse, SaveMap,
                               SaveMapResponse)
from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger, TriggerResponse

from ..conversions import (ConversionError, arrays_to_pointcloud2, matrix_to_pose,
                           pointcloud2_to_arrays, pose_stamped_to_matrix, pose_to_matrix,
                           transform_stamped_to_matrix)
from ..fusion import GridExtent, VoxelMap, VoxelMapConfig, grid_origin_T, limit_openmp_threads
from ..fusion.map_io import load_dense_map, save_dense_map
from ..fusion.mesh import default_K, mesh_from_map, write_mesh
from ..geometry import relative_motion
from ..io.atomic import remove_stale_temporaries
from ..msg_checks import cloud_problem
from ..io.map_dir import (ROTATE_KEEP, MapPathError, after_rotation, check_folder_sessions,
                          default_map_dir, find_session, folder_lock, folder_sessions, map_files,
                          next_session_id, resolve_map_path, session_folder, file_generation,
                          rotate_file)
from ..nav import map_min_confidence, map_products
from .common import (ClockWatch, RunMarker, StampGuard, Throttled, base_session, read_config,
                     skip_future_stamp, transform_listener)
from .config import NODE_CONFIGS, FusionNodeConfig
from .health import ProcessHealth, update_diagnostics
from .memdebug import start_from_env

POSE_NODE_SERVICE_WAIT = 2.0   # s to wait for the pose node's map service


def _is_folder(path: str) -> bool:
    """A map path without a point-cloud extension names a map folder."""
    return os.path.splitext(path)[1].lower() not in (".ply", ".pcd")




class FusionNode:
    def __init__(self, cfg: FusionNodeConfig, map_cfg: VoxelMapConfig):
        self.cfg = cfg
        # what mdr_slam.nav.map_products reads: the display and grid fields, and the map's confidence
        self.products_params = dict(cfg.to_dict(), confidence=map_cfg.confidence)
        self.closed = False
        self.warn = Throttled()
        self.guard = StampGuard()
        if map_cfg.confidence and cfg.publish_grid and \
                cfg.display_min_confidence < cfg.grid_min_confidence:
            rospy.logwarn("fusion_node: display_min_confidence %s < grid_min_confidence %s: "
                          "/mdr/map/points shows points the grid (move_base's map) does not mark "
                          "occupied",
                          cfg.display_min_confidence, cfg.grid_min_confidence)
        self.lock = threading.RLock()
        self.map = VoxelMap(map_cfg)
        self.map_dir = os.path.expanduser(cfg.map_dir or default_map_dir())
        # parameters are the operator's (launch file); only service paths are confined
        self.map_path = resolve_map_path(cfg.map_path, self.map_dir, allow_outside=True)
        self.dirty = True
        self.kf_ids = np.zeros(0, np.int64)
        self.kf_stamps = np.zeros(0)
        self.kf_poses = {}
        self.views = []                      # camera poses for mesh export (subsampled)
        self.camera = None                   # the latest integrated cloud's camera centre in map
        self.goal = None                     # the planner's current goal in map (goal_topic)
        self.base = None                     # the base's position in map freed in the last grid
        self.grid_extent = GridExtent(cfg.grid_resolution, cfg.grid_extent_step, cfg.grid_margin)
        self.n_integrated = 0
        self.n_received = 0                  # clouds that reached integrate() (the rest: queue drops)
        self.rate_window = []                # wall times of recent integrations
        self.last_latency = float("nan")
        self.last_proc = float("nan")
        self.states = []                     # (stamp, TrackingState.state), recent, time-ordered
        self.clock = ClockWatch()            # ROS time jumping back (bag loop): a new timeline
        if _is_folder(self.map_path):
            self.marker = RunMarker(os.path.join(self.map_path, "fusion_node.running"), "fusion_node")
            autosave_file = map_files(self.map_path)["dense"]
        else:
            self.marker = RunMarker(self.map_path + ".running", "fusion_node")
            autosave_file = self.map_path
        path = resolve_map_path(cfg.load_map, self.map_dir, True) if cfg.load_map else ""
        # the mapping session the files are written in (mdr_slam.io.map_dir): the launch's, a
        # loaded folder's, or (respawned) the dead node's, whose autosave it resumes
        self.session = base_session(cfg.session_id)
        if path and os.path.isdir(path):
            ok, note = check_folder_sessions(path)
            if note:
                rospy.logwarn("fusion_node: %s", note)
            self.session = folder_sessions(path).get("dense") or self.session
        if cfg.resume and self.marker.crashed_before(autosave_file):
            path = self.map_path
            if _is_folder(self.map_path):
                self.session = self.marker.session() or \
                    folder_sessions(self.map_path).get("dense") or self.session
                path = find_session(self.map_path, self.session, "dense") or self.map_path
            rospy.logwarn("fusion_node: the previous fusion node of this session did not shut down "
                          "cleanly: resuming its autosave %s (integrations of at most the last "
                          "autosave_period = %.1f s before the crash are lost)", path,
                          cfg.autosave_period)
        if path:
            try:
                n = self.load(path)
                rospy.loginfo("fusion_node: loaded %d map points from %s", n, path)
            except (IOError, OSError, ValueError) as e:
                rospy.logerr("fusion_node: could not load map %s: %s (starting empty)", path, e)
        # localization never changes a map's files
        self.autosaving = cfg.autosave and not (cfg.localization and path)
        if self.autosaving:   # "running, not yet saved on a clean exit": what resume looks for
            self.marker.write(self.session)
            for f in (autosave_file, autosave_file + ".anchors.json",
                      os.path.splitext(autosave_file)[0] + ".json"):
                remove_stale_temporaries(f)
        self.pub_points = rospy.Publisher("mdr/map/points", PointCloud2, queue_size=1, latch=True)
        self.pub_grid = rospy.Publisher("mdr/map/grid", OccupancyGrid, queue_size=1, latch=True)
        self.pub_nav_grid = rospy.Publisher("mdr/map/nav_grid", OccupancyGrid, queue_size=1,
                                            latch=True) if cfg.publish_nav_grid else None
        self.tf_buffer = tf2_ros.Buffer(cache_time=rospy.Duration(60.0))
        self.tf_listener = transform_listener(self.tf_buffer, self.cfg.max_future_stamp, self.warn,
                                              "fusion_node")
        big = 1 << 26
        if cfg.pose_source == "topic":
            self.sub_cloud = message_filters.Subscriber(cfg.cloud_topic, PointCloud2,
                                                        queue_size=cfg.cloud_queue, buff_size=big)
            self.sub_pose = message_filters.Subscriber(cfg.pose_topic, PoseStamped, queue_size=50)
            self.sync = message_filters.ApproximateTimeSynchronizer(
                [self.sub_cloud, self.sub_pose], cfg.sync_queue_size, cfg.sync_tolerance)
            self.sync.registerCallback(self.on_cloud_pose)
        else:
            if cfg.pose_source != "tf":
                rospy.logwarn("fusion_node: unknown pose_source %r, using tf", cfg.pose_source)
            self.sub_cloud = rospy.Subscriber(cfg.cloud_topic, PointCloud2, self.on_cloud,
                                              queue_size=cfg.cloud_queue, buff_size=big)
        self.sub_kf = rospy.Subscriber(cfg.keyframes_topic, KeyFrameArray, self.on_keyframes,
                                       queue_size=20)
        if cfg.goal_topic:
            self.sub_goal = rospy.Subscriber(cfg.goal_topic, PoseStamped, self.on_goal, queue_size=5)
        if cfg.tracking_state_topic:
            self.sub_state = rospy.Subscriber(cfg.tracking_state_topic, TrackingState,
                                              self.on_state, queue_size=50)
        self.srvs = [rospy.Service("~save_map", SaveMap, self.srv_save),
                     rospy.Service("~load_map", LoadMap, self.srv_load),
                     rospy.Service("~reset", Trigger, self.srv_reset),
                     rospy.Service("~export_mesh", ExportMesh, self.srv_mesh)]
        self.timers = []
        if cfg.publish_rate > 0:
            self.timers.append(rospy.Timer(rospy.Duration(1.0 / cfg.publish_rate), self.on_publish,
                                           reset=True))  # reset: survive sim time jumping back
        if self.autosaving and cfg.autosave_period > 0:
            self.timers.append(rospy.Timer(rospy.Duration(cfg.autosave_period), self.on_autosave,
                                           reset=True))
        self.diag = None
        self.health = ProcessHealth()
        try:
            import diagnostic_updater
            self.diag = diagnostic_updater.Updater()
            self.diag.setHardwareID("mdr_slam")
            self.diag.add("fusion", self.diagnostics)
            self.timers.append(rospy.Timer(rospy.Duration(cfg.diagnostics_period),
                                           lambda _e: update_diagnostics(self.diag), reset=True))
        except ImportError:
            rospy.logwarn("fusion_node: diagnostic_updater missing; no diagnostics")

    # ------------------------------------------------------------------ input
    def on_goal(self, msg):
        """The planner's goal: the grid's extent holds it (GridExtent), so a goal in space not
        mapped yet lies in move_base's global costmap and is planned through unknown space."""
        try:
            T = pose_stamped_to_matrix(msg)
            frame = msg.header.frame_id.lstrip("/")
            if frame and frame != self.cfg.map_frame:
                T = transform_stamped_to_matrix(self.tf_buffer.lookup_transform(
                    self.cfg.map_frame, frame, rospy.Time(0), rospy.Duration(0.5))) @ T
        except (ConversionError, tf2_ros.TransformException) as e:
            self.warn("goal", "goal skipped: %s" % e)
            return
        self.goal = T[:3, 3].copy()
        self.dirty = True   # the next publish widens the grid (the map itself may be unchanged)

    def on_state(self, msg):
        """Tracking states, kept for ~30 s (per frame) so clouds can be checked at their stamp."""
        t = msg.header.stamp.to_sec()
        with self.lock:
            if self.states and t < self.states[-1][0]:
                self.states = []               # time went backwards: states of the old timeline
            self.states.append((t, int(msg.state)))
            if len(self.states) > 600:
                del self.states[:100]

    def _tracking_at(self, stamp: float):
        """The tracking state of the latest frame not newer than ``stamp`` (None if unknown)."""
        with self.lock:
            for t, s in reversed(self.states):
                if t <= stamp + 1e-6:
                    return s
        return None

    def _lost_at(self, stamp: float) -> bool:
        """True (and a throttled warning) when the pose node was LOST or not initialised at
        ``stamp``: the cloud's pose is not trustworthy."""
        tracking = self._tracking_at(stamp)
        if tracking in (0, 2):  # TrackingState NOT_INITIALIZED, LOST
            self.warn("lost", "tracking %s at the cloud's stamp %.3f; skipped (no smeared map)" % (
                "LOST" if tracking == 2 else "not initialised", stamp))
            return True
        return False

    def on_time_jump(self, stamp: float) -> None:
        """Time went backwards (a looping bag): forget what belongs to the old timeline, keep
        the map."""
        with self.lock:
            n = self.map.detach_anchors() if len(self.kf_ids) or self.map.anchors else 0
            self.kf_ids = np.zeros(0, np.int64)
            self.kf_stamps = np.zeros(0)
            self.kf_poses = {}
            self.states = [s for s in self.states if s[0] <= stamp + 1e-6]
        self.warn("back", "time went backwards to %.3f (bag loop?): keyframe anchors (%d points) "
                  "and tracking states reset, the map (%d points) stays" % (stamp, n, len(self.map)))

    def _bad_cloud(self, msg) -> bool:
        """An absurd cloud (size, field layout, data length: mdr_slam.msg_checks), refused before
        anything is allocated or waited for."""
        why = cloud_problem(msg)
        if why:
            self.warn("badcloud", "cloud refused: %s" % why)
        return bool(why)

    def on_cloud(self, msg):
        # a cloud stamped while LOST is skipped before its pose lookup, which would otherwise wait
        # up to tf_timeout for the relocalized pose and hold up the clouds queued behind it
        if self._bad_cloud(msg) or self._from_the_future(msg) or \
                self._lost_at(msg.header.stamp.to_sec()):
            return
        try:
            ts = self.tf_buffer.lookup_transform(self.cfg.map_frame, msg.header.frame_id,
                                                 msg.header.stamp, rospy.Duration(self.cfg.tf_timeout))
            T = transform_stamped_to_matrix(ts)
        except tf2_ros.TransformException as e:  # lookup, connectivity, extrapolation, timeout
            self.warn("tf", "no pose for the cloud at %.3f (%s <- %r): %s; skipped" % (
                msg.header.stamp.to_sec(), self.cfg.map_frame, msg.header.frame_id, e))
            return
        except ConversionError as e:
            self.warn("tfbad", "bad transform for the cloud: %s; skipped" % e)
            return
        except rospy.ROSTimeMovedBackwardsException:
            self.warn("tfback", "time went backwards while waiting for the cloud's pose at %.3f "
                      "(bag loop?); skipped" % msg.header.stamp.to_sec())
            return
        self.integrate(msg, T)

    def _from_the_future(self, msg) -> bool:
        """A cloud stamped ahead of the clock: the old lap's last cloud after a bag loop, whose
        pose lookup would interpolate across the jump. Skipped."""
        return skip_future_stamp(msg.header.stamp.to_sec(), self.cfg.max_future_stamp, self.warn,
                                 "cloud")

    def on_cloud_pose(self, cloud, pose):
        if self._bad_cloud(cloud) or self._from_the_future(cloud):
            return
        try:
            T = pose_stamped_to_matrix(pose)
        except ConversionError as e:
            self.warn("posebad", "bad pose paired with the cloud: %s; skipped" % e)
            return
        if pose.header.frame_id and pose.header.frame_id != self.cfg.map_frame:
            self.warn("poseframe", "pose frame %r is not %r; skipped" % (
                pose.header.frame_id, self.cfg.map_frame))
            return
        self.integrate(cloud, T)

    def integrate(self, msg, T):
        t0 = time.monotonic()
        self.n_received += 1
        stamp = msg.header.stamp.to_sec()
        try:
            arr = pointcloud2_to_arrays(msg)
            if not all(k in arr for k in "xyz"):
                raise ConversionError("cloud has no x, y, z fields")
        except ConversionError as e:
            self.warn("cloud", "malformed cloud: %s; skipped" % e)
            return
        P = np.stack([arr["x"], arr["y"], arr["z"]], axis=1)
        if len(P) == 0:
            self.warn("empty", "empty cloud at %.3f; skipped" % stamp)
            return
        state = self.guard.check(stamp)
        if self.clock.jumped():            # the clock itself jumped back: a new timeline
            self.on_time_jump(stamp)
        elif state == "backwards":         # the clock goes on: one stale cloud
            self.warn("stale", "cloud stamp %.3f is older than the last one; skipped" % stamp)
            return
        if state == "duplicate":
            self.warn(state, "cloud stamp %.3f is equal to the last one; skipped" % stamp)
            return
        if self._lost_at(stamp):
            return
        inten = arr.get(self.cfg.intensity_field)
        w = arr.get(self.cfg.weight_field)
        try:
            with self.lock:
                if self.closed:
                    return
                anchor, T_anchor = self._anchor_for(stamp)
                st = self.map.integrate(P, T, stamp, intensity=inten, weights=w,
                                        anchor_id=anchor, T_map_anchor=T_anchor)
        except Exception as e:  # the map must survive whatever a cloud contains
            self.warn("integrate", "integration failed: %r; skipped" % (e,), "err")
            return
        if st.skipped:
            self.warn("skip", "cloud at %.3f skipped: %s" % (stamp, st.skipped))
            return
        self.dirty = True
        self.n_integrated += 1
        now = time.monotonic()
        self.last_proc = now - t0
        self.last_latency = (rospy.Time.now() - msg.header.stamp).to_sec()
        self.rate_window = [t for t in self.rate_window if now - t < 10.0] + [now]
        self.camera = T[:3, 3].copy()
        self._remember_view(T)

    def _anchor_for(self, stamp):
        """The latest keyframe not newer than the cloud, and its current pose (under the lock)."""
        if not self.cfg.anchor_keyframes or not len(self.kf_ids):
            return None, None
        k = np.nonzero(self.kf_stamps <= stamp + 1e-6)[0]
        if not len(k):
            return None, None
        anchor = int(self.kf_ids[k[np.argmax(self.kf_stamps[k])]])
        return anchor, self.kf_poses[anchor]

    def _remember_view(self, T):
        if self.views:
            d, a = relative_motion(self.views[-1], T)
            if d < 0.2 and np.degrees(a) < 10.0:
                return
        self.views.append(T.copy())
        if len(self.views) > 600:
            self.views = self.views[::2]

    def on_keyframes(self, msg):
        corr = {}
        for kf in msg.keyframes:  # one entry per keyframe (hundreds at most), not per point
            try:
                corr[int(kf.id)] = (kf.stamp.to_sec(), pose_to_matrix(kf.pose))
            except ConversionError as e:
                self.warn("kfbad", "keyframe %d has a bad pose: %s; ignored" % (kf.id, e))
        if not corr:
            return
        with self.lock:
            if self.closed:
                return
            for kid, (st, T) in corr.items():
                self.kf_poses[kid] = T
                hit = np.nonzero(self.kf_ids == kid)[0]
                if len(hit):
                    self.kf_stamps[hit[0]] = st
                else:
                    self.kf_ids = np.append(self.kf_ids, kid)
                    self.kf_stamps = np.append(self.kf_stamps, st)
            known = {k: T for k, (_, T) in corr.items() if k in self.map.anchors}
            n = self.map.apply_corrections(known) if known else 0
        if n:
            self.dirty = True
            rospy.loginfo("fusion_node: %d map points follow corrected keyframes (reason %d)",
                          n, msg.reason)

    # ------------------------------------------------------------------ output
    def _base_position(self):
        """The robot base's position in ``map`` now (tf), or None (no footprint to free)."""
        if not (self.cfg.publish_grid and self.cfg.grid_footprint_radius > 0 and self.cfg.base_frame):
            return None
        try:
            T = transform_stamped_to_matrix(self.tf_buffer.lookup_transform(
                self.cfg.map_frame, self.cfg.base_frame, rospy.Time(0)))
        except (ConversionError, tf2_ros.TransformException) as e:
            self.warn("base", "no pose of the base (%s <- %s): its footprint is not freed in the "
                      "grid: %s" % (self.cfg.map_frame, self.cfg.base_frame, e), "debug")
            return None
        return T[:3, 3].copy()

    def on_publish(self, _event=None):
        if self.closed:
            return
        base = self._base_position()
        if not self.dirty:
            # the map is unchanged (no clouds while LOST), but the freed footprint follows the base
            if base is None or (self.base is not None and
                                np.linalg.norm(base - self.base) < 2 * self.cfg.grid_resolution):
                return
        self.dirty = False
        try:
            self.publish(base)
        except Exception as e:
            self.warn("publish", "publishing the map failed: %r" % (e,), "err")

    def publish(self, base=None):
        """Map points and grid of a snapshot of the map; ``base``: the base's position in map
        (its footprint is freed in the grid)."""
        cfg = self.cfg
        with self.lock:  # only the copy holds the lock; integration goes on meanwhile
            c = self.map.to_cloud(min(map_min_confidence(self.products_params)))
        stamp = rospy.Time.now()
        self.base = base
        around = [p for p in (self.camera, self.goal, base) if p is not None]
        around = np.array(around) if around else None
        pts, grid = map_products(c, self.products_params,   # cloud and grid of one snapshot
                                 self.grid_extent, around, base)
        self.pub_points.publish(arrays_to_pointcloud2(
            {"intensity": np.asarray(pts["intensity"], np.float32),
             "confidence": np.asarray(pts["confidence"], np.float32)},
            stamp, cfg.map_frame, xyz=pts["xyz"]))
        if grid is not None:
            data, origin, res = grid
            msg = OccupancyGrid()
            msg.header.stamp = stamp
            msg.header.frame_id = cfg.map_frame
            msg.info.map_load_time = stamp
            msg.info.resolution = res
            msg.info.height, msg.info.width = data.shape
            msg.info.origin = matrix_to_pose(grid_origin_T(origin, cfg.grid_up_axis, cfg.grid_z_min))
            msg.data = data.reshape(-1).tolist()
            self.pub_grid.publish(msg)
            if self.pub_nav_grid is not None:
                unknown = int(np.clip(cfg.nav_grid_unknown, 0, 99))
                msg.data = np.where(data < 0, np.int8(unknown), data).reshape(-1).tolist()
                self.pub_nav_grid.publish(msg)

    def diagnostics(self, stat):
        now = time.monotonic()
        rate = len([t for t in self.rate_window if now - t < 10.0]) / 10.0
        n = len(self.map)
        level = DiagnosticStatus.OK
        text = "fusing"
        if not self.n_integrated:
            level, text = DiagnosticStatus.WARN, "no cloud integrated yet"
        elif rate == 0:
            level, text = DiagnosticStatus.WARN, "no cloud in the last 10 s"
        stat.summary(level, text)
        stat.add("integration rate (Hz)", "%.2f" % rate)
        stat.add("last processing time (ms)", "%.1f" % (1e3 * self.last_proc))
        stat.add("last latency stamp->map (s)", "%.3f" % self.last_latency)
        stat.add("map points", str(n))
        stat.add("clouds integrated", str(self.n_integrated))
        stat.add("clouds received", str(self.n_received))
        stat.add("points removed by cleaning", str(self.map.n_removed))
        rss = self.health.rss_mb()
        stat.add("process RSS (MB)", "%.1f" % rss)
        for k, v in sorted(self.warn.counts.items()):
            stat.add("skipped: " + k, str(v))
        # the keys every node reports (pose_node, depth_node: same names)
        stat.add("rate_hz", "%.2f" % rate)
        stat.add("latency_s", "%.3f" % self.last_latency)
        stat.add("drops", str(sum(v for k, v in self.warn.counts.items()   # clouds not integrated
                                  if k not in ("kfbad", "publish", "autosave"))))
        stat.add("cpu_percent", "%.1f" % self.health.cpu_percent())
        stat.add("rss_mb", "%.1f" % rss)
        return stat

    # ------------------------------------------------------------------ files and services
    def save(self, path=None, fmt=""):
        """The map into a map folder (``dense_map.ply`` + its description) or, for a path with a
        .ply/.pcd extension or a ``fmt``, one file; ``path`` absolute (default ``map_path``)."""
        path = path or self.map_path
        if _is_folder(path) and not fmt:
            with self.lock:
                return path, save_dense_map(self.map, path, self.session)
        if fmt:
            root, ext = os.path.splitext(path)
            if ext.lower() != "." + fmt.lower():
                path = root + "." + fmt.lower()
        with self.lock:
            n = self.map.save(path)
        return path, n

    def load(self, path: str, append: bool = False) -> int:
        """A map folder's dense map or a .ply/.pcd file into the map (ValueError when bad)."""
        with self.lock:
            if os.path.isdir(path):
                n = load_dense_map(self.map, path, append=append)
            else:
                n = self.map.load(path, append=append)
        self.dirty = True
        return n

    def autosave(self):
        """The map into the autosave folder of its session (rotating ``map_path`` when another
        session's maps are there: mdr_slam.io.map_dir.session_folder): (path, points, rotated).
        A ``map_path`` naming a file is written as it is."""
        if not _is_folder(self.map_path):
            return self.save() + (False,)
        # lock order: self.lock, then the folder's (reset holds self.lock while keeping the map)
        with self.lock, folder_lock(self.map_path):
            target, rotated = session_folder(self.map_path, self.session, "dense")
            if rotated:
                rospy.loginfo("fusion_node: %s held another session's maps: moved to %s.1 (%d "
                              "generations kept)", self.map_path, self.map_path, ROTATE_KEEP)
            return self.save(target) + (rotated,)

    def _keep_before_clear(self, why: str):
        """Before a reset or a load replaces the map: save it (the autosave of its session, so a
        mistaken reset loses nothing): (note for the reply, rotated)."""
        if not self.autosaving or len(self.map) == 0:
            return "", False
        try:
            path, n, rotated = self.autosave()
        except (IOError, OSError, ValueError) as e:
            rospy.logerr("fusion_node: could not keep the map before the %s: %s", why, e)
            return "; the map before it could not be kept: %s" % e, False
        if not _is_folder(self.map_path) and rotate_file(self.map_path):
            # a map_path naming a file has no session folders: the file itself is kept aside,
            # or the new session's first autosave would overwrite it
            path, rotated = file_generation(self.map_path, 1), True
        rospy.loginfo("fusion_node: %s: the map before it (%d points, session %s) is kept in %s",
                      why, n, self.session, path)
        return "; the map before it is kept in %s" % path, rotated

    def _new_session(self, session: str = "") -> None:
        """A new map begins: its files carry a new session id (``session``, else the next one)."""
        self.session = session or next_session_id(self.session)
        if self.autosaving:
            self.marker.write(self.session)

    def _service_path(self, path: str) -> str:
        return resolve_map_path(path.strip() or self.cfg.map_path, self.map_dir,
                                self.cfg.allow_any_map_path)

    def _pose_node_call(self, name: str, srv_type, *args) -> str:
        """The pose node's map service ``name`` with ``args``: a note for the reply."""
        if not self.cfg.pose_node:
            return ""
        service = rospy.resolve_name(self.cfg.pose_node + "/" + name)
        try:
            rospy.wait_for_service(service, timeout=POSE_NODE_SERVICE_WAIT)
            res = rospy.ServiceProxy(service, srv_type)(*args)
        except (rospy.ROSException, rospy.ServiceException) as e:
            return "; sparse map: no %s (%s)" % (service, e)
        return "; sparse map: %s" % res.message

    def srv_save(self, req):
        fmt = (req.format or "").strip().lower()
        if fmt not in ("", "ply", "pcd"):
            return SaveMapResponse(False, "format must be ply or pcd, got %r" % req.format, "", 0)
        try:
            path, n = self.save(self._service_path(req.path), fmt)
        except (MapPathError, IOError, OSError, ValueError) as e:
            return SaveMapResponse(False, "could not save: %s" % e, "", 0)
        note = self._pose_node_call("save_map", SaveMap, path, "") if _is_folder(path) and not fmt else ""
        return SaveMapResponse(True, "saved %d points%s" % (n, note), path, n)

    def srv_load(self, req):
        try:
            path = self._service_path(req.path)
        except MapPathError as e:
            return LoadMapResponse(False, str(e), len(self.map))
        if not os.path.exists(path):
            return LoadMapResponse(False, "no such map: %r" % req.path, len(self.map))
        warning = ""
        if os.path.isdir(path):
            # a folder's dense and sparse maps are loaded together: of two sessions they would
            # not fit each other (one file of it can still be loaded by its path)
            ok, why = check_folder_sessions(path)
            if not ok:
                return LoadMapResponse(False, "could not load %s: %s (load %s alone by its path "
                                       "if that is what you want)" % (path, why, map_files(path)[
                                           "dense"]), len(self.map))
            warning = "; warning: " + why if why else ""
        kept = ""
        if not req.append:
            kept, rotated = self._keep_before_clear("load_map")
            if rotated and _is_folder(self.map_path):
                path = after_rotation(path, self.map_path, ROTATE_KEEP)
            elif rotated and os.path.abspath(path) == os.path.abspath(self.map_path):
                path = file_generation(self.map_path, 1)
        try:
            n = self.load(path, append=req.append)
        except (IOError, OSError, ValueError) as e:
            return LoadMapResponse(False, "could not load %s: %s" % (path, e), len(self.map))
        if not req.append:   # the loaded map's session goes on (the pose node's load agrees)
            self._new_session(folder_sessions(path).get("dense", "") if os.path.isdir(path) else "")
        note = self._pose_node_call("load_map", LoadMap, path, False) \
            if os.path.isdir(path) and not req.append else ""
        return LoadMapResponse(True, "map has %d points%s%s%s" % (n, kept, warning, note), n)

    def srv_reset(self, _req):
        """Clear the map; the map there was is kept first (autosaved into its session's folder,
        which the new session's first autosave then rotates to ``last.1``)."""
        with self.lock:
            kept, _ = self._keep_before_clear("reset")
            self._new_session()
            self.map.reset()
        self.guard = StampGuard()
        self.views = []
        self.dirty = True
        return TriggerResponse(True, "map cleared%s" % kept)

    def srv_mesh(self, req):
        cfg = self.cfg
        try:   # the caller's path inside map_dir (as the map services'); the parameter's anywhere
            path = resolve_map_path(req.path, self.map_dir, cfg.allow_any_map_path) \
                if req.path.strip() else resolve_map_path(cfg.mesh_path, self.map_dir, True)
        except MapPathError as e:
            return ExportMeshResponse(False, str(e), "", 0, 0)
        voxel = float(req.voxel_length) if req.voxel_length > 0 else cfg.mesh_voxel
        with self.lock:
            cloud = self.map.to_cloud(cfg.mesh_min_confidence if self.map.confidence else 0)
            views = list(self.views) or None
        if views and len(views) > cfg.mesh_max_views:
            # every view renders the whole map: bound the export time
            views = [views[i] for i in np.linspace(0, len(views) - 1, cfg.mesh_max_views).astype(int)]
        if len(cloud["x"]) == 0:
            return ExportMeshResponse(False, "the map is empty", "", 0, 0)
        try:
            K = default_K(cfg.mesh_width, cfg.mesh_height, cfg.mesh_hfov_deg)
            mesh, nv = mesh_from_map(cloud, views, K, cfg.mesh_width, cfg.mesh_height, voxel,
                                     max(voxel, self.map.voxel_size), 0, cfg.grid_up_axis)
            if len(mesh.triangles) == 0:
                return ExportMeshResponse(False, "the TSDF produced no surface", "", 0, 0)
            n_v, n_t = write_mesh(path, mesh)
        except (IOError, OSError, ValueError, RuntimeError) as e:
            return ExportMeshResponse(False, "mesh export failed: %s" % e, "", 0, 0)
        return ExportMeshResponse(True, "%d views" % nv, path, n_v, n_t)

    def on_autosave(self, _event=None):
        if len(self.map) == 0:
            return
        try:
            path, n, _ = self.autosave()
            rospy.logdebug("fusion_node: autosaved %d points to %s", n, path)
        except (IOError, OSError, ValueError) as e:
            self.warn("autosave", "autosave to %s failed: %s" % (self.map_path, e), "err")

    def shutdown(self):
        """Autosave on exit (SIGINT/roslaunch stop): the map of a run is never lost."""
        for t in self.timers:
            t.shutdown()
        with self.lock:
            try:
                if self.autosaving and len(self.map):
                    path, n, _ = self.autosave()
                    print("fusion_node: saved %d map points to %s" % (n, path), flush=True)
                if self.autosaving:
                    self.marker.clear()  # a clean exit: nothing to resume
            except Exception as e:  # report, never raise while shutting down
                print("fusion_node: autosave failed: %r" % (e,), flush=True)
            self.closed = True
            self.map.close()


def main():
    rospy.init_node("fusion_node")
    start_from_env("fusion_node")   # MDR_MEMDEBUG=FILE (%n: node name): memory stats, memdebug.py
    cfg, map_cfg = read_config("fusion_node", *NODE_CONFIGS["fusion"])
    if cfg.omp_threads > 0:
        limit_openmp_threads(cfg.omp_threads)
    node = FusionNode(cfg, map_cfg)
    rospy.loginfo("fusion_node: fusing %s with poses from %s into %s (voxel %.3f m, confidence %s)",
                  cfg.cloud_topic, cfg.pose_source, cfg.map_frame, map_cfg.voxel_size,
                  map_cfg.confidence)
    try:
        rospy.spin()
    finally:
        node.shutdown()
