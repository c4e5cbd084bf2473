"""Confidence-based global map of node 3 (paper section 3.4): a hashed voxel map with a
fuse-update-clean cycle.

Data layout
-----------
Map points live in flat numpy arrays ("slots", structure of arrays, capacity doubled when full so
appending is amortised O(1)). A hash map (Open3D's ``open3d.core.HashMap``, keys int32[4]) maps a
key ``(ix, iy, iz, nbin)`` to its slot: ``(ix, iy, iz)`` is the voxel the point's (averaged)
position is in, kept up to date as the running mean moves (``rekey``, see the update step), ``nbin``
the direction bin of its normal (0..5 = +x, -x, +y, -y, +z, -z by the dominant component;
always 0 when ``confidence=False``). The normal bin in the key lets both sides of a thin wall (one
voxel, opposite normals) coexist as two map points instead of being averaged into the middle of the
wall. Every operation of :meth:`VoxelMap.integrate` is a batch hash ``find``/``insert`` plus numpy on
the incoming points only, so its cost depends on the size of the cloud and not on the size of the
map (no global KD-tree); the hash ``find`` count is reported in the stats as ``n_lookups``.

Fuse-update-clean (paper 3.4.2)
-------------------------------
* fuse: the cloud is moved into ``map`` with the pose at its stamp (eq. of 3.4.1, ``X_w = T X_c``),
  voxel-downsampled with the map's own grid, and given normals oriented towards the camera
  centre: PCA of the 2x2x2 grid cells of ``normal_radius`` around each point from per-cell
  moments (:func:`grid_normals`, no KD-tree; ``normal_method="knn"``: Open3D ``estimate_normals``).
* update: each incoming point is associated with a map point: first its own voxel (in its normal
  bin and the second most likely bin, so normals near a bin boundary still find their point),
  then, for points still unmatched, the neighbouring voxels on the side(s) where the point is
  closer than ``radius`` to the voxel border (the 2x2x2 block around the point: at most 7 more
  voxels; exact for ``radius <= voxel/2``, and for larger radii it still finds the map points of
  the same surface, which lie near their voxel's centre plane), taking the nearest candidate
  within ``radius`` (a search of every neighbour within ``radius``, exact up to one voxel,
  cost 2.5x the hash lookups and slowed the live tracker without slowing the map's growth).
  A candidate only matches when the normals agree
  within ``normal_angle_deg``. Matched points are averaged into the map point (weighted running
  mean of position, normal and intensity) and its confidence (number of clouds that observed it)
  grows by one; the others are inserted with confidence 1. A map point whose running mean
  crossed into another voxel (stage-2 samples pull it over the border) is re-keyed to that voxel,
  or, when a point of the same bin with an agreeing normal already holds it, folded into that
  point: at most one map point per voxel and normal bin, and the next sample of the voxel finds
  its point in stage 1 instead of inserting a second one (without this, 26 % of the keys of the
  sample room's map were stale after 20 replayed laps and 1157 voxels held two points of one
  bin; with it 95 and 42; map 4.3 % smaller at the same accuracy, scripts/fusion_laps.py).
  An unmatched point whose own key is
  taken by a map point with a disagreeing normal is dropped (``n_conflicts``): the voxel already
  holds a surface, and a single observation must not overwrite an established one.
* clean: points with confidence below ``min_confidence`` once they are older than ``grace``
  seconds are removed (transient noise, moving objects). Confidence never decreases, so each point
  needs checking exactly once, when its grace period ends: insertion batches wait in a FIFO and
  :meth:`clean` only looks at the batches that just came of age (cost independent of map size).
  A point that comes of age as a duplicate of an older point of the same surface (normals agree;
  a second layer within ``dup_normal`` along the normal and ``dup_lateral`` across it, or closer
  than ``dup_radius``, default half a voxel) is folded into the older point
  (``merge_duplicates``): depth noise and the depth filter's correlated clouds otherwise add a
  few permanent stray points on every lap of a repeated room. What still grows on a repeated
  room is a slowing trickle of voxels that reach ``min_confidence`` for the first time (sample
  room, 20 replayed laps: +0.2 %/lap over laps 10-20, one point per voxel and bin kept).
* span (``min_span`` > 0, off by default): a point must also have been seen over at least
  ``min_span`` seconds (first to last sighting) when its grace period ends. Consecutive clouds
  of the depth filter are correlated, so a stray sample published in 3 clouds 0.1 s apart has
  the count without independent evidence; so does a surface that only one moment measures,
  which is the price (sample room, 20 replayed laps, 1 s: RMSE 17.2 -> 14.1 mm, completeness
  19.3 -> 17.8 %).
* in view (``min_view_ratio`` > 0, #8): the count alone confirms any sample that a few correlated
  clouds produce, so a repeated room keeps adding stray points lap after lap (the count grows with
  time, not with the evidence). Every point therefore also counts the clouds that had it IN VIEW
  during its first ``view_window`` seconds (:meth:`_count_views`: a cloud whose nearest measured
  depth along the point's viewing direction is not in front of it by more than ``view_margin``
  saw the surface there, or saw through it: OctoMap's / voxblox's free-space "miss"), and is
  removed at the end of the window when it was seen in fewer than ``min_view_ratio`` of them.
  A ratio, not a count: no number of laps makes a noise sample qualify, and a surface the depth
  filter rarely converges on is not penalised (no measurement there = no evidence). Points
  behind the measured surface (occluded) get no evidence either; those are left to the
  duplicate fold. Sample room, 40 replayed laps (scripts/fusion_laps.py, ratio 0.3, window
  120 s vs off): map 37762 vs 40414 points, RMSE 16.7 vs 17.2 mm, completeness 19.2 vs 19.4 %;
  the creep slows (+482 vs +542 confident points over laps 20-40) but does not stop: what
  still comes is mostly occluded (behind the measured surface) or rarely in view.

Map time
--------
Ages (grace, view window, which of two points is older) are measured in map time: the stamps,
plus an offset that grows whenever a stamp would go back (a looping bag restarts its clock, a map
loaded from a later session), so map time never goes back and every lap of a looped bag is
younger than the one before (``first_seen``/``last_seen`` are map times; equal to the stamps
while time only goes forward). With the raw stamps a lap's stray sample was no younger than the
first lap's point at the same stamp, the fold kept both, and a looped bag grew its map faster
than a live robot would (scripts/fusion_laps.py --wrap: 41747 vs 39862 points after 20 laps).

``confidence=False`` is the ablation's plain voxel grid: key = voxel only, every point averaged
into its voxel, no normal test, no cleaning.

Loop closure
------------
Points remember the keyframe (anchor) of their first observation and the map keeps each anchor's
pose. :meth:`apply_corrections` moves the points of corrected anchors rigidly by
``T_new @ inv(T_old)`` and re-keys them (merging into an occupant when the new key is taken), so the
map follows pose-graph corrections without re-running depth. A merged point follows the anchor that
created it; observations from later keyframes only refine it.
"""
from __future__ import annotations

import collections
import json
import os
from collections import OrderedDict
from typing import Dict, List, Mapping, Optional, Tuple

import numpy as np

from ..geometry import inv_T, is_valid_T, transform_points

__all__ = ["VoxelMap", "IntegrationStats", "normal_bins", "voxel_downsample", "grid_normals"]

# per-slot state: name -> (dtype, trailing shape)
_FIELDS = OrderedDict([
    ("pos", (np.float32, (3,))),
    ("normal", (np.float32, (3,))),
    ("weight", (np.float32, ())),
    ("intensity", (np.float32, ())),
    ("confidence", (np.int32, ())),
    ("views", (np.int32, ())),           # clouds that had the point in view (first view_window s)
    ("first_seen", (np.float64, ())),
    ("last_seen", (np.float64, ())),
    ("anchor", (np.int64, ())),
    ("key", (np.int32, (4,))),
    ("alive", (np.bool_, ())),
])

_TIME_STEP = 1e-3  # s of map time between the last stamp before a jump back and the first after
_PACK_OFFSET = 2 ** 20  # voxel indices are packed in 21 bits per axis: |index| < 2^20
_KEY_LIMIT = 2 ** 20


# the 27 voxels of the 3x3x3 block around a voxel (own voxel first)
_BLOCK27 = np.array(sorted([[ox, oy, oz] for ox in (-1, 0, 1) for oy in (-1, 0, 1) for oz in (-1, 0, 1)],
                           key=lambda o: sum(abs(x) for x in o)), np.int64)

_OFFSETS = [np.array([ox, oy, oz]) for ox in (0, 1) for oy in (0, 1) for oz in (0, 1)
            if ox + oy + oz > 0]
# the 5x5x5 block around a voxel
_BLOCK125 = np.array([[ox, oy, oz] for ox in range(-2, 3) for oy in range(-2, 3) for oz in range(-2, 3)], np.int64)


class IntegrationStats(dict):
    """What one :meth:`VoxelMap.integrate` did (a dict with attribute access)."""

    def __getattr__(self, k):
        try:
            return self[k]
        except KeyError:
            raise AttributeError(k)


def normal_bins(normals: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Primary and secondary direction bins (0..5 = +x, -x, +y, -y, +z, -z) of unit normals.

    Primary = dominant component, secondary = second-largest component (with their signs), the
    bin a slightly different normal of the same surface most likely falls into.
    """
    a = np.abs(normals)
    r = np.arange(len(normals))
    i1 = np.argmax(a, axis=1)
    a[r, i1] = -1.0
    i2 = np.argmax(a, axis=1)
    b1 = 2 * i1 + (normals[r, i1] < 0)
    b2 = 2 * i2 + (normals[r, i2] < 0)
    return b1.astype(np.int32), b2.astype(np.int32)


def _pack(v: np.ndarray) -> np.ndarray:
    """One int64 per integer 3-vector (21 bits per axis, |index| < 2^20)."""
    return (((v[:, 0] + _PACK_OFFSET) << 42) | ((v[:, 1] + _PACK_OFFSET) << 21) |
            (v[:, 2] + _PACK_OFFSET))


_CORNERS = np.array([[ox, oy, oz] for ox in (0, 1) for oy in (0, 1) for oz in (0, 1)], np.int64)
_SYM = [(0, 0, 3), (0, 1, 4), (0, 2, 5), (1, 1, 6), (1, 2, 7), (2, 2, 8)]


def grid_normals(points: np.ndarray, center: np.ndarray, cell: float,
                 min_points: int = 4) -> np.ndarray:
    """Unit normals of a cloud by PCA over a grid neighbourhood, oriented towards ``center``.

    The cloud's first and second moments are summed per cell of a grid of size ``cell``
    (``np.bincount``); a point's neighbourhood is the 2x2x2 block of cells around it (it lies in
    the block's central cell-sized cube, so the block reaches 0.5 to 1.5 cells around it), and its
    normal is the eigenvector of the block covariance with the smallest eigenvalue. Points sharing
    a block share one 3x3 eigen-decomposition. A block with fewer than ``min_points`` points gives
    the viewing ray. Like Open3D's ``estimate_normals`` with a radius of about one cell, without a
    KD-tree: 3-5x less CPU than Open3D on the fusion's downsampled clouds (measured, loaded machine).
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(P)
    if n == 0:
        return np.zeros((0, 3))
    Q = P - P.mean(axis=0)  # centred: the second moments stay well conditioned
    uk, inv = np.unique(_pack(np.floor(Q / cell).astype(np.int64)), return_inverse=True)
    inv = inv.reshape(-1)
    m = len(uk)
    mom = np.empty((m, 10))
    mom[:, 0] = np.bincount(inv, minlength=m)
    for k, c in enumerate((Q[:, 0], Q[:, 1], Q[:, 2], Q[:, 0] * Q[:, 0], Q[:, 0] * Q[:, 1],
                           Q[:, 0] * Q[:, 2], Q[:, 1] * Q[:, 1], Q[:, 1] * Q[:, 2], Q[:, 2] * Q[:, 2])):
        mom[:, k + 1] = np.bincount(inv, weights=c, minlength=m)
    o = np.floor(Q / cell - 0.5).astype(np.int64)  # block origin: cells o + {0, 1}^3
    ub, binv, first = _unique_inv_first(_pack(o))
    ob = o[first]
    acc = np.zeros((len(ub), 10))
    for c in _CORNERS:  # 8 corners of the block, each a batched sorted lookup
        kk = _pack(ob + c)
        j = np.minimum(np.searchsorted(uk, kk), m - 1)
        hit = uk[j] == kk
        acc[hit] += mom[j[hit]]
    cnt = np.maximum(acc[:, 0], 1.0)
    mu = acc[:, 1:4] / cnt[:, None]
    S = np.empty((len(ub), 3, 3))
    for i, j, k in _SYM:
        S[:, i, j] = S[:, j, i] = acc[:, k + 1] / cnt - mu[:, i] * mu[:, j]
    N = np.linalg.eigh(S)[1][:, :, 0][binv]
    ray = np.asarray(center, dtype=np.float64).reshape(1, 3) - P
    bad = (acc[:, 0] < min_points)[binv]
    if bad.any():
        N[bad] = ray[bad] / np.maximum(np.linalg.norm(ray[bad], axis=1, keepdims=True), 1e-12)
    # orient towards the camera: a visible surface faces the viewpoint (n . (c - p) > 0)
    N[np.einsum("ij,ij->i", N, ray) < 0] *= -1.0
    return N


def _unique_inv_first(keys: np.ndarray):
    """(unique keys, inverse, index of one member per unique key)."""
    u, inv = np.unique(keys, return_inverse=True)
    inv = inv.reshape(-1)
    first = np.zeros(len(u), np.int64)
    first[inv] = np.arange(len(keys))
    return u, inv, first


def voxel_downsample(points: np.ndarray, voxel: float, weights: Optional[np.ndarray] = None,
                     extra: Optional[Dict[str, np.ndarray]] = None):
    """Weighted mean per voxel of the grid ``floor(p / voxel)``.

    Returns ``(voxel indices (M, 3) int64, mean points (M, 3), weight sums (M,), {name: mean})``.
    """
    w = np.ones(len(points)) if weights is None else np.asarray(weights, dtype=np.float64)
    vox = np.floor(points / voxel).astype(np.int64)
    # one int64 per voxel (21 bits per axis) so np.unique sorts scalars, not rows (~10x faster)
    packed = (((vox[:, 0] + _PACK_OFFSET) << 42) | ((vox[:, 1] + _PACK_OFFSET) << 21) |
              (vox[:, 2] + _PACK_OFFSET))
    _, first, inv = np.unique(packed, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    m = len(first)
    wsum = np.bincount(inv, weights=w, minlength=m)
    mean = np.stack([np.bincount(inv, weights=w * points[:, k], minlength=m) for k in range(3)],
                    axis=1) / wsum[:, None]
    out = {}
    for name, v in (extra or {}).items():
        out[name] = np.bincount(inv, weights=w * v, minlength=m) / wsum
    return vox[first], mean, wsum, out


class VoxelMap:
    """Hashed voxel map with per-point confidence (see the module docstring).

    Parameters: ``voxel_size`` (m, the map resolution); ``radius`` (m, association radius, at most
    ``voxel_size``, default ``voxel_size``: map points are about a voxel apart, so a new sample of
    the same surface is within one voxel of the nearest one); ``normal_angle_deg`` (merge only when normals
    agree within this angle); ``normal_method`` ("grid": PCA over grid cells of ``normal_radius``,
    :func:`grid_normals`; "knn": Open3D ``estimate_normals`` with ``normal_radius``/``normal_max_nn``);
    ``min_confidence`` and ``grace`` (s) for cleaning; ``clean_every`` (integrations between two
    automatic :meth:`clean` calls) and/or ``clean_period`` (s of stamp time between two; both 0 =
    only when the caller calls :meth:`clean`); ``min_depth``/``max_depth`` (m,
    points of the camera cloud outside are rejected); ``confidence`` (False = plain voxel grid);
    ``merge_duplicates``/``dup_normal``/``dup_lateral``/``dup_radius`` (m, fold of points coming of
    age into an older point of the same surface, :meth:`_merge_duplicates`; ``dup_radius`` default
    half a voxel); ``rekey`` (keys follow the running mean's voxel, one point per voxel and bin,
    :meth:`_rekey`); ``min_view_ratio`` (0 = off), ``view_window`` (s, at least ``grace``),
    ``view_bin`` (direction bin, tangent units) and ``view_margin`` (m, default 2 voxels) for the
    in-view confirmation (:meth:`_count_views`; off by default, here and in config/fusion.yaml);
    ``min_span`` (s, at most ``grace``; 0 = off): confirmation also needs this time between a
    point's first and last sighting.
    """

    def __init__(self, voxel_size: float = 0.02, radius: Optional[float] = None,
                 normal_angle_deg: float = 45.0, normal_radius: Optional[float] = None,
                 normal_max_nn: int = 16, min_confidence: int = 3, grace: float = 5.0,
                 clean_every: int = 10, min_depth: float = 0.1, max_depth: float = 20.0,
                 confidence: bool = True, initial_capacity: int = 1 << 16,
                 clean_period: float = 0.0, normal_method: str = "grid",
                 merge_duplicates: bool = True, dup_normal: Optional[float] = None,
                 dup_lateral: Optional[float] = None, rekey: bool = True,
                 dup_radius: Optional[float] = None, min_view_ratio: float = 0.0,
                 view_bin: float = 0.01, view_margin: Optional[float] = None,
                 view_window: float = 0.0, min_span: float = 0.0):
        if isinstance(voxel_size, Mapping):  # VoxelMap(params) == VoxelMap.from_config(params)
            other = VoxelMap.from_config(voxel_size)
            self.__dict__.update(other.__dict__)
            return
        if not voxel_size > 0:
            raise ValueError("voxel_size must be > 0")
        self.voxel_size = float(voxel_size)
        r = voxel_size if radius is None else float(radius)
        # the search covers the 2x2x2 voxel block around a point: radii beyond a voxel would miss
        self.radius = min(max(r, 0.0), voxel_size)
        self.normal_angle_deg = float(normal_angle_deg)
        self.cos_normal = float(np.cos(np.radians(normal_angle_deg)))
        self.normal_radius = float(normal_radius) if normal_radius else 4.0 * voxel_size
        self.normal_max_nn = int(normal_max_nn)
        if normal_method not in ("grid", "knn"):
            raise ValueError("normal_method must be 'grid' or 'knn', got %r" % (normal_method,))
        self.normal_method = normal_method
        # duplicates of a surface along its normal (see _merge_duplicates); 0 = off
        self.dup_normal = (float(dup_normal) if dup_normal else 1.5 * voxel_size) if merge_duplicates else 0.0
        self.dup_lateral = float(dup_lateral) if dup_lateral else voxel_size
        self.rekey = bool(rekey)  # keys follow the running mean's voxel (see _rekey)
        self.dup_radius = float(dup_radius) if dup_radius else 0.5 * voxel_size
        self.min_confidence = int(min_confidence)
        self.min_span = min(float(min_span or 0.0), float(grace))
        # in-view confirmation (see _count_views); 0 = off
        self.min_view_ratio = float(min_view_ratio) if min_view_ratio else 0.0
        self.view_bin = float(view_bin) if view_bin else 0.01
        self.view_margin = float(view_margin) if view_margin else 2.0 * voxel_size
        self.view_window = max(float(view_window or 0.0), float(grace))
        self.grace = float(grace)
        self.clean_every = int(clean_every)
        self.clean_period = float(clean_period)
        self.min_depth = float(min_depth)
        self.max_depth = float(max_depth)
        self.confidence = bool(confidence)
        self._initial_capacity = max(16, int(initial_capacity))
        self.reset()

    _CONFIG_KEYS = ("voxel_size", "radius", "normal_angle_deg", "normal_radius", "normal_max_nn",
                    "min_confidence", "grace", "clean_every", "clean_period", "min_depth",
                    "max_depth", "confidence", "normal_method", "merge_duplicates", "dup_normal",
                    "dup_lateral", "rekey", "dup_radius", "min_view_ratio", "view_bin", "view_margin",
                    "view_window", "min_span")

    @classmethod
    def from_config(cls, params, **overrides) -> "VoxelMap":
        """A map from the fusion node's parameters (``config/fusion.yaml`` as a dict; other keys
        are ignored, 0 for ``radius``/``normal_radius`` means the default), so the node and the
        offline runner build the same map."""
        kw = {k: params[k] for k in cls._CONFIG_KEYS if k in params}
        kw.update(overrides)
        for k in ("radius", "normal_radius", "dup_normal", "dup_lateral", "dup_radius", "view_margin"):
            if k in kw and not kw[k]:
                kw[k] = None
        return cls(**kw)

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Empty the map (keeps the parameters)."""
        import open3d.core as o3c
        self._o3c = o3c
        self._hash = o3c.HashMap(self._initial_capacity, key_dtype=o3c.int32,
                                 key_element_shape=(4,), value_dtypes=[o3c.int32],
                                 value_element_shapes=[(1,)], device=o3c.Device("CPU:0"))
        self._cap = 0
        self._a = {}
        self._grow(self._initial_capacity)
        self._top = 0                      # slots [0, _top) have been used
        self._free = np.zeros(0, np.int64)  # freed slots below _top, reused first
        self._n = 0
        # insertion batches awaiting their clean check: (grace start, slots, first_seen)
        self._pending = collections.deque()
        # confirmed points still counting views (until view_window): (start, slots, first_seen[])
        self._probation = collections.deque()
        self._probation_flat = None  # its slots and first_seen as two arrays (cache)
        self.anchors: Dict[int, np.ndarray] = {}
        self.n_integrations = 0
        self.last_stamp: Optional[float] = None  # the last stamp integrated, as given
        self._time_offset = 0.0            # map time = stamp + offset (see _map_time)
        self._t_last: Optional[float] = None  # latest map time seen (integrations, loaded points)
        self.n_removed = 0
        self.n_view_removed = 0            # confirmed points removed at the end of view_window
        self.n_duplicates = 0              # points folded into an older point by clean()
        self.n_rekeyed = 0                 # points whose key followed their mean into another voxel
        self.n_cell_folds = 0              # points folded into the holder of the voxel they moved into
        self._last_clean: Optional[float] = None

    def __len__(self) -> int:
        return self._n

    def _grow(self, cap: int) -> None:
        new = {}
        for name, (dt, shape) in _FIELDS.items():
            a = np.zeros((cap,) + shape, dtype=dt)
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

    def _tensor(self, a: np.ndarray):
        return self._o3c.Tensor.from_numpy(np.ascontiguousarray(a, dtype=np.int32))

    def _find(self, keys: np.ndarray) -> np.ndarray:
        """Slots of (M, 4) keys, -1 where absent (one batched hash lookup)."""
        if len(keys) == 0:
            return np.zeros(0, np.int64)
        buf, mask = self._hash.find(self._tensor(keys))
        mask = mask.numpy()
        out = np.full(len(keys), -1, np.int64)
        if mask.any():
            vals = self._hash.value_tensor().numpy().reshape(-1)
            out[mask] = vals[buf.numpy()[mask]]
        return out

    def _insert(self, keys: np.ndarray, slots: np.ndarray) -> np.ndarray:
        """Insert key -> slot; returns the mask of keys that were inserted (False: already there)."""
        if len(keys) == 0:
            return np.zeros(0, bool)
        _, mask = self._hash.insert(self._tensor(keys), self._tensor(slots.reshape(-1, 1)))
        return mask.numpy().astype(bool)

    def _erase(self, keys: np.ndarray) -> None:
        if len(keys):
            self._hash.erase(self._tensor(keys))

    def _keys(self, pos: np.ndarray, bins: np.ndarray) -> np.ndarray:
        vox = np.floor(pos / self.voxel_size).astype(np.int64)
        return np.concatenate([vox, bins.reshape(-1, 1).astype(np.int64)], axis=1).astype(np.int32)

    # ------------------------------------------------------------------ fuse / update
    def _estimate_normals(self, P: np.ndarray, center: np.ndarray) -> np.ndarray:
        if self.normal_method == "grid":  # PCA over the 2x2x2 cells of normal_radius around P
            return grid_normals(P, center, self.normal_radius)
        import open3d as o3d
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(
            radius=self.normal_radius, max_nn=self.normal_max_nn))
        N = np.asarray(pcd.normals)
        if N.shape != P.shape:
            N = np.zeros_like(P)
            N[:, 2] = 1.0
        # orient towards the camera: a visible surface faces the viewpoint (n . (c - p) > 0)
        flip = np.einsum("ij,ij->i", N, center[None, :] - P) < 0
        N[flip] *= -1.0
        return N

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
        ok_range = np.all(np.abs(Pw) < (_KEY_LIMIT - 2) * self.voxel_size, axis=1)
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
        Nd = self._estimate_normals(Pd, center)
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
        if self.confidence and self.min_view_ratio > 0:
            self._count_views(P[ok][ok_range], T, target[matched])
        if matched.any():
            self._merge(target[matched], Pd[matched], Nd[matched], wd[matched], Id[matched], stamp)
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
            a["views"][slots] = 1
            a["first_seen"][slots] = stamp
            a["last_seen"][slots] = stamp
            a["anchor"][slots] = -1 if anchor_id is None else anchor_id
            a["key"][slots] = keys
            a["alive"][slots] = True
            self._n += len(slots)
            st["n_inserted"] = len(slots)
            if self.confidence and len(slots):
                self._pending.append((stamp, slots, stamp))  # (grace starts, slots, first_seen)
        self.n_integrations += 1
        if self.confidence:
            if self._last_clean is None:
                self._last_clean = stamp
            due = self.clean_every > 0 and self.n_integrations % self.clean_every == 0
            due |= self.clean_period > 0 and stamp - self._last_clean >= self.clean_period
            if due:
                self._last_clean = stamp
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

    def _count_views(self, Pc: np.ndarray, T: np.ndarray, hits: np.ndarray) -> None:
        """Count, for every point younger than ``view_window``, whether this cloud had it IN VIEW.

        The camera-frame cloud ``Pc`` is binned by viewing direction (``x/z``, ``y/z`` in steps of
        ``view_bin``, a coarse depth image without the camera model) keeping the nearest depth per
        bin. A young map point is in view when its bin holds a measurement that does not occlude
        it: nearest depth at least ``z - view_margin`` (the cloud saw the surface at the point, or
        saw THROUGH it: free-space evidence, as OctoMap's and voxblox's ray misses). Points this
        cloud associated with (``hits``) are in view by definition. Bins without measurements and
        occluded points give no evidence either way (low-texture surfaces the depth filter rarely
        converges on are not penalised). :meth:`clean` then keeps a point only when it was seen
        in at least ``min_view_ratio`` of the clouds that had it in view: a noise sample that a
        cloud produces now and then (one observation per lap, or a few correlated ones) stays
        below the ratio however many laps pass, while a real surface is seen nearly every time it
        is in view. Cost proportional to the cloud and the young points (those inserted in the
        last ``view_window`` seconds and not removed or folded since), not to the map.
        """
        if not self._pending and not self._probation:
            return
        a = self._a
        if self._probation_flat is None:  # the probation batches change only in clean()
            self._probation_flat = (
                np.concatenate([b[1] for b in self._probation] + [np.zeros(0, np.int64)]),
                np.concatenate([b[2] for b in self._probation] + [np.zeros(0)]))
        s = np.concatenate([self._probation_flat[0]] + [b[1] for b in self._pending])
        t0 = np.concatenate([self._probation_flat[1]] +
                            [np.full(len(b[1]), b[2]) for b in self._pending])
        s = np.unique(s[a["alive"][s] & (a["first_seen"][s] == t0)])
        if len(s) == 0:
            return
        Pc = Pc[Pc[:, 2] > 1e-6]
        iv = np.isin(s, hits)
        if len(Pc):
            lim = _KEY_LIMIT - 1

            def bins(X, z):  # direction bin of camera-frame points (one int64 each)
                d = np.column_stack([X[:, 0] / z, X[:, 1] / z, np.zeros(len(X))]) / self.view_bin
                return _pack(np.clip(np.floor(d), -lim, lim).astype(np.int64))

            kc = bins(Pc, Pc[:, 2])
            order = np.argsort(kc, kind="stable")
            kc, zc = kc[order], Pc[order, 2]
            first = np.concatenate([[0], np.nonzero(np.diff(kc))[0] + 1])
            ku, zmin = kc[first], np.minimum.reduceat(zc, first)
            Ti = inv_T(T)
            Q = a["pos"][s].astype(np.float64) @ Ti[:3, :3].T + Ti[:3, 3]
            front = Q[:, 2] > self.min_depth
            q, zq = Q[front], Q[front, 2]
            kq = bins(q, zq)
            j = np.minimum(np.searchsorted(ku, kq), len(ku) - 1)
            seen = (ku[j] == kq) & (zmin[j] >= zq - self.view_margin)
            iv[np.nonzero(front)[0][seen]] = True
        a["views"][s[iv]] += 1

    def _merge(self, t, P, N, w, I, stamp):
        """Weighted running mean of targets ``t`` (duplicates allowed) with new observations."""
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
            self._probation.clear()
            self._probation_flat = None
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
        if self.min_view_ratio > 0 and (full or self.view_window <= self.grace):
            conf = np.where(self._low_view_ratio(cand), 0, conf)
        bad = cand[conf < self.min_confidence]
        self._remove(bad)
        n_dup = 0
        if self.dup_normal > 0:
            n_dup = self._merge_duplicates(cand[conf >= self.min_confidence])
            self.n_duplicates += n_dup
        n_view = 0
        if self.min_view_ratio > 0 and self.view_window > self.grace and not full:
            # confirmed points keep counting views until view_window, then face the ratio
            good = cand[conf >= self.min_confidence]
            good = good[a["alive"][good]]
            if len(good):
                self._probation.append((now, good, a["first_seen"][good].copy()))
                self._probation_flat = None
            batches = []
            while self._probation and self._probation[0][0] <= now - (self.view_window - self.grace):
                _, s, t0 = self._probation.popleft()
                batches.append(s[a["alive"][s] & (a["first_seen"][s] == t0)])
                self._probation_flat = None
            if batches:
                done = np.concatenate(batches)
                low = done[self._low_view_ratio(done)]
                self._remove(low)
                self.n_view_removed += len(low)
                n_view = len(low)
        return len(bad) + n_dup + n_view

    def _low_view_ratio(self, slots: np.ndarray) -> np.ndarray:
        """Mask of the points seen in fewer than ``min_view_ratio`` of the clouds that had them in
        view (:meth:`_count_views`): noise that one cloud in many happens to produce. Folds add
        both counts, so the ratio survives them."""
        a = self._a
        return a["confidence"][slots] < self.min_view_ratio * a["views"][slots]

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
        gap2 = np.stack([frac + 1.0, frac, np.zeros_like(frac), 1.0 - frac, 2.0 - frac], axis=2) ** 2
        o = _BLOCK125 + 2
        d2 = gap2[:, 0, o[:, 0]] + gap2[:, 1, o[:, 1]] + gap2[:, 2, o[:, 2]]  # (n, 125)
        reach = max(np.hypot(self.dup_normal, self.dup_lateral), self.dup_radius) / self.voxel_size
        near = d2 <= reach * reach
        pi, bj, oi = np.nonzero(use[:, :, None] & near[:, None, :])
        qi = pi
        vox = pv[pi] + _BLOCK125[oi]
        bins = B[pi, bj]
        cand = self._find(np.concatenate([vox, bins[:, None]], axis=1).astype(np.int32))
        f = (cand >= 0)
        qi, cand = qi[f], cand[f]
        f = (cand != slots[qi]) & (a["first_seen"][cand] < a["first_seen"][slots[qi]])
        qi, cand = qi[f], cand[f]
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
        order = np.lexsort((dist, qi))  # the nearest older point of every duplicate
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
        """Move the points of corrected anchors rigidly: ``p' = T_new inv(T_old) p``.

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

    def _merge_slots(self, dst: np.ndarray, src: np.ndarray) -> None:
        """Fold map points ``src`` into ``dst`` (weighted; confidences add)."""
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
        a["views"][u] += np.bincount(inv, weights=a["views"][src], minlength=m).astype(np.int32)
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

    def to_cloud(self, min_confidence: int = 0, keys: bool = False) -> "OrderedDict[str, np.ndarray]":
        """The map as a cloud dict for :func:`mdr_slam.io.write_cloud` / PointCloud2.

        Fields: x, y, z, intensity, confidence, nx, ny, nz, weight, first_seen, last_seen,
        anchor_id, nbin, and with ``keys`` the hash voxel kx, ky, kz (the voxel of the position,
        except for a point that moved into a voxel held by a point whose normal disagrees, or
        with ``rekey=False``): everything :meth:`load` needs to restore the same map.
        """
        a = self._a
        s = self.live_slots()
        s = s[a["confidence"][s] >= min_confidence]
        p, n = a["pos"][s], a["normal"][s]
        out = OrderedDict([
            ("x", p[:, 0].copy()), ("y", p[:, 1].copy()), ("z", p[:, 2].copy()),
            ("intensity", a["intensity"][s].copy()), ("confidence", a["confidence"][s].copy()),
            ("nx", n[:, 0].copy()), ("ny", n[:, 1].copy()), ("nz", n[:, 2].copy()),
            ("weight", a["weight"][s].copy()), ("first_seen", a["first_seen"][s].copy()),
            ("last_seen", a["last_seen"][s].copy()),
            ("anchor_id", a["anchor"][s].astype(np.int32)),
            ("nbin", a["key"][s, 3].astype(np.uint8)),
        ])
        if keys:
            for i, k in enumerate(("kx", "ky", "kz")):
                out[k] = a["key"][s, i].copy()
        return out

    def save(self, path: str) -> int:
        """Write every point with all its state (PLY or PCD by extension, atomic).

        Anchor poses go to a sidecar ``<path>.anchors.json`` (also atomic) when there are any.
        Returns the number of points written.
        """
        from ..io import atomic_write, write_cloud
        n = write_cloud(path, self.to_cloud(0, keys=True))
        side = path + ".anchors.json"
        if self.anchors:
            data = {str(k): np.asarray(v).reshape(-1).tolist() for k, v in self.anchors.items()}
            atomic_write(side, json.dumps({"voxel_size": self.voxel_size, "anchors": data}), "w")
        elif os.path.exists(side):
            os.unlink(side)
        return n

    def load(self, path, append: bool = False) -> int:
        """Read a map written by :meth:`save` (or any PLY/PCD cloud with x, y, z); ``path`` may
        also be a cloud dict (as :meth:`to_cloud` returns) to add points directly.

        ``append=False`` replaces the map. Missing fields get defaults (confidence =
        ``min_confidence`` so a plain cloud survives cleaning, normals +z). Points that fall on an
        occupied key are merged. Returns the number of points in the map afterwards.
        """
        from ..io import read_cloud
        c = read_cloud(path) if isinstance(path, str) else path
        if not all(k in c for k in "xyz"):
            raise ValueError("%s has no x, y, z fields" % (path if isinstance(path, str) else "cloud"))
        side = path + ".anchors.json" if isinstance(path, str) else ""
        anchors = {}
        if side and os.path.exists(side):
            with open(side) as f:
                anchors = {int(k): np.asarray(v, dtype=np.float64).reshape(4, 4)
                           for k, v in json.load(f)["anchors"].items()}
        if not append:
            self.reset()
        self.anchors.update(anchors)
        P = np.stack([c["x"], c["y"], c["z"]], 1).astype(np.float64)
        n = len(P)

        def get(name, default, dt):
            return np.asarray(c[name], dtype=dt) if name in c else np.full(n, default, dt)

        ok = np.all(np.isfinite(P), axis=1)
        if all(k in c for k in ("nx", "ny", "nz")):
            N = np.stack([c["nx"], c["ny"], c["nz"]], 1).astype(np.float64)
        else:
            N = np.tile([0.0, 0.0, 1.0], (n, 1))
        if self.confidence:
            b = get("nbin", -1, np.int32)
            b = np.where((b >= 0) & (b < 6), b, normal_bins(N)[0]) if n else b
        else:
            b = np.zeros(n, np.int32)
        keys = self._keys(P, b)
        if n and all(k in c for k in ("kx", "ky", "kz")):
            saved = np.stack([c["kx"], c["ky"], c["kz"]], 1).astype(np.int64)
            # saved voxels are only valid for the same voxel size: then every point lies in or
            # next to its saved voxel (the running mean drifts by less than a voxel)
            if np.all(np.abs(saved[ok] - keys[ok, :3]) <= 1):
                keys[:, :3] = saved
        sel = np.nonzero(ok)[0]
        slots = self._alloc(len(sel))
        a = self._a
        a["pos"][slots] = P[sel]
        a["normal"][slots] = N[sel]
        a["weight"][slots] = get("weight", 1.0, np.float32)[sel]
        a["intensity"][slots] = get("intensity", 0.0, np.float32)[sel]
        a["confidence"][slots] = get("confidence", max(self.min_confidence, 1), np.int32)[sel]
        a["views"][slots] = a["confidence"][slots]  # not saved: a loaded point counts as confirmed
        a["first_seen"][slots] = get("first_seen", 0.0, np.float64)[sel]
        a["last_seen"][slots] = get("last_seen", 0.0, np.float64)[sel]
        a["anchor"][slots] = get("anchor_id", -1, np.int64)[sel]
        a["key"][slots] = keys[sel]
        a["alive"][slots] = True
        if len(slots):  # the map's clock continues after the loaded points (see _map_time)
            t_max = float(np.max(a["last_seen"][slots]))
            if np.isfinite(t_max) and (self._t_last is None or t_max > self._t_last):
                self._t_last = t_max
        self._n += len(slots)
        ins = self._insert(keys[sel], slots)
        if not ins.all():
            lost = slots[~ins]
            occ = self._find(keys[sel][~ins])  # occupant: an earlier point or a duplicate in the file
            okk = occ >= 0
            self._merge_slots(occ[okk], lost[okk])
            a["alive"][lost] = False
            self._free = np.concatenate([self._free, lost])
            self._n -= len(lost)
        return self._n

    # ------------------------------------------------------------------ occupancy grid
    def occupancy_grid(self, resolution: float = 0.05, z_min: float = 0.1, z_max: float = 1.5,
                       min_confidence: Optional[int] = None, up_axis: str = "z",
                       free_band: float = 0.3):
        """2-D occupancy grid for planners (move_base) from the confident map points (default
        ``min_confidence`` of the map; all points for ``confidence=False``).

        See :func:`mdr_slam.fusion.grid.occupancy_grid` for the cell values and the frame.
        Returns ``(grid int8 (H, W), origin (x, y), resolution)``.
        """
        from .grid import occupancy_grid
        mc = self.min_confidence if min_confidence is None else min_confidence
        if not self.confidence and min_confidence is None:
            mc = 0
        return occupancy_grid(self.points(mc), resolution, z_min, z_max, up_axis, free_band)

    # ------------------------------------------------------------------ misc
    def close(self) -> None:
        """Free the hash table now (Open3D reports tensors still alive at interpreter exit as
        leaks); the map is empty afterwards and :meth:`reset` makes it usable again."""
        self._hash = None
        self._a = {k: v[:0] for k, v in self._a.items()}
        self._cap = self._top = self._n = 0
        self._free = np.zeros(0, np.int64)
        self._pending.clear()
        self._probation.clear()
        self._probation_flat = None

    def memory_bytes(self) -> int:
        """Bytes held by the slot arrays and the hash table (an estimate of the map's footprint)."""
        arrays = sum(v.nbytes for v in self._a.values())
        return int(arrays + self._hash.capacity() * (16 + 4 + 16))

    def __repr__(self):
        return "VoxelMap(%d points, voxel %.3f m, confidence=%s)" % (
            self._n, self.voxel_size, self.confidence)
