"""Tracking: per-frame camera pose against the map (ORB-SLAM2 Tracking, stereo).

Order per frame, as ORB-SLAM2: constant-velocity prediction + projection of the last frame's map
points (TrackWithMotionModel); if that fails, descriptor matching against the reference keyframe
(TrackReferenceKeyFrame); when LOST, relocalization (descriptor matching + PnP RANSAC against
candidate keyframes); then TrackLocalMap (points of the covisible keyframes projected into the
frame, pose-only optimization again) and the keyframe decision (NeedNewKeyFrame).

Beyond ORB-SLAM2, for low-texture rooms and sudden turns (the office sample was lost on its blank
walls): when the motion model and the reference keyframe fail, the whole local map is projected
with a wide window (track_local_map_wide), then the last frame's stereo keypoints are matched by
descriptor and PnP RANSAC gives the pose without a motion prior (track_last_frame_pnp). Frames
that needed the extractor's FAST fallback (or have few stereo keypoints) are "low texture": they
are tracked with fewer inliers (min_inliers_low_texture) and make keyframes from fewer new close
points, so the map keeps up with the few corners there are.
"""
from __future__ import annotations

import time
from typing import List, Optional

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import inv_T
from .frame import Frame, gradient_energy
from .matcher import ORBmatcher, _unique_by, rotation_consistency
from .optimizer import Optimizer, normalize_pose, project_residuals
from .orb import TH_LOW, hamming_knn2

__all__ = ["Tracking", "NOT_INITIALIZED", "OK", "LOST", "RELOCALIZED"]

# Tuned internals (ORB-SLAM2 Tracking's counterpart in brackets where there is one)
MIN_INIT_POINTS = 100          # stereo points needed to initialise (StereoInitialization: 500)
MIN_FRAMES = 0                 # frames after a keyframe before an idle LocalMapping may take one (mMinFrames: 0)
TH_REF_RATIO = 0.75            # keyframe when inliers < this x the reference keyframe's points (thRefRatio)
WEAK_REF_RATIO = 0.5           # ... even while LocalMapping is busy below this x (c1c: 0.25); live, fast
                               # turns past far walls lost track before an idle LocalMapping came
MIN_CLOSE_POINTS = 100         # a new keyframe adds far stereo points only past this many close ones
                               # (CreateNewKeyFrame: 100)
CLOSE_TRACKED_RATIO = 0.45     # also a keyframe (LocalMapping idle) when fewer than this share of the
                               # close stereo points is tracked (bNeedToInsertClose: < 100 tracked, > 70 not)
REVISIT_DISTANCE = 0.3         # m: no keyframe where a keyframe of an earlier pass (older than
REVISIT_ANGLE_DEG = 15.0       # REVISIT_MIN_AGE) sees the place from this close, within this angle
REVISIT_MIN_AGE = 5.0          # s, while the frame is tracked (not in ORB-SLAM2, whose culling
                               # keeps a revisited place bounded only where its points are re-observed)
MAX_LOCAL_KEYFRAMES = 60       # keyframes of the local map frames are tracked against (UpdateLocalKeyFrames: 80)
RESET_IF_LOST_BELOW_KFS = 3    # LOST with at most this many keyframes: the map is reset (Track: 5)
MIN_INLIERS = 30               # local-map inliers for OK (TrackLocalMap: 30)
LOW_TEXTURE_POINTS = 150       # frames needing the FAST fallback or with fewer stereo keypoints are
                               # low-texture ...
MIN_INLIERS_LOW_TEXTURE = 15   # ... and are tracked OK with this many inliers
LOST_COAST_S = 0.5             # LOST: motion-model / wide / frame-to-frame tracking from the last tracked
                               # frame goes on this long before only relocalization (0: ORB-SLAM2) ...
ODOMETRY_SIGMA_M = 0.005       # the motion prior from wheel odometry: sigma = this + REL x the motion's
ODOMETRY_SIGMA_DEG = 0.3       # translation (m) / rotation (rad), per frame gap: a wheeled base is
ODOMETRY_SIGMA_REL = 0.05      # good to a few percent (slip, wheel radius), also in turns in place
ODOMETRY_GATE_M = 0.5          # a pose (tracked, relocalized) is refused when it lands farther than
ODOMETRY_GATE_REL = 0.2        # this + REL x the distance travelled from where the odometry says the
ODOMETRY_GATE_DEG = 15.0       # robot is, or turned by more than this + DEG_PER_M x that distance
ODOMETRY_GATE_DEG_PER_M = 3.0  # (wheel odometry drifts a few percent, ~1-2 deg/m; a wrong place is m away)
ODOMETRY_GATE_CAL_M = 0.15    # the same gate about the calibrated odometry (OdometryCalibration), once
ODOMETRY_GATE_CAL_REL = 0.05   # it is applied: with its scale, rotation scale and yaw creep taken out,
ODOMETRY_GATE_CAL_DEG = 5.0    # a base's dead reckoning is good to centimetres and a degree over metres,
ODOMETRY_GATE_CAL_DEG_PER_M = 0.5  # where a relocalization on a look-alike lands decimetres off
ODOMETRY_STEP_S = 0.5          # a pose tracked this soon after the last tracked frame is refused when its
ODOMETRY_STEP_M = 0.03         # motion since differs from the odometry's by more than this + REL x the
ODOMETRY_STEP_DEG = 1.0        # odometry's translation, or this + REL x its rotation: over a frame or
ODOMETRY_STEP_REL = 0.15       # two wheels are good to millimetres and a tenth of a degree
ODOMETRY_WINDOW_S = 2.0       # planar motion: the tracked motion over about this long (s) ...
ODOMETRY_WINDOW_M = 0.10       # ... may differ from the wheel odometry's by this + REL x the odometry's
ODOMETRY_WINDOW_REL = 0.10     # path (m) and by DEG + DEG_PER_M x that path, else the frame is refused
ODOMETRY_WINDOW_DEG = 5.0      # (and coasts on the odometry): on weak texture a tracker that follows a
ODOMETRY_WINDOW_DEG_PER_M = 2.0  # wrongly mapped patch drifts smoothly, under the per-frame gate
ODOMETRY_COAST_S = 10.0        # ... and this long when the robot's odometry gives the motion (a blank
                               # wall through a turn in place: odometry drifts ~1-2 % over it)
MOTION_PRIOR_ACC = 4.0         # pose-only optimization pulled toward the constant-velocity prediction with
MOTION_PRIOR_ANG_ACC = 120.0   # sigmas acc * dt^2 (m/s^2) and ang_acc * dt^2 (deg/s^2) (0: off, ORB-SLAM2)
SHADING_MAX_SPREAD = 0.3       # inliers spanning less of the image width: the last frame's shading joins
SHADING_MAX_CLOSE = 0.2        # ... when at most this share of them is within th_depth (a far view) ...
SHADING_CELL = 32              # ... one point per cell of this many px (refine_on_one_patch) ...
SHADING_MIN_EIG = 6e-5         # ... where the structure tensor's smaller eigenvalue exceeds this ...
SHADING_WEIGHT = 4.0           # ... with this information (1/px^2) in the pose-only optimization
RELOC_MAX_MS = 60.0            # LOST: no further relocalization candidate after this (wall ms per frame)
FLOW_TRACKING = True           # optical-flow fallback when the motion model fails (blank walls)
FLOW_WINDOW = 21               # Lucas-Kanade window (px) ...
FLOW_LEVELS = 3                # ... pyramid levels above full resolution ...
FLOW_FB_PX = 1.0               # ... and forward-backward disagreement allowed (px)
FLOW_PNP_MIN_TEXTURE = 10.0    # PnP on the tracks whose patch has this x and y gradient energy ...
FLOW_PNP_MIN_TRACKS = 15       # ... when at least this many (else all tracks)
VO_MIN_INLIERS = 50            # frame-to-frame PnP inliers for a frame the map does not cover (not in
                               # ORB-SLAM2: its stereo tracker is LOST there)
WIDE_SEARCH_TH = 6.0
GUESS_KEYFRAMES = 5            # a pose guess is tried against the map points of this many nearest keyframes,
GUESS_METRES_PER_RADIAN = 1.0  # ranked by distance + this x the angle between optical axes           # local-map projection window (x4 px x scale) when both the motion model and
                               # the reference keyframe fail

NOT_INITIALIZED = "NOT_INITIALIZED"
OK = "OK"
LOST = "LOST"
RELOCALIZED = "RELOCALIZED"


def _set_pnp_pose(frame: Frame, rvec, tvec) -> None:
    """The frame takes a PnP pose (cv2 rotation vector, translation) and starts unmatched."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = np.ravel(tvec)
    frame.set_pose(T)
    frame.mp_ids[:] = -1
    frame.outlier[:] = False


def _on_keyframe(kf, T_c_ref: np.ndarray) -> np.ndarray:
    """T_cw of a pose kept relative to keyframe ``kf`` (through the parents of a culled one), so
    it follows the keyframe's corrections (BA, loops)."""
    while kf.bad and kf.parent is not None:
        T_c_ref = T_c_ref @ kf.T_cp
        kf = kf.parent
    return T_c_ref @ kf.T_cw


class Tracking:
    def __init__(self, system, cfg):
        self.system = system
        self.cfg = cfg            # TrackerConfig
        self.map = system.map
        self.extractor = system.extractor
        self.matcher = ORBmatcher(check_orientation=True)
        self.state = NOT_INITIALIZED
        self.velocity: Optional[np.ndarray] = None
        self.velocity_dt = 0.0            # stamp difference the velocity was measured over (s)
        self.reloc_tried: set = set()     # candidate keyframes tried since the last success
        self.n_reloc_tried = 0            # candidates tried by the last relocalization call
        self.last_frame: Optional[Frame] = None
        self.ref_kf = None
        self.last_kf_frame_id = -10 ** 9
        self.last_reloc_frame_id = -10 ** 9
        self.local_kfs: List = []
        self.local_kf_ids: set = set()
        self.n_matches_inliers = 0
        self.n_local_points = 0
        self.lock_wait_ms = 0.0
        # per-frame record for the trajectory: (stamp, ref kf, T_c_ref, lost, T_cw as tracked)
        self.records: List[tuple] = []
        # (index in records, keyframe, reference keyframe before it, T_c_ref to that) of every
        # keyframe made from a tracked frame
        self.kf_records: List[tuple] = []
        self.pose_guess: Optional[np.ndarray] = None   # T_cw to try on the next frame (set_pose_guess)
        self._vo = None   # (frame id, T_cw, world points, keypoints) of track_last_frame_pnp's PnP
        self.n_keyframes_created = 0                   # by this run's frames (a loaded map's not counted)
        self.n_odom_refused = 0                        # poses (tracked, relocalized) the odometry contradicted
        self.last_odom_refusal = None                  # (stamp, m, deg, m travelled, points, check) of the last
        self.n_visual_odometry = 0                     # frames the map did not cover (track_visual_odometry)
        # (stamp, ref kf, T_c_ref, T_odom_cam) of the frames tracked OK lately (planar motion)
        self.odom_window: List[tuple] = []
        self.n_odom_window_refused = 0                 # of those, by odometry_window_agrees
        self.n_odom_step_refused = 0                   # of those, by odometry_agrees' step

    # ------------------------------------------------------------------ entry
    def track(self, frame: Frame) -> dict:
        mp = self.map
        out = {"is_keyframe": False, "keyframe_id": -1}
        t0 = time.perf_counter()
        with mp.lock:
            # time spent waiting for LocalMapping/LoopClosing to release the map (GIL included)
            self.lock_wait_ms = 1000.0 * (time.perf_counter() - t0)
            if self.state == NOT_INITIALIZED:
                if self.stereo_initialization(frame):
                    self.state = OK
                    self.n_keyframes_created += 1
                    out.update(is_keyframe=True, keyframe_id=self.ref_kf.id)
                self._record(frame, self.state == OK)
                if out["is_keyframe"]:
                    self.kf_records.append((len(self.records) - 1, self.ref_kf, None, None))
                self.last_frame = frame
                return out
            self._check_ref_kf()
            relocalized = False
            coasting = self.state == LOST and self.can_coast(frame)
            ok = vo = False
            self._vo = None
            guess, self.pose_guess = self.pose_guess, None
            if guess is not None and self.state == LOST:
                ok = relocalized = self.track_from_guess(frame, guess)
                if ok:
                    ok = self.track_local_map(frame)
            frame.prior = None
            moving = self.has_motion(frame)
            if (self.state in (OK, RELOCALIZED) or coasting) and moving and \
                    frame.id > self.last_reloc_frame_id + 1:
                frame.prior = self.motion_prior(frame)
            if not ok and (self.state in (OK, RELOCALIZED) or coasting):
                if moving and frame.id > self.last_reloc_frame_id + 1:
                    ok = self.track_with_motion_model(frame)
                if not ok and FLOW_TRACKING:
                    ok = self.track_last_frame_flow(frame)
                if not ok:
                    ok = self.track_reference_keyframe(frame)
                frame.ref_kf = self.ref_kf
                if ok:
                    ok = self.track_local_map(frame)
                if not ok and moving:
                    ok = self.track_local_map_wide(frame) and self.track_local_map(frame)
                if not ok:
                    ok = self.track_last_frame_pnp(frame) and self.track_local_map(frame)
                if not ok and not self.system.localization:
                    vo = ok = self.track_visual_odometry(frame)
                    self.n_visual_odometry += int(vo)
                if ok and not self.odometry_agrees(frame):
                    # a long LOST's recovery through the wide search, the frame-to-frame PnP or the
                    # reference keyframe can lock onto a look-alike place as a relocalization can
                    ok = vo = False
                    self.n_odom_refused += 1
                elif ok and not self.odometry_window_agrees(frame):
                    ok = vo = False
                    self.n_odom_refused += 1
                    self.n_odom_window_refused += 1
            prior, frame.prior = frame.prior, None   # relocalization and the keyframe go without it
            if ok:
                self.refine_on_one_patch(frame, prior)
            if self.state == LOST and not ok and not relocalized:
                ok = self.relocalization(frame)
                if ok and not self.odometry_agrees(frame):
                    ok = False
                    self.n_odom_refused += 1
                relocalized = ok
                frame.ref_kf = self.ref_kf
                if ok:
                    ok = self.track_local_map(frame)
            if ok:
                self.state = RELOCALIZED if relocalized else OK
                if self.last_frame is not None and self.last_frame.T_cw is not None:
                    self.velocity = normalize_pose(frame.T_cw @ inv_T(self.last_frame.T_cw))
                    self.velocity_dt = frame.stamp - self.last_frame.stamp
                # drop outliers before the keyframe decision (ORB-SLAM2 end of Track)
                frame.mp_ids[frame.outlier] = -1
                frame.outlier[:] = False
                if vo or (not self.system.localization and self.need_new_keyframe(frame)):
                    kf = self.create_new_keyframe(frame, all_stereo=vo)
                    self.n_keyframes_created += 1
                    out.update(is_keyframe=True, keyframe_id=kf.id)
            else:
                self.state = LOST
                if not self.can_coast(frame):
                    self.velocity = None
                if len(mp.good_keyframes()) <= RESET_IF_LOST_BELOW_KFS and \
                        not self.system.map_loaded:   # a loaded map is never thrown away
                    self.system.request_reset = True
            self._record(frame, ok)
            self._update_odometry_window(frame)
            if out["is_keyframe"]:
                kf, ref = self.ref_kf, self.ref_kf.parent
                self.kf_records.append((len(self.records) - 1, kf, ref, None if ref is None else
                                        frame.T_cw @ inv_T(ref.T_cw)))
            if ok:
                self.last_frame = frame
        return out

    def _record(self, frame: Frame, ok: bool) -> None:
        if ok and self.ref_kf is not None:
            T_c_ref = frame.T_cw @ inv_T(self.ref_kf.T_cw)
            self.records.append((frame.stamp, self.ref_kf, T_c_ref, False, frame.T_cw.copy()))
        else:
            self.records.append((frame.stamp, None, None, True, None))

    def _check_ref_kf(self) -> None:
        while self.ref_kf is not None and self.ref_kf.bad and self.ref_kf.parent is not None:
            self.ref_kf = self.ref_kf.parent

    # ------------------------------------------------------------------ initialization
    def stereo_initialization(self, frame: Frame) -> bool:
        """First frame with enough stereo points becomes keyframe 0 at the origin."""
        stereo = np.nonzero(frame.depth > 0)[0]
        if len(stereo) < MIN_INIT_POINTS:
            return False
        frame.set_pose(np.eye(4))
        kf = self.map.new_keyframe(frame)
        self.map.add_points(frame.unproject_stereo(stereo), frame.desc[stereo], kf, stereo)
        frame.mp_ids[:] = kf.mp_ids
        self.system.local_mapping.insert_keyframe(kf)
        self.ref_kf = kf
        frame.ref_kf = kf
        self.last_kf_frame_id = frame.id
        self.local_kfs = [kf]
        return True

    # ------------------------------------------------------------------ tracking steps
    def _discard_outliers(self, frame: Frame) -> int:
        frame.mp_ids[frame.outlier] = -1
        frame.outlier[:] = False
        return int(np.count_nonzero(frame.mp_ids >= 0))

    def _update_last_frame(self) -> None:
        """Last frame's pose re-anchored on its reference keyframe (BA may have moved it)."""
        last = self.last_frame
        rec = self.records[-1] if self.records else None
        if rec is not None and rec[1] is not None and not rec[3]:
            last.set_pose(_on_keyframe(rec[1], rec[2]))

    def _update_odometry_window(self, frame: Frame) -> None:
        """Keep the frames tracked OK in a row (with wheel odometry, under planar motion) that
        :meth:`odometry_window_agrees` compares against: a relocalization or a reset starts
        anew; a LOST stretch keeps the last ones (the coasting frames are checked against them)."""
        if self.state == RELOCALIZED or self.state == NOT_INITIALIZED or \
                getattr(self.map, "planar", None) is None:
            self.odom_window = []
        if self.state != OK or frame.T_odom_cam is None or self.ref_kf is None or \
                getattr(self.map, "planar", None) is None:
            return
        rec = self.records[-1]
        self.odom_window.append((frame.stamp, rec[1], rec[2], frame.T_odom_cam))
        # the anchor: the newest entry at least ODOMETRY_WINDOW_S old; older ones go
        old = [i for i, e in enumerate(self.odom_window)
               if e[0] <= frame.stamp - float(ODOMETRY_WINDOW_S)]
        if old:
            del self.odom_window[:old[-1]]

    def odometry_window_agrees(self, frame: Frame) -> bool:
        """Under planar motion, the motion tracked since the anchor of :attr:`odom_window` (about
        ODOMETRY_WINDOW_S ago, or the first of the frames tracked since) against the wheel
        odometry's over the same time (True without them): within ODOMETRY_WINDOW_M +
        ODOMETRY_WINDOW_REL x the odometry's path in between and ODOMETRY_WINDOW_DEG +
        ODOMETRY_WINDOW_DEG_PER_M x that path. On a flat floor with the camera rigidly on the base
        the odometry is good to a few percent over seconds, while a tracker that follows a wrongly
        mapped weak-texture patch drifts smoothly, by less per frame than
        :meth:`odometry_agrees` can tell from the wheels' error. Relocalizations are not checked
        against it: the window may hold the start of a drift, which the place recognized ends."""
        if not self.odom_window or frame.T_odom_cam is None or frame.T_cw is None or \
                getattr(self.map, "planar", None) is None:
            return True
        _t, kf, T_c_ref, T_odom_a = self.odom_window[0]
        if kf is None:
            return True
        T_a = _on_keyframe(kf, T_c_ref)
        pred = inv_T(frame.T_odom_cam) @ T_odom_a @ T_a
        steps = [e[3][:3, 3] for e in self.odom_window] + [frame.T_odom_cam[:3, 3]]
        path = float(np.sum(np.linalg.norm(np.diff(np.array(steps), axis=0), axis=1)))
        D = inv_T(pred) @ frame.T_cw
        dist = float(np.linalg.norm(inv_T(frame.T_cw)[:3, 3] - inv_T(pred)[:3, 3]))
        ang = float(np.degrees(np.linalg.norm(Rotation.from_matrix(D[:3, :3]).as_rotvec())))
        agrees = dist <= float(ODOMETRY_WINDOW_M) + float(ODOMETRY_WINDOW_REL) * path and \
            ang <= float(ODOMETRY_WINDOW_DEG) + float(ODOMETRY_WINDOW_DEG_PER_M) * path
        if not agrees:
            self.last_odom_refusal = (frame.stamp, dist, ang, path,
                                      int(np.count_nonzero(frame.mp_ids >= 0)), "window")
        return agrees

    def odometry_motion(self, frame: Frame) -> Optional[np.ndarray]:
        """The motion (T_cw(frame) T_cw(last frame)^-1) the robot's odometry measured between
        the last tracked frame and ``frame``, or None when either lacks ``T_odom_cam``. Wheel
        odometry is good to a few percent over a frame gap, also in the turns in place and over
        the gaps (LOST, frames dropped while busy) where a constant velocity is wrong (as
        ORB-SLAM2 ports for wheeled robots and RTAB-Map's odometry guess use it)."""
        last = self.last_frame
        if last is None or last.T_odom_cam is None or frame.T_odom_cam is None:
            return None
        return normalize_pose(inv_T(frame.T_odom_cam) @ last.T_odom_cam)

    def odometry_agrees(self, frame: Frame, record: bool = True) -> bool:
        """A tracked or relocalized pose within reach of the robot's odometry since the last
        tracked frame (True without odometry): within ODOMETRY_GATE_M + ODOMETRY_GATE_REL x the
        distance travelled, and ODOMETRY_GATE_DEG + ODOMETRY_GATE_DEG_PER_M x that distance. A
        room's repeated furniture and posters can match a wrong keyframe well enough for PnP; a
        wheeled base cannot have jumped there. Once the odometry is calibrated the gate is
        centred on the calibrated odometry (:meth:`calibrated_odometry_motion`) with the
        ODOMETRY_GATE_CAL_* bounds: a relocalization after a blank wall that lands half a
        metre from where the corrected wheels put the base is a look-alike, not the wheels'
        error.

        A pose within ODOMETRY_STEP_S of the last tracked frame is held to the odometry's step
        too: ODOMETRY_STEP_M + ODOMETRY_STEP_REL x its translation and ODOMETRY_STEP_DEG +
        ODOMETRY_STEP_REL x its rotation. On weak texture the local map's few points can pull
        one frame's pose degrees off (a wrong patch, one poster's yaw against a lateral shift),
        and the map built on from there keeps the error; the wheels over a frame or two are not
        that wrong. A relocalization later than that may end a drift, and is not held to it.
        ``record`` False: the refusal counters and :attr:`last_odom_refusal` are left alone."""
        odo = self.odometry_motion(frame)
        if odo is None or frame.T_cw is None:
            return True
        self._update_last_frame()
        cal = self.calibrated_odometry_motion(frame)
        if cal is not None:
            centre = cal
            g_m, g_rel, g_deg, g_deg_m = (ODOMETRY_GATE_CAL_M, ODOMETRY_GATE_CAL_REL,
                                          ODOMETRY_GATE_CAL_DEG, ODOMETRY_GATE_CAL_DEG_PER_M)
        else:
            centre = odo
            g_m, g_rel, g_deg, g_deg_m = (ODOMETRY_GATE_M, ODOMETRY_GATE_REL, ODOMETRY_GATE_DEG,
                                          ODOMETRY_GATE_DEG_PER_M)
        pred = centre @ self.last_frame.T_cw
        travel = float(np.linalg.norm(centre[:3, 3]))
        D = inv_T(pred) @ frame.T_cw
        dist = float(np.linalg.norm(inv_T(frame.T_cw)[:3, 3] - inv_T(pred)[:3, 3]))
        ang = float(np.degrees(np.linalg.norm(Rotation.from_matrix(D[:3, :3]).as_rotvec())))
        agrees = dist <= g_m + g_rel * travel and ang <= g_deg + g_deg_m * travel
        check = "calibrated odometry" if cal is not None else "odometry"
        if agrees and frame.stamp - self.last_frame.stamp <= float(ODOMETRY_STEP_S):
            turn = float(np.degrees(np.linalg.norm(Rotation.from_matrix(odo[:3, :3]).as_rotvec())))
            agrees = dist <= ODOMETRY_STEP_M + ODOMETRY_STEP_REL * travel and \
                ang <= ODOMETRY_STEP_DEG + ODOMETRY_STEP_REL * turn
            self.n_odom_step_refused += int(not agrees and record)
            check = "step"
        if not agrees and record:
            self.last_odom_refusal = (frame.stamp, dist, ang, travel,
                                      int(np.count_nonzero(frame.mp_ids >= 0)), check)
        return agrees

    def calibrated_odometry_motion(self, frame: Frame) -> Optional[np.ndarray]:
        """As :meth:`odometry_motion`, on the calibrated odometry (``T_odom_cam_calibrated``),
        once the system's :class:`OdometryCalibration` applies its fit; None before, or when
        either frame lacks it."""
        calib = getattr(self.system, "odometry_calibration", None)
        last = self.last_frame
        if calib is None or not calib.calibrated or last is None:
            return None
        a = getattr(last, "T_odom_cam_calibrated", None)
        b = getattr(frame, "T_odom_cam_calibrated", None)
        if a is None or b is None:
            return None
        return normalize_pose(inv_T(b) @ a)

    def has_motion(self, frame: Frame) -> bool:
        """A motion to predict ``frame``'s pose from the last frame's: odometry or velocity."""
        return self.velocity is not None or self.odometry_motion(frame) is not None

    def predicted_velocity(self, frame: Frame) -> np.ndarray:
        """The motion from the last frame to ``frame``: the robot's odometry when it has it
        (:meth:`odometry_motion`), else the constant-velocity model: the last measured
        velocity scaled to the real stamp difference (frames dropped while the node was busy, or
        an irregular stream); unchanged when the gap is within 5 % of the measured one."""
        odo = self.odometry_motion(frame)
        if odo is not None:
            return odo
        V = self.velocity
        dt = frame.stamp - self.last_frame.stamp
        if self.velocity_dt <= 0 or not dt > 0:
            return V
        r = dt / self.velocity_dt
        if abs(r - 1.0) <= 0.05:
            return V
        r = min(r, 10.0)   # a long gap: extrapolating further only misleads the search
        out = np.eye(4)
        out[:3, :3] = Rotation.from_rotvec(r * Rotation.from_matrix(V[:3, :3]).as_rotvec()).as_matrix()
        out[:3, 3] = r * V[:3, 3]
        return out

    def motion_prior(self, frame: Frame):
        """(T_pred, information of [rho, phi]) for Optimizer.pose_optimization, or None when off:
        the constant-velocity prediction, with the deviation an unmodelled acceleration makes
        over the frame gap dt as sigmas: ``motion_prior_acc`` (m/s^2) * dt^2 and
        ``motion_prior_ang_acc`` (deg/s^2) * dt^2 (at 20 Hz the defaults 4 m/s^2 and
        120 deg/s^2 give 1 cm and 0.3 deg; skipped frames loosen it quadratically). A ground
        robot's or a walking person's accelerations are around these, so the prior is weak next
        to a few hundred well-spread features, and decides only what the images leave open
        (features on one small patch: lateral translation vs yaw)."""
        acc, ang = float(MOTION_PRIOR_ACC), float(MOTION_PRIOR_ANG_ACC)
        last = self.last_frame
        if acc <= 0 or ang <= 0 or last is None or last.T_cw is None:
            return None
        dt = frame.stamp - last.stamp
        if not dt > 0:
            dt = self.velocity_dt if self.velocity_dt > 0 else 0.05
        self._update_last_frame()
        st, sr = acc * dt * dt, np.radians(ang) * dt * dt
        odo = self.odometry_motion(frame)
        if odo is not None:   # wheel odometry: its error grows with the motion, not with time
            st = ODOMETRY_SIGMA_M + ODOMETRY_SIGMA_REL * float(np.linalg.norm(odo[:3, 3]))
            sr = np.radians(ODOMETRY_SIGMA_DEG) + ODOMETRY_SIGMA_REL * float(
                np.linalg.norm(Rotation.from_matrix(odo[:3, :3]).as_rotvec()))
        info = np.array([1.0 / st ** 2] * 3 + [1.0 / sr ** 2] * 3)
        return normalize_pose(self.predicted_velocity(frame) @ last.T_cw), info

    def can_coast(self, frame: Frame) -> bool:
        """LOST for at most ``lost_coast_s`` since the last tracked frame (not in ORB-SLAM2): the
        next frames still try the motion model, the wide local-map search and the frame-to-frame
        PnP from that frame before relocalization. A frame or two lost in a fast low-texture turn
        (a live node that had to skip frames) is then recovered where relocalization, which needs
        an already mapped view, cannot."""
        last = self.last_frame
        if last is None or last.T_cw is None or not frame.stamp > last.stamp:
            return False
        if self.odometry_motion(frame) is not None:
            return frame.stamp - last.stamp <= float(ODOMETRY_COAST_S)
        return self.velocity is not None and frame.stamp - last.stamp <= float(LOST_COAST_S)

    def low_texture(self, frame: Frame) -> bool:
        """Few stereo keypoints (blank walls): thresholds written for 1000+ features relax."""
        if getattr(frame, "n_primary", self.cfg.n_features) < self.cfg.n_features:
            return True   # the FAST fallback was needed (ORBextractor.n_primary)
        return int(np.count_nonzero(frame.depth > 0)) < LOW_TEXTURE_POINTS

    def track_with_motion_model(self, frame: Frame) -> bool:
        self._update_last_frame()
        frame.set_pose(self.predicted_velocity(frame) @ self.last_frame.T_cw)
        frame.mp_ids[:] = -1
        min_n = 10 if self.low_texture(frame) else 20
        n = self.matcher.search_by_projection_last(frame, self.last_frame, self.map, th=7.0)
        if n < min_n:
            frame.mp_ids[:] = -1
            n = self.matcher.search_by_projection_last(frame, self.last_frame, self.map, th=14.0)
        if n < min_n:
            return False
        Optimizer.pose_optimization(frame, self.map)
        return self._discard_outliers(frame) >= 10

    def track_local_map_wide(self, frame: Frame) -> bool:
        """Last resort before LOST (not in ORB-SLAM2): every local-map point projected with the
        motion-model pose and a wide window (sudden turns, few features: the last frame alone
        holds too few points)."""
        self._update_last_frame()
        frame.set_pose(self.predicted_velocity(frame) @ self.last_frame.T_cw)
        frame.mp_ids[:] = -1
        frame.outlier[:] = False
        pts = [k.valid_mp_ids(self.map.mp_bad) for k in [self.ref_kf] + self.local_kfs
               if k is not None and not k.bad]
        if not pts:
            return False
        pts = np.unique(np.concatenate(pts))
        n, _ = self.matcher.search_local_points(frame, self.map, pts, th=WIDE_SEARCH_TH)
        if n < 10:
            return False
        Optimizer.pose_optimization(frame, self.map)
        return self._discard_outliers(frame) >= 10

    def track_from_guess(self, frame: Frame, T_cw: np.ndarray) -> bool:
        """LOST with a pose from outside (rviz's 2D Pose Estimate on /initialpose): the points of
        the keyframes nearest to it projected with a wide window, then pose-only optimization."""
        kfs = self.map.good_keyframes()
        if not kfs:
            return False
        C = inv_T(T_cw)[:3, 3]
        z = inv_T(T_cw)[:3, 2]
        near = sorted(kfs, key=lambda k: np.linalg.norm(k.T_wc[:3, 3] - C) +
                      GUESS_METRES_PER_RADIAN * np.arccos(np.clip(k.T_wc[:3, 2] @ z, -1.0, 1.0)))
        self.ref_kf = near[0]
        self.local_kfs = near[1:GUESS_KEYFRAMES]
        frame.set_pose(T_cw)
        frame.mp_ids[:] = -1
        frame.outlier[:] = False
        pts = np.unique(np.concatenate([k.valid_mp_ids(self.map.mp_bad) for k in near[:GUESS_KEYFRAMES]]))
        n, _ = self.matcher.search_local_points(frame, self.map, pts, th=WIDE_SEARCH_TH)
        if n < MIN_INLIERS:
            return False
        Optimizer.pose_optimization(frame, self.map)
        if self._discard_outliers(frame) < MIN_INLIERS:
            return False
        self.last_reloc_frame_id = frame.id
        frame.ref_kf = self.ref_kf
        return True

    def track_last_frame_pnp(self, frame: Frame) -> bool:
        """Frame-to-frame fallback (not in ORB-SLAM2): descriptors of every stereo keypoint of the
        last frame, mapped or not, matched against the frame, PnP RANSAC on their 3-D points,
        then the local map projected with that pose. Needs no motion prior, so it carries sudden
        turns (pure rotation starts) and low-texture views where few keypoints are map points."""
        last = self.last_frame
        if last is None or last.T_cw is None:
            return False
        self._update_last_frame()
        st = np.nonzero(last.depth > 0)[0]
        if len(st) < 10 or frame.N < 10:
            return False
        d12, b12 = hamming_knn2(last.desc[st], frame.desc)
        b, d1, d2 = b12[:, 0], d12[:, 0], d12[:, 1]
        ok = (d1 <= TH_LOW) & (d1 < 0.8 * d2)
        ia, jb = np.nonzero(ok)[0], b[ok]
        u_ = _unique_by(jb, d1[ok])
        ia, jb = ia[u_], jb[u_]
        if len(ia) >= 10:
            keep = rotation_consistency(last.angle[st[ia]], frame.angle[jb])
            ia, jb = ia[keep], jb[keep]
        if len(ia) < 10:
            return False
        Pw = last.unproject_stereo(st[ia])
        K = np.array([[frame.fx, 0, frame.cx], [0, frame.fy, frame.cy], [0, 0, 1.0]])
        okp, rvec, tvec, inl = cv2.solvePnPRansac(
            Pw.astype(np.float64), frame.uv[jb].astype(np.float64), K, None,
            iterationsCount=200, reprojectionError=3.0, confidence=0.99, flags=cv2.SOLVEPNP_EPNP)
        if not okp or inl is None or len(inl) < 10:
            return False
        _set_pnp_pose(frame, rvec, tvec)
        inl = inl.ravel()
        self._vo = (frame.id, frame.T_cw.copy(), Pw[inl], jb[inl])
        mp_of = last.mp_ids[st[ia[inl]]]
        good = (mp_of >= 0) & ~self.map.mp_bad[np.maximum(mp_of, 0)]
        frame.mp_ids[jb[inl][good]] = mp_of[good]
        pts = [k.valid_mp_ids(self.map.mp_bad) for k in [self.ref_kf] + self.local_kfs
               if k is not None and not k.bad]
        if pts:
            pts = np.unique(np.concatenate(pts))
            pts = pts[~np.isin(pts, frame.mp_ids)]
            self.matcher.search_local_points(frame, self.map, pts, th=3.0)
        if np.count_nonzero(frame.mp_ids >= 0) < 10:
            return False
        Optimizer.pose_optimization(frame, self.map)
        return self._discard_outliers(frame) >= 10

    def track_visual_odometry(self, frame: Frame) -> bool:
        """The map does not cover the view (not in ORB-SLAM2): a fast turn past far walls while
        LocalMapping lags, so the keyframes' few close points have left the view and their far
        ones are not triangulated yet. The frame-to-frame PnP of :meth:`track_last_frame_pnp`
        (the last frame's stereo points, far ones too) is kept when ``VO_MIN_INLIERS`` support it,
        refined together with the local-map points found around that pose, and the frame then
        becomes a keyframe mapping all its stereo points, as StereoInitialization does, so the
        next frame has a map again (ORB-SLAM2's localization mode tracks such frames by
        visual odometry too, but makes no keyframe)."""
        vo, self._vo = self._vo, None
        if vo is None or vo[0] != frame.id or len(vo[3]) < VO_MIN_INLIERS:
            return False
        _, T0, Pw, jb = vo
        # the wheels' motion and the floor's plane constrain this path as every other one: it
        # runs where texture is weakest
        prior, planar = getattr(frame, "prior", None), getattr(self.map, "planar", None)
        T, outlier, n = Optimizer.pose_from_points(frame, T0, frame.uv[jb], frame.ur[jb],
                                                   frame.octave[jb], frame.inv_level_sigma2, Pw,
                                                   prior=prior, planar=planar)
        if n < VO_MIN_INLIERS:
            return False
        frame.set_pose(T)
        frame.mp_ids[:] = -1
        frame.outlier[:] = False
        pts = [k.valid_mp_ids(self.map.mp_bad) for k in [self.ref_kf] + self.local_kfs
               if k is not None and not k.bad]
        if pts:
            self.matcher.search_local_points(frame, self.map, np.unique(np.concatenate(pts)), th=3.0)
        idx = np.nonzero(frame.mp_ids >= 0)[0]
        if len(idx):
            # the map points join the frame-to-frame ones; those that disagree are outliers
            ids = frame.mp_ids[idx]
            ok_jb = ~outlier
            uv = np.concatenate([frame.uv[idx], frame.uv[jb[ok_jb]]])
            ur = np.concatenate([frame.ur[idx], frame.ur[jb[ok_jb]]])
            octv = np.concatenate([frame.octave[idx], frame.octave[jb[ok_jb]]])
            P = np.concatenate([self.map.mp_pos[ids], Pw[ok_jb]])
            bad = np.concatenate([self.map.mp_bad[ids], np.zeros(int(ok_jb.sum()), bool)])
            T, out2, n = Optimizer.pose_from_points(frame, T, uv, ur, octv, frame.inv_level_sigma2,
                                                    P, bad=bad, prior=prior, planar=planar)
            if n < VO_MIN_INLIERS:
                return False
            frame.set_pose(T)
            frame.outlier[idx] = out2[:len(idx)]
        self.n_matches_inliers = int(np.count_nonzero((frame.mp_ids >= 0) & ~frame.outlier))
        return True

    def _lk(self):
        win = int(FLOW_WINDOW)
        return dict(winSize=(win, win), maxLevel=int(FLOW_LEVELS),
                    criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))

    def _flow(self, img0, img1, p0, p1):
        """Pyramidal Lucas-Kanade from ``p0`` in img0 to img1 started at ``p1``, checked back
        (forward-backward disagreement <= flow_fb_px): (tracked positions, ok mask)."""
        lk = self._lk()
        p0 = np.ascontiguousarray(p0, np.float32).reshape(-1, 1, 2)
        if not len(p0):   # OpenCV refuses an empty point array
            return np.zeros((0, 2), np.float32), np.zeros(0, bool)
        q, st, _ = cv2.calcOpticalFlowPyrLK(img0, img1, p0, np.ascontiguousarray(
            p1, np.float32).reshape(-1, 1, 2), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        b, st2, _ = cv2.calcOpticalFlowPyrLK(img1, img0, q, p0.copy(),
                                             flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        q, b = q.reshape(-1, 2), b.reshape(-1, 2)
        ok = ((st.ravel() == 1) & (st2.ravel() == 1) &
              (np.linalg.norm(b - p0.reshape(-1, 2), axis=1) <= float(FLOW_FB_PX)))
        return q, ok

    def _flow_from_last(self, frame: Frame, sel: np.ndarray, T_pred: np.ndarray):
        """The last frame's keypoints ``sel`` (map points) followed into ``frame``, started at
        their projection with ``T_pred``: (sel, map point ids, world points, positions)."""
        last = self.last_frame
        ids = last.mp_ids[sel]
        Pw = self.map.mp_pos[ids]
        Pc = Pw @ T_pred[:3, :3].T + T_pred[:3, 3]
        p0 = last.uv[sel].astype(np.float32)
        p1 = p0.copy()
        front = Pc[:, 2] > 0.05
        p1[front, 0] = frame.fx * Pc[front, 0] / Pc[front, 2] + frame.cx
        p1[front, 1] = frame.fy * Pc[front, 1] / Pc[front, 2] + frame.cy
        w, h = frame.width, frame.height
        inside = (p1[:, 0] >= 0) & (p1[:, 0] < w) & (p1[:, 1] >= 0) & (p1[:, 1] < h)
        p1[~inside] = p0[~inside]
        p1, good = self._flow(last.image, frame.image, p0, p1)
        edge = 20.0
        good &= (p1[:, 0] >= edge) & (p1[:, 0] < w - edge) & (p1[:, 1] >= edge) & (p1[:, 1] < h - edge)
        return sel[good], ids[good], Pw[good], p1[good]

    def _append_tracks(self, frame: Frame, sel, ids, Pw, p1) -> int:
        """Flow tracks (of the last frame's keypoints ``sel``) become keypoints of ``frame``
        observing map points ``ids``: ORB descriptor computed there at the last keypoint's octave
        and angle (cv2.ORB.compute keeps a given angle and drops keypoints at the border), stereo
        by a left-right flow started at the disparity the map point predicts with the frame's
        pose (kept when on the row, consistent both ways and near that prediction)."""
        last = self.last_frame
        octv = last.octave[sel]
        sc = frame.scale[octv]
        off = 0.5 * (sc - 1.0)   # ORBextractor's level-pixel-centre offset, undone
        kps = [cv2.KeyPoint(float(x), float(y), float(31.0 * c), float(a), 0.0, int(o), int(k))
               for k, (x, y, c, a, o) in enumerate(zip(p1[:, 0] - off, p1[:, 1] - off, sc,
                                                       last.angle[sel], octv))]
        if not kps:
            return 0
        kps, desc = self.extractor.orb.compute(frame.image, kps)
        if desc is None or not kps:
            return 0
        k = np.array([kp.class_id for kp in kps], dtype=np.int64)
        sel, ids, Pw, p1 = sel[k], ids[k], Pw[k], p1[k]
        T = frame.T_cw
        z = np.maximum(Pw @ T[2, :3] + T[2, 3], 1e-3)
        d_pred = frame.bf / z
        ur = -np.ones(len(sel), np.float32)
        depth = -np.ones(len(sel), np.float32)
        right = frame.right_image
        if right is not None:
            q0 = p1.astype(np.float32)
            q1 = q0.copy()
            q1[:, 0] -= (d_pred + frame.doffs).astype(np.float32)
            q1, okr = self._flow(frame.image, right, q0, q1)
            disp = q0[:, 0] - q1[:, 0] - np.float32(frame.doffs)   # StereoCamera.doffs
            okr &= ((np.abs(q1[:, 1] - q0[:, 1]) <= 1.0) & (disp > 0.5) & (disp < frame.fx) &
                    (np.abs(disp - d_pred) <= np.maximum(2.0, 0.25 * d_pred)))
            ur[okr] = q0[okr, 0] - disp[okr]
            depth[okr] = frame.bf / disp[okr]
        new = frame.append_keypoints(p1, octv[k], last.angle[sel], desc, ur, depth)
        frame.mp_ids[new] = ids
        return len(new)

    def track_last_frame_flow(self, frame: Frame) -> bool:
        """Optical-flow fallback (not in ORB-SLAM2; KLT front ends such as VINS-Fusion's): the last
        frame's map-point keypoints are followed into the frame by pyramidal Lucas-Kanade
        (started at the motion-model projection, forward-backward checked), PnP RANSAC on the
        map points gives the pose, and the tracks become keypoints of the frame observing those
        map points. On blank walls the few corners found are sensor noise that does not repeat,
        so descriptor matching finds almost nothing from one frame to the next, while the patches
        around them (the faint texture) are still followed by the flow: tracks then outlive the
        corners, and the map points keep being observed instead of being replaced every frame."""
        last = self.last_frame
        if last is None or last.T_cw is None:
            return False
        self._update_last_frame()
        sel = np.nonzero(last.mp_ids >= 0)[0]
        sel = sel[~self.map.mp_bad[last.mp_ids[sel]]]
        if len(sel) < 10:
            return False
        T_pred = (self.predicted_velocity(frame) if self.has_motion(frame) else np.eye(4)) @ \
            last.T_cw
        sel, ids, Pw, p1 = self._flow_from_last(frame, sel, T_pred)
        if len(sel) < 10:
            return False
        K = np.array([[frame.fx, 0, frame.cx], [0, frame.fy, frame.cy], [0, 0, 1.0]])
        # the pose from the tracks whose patch pins both axes when there are enough of them: on
        # an edge or a blank wall's noise LK only returns its start along the edge (the aperture
        # problem), and the stereo depth there is noise too (office loop seed 10's first frames:
        # 90 % of the tracks on the specular band's flanks, a 2 cm step taken as a 0.4 deg turn)
        fit = np.arange(len(sel))
        th = float(FLOW_PNP_MIN_TEXTURE)
        if th > 0:
            well = np.nonzero(np.min(gradient_energy(last.image, last.uv[sel]), axis=1) >= th)[0]
            if len(well) >= int(FLOW_PNP_MIN_TRACKS):
                fit = well
        okp, rvec, tvec, inl = cv2.solvePnPRansac(
            Pw[fit].astype(np.float64), p1[fit].astype(np.float64), K, None,
            rvec=cv2.Rodrigues(T_pred[:3, :3])[0], tvec=T_pred[:3, 3].reshape(3, 1).copy(),
            useExtrinsicGuess=True, iterationsCount=100, reprojectionError=2.0, confidence=0.99,
            flags=cv2.SOLVEPNP_ITERATIVE)
        if not okp or inl is None or len(inl) < 10:
            return False
        _set_pnp_pose(frame, rvec, tvec)
        if len(fit) < len(sel):   # every track within 2 px of that pose
            e, Pc = project_residuals(frame.T_cw, Pw, np.column_stack([p1, np.zeros(len(p1))]),
                                      np.zeros(len(p1), bool), frame.fx, frame.fy, frame.cx,
                                      frame.cy, frame.bf)
            inl = np.nonzero((Pc[:, 2] > 0) & (np.hypot(e[:, 0], e[:, 1]) <= 2.0))[0]
        else:
            inl = inl.ravel()
        if self._append_tracks(frame, sel[inl], ids[inl], Pw[inl], p1[inl]) < 10:
            return False
        Optimizer.pose_optimization(frame, self.map)
        return self._discard_outliers(frame) >= 10

    def shading_points(self):
        """Points of the last frame's faint texture spread over the whole view, for
        :meth:`refine_on_one_patch`: per ``shading_cell`` grid cell the pixel with the largest
        minimum eigenvalue of the half-resolution structure tensor (cv2.cornerMinEigenVal: the
        soft shading of a blank wall, where FAST finds nothing), kept above ``shading_min_eig``;
        their depth from a Lucas-Kanade flow into the right image, started at the disparity of
        the frame's median stereo keypoint (kept on the row, consistent both ways). Returns
        (world points (M, 3), their left-image positions (M, 2)) or None."""
        last = self.last_frame
        img, right = last.image, last.right_image
        if img is None or right is None:
            return None
        c = int(SHADING_CELL)
        half = cv2.pyrDown(img)
        eig = cv2.cornerMinEigenVal(half, blockSize=7, ksize=3)
        ch = max(2, c // 2)
        h, w = eig.shape
        gh, gw = h // ch, w // ch
        cells = eig[:gh * ch, :gw * ch].reshape(gh, ch, gw, ch).transpose(0, 2, 1, 3).reshape(
            gh, gw, ch * ch)
        k = np.argmax(cells, axis=2)
        best = np.take_along_axis(cells, k[..., None], axis=2)[..., 0]
        gy, gx = np.mgrid[0:gh, 0:gw]
        v = gy * ch + k // ch
        u = gx * ch + k % ch
        ok = best > float(SHADING_MIN_EIG)
        p0 = (np.column_stack([u[ok], v[ok]]).astype(np.float32) * 2.0 + 0.5)
        edge = 24.0
        p0 = p0[(p0[:, 0] >= edge) & (p0[:, 0] < last.width - edge) &
                (p0[:, 1] >= edge) & (p0[:, 1] < last.height - edge)]
        st = last.depth > 0
        if len(p0) < 10 or not np.any(st):
            return None
        d0 = float(last.bf / np.median(last.depth[st]))
        q1 = p0.copy()
        q1[:, 0] -= np.float32(d0 + last.doffs)
        q1, okr = self._flow(img, right, p0, q1)
        disp = p0[:, 0] - q1[:, 0] - np.float32(last.doffs)
        okr &= (np.abs(q1[:, 1] - p0[:, 1]) <= 1.0) & (disp > 0.5) & (disp < last.fx)
        p0, disp = p0[okr], disp[okr].astype(np.float64)
        if len(p0) < 10:
            return None
        z = last.bf / disp
        Xc = np.column_stack([(p0[:, 0] - last.cx) * z / last.fx,
                              (p0[:, 1] - last.cy) * z / last.fy, z])
        T_wc = inv_T(last.T_cw)
        return Xc @ T_wc[:3, :3].T + T_wc[:3, 3], p0

    def refine_on_one_patch(self, frame: Frame, prior=None) -> int:
        """Features on one small patch (not in ORB-SLAM2): when the frame's inliers span less
        than ``shading_max_spread`` of the image width (a blank wall with one poster: simulated
        garage, all 1500 ORB features on a 120 px patch 5-6 m away), a yaw and a sideways step
        move them alike and the pose drifts along that direction by tenths of a degree per
        frame. The wall's faint shading, everywhere else in the view, tells them apart (a yaw
        moves the image edges more than the centre, a step does not): :meth:`shading_points`
        of the last frame are followed into this one by Lucas-Kanade and join the pose-only
        optimization as monocular observations (points placed by the last frame's pose and
        their stereo depth), with the map points as before. Returns the shading points used."""
        if float(SHADING_MAX_SPREAD) <= 0:
            return 0
        last = self.last_frame
        if last is None or last.T_cw is None or frame.T_cw is None:
            return 0
        inl = np.nonzero((frame.mp_ids >= 0) & ~frame.outlier)[0]
        if len(inl) < 10:
            return 0
        u = frame.uv[inl, 0]
        if np.percentile(u, 95) - np.percentile(u, 5) >= float(
                SHADING_MAX_SPREAD) * frame.width:
            return 0
        close = (frame.depth[inl] > 0) & (frame.depth[inl] < frame.th_depth)
        if np.count_nonzero(close) > float(SHADING_MAX_CLOSE) * len(inl):
            return 0   # near points: stereo depth and parallax already separate the two
        got = self.shading_points()
        if got is None:
            return 0
        Pw, p0 = got
        T = frame.T_cw
        Pc = Pw @ T[:3, :3].T + T[:3, 3]
        front = Pc[:, 2] > 0.1
        Pw, p0, Pc = Pw[front], p0[front], Pc[front]
        p1 = np.column_stack([frame.fx * Pc[:, 0] / Pc[:, 2] + frame.cx,
                              frame.fy * Pc[:, 1] / Pc[:, 2] + frame.cy]).astype(np.float32)
        p1, good = self._flow(last.image, frame.image, p0, p1)
        good &= (p1[:, 0] >= 0) & (p1[:, 0] < frame.width) & (p1[:, 1] >= 0) & \
            (p1[:, 1] < frame.height)
        Pw, p1 = Pw[good], p1[good]
        if len(Pw) < 10:
            return 0
        idx = np.nonzero(frame.mp_ids >= 0)[0]
        n, m = len(idx), len(Pw)
        ids = frame.mp_ids[idx]
        # the shading points get a level of their own, weighted by shading_weight (1 px sigma at 1)
        lv = len(frame.inv_level_sigma2)
        T_cw, outlier, n_inl = Optimizer.pose_from_points(
            frame, frame.T_cw,
            np.concatenate([frame.uv[idx], p1.astype(frame.uv.dtype)]),
            np.concatenate([frame.ur[idx], -np.ones(m, frame.ur.dtype)]),
            np.concatenate([frame.octave[idx], np.full(m, lv, frame.octave.dtype)]),
            np.append(frame.inv_level_sigma2, float(SHADING_WEIGHT)),
            np.concatenate([self.map.mp_pos[ids], Pw]),
            bad=np.concatenate([self.map.mp_bad[ids], np.zeros(m, bool)]), prior=prior,
            planar=getattr(self.map, "planar", None))
        if n_inl < 10:
            return 0
        before = frame.T_cw
        frame.set_pose(T_cw)
        if not self.odometry_agrees(frame, record=False):
            frame.set_pose(before)   # the shading pulled the pose off the wheels' step: not kept
            return 0
        frame.outlier[idx] = outlier[:n]
        return m

    def track_reference_keyframe(self, frame: Frame) -> bool:
        frame.mp_ids[:] = -1
        kp, ids = self.matcher.search_by_descriptors(self.ref_kf, frame, self.map)
        if len(kp) < 15:
            return False
        frame.mp_ids[kp] = ids
        frame.set_pose(self.last_frame.T_cw)
        Optimizer.pose_optimization(frame, self.map)
        return self._discard_outliers(frame) >= 10

    def relocalization(self, frame: Frame) -> bool:
        """Candidate keyframes (BoW database when a vocabulary is loaded, else the most recent),
        descriptor matches, PnP RANSAC (cv2.solvePnPRansac), pose-only optimization, and a guided
        projection search of the candidate's covisible points (ORB-SLAM2 Relocalization)."""
        t0 = time.perf_counter()
        budget = float(RELOC_MAX_MS) / 1000.0
        cands = self.system.relocalization_candidates(frame)
        # bounded per frame: candidates not tried by the last LOST frames go first, and after
        # the first candidate no new one starts once reloc_max_ms (wall) is spent; the next
        # LOST frame goes on with the rest
        if cands and all(k.id in self.reloc_tried for k in cands):
            self.reloc_tried.clear()
        cands = sorted(cands, key=lambda k: k.id in self.reloc_tried)
        K = np.array([[frame.fx, 0, frame.cx], [0, frame.fy, frame.cy], [0, 0, 1.0]])
        self.n_reloc_tried = 0
        for kf in cands:
            if self.n_reloc_tried and time.perf_counter() - t0 > budget:
                break
            self.n_reloc_tried += 1
            self.reloc_tried.add(kf.id)
            frame.mp_ids[:] = -1
            kp, ids = self.matcher.search_by_descriptors(kf, frame, self.map, ratio=0.75)
            if len(kp) < 15:
                continue
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                self.map.mp_pos[ids].astype(np.float64), frame.uv[kp].astype(np.float64), K, None,
                iterationsCount=300, reprojectionError=2.0 * 2.0, confidence=0.99,
                flags=cv2.SOLVEPNP_EPNP)
            if not ok or inl is None or len(inl) < 10:
                continue
            T = np.eye(4)
            T[:3, :3] = cv2.Rodrigues(rvec)[0]
            T[:3, 3] = tvec.ravel()
            inl = inl.ravel()
            frame.set_pose(T)
            frame.mp_ids[kp[inl]] = ids[inl]
            n = Optimizer.pose_optimization(frame, self.map)
            if n < 10:
                continue
            self._discard_outliers(frame)
            if n < 50:   # guided search in the candidate's neighbourhood, as ORB-SLAM2
                local = [kf] + self.map.best_covisibles(kf, 10)
                pts = np.unique(np.concatenate([k.valid_mp_ids(self.map.mp_bad) for k in local]))
                pts = pts[~np.isin(pts, frame.mp_ids)]
                self.matcher.search_local_points(frame, self.map, pts, th=10.0 / 4.0)
                n = Optimizer.pose_optimization(frame, self.map)
                self._discard_outliers(frame)
            if n >= 50:
                self.last_reloc_frame_id = frame.id
                self.ref_kf = kf
                self.reloc_tried.clear()
                return True
        frame.mp_ids[:] = -1
        return False

    # ------------------------------------------------------------------ local map
    def update_local_keyframes(self, frame: Frame) -> None:
        """K1: keyframes sharing points with the frame; K2: their best covisibles (ORB-SLAM2
        UpdateLocalKeyFrames); the one sharing most points becomes the reference keyframe."""
        ids = frame.mp_ids[frame.mp_ids >= 0]
        ids = ids[~self.map.mp_bad[ids]]
        cand = {}
        for kf in [self.ref_kf] + self.local_kfs:
            if kf is not None and not kf.bad:
                cand[kf.id] = kf
        for kf in list(cand.values()):
            for kid in getattr(kf, "connections", {}):
                k = self.map.keyframes.get(kid)
                if k is not None and not k.bad:
                    cand[kid] = k
        counts = {}
        if len(ids):
            mark = np.zeros(self.map.n, dtype=bool)
            mark[ids] = True
            for kid, kf in cand.items():
                o = kf.mp_ids[kf.mp_ids >= 0]
                c = int(np.count_nonzero(mark[o]))
                if c > 0:
                    counts[kid] = c
        k1 = sorted(counts, key=counts.get, reverse=True)   # stable: ties keep insertion order
        local = [cand[k] for k in k1]
        seen = set(k1)
        max_kfs = MAX_LOCAL_KEYFRAMES
        for kf in list(local):
            if len(local) >= max_kfs:
                break
            conn = getattr(kf, "connections", {})
            for kid in sorted(conn, key=conn.get, reverse=True)[:10]:
                if kid not in seen:
                    k = self.map.keyframes.get(kid)
                    if k is not None and not k.bad:
                        local.append(k)
                        seen.add(kid)
                        break
            if kf.parent is not None and not kf.parent.bad and kf.parent.id not in seen:
                local.append(kf.parent)
                seen.add(kf.parent.id)
        self.local_kfs = local[:max_kfs]
        self.local_kf_ids = set(k.id for k in self.local_kfs)
        if k1:
            self.ref_kf = cand[k1[0]]
            frame.ref_kf = self.ref_kf

    def track_local_map(self, frame: Frame) -> bool:
        mp = self.map
        self.update_local_keyframes(frame)
        if not self.local_kfs:
            return False
        pts = np.unique(np.concatenate([k.valid_mp_ids(mp.mp_bad) for k in self.local_kfs]))
        self.n_local_points = len(pts)
        matched = frame.mp_ids[frame.mp_ids >= 0]
        mp.mp_visible[matched] += 1
        pts = pts[~np.isin(pts, matched)]
        th = 5.0 if frame.id < self.last_reloc_frame_id + 2 else 1.0
        _, visible = self.matcher.search_local_points(frame, mp, pts, th=th)
        mp.mp_visible[visible] += 1
        Optimizer.pose_optimization(frame, mp)
        inl = (frame.mp_ids >= 0) & ~frame.outlier
        ids = frame.mp_ids[inl]
        mp.mp_found[ids] += 1
        self.n_matches_inliers = int(np.count_nonzero(inl))
        low = self.low_texture(frame)
        need = MIN_INLIERS_LOW_TEXTURE if low else MIN_INLIERS
        if frame.id < self.last_reloc_frame_id + self.cfg.max_frames:
            # ORB-SLAM2 asks 50 inliers for a second after a relocalization; a blank-wall view
            # never has 50, so there it is twice the low-texture minimum (else every
            # relocalization there was followed by a second of LOST frames)
            need = 2 * need if low else max(need, 50)
        return self.n_matches_inliers >= need

    # ------------------------------------------------------------------ keyframes
    def mapped_view(self, frame: Frame) -> bool:
        """A keyframe of an earlier pass (at least ``REVISIT_MIN_AGE`` s old) in the local map
        sees this place from within ``REVISIT_DISTANCE`` and ``REVISIT_ANGLE_DEG``, and the frame
        is tracked (the inliers track_local_map asks): the place is mapped and the view needs no
        keyframe. The local map holds a keyframe of an earlier pass only where that place is
        already linked to the current one (covisible, as after its loop closure), so a place
        first revisited is still mapped and closed as a loop. On weak texture the keyframe rules
        fire on every frame (few close points are tracked, the rest are sensor-noise corners no
        other view re-finds), so without this a patrol added the same blank wall's keyframes and
        points again on every lap, none of them redundant by ORB-SLAM2's culling rule."""
        if self.n_matches_inliers < (MIN_INLIERS_LOW_TEXTURE if self.low_texture(frame)
                                     else MIN_INLIERS):
            return False
        old = [k for k in self.local_kfs
               if not k.bad and k.stamp <= frame.stamp - REVISIT_MIN_AGE]
        if not old:
            return False
        T = frame.T_wc
        C = np.array([-k.T_cw[:3, :3].T @ k.T_cw[:3, 3] for k in old])
        Z = np.array([k.T_cw[2, :3] for k in old])     # optical axes in the world
        near = np.linalg.norm(C - T[:3, 3], axis=1) <= REVISIT_DISTANCE
        aligned = Z @ T[:3, 2] >= np.cos(np.radians(REVISIT_ANGLE_DEG))
        return bool(np.any(near & aligned))

    def need_new_keyframe(self, frame: Frame) -> bool:
        mp = self.map
        lm = self.system.local_mapping
        n_kfs = len(mp.good_keyframes())
        if self.mapped_view(frame):
            return False
        max_frames, min_frames = self.cfg.max_frames, MIN_FRAMES
        if frame.id < self.last_reloc_frame_id + max_frames and n_kfs > max_frames:
            return False
        min_obs = 3 if n_kfs > 2 else 2
        ref_ids = self.ref_kf.valid_mp_ids(mp.mp_bad)
        n_ref = int(np.count_nonzero(mp.mp_nobs[ref_ids] >= min_obs))
        idle = lm.accept_keyframes()
        close = (frame.depth > 0) & (frame.depth < frame.th_depth)
        tracked = frame.mp_ids >= 0
        n_tracked_close = int(np.count_nonzero(close & tracked))
        n_non_tracked_close = int(np.count_nonzero(close & ~tracked))
        low = self.low_texture(frame)
        # ORB-SLAM2's 100/70 assume 1000+ features; on blank walls every new close point counts
        min_new = max(10, 0.3 * np.count_nonzero(close)) if low else 70
        need_close = n_tracked_close < 100 and n_non_tracked_close > min(70, min_new)
        # the map covers too little of what the frame sees nearby (not in ORB-SLAM2): a keyframe
        # when LocalMapping is idle (c1b), never interrupting its BA as need_close does
        sparse = (n_tracked_close < CLOSE_TRACKED_RATIO * np.count_nonzero(close) and
                  n_non_tracked_close > min(70, min_new))
        th_ref = 0.4 if n_kfs < 2 else TH_REF_RATIO
        c1a = frame.id >= self.last_kf_frame_id + max_frames
        c1b = frame.id >= self.last_kf_frame_id + min_frames and idle
        c1c = self.n_matches_inliers < n_ref * WEAK_REF_RATIO or need_close
        c2 = (self.n_matches_inliers < n_ref * th_ref or need_close or sparse) and \
            self.n_matches_inliers > (10 if low else 15)
        if (c1a or c1b or c1c) and c2:
            if idle:
                return True
            lm.interrupt_ba()
            return lm.queue_size() < 3
        return False

    def create_new_keyframe(self, frame: Frame, all_stereo: bool = False):
        """New keyframe with new map points from close stereo keypoints (CreateNewKeyFrame);
        ``all_stereo``: from every stereo keypoint (a view the map does not cover)."""
        mp = self.map
        kf = mp.new_keyframe(frame)
        kf.parent = self.ref_kf
        stereo = np.nonzero(frame.depth > 0)[0]
        stereo = stereo[np.argsort(frame.depth[stereo], kind="stable")]
        if len(stereo):
            n_pts = np.arange(1, len(stereo) + 1)
            stop = (frame.depth[stereo] > frame.th_depth) & (n_pts > MIN_CLOSE_POINTS)
            if np.any(stop) and not all_stereo:
                stereo = stereo[: int(np.argmax(stop))]
            new = stereo[frame.mp_ids[stereo] < 0]
            if len(new):
                ids = mp.add_points(frame.unproject_stereo(new), frame.desc[new], kf, new)
                frame.mp_ids[new] = ids
        self.ref_kf = kf
        frame.ref_kf = kf
        self.last_kf_frame_id = frame.id
        self.system.local_mapping.insert_keyframe(kf)
        return kf
