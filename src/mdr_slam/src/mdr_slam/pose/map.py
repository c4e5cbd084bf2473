"""Map, KeyFrame and MapPoint (ORB-SLAM2's Map, KeyFrame, MapPoint).

Map points live in a struct of arrays inside :class:`Map` (position, descriptor, viewing normal,
scale-invariance distances, visible/found counters, number of observations, bad flag) so that
projection searches and bundle adjustment gather them with fancy indexing instead of Python loops;
:class:`MapPoint` is a thin view (the class name ORB-SLAM2 readers look for). Observations are kept
on the keyframe side (``KeyFrame.mp_ids``: the map point id of each keypoint, -1 if none), which
is what every vectorized query needs; "which keyframes see point p" is a vectorized np.isin.
"""
from __future__ import annotations

import threading
from types import SimpleNamespace
from typing import Dict, List, Optional

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import inv_T, transform_points
from .frame import FeatureGrid
from .optimizer import normalize_pose

__all__ = ["Map", "KeyFrame", "MapPoint"]


class KeyFrame:
    """A frame kept in the map: features, stereo depths, pose, its map points, spanning tree."""

    def __init__(self, kf_id: int, frame):
        self.id = kf_id
        self.frame_id = frame.id
        self.stamp = frame.stamp
        self.uv = frame.uv
        self.octave = frame.octave
        self.angle = frame.angle
        self.desc = frame.desc
        self.ur = frame.ur
        self.depth = frame.depth
        self.N = frame.N
        self.fx, self.fy, self.cx, self.cy, self.bf = frame.fx, frame.fy, frame.cx, frame.cy, frame.bf
        self.baseline = frame.baseline
        self.th_depth = frame.th_depth
        self.scale = frame.scale
        self.inv_level_sigma2 = frame.inv_level_sigma2
        self.log_scale, self.nlevels = frame.log_scale, frame.nlevels
        self.width, self.height = frame.width, frame.height
        self._tree = None
        self._grid = None
        self.mp_ids = frame.mp_ids.copy()
        # per-axis texture weights of the keypoints (Frame.texture_weights), for the BAs
        self.tex_w = frame.texture_weights(np.arange(frame.N)) \
            if getattr(frame, "texture_tau", 0.0) > 0.0 else None
        self.T_cw = frame.T_cw.copy()
        # the robot's wheel odometry at this keyframe (T_odom_cam), None without it or once loaded:
        # a loop correction is checked against it (LoopClosing.odometry_agrees)
        T_odom_cam = getattr(frame, "T_odom_cam", None)
        self.T_odom_cam = None if T_odom_cam is None else np.array(T_odom_cam, float)
        # ... and the same with its fitted errors taken out (OdometryCalibration's chain), or None
        T_cal = getattr(frame, "T_odom_cam_calibrated", None)
        self.T_odom_cam_calibrated = None if T_cal is None else np.array(T_cal, float)
        self.planar = None                            # PlanarMotion (Map.new_keyframe) or None
        self.bad = False
        self.parent: Optional["KeyFrame"] = None      # spanning tree (highest covisibility)
        self.T_cp: Optional[np.ndarray] = None        # pose relative to parent once culled
        self.loop_edges: List[int] = []
        self.connections: Dict[int, int] = {}         # covisibility graph: {kf_id: weight}
        self.bow = None                               # sparse BoW vector (word ids, weights)
        self.bow_words = None

    @classmethod
    def from_fields(cls, kf_id: int, frame_id: int, stamp: float, uv, octave, angle, desc, ur,
                    depth, mp_ids, T_cw, fx: float, fy: float, cx: float, cy: float, bf: float,
                    baseline: float, th_depth: float, scale, inv_level_sigma2, log_scale: float,
                    nlevels: int, width: int, height: int, tex_w=None) -> "KeyFrame":
        """A keyframe rebuilt from saved fields (pose.map_io) rather than from a Frame. It goes
        through ``__init__`` with a stand-in frame, so attributes added there later get their
        defaults here too; the caller sets bad, parent, T_cp, loop_edges and connections."""
        uv = np.asarray(uv, np.float32).reshape(-1, 2)
        fake = SimpleNamespace(
            id=int(frame_id), stamp=float(stamp), uv=uv, octave=np.asarray(octave, np.int64),
            angle=np.asarray(angle, np.float32), desc=np.asarray(desc, np.uint8).reshape(-1, 32),
            ur=np.asarray(ur, np.float32), depth=np.asarray(depth, np.float32), N=len(uv),
            fx=float(fx), fy=float(fy), cx=float(cx), cy=float(cy), bf=float(bf),
            baseline=float(baseline), th_depth=float(th_depth),
            scale=np.asarray(scale, np.float64),
            inv_level_sigma2=np.asarray(inv_level_sigma2, np.float64),
            log_scale=float(log_scale), nlevels=int(nlevels), width=int(width),
            height=int(height), mp_ids=np.asarray(mp_ids, np.int64), texture_tau=0.0,
            T_cw=np.asarray(T_cw, np.float64))
        kf = cls(int(kf_id), fake)
        kf.tex_w = None if tex_w is None else np.asarray(tex_w, np.float32).reshape(-1, 2)
        return kf

    @property
    def T_wc(self) -> np.ndarray:
        return inv_T(self.T_cw)

    @property
    def tree(self):
        """k-d tree of the keypoints (nearest keypoint of a pixel: loop point fusion)."""
        if self._tree is None:
            self._tree = cKDTree(self.uv.astype(np.float64))
        return self._tree

    @property
    def grid(self):
        """The keypoints' FeatureGrid (ORBmatcher projection searches into a keyframe)."""
        if self._grid is None:
            self._grid = FeatureGrid(self.uv)
        return self._grid

    def set_pose(self, T_cw: np.ndarray) -> None:
        T_cw = normalize_pose(np.asarray(T_cw, dtype=float))
        self.T_cw = T_cw if self.planar is None else self.planar.project(T_cw)

    def stereo_points_world(self, idx: np.ndarray) -> np.ndarray:
        z = self.depth[idx].astype(float)
        P = np.stack([(self.uv[idx, 0] - self.cx) * z / self.fx,
                      (self.uv[idx, 1] - self.cy) * z / self.fy, z], axis=1)
        return transform_points(self.T_wc, P)

    def valid_mp_ids(self, mp_bad: np.ndarray) -> np.ndarray:
        ids = self.mp_ids[self.mp_ids >= 0]
        return ids[~mp_bad[ids]]


class MapPoint:
    """View of one map point of a :class:`Map` (ORB-SLAM2 MapPoint accessors)."""

    def __init__(self, map_: "Map", mp_id: int):
        self.map = map_
        self.id = int(mp_id)

    @property
    def position(self) -> np.ndarray:
        return self.map.mp_pos[self.id].copy()

    @property
    def descriptor(self) -> np.ndarray:
        return self.map.mp_desc[self.id].copy()

    @property
    def is_bad(self) -> bool:
        return bool(self.map.mp_bad[self.id])

    @property
    def found_ratio(self) -> float:
        return float(self.map.mp_found[self.id]) / max(1.0, float(self.map.mp_visible[self.id]))


class Map:
    """Keyframes plus the struct-of-arrays map points; one lock guards both (ORB-SLAM2 mMutexMapUpdate)."""

    def __init__(self, capacity: int = 4096):
        self.lock = threading.RLock()
        self.keyframes: Dict[int, KeyFrame] = {}
        self.next_kf_id = 0
        self.n = 0
        self._alloc(capacity)
        self.n_loop_closures = 0
        self.loaded_next_kf_id = 0    # keyframes with smaller ids were loaded (pose.map_io)
        self.planar = None            # PlanarMotion: every keyframe pose kept on the floor plane

    def _alloc(self, cap: int) -> None:
        def grow(name, shape, dtype, fill=0):
            old = getattr(self, name, None)
            a = np.full((cap,) + shape, fill, dtype=dtype)
            if old is not None:
                a[: len(old)] = old
            setattr(self, name, a)
        grow("mp_pos", (3,), np.float64)
        grow("mp_desc", (32,), np.uint8)
        grow("mp_normal", (3,), np.float64)
        grow("mp_min_dist", (), np.float64)
        grow("mp_max_dist", (), np.float64)
        grow("mp_visible", (), np.int32)
        grow("mp_found", (), np.int32)
        grow("mp_nobs", (), np.int32)
        grow("mp_first_kf", (), np.int64, -1)
        grow("mp_ref_kf", (), np.int64, -1)
        grow("mp_bad", (), bool, True)
        self.capacity = cap

    # ---------------------------------------------------------------- map points
    def add_points(self, pos: np.ndarray, desc: np.ndarray, kf: KeyFrame,
                   kp_idx: np.ndarray) -> np.ndarray:
        """New map points observed by ``kf`` at keypoints ``kp_idx``; returns their ids."""
        m = len(pos)
        if self.n + m > self.capacity:
            self._alloc(max(2 * self.capacity, self.n + m + 1024))
        ids = np.arange(self.n, self.n + m)
        self.n += m
        self.mp_pos[ids] = pos
        self.mp_desc[ids] = desc
        self.mp_visible[ids] = 1
        self.mp_found[ids] = 1
        self.mp_nobs[ids] = 0
        self.mp_first_kf[ids] = kf.id
        self.mp_ref_kf[ids] = kf.id
        self.mp_bad[ids] = False
        self.add_observations(kf, kp_idx, ids)
        self.update_normal_and_depth(ids)
        return ids

    def add_observations(self, kf: KeyFrame, kp_idx: np.ndarray, ids: np.ndarray) -> None:
        """kf sees map points ``ids`` at keypoints ``kp_idx`` (stereo observations count 2, as
        ORB-SLAM2's nObs, which the culling thresholds are written for)."""
        kp_idx = np.asarray(kp_idx, dtype=np.int64)
        ids = np.asarray(ids, dtype=np.int64)
        prev = kf.mp_ids[kp_idx]
        had = prev >= 0
        if np.any(had):
            np.add.at(self.mp_nobs, prev[had], -np.where(kf.ur[kp_idx[had]] >= 0, 2, 1))
        kf.mp_ids[kp_idx] = ids
        np.add.at(self.mp_nobs, ids, np.where(kf.ur[kp_idx] >= 0, 2, 1))

    def erase_observations(self, kf: KeyFrame, kp_idx: np.ndarray) -> None:
        kp_idx = np.asarray(kp_idx, dtype=np.int64)
        ids = kf.mp_ids[kp_idx]
        ok = ids >= 0
        np.add.at(self.mp_nobs, ids[ok], -np.where(kf.ur[kp_idx[ok]] >= 0, 2, 1))
        kf.mp_ids[kp_idx] = -1
        dead = ids[ok][self.mp_nobs[ids[ok]] <= 2]
        self.set_bad_points(dead)

    def set_bad_points(self, ids: np.ndarray) -> None:
        """Mark points bad and remove them from every keyframe (ORB-SLAM2 MapPoint::SetBadFlag)."""
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0:
            return
        self.mp_bad[ids] = True
        dead = np.zeros(self.n + 1, dtype=bool)   # one slot more: index -1 (no point) stays False
        dead[ids] = True
        for kf in self.keyframes.values():   # a lookup per keyframe, not np.isin's sort
            if not kf.bad:                   # a culled keyframe has no observations left
                kf.mp_ids[dead[kf.mp_ids]] = -1
        self.mp_nobs[ids] = 0

    def observers(self, mp_id: int) -> List[KeyFrame]:
        return [kf for kf in self.keyframes.values() if not kf.bad and np.any(kf.mp_ids == mp_id)]

    def update_normal_and_depth(self, ids: np.ndarray) -> None:
        """Mean viewing direction and scale-invariance distance range of points ``ids`` from their
        reference keyframe's observation (ORB-SLAM2 UpdateNormalAndDepth, with the reference view)."""
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0:
            return
        for kf_id in np.unique(self.mp_ref_kf[ids]):
            kf = self.keyframes.get(int(kf_id))
            sel = ids[self.mp_ref_kf[ids] == kf_id]
            if kf is None:
                continue
            kp = np.full(self.n, -1, dtype=np.int64)
            m = kf.mp_ids >= 0
            kp[kf.mp_ids[m]] = np.nonzero(m)[0]
            k = kp[sel]
            sel, k = sel[k >= 0], k[k >= 0]
            if len(sel) == 0:
                continue
            C = kf.T_wc[:3, 3]
            v = self.mp_pos[sel] - C
            dist = np.linalg.norm(v, axis=1)
            self.mp_normal[sel] = v / np.maximum(dist, 1e-9)[:, None]
            lvl_scale = kf.scale[kf.octave[k]]
            self.mp_max_dist[sel] = dist * lvl_scale
            self.mp_min_dist[sel] = self.mp_max_dist[sel] / kf.scale[-1]

    def predict_scale(self, ids: np.ndarray, dist: np.ndarray, log_scale: float,
                      nlevels: int) -> np.ndarray:
        """Pyramid level where a point at ``dist`` should be detected (PredictScale)."""
        ratio = self.mp_max_dist[ids] / np.maximum(dist, 1e-9)
        lvl = np.ceil(np.log(np.maximum(ratio, 1e-9)) / log_scale).astype(int)
        return np.clip(lvl, 0, nlevels - 1)

    def replace_points(self, old: np.ndarray, new: np.ndarray) -> None:
        """Fuse duplicates: every observation of ``old[i]`` becomes one of ``new[i]`` (ORB-SLAM2
        MapPoint::Replace), unless that keyframe already sees ``new[i]``."""
        old = np.asarray(old, dtype=np.int64)
        new = np.asarray(new, dtype=np.int64)
        keep = (old != new) & ~self.mp_bad[old] & ~self.mp_bad[new]
        old, new = old[keep], new[keep]
        if len(old) == 0:
            return
        lut = np.arange(self.n + 1, dtype=np.int64)   # one slot more: index -1 maps to itself
        lut[-1] = -1
        lut[old] = new
        is_old = np.zeros(self.n + 1, dtype=bool)
        is_old[old] = True
        for kf in self.keyframes.values():
            if kf.bad:     # a culled keyframe has no observations left
                continue
            kp = np.nonzero(is_old[kf.mp_ids])[0]
            if len(kp) == 0:
                continue
            tgt = lut[kf.mp_ids[kp]]
            mine = np.zeros(self.n + 1, dtype=bool)
            mine[kf.mp_ids] = True
            mine[-1] = False
            already = mine[tgt]
            # two old points of this keyframe with the same target: the first keypoint keeps it
            _, first = np.unique(tgt, return_index=True)
            dup = np.ones(len(tgt), dtype=bool)
            dup[first] = False
            already |= dup
            kf.mp_ids[kp[~already]] = tgt[~already]
            kf.mp_ids[kp[already]] = -1
            np.add.at(self.mp_nobs, tgt[~already], np.where(kf.ur[kp[~already]] >= 0, 2, 1))
        self.mp_visible[new] += self.mp_visible[old]
        self.mp_found[new] += self.mp_found[old]
        self.mp_bad[old] = True
        self.mp_nobs[old] = 0

    def fuse_points(self, kf: KeyFrame, ids: np.ndarray, kp: np.ndarray,
                    keep_given: bool = False) -> int:
        """Apply ORBmatcher.fuse matches (point ``ids[i]`` at keypoint ``kp[i]`` of ``kf``): a
        free keypoint gains the observation; one that sees another point fuses the two, the
        point with more observations surviving (ORB-SLAM2 Fuse), or the given one when
        ``keep_given`` (loop side, SearchAndFuse). Returns the number of matches applied."""
        ids = np.asarray(ids, dtype=np.int64)
        kp = np.asarray(kp, dtype=np.int64)
        ok = ~self.mp_bad[ids]
        ids, kp = ids[ok], kp[ok]
        if len(ids) == 0:
            return 0
        cur = kf.mp_ids[kp]
        free = cur < 0
        if np.any(free):
            self.add_observations(kf, kp[free], ids[free])
        occ = ~free & (cur != ids)
        cur, ids = cur[occ], ids[occ]
        live = ~self.mp_bad[cur]
        cur, ids = cur[live], ids[live]
        if len(cur):
            if keep_given:
                self.replace_points(cur, ids)
            else:
                given_wins = self.mp_nobs[ids] >= self.mp_nobs[cur]
                self.replace_points(np.where(given_wins, cur, ids), np.where(given_wins, ids, cur))
        return int(np.count_nonzero(free)) + len(cur)

    def mp_view(self, mp_id: int) -> MapPoint:
        return MapPoint(self, mp_id)

    # ---------------------------------------------------------------- keyframes
    def new_keyframe(self, frame) -> KeyFrame:
        kf = KeyFrame(self.next_kf_id, frame)
        if self.planar is not None:
            kf.planar = self.planar
            kf.set_pose(kf.T_cw)
        self.next_kf_id += 1
        self.keyframes[kf.id] = kf
        return kf

    def good_keyframes(self) -> List[KeyFrame]:
        return [kf for kf in self.keyframes.values() if not kf.bad]

    def covisibility(self, kf: KeyFrame, min_weight: int = 1) -> Dict[int, int]:
        """{kf_id: shared map points} of keyframes sharing points with ``kf`` (covisibility graph
        edge weights, computed on demand from the observation arrays)."""
        ids = kf.valid_mp_ids(self.mp_bad)
        out = {}
        if len(ids) == 0:
            return out
        mark = np.zeros(self.n, dtype=bool)
        mark[ids] = True
        for other in self.keyframes.values():
            if other is kf or other.bad:
                continue
            o = other.mp_ids[other.mp_ids >= 0]
            w = int(np.count_nonzero(mark[o]))
            if w >= min_weight:
                out[other.id] = w
        return out

    def update_connections(self, kf: KeyFrame, th: int = 15) -> None:
        """Covisibility edges of ``kf`` (weight >= th, or the best one), both directions, and the
        spanning-tree parent on first connection (ORB-SLAM2 UpdateConnections)."""
        cov = self.covisibility(kf, 1)
        conn = {k: w for k, w in cov.items() if w >= th}
        if not conn and cov:
            best = max(cov, key=lambda k: cov[k])
            conn = {best: cov[best]}
        for k in list(kf.connections):
            if k not in conn and k in self.keyframes:
                self.keyframes[k].connections.pop(kf.id, None)
        kf.connections = conn
        for k, w in conn.items():
            self.keyframes[k].connections[kf.id] = w
        if kf.parent is None and conn and kf.id != 0:
            kf.parent = self.keyframes[max(conn, key=lambda k: conn[k])]

    def set_bad_keyframe(self, kf: KeyFrame) -> None:
        """Cull ``kf``: erase its observations, hand its children to its parent, keep T_cp so
        frames that referenced it still resolve to a pose (ORB-SLAM2 KeyFrame::SetBadFlag)."""
        if kf.id == 0 or kf.bad:
            return
        parent = kf.parent
        while parent is not None and parent.bad:
            parent = parent.parent
        if parent is None:
            return
        for k in self.keyframes.values():
            if k.parent is kf:
                k.parent = parent
        for k in list(kf.connections):
            if k in self.keyframes:
                self.keyframes[k].connections.pop(kf.id, None)
        kf.connections = {}
        idx = np.nonzero(kf.mp_ids >= 0)[0]
        self.erase_observations(kf, idx)
        kf.parent = parent
        kf.T_cp = kf.T_cw @ inv_T(parent.T_cw)
        kf.bad = True

    def best_covisibles(self, kf: KeyFrame, n: int, min_weight: int = 1) -> List[KeyFrame]:
        cov = {k: w for k, w in kf.connections.items() if w >= min_weight and k in self.keyframes
               and not self.keyframes[k].bad}
        if not cov:
            cov = self.covisibility(kf, min_weight)
        ids = sorted(cov, key=cov.get, reverse=True)[:n]
        return [self.keyframes[i] for i in ids]

    @property
    def n_points(self) -> int:
        return int(np.count_nonzero(~self.mp_bad[: self.n]))
