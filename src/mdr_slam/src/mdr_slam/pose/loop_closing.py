"""LoopClosing: place recognition, geometric verification, loop correction (ORB-SLAM2 LoopClosing).

Per keyframe: its BoW vector (ORBVocabulary) goes into the KeyFrameDatabase; loop candidates are
keyframes not connected to it whose L1 score beats the lowest score of its covisible neighbours
and that recur for ``loop_consistency`` consecutive keyframes (ORB-SLAM2's consistent groups).
Geometric verification matches map-point descriptors between the two keyframes under the same
vocabulary node (ORB-SLAM2 SearchByBoW: ORBmatcher.search_by_bow) and fits the 3D-3D rigid
transform with RANSAC (batched Umeyama on 3-point samples; SE(3), since stereo fixes the scale);
a candidate that fits is matched again over all descriptors and fitted on those, then the
candidate's neighbourhood is projected with the corrected pose for more matches.
Correction: the current keyframe's covisible group is moved by the loop transform, the loop
side's points are fused into it (SearchAndFuse), and an SE(3) pose graph over the essential graph (spanning tree,
strong covisibility edges >= 100, loop edges) is optimised with GTSAM BetweenFactorPose3; every
map point follows its reference keyframe. The corrected keyframe poses are reported (reason
``loop_closure``) so depth and fusion re-anchor. Pose-graph edges carry information from the
map points they share (``pose_graph_weights``). Then a global bundle adjustment over every
keyframe and point (``global_ba``, ORB-SLAM2 RunGlobalBundleAdjustment; sparse Schur solver in
optimizer.global_bundle_adjustment) refines the result by the observations themselves; its
corrections are reported as ``loop_closure`` too. A verified loop whose correction is larger than
any plausible drift (``loop_max_drift`` x the keyframe path since the match, or
``loop_max_rotation_deg``) is refused: repeated bays passed the geometric check.
A BoW loop whose RANSAC inliers leave its rotation ill-determined (points along one edge:
``loop_rotation_check``, ``loop_max_rot_sigma_deg``) is accepted only when its turn is
``loop_rot_significance`` of those sigmas: otherwise its own error can exceed the drift it corrects.

Proximity loops (``loop_proximity``, ORB-SLAM3/RTAB-Map style), tried when the BoW path closes
nothing: old keyframes whose estimated pose is near the current one (radius growing with the
path since, as the drift gate), ranked by phase correlation of kept low-resolution images and
verified without descriptors (Lucas-Kanade tracks of the stereo keypoints + PnP RANSAC), then
the same drift gate. Where BoW and descriptors fail: on blank walls ORB corners are sensor
noise (office loop seed 1: in the first keyframe 301 of 704 keypoints have a twin descriptor
< 30 bits elsewhere in the image, so the ratio test keeps 22-57 matches of ~720 keypoints at the
revisit, even 0.1 m / 5 deg from the old view, and the old keyframes keep only 25-75 map points).
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Dict, List, Optional

import cv2
import numpy as np

from ..geometry import inv_T, rotation_angle, transform_points
from .ba_process import BAWorker
from .matcher import ORBmatcher, _unique_by
from .optimizer import Optimizer, global_bundle_adjustment, normalize_pose, odometry_motion
from .orb import TH_LOW, hamming_knn2
from .vocabulary import KeyFrameDatabase, bow_score, load_vocabulary

__all__ = ["LoopClosing", "ransac_se3", "rotation_sigma_deg", "loop_rotation_check"]

# Tuned internals (ORB-SLAM2 LoopClosing's counterpart in brackets where there is one)
LOOP_CONSISTENCY = 2           # consecutive keyframes a loop candidate must recur (mnCovisibilityConsistencyTh: 3)
LOOP_MIN_AGE = 3.0             # s; younger keyframes are never loop candidates
LOOP_MAX_DRIFT = 0.3           # a loop may move the keyframe <= this x the keyframe path since the match ...
LOOP_MAX_ROTATION_DEG = 45.0   # ... and turn it at most this much (false-loop gate)
LOOP_MAX_ROT_SIGMA_DEG = 1.0   # a BoW loop whose inliers leave its rotation more uncertain than this ...
LOOP_ROT_SIGNIFICANCE = 5.0    # ... is accepted only when it turns the map by this many sigmas ...
LOOP_ROT_SIGMA_CAP_DEG = 4.0   # ... and never when that sigma exceeds this
LOOP_NN_RATIO = 0.75           # best / second-best distance of a loop match (SearchByBoW: 0.75)
BOW_NODE_DEPTH = 2             # depth of the vocabulary node loop matches share (ORB-SLAM2's direct
                               # index: 4 levels up from the leaves of its 6-level tree, also depth 2)
LOOP_REPROJECTION_REFINE = True  # BoW loop transform refined by the keyframe's pixels (OptimizeSim3)
POSE_GRAPH_WEIGHTS = True      # pose-graph edge information from shared points (OptimizeEssentialGraph: equal)
LOOP_FUSE_COVISIBLES = 10      # the loop keyframe's covisibles whose points are fused into the
                               # corrected group (SearchAndFuse: all of them)
LOOP_FUSE_RADIUS = 4.0         # projection search radius of that fusion, px at level 0 (SearchAndFuse: 4)
GLOBAL_BA_ITERATIONS = 20      # iterations of each global BA (RunGlobalBundleAdjustment: 10)
GLOBAL_BA_TOL = 1e-3           # a global BA round ends once a step lowers the cost by less than this
                               # share of it (local BA's BA_TOL; 0: every iteration)
GLOBAL_BA_MIN_CORRECTION_M = 0.03    # a global BA follows a loop that moved the keyframe more than
GLOBAL_BA_MIN_CORRECTION_DEG = 0.5   # this or turned it more than this (RunGlobalBundleAdjustment: always)
GLOBAL_BA_MIN_KF_POINTS = 20   # keyframes seeing fewer points follow their parent in the global BA
GLOBAL_BA_PROCESS = True       # threads: a loop's pose graph and global BA solved in a child process
#                                (out of the GIL) ...
GLOBAL_BA_NICE = 10            # ... at this nice increment (it yields the CPU to tracking)
# Proximity loops (no ORB-SLAM2 counterpart; ORB-SLAM3 / RTAB-Map style): keyframes near the estimated
# pose, ranked by phase correlation of their quarter images (112 kB kept per keyframe), verified by LK + PnP
LOOP_PROXIMITY = True
LOOP_PROXIMITY_RADIUS = 0.5         # m, + LOOP_MAX_DRIFT x the keyframe path since the candidate ...
LOOP_PROXIMITY_MAX_RADIUS = 2.0     # ... capped at this (m)
LOOP_PROXIMITY_MIN_PATH = 2.0       # m of keyframe path since the candidate (a stop-and-sweep revisits itself)
LOOP_PROXIMITY_ANGLE_DEG = 45.0     # optical axes at most this far apart
LOOP_PROXIMITY_MIN_RESPONSE = 0.3   # phase-correlation response of the quarter images
LOOP_PROXIMITY_CANDIDATES = 2       # verified per keyframe (best responses)
LOOP_PROXIMITY_MIN_INLIERS = 40     # PnP inliers of the LK tracks (and >= 60 % of them) ...
LOOP_PROXIMITY_WEAK_INLIERS = 15    # ... or down to this many when consistent ...
LOOP_PROXIMITY_WEAK_CONSISTENCY = 2  # ... with this many previous weak verifications
LOOP_PROXIMITY_TWO_WAY = True       # the candidate's keypoints tracked into the keyframe too: both poses
LOOP_PROXIMITY_TWO_WAY_DEG = 2.0    # agree within this rotation ...
LOOP_PROXIMITY_TWO_WAY_M = 0.5      # ... and translation (m)

LOOP_MAP_CHECK = True          # a loop keyframe's neighbourhood must line up with the current keyframe
LOOP_MAP_LARGE_RATIO = 2.0     # this x as often with the correction as without it ...
LOOP_MAP_SMALL_RATIO = 0.9     # ... or this x when the correction moves the projections by at most
LOOP_MAP_SMALL_PX = 12.0       # this (median px, the search window: both poses find the same points)

LOOP_CONFIRMATIONS = 2         # later keyframes that must see the loop place through the same
#                                correction before it is closed (ORB-SLAM3 mnLoopNumCoincidences: 3
#                                keyframes in all) ...
LOOP_CONFIRM_MATCHES = 30      # ... each matching this many of its points (DetectAndReffineSim3-
#                                FromLastKF: nProjMatches 30), with the map check's ratio
LOOP_CONFIRM_MISSES = 2        # keyframes that fail in a row drop the candidate (mnLoopNumNotFound)

LOOP_ODOM_GATE_M = 0.1          # a loop may leave the map this far from the wheel odometry's motion
LOOP_ODOM_GATE_REL = 0.05       # ... + this x the odometry's path between the two keyframes (m) ...
LOOP_ODOM_GATE_DEG = 2.0        # ... and turned this far + DEG_PER_M x that path, unless it was farther
LOOP_ODOM_GATE_DEG_PER_M = 1.5  # before (wheel odometry: a few % of the path, ~1 deg/m of yaw)
LOOP_ODOM_AWAY_M = 0.1          # whatever those bounds, a loop may move the keyframe away from where
LOOP_ODOM_AWAY_REL = 0.01       # the odometry puts it by at most this + REL x the path (m), and turn
LOOP_ODOM_AWAY_DEG = 2.0        # it away from the odometry's heading by at most this (deg)


def _umeyama_batch(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(H, 4, 4) rigid transforms mapping A[h] (H, n, 3) onto B[h] (batched SVD)."""
    ma, mb = A.mean(1, keepdims=True), B.mean(1, keepdims=True)
    C = np.einsum("hni,hnj->hij", B - mb, A - ma)
    U, _, Vt = np.linalg.svd(C)
    d = np.sign(np.linalg.det(U @ Vt))
    S = np.tile(np.eye(3), (len(A), 1, 1))
    S[:, 2, 2] = d
    R = U @ S @ Vt
    T = np.tile(np.eye(4), (len(A), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = mb[:, 0] - np.einsum("hij,hj->hi", R, ma[:, 0])
    return T


def ransac_se3(A: np.ndarray, B: np.ndarray, th: np.ndarray, iters: int = 300, seed: int = 0):
    """Rigid T with B ~ T A from correspondences with outliers: (T, inlier mask) or (None, None).
    ``th`` is the per-correspondence 3-D distance threshold."""
    n = len(A)
    if n < 3:
        return None, None
    rng = np.random.RandomState(seed)
    idx = rng.randint(0, n, size=(iters, 3))   # 3 distinct per row: rows with a repeat redrawn
    while True:
        rep = (idx[:, 0] == idx[:, 1]) | (idx[:, 0] == idx[:, 2]) | (idx[:, 1] == idx[:, 2])
        if not rep.any():
            break
        idx[rep] = rng.randint(0, n, size=(int(rep.sum()), 3))
    Ts = _umeyama_batch(A[idx], B[idx])
    pred = np.einsum("hij,nj->hni", Ts[:, :3, :3], A) + Ts[:, None, :3, 3]
    err = np.linalg.norm(pred - B[None], axis=2)
    inl = err < th[None]
    best = int(np.argmax(inl.sum(1)))
    mask = inl[best]
    if mask.sum() < 3:
        return None, None
    for _ in range(2):   # refine on all inliers
        T = _umeyama_batch(A[mask][None], B[mask][None])[0]
        err = np.linalg.norm(A @ T[:3, :3].T + T[:3, 3] - B, axis=1)
        mask = err < th
        if mask.sum() < 3:
            return None, None
    return T, mask


def rotation_sigma_deg(B: np.ndarray, resid: np.ndarray) -> float:
    """Standard deviation (deg) of the worst-determined rotation axis of a rigid 3-D-3-D fit
    whose inliers sit at ``B`` (n, 3) with residuals ``resid`` (n,) in metres. The rotational
    block of the fit's information, sum(|q|^2 I - q q^T) over the centred points q, against the
    per-axis residual variance (3n values, 6 fitted parameters; at least 5 mm): points along one
    line (a door edge) leave the rotation about that line free, and centimetres of noise then
    turn the loop by degrees."""
    n = len(B)
    if n < 3:
        return float("inf")
    q = B - B.mean(0)
    lam = float(np.linalg.eigvalsh(np.sum(q * q) * np.eye(3) - q.T @ q)[0])
    sig = max(float(np.sqrt(np.sum(resid ** 2) / max(3 * n - 6, 1))), 0.005)
    return float(np.degrees(sig / np.sqrt(lam))) if lam > 0 else float("inf")


def loop_rotation_check(A: np.ndarray, B: np.ndarray, S: np.ndarray, max_sigma_deg: float,
                        significance: float, sigma_cap_deg: float = 0.0):
    """(accept, rotation sigma deg, turn deg) of a loop correction S (B ~ S A on the inliers):
    refused when the inliers leave its rotation more uncertain than ``max_sigma_deg`` and it
    turns the map by less than ``significance`` of those sigmas, i.e. when the loop's own error
    can be as large as the drift it corrects. The sample (office, loop + pure rotation) returns
    to a view whose matched points lie on one vertical edge (sigma 2.3-2.9 deg about it): without
    the motion prior the drift there is 25 deg and the loop turns the map by 21 (9.2 sigma, kept:
    4.3 deg left); with it the drift is 1.9 deg and the loop turned the map by 9.8 (3.5 sigma)
    and was 8.3 deg wrong: the real error exceeds sigma (the map points' own errors are
    correlated), hence the default of 5 sigmas. ``sigma_cap_deg`` > 0: refused whatever it turns
    when the sigma exceeds it (simulated garage seed 11: 60 inliers on one poster 5 m away, sigma
    5.0 deg, turned the map by 35 deg where the drift was 4 deg)."""
    cos = np.clip((np.trace(S[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    turn = float(np.degrees(np.arccos(cos)))
    if max_sigma_deg <= 0 or significance <= 0:
        return True, float("nan"), turn
    r = np.linalg.norm(A @ S[:3, :3].T + S[:3, 3] - B, axis=1)
    sig = rotation_sigma_deg(B, r)
    if sigma_cap_deg > 0 and sig > sigma_cap_deg:
        return False, sig, turn
    return bool(sig <= max_sigma_deg or turn >= significance * sig), sig, turn


class LoopClosing:
    def __init__(self, system, cfg):
        self.system = system
        self.map = system.map
        self.cfg = cfg            # TrackerConfig
        self.voc = load_vocabulary(cfg.vocabulary or None)
        self.db = KeyFrameDatabase(self.voc)
        self.matcher = ORBmatcher(check_orientation=True)
        self.queue = deque()
        self.cv = threading.Condition()
        self.stop_flag = False
        self.thread: Optional[threading.Thread] = None
        self.corrections = []
        self.last_loop_kf_id = -10 ** 9
        self.consistent_groups: List[tuple] = []   # (set of kf ids, consistency count)
        self.min_consistency = LOOP_CONSISTENCY
        self.min_inliers = 20
        self.loops: List[tuple] = []               # accepted (current kf id, loop kf id)
        # accepted, for the log: dicts of kf, cand (ids), stamp (kf's), source (bow, proximity),
        # found (the keyframe that found it; kf confirmed it), moved_m, turned_deg (the
        # correction at kf), path_m (keyframe path between them), graph_ms, graph_edges,
        # graph_process (the essential graph's solve, in a child process or not), held_ms (the
        # map lock held for the keyframe: tracking waits that long), and the checks it passed:
        # map_check (matches uncorrected, corrected, median px moved) and odometry_check (m off
        # the odometry before, after, odometry path m, deg off it before, after), None where
        # not run
        self.closed: List[dict] = []
        self.global_ba_runs: List[dict] = []       # global_bundle_adjustment summaries (+ ms)
        self.rejected: List[tuple] = []            # (kf, cand, moved m, turned deg, path m)
        self.images: Dict[int, tuple] = {}         # kf id -> (half, quarter) left image (proximity)
        self.proximity_loops: List[tuple] = []     # closed, found by proximity (found kf, cand, inliers)
        self.odom_checks: List[tuple] = []         # (kf, cand, odometry path m, m and deg off it
        #                                            before / after the correction, accepted)
        self.correction_checks: List[tuple] = []   # correction_fits_map (kf, cand, n before, after, px, ok)
        self.proximity_tries = 0                   # proximity verifications run (LK + PnP)
        self.one_way: List[tuple] = []             # refused by the two-way check (kf, cand, m, deg)
        self._exclude: set = set()
        self.last_correction = (0.0, 0.0)          # (m, deg) of the last verified loop transform
        self._last_path = 0.0                      # m of keyframe path it spans
        self._weak: List[tuple] = []               # (kf id, S) of weak proximity verifications
        self._graph_job = None                     # correct_loop's essential graph, to solve
        self.ill_conditioned: List[tuple] = []     # refused: (kf, cand, inliers, rot sigma, turn deg)
        # a verified loop waiting for LOOP_CONFIRMATIONS later keyframes: dict of cand, S,
        # source, first (kf id), confirmed, missed, n (the verification's inliers)
        self.pending: Optional[dict] = None
        self.unconfirmed: List[tuple] = []         # dropped: (first kf, cand, confirmations)
        self.held_ms: List[float] = []             # per keyframe processed: the map lock held (ms)

    # ------------------------------------------------------------------ queue / thread
    def insert_keyframe(self, kf) -> None:
        with self.cv:
            self.queue.append(kf)
            self.cv.notify()

    def start(self) -> None:
        self.thread = threading.Thread(target=self._run, name="LoopClosing", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            with self.cv:
                while not self.queue and not self.stop_flag:
                    self.cv.wait(0.1)
                if self.stop_flag and not self.queue:
                    return
                kf = self.queue.popleft()
            self.process(kf)

    def stop(self) -> None:
        with self.cv:
            self.stop_flag = True
            self.cv.notify()
        if self.thread is not None:
            self.thread.join(60.0)

    def spin_sync(self) -> None:
        while self.queue:
            self.process(self.queue.popleft())

    # ------------------------------------------------------------------ BoW
    def bow(self, kf):
        """The keyframe's BoW vector (ORB-SLAM2 KeyFrame::ComputeBoW), and its keypoints' words
        in ``kf.bow_words`` for the direct index (``search_by_bow``)."""
        if kf.bow is None or kf.bow_words is None:
            words = self.voc.transform_words(kf.desc)
            kf.bow_words = words.astype(np.int32)
            kf.bow = self.voc.bow_vector(words)
        return kf.bow

    def relocalization_candidates(self, frame, n: int):
        """Keyframes most similar to ``frame`` by BoW (ORB-SLAM2 DetectRelocalizationCandidates)."""
        if not self.db.bows:
            return None
        bow = self.voc.transform(frame.desc)   # the frame's own descriptors: no lock needed
        with self.map.lock:
            res = self.db.query(bow, top=n)
            return [self.map.keyframes[k] for k, _ in res
                    if k in self.map.keyframes and not self.map.keyframes[k].bad]

    # ------------------------------------------------------------------ per keyframe
    def keep_image(self, kf_id: int, image: np.ndarray) -> None:
        """Keep a keyframe's left image at half and quarter resolution (90 + 22 kB at 752x480)
        for the proximity loop path (``loop_proximity``); called by System after tracking."""
        if not LOOP_PROXIMITY or image is None or image.ndim != 2:
            return
        half = cv2.pyrDown(image)
        self.images[int(kf_id)] = (half, cv2.pyrDown(half))

    def process(self, kf) -> None:
        closed = False
        self.system.yield_to_tracking()
        bow = self.bow(kf)   # the keyframe's descriptors never change: outside the map lock
        n_closed = len(self.closed)
        with self.map.lock:
            t_lock = time.perf_counter()
            if kf.bad:
                return
            self._exclude = set()
            if self.pending is not None:   # no new detection while a loop awaits confirmation
                closed = self.confirm_pending(kf)
            else:
                cand = self.detect_loop(kf, bow)
                if cand is not None:
                    closed = self.try_close(kf, cand)
                if not closed and self.pending is None and self._exclude and LOOP_PROXIMITY:
                    closed = self.try_proximity(kf)
            self.db.add(kf.id, bow)
            if kf.id % 20 == 0:   # culled keyframes are no longer candidates (KeyFrame::SetBadFlag
                # erases them from the database): their images and BoW entries go
                for k in [k for k in list(self.images) if k not in self.map.keyframes or
                          self.map.keyframes[k].bad]:   # list(): tracking adds meanwhile
                    self.images.pop(k, None)
                for k in [k for k in self.db.bows if k not in self.map.keyframes or
                          self.map.keyframes[k].bad]:
                    self.db.erase(k)
            held_ms = 1000.0 * (time.perf_counter() - t_lock)
            self.held_ms.append(held_ms)
        if len(self.closed) > n_closed:   # tracking waits on the map lock this long
            self.closed[-1]["held_ms"] = held_ms
        gba = closed and self.cfg.global_ba and self.global_ba_pays()
        if self._graph_job is None and not gba:
            return
        worker = None
        if self.system.threads and GLOBAL_BA_PROCESS:
            # one child process per loop for its pose graph and global BA (loops are rare: its
            # ~60 MB are not kept); in this thread GTSAM and the solver's long numpy/scipy steps
            # hold the GIL, and tracking and the node's tf stand still meanwhile
            worker = BAWorker(nice=int(GLOBAL_BA_NICE))
        try:
            self.finish_correction(worker)
            if gba:
                self.run_global_ba(worker)
        finally:
            if worker is not None:
                worker.close()

    def global_ba_pays(self) -> bool:
        """A full BA after a loop only where the loop moved the map by more than
        ``GLOBAL_BA_MIN_CORRECTION_M`` or ``GLOBAL_BA_MIN_CORRECTION_DEG``: a place closed again
        with a correction of millimetres is settled by the pose graph, and a full BA over the
        whole map would cost seconds for nothing. (ORB-SLAM3 runs it only in maps of fewer than
        200 keyframes.)"""
        moved, rot = self.last_correction
        return moved > GLOBAL_BA_MIN_CORRECTION_M or rot > GLOBAL_BA_MIN_CORRECTION_DEG

    def _gba_abort(self) -> bool:
        self.system.yield_to_tracking()   # per iteration, without the map lock
        return self.stop_flag

    def run_global_ba(self, worker=None) -> dict:
        """Global bundle adjustment after a loop correction (ORB-SLAM2 RunGlobalBundleAdjustment):
        the pose graph spreads the loop error by edge count, the full BA by the information of
        every observation, so segments tracked on few points (blank walls) take the larger share
        of the correction. In threaded mode the map lock is released while the solver runs
        (tracking goes on; keyframes and points made meanwhile follow their ancestors); the
        corrected keyframe poses are reported like the loop correction."""
        t0 = time.perf_counter()
        res = global_bundle_adjustment(   # the first keyframe holds the map frame (ORB-SLAM2)
            self.map, iterations=int(GLOBAL_BA_ITERATIONS),
            min_kf_points=int(GLOBAL_BA_MIN_KF_POINTS), tol=float(GLOBAL_BA_TOL),
            abort=self._gba_abort if self.system.threads else None,
            lock_solve=not self.system.threads, worker=worker)
        res["ms"] = 1000.0 * (time.perf_counter() - t0)
        res["process"] = worker is not None and not worker.failed
        self.global_ba_runs.append(res)
        with self.map.lock:
            self.corrections.append(("loop_closure", {k: self.map.keyframes[k].T_cw.copy()
                                                      for k in res["moved"]
                                                      if k in self.map.keyframes}))
        return res

    def detect_loop(self, kf, bow):
        mp = self.map
        if kf.id < self.last_loop_kf_id + 10 or len(self.db.bows) < 5:
            self.consistent_groups = []
            return None
        conn = [k for k in kf.connections if k in mp.keyframes and not mp.keyframes[k].bad]
        scores = [bow_score_safe(bow, self.bow(mp.keyframes[k])) for k in conn]
        min_score = min(scores) if scores else 0.0
        # connected and recent keyframes are not loops (ORB-SLAM2 excludes the connected). On
        # blank walls consecutive keyframes share too few points to be connected, yet they share
        # the most words with the current one: they filled the candidate list and cost a
        # geometric verification each (office loop seed 1: 34 failed verifications, most
        # against keyframes 1-2 s old; 18 with this). So the neighbours' neighbours and every
        # keyframe of the last loop_min_age seconds are excluded too.
        near = set(conn)
        for k in conn:
            near |= set(mp.keyframes[k].connections)
        min_age = float(LOOP_MIN_AGE)
        exclude = near | {kf.id} | {k for k in self.db.bows if k > kf.id - 5} | \
            {k for k in self.db.bows if k in mp.keyframes and k >= mp.loaded_next_kf_id and
             kf.stamp - mp.keyframes[k].stamp < min_age}   # a loaded map's keyframes are old
        self._exclude = exclude
        cands = [k for k, s in self.db.query(bow, exclude=exclude, min_score=min_score, top=5)]
        # consistency: a candidate's group (it + its connections) must overlap a group that was
        # detected for the previous keyframes, min_consistency times in a row
        new_groups = []
        accepted = []
        for c in cands:
            ck = mp.keyframes.get(c)
            if ck is None or ck.bad:
                continue
            group = {c} | set(ck.connections)
            best = 0
            for g, n in self.consistent_groups:
                if group & g:
                    best = max(best, n + 1)
            n = max(best, 1)
            new_groups.append((group, n))
            if n >= self.min_consistency:
                accepted.append(ck)
        self.consistent_groups = new_groups
        return accepted or None

    def try_close(self, kf, cands) -> bool:
        for cand in cands:
            res = self.compute_se3(kf, cand)
            if res is None:
                continue
            S, cur_ids, loop_ids, new_kp, new_ids = res
            if not self.plausible_correction(kf, cand, S) or \
                    not self.correction_fits_map(kf, cand, S):
                continue
            self.consistent_groups = []
            if self._defer(kf, cand, S, "bow"):
                return False
            self.correct_loop(kf, cand, S, cur_ids, loop_ids, new_kp, new_ids, source="bow")
            return True
        return False

    def _defer(self, kf, cand, S, source: str, n: int = 0) -> bool:
        """Keep a verified loop (``n``: its verification's inliers) for confirmation by the next
        keyframes (True), unless LOOP_CONFIRMATIONS is 0."""
        if int(LOOP_CONFIRMATIONS) <= 0:
            return False
        self.pending = dict(cand=cand, S=S.copy(), source=source, first=kf.id, confirmed=0,
                            missed=0, n=int(n))
        return True

    def confirm_pending(self, kf) -> bool:
        """ORB-SLAM3's loop confirmation (LoopClosing::NewDetectCommonRegions with
        DetectAndReffineSim3FromLastKF): a keyframe after the one that found the loop is placed
        by the same correction, and the loop keyframe's neighbourhood projected into it must
        match at least LOOP_CONFIRM_MATCHES of its keypoints and pass the map check. A place that
        only looks like the old one from one viewpoint (another bay of a garage) stops matching
        as the robot moves on. After LOOP_CONFIRMATIONS confirmations the loop is closed with
        this keyframe; after LOOP_CONFIRM_MISSES failures in a row it is dropped."""
        p = self.pending
        cand, S = p["cand"], p["S"]
        if cand.bad or kf.bad:
            self.pending = None
            return False
        n_checks = len(self.correction_checks)
        ok = self.correction_fits_map(kf, cand, S)
        n1 = self.correction_checks[-1][3] if len(self.correction_checks) > n_checks else 0
        if ok and n1 >= int(LOOP_CONFIRM_MATCHES):
            p["confirmed"] += 1
            p["missed"] = 0
        else:
            p["missed"] += 1
            if p["missed"] >= int(LOOP_CONFIRM_MISSES):
                self.unconfirmed.append((p["first"], cand.id, p["confirmed"]))
                self.pending = None
            return False
        if p["confirmed"] < int(LOOP_CONFIRMATIONS):
            return False
        self.pending = None
        if not self.plausible_correction(kf, cand, S):   # the gates again, for this keyframe
            self.unconfirmed.append((p["first"], cand.id, p["confirmed"]))
            return False
        # SearchAndFuse in correct_loop merges what the guided search leaves
        new_kp, new_ids = self.guided_matches(kf, cand, S)
        empty = np.zeros(0, np.int64)
        if p["source"] == "proximity":
            self.proximity_loops.append((p["first"], cand.id, p["n"]))
        self.correct_loop(kf, cand, S, empty, empty, new_kp, new_ids,
                          n_match=max(int(n1), len(new_kp)), source=p["source"], found=p["first"])
        return True

    # ------------------------------------------------------------------ proximity loops
    def proximity_candidates(self, kf) -> List[tuple]:
        """Old keyframes whose ESTIMATED pose is near the current one (ORB-SLAM3/RTAB-Map style
        proximity detection, for places the BoW misses: office loop seed 1 returns to a blank
        wall whose corners are sensor noise, so old and new keyframes share almost no ORB
        descriptor although the views are the same). Not covisible, not recent (the BoW path's
        exclusion set), at least ``loop_proximity_min_path`` of keyframe path ago (a stop-and-sweep
        revisits its own views: no drift to correct there), within ``loop_proximity_radius`` +
        ``loop_max_drift`` x that path (at most ``loop_proximity_max_radius``) and
        ``loop_proximity_angle_deg`` of optical axis; ranked by the phase-correlation response
        of the quarter images (cv2.phaseCorrelate; its shift starts the LK search; responses
        below ``loop_proximity_min_response`` are dropped). Returns [(response, kf id, (dx, dy)
        full-image shift)] best first, at most ``loop_proximity_candidates``."""
        mp = self.map
        if kf.id not in self.images:
            return []
        ids = sorted(k.id for k in mp.good_keyframes() if k.id <= kf.id)
        P = np.array([mp.keyframes[k].T_wc[:3, 3] for k in ids])
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
        pos = dict(zip(ids, range(len(ids))))
        old = np.array([k for k in ids if k not in self._exclude and k in self.images], np.int64)
        if len(old) == 0:
            return []
        T = kf.T_wc
        Po = P[[pos[k] for k in old]]
        Zo = np.array([mp.keyframes[k].T_wc[:3, 2] for k in old])
        dist = np.linalg.norm(Po - T[:3, 3], axis=1)
        ang = np.degrees(np.arccos(np.clip(Zo @ T[:3, 2], -1.0, 1.0)))
        path = cum[pos[kf.id]] - cum[[pos[k] for k in old]]
        radius = np.minimum(float(LOOP_PROXIMITY_RADIUS) +
                            float(LOOP_MAX_DRIFT) * path,
                            float(LOOP_PROXIMITY_MAX_RADIUS))
        ok = (dist <= radius) & (ang <= float(LOOP_PROXIMITY_ANGLE_DEG)) & \
            (path >= float(LOOP_PROXIMITY_MIN_PATH))
        sel = old[ok][np.argsort(dist[ok])][:60]   # bounded cost: ~0.3 ms per response
        q = self.images[kf.id][1].astype(np.float32)
        win = cv2.createHanningWindow(q.shape[::-1], cv2.CV_32F)
        out = []
        for k in sel.tolist():
            (dx, dy), r = cv2.phaseCorrelate(q, self.images[k][1].astype(np.float32), win)
            out.append((float(r), int(k), (2.0 * dx, 2.0 * dy)))
        th = float(LOOP_PROXIMITY_MIN_RESPONSE)
        out = sorted([o for o in out if o[0] >= th], key=lambda o: -o[0])
        return out[: int(LOOP_PROXIMITY_CANDIDATES)]

    def verify_proximity(self, kf, cand, shift=(0.0, 0.0)):
        """Appearance-free geometric verification of a proximity candidate: kf's stereo keypoints
        are followed into cand's image by pyramidal Lucas-Kanade (half resolution, started at
        the phase-correlation shift, forward-backward checked to 0.5 px), and cand's pose
        relative to kf comes from PnP RANSAC on their stereo 3-D points (2 px). With
        ``loop_proximity_two_way`` the same is done from cand's side (its stereo keypoints into
        kf's image); when that gives a pose, the two relative poses must agree within
        ``loop_proximity_two_way_deg`` and ``loop_proximity_two_way_m`` (office loop seeds 5
        and 9: verifications 0.2-0.9 m / 4-26 deg off the truth, with sub-pixel PnP residuals
        from kf's side, were 2.2-15.6 deg apart from cand's). Returns (S, inliers, kf keypoint index,
        cand image position) of the inliers, or None."""
        if kf.id not in self.images or cand.id not in self.images:
            return None
        self.proximity_tries += 1
        min_inl = int(LOOP_PROXIMITY_MIN_INLIERS)
        weak = int(LOOP_PROXIMITY_WEAK_INLIERS)
        if weak > 0:
            min_inl = min(min_inl, weak)
        fwd = self._lk_pnp(kf, cand, shift, min_inl)
        if fwd is None:
            return None
        T_ck, sel, uv = fwd
        if LOOP_PROXIMITY_TWO_WAY:
            back = self._lk_pnp(cand, kf, (-shift[0], -shift[1]), min_inl)
            if back is not None:   # cand's side gave a pose: the two must agree
                D = back[0] @ T_ck   # T_kc T_ck: identity when they agree
                moved = float(np.linalg.norm(D[:3, 3]))
                ang = float(np.degrees(rotation_angle(D)))
                if moved > float(LOOP_PROXIMITY_TWO_WAY_M) or \
                        ang > float(LOOP_PROXIMITY_TWO_WAY_DEG):
                    self.one_way.append((kf.id, cand.id, moved, ang))
                    return None
        S = cand.T_wc @ T_ck @ kf.T_cw   # corrected kf pose (cand T_wc T_ck) times the old inverse
        return S, len(sel), sel, uv

    def _lk_pnp(self, src, dst, shift, min_inl):
        """src's stereo keypoints tracked into dst's image (LK, half resolution) and dst's pose
        relative to src by PnP RANSAC: (T_dst_src, src keypoint index, dst image position) of
        the inliers, or None."""
        a, b = self.images[src.id][0], self.images[dst.id][0]
        sel = np.nonzero(src.depth > 0)[0]
        if len(sel) < min_inl:
            return None
        p0 = (src.uv[sel] * 0.5).astype(np.float32)
        p1 = p0 + np.float32([shift[0] * 0.5, shift[1] * 0.5])
        lk = dict(winSize=(21, 21), maxLevel=3)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, p1.astype(np.float32),
                                             flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        pb, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, None, **lk)
        ok = (st[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm(pb - p0, axis=1) < 0.5)
        if np.count_nonzero(ok) < min_inl:
            return None
        sel, uv = sel[ok], p1[ok].astype(np.float64) * 2.0
        z = src.depth[sel].astype(np.float64)
        X = np.stack([(src.uv[sel, 0] - src.cx) * z / src.fx,
                      (src.uv[sel, 1] - src.cy) * z / src.fy, z], axis=1)
        K = np.array([[src.fx, 0.0, src.cx], [0.0, src.fy, src.cy], [0.0, 0.0, 1.0]])
        good, rv, tv, inl = cv2.solvePnPRansac(X, uv, K, None, iterationsCount=200,
                                               reprojectionError=2.0, confidence=0.999,
                                               flags=cv2.SOLVEPNP_EPNP)
        if not good or inl is None or len(inl) < min_inl or len(inl) < 0.6 * len(sel):
            return None
        inl = inl[:, 0]
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rv)[0]
        T[:3, 3] = tv[:, 0]
        return T, sel[inl], uv[inl]

    def _weak_consistent(self, kf, S) -> bool:
        """A weak proximity verification (``loop_proximity_weak_inliers`` <= inliers <
        ``loop_proximity_min_inliers``) is accepted only when the corrections of the last
        ``loop_proximity_weak_consistency`` weak ones (keyframes at most 4 ids apart, each to
        the next) agree with it: the current keyframe corrected by each lies within 0.1 m and
        3 deg of its correction by S."""
        need = int(LOOP_PROXIMITY_WEAK_CONSISTENCY)
        T = S @ kf.T_wc
        hist = [(k, S_) for k, S_ in self._weak if kf.id - k <= 4 * need]
        ok = 0
        for k, S_ in reversed(hist):
            D = inv_T(T) @ S_ @ kf.T_wc
            ang = np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
            if np.linalg.norm(D[:3, 3]) < 0.1 and ang < 3.0:
                ok += 1
        self._weak = hist[-8:] + [(kf.id, S)]
        return ok >= need

    def try_proximity(self, kf) -> bool:
        mp = self.map
        for resp, c, shift in self.proximity_candidates(kf):
            cand = mp.keyframes.get(c)
            if cand is None or cand.bad:
                continue
            res = self.verify_proximity(kf, cand, shift)
            if res is None:
                continue
            S, n_inl, kp, uv = res
            if not self.plausible_correction(kf, cand, S):
                continue
            if n_inl < int(LOOP_PROXIMITY_MIN_INLIERS) and \
                    not self._weak_consistent(kf, S):
                continue
            if not self.correction_fits_map(kf, cand, S):
                continue
            # point fusion: kf's map points whose track ends on a cand keypoint with a map point
            d, j = cand.tree.query(uv)
            near = d < 2.0
            cur, loop = kf.mp_ids[kp[near]], cand.mp_ids[j[near]]
            pair = (cur >= 0) & (loop >= 0)
            cur_ids, loop_ids = cur[pair], loop[pair]
            pair = ~mp.mp_bad[cur_ids] & ~mp.mp_bad[loop_ids] & (cur_ids != loop_ids)
            cur_ids, loop_ids = cur_ids[pair], loop_ids[pair]
            self.consistent_groups = []
            if self._defer(kf, cand, S, "proximity", n_inl):
                return False
            new_kp, new_ids = self.guided_matches(kf, cand, S)   # as the BoW path does
            self.proximity_loops.append((kf.id, cand.id, n_inl))
            self.correct_loop(kf, cand, S, cur_ids, loop_ids, new_kp, new_ids,
                              n_match=n_inl, source="proximity")
            return True
        return False

    def guided_matches(self, kf, cand, S):
        """Guided search with the corrected pose (ComputeSim3's SearchByProjection): the loop
        keyframe's neighbourhood projected into ``kf`` seen through ``S``; returns (keypoint
        indices of kf, map point ids) it matched."""
        mp = self.map
        local = [cand] + mp.best_covisibles(cand, 10)
        pts = np.unique(np.concatenate([k.valid_mp_ids(mp.mp_bad) for k in local]))
        view = _KeyFrameView(kf, kf.T_cw @ inv_T(S))
        pts = pts[~np.isin(pts, kf.mp_ids)]
        self.matcher.search_local_points(view, mp, pts, th=3.0)
        new_kp = np.nonzero(view.mp_ids >= 0)[0]
        return new_kp, view.mp_ids[new_kp]

    def plausible_correction(self, kf, cand, S) -> bool:
        """Drift gate against false loops in repetitive or symmetric places (garage seed 4: two
        bays 11.7 m apart and turned 180 deg passed the geometric verification): the correction
        may move the current keyframe by at most loop_max_drift times the keyframe path
        travelled since the candidate, plus what its own rotation explains (a heading error of
        theta accrued before travelling L displaces by at most 2 sin(theta/2) L: seed 7 of
        office_loop_rotation drifted 22 deg of yaw at a blank wall, and its true loop moved the
        keyframe 1.24 m over 2.94 m), and turn it by at most loop_max_rotation_deg."""
        mp = self.map
        ids = sorted(k.id for k in mp.good_keyframes() if cand.id <= k.id <= kf.id)
        P = np.array([mp.keyframes[k].T_wc[:3, 3] for k in ids])
        path = float(np.sum(np.linalg.norm(np.diff(P, axis=0), axis=1))) if len(P) > 1 else 0.0
        p = kf.T_wc[:3, 3]
        moved = float(np.linalg.norm(S[:3, :3] @ p + S[:3, 3] - p))
        cos = np.clip((np.trace(S[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
        rot = float(np.degrees(np.arccos(cos)))
        allowed = (float(LOOP_MAX_DRIFT) +
                   2.0 * np.sin(np.radians(rot) / 2.0)) * max(path, 1.0)
        ok = moved <= allowed and rot <= float(LOOP_MAX_ROTATION_DEG)
        self.last_correction = (moved, rot)
        self._last_path = path
        if ok:
            ok = self.odometry_agrees(kf, cand, S)
        if not ok:
            self.rejected.append((kf.id, cand.id, moved, rot, path))
        return ok

    def correction_fits_map(self, kf, cand, S) -> bool:
        """The loop keyframe's neighbourhood (cand and its best covisibles, as the guided search
        of ComputeSim3) is projected into the current keyframe with and without the correction
        S, and each pose's matches are counted as SearchAndFuse would find them. Where the map
        drifted by more than the search window, the uncorrected projections miss their
        keypoints and the correction finds them: it must match at least LOOP_MAP_LARGE_RATIO x
        as many. Where the uncorrected pose already lines up with those points the map is
        consistent there, and a large correction is a look-alike verification (Lucas-Kanade locked onto a repeated texture 20 deg off, a
        BoW match on far points). A correction within the window (median LOOP_MAP_SMALL_PX)
        finds the same points as no correction, and needs LOOP_MAP_SMALL_RATIO x as many. Not in
        ORB-SLAM2, whose loops need three consistent BoW detections. ``correction_checks``
        keeps (kf id, cand id, matches uncorrected, matches corrected, median shift px, closed)."""
        if not LOOP_MAP_CHECK:
            return True
        mp = self.map
        local = [cand] + mp.best_covisibles(cand, 10)
        pts = np.unique(np.concatenate([k.valid_mp_ids(mp.mp_bad) for k in local]))
        poses = (kf.T_cw, kf.T_cw @ inv_T(S))
        # Fuse's test (TH_LOW, the reprojection chi2, any keypoint): a point counts where it lands
        # on a keypoint like its own, whether kf made a point of that keypoint or not
        n = [len(self.matcher.fuse(kf, mp, pts, T_cw=T, th=3.0)[0]) for T in poses]
        P0, P1 = (transform_points(T, mp.mp_pos[pts]) for T in poses)
        front = (P0[:, 2] > 0.1) & (P1[:, 2] > 0.1)
        f = np.array([kf.fx, kf.fy])
        shift = float(np.median(np.linalg.norm(
            (P1[front, :2] / P1[front, 2:] - P0[front, :2] / P0[front, 2:]) * f, axis=1))) \
            if np.any(front) else np.inf
        ratio = LOOP_MAP_SMALL_RATIO if shift <= LOOP_MAP_SMALL_PX else LOOP_MAP_LARGE_RATIO
        ok = n[1] >= float(ratio) * n[0]
        self.correction_checks.append((kf.id, cand.id, int(n[0]), int(n[1]), round(shift, 1), ok))
        return ok

    def odometry_agrees(self, kf, cand, S) -> bool:
        """Wheel-odometry check of a loop (True when either keyframe lacks odometry): the motion
        from ``cand`` to ``kf`` after the correction S may differ from the odometry's by at most
        LOOP_ODOM_GATE_M + LOOP_ODOM_GATE_REL x the odometry's path between them (translation of
        the camera) and LOOP_ODOM_GATE_DEG + LOOP_ODOM_GATE_DEG_PER_M x that path, unless it
        differed more before the correction (the loop then brings the map closer to the
        odometry). In a weakly textured room a BoW match 2 m away, on far points, fits a
        transform 0.3 m off, and the loop then moves a map that was right (RTAB-Map rejects such
        a loop by the odometry links' error after optimization, RGBD/OptimizeMaxError). The
        odometry is the calibrated one (OdometryCalibration: scale, rotation scale and yaw creep
        fitted against the tracked motion) where both keyframes carry it: over 37 m of a garage
        drive the raw one's yaw creep had it 3.7 m off the map before a loop and 2.9 m after, so
        it could not judge a loop that moved the keyframe 6.3 m.

        Whatever the bounds, the correction may move the keyframe away from the odometry's
        place by at most LOOP_ODOM_AWAY_M + LOOP_ODOM_AWAY_REL x the path, and turn it away from
        the odometry's heading by at most LOOP_ODOM_AWAY_DEG. Over a room's turns the calibrated
        odometry's heading can be 16-24 deg off after 18-25 m, so the bounds are wide; but a loop
        that moves the map towards the truth cannot raise the disagreement by more than its own
        correction, and a right map's loop is small."""
        if kf.T_odom_cam is None or cand.T_odom_cam is None:
            return True
        odo = odometry_motion(kf, cand)          # T_kf_cand as the wheels saw it
        before = kf.T_cw @ inv_T(cand.T_cw)
        after = kf.T_cw @ inv_T(S) @ inv_T(cand.T_cw)

        def off(T):
            D = inv_T(odo) @ T
            cos = np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
            return float(np.linalg.norm(D[:3, 3])), float(np.degrees(np.arccos(cos)))
        path = self._odometry_path(cand, kf)
        e0, a0 = off(before)
        e1, a1 = off(after)
        bound_m = float(LOOP_ODOM_GATE_M) + float(LOOP_ODOM_GATE_REL) * path
        bound_deg = float(LOOP_ODOM_GATE_DEG) + float(LOOP_ODOM_GATE_DEG_PER_M) * path
        ok = (e1 <= bound_m or e1 <= e0) and (a1 <= bound_deg or a1 <= a0) and \
            e1 - e0 <= float(LOOP_ODOM_AWAY_M) + float(LOOP_ODOM_AWAY_REL) * path and \
            a1 - a0 <= float(LOOP_ODOM_AWAY_DEG)
        self.odom_checks.append((kf.id, cand.id, round(path, 3), round(e0, 3), round(e1, 3),
                                 round(a0, 2), round(a1, 2), ok))
        return ok

    def _odometry_path(self, a, b) -> float:
        """Length of the odometry's camera path from keyframe ``a`` to ``b`` through the good
        keyframes between them that carry odometry."""
        mp = self.map
        P = [k.T_odom_cam[:3, 3] for k in (mp.keyframes.get(i) for i in range(a.id, b.id + 1))
             if k is not None and (not k.bad or k is a or k is b) and k.T_odom_cam is not None]
        return float(np.sum(np.linalg.norm(np.diff(np.array(P), axis=0), axis=1))) \
            if len(P) > 1 else 0.0

    def compute_se3(self, kf, cand):
        """World correction S (T_w_w') with cand's points ~ S * kf's points, and matched ids."""
        mp = self.map
        a = np.nonzero(kf.mp_ids >= 0)[0]
        a = a[~mp.mp_bad[kf.mp_ids[a]]]
        b = np.nonzero(cand.mp_ids >= 0)[0]
        b = b[~mp.mp_bad[cand.mp_ids[b]]]
        if len(a) < self.min_inliers or len(b) < self.min_inliers:
            return None
        self.bow(kf)
        self.bow(cand)
        node = self.voc.node_of_words
        # screened on the descriptors under the same vocabulary node (most candidates end here);
        # one that fits a transform there is matched over all descriptors, whose larger set
        # gives the transform its accuracy
        for full in (False, True):
            if full:
                d, nn = hamming_knn2(kf.desc[a], cand.desc[b])   # in C++, out of the GIL
                ok = (d[:, 0] <= TH_LOW) & (d[:, 0] < LOOP_NN_RATIO * d[:, 1])
                i, j = np.nonzero(ok)[0], nn[ok, 0]
                u = _unique_by(j, d[i, 0])
                i, j = i[u], j[u]
            else:
                i, j, _ = self.matcher.search_by_bow(
                    kf.desc[a], node(kf.bow_words[a], BOW_NODE_DEPTH),
                    cand.desc[b], node(cand.bow_words[b], BOW_NODE_DEPTH), LOOP_NN_RATIO)
            if len(i) < self.min_inliers:
                return None
            ca, cb = kf.mp_ids[a[i]], cand.mp_ids[b[j]]
            A, B = mp.mp_pos[ca], mp.mp_pos[cb]
            # distance threshold grows with depth (stereo depth error ~ z^2)
            z = np.linalg.norm(A - kf.T_wc[:3, 3], axis=1)
            th = 0.05 + 0.01 * z + 0.002 * z ** 2
            S, mask = ransac_se3(A, B, th)
            if S is None or mask.sum() < self.min_inliers:
                return None
        if LOOP_REPROJECTION_REFINE and \
                float(np.median(z[mask])) > kf.th_depth:   # far points: their 3-D fit is poor
            S = self.refine_by_reprojection(kf, S, a[i][mask], B[mask])
        ok, sig, turn = loop_rotation_check(
            A[mask], B[mask], S, float(LOOP_MAX_ROT_SIGMA_DEG),
            float(LOOP_ROT_SIGNIFICANCE),
            float(LOOP_ROT_SIGMA_CAP_DEG))
        if not ok:
            self.ill_conditioned.append((kf.id, cand.id, int(mask.sum()), sig, turn))
            return None
        # guided search: project the candidate's neighbourhood with the corrected pose
        local = [cand] + mp.best_covisibles(cand, 10)
        pts = np.unique(np.concatenate([k.valid_mp_ids(mp.mp_bad) for k in local]))
        # a temporary view of kf with the corrected pose, over its free keypoints only
        view = _KeyFrameView(kf, kf.T_cw @ inv_T(S))
        pts = pts[~np.isin(pts, kf.mp_ids)]
        n, _ = self.matcher.search_local_points(view, mp, pts, th=3.0)
        total = int(mask.sum()) + n
        if total < 40:
            return None
        new_kp = np.nonzero(view.mp_ids >= 0)[0]
        return S, ca[mask], cb[mask], new_kp, view.mp_ids[new_kp]

    def refine_by_reprojection(self, kf, S, kp_idx, Pw):
        """The loop correction S re-estimated from the images, as ORB-SLAM2's OptimizeSim3 does
        after its RANSAC: kf's corrected pose is the robust pose-only optimization of its
        keypoints ``kp_idx`` (pixels and stereo) against the loop side's map points ``Pw``,
        started at kf.T_cw S^-1. The 3-D fit weighs every point's stereo depth, which for far
        points is poor, so its rotation can be off by many degrees where the pixels hold it to
        about one (simulated garage seed 11: the start's far poster, 151 inliers, a 30 deg turn
        for 4 deg of drift, 3.4 deg after). Used when the matched points' median distance
        exceeds th_depth (near ones fit well in 3-D; refining them too made the sample's loop
        worse, 0.42 -> 1.13 % of the path). Returns the refined S, or S when too few inliers
        remain."""
        T_cw, _, n_inl = Optimizer.pose_from_points(
            kf, kf.T_cw @ inv_T(S), kf.uv[kp_idx], kf.ur[kp_idx], kf.octave[kp_idx],
            kf.inv_level_sigma2, Pw)
        if n_inl < self.min_inliers:
            return S
        return normalize_pose(inv_T(T_cw) @ kf.T_cw)

    def correct_loop(self, kf, cand, S, cur_ids, loop_ids, new_kp, new_ids,
                     n_match: Optional[int] = None, source: str = "bow",
                     found: Optional[int] = None) -> None:
        mp = self.map
        group = [kf] + [mp.keyframes[k] for k in kf.connections
                        if k in mp.keyframes and not mp.keyframes[k].bad]
        old_wc = {k.id: k.T_wc for k in mp.good_keyframes()}
        corr_wc = {k.id: S @ old_wc[k.id] for k in group}
        # points seen by the group follow the group's correction
        gpts = np.unique(np.concatenate([k.valid_mp_ids(mp.mp_bad) for k in group]))
        mp.mp_pos[gpts] = mp.mp_pos[gpts] @ S[:3, :3].T + S[:3, 3]
        for k in group:
            k.set_pose(inv_T(corr_wc[k.id]))
        # fuse: current-side duplicates become the loop-side points
        valid = (cur_ids >= 0) & (loop_ids >= 0)
        mp.replace_points(cur_ids[valid], loop_ids[valid])
        free = (kf.mp_ids[new_kp] < 0) & ~mp.mp_bad[new_ids]   # guided-search matches
        if np.any(free):
            mp.add_observations(kf, new_kp[free], new_ids[free])
        # SearchAndFuse: the loop side's points projected into every corrected keyframe of the
        # group, the loop side's copy surviving; otherwise the group keeps its duplicates, the
        # next keyframes track those, and the place is mapped (and closed) again on every pass
        loop_kfs = [cand] + mp.best_covisibles(cand, LOOP_FUSE_COVISIBLES)
        loop_pts = np.unique(np.concatenate([k.valid_mp_ids(mp.mp_bad) for k in loop_kfs]))
        for k in group:
            if not k.bad:
                ids_, kp_ = self.matcher.fuse(k, mp, loop_pts, th=LOOP_FUSE_RADIUS)
                mp.fuse_points(k, ids_, kp_, keep_given=True)
        kf.loop_edges.append(cand.id)
        cand.loop_edges.append(kf.id)
        # new covisibility links created by the fusion are loop edges too (ORB-SLAM2
        # LoopConnections): many edges, so the loop dominates the old chain in the pose graph
        before = {k.id: set(k.connections) for k in group}
        group_ids = set(before)
        loop_links = set()
        for k in group:
            mp.update_connections(k)
            for o in k.connections:
                if o not in before[k.id] and o not in group_ids:
                    loop_links.add((min(k.id, o), max(k.id, o)))
        # essential graph: spanning tree and strong covisibility edges measured before the
        # correction (relative poses inside the moved group are unchanged by S), loop edges now
        poses = {k.id: k.T_wc for k in mp.good_keyframes()}
        # edge information: with pose_graph_weights, shared map points / 100 (a link tracked on
        # a blank wall over 20 points is weaker than one over 500), loop edges by their inliers
        weighted = bool(POSE_GRAPH_WEIGHTS)

        def wt(n):
            return max(float(n), 15.0) / 100.0 if weighted else None
        n_loop = int(len(cur_ids)) + int(len(new_kp)) if n_match is None else int(n_match)
        edges = []
        for k in mp.good_keyframes():
            par = k.parent
            while par is not None and par.bad:
                par = par.parent
            if par is not None and par.id in poses and par.id != k.id:
                edges.append((par.id, k.id, inv_T(old_wc[par.id]) @ old_wc[k.id],
                              wt(k.connections.get(par.id, 15))))
            for o, w in k.connections.items():
                if o > k.id and w >= 100 and o in poses:
                    edges.append((k.id, o, inv_T(old_wc[k.id]) @ old_wc[o], wt(w)))
            for o in k.loop_edges:
                if o > k.id and o in poses:
                    edges.append((k.id, o, inv_T(poses[k.id]) @ poses[o], wt(n_loop)))
        for a_, b_ in loop_links:
            if a_ in poses and b_ in poses:
                edges.append((a_, b_, inv_T(poses[a_]) @ poses[b_],
                              wt(mp.keyframes[a_].connections.get(b_, 15))))
        # map points follow their reference keyframe: P' = T_new T_used^-1 P
        owner = np.full(mp.n, -1, dtype=np.int64)
        for k in group:   # points moved by S follow a group keyframe (ORB-SLAM2 mnCorrectedByKF)
            if k.bad:
                continue
            ids = k.valid_mp_ids(mp.mp_bad)
            ids = ids[np.isin(ids, gpts)]
            free = owner[ids] < 0
            owner[ids[free]] = k.id
        for k in sorted(mp.good_keyframes(), key=lambda k: k.id):
            ids = k.valid_mp_ids(mp.mp_bad)
            free = owner[ids] < 0
            owner[ids[free]] = k.id
        mp.n_loop_closures += 1
        self.last_loop_kf_id = kf.id
        self.loops.append((kf.id, cand.id))
        mc = [c for c in self.correction_checks if c[:2] == (kf.id, cand.id)]
        oc = [c for c in self.odom_checks if c[:2] == (kf.id, cand.id)]
        self.closed.append(dict(
            kf=kf.id, cand=cand.id, stamp=float(kf.stamp), source=source,
            found=kf.id if found is None else int(found),
            graph_ms=None, graph_edges=len(edges), graph_process=False, held_ms=None,
            moved_m=float(self.last_correction[0]),
            turned_deg=float(self.last_correction[1]), path_m=float(self._last_path),
            map_check=(mc[-1][2], mc[-1][3], mc[-1][4]) if mc else None,
            odometry_check=(oc[-1][3], oc[-1][4], oc[-1][2], oc[-1][5], oc[-1][6])
            if oc else None))
        self._graph_job = (poses, edges, cand.id, owner)
        if not self.system.threads:   # the caller holds the map lock: solve and apply now
            self.finish_correction(None)

    def finish_correction(self, worker) -> None:
        """The essential graph of the last correct_loop solved (in ``worker``'s child process when
        given: GTSAM keeps the GIL while it solves: 2.4 s for a graph of 700 keyframes) and
        applied. Called without the map lock in threaded mode, so tracking goes on meanwhile
        (ORB-SLAM2 stops it); the solution is then applied as a correction C = T_new T_used^-1
        of each keyframe's current pose and of its points, so a local BA or a keyframe made
        meanwhile is kept (new keyframes follow their nearest corrected ancestor, new points
        their reference keyframe, as after a global BA)."""
        job, self._graph_job = self._graph_job, None
        if job is None:
            return
        poses, edges, fixed, owner = job
        t_graph = time.perf_counter()
        if worker is not None:
            new = worker.run((poses, edges, fixed), {}, solver="essential_graph")
        else:
            new = Optimizer.optimize_essential_graph(poses, edges, fixed=fixed)
        self.closed[-1]["graph_ms"] = 1000.0 * (time.perf_counter() - t_graph)
        self.closed[-1]["graph_process"] = worker is not None and not worker.failed
        mp = self.map
        with mp.lock:
            C = {kid: new[kid] @ inv_T(poses[kid]) for kid in new}
            for k in sorted(mp.good_keyframes(), key=lambda k: k.id):
                if k.id in C:
                    continue
                a = k.parent
                while a is not None and a.id not in C:
                    a = a.parent
                if a is not None:
                    C[k.id] = C[a.id]
            n = mp.n
            if len(owner) < n:   # points made meanwhile follow their reference keyframe
                owner = np.concatenate([owner, mp.mp_ref_kf[len(owner):n]])
            owner = owner[:n].copy()
            owner[mp.mp_bad[:n]] = -1
            alive = np.nonzero(owner >= 0)[0]
            moved = []
            for kid in np.unique(owner[alive]).tolist():
                if kid not in C:
                    continue
                sel = alive[owner[alive] == kid]
                Ck = C[kid]
                mp.mp_pos[sel] = mp.mp_pos[sel] @ Ck[:3, :3].T + Ck[:3, 3]
                moved.append(sel)
            done = []
            for kid, Ck in C.items():
                k = mp.keyframes.get(kid)
                if k is not None and not k.bad:
                    k.set_pose(normalize_pose(inv_T(Ck @ k.T_wc)))
                    done.append(kid)
            if moved:
                mp.update_normal_and_depth(np.concatenate(moved))
            self.corrections.append(("loop_closure", {k: mp.keyframes[k].T_cw.copy()
                                                      for k in done}))


def bow_score_safe(a, b) -> float:
    return bow_score(a, b)


class _KeyFrameView:
    """A keyframe seen with another pose, for projection searches (free keypoints only)."""

    def __init__(self, kf, T_cw):
        for name in ("fx", "fy", "cx", "cy", "bf", "width", "height", "uv", "ur", "octave",
                     "desc", "angle", "scale", "log_scale", "nlevels", "grid", "N"):
            setattr(self, name, getattr(kf, name))
        self.T_cw = T_cw
        self.mp_ids = np.where(kf.mp_ids >= 0, -2, -1)   # occupied keypoints are not candidates
        self.outlier = np.zeros(kf.N, dtype=bool)

    @property
    def T_wc(self):
        return inv_T(self.T_cw)
