"""Keyframe anchoring of the voxel map: loop-closure corrections move the points with their keyframe.

:class:`AnchorCorrections` is a mixin of :class:`~mdr_slam.fusion.voxel_map.VoxelMap`. Points remember
the keyframe (anchor) of their first observation and the map keeps each anchor's pose (``anchors``);
a pose-graph correction of an anchor moves its points rigidly and re-keys them (see "Loop closure"
in :mod:`mdr_slam.fusion.voxel_map`).
"""
from __future__ import annotations

from typing import Dict

import numpy as np

from ..geometry import inv_T, is_valid_T
from .cloud import normal_bins

__all__ = ["AnchorCorrections"]


class AnchorCorrections:
    """Keyframe anchors of a :class:`~mdr_slam.fusion.voxel_map.VoxelMap` (mixin)."""

    # ------------------------------------------------------------------ loop closure
    def detach_anchors(self) -> int:
        """Forget every keyframe anchor (points stay where they are, no longer follow corrections).

        For a pose source that restarts its keyframe ids (a looping bag starts a new tracking map):
        a new keyframe reusing an old id must not move the old points. Returns the points detached.
        """
        a = self._a
        live = a["alive"][: self._top] & (a["anchor"][: self._top] >= 0)
        a["anchor"][: self._top][live] = -1
        self.anchors = {}
        return int(live.sum())

    def apply_corrections(self, corrections: Dict[int, np.ndarray]) -> int:
        """Move the points of corrected anchors rigidly: ``p' = T_new inv(T_old) p`` (their
        normals and views with them).

        ``corrections``: ``{anchor_id: T_map_anchor_new}``. Anchors the map has never seen are
        stored (future clouds anchored to them will use the pose). Moved points are re-keyed in
        the hash; a point whose new key is already taken is merged into the occupant. Returns the
        number of points moved. Cost: one vectorized pass over the map's anchor ids (corrections are
        rare events, not per cloud).
        """
        moved_ids, deltas = [], []
        for kf, Tn in corrections.items():
            Tn = np.asarray(Tn, dtype=np.float64)
            if not is_valid_T(Tn):
                continue
            kf = int(kf)
            To = self.anchors.get(kf)
            self.anchors[kf] = Tn.copy()
            if To is None:
                continue
            D = Tn @ inv_T(To)
            if np.allclose(D, np.eye(4), atol=1e-12):
                continue
            moved_ids.append(kf)
            deltas.append(D)
        if not moved_ids or self._n == 0:
            return 0
        a = self._a
        live = np.nonzero(a["alive"][: self._top])[0]
        ids = np.asarray(moved_ids, dtype=np.int64)
        order = np.argsort(ids)
        ids, Ds = ids[order], np.stack(deltas)[order]
        anc = a["anchor"][live]
        pos_in = np.searchsorted(ids, anc)
        pos_in = np.minimum(pos_in, len(ids) - 1)
        hit = ids[pos_in] == anc
        slots, which = live[hit], pos_in[hit]
        if len(slots) == 0:
            return 0
        R, t = Ds[which, :3, :3], Ds[which, :3, 3]
        P = np.einsum("nij,nj->ni", R, a["pos"][slots].astype(np.float64)) + t
        N = np.einsum("nij,nj->ni", R, a["normal"][slots].astype(np.float64))
        a["pos"][slots] = P
        a["normal"][slots] = N
        # the ray from the view to the point moves with the point (a missing view stays NaN)
        a["view"][slots] = np.einsum("nij,nj->ni", R, a["view"][slots].astype(np.float64)) + t
        self._erase(a["key"][slots])
        if self.confidence:
            b = normal_bins(N)[0]  # the bin of the rotated normal, as at insertion
        else:
            b = np.zeros(len(slots), np.int32)
        keys = self._keys(P, b)
        ins = self._insert(keys, slots)
        a["key"][slots[ins]] = keys[ins]
        if not ins.all():
            lost = slots[~ins]
            occ = self._find(keys[~ins])
            ok = occ >= 0
            if ok.any():
                self._merge_slots(occ[ok], lost[ok])
            a["alive"][lost] = False
            self._free = np.concatenate([self._free, lost])
            self._n -= len(lost)
        return len(slots)
