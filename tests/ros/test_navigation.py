"""Planners: the grid planner (mdr_slam.nav), the move_base configuration, and
the contract a planner relies on: on the sample map (the README demo's sample bag, mapped by the
offline pipeline with its true poses) the occupancy grid agrees with the map cloud (frame,
resolution, origin), A* finds a path between far-apart cells of the office and none into an
obstacle, and the map points move_base's obstacle layer marks all lie in occupied grid cells (the
two costmap layers agree); on a live run tf map -> base_link exists at the stamps of the map and
depth clouds. move_base itself is not in Debian."""
from __future__ import annotations

import os
import subprocess
import time

import numpy as np
import pytest
import yaml

from conftest import ROOT, wait_for
from mdr_slam.nav import (cell_to_world, grid_from_msg, map_products, plan_path, traversable,
                          world_to_cell)

CONFIG = os.path.join(ROOT, "src", "mdr_slam", "config")


def _check_path(plan, ok, start_cell, goal_cell):
    """The path is 8-connected, starts and ends in the right cells and only uses allowed cells."""
    c = plan.cells
    assert tuple(c[0]) == tuple(start_cell) and tuple(c[-1]) == tuple(goal_cell)
    steps = np.abs(np.diff(c, axis=0))
    assert steps.max() <= 1 and steps.sum(1).min() >= 1
    assert ok[c[:, 0], c[:, 1]].all()


# ---------------------------------------------------------------------- (a) planner, known answers
def test_wall_with_gap_goes_through_the_gap():
    res, origin = 0.1, (-1.0, 2.0)
    g = np.zeros((40, 60), np.int8)
    g[:, 30] = 100
    g[18:21, 30] = 0                      # a 3-cell (0.3 m) gap at rows 18..20
    start, goal = cell_to_world((10, 5), origin, res), cell_to_world((10, 55), origin, res)
    plans = {m: plan_path(g, start, goal, res, origin, method=m) for m in ("astar", "dijkstra")}
    for p in plans.values():
        _check_path(p, g == 0, (10, 5), (10, 55))
        assert (p.cells[:, 1] == 30).sum() >= 1 and 18 <= p.cells[p.cells[:, 1] == 30, 0].min() <= 20
    # known optimum: 8 diagonal steps down to row 18, straight through the gap, 8 back up:
    # 16 diagonals + (50 - 16) straight cells
    want = (34 + 16 * np.sqrt(2)) * res
    assert plans["astar"].length == pytest.approx(want, abs=1e-9)
    assert plans["dijkstra"].length == pytest.approx(want, abs=1e-9)
    np.testing.assert_allclose(plans["astar"].xy[0], start)
    # tuple form (as occupancy_grid returns it) gives the same plan
    assert plan_path((g, origin, res), start, goal).length == pytest.approx(want)


def test_no_path_when_blocked_and_bad_queries():
    g = np.zeros((20, 20), np.int8)
    g[:, 10] = 100
    assert plan_path(g, (0.25, 0.25), (1.75, 0.25), 0.1, (0, 0)) is None
    assert plan_path(g, (0.25, 0.25), (1.75, 0.25), 0.1, (0, 0), method="dijkstra") is None
    # diagonal corner cutting between two obstacle cells is not a way through either
    assert plan_path(np.array([[0, 100], [100, 0]], np.int8), (0.5, 0.5), (1.5, 1.5), 1.0, (0, 0)) is None
    assert plan_path(g, (1.05, 0.25), (0.25, 0.25), 0.1, (0, 0)) is None   # start on an obstacle
    with pytest.raises(ValueError, match="outside"):
        plan_path(g, (-0.5, 0.25), (0.25, 0.25), 0.1, (0, 0))
    with pytest.raises(ValueError, match="resolution"):
        plan_path(g, (0.5, 0.25), (0.25, 0.25))


def test_inflation_closes_a_narrow_gap_and_unknown_is_configurable():
    res = 0.05
    g = np.zeros((60, 60), np.int8)
    g[:, 30] = 100
    g[28:32, 30] = 0                      # 4 cells = 0.2 m gap
    s, t = (0.3, 1.5), (2.7, 1.5)
    assert plan_path(g, s, t, res, (0, 0), robot_radius=0.05) is not None   # 0.1 m robot fits
    assert plan_path(g, s, t, res, (0, 0), robot_radius=0.15) is None       # 0.3 m robot does not
    ok = traversable(g, res, 0.15)
    assert not ok[:20, 27:34].any() and not ok[:, 30].any() and ok[:, :27].all() and ok[:20, 34:].all()
    # unknown cells: blocked by default, traversable on request
    u = np.zeros((10, 30), np.int8)
    u[:, 10:20] = -1
    assert plan_path(u, (0.25, 0.25), (2.75, 0.25), 0.1, (0, 0)) is None
    p = plan_path(u, (0.25, 0.25), (2.75, 0.25), 0.1, (0, 0), unknown_traversable=True)
    assert p is not None and p.length == pytest.approx(2.5)


def test_world_cell_roundtrip_and_grid_message():
    from nav_msgs.msg import OccupancyGrid
    origin, res = (1.25, -3.5), 0.05
    rc = np.array([[0, 0], [7, 3], [99, 41]])
    xy = cell_to_world(rc, origin, res)
    np.testing.assert_array_equal(world_to_cell(xy, origin, res), rc)
    np.testing.assert_array_equal(world_to_cell(np.array(origin) + [0.0999, 0.0001], origin, res), [0, 1])
    m = OccupancyGrid()
    m.info.resolution, m.info.width, m.info.height = res, 4, 3
    m.info.origin.position.x, m.info.origin.position.y = origin
    m.info.origin.orientation.w = 1.0
    m.data = list(range(12))
    g, o, r = grid_from_msg(m)
    assert g.shape == (3, 4) and g[1, 0] == 4 and o == origin and r == res
    m.info.origin.orientation.z, m.info.origin.orientation.w = 0.7071, 0.7071
    with pytest.raises(ValueError, match="rotated"):
        grid_from_msg(m)


def test_costmap_parameters_match_the_fusion_grid():
    fusion = yaml.safe_load(open(os.path.join(CONFIG, "fusion.yaml")))
    nav = os.path.join(CONFIG, "navigation")
    common = yaml.safe_load(open(os.path.join(nav, "costmap_common_params.yaml")))
    glob = yaml.safe_load(open(os.path.join(nav, "global_costmap_params.yaml")))["global_costmap"]
    local = yaml.safe_load(open(os.path.join(nav, "local_costmap_params.yaml")))["local_costmap"]
    mb = yaml.safe_load(open(os.path.join(nav, "move_base.yaml")))
    # relative: follows a namespace; the grid with unknown cells free, which the fusion node
    # publishes by default
    assert common["static_layer"]["map_topic"] == "mdr/map/nav_grid" and fusion["publish_nav_grid"]
    # its unknown cells free or at a cost, never lethal: the static layer scales the value
    sl = common["static_layer"]
    assert not sl["trinary_costmap"] and 0 <= fusion["nav_grid_unknown"] < sl["lethal_cost_threshold"]
    assert glob["global_frame"] == fusion["map_frame"] and glob["robot_base_frame"] == "base_link"
    assert glob["resolution"] == fusion["grid_resolution"]
    assert local["global_frame"] == "odom" and local["rolling_window"]
    ol = common["obstacle_layer"]
    srcs = {ol[s]["topic"]: ol[s] for s in ol["observation_sources"].split()}
    # the map's obstacles come from the grid alone: marks of map points stay where a loop
    # correction has since moved them from (tests/ros/test_move_base.py)
    assert "mdr/map/points" not in srcs and not srcs["mdr/depth/points"]["marking"]
    for s in srcs.values():
        assert s["min_obstacle_height"] == fusion["grid_z_min"]
        assert s["max_obstacle_height"] == fusion["grid_z_max"]
    assert fusion["grid_up_axis"] == "z"         # the costmaps measure heights along map z
    # /mdr/map/points shows no point less confident than the grid's, so the cloud in rviz shows
    # the obstacles move_base has (test_map_points_are_occupied_grid_cells measures it)
    from mdr_slam.nodes import node_defaults
    for conf in (fusion, node_defaults("fusion")):
        assert conf["display_min_confidence"] >= conf["grid_min_confidence"]
    # the display cells nest in the grid cells, in the plane and at the band's edges
    for v in (fusion["grid_resolution"], fusion["grid_z_min"], fusion["grid_z_max"]):
        assert v / fusion["display_voxel"] == pytest.approx(round(v / fusion["display_voxel"]))
    names = [p["name"] for p in glob["plugins"]]
    assert names == ["static_layer", "obstacle_layer", "inflation_layer"]
    # the local costmap (odom) marks what the cameras see now, not the map cloud, whose marks
    # stay where an old map -> odom put them (tests/ros/test_move_base.py)
    assert [p["name"] for p in local["plugins"]] == names[1:]
    assert local["obstacle_layer"]["observation_sources"].split() == \
        ["mdr_depth", "mdr_depth_lost", "bumper"]
    assert local["obstacle_layer"]["mdr_depth"]["marking"] and srcs["mdr/depth/points"]["clearing"]
    # while LOST: the depth node's single-frame cloud, in the local costmap (odom) only
    lost = local["obstacle_layer"]["mdr_depth_lost"]
    assert lost["topic"] == "mdr/depth/raw_points" and lost["marking"] and lost["clearing"]
    assert lost["min_obstacle_height"] == fusion["grid_z_min"]
    assert lost["max_obstacle_height"] == fusion["grid_z_max"]
    assert "mdr/depth/raw_points" not in srcs
    # the costmap's own unknown cells are only those of a global costmap just resized (blank):
    # the planner must not cross them (tests/ros/test_move_base.py)
    assert glob["track_unknown_space"] and not mb["GlobalPlanner"]["allow_unknown"]
    assert mb["base_global_planner"] == "global_planner/GlobalPlanner"


def test_navigation_launch_parses_with_and_without_move_base():
    def nodes(*args):
        r = subprocess.run(["roslaunch", "--nodes", os.path.join(ROOT, "launch", "navigation.launch")]
                           + list(args), capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        return set(r.stdout.split())
    assert nodes() == {"/pose_node", "/depth_node", "/fusion_node"}
    assert nodes("move_base:=true", "bag:=/x.bag") == {"/pose_node", "/depth_node", "/fusion_node",
                                                       "/bag_player", "/move_base"}


def test_navigation_launch_passes_every_mdr_launch_argument():
    """navigation.launch declares every argument of mdr.launch with the same default and hands it
    to mdr.launch, so an option of the map nodes works the same with move_base (but planar motion,
    auto for the ground robot move_base drives); and roslaunch really applies one (weak_texture,
    mapping_nice, depth_malloc_arena_max, planar_motion)."""
    import xml.etree.ElementTree as ET

    def declared(root):
        return {a.get("name"): a.get("default") for a in root.findall("arg") if "default" in a.attrib}
    mdr = ET.parse(os.path.join(ROOT, "launch", "mdr.launch")).getroot()
    nav = ET.parse(os.path.join(ROOT, "launch", "navigation.launch")).getroot()
    want, have = declared(mdr), declared(nav)
    inc = [i for i in nav.findall("include") if i.get("file").endswith("/launch/mdr.launch")]
    assert len(inc) == 1
    passed = {a.get("name"): a.get("value") for a in inc[0].findall("arg")}
    missing = sorted(set(want) - set(have))
    other_default = {k: (want[k], have[k]) for k in want if k in have and have[k] != want[k]}
    assert other_default.pop("planar_motion", None) == ("false", "auto")
    not_passed = sorted(k for k in want if passed.get(k) != "$(arg %s)" % k)
    print("mdr.launch: %d arguments; navigation.launch lacks %s, other defaults %s, not passed %s"
          % (len(want), missing, other_default, not_passed))
    assert not missing and not other_default and not not_passed
    assert set(passed) <= set(want)       # roslaunch refuses an argument mdr.launch does not declare

    r = subprocess.run(["roslaunch", "--dump-params", os.path.join(ROOT, "launch", "navigation.launch"),
                        "weak_texture:=sgbm", "move_base:=true"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    params = yaml.safe_load(r.stdout)
    assert params["/depth_node/weak_texture"] == "sgbm"
    assert params["/pose_node/planar_motion"] == "auto"
    r = subprocess.run(["roslaunch", "--args", "depth_node", os.path.join(ROOT, "launch", "navigation.launch"),
                        "mapping_nice:=3"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.startswith("nice -n 3 "), (r.stdout, r.stderr)


# ---------------------------------------------------------------------- (b) the sample map
MID_FRAME = 300   # 15 s into the sample: the pure-rotation segment, the map full of young points


@pytest.fixture(scope="module")
def nav_sim(tmp_path_factory):
    """The office loop at half resolution and 10 Hz (as tests/cli/test_pipeline.py's small_sim), for
    the live run: a light bag for the three nodes on a shared 2-core machine."""
    from mdr_slam.sim import generate
    d = str(tmp_path_factory.mktemp("nav_office"))
    generate(d, scene="office", duration=30.0, seed=1, rate=10.0, scale=0.5, workers=2,
             map_cell=0.02)
    return d


@pytest.fixture(scope="module")
def sample_map(sample_bag):
    """The README demo's map of the sample bag (conftest ``sample_bag``: 752x480, 20 Hz, 600
    pairs): the offline pipeline of ``mdr run BAG --pose-source groundtruth`` (what
    ``./run_demo.sh --pose-source groundtruth`` maps) on every frame, in-process. Ground-truth
    poses, not ORB: the ORB map is in the first camera's optical frame (no floor-level z-up
    ``map``, so the grid's obstacle band has no meaning there without aligning it to the ground
    truth) and tracking would add ~30 s of CPU. Returns the map snapshots ``{"mid", "end"}``
    (``to_cloud(0)`` after frame MID_FRAME and after the last frame), the fusion parameters, the
    camera positions and the costmap parameters."""
    from mdr_slam.pipeline import Pipeline, PipelineConfig, frames_from_bag, load_params
    cam, frames = frames_from_bag(os.path.join(sample_bag, "sequence.bag"), ground_truth=True)
    pl = Pipeline(cam, PipelineConfig(pose_source="groundtruth"))
    snaps = {}
    t0 = time.perf_counter()
    for i, f in enumerate(frames, 1):
        pl.process(f)
        if i == MID_FRAME:
            snaps["mid"] = pl.map.to_cloud(0)
    snaps["end"] = pl.map.to_cloud(0)
    print("sample map: %d frames in %.1f s, %d points" % (i, time.perf_counter() - t0, len(pl.map)))
    assert i == 600 and len(pl.poses) == 600
    common = yaml.safe_load(open(os.path.join(CONFIG, "navigation", "costmap_common_params.yaml")))
    return snaps, load_params("fusion"), np.array([T[:3, 3] for _, T in pl.poses]), common


def _grid_message(grid, p):
    """The grid as the fusion node publishes it (same functions, same parameters)."""
    from nav_msgs.msg import OccupancyGrid
    from mdr_slam.conversions import matrix_to_pose
    from mdr_slam.fusion import grid_origin_T
    data, origin, res = grid
    m = OccupancyGrid()
    m.header.frame_id = p["map_frame"]
    m.info.resolution = res
    m.info.height, m.info.width = data.shape
    m.info.origin = matrix_to_pose(grid_origin_T(origin, p["grid_up_axis"], p["grid_z_min"]))
    m.data = data.reshape(-1).tolist()
    return m


def test_sample_map_grid_agrees_with_the_cloud_and_plans_a_path(sample_map):
    from scipy import ndimage
    from scipy.spatial import cKDTree
    snaps, p, traj, common = sample_map
    c = snaps["end"]
    xyz = np.stack([c["x"], c["y"], c["z"]], 1).astype(np.float64)
    xyz = xyz[c["confidence"] >= p["grid_min_confidence"]]     # the grid's points, unsampled
    _, grid = map_products(c, p)                                # what the fusion node publishes
    msg = _grid_message(grid, p)
    g, origin, res = grid_from_msg(msg)
    H, W = g.shape
    assert msg.header.frame_id == p["map_frame"] and res == pytest.approx(p["grid_resolution"])
    assert msg.info.origin.position.z == pytest.approx(p["grid_z_min"])
    # origin on the global lattice of the resolution: successive grids line up cell for cell
    assert np.allclose(np.array(origin) / res, np.round(np.array(origin) / res), atol=1e-6)
    band = xyz[(xyz[:, 2] >= p["grid_z_min"]) & (xyz[:, 2] <= p["grid_z_max"])]
    floor = xyz[(xyz[:, 2] < p["grid_z_min"]) & (xyz[:, 2] >= p["grid_z_min"] - p["grid_free_band"])]
    assert len(band) > 3000 and len(floor) > 100
    # every obstacle-band point lies inside the grid, in an occupied cell; every occupied cell
    # holds band points, except the few that close wall gaps (grid_max_gap: unknown or only
    # grazed by rays without it); the floor points lie in free or occupied cells (never unknown)
    rc = world_to_cell(band[:, :2], origin, res)
    assert (rc >= 0).all() and (rc[:, 0] < H).all() and (rc[:, 1] < W).all()
    assert (g[rc[:, 0], rc[:, 1]] == 100).all()
    g_open, o_open, _ = map_products(c, dict(p, grid_max_gap=0.0))[1]
    assert o_open == origin and g_open.shape == g.shape
    assert len(np.unique(rc[:, 0] * W + rc[:, 1])) == (g_open == 100).sum()
    closed = (g == 100) & (g_open != 100)
    assert p["grid_max_gap"] > 0 and 0 < closed.sum() < 0.05 * (g == 100).sum()
    assert ((g == 100) | ~(g_open == 100)).all() and ((g == g_open) | closed).all()
    fc = world_to_cell(floor[:, :2], origin, res)
    assert (fc >= 0).all() and (fc[:, 0] < H).all() and (fc[:, 1] < W).all()
    assert (g[fc[:, 0], fc[:, 1]] >= 0).all()
    lo, hi = np.array(origin), np.array(origin) + res * np.array([W, H])
    used = np.vstack([band, floor])[:, :2]
    assert (used.min(0) >= lo - 1e-9).all() and (used.max(0) <= hi + 1e-9).all()
    # the grid covers the office (8 x 6 m) and the camera's whole route; no cell on the route is
    # occupied (no phantom obstacles where the robot went)
    assert W * res > 6.0 and H * res > 4.5
    tc = world_to_cell(traj[:, :2], origin, res)
    assert ((tc >= 0).all(1) & (tc[:, 0] < H) & (tc[:, 1] < W)).all()
    assert (g[tc[:, 0], tc[:, 1]] != 100).all()

    # The robot of config/navigation (robot_radius) on the grid as navfn reads it (allow_unknown,
    # move_base.yaml). The sample's low-texture floor is mostly unmapped, but the rays from the
    # cameras free the office around the route (grid_raytrace), the route itself included.
    radius = float(common["robot_radius"])
    ok = traversable(g, res, radius, unknown_traversable=True)
    occ_xy = cell_to_world(np.argwhere(g == 100), origin, res)
    start, half = traj[0, :2], traj[len(traj) // 2, :2]       # t = 0 and t = 15 s of the loop
    sc, hc = world_to_cell(start, origin, res), world_to_cell(half, origin, res)
    assert ok[tuple(sc)] and ok[tuple(hc)]                     # both ends: a robot fits there
    straight = np.linalg.norm(half - start)
    assert straight > 1.5                                      # far apart in the office
    t0 = time.perf_counter()
    plan = plan_path((g, origin, res), start, half, robot_radius=radius, unknown_traversable=True)
    t_astar = time.perf_counter() - t0
    assert plan is not None
    _check_path(plan, ok, sc, hc)
    d, _ = cKDTree(occ_xy).query(plan.xy)   # independent clearance check: no cell within radius
    assert d.min() > radius
    dij = plan_path((g, origin, res), start, half, robot_radius=radius, unknown_traversable=True,
                    method="dijkstra")
    assert dij.length == pytest.approx(plan.length, abs=1e-9)
    # plausible: at least the straight line between the cell centres, at most the camera's own
    # route between the two poses (a feasible way, up to the octile detour of a grid path)
    route = float(np.sum(np.linalg.norm(np.diff(traj[:len(traj) // 2 + 1, :2], axis=0), axis=1)))
    assert plan.length >= np.linalg.norm(plan.xy[-1] - plan.xy[0]) - 1e-9
    assert plan.length <= 1.09 * max(route, straight) + 2 * res
    for q in traj[::20, :2]:                # every part of the route is reachable from the start
        assert plan_path((g, origin, res), start, q, robot_radius=radius,
                         unknown_traversable=True) is not None, q

    # Negative: a goal in an obstacle (the middle of the largest occupied blob) has no path, with
    # or without unknown cells; a goal in an unknown cell has none when unknown is not allowed
    lab, n = ndimage.label(g == 100)
    big = np.argmax(ndimage.sum(g == 100, lab, range(1, n + 1))) + 1
    core = ndimage.binary_erosion(lab == big)
    assert core.any()
    wall = cell_to_world(np.argwhere(core)[len(np.argwhere(core)) // 2], origin, res)
    assert plan_path((g, origin, res), start, wall, robot_radius=radius, unknown_traversable=True) is None
    assert plan_path((g, origin, res), start, wall) is None
    # on the free cells alone (unknown not traversable) the same trip has a path: no shorter
    # than the one across the unknown middle of the loop (no camera looked there), no longer than
    # the camera's own way; without the rays it has none (the route is unknown)
    assert (g[tc[:, 0], tc[:, 1]] == 0).mean() > 0.95
    known = plan_path((g, origin, res), start, half, robot_radius=radius)
    assert known is not None and plan.length - 1e-9 <= known.length <= 1.09 * route + 2 * res
    g_floor, o_floor, _ = map_products(c, dict(p, grid_raytrace=False))[1]
    assert (g_floor[world_to_cell(traj[:, :2], o_floor, res)[:, 0],
                    world_to_cell(traj[:, :2], o_floor, res)[:, 1]] == -1).all()
    assert plan_path((g_floor, o_floor, res), start, half, robot_radius=radius) is None

    # Strictly on free cells: the two farthest-apart cells of the largest free component
    free = g == 0
    lab, n = ndimage.label(free)          # 4-connected: reachable without cutting corners
    assert n >= 1
    big = np.argmax(ndimage.sum(free, lab, range(1, n + 1))) + 1
    cells = np.argwhere(lab == big)
    a = cells[0]
    b = cells[np.argmax(np.linalg.norm(cells - a, axis=1))]
    a = cells[np.argmax(np.linalg.norm(cells - b, axis=1))]
    strict = plan_path((g, origin, res), cell_to_world(a, origin, res), cell_to_world(b, origin, res))
    assert strict is not None and len(cells) >= 20
    _check_path(strict, free, a, b)
    assert (g[strict.cells[:, 0], strict.cells[:, 1]] == 0).all()
    print("sample map: grid %dx%d at %s, %d occupied, %d free, %d unknown cells (%d of %d route "
          "cells unknown); start->half-way path %.2f m (straight %.2f m, route %.2f m, A* %.1f ms, "
          "robot radius %.2f m); on free cells %.2f m over %d free cells"
          % (W, H, origin, (g == 100).sum(), free.sum(), (g == -1).sum(),
             (g[tc[:, 0], tc[:, 1]] == -1).sum(), len(tc), plan.length, straight, route,
             1e3 * t_astar, radius, strict.length, len(cells)))


def _points_off_occupied(pts, grid, lo_h, hi_h):
    """(band points, of them in free cells, in unknown cells, outside the grid): the published
    map points move_base's obstacle layer marks (height in [lo_h, hi_h], as costmap_2d's
    min/max_obstacle_height) against the published grid's cells."""
    g, origin, res = grid
    x = pts["xyz"]
    band = x[(x[:, 2] >= lo_h) & (x[:, 2] <= hi_h)]
    rc = world_to_cell(band[:, :2], origin, res)
    inside = (rc >= 0).all(1) & (rc[:, 0] < g.shape[0]) & (rc[:, 1] < g.shape[1])
    v = g[rc[inside, 0], rc[inside, 1]]
    return len(band), int((v == 0).sum()), int((v == -1).sum()), int((~inside).sum())


@pytest.mark.parametrize("when", ["mid", "end"])
def test_map_points_are_occupied_grid_cells(sample_map, when):
    """The cloud and the grid agree: every /mdr/map/points point in the grid's height band falls
    in a cell /mdr/map/grid (move_base's static layer) marks occupied, in the middle of the run
    (young points everywhere) and at its end."""
    snaps, p, _, _common = sample_map
    lo_h, hi_h = p["grid_z_min"], p["grid_z_max"]
    assert p["display_min_confidence"] >= p["grid_min_confidence"]
    pts, grid = map_products(snaps[when], p)
    n, n_free, n_unknown, n_out = _points_off_occupied(pts, grid, lo_h, hi_h)
    # the check can fail: with the former default display_min_confidence 2 the cloud holds young
    # points (seen by 2 clouds) the grid (confidence >= 3) does not mark
    old = _points_off_occupied(map_products(snaps[when], dict(p, display_min_confidence=2))[0],
                               grid, lo_h, hi_h)
    print("%s (frame %s): %d band points of /mdr/map/points, %d in free, %d in unknown cells, %d "
          "outside the grid; with display_min_confidence 2: %d band points, %d free, %d unknown, "
          "%d outside" % (when, MID_FRAME if when == "mid" else "600", n, n_free, n_unknown, n_out,
                          *old))
    assert n > 3000
    assert (n_free, n_unknown, n_out) == (0, 0, 0)
    assert sum(old[1:]) > 0


# ---------------------------------------------------------------------- (c) live run: tf and frames
@pytest.mark.ros
def test_live_tf_at_cloud_stamps_and_grid_frame(nav_sim, rospy_client, start_process, tmp_path):
    rospy = rospy_client
    import tf2_ros
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import PointCloud2
    fusion = yaml.safe_load(open(os.path.join(CONFIG, "fusion.yaml")))
    fusion.update(map_path=str(tmp_path / "map.ply"), autosave=False, publish_rate=2.0)
    fparams = tmp_path / "fusion.yaml"
    fparams.write_text(yaml.safe_dump(fusion))
    buf = tf2_ros.Buffer(cache_time=rospy.Duration(120.0))
    tf2_ros.TransformListener(buf)
    maps, grids, depths = [], [], []
    subs = [rospy.Subscriber("/mdr/map/points", PointCloud2, maps.append, queue_size=5),
            rospy.Subscriber("/mdr/map/grid", OccupancyGrid, grids.append, queue_size=5),
            rospy.Subscriber("/mdr/depth/points", PointCloud2, depths.append, queue_size=5)]
    launch = start_process(["roslaunch", os.path.join(ROOT, "launch", "navigation.launch"),
                            "bag:=" + os.path.join(nav_sim, "sequence.bag"),
                            "pose_source:=groundtruth", "respawn:=false", "delay:=3", "rate:=2",
                            "fusion_params:=%s" % fparams], "navigation_launch")
    try:
        def n_occupied(gm):
            return int((np.asarray(gm.data, np.int8) == 100).sum())
        got = wait_for(lambda: len(maps) >= 3 and len(depths) >= 5 and len(grids) >= 3
                       and n_occupied(grids[-1]) >= 50, 45, 0.5)
        assert got, "maps %d grids %d depth %d\n%s" % (len(maps), len(grids), len(depths),
                                                        launch.output()[-3000:])

        def tf_at(msg):
            stamp = msg.header.stamp
            ok = wait_for(lambda: buf.can_transform("map", "base_link", stamp), 5.0, 0.05)
            return buf.lookup_transform("map", "base_link", stamp) if ok else None
        for kind, msgs in (("map", maps[:3]), ("depth", depths[:5])):
            for m in msgs:
                assert tf_at(m) is not None, "no tf map -> base_link at the %s cloud stamp %.3f" % (
                    kind, m.header.stamp.to_sec())
                assert buf.can_transform("map", m.header.frame_id, m.header.stamp)
        for gm in grids:
            assert gm.header.frame_id == maps[0].header.frame_id == fusion["map_frame"]
            assert gm.info.resolution == pytest.approx(fusion["grid_resolution"])
        # a grid and the cloud of the same publish (same stamp) agree cell for cell
        from mdr_slam.conversions import pointcloud2_to_xyz
        pairs = [(gm, m) for gm in grids for m in maps if gm.header.stamp == m.header.stamp]
        assert pairs
        gm, m = pairs[-1]
        g, origin, res = grid_from_msg(gm)
        xyz = pointcloud2_to_xyz(m)
        band = xyz[(xyz[:, 2] >= fusion["grid_z_min"]) & (xyz[:, 2] <= fusion["grid_z_max"])]
        rc = world_to_cell(band[:, :2], origin, res)
        inside = (rc >= 0).all(1) & (rc[:, 0] < g.shape[0]) & (rc[:, 1] < g.shape[1])
        hit = np.zeros(g.shape, bool)
        hit[rc[inside, 0], rc[inside, 1]] = True
        occ = g == 100
        assert occ.sum() >= 50
        print("live: %d map clouds, %d grids, %d depth clouds; grid %dx%d, %d occupied cells, "
              "%.1f %% of them hold a map-cloud point, %.1f %% of band points inside the grid"
              % (len(maps), len(grids), len(depths), g.shape[1], g.shape[0], occ.sum(),
                 100 * hit[occ].mean(), 100 * inside.mean()))
        # the occupied cells without a point are closed wall gaps (grid_max_gap): each lies in a
        # gap between cells that hold points, at most half a gap from one of them
        from scipy.ndimage import distance_transform_edt
        to_hit = distance_transform_edt(~hit) * res
        assert hit[occ].mean() > 0.85
        assert to_hit[occ].max() <= fusion["grid_max_gap"] / 2 + res, (
            np.sort(to_hit[occ & ~hit]))
        # ... and every band point of that cloud (what move_base's obstacle layer marks) is in an
        # occupied cell of the grid (the static layer): the two layers agree
        assert inside.all() and (g[rc[:, 0], rc[:, 1]] == 100).all(), (
            "%d of %d band points of /mdr/map/points outside the grid's occupied cells"
            % ((~inside).sum() + (g[rc[inside, 0], rc[inside, 1]] != 100).sum(), len(band)))
    finally:
        for s in subs:
            s.unregister()
        launch.stop()
