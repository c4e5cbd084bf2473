"""Navigation benchmark scoring (ROS-free): a simulator scene's true occupancy, seeded goals and
the per-goal figures of a closed-loop run (the robot driven by move_base on MDR-SLAM's grid).

* :func:`true_grid`: the cells of the scene's surfaces between ``z_min`` and ``z_max`` (the
  fusion grid's obstacle band), rasterised from the exact rectangles;
* :func:`sample_goals`: ``n`` goals in the true free space, each reachable from the previous one
  (the robot chains them), about half of them hidden (the straight line from the previous goal
  crosses an obstacle, so the robot must map its way round something it has not seen yet);
  each with the shortest true path length (:func:`mdr_slam.nav.plan_path`, disc robot);
* :func:`score_goal`: reached, time, path length, smallest clearance, localization error and
  the plans that crossed a cell the grid marked occupied when the plan was made.
"""
from __future__ import annotations

import math
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy.ndimage import distance_transform_edt, label

from ..nav import cell_to_world, plan_path, traversable, world_to_cell

__all__ = ["TrueGrid", "true_grid", "sample_goals", "path_length", "clearance_along",
           "plan_crosses_occupied", "localization_errors", "map_alignment",
           "keyframe_trajectory_error", "score_goal", "summarise"]

OCCUPIED = 100
GOAL_CLEARANCE = 0.45     # m from a goal's centre to the nearest true obstacle
MIN_GOAL_STEP = 2.0       # m between consecutive goals (straight line)
HIDDEN_SHARE = 0.5        # about this share of goals is out of sight of the previous one
ALIGN_MIN_SPREAD = 1.0    # m: a trajectory shorter than this fixes no rotation (identity then)


class TrueGrid:
    """Boolean obstacle raster ``occ`` (H, W) of a scene, rows along y, at ``origin`` (x0, y0)."""

    def __init__(self, occ: np.ndarray, origin: Tuple[float, float], resolution: float):
        self.occ = occ
        self.origin = (float(origin[0]), float(origin[1]))
        self.resolution = float(resolution)
        # metres from each cell centre to the nearest obstacle cell's centre
        self.distance = distance_transform_edt(~occ) * self.resolution

    @property
    def grid(self) -> np.ndarray:
        """As an occupancy grid (100 occupied, 0 free): :func:`mdr_slam.nav.plan_path`'s input."""
        return np.where(self.occ, OCCUPIED, 0).astype(np.int8)

    def cells(self, xy) -> Tuple[np.ndarray, np.ndarray]:
        """(row, col) of points (N, 2), clipped into the grid."""
        rc = world_to_cell(np.asarray(xy, float).reshape(-1, 2), self.origin, self.resolution)
        H, W = self.occ.shape
        return np.clip(rc[:, 0], 0, H - 1), np.clip(rc[:, 1], 0, W - 1)

    def clearance(self, xy) -> np.ndarray:
        """Distance (m) from points (N, 2) to the nearest true obstacle (cell-centre accuracy)."""
        r, c = self.cells(xy)
        return self.distance[r, c]


def true_grid(scene, resolution: float = 0.05, z_min: float = 0.1, z_max: float = 1.5,
              margin: float = 1.0) -> TrueGrid:
    """Rasterise the scene's rectangles where they pass through the height band [z_min, z_max]:
    each is sampled every half cell over its part inside the band (vectorized per rectangle)."""
    lo, hi = (np.asarray(v, float) for v in scene.bounds)
    origin = (math.floor((lo[0] - margin) / resolution) * resolution,
              math.floor((lo[1] - margin) / resolution) * resolution)
    W = int(math.ceil((hi[0] + margin - origin[0]) / resolution))
    H = int(math.ceil((hi[1] + margin - origin[1]) / resolution))
    occ = np.zeros((H, W), bool)
    step = 0.5 * resolution
    for rc in scene.rects:
        z = rc.corners()[:, 2]
        if z.max() < z_min or z.min() > z_max:
            continue
        s = np.linspace(0.0, rc.a, max(2, int(math.ceil(rc.a / step)) + 1))
        r = np.linspace(0.0, rc.b, max(2, int(math.ceil(rc.b / step)) + 1))
        P = rc.to_world(*np.meshgrid(s, r, indexing="xy")).reshape(-1, 3)
        P = P[(P[:, 2] >= z_min) & (P[:, 2] <= z_max)]
        if not len(P):
            continue
        cells = world_to_cell(P[:, :2], origin, resolution)
        ok = (cells[:, 0] >= 0) & (cells[:, 0] < H) & (cells[:, 1] >= 0) & (cells[:, 1] < W)
        occ[cells[ok, 0], cells[ok, 1]] = True
    return TrueGrid(occ, origin, resolution)


def _line_blocked(tg: TrueGrid, a, b) -> bool:
    n = max(2, int(np.linalg.norm(np.subtract(b, a)) / (0.5 * tg.resolution)) + 1)
    xy = np.linspace(a, b, n)
    r, c = tg.cells(xy)
    return bool(tg.occ[r, c].any())


def sample_goals(tg: TrueGrid, start_xy, n: int, seed: int, robot_radius: float = 0.2,
                 clearance: float = GOAL_CLEARANCE, min_step: float = MIN_GOAL_STEP,
                 hidden_share: float = HIDDEN_SHARE, tries: int = 400) -> List[Dict]:
    """``n`` goals ``{"xy", "yaw", "hidden", "shortest_m", "from"}`` chained from ``start_xy``.

    A goal lies at least ``clearance`` from every true obstacle, in the free component the start
    is in, at least ``min_step`` from the previous goal; ``hidden`` when the straight segment from
    the previous goal crosses an obstacle (about ``hidden_share`` of them are drawn so).
    ``shortest_m``: the shortest path for a disc of ``robot_radius`` on the true grid.
    Deterministic for ``seed``.
    """
    rng = np.random.default_rng([int(seed), 4242])
    ok = traversable(tg.grid, tg.resolution, robot_radius)
    comp, _ = label(ok, structure=np.ones((3, 3)))
    r0, c0 = (int(v[0]) for v in tg.cells(start_xy))
    if not ok[r0, c0]:
        raise ValueError("the start %s is not free for a robot of radius %.2f m"
                         % (tuple(np.round(start_xy, 2)), robot_radius))
    cand = np.argwhere((comp == comp[r0, c0]) & (tg.distance >= clearance))
    if not len(cand):
        raise ValueError("no free cell %.2f m from the obstacles" % clearance)
    goals: List[Dict] = []
    prev = np.asarray(start_xy, float)[:2]
    for k in range(n):
        want_hidden = rng.random() < hidden_share
        best = None
        for t in range(tries):
            xy = cell_to_world(cand[rng.integers(len(cand))], tg.origin, tg.resolution)
            if np.linalg.norm(xy - prev) < min_step:
                continue
            hidden = _line_blocked(tg, prev, xy)
            if hidden != want_hidden and t < tries // 2:
                continue
            plan = plan_path(tg.grid, prev, xy, tg.resolution, tg.origin, robot_radius)
            if plan is None:
                continue
            best = (xy, hidden, plan.length)
            break
        if best is None:
            raise ValueError("no reachable goal found for goal %d from %s" % (k, tuple(prev)))
        xy, hidden, length = best
        goals.append({"xy": [float(xy[0]), float(xy[1])],
                      "yaw": float(rng.uniform(-math.pi, math.pi)), "hidden": bool(hidden),
                      "shortest_m": round(float(length), 3),
                      "from": [float(prev[0]), float(prev[1])]})
        prev = xy
    return goals


def path_length(xy) -> float:
    """Length (m) of a polyline (N, 2)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    return float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1))) if len(xy) > 1 else 0.0


def clearance_along(tg: TrueGrid, xy, robot_radius: float) -> float:
    """Smallest gap (m) between the robot's disc and the true obstacles along a path (N, 2)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    if not len(xy):
        return float("nan")
    return float(tg.clearance(xy).min() - robot_radius)


def plan_crosses_occupied(plan_xy, grid: np.ndarray, origin, resolution: float) -> int:
    """Number of cells of the grid marked occupied (100) that a plan (N, 2 in the grid's frame)
    passes through, the polyline sampled every quarter cell. Cells outside the grid are unknown:
    not counted (a plan may cross unknown space)."""
    xy = np.asarray(plan_xy, float).reshape(-1, 2)
    if len(xy) == 0:
        return 0
    if len(xy) > 1:
        seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        n = np.maximum(1, np.ceil(seg / (0.25 * resolution)).astype(int))
        parts = [xy[i] + np.outer(np.arange(n[i]) / n[i], xy[i + 1] - xy[i])
                 for i in range(len(seg))]
        xy = np.vstack(parts + [xy[-1:]])
    rc = world_to_cell(xy, origin, resolution)
    H, W = grid.shape
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < H) & (rc[:, 1] >= 0) & (rc[:, 1] < W)
    rc = np.unique(rc[inside], axis=0)
    return int(np.count_nonzero(grid[rc[:, 0], rc[:, 1]] >= OCCUPIED)) if len(rc) else 0


def localization_errors(est_t: Sequence[float], est_xy, gt_t: Sequence[float], gt_xy,
                        max_gap: float = 0.5) -> np.ndarray:
    """|estimated - true| base position (m, in the plane) at each estimate's stamp, the truth
    interpolated linearly; estimates farther than ``max_gap`` s from any truth are dropped.
    Both positions in the same frame (the caller maps the estimate's ``map`` into the world)."""
    est_xy = np.asarray(est_xy, float).reshape(-1, 2)
    truth, keep = _truth_at(est_t, gt_t, gt_xy, max_gap)
    return np.linalg.norm(est_xy[keep] - truth, axis=1)


def _truth_at(t: Sequence[float], gt_t: Sequence[float], gt_xy, max_gap: float):
    """The true positions at stamps ``t``, interpolated linearly, and which of ``t`` have one
    (a truth within ``max_gap`` s): ``(truth (K, 2), keep (N,) bool)``."""
    t, gt_t = np.asarray(t, float), np.asarray(gt_t, float)
    gt_xy = np.asarray(gt_xy, float).reshape(-1, 2)
    if not len(t) or len(gt_t) < 2:
        return np.zeros((0, 2)), np.zeros(len(t), bool)
    order = np.argsort(gt_t)
    gt_t, gt_xy = gt_t[order], gt_xy[order]
    j = np.clip(np.searchsorted(gt_t, t), 1, len(gt_t) - 1)
    gap = np.minimum(np.abs(t - gt_t[j - 1]), np.abs(gt_t[j] - t))
    keep = (t >= gt_t[0] - max_gap) & (t <= gt_t[-1] + max_gap) & (gap <= max_gap)
    w = np.clip((t - gt_t[j - 1]) / np.maximum(gt_t[j] - gt_t[j - 1], 1e-9), 0.0, 1.0)
    truth = gt_xy[j - 1] + w[:, None] * (gt_xy[j] - gt_xy[j - 1])
    return truth[keep], keep


def map_alignment(est_xy, true_xy) -> np.ndarray:
    """The planar rigid transform (3x3, homogeneous) that best maps estimated base positions onto
    the true ones (least squares, evo's Umeyama without scale): how the map a user sees lies on
    the scene. A user picks a goal on the map's walls, so an early heading error that rotates the
    whole map moves the goal with it; the error left after this alignment is the pose's error
    against its own map. Identity while the positions span less than ALIGN_MIN_SPREAD m."""
    from evo.core.geometry import umeyama_alignment
    est = np.asarray(est_xy, float).reshape(-1, 2)
    true = np.asarray(true_xy, float).reshape(-1, 2)
    A = np.eye(3)
    if len(est) < 3 or np.linalg.norm(np.ptp(est, axis=0)) < ALIGN_MIN_SPREAD:
        return A
    R, t, _ = umeyama_alignment(est.T, true.T, False)
    A[:2, :2], A[:2, 2] = R, t
    return A


def keyframe_trajectory_error(kf_t: Sequence[float], kf_xy, gt_t: Sequence[float], gt_xy,
                              max_gap: float = 0.5) -> Optional[Dict]:
    """The map's keyframe trajectory against the truth, its absolute trajectory error (evo's APE
    on positions after :func:`map_alignment`): ``kf_xy`` the keyframes' base positions in
    ``map`` (as the pose node last published them, loop and BA corrections included, or as
    first published), ``gt_xy`` the true base positions at ``gt_t``. A localization error that
    the map shares (the map drifted with the pose) is not in it; a map a loop closure bent is.
    ``{"keyframes", "rmse_m", "max_m"}``; None with fewer than 3 keyframes matched in time."""
    kf_xy = np.asarray(kf_xy, float).reshape(-1, 2)
    if len(kf_xy) < 3:
        return None
    truth, keep = _truth_at(kf_t, gt_t, gt_xy, max_gap)
    if keep.sum() < 3:
        return None
    est = kf_xy[keep]
    A = map_alignment(est, truth)
    err = np.linalg.norm(est @ A[:2, :2].T + A[:2, 2] - truth, axis=1)
    return {"keyframes": int(len(err)), "rmse_m": round(float(np.sqrt(np.mean(err ** 2))), 3),
            "max_m": round(float(err.max()), 3)}


def score_goal(goal: Dict, reached: bool, time_s: float, true_xy, tg: TrueGrid,
               robot_radius: float, collisions: int, plans_through_occupied: int,
               loc_errors, start_errors=()) -> Dict:
    """The figures of one goal (``navigation.json``'s per-goal record). ``loc_errors``: the
    pose's errors against its map aligned to the scene (:func:`map_alignment`);
    ``start_errors``: against the map fixed to the scene at the first tracked frame."""
    loc = np.asarray(loc_errors, float)
    start = np.asarray(start_errors, float)
    return {"goal": goal["xy"], "hidden": goal["hidden"], "reached": bool(reached),
            "time_s": round(float(time_s), 2), "path_m": round(path_length(true_xy), 3),
            "shortest_m": goal["shortest_m"], "collisions": int(collisions),
            "min_clearance_m": round(clearance_along(tg, true_xy, robot_radius), 3),
            "plans_through_occupied": int(plans_through_occupied),
            "max_localization_error_m": round(float(loc.max()), 3) if len(loc) else None,
            "max_error_from_start_m": round(float(start.max()), 3) if len(start) else None}


def summarise(records: List[Dict], max_speed: float) -> Dict:
    """Per-scene totals: goals reached, collisions, plans through occupied cells, the worst
    localization error, and the goals slower than twice the shortest path at ``max_speed``."""
    slow = [i for i, r in enumerate(records)
            if r["reached"] and r["time_s"] > 2.0 * r["shortest_m"] / max_speed]
    loc = [r["max_localization_error_m"] for r in records if r["max_localization_error_m"] is not None]
    start = [r.get("max_error_from_start_m") for r in records
             if r.get("max_error_from_start_m") is not None]
    return {"goals": len(records), "reached": sum(r["reached"] for r in records),
            "collisions": sum(r["collisions"] for r in records),
            "plans_through_occupied": sum(r["plans_through_occupied"] for r in records),
            "max_localization_error_m": max(loc) if loc else None,
            "max_error_from_start_m": max(start) if start else None,
            "slower_than_2x_shortest": slow}
