"""The voxel map's key -> slot hash (voxblox's ``BlockHashMap``): batched, vectorized numpy.

Keys ``(ix, iy, iz, nbin)`` are packed into one int64 (20 bits per axis, 3 for the bin) and kept
in an open-addressing table with linear probing; every operation takes a batch of keys and loops
over probe steps, not over keys. Erased keys leave a tombstone; the table is rebuilt when live keys
and tombstones pass half of it.

Not Open3D's ``open3d.core.HashMap``: on the CPU its batched lookups were several times slower
at these batch sizes, its OpenMP threads compete with the other nodes for the cores, and loading
Open3D costs the fusion node about 160 MB.
"""
from __future__ import annotations

import numpy as np

__all__ = ["KeyHash", "pack_keys", "KEY_LIMIT"]

KEY_LIMIT = 2 ** 19          # |ix|, |iy|, |iz| < KEY_LIMIT (at 2 cm voxels: 10.5 km)
_AXIS_BITS = 20
_BIN_BITS = 3
_EMPTY = -1
_TOMB = -2
_MAX_LOAD = 0.5              # live keys + tombstones per table entry before a rebuild
_GROW_LOAD = 0.25            # live keys per table entry just after a rebuild
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)   # Fibonacci hashing: multiply, keep the high bits


def pack_keys(keys: np.ndarray) -> np.ndarray:
    """(M, 4) integer keys -> (M,) int64. Voxel indices beyond the limit are clamped to it (the
    map keeps points far inside it); the bin must be 0..7."""
    k = np.asarray(keys).reshape(-1, 4)
    v = k[:, :3].astype(np.int64)
    v += KEY_LIMIT
    np.minimum(v, 2 * KEY_LIMIT - 1, out=v)
    np.maximum(v, 0, out=v)
    out = v[:, 0] << (2 * _AXIS_BITS + _BIN_BITS)
    out |= v[:, 1] << (_AXIS_BITS + _BIN_BITS)
    out |= v[:, 2] << _BIN_BITS
    out |= k[:, 3] & ((1 << _BIN_BITS) - 1)
    return out


class KeyHash:
    """int64 key -> int64 value, open addressing (linear probing), batch operations only."""

    def __init__(self, capacity: int = 16):
        self._make(max(16, int(capacity)))

    def _make(self, n: int) -> None:
        bits = max(4, int(np.ceil(np.log2(max(n, 2)))))
        self._bits = bits
        self._keys = np.full(1 << bits, _EMPTY, np.int64)
        self._vals = np.zeros(1 << bits, np.int64)
        self._live = 0
        self._tombs = 0

    def __len__(self) -> int:
        return self._live

    def capacity(self) -> int:
        return len(self._keys)

    def nbytes(self) -> int:
        return int(self._keys.nbytes + self._vals.nbytes)

    def _home(self, keys: np.ndarray) -> np.ndarray:
        return (keys.astype(np.uint64) * _GOLDEN >> np.uint64(64 - self._bits)).astype(np.int64)

    def _positions(self, keys: np.ndarray) -> np.ndarray:
        """Table position of each key, -1 where absent."""
        out = np.full(len(keys), -1, np.int64)
        idx = np.arange(len(keys))
        pos = self._home(keys)
        mask = len(self._keys) - 1
        while len(idx):
            t = self._keys[pos]
            hit = t == keys[idx]
            out[idx[hit]] = pos[hit]
            go = ~hit & (t != _EMPTY)      # a tombstone or another key: probe on
            idx, pos = idx[go], (pos[go] + 1) & mask
        return out

    def find(self, keys: np.ndarray) -> np.ndarray:
        """Values of ``keys`` (int64), -1 where absent."""
        keys = np.asarray(keys, dtype=np.int64)
        pos = self._positions(keys)
        out = np.full(len(keys), -1, np.int64)
        f = pos >= 0
        out[f] = self._vals[pos[f]]
        return out

    def insert(self, keys: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Insert key -> value where the key is absent; returns the mask of inserted keys (False:
        already present, or a repeat of a key earlier in the same batch)."""
        keys = np.asarray(keys, dtype=np.int64)
        values = np.asarray(values, dtype=np.int64).reshape(-1)
        ok = np.zeros(len(keys), bool)
        if len(keys) == 0:
            return ok
        _, first = np.unique(keys, return_index=True)
        ok[first] = True
        ok &= self._positions(keys) < 0
        idx = np.nonzero(ok)[0]
        if self._live + self._tombs + len(idx) > _MAX_LOAD * len(self._keys):
            self._rebuild(self._live + len(idx))
        mask = len(self._keys) - 1
        pos = self._home(keys[idx])
        while len(idx):
            t = self._keys[pos]
            free = (t == _EMPTY) | (t == _TOMB)
            fi = np.nonzero(free)[0]
            # keys are unique here: of several claims on one free entry the last write stays,
            # and exactly that claim reads its own key back
            self._keys[pos[fi]] = keys[idx[fi]]
            won = np.zeros(len(idx), bool)
            won[fi] = self._keys[pos[fi]] == keys[idx[fi]]
            self._tombs -= int((t[won] == _TOMB).sum())   # one winner per entry taken
            self._vals[pos[won]] = values[idx[won]]
            self._live += int(won.sum())
            idx, pos = idx[~won], (pos[~won] + 1) & mask
        return ok

    def erase(self, keys: np.ndarray) -> int:
        """Remove ``keys`` (absent ones are ignored); returns how many were removed."""
        pos = self._positions(np.asarray(keys, dtype=np.int64))
        pos = np.unique(pos[pos >= 0])
        self._keys[pos] = _TOMB
        self._live -= len(pos)
        self._tombs += len(pos)
        return len(pos)

    def items(self):
        """(keys, values) of every live entry."""
        live = self._keys >= 0
        return self._keys[live].copy(), self._vals[live].copy()

    def _rebuild(self, n_live: int) -> None:
        """A fresh table holding the live entries at a quarter load (tombstones dropped)."""
        k, v = self.items()
        self._make(int(max(n_live, len(k)) / _GROW_LOAD))
        if len(k):
            self.insert(k, v)
