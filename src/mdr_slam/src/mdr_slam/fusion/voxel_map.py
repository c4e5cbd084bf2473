"""Confidence-based global map of node 3 (paper section 3.4): a hashed voxel map with a
fuse-update-clean cycle.

Data layout
-----------
Map points live in flat numpy arrays ("slots", structure of arrays, capacity doubled when full so
appending is amortised O(1)). A hash map (:class:`~mdr_slam.fusion.hash_map.KeyHash`, numpy) maps a
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
  moments (:func:`grid_normals`, no KD-tree: about 4x cheaper than Open3D's ``estimate_normals``).
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

Map time
--------
Ages (grace, which of two points is older) are measured in map time: the stamps,
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

Views
-----
Every point also keeps its ``view``: the camera centre (map frame) of the latest cloud that
created or updated it. The occupancy grid traces a ray from the view to the point to mark free
space. A correction moves the view with the point (same rigid motion), so the ray stays the
one that was observed; a fold of one point into another keeps the view of the more recent
sighting (a missing view, NaN, never replaces one). Saved and loaded with the map
(``view_x``, ``view_y``, ``view_z``; NaN, i.e. no ray, for a map file without them).

The map is one class, :class:`VoxelMap`, assembled from mixins along its jobs: storage
(:mod:`.layer`), fuse/update (:mod:`.integrator`), clean (:mod:`.cleaning`), keyframe anchors
(:mod:`.anchors`) and file I/O (:mod:`.map_io`); per-cloud helpers are in :mod:`.cloud`.
"""
from __future__ import annotations

import collections
from typing import Dict, Mapping, Optional, Union

import numpy as np

from .anchors import AnchorCorrections
from .cleaning import VoxelCleaning
from .cloud import grid_normals, normal_bins, voxel_downsample
from .config import VoxelMapConfig
from .integrator import IntegrationStats, VoxelIntegrator
from .layer import VoxelLayer
from .map_io import MapIO

__all__ = ["VoxelMap", "IntegrationStats", "normal_bins", "voxel_downsample", "grid_normals"]


def _config_of(config) -> VoxelMapConfig:
    if config is None:
        return VoxelMapConfig()
    if isinstance(config, VoxelMapConfig):
        return config
    if isinstance(config, Mapping):  # e.g. a whole fusion.yaml: the node's own keys are skipped
        return VoxelMapConfig.from_dict(config, ignore=set(config) - set(VoxelMapConfig.keys()))
    if isinstance(config, (int, float)) and not isinstance(config, bool):
        return VoxelMapConfig(voxel_size=config)
    raise TypeError("VoxelMap wants a VoxelMapConfig, a mapping of its parameters or a voxel "
                    "size, got %r" % (config,))


class VoxelMap(VoxelLayer, VoxelIntegrator, VoxelCleaning, AnchorCorrections, MapIO):
    """Hashed voxel map with per-point confidence (see the module docstring).

    ``VoxelMap(config=None, **overrides)``: ``config`` a
    :class:`~mdr_slam.fusion.config.VoxelMapConfig` (the parameters, each explained there), a
    mapping of its fields (other keys are skipped, so a whole ``config/fusion.yaml`` works: the
    node and the offline runner build the same map), or a number, the voxel size
    (``VoxelMap(0.05, grace=2.0)``); keyword ``overrides`` change single fields and are checked
    (an unknown name or a wrong type raises :class:`~mdr_slam.config.ConfigError`).
    ``initial_capacity``: slots allocated up front (the arrays double when full).

    ``cfg`` is the configuration as given (0 = derived default); the attributes ``voxel_size``,
    ``radius``, ``normal_radius``, ``dup_*``, ``min_span``, ... are the values in use.
    """

    def __init__(self, config: Union[None, float, VoxelMapConfig, Mapping] = None, *,
                 initial_capacity: int = 1 << 16, **overrides):
        cfg = _config_of(config)
        if overrides:
            cfg = cfg.replace(**overrides)
        self.cfg = cfg
        v = self.voxel_size = cfg.voxel_size
        # the search covers the 2x2x2 voxel block around a point: radii beyond a voxel would miss
        self.radius = min(max(cfg.radius or v, 0.0), v)
        self.normal_angle_deg = cfg.normal_angle_deg
        self.cos_normal = float(np.cos(np.radians(cfg.normal_angle_deg)))
        self.normal_radius = cfg.normal_radius or 4.0 * v
        # duplicates of a surface along its normal (see _merge_duplicates); 0 = off
        self.dup_normal = (cfg.dup_normal or 1.5 * v) if cfg.merge_duplicates else 0.0
        self.dup_lateral = cfg.dup_lateral or v
        self.dup_radius = cfg.dup_radius or 0.5 * v
        self.rekey = cfg.rekey  # keys follow the running mean's voxel (see _rekey)
        self.min_confidence = cfg.min_confidence
        self.grace = cfg.grace
        self.min_span = min(cfg.min_span, cfg.grace)
        self.clean_every = cfg.clean_every
        self.min_depth = cfg.min_depth
        self.max_depth = cfg.max_depth
        self.confidence = cfg.confidence
        self._initial_capacity = max(16, int(initial_capacity))
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Empty the map (keeps the parameters)."""
        self._reset_storage()
        # insertion batches awaiting their clean check: (grace start, slots, first_seen)
        self._pending = collections.deque()
        self.anchors: Dict[int, np.ndarray] = {}
        self.n_integrations = 0
        self.last_stamp: Optional[float] = None  # the last stamp integrated, as given
        self._time_offset = 0.0            # map time = stamp + offset (see _map_time)
        self._t_last: Optional[float] = None  # latest map time seen (integrations, loaded points)
        self.n_removed = 0
        self.n_duplicates = 0              # points folded into an older point by clean()
        self.n_rekeyed = 0                 # points whose key followed their mean into another voxel
        self.n_cell_folds = 0              # points folded into the holder of the voxel they moved into

    # ------------------------------------------------------------------ occupancy grid
    def occupancy_grid(self, resolution: float = 0.05, z_min: float = 0.1, z_max: float = 1.5,
                       min_confidence: Optional[int] = None, up_axis: str = "z",
                       free_band: float = 0.3, raytrace: bool = True, max_gap: float = 0.5,
                       raytrace_range: float = 0.0):
        """2-D occupancy grid for planners (move_base) from the confident map points (default
        ``min_confidence`` of the map; all points for ``confidence=False``), with free space
        along the rays from the points' views (``raytrace``) and wall gaps of at most
        ``max_gap`` m closed (defaults: the fusion node's).

        See :func:`mdr_slam.fusion.grid.occupancy_grid` for the cell values and the frame.
        Returns ``(grid int8 (H, W), origin (x, y), resolution)``.
        """
        from .grid import occupancy_grid
        mc = self.min_confidence if min_confidence is None else min_confidence
        if not self.confidence and min_confidence is None:
            mc = 0
        s = self.live_slots()
        s = s[self._a["confidence"][s] >= mc]
        views = self._a["view"][s] if raytrace else None
        return occupancy_grid(self._a["pos"][s].astype(np.float64), resolution, z_min, z_max,
                              up_axis, free_band, views, max_gap, raytrace_range)

    # ------------------------------------------------------------------ misc
    def close(self) -> None:
        """Free the hash table and the slot arrays now; the map is empty afterwards and
        :meth:`reset` makes it usable again."""
        self._close_storage()
        self._pending.clear()

    def __repr__(self):
        return "VoxelMap(%d points, voxel %.3f m, confidence=%s)" % (
            self._n, self.voxel_size, self.confidence)
