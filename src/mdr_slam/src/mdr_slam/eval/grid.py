"""The planner's occupancy grid against the true occupancy of a simulated scene.

Both grids come from :func:`mdr_slam.fusion.occupancy_grid`, the function behind the fusion node's
``/mdr/map/grid``, with the node's parameters (FusionNodeConfig: ``grid_resolution``,
``grid_z_min``/``grid_z_max`` band, ``grid_up_axis``, ``grid_free_band``): the true grid from the
simulator's ground-truth map (every surface point the camera saw), the estimated one from a run's
map, keeping the points of confidence ``>= grid_min_confidence`` as the node does (all points of a
map without confidence, e.g. the plain voxel grid or a peer's cloud). Cells are compared whole, on
one lattice (``occupancy_grid`` puts cell edges at multiples of the resolution, so its origin
divided by the resolution is an integer cell offset): the obstacle cells (value 100) of both
grids, and the estimate's free cells (0) against the true obstacle cells.

* recall: share of true obstacle cells with an estimated obstacle cell within ``tolerance`` cells
  (Chebyshev distance: one cell of tolerance includes the diagonal neighbours), also per surface
  label (a true cell belongs to every label of a point in it) and, with a camera path, for the true
  cells of the points within ``max_range`` of the path;
* precision: share of estimated obstacle cells with a true obstacle cell within ``tolerance``,
  also, with a camera path, for the estimated cells of the estimated points within ``max_range``
  of the path (against ALL true cells, so a cell is not penalised for a wall just beyond range);
* route: cells the camera's ground projection passes through (the path sampled every quarter
  cell, a footprint of one cell) that the estimated grid marks occupied. The camera went there,
  so an obstacle there is a phantom that would block a planner: it must be 0;
* free precision: share of the estimated grid's free cells (value 0: mapped floor, or crossed by
  a ray) that are not true obstacle cells (no tolerance: a ray or a floor point that frees a
  wall's cell is an error a planner would drive into).

The estimated grid is built as the node builds it: with free space along the rays from the
points' views when the map has them (``map.ply``'s ``view_x, view_y, view_z``, parameter
``grid_raytrace``) and wall gaps of at most ``grid_max_gap`` closed; the true grid from the
ground-truth points alone (no views, no gap closing: the truth is not repaired).
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Dict, Optional

import numpy as np

from ..fusion.grid import grid_axes, occupancy_grid
from .map import SURFACE_LABELS, path_positions, within_range

__all__ = ["grid_params", "grid_cells", "obstacle_cells", "route_cells", "cells_near",
           "grid_metrics"]

OCCUPIED = 100
FREE = 0


def grid_params(**overrides) -> Dict[str, object]:
    """The fusion node's grid parameters (FusionNodeConfig defaults, as config/fusion.yaml ships
    them) under the keyword names of :func:`grid_metrics` (plus ``raytrace``: whether the map's
    views are used); ``overrides`` replace them (strings are converted, e.g. from ``--set``)."""
    from ..nodes.config import FusionNodeConfig   # ROS-free dataclass
    c = FusionNodeConfig()
    out = OrderedDict([("resolution", float(c.grid_resolution)), ("z_min", float(c.grid_z_min)),
                       ("z_max", float(c.grid_z_max)), ("up_axis", str(c.grid_up_axis)),
                       ("free_band", float(c.grid_free_band)),
                       ("min_confidence", int(c.grid_min_confidence)),
                       ("raytrace", bool(c.grid_raytrace)),
                       ("raytrace_range", float(c.grid_raytrace_range)),
                       ("max_gap", float(c.grid_max_gap))])
    for k, v in overrides.items():
        if k not in out:
            raise ValueError("unknown grid parameter %r (known: %s)" % (k, ", ".join(out)))
        if v is None:
            continue
        if isinstance(out[k], bool) and isinstance(v, str):
            word = v.strip().lower()
            if word not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
                raise ValueError("grid parameter %s must be true or false, got %r" % (k, v))
            v = word in ("true", "1", "yes", "on")
        out[k] = type(out[k])(v)
    return out


def grid_cells(points: np.ndarray, resolution: float = 0.05, z_min: float = 0.1,
               z_max: float = 1.5, up_axis: str = "z", free_band: float = 0.3,
               views: Optional[np.ndarray] = None, max_gap: float = 0.0,
               raytrace_range: float = 0.0):
    """``(occupied, free)``: (N, 2) int64 lattice cells ``(i, j)`` (grid-plane x and y over
    ``resolution``, floored) that :func:`mdr_slam.fusion.occupancy_grid` of ``points`` (and
    their ``views``, NaN rows: no ray) marks occupied and free. Non-finite points are dropped."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ok = np.all(np.isfinite(P), axis=1)
    if views is not None:
        views = np.asarray(views, dtype=np.float64).reshape(-1, 3)
        if len(views) != len(P):
            raise ValueError("%d views for %d points" % (len(views), len(P)))
        views = views[ok]
    P = P[ok]
    if len(P) == 0:
        return np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64)
    grid, origin, res = occupancy_grid(P, resolution, z_min, z_max, up_axis, free_band, views,
                                       max_gap, raytrace_range)
    off = np.rint(np.asarray(origin) / res).astype(np.int64)

    def cells(value):
        rows, cols = np.nonzero(grid == value)
        return np.stack([cols + off[0], rows + off[1]], axis=1).astype(np.int64)
    return cells(OCCUPIED), cells(FREE)


def obstacle_cells(points: np.ndarray, resolution: float = 0.05, z_min: float = 0.1,
                   z_max: float = 1.5, up_axis: str = "z", free_band: float = 0.3,
                   views: Optional[np.ndarray] = None, max_gap: float = 0.0,
                   raytrace_range: float = 0.0) -> np.ndarray:
    """(N, 2) int64 lattice cells ``(i, j)`` (grid-plane x and y over ``resolution``, floored)
    that :func:`mdr_slam.fusion.occupancy_grid` of ``points`` marks occupied (with ``views``
    and ``max_gap``, as :func:`grid_cells`)."""
    return grid_cells(points, resolution, z_min, z_max, up_axis, free_band, views, max_gap,
                      raytrace_range)[0]


def route_cells(path, resolution: float = 0.05, up_axis: str = "z") -> np.ndarray:
    """(N, 2) int64 lattice cells the ground projection of the camera path (a Trajectory or (K, 3)
    positions) passes through: the segments between consecutive positions sampled every quarter
    cell, so a fast step does not skip a cell."""
    P = path_positions(path)
    Q = (P @ grid_axes(up_axis).T)[:, :2]
    if len(Q) > 1:
        seg = np.diff(Q, axis=0)
        n = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / (0.25 * resolution)), 1).astype(np.int64)
        idx = np.repeat(np.arange(len(seg)), n)
        k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        Q = np.vstack([Q[idx] + seg[idx] * (k / n[idx])[:, None], Q[-1:]])
    return np.unique(np.floor(Q / resolution).astype(np.int64), axis=0)


def _keys(cells: np.ndarray) -> np.ndarray:
    # one int64 per cell: lattice indices stay far below 2**31 for any map in metres
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
    return (c[:, 0] << 32) + (c[:, 1] & 0xFFFFFFFF)


def cells_near(cells: np.ndarray, ref: np.ndarray, tolerance: int = 1) -> np.ndarray:
    """Boolean mask of ``cells`` (N, 2) with a ``ref`` cell within ``tolerance`` cells (Chebyshev
    distance): one sorted-key membership test per offset of the (2t+1)^2 neighbourhood."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
    ref_keys = np.unique(_keys(ref))
    hit = np.zeros(len(cells), bool)
    if len(cells) == 0 or len(ref_keys) == 0:
        return hit
    t = int(tolerance)
    for di in range(-t, t + 1):
        for dj in range(-t, t + 1):
            hit |= np.isin(_keys(cells + [di, dj]), ref_keys, assume_unique=False)
    return hit


def _share(mask: np.ndarray) -> Optional[float]:
    return float(mask.mean()) if len(mask) else None


def _label_recall(gt, labels, est_cells, kw, tolerance):
    per = OrderedDict()
    for lab in np.unique(labels):
        true_l = obstacle_cells(gt[labels == lab], **kw)
        found = cells_near(true_l, est_cells, tolerance)
        per[SURFACE_LABELS.get(int(lab), "label_%d" % lab)] = {
            "label": int(lab), "n_true_cells": int(len(true_l)), "recall": _share(found)}
    return per


def grid_metrics(est_xyz: np.ndarray, gt_xyz: np.ndarray, gt_labels: Optional[np.ndarray] = None,
                 path=None, est_confidence: Optional[np.ndarray] = None,
                 min_confidence: int = 3, resolution: float = 0.05, z_min: float = 0.1,
                 z_max: float = 1.5, up_axis: str = "z", free_band: float = 0.3,
                 tolerance: int = 1, max_range: Optional[float] = None,
                 est_views: Optional[np.ndarray] = None, max_gap: float = 0.0,
                 raytrace_range: float = 0.0) -> Dict[str, object]:
    """Obstacle-cell recall and precision of the grid of ``est_xyz`` against that of ``gt_xyz``,
    the estimated obstacles on the camera's route and the free cells' precision (see the module
    docstring).

    ``est_confidence`` (N,): only estimated points with ``confidence >= min_confidence`` mark
    cells (None: all points). ``est_views`` (N, 3): the camera centre each estimated point was
    last seen from (NaN rows: none) for the estimated grid's rays (None: no rays);
    ``max_gap``, ``raytrace_range``: the node's ``grid_max_gap``, ``grid_raytrace_range`` for
    the estimated grid (the defaults here are off; :func:`grid_params` has the node's).
    ``gt_labels`` (M,) adds per-label recall; ``path`` (a Trajectory or (K, 3) positions in the
    map frame) adds ``route`` and, with ``max_range``, ``in_range``: the recall of the true
    cells of the ground-truth points within ``max_range`` m of the path and the precision of the
    estimated cells of the estimated points within it.
    """
    est = np.asarray(est_xyz, dtype=np.float64).reshape(-1, 3)
    gt = np.asarray(gt_xyz, dtype=np.float64).reshape(-1, 3)
    views = None
    if est_views is not None:
        views = np.asarray(est_views, dtype=np.float64).reshape(-1, 3)
        if len(views) != len(est):
            raise ValueError("%d views for %d estimated points" % (len(views), len(est)))
    if est_confidence is not None:
        conf = np.asarray(est_confidence).reshape(-1)
        if len(conf) != len(est):
            raise ValueError("%d confidences for %d estimated points" % (len(conf), len(est)))
        est = est[conf >= min_confidence]
        if views is not None:
            views = views[conf >= min_confidence]
    labels = None
    if gt_labels is not None:
        labels = np.asarray(gt_labels).reshape(-1).astype(int)
        if len(labels) != len(gt):
            raise ValueError("%d ground-truth labels for %d points" % (len(labels), len(gt)))
    if path is not None:
        path = path_positions(path)
    kw = dict(resolution=float(resolution), z_min=float(z_min), z_max=float(z_max),
              up_axis=up_axis, free_band=float(free_band))
    true_cells = obstacle_cells(gt, **kw)
    if len(true_cells) == 0:
        raise ValueError("the ground-truth cloud has no point in the obstacle band [%g, %g] m "
                         "along %s" % (z_min, z_max, up_axis))
    est_cells, free_cells = grid_cells(est, views=views, max_gap=float(max_gap),
                                       raytrace_range=float(raytrace_range), **kw)
    found = cells_near(true_cells, est_cells, tolerance)
    right = cells_near(est_cells, true_cells, tolerance)
    free_ok = ~cells_near(free_cells, true_cells, 0)
    out = OrderedDict([
        ("resolution", float(resolution)), ("z_min", float(z_min)), ("z_max", float(z_max)),
        ("up_axis", up_axis), ("tolerance_cells", int(tolerance)),
        ("min_confidence", int(min_confidence) if est_confidence is not None else None),
        ("n_est_points", int(len(est))),
        ("n_true_cells", int(len(true_cells))), ("n_est_cells", int(len(est_cells))),
        ("recall", _share(found)), ("precision", _share(right)),
        ("raytrace", views is not None), ("max_gap", float(max_gap)),
        ("n_est_free_cells", int(len(free_cells))), ("free_precision", _share(free_ok))])
    if labels is not None:
        out["per_label"] = _label_recall(gt, labels, est_cells, kw, tolerance)
    if path is not None:
        if max_range is not None:
            near = within_range(gt, path, max_range)
            true_r = obstacle_cells(gt[near], **kw)
            # the estimated points' own cells (occupied wins over free in the grid, so they are
            # cells of est_cells; a gap closed between walls is not a point's cell)
            est_r = obstacle_cells(est[within_range(est, path, max_range)], **kw)
            rng = OrderedDict([("max_range_m", float(max_range)),
                               ("n_true_cells", int(len(true_r))),
                               ("recall", _share(cells_near(true_r, est_cells, tolerance))),
                               ("n_est_cells", int(len(est_r))),
                               ("precision", _share(cells_near(est_r, true_cells, tolerance)))])
            if labels is not None:
                rng["per_label"] = _label_recall(gt[near], labels[near], est_cells, kw, tolerance)
            out["in_range"] = rng
        route = route_cells(path, resolution, up_axis)
        rk = _keys(route)
        out["route"] = OrderedDict([
            ("n_cells", int(len(route))),
            ("occupied_est", int(np.isin(rk, _keys(est_cells)).sum())),
            ("occupied_true", int(np.isin(rk, _keys(true_cells)).sum()))])
    return out
