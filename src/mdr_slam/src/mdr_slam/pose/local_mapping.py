"""LocalMapping: keyframe processing, map point creation and culling, local BA, keyframe culling.

ORB-SLAM2 LocalMapping::Run per new keyframe: ProcessNewKeyFrame (observations, covisibility),
MapPointCulling (recent points found in < 25 % of the frames that should see them, or seen by too
few keyframes, are removed), CreateNewMapPoints (triangulation of unmatched keypoints with the 10
best covisible keyframes under the epipolar constraint, parallax and scale-consistency tests; the
stereo depth is used instead when its parallax is larger), SearchInNeighbors (duplicates fused
with the neighbours' points, where the keyframe revisits a place), LocalBundleAdjustment and
KeyFrameCulling (a keyframe whose points are 90 % seen at the same or finer scale by >= 3 other
keyframes is redundant).

It runs in a thread (System(threads=True)) or synchronously inside System.track (threads=False,
the deterministic offline runner).

Cost (CPU per keyframe on the 752x480 sample, measured under load):
local BA dominates, so its rounds end once converged (``BA_TOL``). The triangulation search
compares every pair against the epipolar line (vectorized); ORB-SLAM2's prefilter by vocabulary
node saved only ~15 % of this step here and made the ATE worse.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Optional

import numpy as np

from .ba_process import BAWorker
from .optimizer import CHI2_MONO, CHI2_STEREO, Optimizer, project_residuals
from .matcher import ORBmatcher
from .orb import TH_LOW, hamming
from .tracking import REVISIT_MIN_AGE

__all__ = ["LocalMapping"]

# Tuned internals (ORB-SLAM2 LocalMapping's counterpart in brackets)
BA_COVISIBLE = 10              # covisible keyframes optimised with the new one (LocalBundleAdjustment: all)
BA_ITERATIONS = 8              # local BA iterations per round (5 + 10 after outlier removal)
BA_TOL = 1e-3                  # a round ends once a step lowers the robust cost by less than this share of it
TRIANGULATION_NEIGHBOURS = 10  # best covisible keyframes a new keyframe triangulates with (CreateNewMapPoints: 10)
FUSE_NEIGHBOURS = 10           # best covisibles a new keyframe fuses its points with (SearchInNeighbors: 10) ...
FUSE_SECOND_NEIGHBOURS = 5     # ... and their best covisibles (5)


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def triangulate(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of normalized/pixel points with 3x4 projections (N, 3);
    vectorized SVD over all matches (ORB-SLAM2 Triangulate)."""
    A = np.stack([x1[:, 0:1] * P1[2] - P1[0], x1[:, 1:2] * P1[2] - P1[1],
                  x2[:, 0:1] * P2[2] - P2[0], x2[:, 1:2] * P2[2] - P2[1]], axis=1)
    _, _, Vt = np.linalg.svd(A)
    X = Vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :3] / X[:, 3:4]


class LocalMapping:
    def __init__(self, system, cfg):
        self.system = system
        self.map = system.map
        self.cfg = cfg            # TrackerConfig
        self.queue = deque()
        self.cv = threading.Condition()
        self.abort_ba = False
        self.idle = True
        self.stop_flag = False
        self.recent_points = np.zeros(0, dtype=np.int64)
        self.corrections = []      # (reason, {kf_id: T_cw}) waiting for System.track to report
        self.thread: Optional[threading.Thread] = None
        self.n_processed = 0
        self.last_ba_ms = 0.0
        self.ba_worker = None      # ba_process.BAWorker: local BA in a child process (threads only)
        self.matcher = ORBmatcher()
        self.n_fused = 0           # duplicate points fused or observations added (SearchInNeighbors)

    # ------------------------------------------------------------------ queue / thread
    def insert_keyframe(self, kf) -> None:
        with self.cv:
            self.queue.append(kf)
            self.abort_ba = True
            self.cv.notify()

    def queue_size(self) -> int:
        return len(self.queue)

    def accept_keyframes(self) -> bool:
        return self.idle and not self.queue

    def wait_queue_below(self, n: int, timeout: float = 1.0) -> bool:
        """Block (without the map lock) until fewer than ``n`` keyframes wait, or timeout."""
        end = time.monotonic() + timeout
        while len(self.queue) >= n and time.monotonic() < end:
            if self.thread is None or not self.thread.is_alive():
                return False
            time.sleep(0.005)
        return len(self.queue) < n

    def interrupt_ba(self) -> None:
        self.abort_ba = True

    def start(self) -> None:
        if self.cfg.ba_process:
            self.ba_worker = BAWorker()
            self.ba_worker.prewarm()
        self.thread = threading.Thread(target=self._run, name="LocalMapping", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            with self.cv:
                while not self.queue and not self.stop_flag:
                    self.idle = True
                    self.cv.wait(0.1)
                if self.stop_flag and not self.queue:
                    return
                self.idle = False
            self.run_once()

    def stop(self) -> None:
        with self.cv:
            self.stop_flag = True
            self.cv.notify()
        if self.thread is not None:
            self.thread.join(30.0)
        if self.ba_worker is not None:
            self.ba_worker.close()
            self.ba_worker = None

    def spin_sync(self) -> None:
        """Synchronous mode: process every queued keyframe now."""
        while self.queue:
            self.idle = False
            self.run_once()
        self.idle = True

    # ------------------------------------------------------------------ one keyframe
    def run_once(self) -> None:
        with self.cv:
            if not self.queue:
                return
            kf = self.queue.popleft()
            self.abort_ba = False
        mp = self.map
        pause = self.system.yield_to_tracking
        pause()
        with mp.lock:
            if kf.bad:
                return
            self.process_new_keyframe(kf)
            self.map_point_culling(kf)
        pause()
        # the epipolar search reads keyframes only; it takes the map lock just to add points, so
        # tracking is not blocked behind it (it held the lock ~250 ms per keyframe under load)
        self.create_new_map_points(kf)
        if not self.queue:
            pause()
            with mp.lock:
                if not kf.bad and self.revisits(kf):
                    self.search_in_neighbors(kf)
        if not self.queue and len(mp.keyframes) > 2 and self.cfg.local_ba:
            t0 = time.perf_counter()

            def abort():   # per LM iteration, without the map lock
                pause()
                return self.abort_ba and self.system.threads
            pause()
            moved, _ = Optimizer.local_bundle_adjustment(
                kf, mp, n_covisible=BA_COVISIBLE, iterations=BA_ITERATIONS,
                abort=abort, worker=self.ba_worker, tol=BA_TOL)
            self.last_ba_ms = 1000.0 * (time.perf_counter() - t0)
            pause()
            with mp.lock:
                if moved:
                    self.corrections.append(("local_ba", {k: mp.keyframes[k].T_cw.copy()
                                                          for k in moved}))
                self.keyframe_culling(kf)
        with mp.lock:
            mp.update_connections(kf)
        self.system.loop_closing_insert(kf)
        self.n_processed += 1

    def process_new_keyframe(self, kf) -> None:
        """Observations of the tracked points (the new ones were added at creation)."""
        mp = self.map
        idx = np.nonzero(kf.mp_ids >= 0)[0]
        ids = kf.mp_ids[idx]
        tracked = (mp.mp_first_kf[ids] != kf.id) & ~mp.mp_bad[ids]
        dead = idx[mp.mp_bad[ids]]
        kf.mp_ids[dead] = -1
        if np.any(tracked):
            # a point can be matched by two keypoints only once per keyframe
            np.add.at(mp.mp_nobs, ids[tracked], np.where(kf.ur[idx[tracked]] >= 0, 2, 1))
            mp.update_normal_and_depth(ids[tracked])
        created = ids[mp.mp_first_kf[ids] == kf.id]
        self.recent_points = np.concatenate([self.recent_points, created])
        mp.update_connections(kf)

    def map_point_culling(self, kf) -> None:
        mp = self.map
        r = self.recent_points
        if len(r) == 0:
            return
        th_obs = 3   # stereo (ORB-SLAM2 cnThObs)
        age = kf.id - mp.mp_first_kf[r]
        ratio = mp.mp_found[r] / np.maximum(mp.mp_visible[r], 1)
        bad = ~mp.mp_bad[r] & ((ratio < 0.25) | ((age >= 2) & (mp.mp_nobs[r] <= th_obs)))
        mp.set_bad_points(r[bad])
        keep = ~mp.mp_bad[r] & (age < 3)
        self.recent_points = r[keep]

    def create_new_map_points(self, kf) -> int:
        """Triangulate unmatched keypoints of ``kf`` with its best covisible keyframes."""
        mp = self.map
        with mp.lock:
            neigh = mp.best_covisibles(kf, TRIANGULATION_NEIGHBOURS)
        R1, t1 = kf.T_cw[:3, :3], kf.T_cw[:3, 3]
        O1 = kf.T_wc[:3, 3]
        K = np.array([[kf.fx, 0, kf.cx], [0, kf.fy, kf.cy], [0, 0, 1.0]])
        Kinv = np.linalg.inv(K)
        ratio_factor = 1.5 * kf.scale[1] if len(kf.scale) > 1 else 1.8
        total = 0
        live = bool(getattr(self.system, "threads", False))
        for n_done, kf2 in enumerate(neigh):
            if live and n_done > 0 and self.queue:
                break   # a newer keyframe waits (ORB-SLAM2 CheckNewKeyFrames): it comes first
            if kf2.bad:
                continue
            O2 = kf2.T_wc[:3, 3]
            if np.linalg.norm(O2 - O1) < kf.baseline:
                continue
            f1 = np.nonzero(kf.mp_ids < 0)[0]
            f2 = np.nonzero(kf2.mp_ids < 0)[0]
            if len(f1) == 0 or len(f2) == 0:
                continue
            R2, t2 = kf2.T_cw[:3, :3], kf2.T_cw[:3, 3]
            R12 = R1 @ R2.T
            t12 = -R1 @ R2.T @ t2 + t1
            F12 = Kinv.T @ _skew(t12) @ R12 @ Kinv     # x1^T F12 x2 = 0
            x1 = np.column_stack([kf.uv[f1], np.ones(len(f1))])
            x2 = np.column_stack([kf2.uv[f2], np.ones(len(f2))])
            # float32: pixel distances need no more, and the (n1, n2) product below is this
            # step's cost (KITTI: ~1000 x 1000 per neighbour; a quarter faster than float64)
            lines = (x1 @ F12).astype(np.float32)              # epipolar lines in image 2
            sig2 = 3.84 * kf2.scale[kf2.octave[f2]] ** 2
            # point-to-line distances |l . x2| / |l_xy| of all pairs, in place on the one
            # (n1, n2) product (no squared or broadcast temporaries: ~2.5x faster)
            dist_l = lines @ x2.T.astype(np.float32)       # (n1, n2)
            with np.errstate(divide="ignore"):
                dist_l *= (1.0 / np.sqrt(lines[:, 0] ** 2 + lines[:, 1] ** 2))[:, None]
            np.abs(dist_l, out=dist_l)
            pi, pj = np.nonzero(dist_l < np.sqrt(sig2).astype(np.float32)[None, :])
            # Hamming only on the pairs that satisfy the epipolar constraint (a few %)
            if len(pi) == 0:
                continue
            dist = hamming(kf.desc[f1[pi]], kf2.desc[f2[pj]])
            keep = dist <= TH_LOW
            pi, pj, dist = pi[keep], pj[keep], dist[keep]
            if len(pi) == 0:
                continue
            o = np.lexsort((dist, pi))               # best per kf keypoint
            first = np.r_[True, pi[o][1:] != pi[o][:-1]]
            i, j, dbest = pi[o][first], pj[o][first], dist[o][first]
            o = np.lexsort((dbest, j))               # then one per kf2 keypoint
            first = np.r_[True, j[o][1:] != j[o][:-1]]
            i, j = i[o][first], j[o][first]
            a, b = f1[i], f2[j]
            # rays and parallax
            r1 = (np.column_stack([kf.uv[a], np.ones(len(a))]) @ Kinv.T) @ R1   # world dirs
            r2 = (np.column_stack([kf2.uv[b], np.ones(len(b))]) @ Kinv.T) @ R2
            cos_rays = np.einsum("ij,ij->i", r1, r2) / (np.linalg.norm(r1, axis=1) *
                                                          np.linalg.norm(r2, axis=1))
            st1, st2 = kf.depth[a] > 0, kf2.depth[b] > 0
            with np.errstate(divide="ignore", invalid="ignore"):
                cos_st1 = np.where(st1, np.cos(2 * np.arctan2(kf.baseline / 2, kf.depth[a])), 2.0)
                cos_st2 = np.where(st2, np.cos(2 * np.arctan2(kf2.baseline / 2, kf2.depth[b])), 2.0)
            cos_st = np.minimum(cos_st1, cos_st2)
            use_tri = (cos_rays > 0) & (cos_rays < cos_st) & (st1 | st2 | (cos_rays < 0.9998))
            use_s1 = ~use_tri & st1 & (cos_st1 < cos_st2)
            use_s2 = ~use_tri & ~use_s1 & st2 & (cos_st2 <= cos_st1)
            X = np.full((len(a), 3), np.nan)
            if np.any(use_tri):
                n1 = np.column_stack([kf.uv[a[use_tri]], np.ones(np.count_nonzero(use_tri))]) @ Kinv.T
                n2 = np.column_stack([kf2.uv[b[use_tri]], np.ones(np.count_nonzero(use_tri))]) @ Kinv.T
                X[use_tri] = triangulate(kf.T_cw[:3], kf2.T_cw[:3], n1[:, :2], n2[:, :2])
            if np.any(use_s1):
                X[use_s1] = kf.stereo_points_world(a[use_s1])
            if np.any(use_s2):
                X[use_s2] = kf2.stereo_points_world(b[use_s2])
            good = np.all(np.isfinite(X), axis=1)
            a, b, X, st1, st2 = a[good], b[good], X[good], st1[good], st2[good]
            if len(a) == 0:
                continue
            ok = np.ones(len(a), bool)
            for k_, idx_, st_ in ((kf, a, st1), (kf2, b, st2)):
                obs = np.column_stack([k_.uv[idx_], np.where(st_, k_.ur[idx_], 0.0)])
                e, Pc = project_residuals(k_.T_cw, X, obs, st_, k_.fx, k_.fy, k_.cx, k_.cy, k_.bf)
                chi2 = k_.inv_level_sigma2[k_.octave[idx_]] * np.einsum("ij,ij->i", e, e)
                ok &= (Pc[:, 2] > 0) & (chi2 <= np.where(st_, CHI2_STEREO, CHI2_MONO))
            d1 = np.linalg.norm(X - O1, axis=1)
            d2 = np.linalg.norm(X - O2, axis=1)
            # scale consistency: a point seen larger (higher octave) in kf must be closer to it
            ratio_dist = d2 / np.maximum(d1, 1e-9)
            ratio_oct = kf.scale[kf.octave[a]] / kf2.scale[kf2.octave[b]]
            ok &= (d1 > 0) & (d2 > 0)
            ok &= ~((ratio_dist * ratio_factor < ratio_oct) | (ratio_dist > ratio_oct * ratio_factor))
            a, b, X = a[ok], b[ok], X[ok]
            with mp.lock:
                # keypoints may have been taken by an earlier neighbour round (or another
                # thread while the search ran without the lock): re-check
                if kf.bad or kf2.bad:
                    continue
                free = (kf.mp_ids[a] < 0) & (kf2.mp_ids[b] < 0)
                a, b, X = a[free], b[free], X[free]
                if len(a) == 0:
                    continue
                ids = mp.add_points(X, kf.desc[a], kf, a)
                mp.add_observations(kf2, b, ids)
                mp.mp_visible[ids] = 2
                mp.mp_found[ids] = 2
            self.recent_points = np.concatenate([self.recent_points, ids])
            total += len(a)
        return total

    def revisits(self, kf) -> bool:
        """Whether ``kf`` is covisible with a keyframe of an earlier pass (``REVISIT_MIN_AGE`` s
        older): a place seen again, where it may hold a second copy of the points."""
        return any(k.stamp <= kf.stamp - REVISIT_MIN_AGE
                   for k in self.map.best_covisibles(kf, FUSE_NEIGHBOURS))

    def search_in_neighbors(self, kf) -> int:
        """Fuse duplicate map points between ``kf`` and its neighbours (ORB-SLAM2
        SearchInNeighbors): ``kf``'s points are projected into its best covisibles and theirs
        (second neighbours), and all their points into ``kf``; a match on a free keypoint adds
        the observation, one on a keypoint with another point merges the two. Without it a place
        seen again keeps a second copy of its points: its keyframes share too few points to be
        covisible or redundant, and the map grows with every pass. Run where the keyframe
        revisits a place (``revisits``): on a first pass there are few duplicates to fuse, and
        fusing there made the forward drives (KITTI) less accurate. Returns the fusions made."""
        mp = self.map
        targets = {}
        for k in mp.best_covisibles(kf, FUSE_NEIGHBOURS):
            if k.bad or k is kf:
                continue
            targets[k.id] = k
            for k2 in mp.best_covisibles(k, FUSE_SECOND_NEIGHBOURS):
                if not k2.bad and k2 is not kf:
                    targets.setdefault(k2.id, k2)
        if not targets:
            return 0
        n = 0
        for k in targets.values():
            ids, kp = self.matcher.fuse(k, mp, kf.valid_mp_ids(mp.mp_bad))
            n += mp.fuse_points(k, ids, kp)
        cand = np.unique(np.concatenate([k.valid_mp_ids(mp.mp_bad) for k in targets.values()]))
        ids, kp = self.matcher.fuse(kf, mp, cand)
        n += mp.fuse_points(kf, ids, kp)
        if n:
            mp.update_normal_and_depth(kf.valid_mp_ids(mp.mp_bad))
            mp.update_connections(kf)
        self.n_fused += n
        return n

    def keyframe_culling(self, kf) -> int:
        """Cull covisible keyframes whose points are 90 % redundant (seen by >= 3 others at the
        same or a finer scale); only close (stereo) points count, as ORB-SLAM2 does for stereo."""
        mp = self.map
        n_culled = 0
        local = mp.best_covisibles(kf, 30)
        lookup = np.full(mp.n + 1, -1, dtype=np.int64)   # point id -> index in k; [-1]: none
        for k in local:
            if k.id == 0 or k.bad or k is kf:
                continue
            sel = np.nonzero(k.mp_ids >= 0)[0]
            sel = sel[~mp.mp_bad[k.mp_ids[sel]]]
            sel = sel[(k.depth[sel] > 0) & (k.depth[sel] < k.th_depth)]
            if len(sel) == 0:
                continue
            ids = k.mp_ids[sel]
            lvl = k.octave[sel]
            sel_ok = mp.mp_nobs[ids] > 3
            count = np.zeros(len(ids), dtype=np.int64)
            others = [o for o in (mp.keyframes.get(kid) for kid in k.connections)
                      if o is not None and not o.bad]
            if others:
                # every connection's observations in one gather (a point k saw twice counts at
                # its last keypoint)
                lookup[ids] = np.arange(len(ids))
                pos = lookup[np.concatenate([o.mp_ids for o in others])]
                hit = pos >= 0
                pos = pos[hit]
                finer = np.concatenate([o.octave for o in others])[hit] <= lvl[pos] + 1
                count = np.bincount(pos[finer], minlength=len(ids))
                lookup[ids] = -1
            redundant = int(np.count_nonzero(sel_ok & (count >= 3)))
            if redundant > 0.9 * len(ids):
                mp.set_bad_keyframe(k)
                n_culled += 1
        return n_culled
