"""Occupancy grid of the map for planners: cells from the points' heights, free space along
the rays from the cameras, straight walls closed over small unseen gaps; the grid plane of an
``up`` axis and its pose in ``map``."""
from __future__ import annotations

from typing import Optional

import numpy as np

__all__ = ["grid_axes", "grid_origin_T", "occupancy_grid", "close_wall_gaps", "free_footprint",
           "GridExtent"]

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


_SHIFT = 8           # fractional bits of the line end points given to OpenCV (1/256 cell)
_END_MARGIN = 0.02   # cells: a ray's drawn end stays this far outside its point's own cell
_SUPPORT = 0.2       # m of wall each side of a gap must show (mostly occupied) to close the gap
# ray groups rasterized per grid, a bound on its cost (OpenCV draws 80k in ~35 ms)
_MAX_RAYS = 80000


def occupancy_grid(points: np.ndarray, resolution: float = 0.05, z_min: float = 0.1,
                   z_max: float = 1.5, up_axis: str = "z", free_band: float = 0.3,
                   views: Optional[np.ndarray] = None, max_gap: float = 0.0,
                   raytrace_range: float = 0.0):
    """2-D occupancy grid (nav_msgs/OccupancyGrid values) of map points.

    Heights are measured along ``up_axis`` ('x', 'y', 'z', '-x', '-y' or '-z'; e.g. '-y' for a
    map in the first camera's optical frame). Points with height in ``[z_min, z_max]`` mark their
    cell occupied (100); cells with floor points (height in ``[z_min - free_band, z_min)``) are
    free (0: the floor was seen there and nothing stands on it up to the obstacle band).

    ``views`` (N, 3), the camera centre in the map frame that each point was last seen from
    (NaN rows: no ray), adds ray-traced free space as costmap_2d's obstacle layer clears it: the
    segment from the view to the point frees the cells it crosses while its height is inside
    ``[z_min, z_max]``, up to (not including) the point's own cell and, with ``raytrace_range``
    > 0, only its first ``raytrace_range`` metres from the view. Rays are grouped by (point
    cell, view cell) first (one segment per group, spanning the band parts of all its rays; at
    most ``_MAX_RAYS`` groups, every point cell keeping one) and rasterized by OpenCV in one
    call (``cv2.polylines``, 4-connected lines: the cells a ray passes through, without the
    one-cell seams 8-connected lines leave between neighbouring rays). Occupied always wins
    over free.

    ``max_gap`` > 0 (m) closes gaps in straight walls (:func:`close_wall_gaps`): a gap of at
    most ``max_gap`` along a straight run of obstacle cells (found by ``cv2.HoughLinesP``) with
    wall on both sides becomes occupied unless a ray looked through it (free cells on both sides
    of the wall there: a doorway the camera saw through stays open).

    Every other cell is unknown (-1). Returns ``(grid int8 (H, W), origin (x, y), resolution)``:
    cell ``(row, col)`` covers ``[x0 + col*res, x0 + (col+1)*res) x [y0 + row*res,
    y0 + (row+1)*res)`` in the grid plane, whose axes are :func:`grid_axes` (``(x, y)`` for
    ``up_axis='z'``), row-major with row 0 at ``origin`` as nav_msgs/OccupancyGrid; the origin
    is a multiple of the resolution; :func:`grid_origin_T` gives ``info.origin``.
    """
    res = float(resolution)
    if not res > 0:
        raise ValueError("resolution must be > 0 (got %r)" % (resolution,))
    if not max_gap >= 0 or not raytrace_range >= 0:
        raise ValueError("max_gap and raytrace_range must be >= 0 (got %r, %r)"
                         % (max_gap, raytrace_range))
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    A = grid_axes(up_axis)  # rows: grid x axis, grid y axis, up
    Q = P @ A.T
    h = Q[:, 2]
    occ = (h >= z_min) & (h <= z_max)
    floor = (h < z_min) & (h >= z_min - free_band)
    use = occ | floor
    seg = None
    if views is not None:
        V = np.asarray(views, dtype=np.float64)
        if V.size != P.size:
            raise ValueError("views must be (N, 3) like the %d points, got shape %s"
                             % (len(P), V.shape))
        seg = _ray_segments(Q, V.reshape(-1, 3) @ A.T, float(z_min), float(z_max), res,
                            float(raytrace_range))
    if not use.any() and (seg is None or len(seg) == 0):
        return np.full((1, 1), -1, np.int8), (0.0, 0.0), res
    Qu = Q[use]
    ix = np.floor(Qu[:, 0] / res).astype(np.int64)   # one array per axis: fast min / max
    iy = np.floor(Qu[:, 1] / res).astype(np.int64)
    bounds = [(ix.min(), ix.max(), iy.min(), iy.max())] if len(ix) else []
    if seg is not None and len(seg):
        # fixed-point line ends as OpenCV takes them (pixel centres at integers); the cell of an
        # end is OpenCV's rounding of it
        fix = np.round(seg * (1 << _SHIFT)).astype(np.int64)
        cx = (fix[:, :, 0] + (1 << (_SHIFT - 1))) >> _SHIFT
        cy = (fix[:, :, 1] + (1 << (_SHIFT - 1))) >> _SHIFT
        bounds.append((cx.min(), cx.max(), cy.min(), cy.max()))
    b = np.array(bounds, np.int64)
    lo = np.array([b[:, 0].min(), b[:, 2].min()])
    W, H = b[:, 1].max() - lo[0] + 1, b[:, 3].max() - lo[1] + 1
    grid = np.full((int(H), int(W)), -1, np.int8)
    if seg is not None and len(seg):
        import cv2
        free = np.zeros((int(H), int(W)), np.uint8)
        cv2.polylines(free, (fix - (lo << _SHIFT)).astype(np.int32), False, 1, 1, cv2.LINE_4,
                      _SHIFT)
        grid[free > 0] = 0
    ix -= lo[0]
    iy -= lo[1]
    fl = floor[use]
    grid[iy[fl], ix[fl]] = 0
    grid[iy[~fl], ix[~fl]] = 100   # occupied wins over floor and rays in the same cell
    if max_gap > 0:
        close_wall_gaps(grid, res, max_gap)
    return grid, (float(lo[0] * res), float(lo[1] * res)), res


def _ray_segments(Q: np.ndarray, Qv: np.ndarray, z_min: float, z_max: float, res: float,
                  max_range: float) -> np.ndarray:
    """(M, 2, 2) float segments (start, end) in pixel units (cell (i, j) centred on (i, j)) of
    the parts of the rays view -> point (grid-plane coordinates ``Qv`` -> ``Q``, height in
    column 2) that lie in the height band, grouped by (point cell, view cell), each ending
    before its point's cell; at most ``_MAX_RAYS`` of them (:func:`_thin`)."""
    if len(Q) == 0:
        return np.zeros((0, 2, 2))
    # one contiguous float32 array per coordinate, in cells from the points' lowest cell: the
    # per-ray passes are the grid's main cost and this halves their memory traffic (1/256 of a
    # cell, the line ends' precision, is far above float32's)
    bx = np.floor(np.nanmin(Q[:, 0]) / res)
    by = np.floor(np.nanmin(Q[:, 1]) / res)
    if not (np.isfinite(bx) and np.isfinite(by)):
        return np.zeros((0, 2, 2))
    x0 = (Qv[:, 0] / res - bx).astype(np.float32)
    y0 = (Qv[:, 1] / res - by).astype(np.float32)
    x1 = (Q[:, 0] / res - bx).astype(np.float32)
    y1 = (Q[:, 1] / res - by).astype(np.float32)
    hv = Qv[:, 2].astype(np.float32)
    dh = Q[:, 2].astype(np.float32) - hv
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv = np.float32(1.0) / dh
        ta = (np.float32(z_min) - hv) * inv
        tb = (np.float32(z_max) - hv) * inv
    # ray parameter t in [0, 1] (view -> point) of the part inside the band
    t0 = np.minimum(ta, tb)
    np.maximum(t0, 0, out=t0)
    t1 = np.maximum(ta, tb, out=ta)
    np.minimum(t1, 1, out=t1)
    level = np.abs(dh) < 1e-6
    if level.any():   # a level ray: all of it or nothing
        inb = (hv[level] >= z_min) & (hv[level] <= z_max)
        t0[level] = np.where(inb, 0.0, np.inf)
        t1[level] = np.where(inb, 1.0, -np.inf)
    if max_range > 0:
        with np.errstate(invalid="ignore"):
            length = np.sqrt(((x1 - x0) * res) ** 2 + ((y1 - y0) * res) ** 2 + dh ** 2)
            np.minimum(t1, max_range / np.maximum(length, 1e-6), out=t1)
    # a NaN view (or point) fails one of the comparisons: no ray
    with np.errstate(invalid="ignore"):
        keep = (t1 > t0) & np.isfinite(x0 + y0 + x1 + y1)
    if not keep.all():
        x0, y0, x1, y1, t0, t1 = (a[keep] for a in (x0, y0, x1, y1, t0, t1))
    if len(x0) == 0:
        return np.zeros((0, 2, 2))
    # one segment per (point cell, view cell): the union of its rays' band parts, along one
    # ray of the group (the others run within a cell of it)
    cells = [np.floor(a).astype(np.int64) for a in (x1, y1, x0, y0)]
    los = [int(c.min()) for c in cells]
    span = [int(c.max()) - lo + 1 for c, lo in zip(cells, los)]
    if float(np.prod(np.array(span, np.float64))) < 2.0 ** 62:
        key = cells[0] - los[0]
        for c, lo, n in zip(cells[1:], los[1:], span[1:]):
            key *= n
            key += c - lo
        point_key = key // (span[2] * span[3])
    else:   # a map spanning more cells than an int64 key holds: slower, same groups
        key = np.unique(np.stack(cells, axis=1), axis=0, return_inverse=True)[1].reshape(-1)
        point_key = np.unique(np.stack(cells[:2], axis=1), axis=0,
                              return_inverse=True)[1].reshape(-1)
    order = np.argsort(key)
    ks = key[order]
    starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    rep = order[starts]
    g0 = np.minimum.reduceat(t0[order], starts).astype(np.float64)
    g1 = np.maximum.reduceat(t1[order], starts).astype(np.float64)
    if len(rep) > _MAX_RAYS:
        sel = _thin(point_key[rep], _MAX_RAYS)
        rep, g0, g1 = rep[sel], g0[sel], g1[sel]
    ax, ay = x0[rep].astype(np.float64), y0[rep].astype(np.float64)
    dx, dy = x1[rep] - ax, y1[rep] - ay
    # stop before the point's own cell: where the representative ray enters it (slab test)
    enter = np.full(len(rep), -np.inf)
    for a, da, c in ((ax, dx, cells[0][rep] + los[0]), (ay, dy, cells[1][rep] + los[1])):
        with np.errstate(divide="ignore", invalid="ignore"):
            e = np.minimum((c - a) / da, (c + 1 - a) / da)
        np.maximum(enter, np.where(da != 0, e, -np.inf), out=enter)
    n = np.maximum(np.hypot(dx, dy), 1e-12)
    g1 = np.minimum(g1, enter - _END_MARGIN / n)
    keep = np.flatnonzero(g1 >= g0)
    seg = np.empty((len(keep), 2, 2))
    for j, g in enumerate((g0[keep], g1[keep])):
        seg[:, j, 0] = ax[keep] + g * dx[keep] + (bx - 0.5)
        seg[:, j, 1] = ay[keep] + g * dy[keep] + (by - 0.5)
    return seg


def _thin(point_key: np.ndarray, budget: int) -> np.ndarray:
    """Indices of at most ``budget`` ray groups, given their point cells' keys in ascending
    order: the first group of every point cell (each cell in front of a mapped surface keeps a
    ray), then evenly spaced others. Rays to one cell overlap near it and fan out towards the
    cameras, where the rest of the map's rays cross too: on a 300k-point, 20 x 20 m map whose
    points have random views of their room (270k groups), 80k groups freed 99.2 % of the cells
    all of them did."""
    first = np.flatnonzero(np.r_[True, point_key[1:] != point_key[:-1]])
    if len(first) >= budget:
        return first[np.linspace(0, len(first) - 1, budget).astype(np.int64)]
    rest = np.ones(len(point_key), bool)
    rest[first] = False
    rest = np.flatnonzero(rest)
    more = rest[np.linspace(0, len(rest) - 1, budget - len(first)).astype(np.int64)]
    return np.sort(np.concatenate([first, more]))


def close_wall_gaps(grid: np.ndarray, resolution: float, max_gap: float) -> int:
    """Close gaps of at most ``max_gap`` m in straight walls of ``grid`` (in place); returns the
    number of cells set occupied.

    Straight runs of obstacle cells come from ``cv2.HoughLinesP`` on the occupied mask (gaps of
    up to ``max_gap`` bridged). Along each segment (its cells by a DDA walk), a gap is a run of
    non-occupied cells between two occupied ones. It is closed when it is at most ``max_gap``
    long, the wall shows on both sides (of the ``_SUPPORT`` m of segment beyond each end of the
    gap, more than half the cells are occupied) and no ray looked through it: no cell of the gap
    is free with free cells on both sides of the wall line (a doorway seen through stays open).
    A gap cell freed by rays on one side only was grazed by rays running along the wall, in
    front of its surface, so it is closed with the unknown cells of the gap.
    """
    import cv2
    res = float(resolution)
    gap = int(np.floor(max_gap / res + 1e-9))
    occ = grid == 100
    if gap < 1 or occ.sum() < 2:
        return 0
    k = max(2, int(np.ceil(_SUPPORT / res - 1e-9)))  # support cells on each side
    lines = cv2.HoughLinesP(occ.astype(np.uint8), 1, np.pi / 180, threshold=2 * k,
                            minLineLength=2 * k + 1, maxLineGap=gap + 1)
    if lines is None:
        return 0
    L = lines.reshape(-1, 4).astype(np.int64)
    d = L[:, 2:] - L[:, :2]
    n = np.abs(d).max(axis=1) + 1                   # cells along the major axis, both ends in
    seg = np.repeat(np.arange(len(L)), n)
    first = np.cumsum(n) - n
    step = np.arange(int(n.sum())) - np.repeat(first, n)
    f = step / np.maximum(n[seg] - 1, 1)
    x = np.rint(L[seg, 0] + f * d[seg, 0]).astype(np.int64)
    y = np.rint(L[seg, 1] + f * d[seg, 1]).astype(np.int64)
    v = grid[y, x]
    o = v == 100
    # looked through: a free cell with free 8-neighbours on both sides of the segment's line
    H, W = grid.shape
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)
    nx, ny = -d[seg, 1] / length[seg], d[seg, 0] / length[seg]
    side_a = np.zeros(len(v), bool)
    side_b = np.zeros(len(v), bool)
    for ox in (-1, 0, 1):          # the 8 neighbour offsets, each over all samples at once
        for oy in (-1, 0, 1):
            if ox == 0 and oy == 0:
                continue
            xx, yy = x + ox, y + oy
            ok = (xx >= 0) & (xx < W) & (yy >= 0) & (yy < H)
            fr = np.zeros(len(v), bool)
            fr[ok] = grid[yy[ok], xx[ok]] == 0
            dot = ox * nx + oy * ny
            side_a |= fr & (dot > 0.3)
            side_b |= fr & (dot < -0.3)
    through = (v == 0) & side_a & side_b
    idx = np.arange(len(v))
    # nearest occupied sample at or before / at or after each sample, within its segment
    prev = np.maximum.accumulate(np.where(o, idx, -1))
    nxt = np.minimum.accumulate(np.where(o, idx, len(v))[::-1])[::-1]
    start, end = first[seg], first[seg] + n[seg] - 1
    inside = ~o & (prev >= start) & (nxt <= end)
    # gap length in metres along the segment: its samples times the step between samples
    step_m = res * length / np.maximum(n - 1, 1)
    width = (nxt - prev - 1) * step_m[seg]
    prev_c, nxt_c = np.clip(prev, 0, len(v) - 1), np.clip(nxt, 0, len(v) - 1)
    ct = np.r_[0, np.cumsum(through)]               # looked-through samples before each index
    co = np.r_[0, np.cumsum(o)]
    seen = ct[nxt_c] - ct[prev_c + 1] > 0
    lo_w = np.maximum(prev_c - k + 1, start)
    hi_w = np.minimum(nxt_c + k - 1, end)
    left = co[prev_c + 1] - co[lo_w]
    right = co[hi_w + 1] - co[nxt_c]
    fill = inside & (width <= max_gap + 1e-9) & ~seen & (2 * left > k) & (2 * right > k)
    if not fill.any():
        return 0
    cells = np.unique(y[fill] * W + x[fill])
    grid[cells // W, cells % W] = 100
    return int(len(cells))


def free_footprint(grid: np.ndarray, origin, resolution: float, centres, radius: float) -> int:
    """Mark free (0), in place, every cell of ``grid`` whose centre lies within ``radius`` m of
    one of the grid-plane positions ``centres`` ((N, 2) m; the robot's base): the robot stands
    there, so nothing else does. Returns the number of occupied cells freed.

    RTAB-Map drops the points inside the robot's footprint from its obstacle cloud (Grid/Footprint*)
    for the same reason. Here it guards against a wall fused at a wrong pose that now lies under
    the base: move_base's recoveries clear only obstacle layers, never the static map, so with
    every cell around the base lethal or inscribed no plan can start. A ``radius`` above the
    costmap's inscribed radius leaves the base's own cell below the inscribed cost."""
    r = float(radius)
    C = np.asarray(centres, np.float64).reshape(-1, 2)
    C = C[np.isfinite(C).all(axis=1)]
    if not r > 0 or not len(C) or grid.size == 0:
        return 0
    res = float(resolution)
    H, W = grid.shape
    k = int(np.ceil(r / res)) + 1
    freed = 0
    for c in C:
        # cell indices of the centre, then a (2k+1)^2 window around it clipped to the grid
        col, row = np.floor((c - np.asarray(origin, np.float64)) / res).astype(np.int64)
        r0, r1 = max(row - k, 0), min(row + k + 1, H)
        c0, c1 = max(col - k, 0), min(col + k + 1, W)
        if r0 >= r1 or c0 >= c1:
            continue
        ys = origin[1] + (np.arange(r0, r1) + 0.5) * res - c[1]
        xs = origin[0] + (np.arange(c0, c1) + 0.5) * res - c[0]
        inside = ys[:, None] ** 2 + xs[None, :] ** 2 <= r * r
        win = grid[r0:r1, c0:c1]
        freed += int(np.count_nonzero(win[inside] == 100))
        win[inside] = 0
    return freed


class GridExtent:
    """The extent of a published grid that grows in whole steps and never shrinks.

    move_base's static layer resizes the whole global costmap whenever a grid's size or origin
    changes, and the resized costmap is blank until its next update: a plan made meanwhile goes
    through walls. A grid as wide as its content's bounding box changes with nearly every map
    update. Here the extent is the bounding box snapped
    outwards to a lattice of ``step`` metres (anchored at the map origin), joined with every
    earlier extent and with a square of ``margin`` metres around each given position (the
    camera: the robot and the depth sensor's origin then lie inside the global costmap, which
    costmap_2d requires to plan and to clear). It changes only when the map or the robot crosses
    a lattice line. ``step`` 0: the bounding box itself (no padding, no memory)."""

    def __init__(self, resolution: float, step: float = 5.0, margin: float = 2.0):
        self.res = float(resolution)
        self.step = max(1, int(round(float(step) / self.res))) if step > 0 else 0   # cells
        self.margin = float(margin) if step > 0 else 0.0
        self.box = None          # (col0, row0, col1, row1) cells, inclusive-exclusive

    def apply(self, grid, origin, around=()):
        """``(grid, origin)`` padded with unknown cells (-1) to the extent, updated with this
        grid and the grid-plane positions ``around`` ((N, 2) metres)."""
        if not self.step:
            return grid, origin
        res = self.res
        H, W = grid.shape
        c0, r0 = int(round(origin[0] / res)), int(round(origin[1] / res))
        lo = [c0, r0]
        hi = [c0 + W, r0 + H]
        for xy in np.asarray(around, np.float64).reshape(-1, 2):
            if not np.isfinite(xy).all():
                continue
            a = np.floor((xy - self.margin) / res).astype(np.int64)
            b = np.floor((xy + self.margin) / res).astype(np.int64) + 1
            lo = [min(lo[0], int(a[0])), min(lo[1], int(a[1]))]
            hi = [max(hi[0], int(b[0])), max(hi[1], int(b[1]))]
        k = self.step
        box = (lo[0] // k * k, lo[1] // k * k, -(-hi[0] // k) * k, -(-hi[1] // k) * k)
        if self.box is not None:
            box = (min(box[0], self.box[0]), min(box[1], self.box[1]),
                   max(box[2], self.box[2]), max(box[3], self.box[3]))
        self.box = box
        out = np.full((box[3] - box[1], box[2] - box[0]), -1, np.int8)
        out[r0 - box[1]:r0 - box[1] + H, c0 - box[0]:c0 - box[0] + W] = grid
        return out, (float(box[0] * res), float(box[1] * res))
