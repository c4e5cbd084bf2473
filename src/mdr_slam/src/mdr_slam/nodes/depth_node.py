"""Node 2: ELAS stereo depth with the keyframe-guided Kalman temporal filter -> /mdr/depth/points.

Thin shell around :class:`mdr_slam.depth.StereoDepth`:

- inputs ``left/image``, ``right/image`` (raw or ``~image_transport: compressed``) and
  ``left/camera_info``, ``right/camera_info`` (unless a ``~calib`` file is given), paired by
  approximate time (``~sync_tolerance``; :mod:`mdr_slam.nodes.stereo_input`);
- the left camera pose at the image stamp from tf2 (``map`` <- camera frame, ``~use_tf``) or from
  the ``~pose_source_topic`` PoseStamped stream through an interpolating time cache;
- optional keyframe events and pose corrections from ``/mdr/keyframes`` (KeyFrameArray);
- outputs ``/mdr/depth/points`` (PointCloud2 in the left optical frame at the image stamp, fields
  x y z intensity variance n_obs), optionally ``/mdr/depth/image`` (32FC1, metres), and rate,
  latency and drops on ``/diagnostics``;
- while the pose node reports LOST, ``/mdr/depth/raw_points``: single-frame ELAS clouds (same
  frame and fields, n_obs 1) at ``~lost_cloud_rate``, for costmaps' obstacle layers, and one
  empty cloud when tracking resumes: costmap_2d re-marks a source's last cloud until a newer one
  comes, and the last one of a LOST stretch would otherwise stay in the costmap for good.

Two worker threads form a pipeline, so waiting for a frame's pose does not stall matching:
``depth_elas`` takes the newest pair (the callbacks only store it, so a slow frame drops the pairs
that arrived meanwhile, counted, instead of building a backlog of stale images) and runs ELAS,
which needs no pose; ``depth_filter`` takes the matched pairs in stamp order, waits for each one's
pose (the pose node is still tracking that frame) and runs the temporal filter and publishes.
``~max_rate`` (Hz, 0 = every pair) skips pairs by their stamps before any work: the keyframe
filter needs no more, and on a 2-core robot the tracker needs the CPU more. While the pose node
reports LOST (``~tracking_state_topic``), pairs get no pose and the filter pauses; only
``~lost_cloud_rate`` pairs a second are matched, and their single-frame points (sigma_Z at most
``LOST_CLOUD_MAX_SIGMA``) go to ``/mdr/depth/raw_points``, so that a robot driving on wheel
odometry meanwhile still sees what is in front of it; the rest of the CPU is relocalization's.
The fusion node does not read that topic: a map needs the pose these clouds lack.
Bad input is logged (throttled, one line per kind) and skipped; the node never dies on input.
A bag loop (the clock jumping back) resets the filter and the tf buffer; pairs and transforms
stamped more than ``~max_future_stamp`` ahead of the clock (the old lap's last ones, delivered
after the jump) are dropped, so no pose is interpolated across the jump (tests/ros/test_time_jump.py).

Memory in long runs: the node's ~20 threads (the two workers, rospy's per-connection receivers,
timers) allocate in up to 16 glibc malloc arenas. The slow RSS creep of a looped live run
(0.1-0.5 MB/min) is there: the anonymous mappings of the thread arenas grow while malloc's bytes
in use and the gc-tracked Python objects stay flat. glibc's dynamic mmap threshold is the lever:
once a large mmapped block is freed, it rises to its size (up to 32 MB) and takes every arena's trim
threshold with it, so the 1-2 MB frame arrays the threads free stay resident in their arenas.
``~malloc_mmap_threshold`` (bytes, 0 = glibc's dynamic default) fixes the threshold: larger
blocks are mmapped and unmapped on free. 1048576 held the RSS flat (-0.00 MB/min, minutes 2-9 of
a looped 10-minute live run, against +0.5) and 16 MB lower, but costs CPU: every frame array is
then freshly mapped and faulted in, 14k page faults per frame, +29 ms (+60 %) CPU per frame
offline on the 2-core test VM. The creep itself slows down (+3 MB over minutes 2-30 of a 30-minute
run), so the default stays glibc's. ``MDR_MEMDEBUG=FILE`` in the environment writes periodic memory
samples (smaps by mapping kind, mallinfo2, Python object growth, optionally tracemalloc): see
:mod:`mdr_slam.nodes.memdebug`.
"""
from __future__ import annotations

import collections
import threading
import time
from typing import Optional

import diagnostic_updater
import numpy as np
import rospy
import tf2_ros
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import Image, PointCloud2

from ..camera import CalibrationError, StereoCamera, images_are_rectified
from ..conversions import (ConversionError, arrays_to_pointcloud2, camera_info_to_model,
                           image_msg_to_mono8 as to_mono8, numpy_to_image, pose_stamped_to_matrix,
                           pose_to_matrix, transform_stamped_to_matrix)
from ..depth import DepthConfig, PoseCache, StereoDepth, render_depth
from .common import (ClockWatch, StampGuard, StampRateLimiter, Throttled, read_config,
                     skip_future_stamp, transform_listener)
from .config import NODE_CONFIGS, DepthNodeConfig
from .health import ProcessHealth, update_diagnostics
from .memdebug import set_mmap_threshold, start_from_env
from .stereo_input import StereoInput

# m: the largest sigma_Z of a single-frame point published while LOST (about 3 m away at 0.5 px
# on an 11 cm, 458 px rig; less on weak texture), where one match is good enough for a costmap
LOST_CLOUD_MAX_SIGMA = 0.10


class DepthNode:
    def __init__(self, cfg: DepthNodeConfig, depth_cfg: DepthConfig):
        self.cfg = cfg
        self.depth_cfg = depth_cfg            # StereoDepth's, (re)built per calibration
        self.warn = Throttled()
        self.guard = StampGuard()
        self.lock = threading.Lock()          # the filter: worker thread vs keyframe events
        self.cv = threading.Condition()
        self.pending = None
        self.depth = None
        self.camera_key = None
        self.fixed_camera = None
        self.counts = {"received": 0, "processed": 0, "dropped": 0, "skipped": 0, "published": 0,
                       "throttled": 0, "paused_lost": 0, "future": 0,
                       "lost_clouds": 0}
        self.lost_at = None                   # stamp of the pose node's last LOST report
        self.lost_cloud_frame = None          # frame of the last raw cloud of this LOST stretch
        self.raw_lock = threading.Lock()      # a raw cloud is never sent after the empty one
        self.matched = collections.deque()    # ELAS done, waiting for the filter (stamp order)
        self.max_matched = 3                  # more: the filter stage is behind, drop the oldest
        self.limiter = StampRateLimiter(cfg.max_rate)
        self.lost_limiter = StampRateLimiter(cfg.lost_cloud_rate)
        self.cpu_s = {"match": 0.0, "filter": 0.0}   # thread CPU of the two stages (diagnostics)
        self.generation = 0                   # +1 per filter reset: queued pairs of before are stale
        self.last_latency = float("nan")
        self.last_timings = {}
        self.last_stats = {}
        self.last_points = 0
        self.t_start = time.monotonic()
        self.kf_events_seen = False
        self.kf_pending = []                  # (stamp, id) of keyframes not yet started
        self.kf_poses = {}                    # id -> last known pose of pending / current keyframes
        self.clock = ClockWatch()             # ROS time jumping back: a new timeline

        if cfg.calib:
            self.fixed_camera = self._load_calib(cfg.calib)
        self.pub_points = rospy.Publisher("mdr/depth/points", PointCloud2, queue_size=2)
        self.pub_raw = (rospy.Publisher("mdr/depth/raw_points", PointCloud2, queue_size=2)
                        if cfg.lost_cloud_rate > 0 and cfg.tracking_state_topic else None)
        self.pub_image = (rospy.Publisher("mdr/depth/image", Image, queue_size=2)
                          if cfg.publish_depth_image else None)
        self.input = StereoInput("depth_node", self.on_images, self.warn,
                                 cfg.sync_tolerance, cfg.image_transport,
                                 with_info=self.fixed_camera is None,
                                 queue_size=cfg.sync_queue_size)
        if self.fixed_camera is not None:
            self.fixed_camera = self._rectified(self.fixed_camera)

        self.tf_buffer = None
        self.pose_cache = PoseCache(max_gap=cfg.pose_max_gap)
        if cfg.use_tf:
            self.tf_buffer = tf2_ros.Buffer(cache_time=rospy.Duration(30.0))
            self.tf_listener = transform_listener(self.tf_buffer, cfg.max_future_stamp, self.warn,
                                                  "depth_node")
        else:
            self.sub_pose = rospy.Subscriber(cfg.pose_source_topic, PoseStamped, self.on_pose,
                                             queue_size=100)
        if cfg.tracking_state_topic:
            try:
                from mdr_slam_msgs.msg import TrackingState
                self.sub_state = rospy.Subscriber(cfg.tracking_state_topic, TrackingState,
                                                  self.on_state, queue_size=20)
            except ImportError as e:
                rospy.logwarn("depth_node: mdr_slam_msgs unavailable (%s); not pausing when LOST", e)
        if cfg.use_keyframe_events:
            try:
                from mdr_slam_msgs.msg import KeyFrameArray
                self.sub_kf = rospy.Subscriber(cfg.keyframe_topic, KeyFrameArray, self.on_keyframes,
                                               queue_size=20)
            except ImportError as e:
                rospy.logwarn("depth_node: mdr_slam_msgs unavailable (%s); automatic keyframes", e)

        self.health = ProcessHealth()
        self.updater = diagnostic_updater.Updater()
        self.updater.setHardwareID("mdr_depth")
        self.updater.period = cfg.diagnostics_period
        self.updater.add("depth", self._diagnostics)
        # also without input (the worker updates after each frame): "no frame processed yet"
        self.diag_timer = rospy.Timer(rospy.Duration(max(0.1, cfg.diagnostics_period)),
                                      lambda _e: update_diagnostics(self.updater), reset=True)
        self.worker = threading.Thread(target=self._work, name="depth_elas", daemon=True)
        self.worker.start()
        self.filter_worker = threading.Thread(target=self._work_filter, name="depth_filter",
                                              daemon=True)
        self.filter_worker.start()
        if cfg.malloc_mmap_threshold > 0 and not set_mmap_threshold(cfg.malloc_mmap_threshold):
            rospy.logwarn("depth_node: cannot set malloc_mmap_threshold (not glibc?)")
        rospy.loginfo("depth_node: %s, temporal=%s, pose from %s, listening on %s and %s",
                      "calib file" if self.fixed_camera is not None else "camera_info",
                      depth_cfg.temporal, "tf" if cfg.use_tf else cfg.pose_source_topic,
                      self.input.topics["left"], self.input.topics["right"])

    # ------------------------------------------------------------------ set-up helpers
    def _load_calib(self, path):
        try:
            from ..calib import load_stereo_calibration
            cam = load_stereo_calibration(path)
            rospy.loginfo("depth_node: calibration from %s (%dx%d, B=%.4f m)", path,
                          cam.size[0], cam.size[1], cam.baseline)
            return cam
        except Exception as e:  # missing module, unreadable file: camera_info still works
            rospy.logerr("depth_node: cannot use calib %r (%s); falling back to camera_info", path, e)
            return None

    def _camera_for(self, linfo, rinfo):
        """StereoCamera for this pair; StereoDepth is (re)built when the calibration changes."""
        if self.fixed_camera is not None:
            key = "calib"
            if self.camera_key != key:
                self.depth = StereoDepth(self.fixed_camera, self.depth_cfg)
                self.camera_key = key
            return
        key = (tuple(linfo.K), tuple(linfo.P), tuple(linfo.D), tuple(linfo.R), linfo.width,
               linfo.height, tuple(rinfo.K), tuple(rinfo.P), tuple(rinfo.D), tuple(rinfo.R))
        if key != self.camera_key:
            cam = self._rectified(StereoCamera(camera_info_to_model(linfo),
                                               camera_info_to_model(rinfo)))
            self.depth = StereoDepth(cam, self.depth_cfg)
            self.camera_key = key
            rospy.loginfo("depth_node: camera %dx%d fx=%.1f B=%.4f m%s%s", cam.size[0], cam.size[1],
                          cam.fx, cam.baseline, "" if cam.is_rectified else " (rectifying)",
                          " doffs=%+.3f px (right cx differs)" % cam.doffs if cam.doffs else "")

    def _rectified(self, cam):
        """``cam``, taken as rectified when the images already are (``~rectified``)."""
        if images_are_rectified(self.cfg.rectified, self.input.topics["left"], cam) and \
                not cam.is_rectified:
            return cam.assume_rectified()
        return cam

    # ------------------------------------------------------------------ callbacks
    def on_images(self, left, right, linfo=None, rinfo=None):
        with self.cv:
            self.counts["received"] += 1
            t = left.header.stamp.to_sec()
            if self._from_the_future(t):
                return
            lost = self.lost_at is not None and abs(t - self.lost_at) < 1.0
            if lost and (self.pub_raw is None or self.lost_limiter.skip(t)):
                self.counts["paused_lost"] += 1   # no pose will come for it
                return
            if not lost and self.limiter.skip(t):   # max_rate
                self.counts["throttled"] += 1
                return
            if self.pending is not None:
                self.counts["dropped"] += 1   # the worker is busy: keep only the newest pair
            self.pending = (left, right, linfo, rinfo, time.monotonic(), lost)
            self.cv.notify()

    def _from_the_future(self, t: float) -> bool:
        """A pair stamped ahead of the clock (the old lap's last pairs after a bag loop): skip."""
        if skip_future_stamp(t, self.cfg.max_future_stamp, self.warn, "depth_node: stereo"):
            self.counts["future"] += 1
            return True
        return False

    def on_state(self, msg):
        """The tracker's state per frame: LOST / NOT_INITIALIZED pause the filter (on_images)."""
        lost = msg.state in (msg.LOST, msg.NOT_INITIALIZED)
        with self.raw_lock:
            with self.cv:
                self.lost_at = msg.header.stamp.to_sec() if lost else None
                frame, self.lost_cloud_frame = (None, self.lost_cloud_frame) if lost else \
                    (self.lost_cloud_frame, None)
            if frame is not None:   # tracking resumed: the obstacle layers drop the last raw cloud
                self.pub_raw.publish(_cloud_msg(None, msg.header.stamp, frame))

    def on_pose(self, msg):
        try:
            T = pose_stamped_to_matrix(msg)
        except ConversionError as e:
            self.warn("pose", "depth_node: pose skipped: %s" % e)
            return
        t = msg.header.stamp.to_sec()
        if self.pose_cache.latest is not None and t < self.pose_cache.latest - 1.0:
            self.pose_cache.clear()            # time went backwards (bag loop)
        self.pose_cache.add(t, T)

    def on_keyframes(self, msg):
        self.kf_events_seen = True
        with self.lock:
            for kf in msg.keyframes:
                t = kf.stamp.to_sec()
                try:
                    T = pose_to_matrix(kf.pose)
                except (ConversionError, ValueError) as e:
                    self.warn("kfpose", "depth_node: keyframe %d skipped: %s" % (kf.id, e))
                    continue
                if msg.reason == msg.NEW_KEYFRAME:
                    self.kf_pending.append((t, int(kf.id)))
                    self.kf_poses[int(kf.id)] = T
                    continue
                cur = self.depth.filter.keyframe if self.depth is not None else None
                if cur is None:
                    continue
                T_old = self.kf_poses.get(int(kf.id))
                try:  # loop closure / BA moved our keyframe: its points follow
                    if cur.id == kf.id and T_old is not None:
                        # ours may sit frames after the pose keyframe: move it rigidly with it
                        self.depth.filter.correct_keyframe(T_old, T)
                    elif abs(cur.stamp - t) < 1e-3:   # the same frame: its pose is ours
                        self.depth.filter.set_keyframe_pose(T)
                except ValueError as e:
                    self.warn("kfpose", "depth_node: keyframe correction skipped: %s" % e)
                if int(kf.id) in self.kf_poses:
                    self.kf_poses[int(kf.id)] = T

    # ------------------------------------------------------------------ workers
    def _work_filter(self):
        """Stage 2: matched pairs in stamp order -> pose, temporal filter, publish."""
        while not rospy.is_shutdown():
            with self.cv:
                while not self.matched and not rospy.is_shutdown():
                    self.cv.wait(0.2)
                if not self.matched:
                    continue
                item = self.matched.popleft()
                self.cv.notify_all()   # room in the queue: stage 1 may match the newest pair
            self._step("filter", self.filter_and_publish, item)
            update_diagnostics(self.updater)

    def _step(self, stage: str, fn, item) -> None:
        """One pair through one stage; an error skips the pair (the node never dies on input)
        and the stage's thread CPU is counted for the diagnostics."""
        c0 = time.thread_time()
        try:
            fn(*item)
        except Exception as e:  # never die on input: log and go on with the next pair
            self.counts["skipped"] += 1
            self.warn("error", "depth_node: frame skipped after an error: %r" % (e,), "err")
        self.cpu_s[stage] += time.thread_time() - c0

    def _work(self):
        """Stage 1: the newest pair -> checks, conversion, ELAS -> the filter stage's queue."""
        while not rospy.is_shutdown():
            with self.cv:
                # a pair is matched only when the filter stage has room for it: matching pairs
                # that the filter would drop as too old takes the CPU the tracker needs, while
                # the newest pair keeps replacing the pending one meanwhile
                while (self.pending is None or len(self.matched) >= self.max_matched) \
                        and not rospy.is_shutdown():
                    self.cv.wait(0.2)
                item, self.pending = self.pending, None
            if item is None:
                continue
            self._step("match", self.process, item)

    def _pose_at(self, stamp, frame: str) -> Optional[np.ndarray]:
        if self.tf_buffer is not None:
            try:
                ts = self.tf_buffer.lookup_transform(self.cfg.map_frame, frame, stamp,
                                                     rospy.Duration(self.cfg.tf_timeout))
                return transform_stamped_to_matrix(ts)
            except (tf2_ros.LookupException, tf2_ros.ConnectivityException,
                    tf2_ros.ExtrapolationException, tf2_ros.TransformException) as e:
                self.warn("tf", "depth_node: no pose %s <- %s at %.3f (%s); frame skipped"
                          % (self.cfg.map_frame, frame, stamp.to_sec(), str(e).splitlines()[0]))
                return None
            except rospy.ROSTimeMovedBackwardsException:
                self.warn("tfback", "depth_node: time went backwards while waiting for the pose at "
                          "%.3f (bag loop?); frame skipped" % stamp.to_sec())
                return None
        t = stamp.to_sec()
        deadline = time.monotonic() + self.cfg.tf_timeout
        while True:  # the pose of this very frame may still be on its way from the pose node
            T = self.pose_cache.lookup(t)
            if T is not None or time.monotonic() > deadline:
                break
            time.sleep(0.005)
        if T is None:
            self.warn("pose", "depth_node: no pose at %.3f on %s (have %d poses, latest %s); "
                      "frame skipped" % (t, self.cfg.pose_source_topic, len(self.pose_cache),
                                         self.pose_cache.latest))
        return T

    def process(self, left, right, linfo, rinfo, t_recv, lost=False):
        """Stage 1 of one pair: stamp checks, camera, conversion, ELAS; queued for stage 2, or
        published at once as a single-frame cloud when it came while the tracker was ``lost``."""
        stamp = left.header.stamp
        t = stamp.to_sec()
        state = self.guard.check(t)
        jumped = self.clock.jumped()
        if state == "backwards" and not jumped:   # the clock goes on: one out-of-order pair
            self.warn("stale", "depth_node: stereo stamp %.3f is older than the last one; skipped" % t)
            self.counts["skipped"] += 1
            return
        if jumped:
            self.warn("back", "depth_node: time went backwards to %.3f (bag loop?); filter reset" % t)
            with self.cv:
                self.matched.clear()
            with self.lock:
                self.generation += 1
                if self.depth is not None:
                    self.depth.reset()
                self.kf_pending = []
                self.kf_poses = {}
            self.pose_cache.clear()
            if self.tf_buffer is not None:   # poses of the old timeline must not answer lookups
                self.tf_buffer.clear()       # of the new one before the listener sees the jump
        if state == "duplicate":
            self.warn("dup", "depth_node: duplicate stamp %.3f; skipped" % t)
            self.counts["skipped"] += 1
            return
        key = "camera"   # one throttled line per kind of problem, so none hides another
        try:
            if self.fixed_camera is None and (linfo is None or rinfo is None):
                raise ConversionError("no camera_info and no calib file")
            self._camera_for(linfo, rinfo)
            key = "image"
            L = to_mono8(left)
            R = to_mono8(right)
            key = "size"
            if L.shape != R.shape:
                raise ConversionError("left %s and right %s images differ in size" % (L.shape, R.shape))
        except (ConversionError, CalibrationError, ValueError) as e:
            self.warn(key, "depth_node: input skipped: %s" % e)
            self.counts["skipped"] += 1
            return
        frame = self.cfg.camera_frame or left.header.frame_id or "camera_left_optical_frame"
        # ELAS here, without the pose: the pose node is still tracking this frame, and the filter
        # stage waits for its pose while this stage matches the next pair
        try:
            meas = self.depth.measure(L, R)
        except ValueError as e:
            self.warn("depth", "depth_node: input skipped: %s" % e)
            self.counts["skipped"] += 1
            return
        if lost:
            self.publish_lost_cloud(left.header, frame, meas)
            return
        with self.cv:
            if len(self.matched) >= self.max_matched:
                self.matched.popleft()
                self.counts["dropped"] += 1
            self.matched.append((left.header, frame, meas, self.depth, self.generation))
            self.cv.notify_all()

    def publish_lost_cloud(self, header, frame, meas):
        """A pair matched while the tracker is LOST: its own points, on ``mdr/depth/raw_points``."""
        out = self.depth.single_frame(meas, LOST_CLOUD_MAX_SIGMA)
        frame_id = header.frame_id or frame
        msg = _cloud_msg(out, header.stamp, frame_id)
        with self.raw_lock:   # checked and sent before on_state can send the empty cloud
            with self.cv:
                if self.lost_at is None:   # tracking resumed while this pair was matched: stale
                    return
                self.lost_cloud_frame = frame_id
            self.pub_raw.publish(msg)
        self.counts["lost_clouds"] += 1

    def filter_and_publish(self, header, frame, meas, depth, generation):
        """Stage 2 of one pair: its pose (waiting for the pose node), the filter, publishing."""
        stamp = header.stamp
        t = stamp.to_sec()
        if self._from_the_future(t):   # matched before the clock jumped back
            self.counts["skipped"] += 1
            return
        T = self._pose_at(stamp, frame)
        if T is None:
            self.counts["skipped"] += 1
            return
        with self.lock:
            if depth is not self.depth or generation != self.generation:   # since replaced/reset
                self.counts["skipped"] += 1
                return
            new_kf, kf_id = None, None
            if self.kf_events_seen:
                new_kf = False
                due = [k for k in self.kf_pending if k[0] <= t + 1e-4]
                if due:
                    new_kf, kf_id = True, due[-1][1]
                    self.kf_pending = [k for k in self.kf_pending if k[0] > t + 1e-4]
                    keep = {k[1] for k in self.kf_pending} | {kf_id}
                    self.kf_poses = {k: v for k, v in self.kf_poses.items() if k in keep}
            try:
                out = depth.update(t, meas, T, new_keyframe=new_kf, keyframe_id=kf_id)
            except ValueError as e:
                self.warn("depth", "depth_node: input skipped: %s" % e)
                self.counts["skipped"] += 1
                return
        self.counts["processed"] += 1
        frame_id = header.frame_id or frame
        self.pub_points.publish(_cloud_msg(out, stamp, frame_id))
        self.counts["published"] += 1
        if self.pub_image is not None:
            img = render_depth(out.points, depth.camera)
            self.pub_image.publish(numpy_to_image(img, "32FC1", stamp=stamp, frame_id=frame_id))
        self.last_points = len(out)
        self.last_timings = out.timings
        self.last_stats = out.stats
        self.last_latency = (rospy.Time.now() - stamp).to_sec()

    def _diagnostics(self, stat):
        c = self.counts
        dt = max(1e-6, time.monotonic() - self.t_start)
        level = DiagnosticStatus.OK
        text = "ok"
        if c["processed"] == 0:
            level, text = DiagnosticStatus.WARN, "no frame processed yet"
        elif c["skipped"] > c["processed"]:
            level, text = DiagnosticStatus.WARN, "most frames skipped (see the log)"
        stat.summary(level, text)
        stat.add("rate_hz", "%.2f" % (c["processed"] / dt))
        stat.add("latency_s", "%.3f" % self.last_latency)
        for k, v in c.items():
            stat.add(k, str(v))
        stat.add("points_last_frame", str(self.last_points))
        for k, v in self.last_timings.items():
            stat.add("ms_" + k, "%.1f" % v)
        for k, v in self.cpu_s.items():   # per published cloud: the rest of the process CPU is
            stat.add("cpu_ms_%s_per_cloud" % k,   # receiving images and ROS itself
                     "%.1f" % (1e3 * v / max(1, c["published"])))
        stat.add("drops", str(c["dropped"] + c["skipped"]))   # pairs received but not published
        self.health.add_to(stat)
        return stat


def _cloud_msg(out, stamp, frame_id: str) -> PointCloud2:
    """A DepthOutput's points (x y z intensity variance n_obs) as a PointCloud2; None: an empty
    cloud with the same fields."""
    if out is None:
        return arrays_to_pointcloud2({"intensity": np.zeros(0, np.float32),
                                      "variance": np.zeros(0, np.float32),
                                      "n_obs": np.zeros(0, np.uint32)}, stamp=stamp,
                                     frame_id=frame_id, xyz=np.zeros((0, 3), np.float32))
    return arrays_to_pointcloud2({"intensity": out.intensity, "variance": out.variance,
                                  "n_obs": out.n_obs.astype(np.uint32)},
                                 stamp=stamp, frame_id=frame_id, xyz=out.points)


def main():
    rospy.init_node("depth_node")
    start_from_env("depth_node")   # MDR_MEMDEBUG=FILE: memory stats for long runs (memdebug.py)
    try:
        DepthNode(*read_config("depth_node", *NODE_CONFIGS["depth"]))
    except Exception as e:  # bad parameters: say which, and stay up so the launch keeps running
        rospy.logerr("depth_node: cannot start: %s", e)
    rospy.spin()
