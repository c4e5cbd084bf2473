"""A short time-indexed cache of camera poses with interpolation, for the depth node's
``/mdr/pose`` input (the image stamps and the pose stamps are the same frames, but the pose of a
frame may arrive a little after its image, and an approximate pairing may need interpolation)."""
from __future__ import annotations

import bisect
from typing import List, Optional

import numpy as np

from ..geometry import interpolate_pose

__all__ = ["PoseCache"]


class PoseCache:
    """Poses by stamp (seconds). ``lookup(t)``: the exact pose, or the interpolation (linear
    translation, slerp rotation) of the two poses around ``t`` when they are at most ``max_gap``
    apart; None otherwise (never extrapolates: a wrong pose smears the map)."""

    def __init__(self, max_age: float = 10.0, max_gap: float = 0.25, tolerance: float = 1e-4):
        self.max_age = float(max_age)
        self.max_gap = float(max_gap)
        self.tolerance = float(tolerance)
        self._t: List[float] = []
        self._T: List[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._t)

    def clear(self) -> None:
        self._t, self._T = [], []

    @property
    def latest(self) -> Optional[float]:
        return self._t[-1] if self._t else None

    def add(self, t: float, T: np.ndarray) -> None:
        t = float(t)
        i = bisect.bisect_left(self._t, t)
        if i < len(self._t) and abs(self._t[i] - t) <= self.tolerance:
            self._T[i] = np.asarray(T, dtype=float)
        else:
            self._t.insert(i, t)
            self._T.insert(i, np.asarray(T, dtype=float))
        cut = bisect.bisect_left(self._t, self._t[-1] - self.max_age)
        if cut:
            del self._t[:cut], self._T[:cut]

    def lookup(self, t: float) -> Optional[np.ndarray]:
        t = float(t)
        i = bisect.bisect_left(self._t, t - self.tolerance)
        if i < len(self._t) and abs(self._t[i] - t) <= self.tolerance:
            return self._T[i].copy()
        if i == 0 or i >= len(self._t):
            return None
        t0, t1 = self._t[i - 1], self._t[i]
        if t1 - t0 > self.max_gap:
            return None
        a = (t - t0) / (t1 - t0)
        T0, T1 = self._T[i - 1], self._T[i]
        return interpolate_pose(T0, T1, a)
