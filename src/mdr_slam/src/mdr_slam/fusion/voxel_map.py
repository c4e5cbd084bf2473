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
* in view (``min_view_ratio`` > 0): the count alone confirms any sample that a few correlated
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

The map is one class, :class:`VoxelMap`, assembled from mixins along its jobs: storage
(:mod:`.layer`), fuse/update (:mod:`.integrator`), clean (:mod:`.cleaning`), keyframe anchors
(:mod:`.anchors`) and file I/O (:mod:`.map_io`); per-cloud helpers are in :mod:`.cloud`.
"""
from __future__ import annotations

import collections
from typing import Dict, Mapping, Optional

import numpy as np

from .anchors import AnchorCorrections
from .cleaning import VoxelCleaning
from .cloud import grid_normals, normal_bins, voxel_downsample
from .integrator import IntegrationStats, VoxelIntegrator
from .layer import VoxelLayer
from .map_io import MapIO

__all__ = ["VoxelMap", "IntegrationStats", "normal_bins", "voxel_downsample", "grid_normals"]


class VoxelMap(VoxelLayer, VoxelIntegrator, VoxelCleaning, AnchorCorrections, MapIO):
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
        self._reset_storage()
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
        self._close_storage()
        self._pending.clear()
        self._probation.clear()
        self._probation_flat = None

    def __repr__(self):
        return "VoxelMap(%d points, voxel %.3f m, confidence=%s)" % (
            self._n, self.voxel_size, self.confidence)
