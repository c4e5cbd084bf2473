"""System: the stereo SLAM entry point (ORB-SLAM2 System) used by pose_node and `mdr run`.

    sys = System(camera, config=None, threads=True)   # TrackerConfig or a dict of its fields
    res = sys.track(stamp, left_rect, right_rect)     # -> TrackResult
    traj = sys.trajectory()                            # mdr_slam.io.Trajectory (T_map_cam)
    sys.shutdown()

``threads=True`` runs LocalMapping (and LoopClosing) in background threads so tracking is not
stalled by bundle adjustment; ``threads=False`` runs them synchronously inside ``track`` after the
frame is tracked, which makes results deterministic (the offline runner).
"""
from __future__ import annotations

import threading
import time
from typing import Dict, Optional, Tuple

import cv2
import numpy as np

from ..geometry import interpolate_poses, inv_T
from ..io import Trajectory
from .ba_process import BAWorker
from .config import TrackerConfig
from .frame import Frame
from .local_mapping import LocalMapping
from .loop_closing import LoopClosing
from .map import Map
from .odometry_calibration import OdometryCalibration
from .orb import ORBextractor
from .planar import PlanarMotion
from .result import TrackResult
from .tracking import OK, RELOCALIZED, Tracking

# TrackerConfig and TrackResult live in .config and .result (shared with the orbslam3 backend);
# make_system: mdr_slam.pose.factory
__all__ = ["System", "TrackResult", "TrackerConfig"]

# Tuned internals (where ORB-SLAM2 differs, its way in brackets)
RELOC_CANDIDATES = 10          # LOST: keyframes tried for relocalization per frame
TEXTURE_TAU = 10.0             # a keypoint's x (u, u_R) and y residuals weigh min(1, gradient energy / tau)
                               # (grey levels^2, 7x7 patch; 0: isotropic, ORB-SLAM2)
TRAJECTORY_BLEND = True        # frames between two keyframes follow both (false: the reference keyframe
                               # only, ORB-SLAM2 SaveTrajectoryTUM)
YIELD_MAX_MS = 60.0            # threads: mapping waits at most this long for a frame's tracking, so its
                               # share of the GIL does not slow tracking (0: off)
BACKPRESSURE_INLIERS = 80      # threads: tracking waits for LocalMapping when it gets this weak
FRAME_PROCESS = True           # threads: frames (ORB on both images, stereo matching) are made in a
                               # child process, out of the interpreter lock that tracking and the
                               # mapping threads share (ORB-SLAM2: in the tracking thread)

ODOMETRY_CALIBRATION = True    # wheel odometry corrected by its errors fitted against tracking
                               # (odometry_calibration) carries the pose while LOST

_REASONS = {"local_ba": 1, "loop_closure": 2}


def _refusal_at(refusal, stamp: float):
    """Tracking.last_odom_refusal without its stamp if it was made for the frame at ``stamp``."""
    if refusal is None or abs(refusal[0] - float(stamp)) > 1e-9:
        return None
    return tuple(refusal[1:])


class System:
    def __init__(self, camera, config=None, threads: bool = True,
                 T_map_cam0: Optional[np.ndarray] = None):
        """``T_map_cam0``: the map frame the poses are reported in, as the pose of the first
        camera (tracking's own world) in it; REP-105 users pass T_base_cam so that map is
        base_link where tracking starts (z up for a level robot). Default identity: map is the
        first camera's optical frame. Only outputs change; the tracker works in its own world.
        ``config``: a TrackerConfig, or a mapping of its fields (unknown keys raise ConfigError)."""
        self.cfg = TrackerConfig.of(config)
        self.camera = camera
        self.threads = bool(threads)
        self.T_map_world = np.eye(4) if T_map_cam0 is None else np.asarray(T_map_cam0, float)
        self.T_base_cam = None if T_map_cam0 is None else np.asarray(T_map_cam0, float).copy()
        self.extractor = ORBextractor(self.cfg.n_features, self.cfg.scale_factor, self.cfg.n_levels,
                                      self.cfg.fast_threshold,
                                      min_fast_threshold=self.cfg.min_fast_threshold)
        self.extractor_right = ORBextractor(self.cfg.n_features, self.cfg.scale_factor, self.cfg.n_levels,
                                            self.cfg.fast_threshold,
                                            min_fast_threshold=self.cfg.min_fast_threshold)
        self.request_reset = False
        self.reset_pending_anchor = False   # a reset map waits for its first keyframe's place
        self.correction_id = 0
        # the robot's odometry errors: kept across map resets (they are the wheels', not the map's)
        self.odometry_calibration = OdometryCalibration()
        # localization mode (ORB-SLAM2 ActivateLocalizationMode): tracking against the map only,
        # no new keyframes or points, so a loaded map is used and never changed
        self.localization = False
        self.map_loaded = False    # a saved map was loaded (pose.map_io): never reset it
        self.planar_recheck = False   # planar_motion decided again at the next frame (a map loaded)
        self._created_before_reset = 0
        # threads: set while no frame is being tracked. LocalMapping and LoopClosing wait for it
        # between their steps and BA iterations (yield_to_tracking): Python runs one thread at a
        # time (the GIL), so without this a keyframe's BA takes half of tracking's turns and the
        # frame's wall time doubles (a live node then skips frames)
        self.tracking_idle = threading.Event()
        self.tracking_idle.set()
        self.frame_worker = None   # ba_process.BAWorker making the frames (threads, FRAME_PROCESS)
        if self.threads and FRAME_PROCESS:
            self.frame_worker = BAWorker()
            self.frame_worker.prewarm()
        self._orb_params = (self.cfg.n_features, self.cfg.scale_factor, self.cfg.n_levels,
                            self.cfg.fast_threshold, self.cfg.min_fast_threshold)
        self._build()

    def _build(self) -> None:
        self.map = Map()
        self.local_mapping = LocalMapping(self, self.cfg)
        self.loop_closing = None
        if self.cfg.loop_closing:
            self.loop_closing = LoopClosing(self, self.cfg)
        self.tracking = Tracking(self, self.cfg)
        if self.threads:
            self.local_mapping.start()
            if self.loop_closing is not None:
                self.loop_closing.start()

    def set_map_frame(self, T_map_cam0: np.ndarray) -> None:
        """Put map where ``T_map_cam0`` (T_base_cam) says, once the camera's mount is known after
        tracking began (see __init__); planar_motion is decided again at the next frame."""
        self.T_map_world = np.asarray(T_map_cam0, float).copy()
        self.T_base_cam = self.T_map_world.copy()
        self.planar_recheck = True

    def planar_wanted(self, frame=None) -> bool:
        """``planar_motion``: true, false, or auto (true once the frames carry the robot's wheel
        odometry, ``frame.T_odom_cam``: a wheeled base on a floor). Never without the camera's
        mount on the base (map is then the first camera's frame, whose plane is not the floor)."""
        mode = str(self.cfg.planar_motion).lower()
        if self.T_base_cam is None or mode in ("false", "0", "off", "no"):
            return False
        if mode == "auto":
            return frame is not None and getattr(frame, "T_odom_cam", None) is not None
        return True

    def make_planar(self, frame=None) -> Optional[PlanarMotion]:
        """The floor plane for the current T_map_world, or None (:meth:`planar_wanted`)."""
        return PlanarMotion(self.T_map_world, self.T_base_cam) if self.planar_wanted(frame) \
            else None

    # ------------------------------------------------------------------ hooks
    def loop_closing_insert(self, kf) -> None:
        if self.loop_closing is not None:
            self.loop_closing.insert_keyframe(kf)

    def relocalization_candidates(self, frame) -> list:
        if self.loop_closing is not None:
            c = self.loop_closing.relocalization_candidates(frame, RELOC_CANDIDATES)
            if c is not None:
                return c
        kfs = self.map.good_keyframes()
        return sorted(kfs, key=lambda k: -k.id)[: RELOC_CANDIDATES]

    def yield_to_tracking(self) -> None:
        """Called by the mapping threads where they hold no map lock: wait (at most
        ``yield_max_ms``) while a frame is being tracked, so tracking has the interpreter."""
        if self.threads and not self.tracking_idle.is_set():
            self.tracking_idle.wait(float(YIELD_MAX_MS) / 1000.0)

    # ------------------------------------------------------------------ API
    def make_frame(self, stamp: float, left_rect: np.ndarray, right_rect: np.ndarray) -> Frame:
        """The Frame of a rectified stereo pair: ORB on both images and stereo matching.

        It reads no map, so a caller may build the next frame while the previous one is being
        tracked (``track(..., frame=...)``): the two stages then overlap on two cores. Call it from
        one thread at a time (the ORB extractors are not re-entrant). With ``threads`` the
        features are computed in a child process (``FRAME_PROCESS``; in this thread when it
        cannot run), so ``build_cpu_ms`` then counts only this process's share."""
        t0 = time.perf_counter()
        c0 = time.thread_time()
        if left_rect.ndim == 3:
            left_rect = cv2.cvtColor(left_rect, cv2.COLOR_BGR2GRAY)
            right_rect = cv2.cvtColor(right_rect, cv2.COLOR_BGR2GRAY)
        features = None
        if self.frame_worker is not None and not self.frame_worker.failed:
            cam = self.camera
            features = self.frame_worker.run(
                (self._orb_params, left_rect, right_rect, cam.fx, cam.baseline,
                 float(getattr(cam, "doffs", 0.0))), {}, solver="stereo_features")
        frame = Frame(stamp, left_rect, right_rect, self.camera, self.extractor,
                      self.extractor_right, th_depth_factor=self.cfg.th_depth, features=features)
        frame.texture_tau = float(TEXTURE_TAU)
        frame.build_ms = 1000.0 * (time.perf_counter() - t0)
        frame.build_cpu_ms = 1000.0 * (time.thread_time() - c0)   # the right image's thread excluded
        return frame

    def track(self, stamp: float, left_rect: Optional[np.ndarray] = None,
              right_rect: Optional[np.ndarray] = None, frame: Optional[Frame] = None) -> TrackResult:
        """Track one stereo pair (rectified images) or a Frame already made by ``make_frame``."""
        if frame is None:
            frame = self.make_frame(stamp, left_rect, right_rect)
        if self.threads and YIELD_MAX_MS > 0:
            self.tracking_idle.clear()
        try:
            return self._track(frame)
        finally:
            self.tracking_idle.set()

    def _track(self, frame: Frame) -> TrackResult:
        stamp = frame.stamp
        t0 = time.perf_counter()
        c0 = time.thread_time()
        if self.request_reset:
            self.reset()
        T_odom_base = None
        if ODOMETRY_CALIBRATION and self.T_base_cam is not None and \
                getattr(frame, "T_odom_cam", None) is not None:
            # the tracker's motion model keeps the raw odometry; the corrected chain carries the
            # pose while it is lost, and the gates, loops and local BA use it once calibrated
            T_odom_base = frame.T_odom_cam @ inv_T(self.T_base_cam)
            T_cal = self.odometry_calibration.correct(stamp, T_odom_base) @ self.T_base_cam
            if self.odometry_calibration.calibrated:   # before, the chain is the raw odometry
                frame.T_odom_cam_calibrated = T_cal
        if self.reset_pending_anchor and not self.map.keyframes:
            self._anchor_new_map()
        if self.map.planar is None and (not self.map.keyframes or self.planar_recheck):
            # decided with a map's first frame (or the first after loading one)
            self.planar_recheck = False
            planar = self.make_planar(frame)
            if planar is not None:
                self.map.planar = planar
                for kf in self.map.keyframes.values():
                    kf.planar = planar
        t_frame = frame.build_ms
        out = self.tracking.track(frame)
        if self.map.keyframes:
            self.reset_pending_anchor = False
        if out["is_keyframe"] and self.loop_closing is not None:   # proximity loop path
            self.loop_closing.keep_image(out["keyframe_id"], frame.image)
        state = self.tracking.state
        tracked_ok = state in (OK, RELOCALIZED) and frame.T_cw is not None and \
            self.tracking.records[-1][1] is not None
        t_track = t_frame + 1000.0 * (time.perf_counter() - t0)
        c_track = frame.build_cpu_ms + 1000.0 * (time.thread_time() - c0)
        self.tracking_idle.set()   # the mapping threads may go on (back-pressure waits for them)
        if self.threads and tracked_ok and self.local_mapping.queue_size() >= 2 and \
                self.tracking.n_matches_inliers < BACKPRESSURE_INLIERS:
            # back-pressure: weak tracking while LocalMapping lags (the GIL and a loaded CPU
            # starve its thread) would soon be LOST; let it catch up before the next frame
            self.local_mapping.wait_queue_below(2, timeout=1.0)
        if not self.threads:
            self.local_mapping.spin_sync()
            if self.loop_closing is not None:
                self.loop_closing.spin_sync()
        corrections = self._collect_corrections()
        n_tracked = int(np.count_nonzero(frame.mp_ids >= 0)) if tracked_ok else 0
        T_map_cam = T_map_cam_coasted = odometry_errors = None
        if tracked_ok:   # through the reference keyframe: includes a correction made just now
            with self.map.lock:
                _, kf, T_c_ref, _, _ = self.tracking.records[-1]
                T_map_cam = self.T_map_world @ inv_T(self._current(T_c_ref, kf))
        if T_odom_base is not None:
            # a relocalization's pose may be the far end of a jump: not a pair for the fit
            self.odometry_calibration.observe(stamp, T_map_cam @ inv_T(self.T_base_cam)
                                              if T_map_cam is not None and state == OK else None)
            if T_map_cam is None:
                T = self.odometry_calibration.coasted()
                T_map_cam_coasted = None if T is None else T @ self.T_base_cam
            odometry_errors = self.odometry_calibration.errors()
        return TrackResult(
            stamp=float(stamp), state=state,
            T_map_cam=T_map_cam, T_map_cam_coasted=T_map_cam_coasted,
            odometry_errors=odometry_errors,
            n_tracked=n_tracked, is_keyframe=bool(out["is_keyframe"]),
            keyframe_id=int(out["keyframe_id"]), corrections=corrections,
            time_ms=t_track if self.threads else t_frame + 1000.0 * (time.perf_counter() - t0),
            ref_keyframe_id=self.tracking.ref_kf.id if self.tracking.ref_kf is not None else -1,
            n_map_points=self.tracking.n_local_points,
            n_keyframes=len(self.map.good_keyframes()),
            n_loop_closures=self.map.n_loop_closures,
            n_visual_odometry=self.tracking.n_visual_odometry,
            n_odom_refused=self.tracking.n_odom_refused,
            odom_refusal=_refusal_at(self.tracking.last_odom_refusal, stamp),
            track_ms=t_track, track_cpu_ms=c_track,
            lock_wait_ms=self.tracking.lock_wait_ms, frame_ms=t_frame)

    def _collect_corrections(self):
        pending = []
        with self.map.lock:
            pending += self.local_mapping.corrections
            self.local_mapping.corrections = []
            if self.loop_closing is not None:
                pending += self.loop_closing.corrections
                self.loop_closing.corrections = []
            if not pending:
                return None
            reason = max((r for r, _ in pending), key=lambda r: _REASONS.get(r, 0))
            moved = set()
            for _, d in pending:
                moved |= set(d)
            self.correction_id += 1
            out = {}
            for k in sorted(moved):
                kf = self.map.keyframes.get(k)
                if kf is not None and not kf.bad:
                    out[k] = (kf.stamp, self.T_map_world @ inv_T(kf.T_cw))
            # culled keyframes follow their surviving ancestor (ORB-SLAM2 keeps T_cp for the
            # trajectory): depth and fusion anchored data on them when they were alive, and
            # without this those points stayed where the old pose put them (doubled walls after
            # a loop closure)
            for kf in self.map.keyframes.values():
                if not kf.bad or kf.T_cp is None or kf.id in out:
                    continue
                T, a = kf.T_cp, kf.parent
                while a is not None and a.bad and a.T_cp is not None:
                    T, a = T @ a.T_cp, a.parent
                if a is not None and a.id in out:
                    out[kf.id] = (kf.stamp, self.T_map_world @ inv_T(T @ a.T_cw))
        return (reason, self.correction_id, out)

    def keyframe_poses(self) -> Dict[int, Tuple[float, np.ndarray]]:
        """{kf_id: (stamp, T_map_kf)} of every live keyframe (FULL_MAP message)."""
        with self.map.lock:
            return {k.id: (k.stamp, self.T_map_world @ inv_T(k.T_cw))
                    for k in self.map.good_keyframes()}

    def trajectory(self, include_lost: bool = False):
        """Every tracked frame's T_map_cam, recomputed from its reference keyframe's current pose
        (so BA and loop corrections propagate, as ORB-SLAM2 SaveTrajectoryTUM) and, between two
        keyframes, from the next one's too (not in ORB-SLAM2): a frame made after keyframe a and
        before keyframe b takes the pose through a, weighted (t_b - t) / (t_b - t_a), blended with
        the pose through b as tracked then, weighted (t - t_a) / (t_b - t_a). Tracking drifts
        between keyframes (the yaw/step ambiguity of a blank wall's one poster); the corrections
        BA makes at a and at b are spread over the frames between them, as a pose graph of
        frame-to-frame edges of equal weight would spread them."""
        stamps, Ts, blend = [], [], []   # blend: (index in Ts, T_cw through b, weight of b)
        with self.map.lock:
            recs = self.tracking.records
            kfr = self.tracking.kf_records
            kf_idx = np.array([k[0] for k in kfr], np.int64)
            for i, (stamp, kf, T_c_ref, lost, T_online) in enumerate(recs):
                if lost or kf is None:
                    continue
                stamps.append(stamp)
                Ts.append(self._current(T_c_ref, kf))
                n = int(np.searchsorted(kf_idx, i, side="right"))   # kfr[n]: the next keyframe
                if TRAJECTORY_BLEND and 0 < n < len(kfr):
                    ia = kf_idx[n - 1]
                    ib, kb, ref_b, T_b_ref = kfr[n]
                    # this frame relative to keyframe b as tracked: through their common
                    # reference keyframe when they share one (BA may move it in between)
                    if ref_b is kf:
                        T_c_b = T_c_ref @ inv_T(T_b_ref)
                    else:
                        T_c_b = T_online @ inv_T(recs[ib][4])
                    w = (stamp - recs[ia][0]) / max(1e-9, recs[ib][0] - recs[ia][0])
                    blend.append((len(Ts) - 1, self._current(T_c_b, kb), float(np.clip(w, 0, 1))))
        T_wc = np.linalg.inv(np.array(Ts).reshape(-1, 4, 4))
        if blend:
            j = np.array([b[0] for b in blend])
            T_wc[j] = interpolate_poses(T_wc[j], np.linalg.inv(np.array([b[1] for b in blend])),
                                        np.array([b[2] for b in blend]))
        return Trajectory.from_matrices(stamps, np.einsum("ij,njk->nik", self.T_map_world, T_wc))

    @staticmethod
    def _current(T_c_kf: np.ndarray, kf) -> np.ndarray:
        """T_cw of a pose given relative to ``kf``, at kf's current pose (through its surviving
        ancestor when it was culled)."""
        T = T_c_kf
        while kf.bad and kf.parent is not None:
            T = T @ kf.T_cp
            kf = kf.parent
        return T @ kf.T_cw

    def set_pose_guess(self, T_map_cam: np.ndarray) -> None:
        """A pose for the next frame while LOST (rviz's 2D Pose Estimate): it is tried before
        relocalization by bag of words."""
        self.tracking.pose_guess = inv_T(inv_T(self.T_map_world) @ np.asarray(T_map_cam, float))

    @property
    def n_keyframes_created(self) -> int:
        """Keyframes this run made (keyframes of a loaded map not counted)."""
        return self._created_before_reset + self.tracking.n_keyframes_created

    def reset(self) -> None:
        """Start a new map (ORB-SLAM2 Reset after losing track right after initialisation).
        Frames of the discarded map are dropped from the trajectory. With wheel odometry the new
        map starts where the odometry carried the base (:meth:`_anchor_new_map`)."""
        self.request_reset = False
        self.reset_pending_anchor = True
        self.map_loaded = False
        self._created_before_reset += self.tracking.n_keyframes_created
        self._stop_threads()
        self._build()

    def _anchor_new_map(self) -> None:
        """Put the new map's first camera (tracking's world origin) where the corrected wheel
        odometry carried the base since the last tracked frame, so that ``map`` stays where it
        was. ORB-SLAM2 starts a reset map at its new first frame; reported in the old ``map``
        that would put the robot back at its start pose, turned by whatever it turned meanwhile
        (a reset during a turn on the spot rotated every later pose about that spot)."""
        T = self.odometry_calibration.coasted()
        if T is None:
            return
        self.T_map_world = T @ self.T_base_cam
        self.map.planar = None       # decided again on the new floor frame

    def _stop_threads(self) -> None:
        if self.threads:
            self.local_mapping.stop()
            if self.loop_closing is not None:
                self.loop_closing.stop()

    def shutdown(self) -> None:
        self._stop_threads()
        if self.frame_worker is not None:
            self.frame_worker.close()
            self.frame_worker = None

    @property
    def state(self) -> str:
        return self.tracking.state

