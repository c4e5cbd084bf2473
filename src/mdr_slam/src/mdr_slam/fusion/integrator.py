"""Fuse and update steps of the voxel map (paper 3.4.2; voxblox's ``Integrator``): one cloud in.

:class:`VoxelIntegrator` is a mixin of :class:`~mdr_slam.fusion.voxel_map.VoxelMap`:
:meth:`~VoxelIntegrator.integrate` moves a camera cloud into ``map``, downsamples it and gives it
normals, associates every point with a map point (own voxel, then the neighbours near its border),
averages the matches in, inserts the rest, keeps keys on their points' voxels (re-keying) and
keeps the map clock (see :mod:`mdr_slam.fusion.voxel_map`).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..geometry import is_valid_T, transform_points
from .cloud import grid_normals, normal_bins, voxel_downsample
from .hash_map import KEY_LIMIT

__all__ = ["VoxelIntegrator", "IntegrationStats"]

_TIME_STEP = 1e-3  # s of map time between the last stamp before a jump back and the first after

_OFFSETS = [np.array([ox, oy, oz]) for ox in (0, 1) for oy in (0, 1) for oz in (0, 1)
            if ox + oy + oz > 0]


class IntegrationStats(dict):
    """What one :meth:`VoxelMap.integrate` did (a dict with attribute access)."""

    def __getattr__(self, k):
        try:
            return self[k]
        except KeyError:
            raise AttributeError(k)


class VoxelIntegrator:
    """Fuse-update of a :class:`~mdr_slam.fusion.voxel_map.VoxelMap` (mixin)."""

    # ------------------------------------------------------------------ fuse / update
    def integrate(self, points_cam, T_map_cam, stamp: float, intensity=None, weights=None,
                  anchor_id: Optional[int] = None, T_map_anchor=None) -> IntegrationStats:
        """Fuse one camera-frame cloud observed at ``stamp`` (s) with pose ``T_map_cam``.

        ``intensity``/``weights``: optional per-point arrays (weights: e.g. inverse depth variance
        of the temporal filter; default 1). ``anchor_id``: keyframe the cloud belongs to, with its
        pose ``T_map_anchor`` (default ``T_map_cam``); if the map holds an older pose of that
        anchor, its points are first corrected to the new one. Returns the stats; a cloud that
        cannot be used (bad pose, nothing valid) returns ``stats.skipped`` with the reason and
        leaves the map unchanged.
        """
        P = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        st = IntegrationStats(n_in=len(P), n_valid=0, n_down=0, n_merged=0, n_inserted=0,
                              n_conflicts=0, n_lookups=0, n_removed=0, map_size=self._n,
                              skipped="")
        T = np.asarray(T_map_cam, dtype=np.float64)
        if not is_valid_T(T):
            st["skipped"] = "pose is not a finite rigid transform"
            return st
        stamp = float(stamp)
        if not np.isfinite(stamp):
            st["skipped"] = "stamp is not finite"
            return st
        ok = np.all(np.isfinite(P), axis=1) & (P[:, 2] >= self.min_depth) & (P[:, 2] <= self.max_depth)
        inten = None if intensity is None else np.asarray(intensity, dtype=np.float64).reshape(-1)
        w = None if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
        if inten is not None:
            if len(inten) != len(P):
                st["skipped"] = "intensity has %d values for %d points" % (len(inten), len(P))
                return st
            inten = np.where(np.isfinite(inten), inten, 0.0)
        if w is not None:
            if len(w) != len(P):
                st["skipped"] = "weights have %d values for %d points" % (len(w), len(P))
                return st
            ok &= np.isfinite(w) & (w > 0)
        Pw = transform_points(T, P[ok])
        ok_range = np.all(np.abs(Pw) < (KEY_LIMIT - 2) * self.voxel_size, axis=1)
        Pw = Pw[ok_range]
        st["n_valid"] = len(Pw)
        if len(Pw) == 0:
            st["skipped"] = "no valid points"
            return st
        if anchor_id is not None:
            Ta = T if T_map_anchor is None else np.asarray(T_map_anchor, dtype=np.float64)
            if not is_valid_T(Ta):
                st["skipped"] = "anchor pose is not a finite rigid transform"
                return st
            anchor_id = int(anchor_id)
            old = self.anchors.get(anchor_id)
            if old is not None and not np.allclose(old, Ta, atol=1e-9):
                st["n_corrected"] = self.apply_corrections({anchor_id: Ta})
            self.anchors[anchor_id] = Ta.copy()
        self.last_stamp = stamp
        stamp = self._map_time(stamp)  # from here on: map time (monotonic)

        extra = {}
        if inten is not None:
            extra["intensity"] = inten[ok][ok_range]
        wv = None if w is None else w[ok][ok_range]
        vox, Pd, wd, ex = voxel_downsample(Pw, self.voxel_size, wv, extra)
        Id = ex.get("intensity", np.zeros(len(Pd)))
        st["n_down"] = len(Pd)
        center = T[:3, 3]
        Nd = grid_normals(Pd, center, self.normal_radius)  # PCA over the 2x2x2 cells around P
        a = self._a

        if self.confidence:
            b1, b2 = normal_bins(Nd)
            target = np.full(len(Pd), -1, np.int64)
            # stage 1: own voxel, primary and secondary normal bin
            k1 = np.concatenate([vox, b1[:, None]], axis=1).astype(np.int32)
            k2 = np.concatenate([vox, b2[:, None]], axis=1).astype(np.int32)
            s12 = self._find(np.concatenate([k1, k2]))
            st["n_lookups"] += 2 * len(Pd)
            s1, s2 = s12[: len(Pd)], s12[len(Pd):]
            for s in (s2, s1):  # primary wins when both agree
                good = s >= 0
                good[good] = np.einsum("ij,ij->i", a["normal"][s[good]], Nd[good]) >= self.cos_normal
                target[good] = s[good]
            # stage 2: unmatched points near a voxel border look in the neighbours on that side;
            # all queries go to the hash in one batch (a find call has a fixed overhead)
            um = np.nonzero(target < 0)[0]
            if len(um) and self.radius > 0:
                frac = Pd[um] / self.voxel_size - vox[um]
                side = np.where(frac < 0.5, -1, 1)
                near = np.minimum(frac, 1.0 - frac) * self.voxel_size < self.radius
                qi, qk = [], []
                for o in _OFFSETS:  # 7 neighbour offsets of the 2x2x2 block, not a loop over points
                    idx = np.nonzero(np.all(near | (o == 0), axis=1))[0]
                    if len(idx) == 0:
                        continue
                    nv = vox[um[idx]] + side[idx] * o
                    for b in (b1, b2):
                        qi.append(idx)
                        qk.append(np.concatenate([nv, b[um[idx], None]], axis=1))
                if qi:
                    qi = np.concatenate(qi)
                    s = self._find(np.concatenate(qk))
                    st["n_lookups"] += len(qi)
                    f = s >= 0
                    qi, s = qi[f], s[f]
                    d = np.linalg.norm(a["pos"][s] - Pd[um[qi]], axis=1)
                    agree = np.einsum("ij,ij->i", a["normal"][s], Nd[um[qi]]) >= self.cos_normal
                    ok2 = agree & (d <= self.radius)
                    qi, s, d = qi[ok2], s[ok2], d[ok2]
                    order = np.lexsort((d, qi))  # nearest candidate first for every point
                    qi, s = qi[order], s[order]
                    _, first = np.unique(qi, return_index=True)
                    target[um[qi[first]]] = s[first]
            new_keys = k1
        else:
            new_keys = np.concatenate([vox, np.zeros((len(vox), 1), np.int64)], axis=1).astype(np.int32)
            target = self._find(new_keys)
            st["n_lookups"] += len(Pd)

        matched = target >= 0
        if matched.any():
            self._merge(target[matched], Pd[matched], Nd[matched], wd[matched], Id[matched], stamp,
                        center)
        st["n_merged"] = int(matched.sum())
        um = np.nonzero(~matched)[0]
        if len(um):
            keys = new_keys[um]
            slots = self._alloc(len(um))
            a = self._a  # _alloc may have grown (replaced) the arrays
            ins = self._insert(keys, slots)
            if not ins.all():
                # key taken by a map point with a disagreeing normal: keep the established one
                self._free = np.concatenate([self._free, slots[~ins]])
                st["n_conflicts"] = int((~ins).sum())
            um, slots, keys = um[ins], slots[ins], keys[ins]
            a["pos"][slots] = Pd[um]
            a["normal"][slots] = Nd[um]
            a["weight"][slots] = wd[um]
            a["intensity"][slots] = Id[um]
            a["confidence"][slots] = 1
            a["first_seen"][slots] = stamp
            a["last_seen"][slots] = stamp
            a["anchor"][slots] = -1 if anchor_id is None else anchor_id
            a["key"][slots] = keys
            a["alive"][slots] = True
            a["view"][slots] = center
            self._n += len(slots)
            st["n_inserted"] = len(slots)
            if self.confidence and len(slots):
                self._pending.append((stamp, slots, stamp))  # (grace starts, slots, first_seen)
        self.n_integrations += 1
        if self.confidence and self.clean_every > 0 and \
                self.n_integrations % self.clean_every == 0:
            st["n_removed"] = self._clean(stamp)
        st["map_size"] = self._n
        return st

    def _map_time(self, stamp: float) -> float:
        """Map time of ``stamp``: the stamp plus an offset that only grows. When a stamp would
        go back in map time (a looping bag restarts its clock; a map loaded from a later session),
        the offset grows so that map time continues just after the latest map time: the points
        of every lap stay ordered by age (the duplicate fold keeps the older point of a surface;
        with the bag's repeating stamps it compared the laps' stamps, so a lap's duplicate
        of an earlier lap's point looked older or equally old about half of the time and was
        kept: scripts/fusion_laps.py --wrap) and young points get their full grace period."""
        t = float(stamp) + self._time_offset
        if self._t_last is not None and t < self._t_last:
            self._time_offset += self._t_last - t + _TIME_STEP
            t = float(stamp) + self._time_offset
        self._t_last = t  # >= the previous one by construction
        return t

    def _merge(self, t, P, N, w, I, stamp, view):
        """Weighted running mean of targets ``t`` (duplicates allowed) with new observations
        seen from the camera centre ``view`` (which becomes their view)."""
        a = self._a
        u, inv = np.unique(t, return_inverse=True)
        m = len(u)
        W0 = a["weight"][u].astype(np.float64)
        ws = np.bincount(inv, weights=w, minlength=m)
        Wn = W0 + ws

        def acc(v):
            return np.bincount(inv, weights=w * v, minlength=m)

        pos = (W0[:, None] * a["pos"][u] + np.stack([acc(P[:, k]) for k in range(3)], 1)) / Wn[:, None]
        nrm = W0[:, None] * a["normal"][u] + np.stack([acc(N[:, k]) for k in range(3)], 1)
        nn = np.linalg.norm(nrm, axis=1, keepdims=True)
        nrm = np.where(nn > 1e-12, nrm / np.maximum(nn, 1e-12), a["normal"][u])
        a["pos"][u] = pos
        a["normal"][u] = nrm
        a["intensity"][u] = (W0 * a["intensity"][u] + acc(I)) / Wn
        a["weight"][u] = Wn
        a["confidence"][u] += 1  # one vote per cloud that saw the point
        a["last_seen"][u] = stamp
        a["view"][u] = view
        if self.confidence and self.rekey:
            self.n_cell_folds += self._rekey(u)

    def _rekey(self, slots: np.ndarray) -> int:
        """Keep the hash key of the updated points ``slots`` on the voxel of their CURRENT position.

        A running mean fed by stage-2 associations (a neighbour voxel's samples) can cross the
        voxel border; left under its old key, the next lap's sample of its new voxel finds no point
        there and inserts a second point of the same surface cell. Points whose position left
        their key voxel are re-keyed to the voxel they are in (same normal bin); if another point
        of the same bin (normals agreeing) already holds that voxel, the mover is folded into it:
        at most one map point per surface cell and normal bin. Cost: one floor/compare over the
        updated points and hash find/erase/insert for the few that moved (not the map size).
        Returns the number of points folded.
        """
        a = self._a
        key = a["key"][slots]
        vox = np.floor(a["pos"][slots].astype(np.float64) / self.voxel_size).astype(np.int64)
        moved = np.any(vox != key[:, :3], axis=1)
        if not moved.any():
            return 0
        s = slots[moved]
        old = key[moved]
        nk = np.concatenate([vox[moved], old[:, 3:]], axis=1).astype(np.int32)
        occ = self._find(nk)
        # a free voxel: the first mover into it takes it
        _, first = np.unique(nk, axis=0, return_index=True)
        go = np.zeros(len(s), bool)
        go[first] = True
        go &= occ < 0
        if go.any():
            self._erase(old[go])
            self._insert(nk[go], s[go])
            a["key"][s[go]] = nk[go]
            self.n_rekeyed += int(go.sum())
        # a taken voxel: fold the mover into the occupant (not into another mover this time)
        f = (occ >= 0) & ~np.isin(occ, s)
        if f.any():
            f[f] = np.einsum("ij,ij->i", a["normal"][s[f]], a["normal"][occ[f]]) >= self.cos_normal
        if not f.any():
            return 0
        src, dst = s[f], occ[f]
        self._merge_slots(dst, src)
        self._erase(old[f])
        a["alive"][src] = False
        self._free = np.concatenate([self._free, src.astype(np.int64)])
        self._n -= len(src)
        return len(src)
