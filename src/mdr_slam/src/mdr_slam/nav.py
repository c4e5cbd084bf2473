"""Grid path planning on the fusion node's occupancy grid (ROS-free).

The grid is the one :func:`mdr_slam.fusion.occupancy_grid` builds and the fusion node publishes as
``/mdr/map/grid`` (nav_msgs/OccupancyGrid values: 100 occupied, 0 free, -1 unknown; row-major,
row 0 at ``origin``; cell ``(row, col)`` covers ``[x0 + col*res, x0 + (col+1)*res) x
[y0 + row*res, y0 + (row+1)*res)`` in the grid plane, which is the ``map`` x-y plane for the
default up axis ``z``). This module is a small stand-in for a move_base global planner, used to
check that the published map is plannable:

* :func:`world_to_cell` / :func:`cell_to_world` convert between grid-plane metres and cells;
* :func:`traversable` marks the cells a disc robot of ``robot_radius`` can stand on (obstacles
  inflated with SciPy's Euclidean distance transform; unknown cells are not traversable unless
  ``unknown_traversable``);
* :func:`plan_path` finds a shortest 8-connected path (no corner cutting) with A* (a heap over the
  search frontier) or with SciPy's compiled Dijkstra on the free-cell graph built vectorized;
* :func:`map_products` is what the fusion node publishes from one snapshot of its map: the
  display/obstacle cloud ``/mdr/map/points`` and the grid ``/mdr/map/grid`` (the node calls it, so
  tests check the published contract without ROS); :func:`map_views` reads a map cloud's views.
"""
from __future__ import annotations

import heapq
import math
from typing import NamedTuple, Optional, Tuple

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from .fusion import free_footprint, grid_axes, occupancy_grid, voxel_downsample

__all__ = ["Plan", "world_to_cell", "cell_to_world", "grid_from_msg", "traversable", "plan_path",
           "map_min_confidence", "map_views", "map_products"]

_SQRT2 = math.sqrt(2.0)
# 8-neighbourhood (drow, dcol) and step length in cells
_MOVES = [(-1, 0, 1.0), (1, 0, 1.0), (0, -1, 1.0), (0, 1, 1.0),
          (-1, -1, _SQRT2), (-1, 1, _SQRT2), (1, -1, _SQRT2), (1, 1, _SQRT2)]


class Plan(NamedTuple):
    """A planned path: ``cells`` (N, 2) int (row, col), ``xy`` (N, 2) cell centres in metres
    (grid plane) and ``length`` in metres (sum of the steps between cell centres)."""
    cells: np.ndarray
    xy: np.ndarray
    length: float


def world_to_cell(xy, origin, resolution: float) -> np.ndarray:
    """(N, 2) or (2,) grid-plane metres -> int (row, col) of the cells containing them (may lie
    outside the grid: compare with its shape)."""
    q = np.asarray(xy, dtype=np.float64)
    col_row = np.floor((q - np.asarray(origin, dtype=np.float64)) / float(resolution))
    return col_row[..., ::-1].astype(np.int64)


def cell_to_world(cells, origin, resolution: float) -> np.ndarray:
    """(N, 2) or (2,) int (row, col) -> grid-plane metres of the cell centres."""
    rc = np.asarray(cells, dtype=np.float64)
    return np.asarray(origin, dtype=np.float64) + (rc[..., ::-1] + 0.5) * float(resolution)


def grid_from_msg(msg) -> Tuple[np.ndarray, Tuple[float, float], float]:
    """``(grid int8 (H, W), origin (x, y), resolution)`` of a nav_msgs/OccupancyGrid (duck-typed:
    anything with ``info`` and ``data``). Only an axis-aligned origin (identity orientation) is
    supported, as the fusion node publishes for ``grid_up_axis: z``."""
    info = msg.info
    q = info.origin.orientation
    if not np.allclose([q.x, q.y, q.z], 0.0, atol=1e-6):
        raise ValueError("grid origin is rotated (q = %.3f %.3f %.3f %.3f); only an axis-aligned "
                         "grid is supported" % (q.x, q.y, q.z, q.w))
    H, W = int(info.height), int(info.width)
    raw = msg.data
    data = (np.frombuffer(raw, dtype=np.int8) if isinstance(raw, (bytes, bytearray))
            else np.asarray(raw, dtype=np.int8).reshape(-1))
    if data.size != H * W:
        raise ValueError("grid data has %d cells, info says %dx%d" % (data.size, W, H))
    return (data.reshape(H, W).copy(), (float(info.origin.position.x), float(info.origin.position.y)),
            float(info.resolution))


def traversable(grid: np.ndarray, resolution: float, robot_radius: float = 0.0,
                unknown_traversable: bool = False, occupied_threshold: int = 50) -> np.ndarray:
    """Boolean (H, W) mask of the cells a disc robot of ``robot_radius`` m can be centred on.

    A cell is an obstacle when its value is ``>= occupied_threshold``; unknown (negative) cells are
    blocked unless ``unknown_traversable``. Obstacles (not unknown cells) are inflated: a cell whose
    centre lies within ``robot_radius`` of an obstacle cell's centre is blocked.
    """
    g = np.asarray(grid)
    if g.ndim != 2:
        raise ValueError("grid must be 2-D, got shape %s" % (g.shape,))
    occupied = g >= occupied_threshold
    ok = ~occupied
    if not unknown_traversable:
        ok &= g >= 0
    if robot_radius > 0 and occupied.any():
        dist = distance_transform_edt(~occupied) * float(resolution)
        ok &= dist > robot_radius + 1e-6 * float(resolution)   # "within" includes the radius
    return ok


def _astar(ok: np.ndarray, s: Tuple[int, int], g: Tuple[int, int]) -> Optional[np.ndarray]:
    """A* over the 8-connected traversable cells (octile heuristic); the loop runs over the
    search frontier. Returns the (N, 2) cells from s to g or None."""
    H, W = ok.shape
    gr, gc = g

    def h(r, c):
        dr, dc = abs(r - gr), abs(c - gc)
        return (dr + dc) + (_SQRT2 - 2.0) * min(dr, dc)

    cost = np.full(ok.shape, np.inf)
    parent = np.full(ok.shape, -1, np.int64)
    cost[s] = 0.0
    heap = [(h(*s), 0.0, s[0], s[1])]
    while heap:
        _, d, r, c = heapq.heappop(heap)
        if d > cost[r, c]:
            continue
        if (r, c) == g:
            break
        for dr, dc, step in _MOVES:
            nr, nc = r + dr, c + dc
            if not (0 <= nr < H and 0 <= nc < W) or not ok[nr, nc]:
                continue
            if dr and dc and not (ok[r, nc] and ok[nr, c]):
                continue  # no corner cutting past an obstacle
            nd = d + step
            if nd < cost[nr, nc]:
                cost[nr, nc] = nd
                parent[nr, nc] = r * W + c
                heapq.heappush(heap, (nd + h(nr, nc), nd, nr, nc))
    if not np.isfinite(cost[g]):
        return None
    return _backtrack(parent.reshape(-1), s[0] * W + s[1], gr * W + gc, W)


def _backtrack(parent: np.ndarray, s: int, g: int, W: int) -> np.ndarray:
    out = [g]
    while out[-1] != s:
        out.append(int(parent[out[-1]]))
    idx = np.array(out[::-1], np.int64)
    return np.stack([idx // W, idx % W], axis=1)


def _dijkstra(ok: np.ndarray, s: Tuple[int, int], g: Tuple[int, int]) -> Optional[np.ndarray]:
    """SciPy's Dijkstra on the traversable-cell graph (edges built vectorized, same moves and
    corner rule as :func:`_astar`)."""
    H, W = ok.shape
    idx = np.arange(H * W).reshape(H, W)
    rows, cols, w = [], [], []
    pad = np.zeros((H + 2, W + 2), bool)
    pad[1:-1, 1:-1] = ok
    for dr, dc, step in _MOVES:
        nb = pad[1 + dr:1 + dr + H, 1 + dc:1 + dc + W]
        e = ok & nb
        if dr and dc:
            e &= pad[1:1 + H, 1 + dc:1 + dc + W] & pad[1 + dr:1 + dr + H, 1:1 + W]
        src = idx[e]
        rows.append(src)
        cols.append(src + dr * W + dc)
        w.append(np.full(len(src), step))
    G = coo_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))),
                   shape=(H * W, H * W)).tocsr()
    si, gi = s[0] * W + s[1], g[0] * W + g[1]
    dist, pred = dijkstra(G, directed=True, indices=si, return_predecessors=True)
    if not np.isfinite(dist[gi]):
        return None
    return _backtrack(pred, si, gi, W)


def plan_path(grid, start_xy, goal_xy, resolution: Optional[float] = None, origin=None,
              robot_radius: float = 0.0, unknown_traversable: bool = False,
              occupied_threshold: int = 50, method: str = "astar") -> Optional[Plan]:
    """Shortest 8-connected path between two grid-plane points on an occupancy grid.

    ``grid`` is an int (H, W) array (then give ``resolution`` and ``origin``) or the
    ``(grid, origin, resolution)`` tuple of :func:`mdr_slam.fusion.occupancy_grid` /
    :func:`grid_from_msg`. ``method``: ``'astar'`` or ``'dijkstra'`` (SciPy); both return a
    shortest path. Returns a :class:`Plan`, or None when the start or goal cell is not traversable
    (obstacle, inflated obstacle, unknown) or no path connects them. Raises ValueError for a start
    or goal outside the grid.
    """
    if isinstance(grid, tuple):
        grid, origin, resolution = grid
    if resolution is None or origin is None:
        raise ValueError("give the grid's resolution and origin (or the (grid, origin, res) tuple)")
    if method not in ("astar", "dijkstra"):
        raise ValueError("method must be 'astar' or 'dijkstra', got %r" % (method,))
    ok = traversable(grid, resolution, robot_radius, unknown_traversable, occupied_threshold)
    H, W = ok.shape
    ends = []
    for name, xy in (("start", start_xy), ("goal", goal_xy)):
        r, c = (int(v) for v in world_to_cell(np.asarray(xy, dtype=np.float64)[:2], origin, resolution))
        if not (0 <= r < H and 0 <= c < W):
            raise ValueError("%s %s is outside the %dx%d grid at origin %s (res %.3f m)"
                             % (name, tuple(np.round(xy, 3)), W, H, tuple(origin), resolution))
        ends.append((r, c))
    s, g = ends
    if not (ok[s] and ok[g]):
        return None
    cells = (_astar if method == "astar" else _dijkstra)(ok, s, g)
    if cells is None:
        return None
    steps = np.diff(cells, axis=0)
    length = float(np.sum(np.hypot(steps[:, 0], steps[:, 1]))) * float(resolution)
    return Plan(cells, cell_to_world(cells, origin, resolution), length)


# ---------------------------------------------------------------------- the fusion node's outputs
def map_min_confidence(params: dict) -> Tuple[int, int]:
    """``(points, grid)`` minimum confidences of ``/mdr/map/points`` and ``/mdr/map/grid`` for
    the fusion parameters ``params`` (``display_min_confidence``, ``grid_min_confidence``; both 0
    when ``confidence`` is off: a plain voxel grid has no confidence to filter on)."""
    if not params.get("confidence", True):
        return 0, 0
    return int(params["display_min_confidence"]), int(params["grid_min_confidence"])


def map_views(cloud) -> Optional[np.ndarray]:
    """(N, 3) float64 views (the camera centre each point was last seen from, NaN: none) of a
    map cloud (:meth:`mdr_slam.fusion.VoxelMap.to_cloud`, or a ``map.ply``), or None when the
    cloud has no ``view_x, view_y, view_z`` fields (a peer's map, a map saved without views)."""
    if not all(k in cloud for k in ("view_x", "view_y", "view_z")):
        return None
    return np.stack([cloud["view_x"], cloud["view_y"], cloud["view_z"]], 1).astype(np.float64)


def map_products(cloud: dict, params: dict, extent=None, around=None, base=None):
    """What the fusion node publishes from one snapshot ``cloud`` of its map
    (:meth:`mdr_slam.fusion.VoxelMap.to_cloud` at ``min(map_min_confidence(params))`` or lower:
    fields ``x y z intensity confidence``).

    Returns ``(points, grid)``: ``points`` a dict ``xyz`` (N, 3) float64, ``intensity`` and
    ``confidence`` (N,) of ``/mdr/map/points`` (points of confidence ``>= display_min_confidence``,
    averaged per ``display_voxel`` cell when that is > 0), and ``grid`` the
    :func:`mdr_slam.fusion.occupancy_grid` tuple ``(data, origin, resolution)`` of
    ``/mdr/map/grid`` from the points of confidence ``>= grid_min_confidence`` (None when
    ``publish_grid`` is off): with ``grid_raytrace`` and the cloud's views (``view_x, view_y,
    view_z``) free space along the rays (``grid_raytrace_range``), and wall gaps of at most
    ``grid_max_gap`` closed (missing keys: off). Both are in the map frame. ``extent``, a
    :class:`mdr_slam.fusion.GridExtent`, pads the grid to its extent, kept around the ``map``
    positions ``around`` ((N, 3), the camera), so that move_base's costmap is rarely resized.
    ``base`` ((N, 3) ``map`` positions of the robot's base): the grid's cells within
    ``grid_footprint_radius`` of it are free (:func:`mdr_slam.fusion.free_footprint`).

    move_base's obstacle layer marks ``/mdr/map/points`` between its min/max obstacle heights
    (config/navigation: ``grid_z_min``/``grid_z_max``) and never clears them (the cloud is in
    ``map``), so with ``display_min_confidence >= grid_min_confidence`` every such point falls in a
    cell the grid marks occupied: the two layers agree. Below it, young points that the fusion
    may still remove as noise become lasting obstacles the grid does not have.
    """
    p = params
    mc_disp, mc_grid = map_min_confidence(p)
    conf_all = np.asarray(cloud["confidence"])
    xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], 1).astype(np.float64)
    grid = None
    if p["publish_grid"]:
        sel = conf_all >= mc_grid
        views = map_views(cloud) if p.get("grid_raytrace", False) else None
        grid = occupancy_grid(xyz[sel], p["grid_resolution"], p["grid_z_min"],
                              p["grid_z_max"], p["grid_up_axis"], p["grid_free_band"],
                              None if views is None else views[sel],
                              float(p.get("grid_max_gap", 0.0)),
                              float(p.get("grid_raytrace_range", 0.0)))
        if extent is not None:
            xy = np.zeros((0, 2))
            if around is not None and len(around):
                xy = (np.asarray(around, np.float64).reshape(-1, 3)
                      @ grid_axes(p["grid_up_axis"]).T)[:, :2]
            data, origin = extent.apply(grid[0], grid[1], xy)
            grid = (data, origin, grid[2])
        r = float(p.get("grid_footprint_radius", 0.0))
        if base is not None and r > 0:
            xy = (np.asarray(base, np.float64).reshape(-1, 3) @ grid_axes(p["grid_up_axis"]).T)
            free_footprint(grid[0], grid[1], grid[2], xy[:, :2], r)
    keep = conf_all >= mc_disp
    xyz = xyz[keep]
    inten = np.asarray(cloud["intensity"])[keep]
    conf = conf_all[keep].astype(np.float64)
    if p["display_voxel"] > 0 and len(xyz):
        _, xyz, _, ex = voxel_downsample(xyz, p["display_voxel"], None,
                                         {"intensity": inten, "confidence": conf})
        inten, conf = ex["intensity"], ex["confidence"]
    return {"xyz": xyz, "intensity": inten, "confidence": conf}, grid
