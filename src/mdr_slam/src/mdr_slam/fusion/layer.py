"""Storage of the voxel map (voxblox's ``Layer``): the slot arrays, the key -> slot hash, growth.

Map points live in flat numpy arrays ("slots", structure of arrays, capacity doubled when full);
a :class:`~mdr_slam.fusion.hash_map.KeyHash` maps a key ``(ix, iy, iz, nbin)`` to its slot (see
:mod:`mdr_slam.fusion.voxel_map` for the data layout). :class:`VoxelLayer` is a mixin of
:class:`~mdr_slam.fusion.voxel_map.VoxelMap`: it holds the batch hash operations, slot allocation,
the fold of one map point into another and the read-outs of the live points; the parameters
(``voxel_size``, ...) are set by ``VoxelMap.__init__``.
"""
from __future__ import annotations

from collections import OrderedDict

import numpy as np

from .hash_map import KeyHash, pack_keys

__all__ = ["VoxelLayer"]

# per-slot state: name -> (dtype, trailing shape)
_FIELDS = OrderedDict([
    ("pos", (np.float32, (3,))),
    ("normal", (np.float32, (3,))),
    ("weight", (np.float32, ())),
    ("intensity", (np.float32, ())),
    ("confidence", (np.int32, ())),
    ("first_seen", (np.float64, ())),
    ("last_seen", (np.float64, ())),
    ("anchor", (np.int64, ())),
    ("key", (np.int32, (4,))),
    ("alive", (np.bool_, ())),
    ("view", (np.float32, (3,))),   # camera centre (map) of the latest cloud that integrated it
])
# a slot's value before anything sets it (others: 0): no viewpoint, so no ray in the grid
_FILL = {"view": np.nan}


class VoxelLayer:
    """Slot arrays and key hash of a :class:`~mdr_slam.fusion.voxel_map.VoxelMap` (mixin)."""

    def _reset_storage(self) -> None:
        """Empty hash and slot arrays (the storage part of :meth:`VoxelMap.reset`)."""
        self._hash = KeyHash(2 * self._initial_capacity)
        self._cap = 0
        self._a = {}
        self._grow(self._initial_capacity)
        self._top = 0                      # slots [0, _top) have been used
        self._free = np.zeros(0, np.int64)  # freed slots below _top, reused first
        self._n = 0

    def _close_storage(self) -> None:
        """Free the hash table and the slot arrays (the storage part of :meth:`VoxelMap.close`)."""
        self._hash = None
        self._a = {k: v[:0] for k, v in self._a.items()}
        self._cap = self._top = self._n = 0
        self._free = np.zeros(0, np.int64)

    def __len__(self) -> int:
        return self._n

    def _grow(self, cap: int) -> None:
        new = {}
        for name, (dt, shape) in _FIELDS.items():
            a = np.full((cap,) + shape, _FILL.get(name, 0), dtype=dt)
            if name in self._a:
                a[: self._cap] = self._a[name][: self._cap]
            new[name] = a
        self._a, self._cap = new, cap

    def _alloc(self, n: int) -> np.ndarray:
        take = min(n, len(self._free))
        slots = self._free[len(self._free) - take:]
        self._free = self._free[: len(self._free) - take]
        rest = n - take
        if self._top + rest > self._cap:
            cap = self._cap
            while self._top + rest > cap:
                cap *= 2
            self._grow(cap)
        slots = np.concatenate([slots, np.arange(self._top, self._top + rest)])
        self._top += rest
        return slots.astype(np.int64)

    def _find(self, keys: np.ndarray) -> np.ndarray:
        """Slots of (M, 4) keys, -1 where absent (one batched hash lookup)."""
        if len(keys) == 0:
            return np.zeros(0, np.int64)
        return self._hash.find(pack_keys(keys))

    def _insert(self, keys: np.ndarray, slots: np.ndarray) -> np.ndarray:
        """Insert key -> slot; returns the mask of keys that were inserted (False: already there)."""
        if len(keys) == 0:
            return np.zeros(0, bool)
        return self._hash.insert(pack_keys(keys), slots)

    def _erase(self, keys: np.ndarray) -> None:
        if len(keys):
            self._hash.erase(pack_keys(keys))

    def _keys(self, pos: np.ndarray, bins: np.ndarray) -> np.ndarray:
        vox = np.floor(pos / self.voxel_size).astype(np.int64)
        return np.concatenate([vox, bins.reshape(-1, 1).astype(np.int64)], axis=1).astype(np.int32)

    def _merge_slots(self, dst: np.ndarray, src: np.ndarray) -> None:
        """Fold map points ``src`` into ``dst`` (weighted; confidences add; the view of the
        most recent sighting)."""
        if len(src) == 0:
            return
        a = self._a
        u, inv = np.unique(dst, return_inverse=True)
        m = len(u)
        w = a["weight"][src].astype(np.float64)
        W0 = a["weight"][u].astype(np.float64)
        Wn = W0 + np.bincount(inv, weights=w, minlength=m)

        def acc(v):
            return np.bincount(inv, weights=w * v, minlength=m)

        a["pos"][u] = (W0[:, None] * a["pos"][u] +
                       np.stack([acc(a["pos"][src, k]) for k in range(3)], 1)) / Wn[:, None]
        nrm = W0[:, None] * a["normal"][u] + np.stack([acc(a["normal"][src, k]) for k in range(3)], 1)
        nn = np.linalg.norm(nrm, axis=1, keepdims=True)
        a["normal"][u] = np.where(nn > 1e-12, nrm / np.maximum(nn, 1e-12), a["normal"][u])
        a["intensity"][u] = (W0 * a["intensity"][u] + acc(a["intensity"][src])) / Wn
        a["weight"][u] = Wn
        a["confidence"][u] += np.bincount(inv, weights=a["confidence"][src], minlength=m).astype(np.int32)
        # the view of the newer sighting: the newest source with a view, when it was seen later
        # than the target or the target has none (a view is never replaced by none)
        ls = np.where(np.all(np.isfinite(a["view"][src]), axis=1), a["last_seen"][src], -np.inf)
        o = np.lexsort((ls, inv))
        last = o[np.r_[np.flatnonzero(inv[o][1:] != inv[o][:-1]), len(o) - 1]]  # one per target
        has = np.all(np.isfinite(a["view"][u]), axis=1)
        take = (ls[last] > -np.inf) & ((ls[last] > a["last_seen"][u]) | ~has)
        a["view"][u[take]] = a["view"][src[last[take]]]
        np.minimum.at(a["first_seen"], u[inv], a["first_seen"][src])
        np.maximum.at(a["last_seen"], u[inv], a["last_seen"][src])

    # ------------------------------------------------------------------ output
    def live_slots(self) -> np.ndarray:
        return np.nonzero(self._a["alive"][: self._top])[0]

    def points(self, min_confidence: int = 0) -> np.ndarray:
        """(N, 3) float64 positions of the points with confidence >= ``min_confidence``."""
        s = self.live_slots()
        s = s[self._a["confidence"][s] >= min_confidence]
        return self._a["pos"][s].astype(np.float64)

    def memory_bytes(self) -> int:
        """Bytes held by the slot arrays and the hash table (an estimate of the map's footprint)."""
        arrays = sum(v.nbytes for v in self._a.values())
        return int(arrays + self._hash.nbytes())
