"""Clean step of the voxel map (paper 3.4.2): confidence and span checks, duplicate fold.

:class:`VoxelCleaning` is a mixin of :class:`~mdr_slam.fusion.voxel_map.VoxelMap`: points that come
of age (``grace``) without enough confidence (or, with ``min_span``, seen over too short a time)
are removed, those of the same surface as an older point are folded into it (ORB-SLAM2's
``MapPointCulling`` likewise culls recent map points seen by too few keyframes). See
:mod:`mdr_slam.fusion.voxel_map`.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

__all__ = ["VoxelCleaning"]

# the 27 voxels of the 3x3x3 block around a voxel (own voxel first)
_BLOCK27 = np.array(sorted([[ox, oy, oz] for ox in (-1, 0, 1) for oy in (-1, 0, 1) for oz in (-1, 0, 1)],
                           key=lambda o: sum(abs(x) for x in o)), np.int64)

# the 5x5x5 block around a voxel
_BLOCK125 = np.array([[ox, oy, oz] for ox in range(-2, 3) for oy in range(-2, 3) for oz in range(-2, 3)], np.int64)
# points whose duplicate search runs at once: ~200 hash keys each, about 20 MB of queries
_DUP_CHUNK = 2048


class VoxelCleaning:
    """Clean step of a :class:`~mdr_slam.fusion.voxel_map.VoxelMap` (mixin)."""

    # ------------------------------------------------------------------ clean
    def clean(self, now: Optional[float] = None, full: bool = False) -> int:
        """Remove points with confidence < ``min_confidence`` older than ``grace`` at ``now``
        (a stamp, as given to :meth:`integrate`; default: the last one).

        Incremental: only insertion batches whose grace period ended are checked (a point that
        reached the threshold keeps it, confidence never decreases). ``full=True`` checks every
        point (e.g. after loading a map). No-op for ``confidence=False``. Returns the number removed.
        """
        if not self.confidence:
            return 0
        if now is None:
            if self._t_last is None:
                return 0
            return self._clean(self._t_last, full)
        return self._clean(float(now) + self._time_offset, full)

    def _clean(self, now: float, full: bool = False) -> int:
        """:meth:`clean` at map time ``now``."""
        a = self._a
        if full:
            self._pending.clear()
            cand = np.nonzero(a["alive"][: self._top])[0]
            cand = cand[a["first_seen"][cand] <= now - self.grace]
        else:
            batches = []
            while self._pending and self._pending[0][0] <= now - self.grace:
                _, s, t0 = self._pending.popleft()
                s = s[a["alive"][s] & (a["first_seen"][s] == t0)]  # slot not freed and reused
                batches.append(s)
            if not batches:
                return 0
            cand = np.concatenate(batches)
        conf = a["confidence"][cand]
        if self.min_span > 0:  # seen over too short a time: correlated clouds of one moment
            conf = np.where(a["last_seen"][cand] - a["first_seen"][cand] < self.min_span, 0, conf)
        bad = cand[conf < self.min_confidence]
        self._remove(bad)
        n_dup = 0
        if self.dup_normal > 0:
            n_dup = self._merge_duplicates(cand[conf >= self.min_confidence])
            self.n_duplicates += n_dup
        return len(bad) + n_dup

    def _merge_duplicates(self, slots: np.ndarray) -> int:
        """Fold the points ``slots`` (that just came of age) into an OLDER map point of the same
        surface, when there is one: normals agree within ``normal_angle_deg``, the offset along
        the older point's normal is at most ``dup_normal`` and across it at most ``dup_lateral``.

        Depth noise spreads the samples of one surface along its normal; a sample that lands a
        voxel in front of or behind the surface's map point and is seen a few times (the depth
        filter's consecutive clouds are correlated) would otherwise become a second, permanent
        layer, and every lap of a repeated room adds a few more such points (the map grows with
        time, not with the surface). In-plane neighbours (offset across the normal, one voxel)
        are left alone. The search covers the voxels of the 5x5x5 block around the point's
        position whose box comes within the fold window (an older point 1.5 voxels along the
        normal and one across can be two voxels away), in the point's key bin and the three bins
        of its normal's component signs (an older point of the same surface can be filed under
        any of them). On the sample's 20 repeated laps (scripts/fusion_laps.py) this folds what
        the old 3x3x3 block in two bins missed: final map 5.5 % smaller at the same accuracy.
        Cost proportional to the points coming of age, not to the map.
        Returns the number of points folded (removed).
        """
        if len(slots) == 0:
            return 0
        a = self._a
        P = a["pos"][slots].astype(np.float64)
        N = a["normal"][slots].astype(np.float64)
        key = a["key"][slots].astype(np.int64)
        # bins: the point's own key bin and the bins of its (current) normal's component signs,
        # where an older point of the same surface (normals agree) is filed
        B = np.concatenate([key[:, 3:], 2 * np.arange(3) + (N < 0)], axis=1)  # (n, 4)
        use = np.ones(B.shape, bool)
        use[:, 1:] = B[:, 1:] != B[:, :1]
        # voxels (5x5x5 block around the point's position) whose box comes within reach of the
        # fold window: an older point up to dup_normal along and dup_lateral across can be two
        # voxels away
        pv = np.floor(P / self.voxel_size).astype(np.int64)
        frac = P / self.voxel_size - pv
        reach = max(np.hypot(self.dup_normal, self.dup_lateral), self.dup_radius) / self.voxel_size
        o = _BLOCK125 + 2
        first_seen = a["first_seen"][slots]
        found_q, found_c = [], []
        # in chunks: a point queries ~200 (voxel, bin) keys, so the queries of a whole batch
        # (thousands of points come of age together on a large wall) would take hundreds of MB
        for c0 in range(0, len(slots), _DUP_CHUNK):
            c1 = min(c0 + _DUP_CHUNK, len(slots))
            fc = frac[c0:c1]
            gap2 = np.stack([fc + 1.0, fc, np.zeros_like(fc), 1.0 - fc, 2.0 - fc], axis=2) ** 2
            d2 = gap2[:, 0, o[:, 0]] + gap2[:, 1, o[:, 1]] + gap2[:, 2, o[:, 2]]  # (n, 125)
            pi, oi = np.nonzero(d2 <= reach * reach)
            vox = (pv[c0:c1][pi] + _BLOCK125[oi]).astype(np.int32)
            r, bj = np.nonzero(use[c0:c1][pi])      # every bin the point searches, per voxel
            q = pi[r]
            keys = np.empty((len(r), 4), np.int32)
            keys[:, :3] = vox[r]
            keys[:, 3] = B[c0:c1][q, bj]
            cand = self._find(keys)
            q = q + c0
            f = cand >= 0
            q, cand = q[f], cand[f]
            f = (cand != slots[q]) & (a["first_seen"][cand] < first_seen[q])
            found_q.append(q[f])
            found_c.append(cand[f])
        qi, cand = np.concatenate(found_q), np.concatenate(found_c)
        Nc = a["normal"][cand].astype(np.float64)
        d = P[qi] - a["pos"][cand]
        along = np.einsum("ij,ij->i", Nc, d)
        lateral = np.linalg.norm(d - along[:, None] * Nc, axis=1)
        dist = np.linalg.norm(d, axis=1)
        # a second layer along the normal (in-plane neighbours, a voxel apart, are not
        # duplicates), or two points of the surface closer than dup_radius (default half a
        # voxel; the map keeps one point per voxel: such a pair is one surface sample split over
        # a voxel border)
        ok = (np.einsum("ij,ij->i", Nc, N[qi]) >= self.cos_normal) & (
            ((np.abs(along) <= self.dup_normal) & (lateral <= self.dup_lateral) &
             (np.abs(along) >= 0.25 * self.voxel_size)) | (dist <= self.dup_radius))
        qi, cand, dist = qi[ok], cand[ok], dist[ok]
        if len(qi) == 0:
            return 0
        # the nearest older point of every duplicate (ties: the lowest slot)
        order = np.lexsort((cand, dist, qi))
        qi, cand = qi[order], cand[order]
        _, first = np.unique(qi, return_index=True)
        src, dst = slots[qi[first]], cand[first]
        keep = ~np.isin(dst, src)  # a target that is itself folded away this time: next time
        src, dst = src[keep], dst[keep]
        if len(src) == 0:
            return 0
        self._merge_slots(dst, src)
        self._erase(a["key"][src])
        a["alive"][src] = False
        self._free = np.concatenate([self._free, src.astype(np.int64)])
        self._n -= len(src)
        if self.rekey:
            self.n_cell_folds += self._rekey(np.unique(dst))  # the folds moved the targets
        return len(src)

    def _remove(self, slots: np.ndarray) -> None:
        if len(slots) == 0:
            return
        self._erase(self._a["key"][slots])
        self._a["alive"][slots] = False
        self._free = np.concatenate([self._free, slots.astype(np.int64)])
        self._n -= len(slots)
        self.n_removed += len(slots)
