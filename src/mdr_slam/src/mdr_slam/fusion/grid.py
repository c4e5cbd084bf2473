"""Occupancy-grid helpers: the grid plane of an ``up`` axis and its pose in ``map``."""
from __future__ import annotations

import numpy as np

__all__ = ["grid_axes", "grid_origin_T", "occupancy_grid"]

_AXES = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}


def grid_axes(up_axis: str = "z") -> np.ndarray:
    """3x3 matrix whose rows are the grid's x axis, y axis and up axis in ``map`` coordinates.

    The three rows form a right-handed frame (x × y = up). For ``'z'`` this is the identity, so
    REP-105 maps give the usual move_base grid; for ``'-y'`` (a map in a camera optical frame) the
    grid spans (x, z).
    """
    s = str(up_axis).strip().lower()
    sign = -1.0 if s.startswith("-") else 1.0
    name = s.lstrip("+-")
    if name not in _AXES:
        raise ValueError("up_axis must be one of x, y, z, -x, -y, -z (got %r)" % (up_axis,))
    up = sign * _AXES[name]
    gx = next(_AXES[k] for k in "xyz" if k != name)
    gy = np.cross(up, gx)
    return np.stack([gx, gy, up])


def grid_origin_T(origin_xy, up_axis: str = "z", height: float = 0.0) -> np.ndarray:
    """4x4 pose in ``map`` of the grid's cell (0, 0) corner (nav_msgs/OccupancyGrid info.origin)."""
    A = grid_axes(up_axis)
    T = np.eye(4)
    T[:3, :3] = A.T  # columns: grid axes in map
    T[:3, 3] = A.T @ np.array([origin_xy[0], origin_xy[1], height])
    return T


def occupancy_grid(points: np.ndarray, resolution: float = 0.05, z_min: float = 0.1,
                   z_max: float = 1.5, up_axis: str = "z", free_band: float = 0.3):
    """2-D occupancy grid (nav_msgs/OccupancyGrid values) of map points.

    Heights are measured along ``up_axis`` ('x', 'y', 'z', '-x', '-y' or '-z'; e.g. '-y' for a
    map in the first camera's optical frame). Points with height in ``[z_min, z_max]`` mark their
    cell occupied (100); cells with only floor points (height in ``[z_min - free_band, z_min)``)
    are free (0: the floor was seen there and nothing stands on it up to the obstacle band);
    every other cell is unknown (-1). Free space is not ray-traced: a cell is free only where the
    floor itself was mapped.

    Returns ``(grid int8 (H, W), origin (x, y), resolution)``: cell ``(row, col)`` covers
    ``[x0 + col*res, x0 + (col+1)*res) x [y0 + row*res, y0 + (row+1)*res)`` in the grid plane,
    whose axes are :func:`grid_axes` (``(x, y)`` for ``up_axis='z'``), row-major with row 0 at
    ``origin`` as nav_msgs/OccupancyGrid; :func:`grid_origin_T` gives ``info.origin``.
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    A = grid_axes(up_axis)  # rows: grid x axis, grid y axis, up
    Q = P @ A.T
    h = Q[:, 2]
    occ = (h >= z_min) & (h <= z_max)
    floor = (h < z_min) & (h >= z_min - free_band)
    use = occ | floor
    if not use.any():
        return np.full((1, 1), -1, np.int8), (0.0, 0.0), float(resolution)
    ij = np.floor(Q[use, :2] / resolution).astype(np.int64)
    lo = ij.min(0)
    ij -= lo
    W, H = ij.max(0) + 1
    grid = np.full((int(H), int(W)), -1, np.int8)
    fl = floor[use]
    grid[ij[fl, 1], ij[fl, 0]] = 0
    grid[ij[~fl, 1], ij[~fl, 0]] = 100   # occupied wins over floor in the same cell
    return grid, (float(lo[0] * resolution), float(lo[1] * resolution)), float(resolution)
