"""The planner's occupancy grid with ray-traced free space and closed wall gaps, and the per-point
views of the voxel map that feed it (mdr_slam.fusion.grid, VoxelMap views, nav.map_products,
eval.grid)."""
from __future__ import annotations

import numpy as np
import pytest

from mdr_slam.fusion import limit_openmp_threads

limit_openmp_threads(1)  # as the node does: Open3D's spinning OpenMP threads slow small calls

from mdr_slam.fusion import VoxelMap, occupancy_grid
from mdr_slam.geometry import make_T, transform_points
from mdr_slam.io import read_cloud, write_cloud
from scipy.spatial.transform import Rotation

RES = 0.05
ROOM = 4.0           # m, walls on the cell centres 0.025 and 4.025 (no point on a cell edge)
C0, C1 = 0.025, 0.025 + ROOM
GAP = (1.5, 1.8)     # 0.3 m gap in the wall y = C1: cells 30..35
CAMS = np.array([[1.0, 1.0, 1.0], [3.0, 1.0, 1.0], [2.0, 3.0, 1.0], [1.0, 3.0, 1.0],
                 [3.0, 3.0, 1.0]])


def _wall_x(x, y0, y1, z1=2.5):
    y, z = np.meshgrid(np.arange(y0, y1, 0.02), np.arange(0.0, z1, 0.05))
    return np.c_[np.full(y.size, x), y.ravel(), z.ravel()]


def _wall_y(y, x0, x1, z1=2.5):
    x, z = np.meshgrid(np.arange(x0, x1, 0.02), np.arange(0.0, z1, 0.05))
    return np.c_[x.ravel(), np.full(x.size, y), z.ravel()]


def _room(gap=False, seed=0):
    """A 4 x 4 m room (walls 2.5 m high, floor mapped in one patch only: low texture) seen from
    inside by five cameras 1 m high, and a pillar 1.5 m outside it that no camera saw (no view).
    Returns (points, views)."""
    rng = np.random.default_rng(seed)
    walls = [_wall_x(C0, C0, C1), _wall_x(C1, C0, C1), _wall_y(C0, C0, C1)]
    walls += [_wall_y(C1, C0, GAP[0]), _wall_y(C1, GAP[1], C1)] if gap else [_wall_y(C1, C0, C1)]
    floor = np.c_[rng.uniform(0.5, 1.0, (400, 2)), np.zeros(400)]
    P = np.vstack(walls + [floor])
    V = CAMS[rng.integers(0, len(CAMS), len(P))]
    pillar = np.array([[C1 + 1.5, 2.025, 0.5]])
    return np.vstack([P, pillar]), np.vstack([V, np.full((1, 3), np.nan)])


def _cell(g, origin, x, y):
    return g[int(np.floor((y - origin[1]) / RES + 1e-9)),
             int(np.floor((x - origin[0]) / RES + 1e-9))]


def _todays_grid(points, resolution, z_min, z_max, free_band):
    """The grid without views as the fusion node built it before rays (reference, up axis z)."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    h = P[:, 2]
    occ = (h >= z_min) & (h <= z_max)
    floor = (h < z_min) & (h >= z_min - free_band)
    use = occ | floor
    ij = np.floor(P[use, :2] / resolution).astype(np.int64)
    lo = ij.min(0)
    ij -= lo
    W, H = ij.max(0) + 1
    grid = np.full((int(H), int(W)), -1, np.int8)
    fl = floor[use]
    grid[ij[fl, 1], ij[fl, 0]] = 0
    grid[ij[~fl, 1], ij[~fl, 0]] = 100
    return grid, (float(lo[0] * resolution), float(lo[1] * resolution)), float(resolution)


# ------------------------------------------------------------------------------- rays
def test_room_seen_from_inside_interior_free_walls_occupied_outside_unknown():
    P, V = _room()
    g, origin, res = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V)
    assert origin == (0.0, 0.0) and res == RES
    n = int(ROOM / RES)                         # wall cells 0 and n, interior 1 .. n-1
    assert g.shape == (n + 1, n + 1 + 30)       # x up to the pillar's cell
    assert (g[0, : n + 1] == 100).all() and (g[n, : n + 1] == 100).all()
    assert (g[:, 0] == 100).all() and (g[:, n] == 100).all()
    interior = g[1:n, 1:n]
    assert (interior == 0).all(), np.argwhere(interior != 0)
    outside = g[:, n + 1:]                      # between the wall x = 4.025 and the pillar
    assert (outside[outside != 100] == -1).all() and (outside == 100).sum() == 1
    # without views only the mapped floor patch is free: the rays freed the rest
    g0, o0, _ = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3)
    assert o0 == origin and g0.shape == g.shape
    assert (g0 == 0).sum() < 0.1 * (interior == 0).sum()
    assert (g0[1:n, 1:n] == -1).sum() > 0.8 * (n - 1) ** 2
    np.testing.assert_array_equal(g0 == 100, g == 100)   # rays never change an obstacle
    # a range cap: only the first 0.5 m of each ray is traced
    gr, _, _ = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V, raytrace_range=0.5)
    assert _cell(gr, origin, 1.0, 1.3) == 0 and _cell(gr, origin, 2.0, 2.0) == -1
    assert 0 < (gr == 0).sum() < 0.6 * (g == 0).sum()


def test_many_rays_are_thinned_with_one_kept_per_point_cell(monkeypatch):
    from mdr_slam.fusion import grid as grid_module
    P, V = _room()
    full, origin, _ = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V)
    monkeypatch.setattr(grid_module, "_MAX_RAYS", 600)   # of ~1900 groups in this room
    g, o, _ = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V)
    assert o == origin and g.shape == full.shape
    np.testing.assert_array_equal(g == 100, full == 100)
    assert not ((g == 0) & (full != 0)).any()           # a subset of the same rays
    n = int(ROOM / RES)
    inner = g[1:n, 1:n]
    assert 0.9 * (n - 1) ** 2 < (inner == 0).sum() < (full[1:n, 1:n] == 0).sum()
    # every wall cell keeps a ray ending in front of it: the ring inside the walls is free
    ring = np.r_[inner[0], inner[-1], inner[:, 0], inner[:, -1]]
    assert (ring == 0).mean() > 0.97
    np.testing.assert_array_equal(occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V)[0], g)


def test_a_ray_frees_the_band_only_and_stops_before_its_point():
    # a camera 1.5 m up at the centre of cell (0, 0) looks down at a point 1 m below the floor
    # in the next cell: the ray is in the band [0.1, 1.5] over both cells, but the point's own
    # cell stays unknown; a marker wall 1 m away spans the grid
    P = np.array([[0.099, 0.025, -1.0], [1.025, 0.025, 1.0], [1.025, 0.525, 1.0]])
    V = np.array([[0.025, 0.025, 1.5], [np.nan] * 3, [np.nan] * 3])
    g, origin, _ = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V)
    assert origin == (0.0, 0.0)
    assert g[0, 0] == 0 and g[0, 1] == -1
    # a camera above the band sees the floor far away: only the cells where the ray is in the
    # band are free (heights 1.5 .. 0.1 of a ray from 3 m to 0 m: 50 % .. 97 % of the way)
    P = np.array([[2.025, 0.025, 0.0], [-0.025, 0.025, 1.0]])
    V = np.array([[0.025, 0.025, 3.0], [np.nan] * 3])
    g, origin, _ = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V)
    row = g[0]
    x = origin[0] + (np.arange(len(row)) + 0.5) * RES
    free = x[(row == 0) & (x < 2.0)]                    # the ray's cells (not the point's)
    assert free.min() == pytest.approx(0.025 + 0.5 * 2.0, abs=0.06)
    assert free.max() == pytest.approx(0.025 + (2.9 / 3.0) * 2.0, abs=0.06)
    assert _cell(g, origin, 2.025, 0.025) == 0          # the floor point's own cell: floor rule


def test_a_map_without_views_gives_the_grid_it_gave_before():
    rng = np.random.default_rng(3)
    P = np.vstack([np.c_[rng.uniform(-3, 5, (3000, 2)), rng.uniform(-0.5, 2.5, 3000)],
                   np.c_[rng.uniform(-3, 5, (2000, 2)), rng.uniform(-0.15, 0.05, 2000)]])
    ref = _todays_grid(P, RES, 0.1, 1.5, 0.3)
    for kw in ({}, {"views": None}, {"views": np.full((len(P), 3), np.nan)}):
        g, origin, res = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, **kw)
        np.testing.assert_array_equal(g, ref[0])
        assert (origin, res) == ref[1:]
    # the positional signature of before still works
    g, origin, res = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3)
    np.testing.assert_array_equal(g, ref[0])
    # views make a difference here (the test above can fail)
    V = np.tile([1.0, 1.0, 1.0], (len(P), 1))
    assert (occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V)[0] == 0).sum() > (ref[0] == 0).sum()
    with pytest.raises(ValueError):
        occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V[:10])


# ------------------------------------------------------------------------------- wall gaps
def _gap_cells(g, origin):
    row = int(np.floor((C1 - origin[1]) / RES))
    cols = np.arange(int(round(GAP[0] / RES)), int(round(GAP[1] / RES)))
    return g[row, cols]


def test_an_unseen_wall_gap_is_closed():
    P, V = _room(gap=True)
    g0, origin, _ = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V)
    assert len(_gap_cells(g0, origin)) == 6 and (_gap_cells(g0, origin) != 100).all()
    g, o, _ = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V, max_gap=0.5)
    assert o == origin
    assert (_gap_cells(g, origin) == 100).all()
    # only the gap changed: no wall grew elsewhere, nothing behind the wall
    changed = np.argwhere(g != g0)
    assert len(changed) == 6 and (changed[:, 0] == int(np.floor(C1 / RES))).all()
    # a gap wider than max_gap stays open
    g2, _, _ = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V, max_gap=0.2)
    np.testing.assert_array_equal(g2, g0)
    # without rays the gap is unknown all the same, and closed
    g3, _, _ = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, max_gap=0.5)
    assert (_gap_cells(g3, origin) == 100).all()


def test_a_gap_the_camera_looked_through_stays_open():
    P, V = _room(gap=True)
    # a farther wall 1.5 m behind the gap, its points seen through the gap from camera 2
    outer = _wall_y(C1 + 1.5, -1.0, 5.0)
    c = CAMS[2]
    t = (C1 - c[1]) / (outer[:, 1] - c[1])
    x_at_wall = c[0] + t * (outer[:, 0] - c[0])
    seen = outer[(x_at_wall > GAP[0] + 0.05) & (x_at_wall < GAP[1] - 0.05)]
    assert len(seen) > 100
    P2 = np.vstack([P, seen])
    V2 = np.vstack([V, np.tile(c, (len(seen), 1))])
    g, origin, _ = occupancy_grid(P2, RES, 0.1, 1.5, "z", 0.3, views=V2, max_gap=0.5)
    gap = _gap_cells(g, origin)
    assert (gap == 0).sum() >= 4 and (gap != 100).sum() >= 4, gap
    # the free space beyond the opening, on the line from the camera through its middle
    beyond = c[:2] + (np.array([1.65, C1]) - c[:2]) * (1.5 / (C1 - c[1]))
    assert _cell(g, origin, *beyond) == 0
    assert _cell(g, origin, seen[0, 0], C1 + 1.5) == 100


def test_a_gap_needs_wall_on_both_sides():
    # a wall over cells 0..39 (x < 2 m), a 0.3 m gap (cells 40..45), then a post of one or two
    # cells: not a wall (0.2 m of support needed), nothing is closed; with 0.5 m of wall after
    # the gap instead, it is closed
    def grid(after):
        P = np.vstack([_wall_y(0.025, 0.025, 2.0), after, [[5.025, 2.025, 1.0]]])
        return occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, max_gap=0.5)[0]
    for post in ([[2.325, 0.025, 1.0]], [[2.325, 0.025, 1.0], [2.375, 0.025, 1.0]]):
        g = grid(np.array(post))
        assert (g[0, 40:46] == -1).all() and g[0, 46] == 100
    g = grid(_wall_y(0.025, 2.325, 2.825))
    assert (g[0, 40:46] == 100).all()


# ------------------------------------------------------------------------------- views in the map
def _wall_cam(rng, n=6000, depth=2.025, half=1.0):
    u = rng.uniform(-half, half, (n, 2))
    return np.column_stack([u, np.full(n, depth)])


def _views(c):
    return np.stack([c["view_x"], c["view_y"], c["view_z"]], 1).astype(np.float64)


def test_views_are_the_latest_camera_and_follow_anchor_corrections():
    rng = np.random.default_rng(8)
    m = VoxelMap(0.05, grace=100.0)
    T1 = make_T(np.eye(3), [0.0, 0.0, 0.1])
    T2 = make_T(Rotation.from_euler("y", 90, degrees=True).as_matrix(), [0.1, 0.3, -0.2])
    m.integrate(_wall_cam(rng), T1, 0.0, anchor_id=1)
    m.integrate(_wall_cam(rng), T2, 1.0, anchor_id=2)
    c = m.to_cloud()
    a1, a2 = c["anchor_id"] == 1, c["anchor_id"] == 2
    assert a1.sum() > 100 and a2.sum() > 100
    np.testing.assert_allclose(_views(c)[a1], np.tile(T1[:3, 3], (a1.sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(_views(c)[a2], np.tile(T2[:3, 3], (a2.sum(), 1)), atol=1e-6)
    # a later cloud of the same wall from another place: merged points take its camera
    T1b = make_T(np.eye(3), [0.02, 0.0, 0.12])
    m.integrate(_wall_cam(rng), T1b, 2.0)
    c = m.to_cloud()
    a1 = c["anchor_id"] == 1
    newest = np.all(np.abs(_views(c)[a1] - T1b[:3, 3]) < 1e-6, axis=1)
    assert newest.mean() > 0.9
    # a correction moves anchor 2's points and their views by the same rigid motion
    D = make_T(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [0.3, 0.1, 0.0])
    before = m.to_cloud()
    b2 = before["anchor_id"] == 2
    m.apply_corrections({2: D @ T2})
    after = m.to_cloud()
    assert len(after["x"]) == len(before["x"])
    np.testing.assert_allclose(_views(after)[b2], transform_points(D, _views(before)[b2]),
                               atol=1e-5)
    np.testing.assert_allclose(_views(after)[~b2], _views(before)[~b2], atol=0)
    np.testing.assert_allclose(_views(after)[b2], np.tile(D[:3, 3] + D[:3, :3] @ T2[:3, 3],
                                                          (b2.sum(), 1)), atol=1e-5)


def test_a_fold_keeps_the_view_of_the_newer_sighting():
    m = VoxelMap(0.05)
    base = {"x": np.array([0.01, 1.01, 2.01]), "y": np.zeros(3) + 0.01, "z": np.zeros(3) + 0.01,
            "last_seen": np.array([5.0, 5.0, 5.0]),
            "view_x": np.zeros(3), "view_y": np.zeros(3), "view_z": np.ones(3)}
    m.load(base)
    # the same voxels again (they merge): newer, older, and newer without a view
    m.load({"x": base["x"] + 0.005, "y": base["y"], "z": base["z"],
            "last_seen": np.array([9.0, 1.0, 9.0]),
            "view_x": np.array([7.0, 7.0, np.nan]), "view_y": np.zeros(3), "view_z": np.ones(3)},
           append=True)
    c = m.to_cloud()
    assert len(c["x"]) == 3
    order = np.argsort(c["x"])
    np.testing.assert_allclose(c["view_x"][order], [7.0, 0.0, 0.0])
    np.testing.assert_allclose(c["last_seen"][order], [9.0, 5.0, 9.0])


def test_views_survive_save_and_load_and_old_files_load_without_rays(tmp_path):
    rng = np.random.default_rng(7)
    m = VoxelMap(0.05, grace=100.0, min_confidence=1)
    for i in range(3):
        T = make_T(Rotation.from_rotvec([0, 0.01 * i, 0]).as_matrix(), [0.05 * i, 0.2, 0])
        m.integrate(_wall_cam(rng), T, 10.0 + i, anchor_id=i)
    path = str(tmp_path / "map.ply")
    m.save(path)
    fields = read_cloud(path)
    assert {"view_x", "view_y", "view_z"} <= set(fields)
    m2 = VoxelMap(0.05, min_confidence=1)
    m2.load(path)
    a, b = m.to_cloud(), m2.to_cloud()
    oa = np.lexsort((a["z"], a["y"], a["x"]))
    ob = np.lexsort((b["z"], b["y"], b["x"]))
    np.testing.assert_array_equal(_views(a)[oa], _views(b)[ob])
    assert np.isfinite(_views(b)).all()
    # the grid of the reloaded map is the same, rays included
    for raytrace in (True, False):
        ga, gb = m.occupancy_grid(up_axis="-y", raytrace=raytrace), \
            m2.occupancy_grid(up_axis="-y", raytrace=raytrace)
        np.testing.assert_array_equal(ga[0], gb[0])
        assert ga[1:] == gb[1:]
    # a map file written before views were kept: NaN views, the grid of the points alone
    old = {k: v for k, v in fields.items() if not k.startswith("view_")}
    write_cloud(str(tmp_path / "old.ply"), old)
    m3 = VoxelMap(0.05, min_confidence=1)
    m3.load(str(tmp_path / "old.ply"))
    assert len(m3) == len(m) and np.isnan(_views(m3.to_cloud())).all()
    g3 = m3.occupancy_grid(up_axis="-y")
    np.testing.assert_array_equal(g3[0], m.occupancy_grid(up_axis="-y", raytrace=False)[0])
    assert (m.occupancy_grid(up_axis="-y")[0] == 0).sum() > (g3[0] == 0).sum()


# ------------------------------------------------------------------------------- node and scores
def _params(**over):
    from mdr_slam.nodes.config import FusionNodeConfig
    p = dict(FusionNodeConfig().to_dict(), confidence=True, grid_min_confidence=0,
             display_min_confidence=0)
    p.update(over)
    return p


def test_the_published_grid_uses_the_views_and_the_gap_rule():
    from mdr_slam.nav import map_products
    P, V = _room(gap=True)
    cloud = {"x": P[:, 0], "y": P[:, 1], "z": P[:, 2], "intensity": np.zeros(len(P)),
             "confidence": np.full(len(P), 5), "view_x": V[:, 0], "view_y": V[:, 1],
             "view_z": V[:, 2]}
    p = _params()
    assert p["grid_raytrace"] is True and p["grid_max_gap"] == 0.5
    _, (g, origin, res) = map_products(cloud, p)
    ref = occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, views=V, max_gap=0.5)
    np.testing.assert_array_equal(g, ref[0])
    assert (_gap_cells(g, origin) == 100).all()
    _, (g0, _, _) = map_products(cloud, _params(grid_raytrace=False, grid_max_gap=0.0))
    np.testing.assert_array_equal(g0, occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3)[0])
    # a cloud without views (a peer's map) gives the grid without rays
    plain = {k: v for k, v in cloud.items() if not k.startswith("view_")}
    _, (g1, _, _) = map_products(plain, p)
    np.testing.assert_array_equal(g1, occupancy_grid(P, RES, 0.1, 1.5, "z", 0.3, max_gap=0.5)[0])


def test_grid_metrics_free_precision_and_the_bench_parameters():
    from mdr_slam.cli.main_bench import _grid_params
    from mdr_slam.eval import grid_metrics, obstacle_cells
    from mdr_slam.eval.grid import grid_cells
    P, V = _room()
    gt = P[:-1]
    g = grid_metrics(P, gt, resolution=RES, est_views=V)
    assert g["free_precision"] == 1.0 and g["n_est_free_cells"] > 0.9 * 79 ** 2
    assert g["raytrace"] is True and g["recall"] == 1.0
    g0 = grid_metrics(P, gt, resolution=RES)
    assert g0["n_est_free_cells"] < 0.1 * g["n_est_free_cells"] and g0["raytrace"] is False
    for k in ("recall", "precision", "n_true_cells", "n_est_cells", "n_est_points"):
        assert g0[k] == g[k]
    # the estimate misses a piece of a true wall and a stray point behind it is seen through
    # the hole: its ray frees true obstacle cells
    hole = (gt[:, 0] == C1) & (gt[:, 1] > 1.0) & (gt[:, 1] < 1.5)
    est, ev = P[~np.r_[hole, False]], V[~np.r_[hole, False]]
    stray = np.array([[C1 + 1.0, 1.25, 1.0]])
    g2 = grid_metrics(np.vstack([est, stray]), gt, resolution=RES,
                      est_views=np.vstack([ev, [[1.0, 1.25, 1.0]]]))
    assert g2["free_precision"] < 1.0
    _, free = grid_cells(np.vstack([est, stray]), RES, views=np.vstack([ev, [[1.0, 1.25, 1.0]]]))
    wrong = {tuple(c) for c in free} & {tuple(c) for c in obstacle_cells(gt, RES)}
    assert len(wrong) == round((1 - g2["free_precision"]) * g2["n_est_free_cells"])
    # the stray's ray through the wall, and rays grazing along the wall's missing piece
    assert (80, 25) in wrong and all(c[0] == 80 and 20 <= c[1] < 30 for c in wrong), wrong
    # the bench and `mdr eval grid` take the node's grid parameters, --set overrides included
    gp = _grid_params([])
    assert gp["raytrace"] is True and gp["max_gap"] == 0.5 and gp["raytrace_range"] == 0.0
    gp = _grid_params(["fusion.grid_raytrace=false", "fusion.grid_max_gap=0.3",
                       "fusion.grid_raytrace_range=4", "depth.grid_max_gap=9"])
    assert gp["raytrace"] is False and gp["max_gap"] == 0.3 and gp["raytrace_range"] == 4.0
    with pytest.raises(ValueError):
        _grid_params(["fusion.grid_raytrace=maybe"])
