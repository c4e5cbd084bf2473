"""The navigation benchmark's scoring (mdr_slam.eval.navigation), without ROS."""
from __future__ import annotations

import numpy as np
import pytest

from mdr_slam.eval.navigation import (TrueGrid, clearance_along, localization_errors, path_length,
                                      plan_crosses_occupied, sample_goals, summarise, true_grid)


def test_true_grid_holds_the_walls_and_furniture_in_the_band_only():
    from mdr_slam.sim import make_scene
    sc = make_scene("office", seed=0)
    tg = true_grid(sc, resolution=0.05)
    # the office's walls (x = 0, 8; y = 0, 6) are occupied, its middle is free
    for xy in ((0.0, 3.0), (8.0, 3.0), (4.0, 0.0), (4.0, 6.0)):
        assert tg.occ[tuple(v[0] for v in tg.cells([xy]))], xy
    assert not tg.occ[tuple(v[0] for v in tg.cells([(4.0, 3.0)]))]
    # the desk (0.74 m high) is in the 0.1-1.5 m band; the floor mat (4 mm) is not
    assert tg.occ[tuple(v[0] for v in tg.cells([(6.6, 0.75)]))]
    assert not tg.occ[tuple(v[0] for v in tg.cells([(3.5, 2.5)]))]
    # clearance is the distance to the nearest obstacle: from the room's centre, the corner of
    # the drawers at (4.6, 5.3), 2.38 m (the floor mat under the centre is flat)
    assert tg.clearance([(4.0, 3.0)])[0] == pytest.approx(np.hypot(0.6, 2.3), abs=0.1)


def _box_world():
    """A 6 x 4 m room with a 2 m wall segment in its middle (x = 3, y in [1, 4])."""
    res = 0.05
    occ = np.zeros((int(4.0 / res) + 20, int(6.0 / res) + 20), bool)
    origin = (-0.5, -0.5)
    tg0 = TrueGrid(occ, origin, res)
    r, c = tg0.cells(np.array([[x, y] for x in np.arange(0, 6.0, 0.02) for y in (0.0, 4.0)] +
                              [[x, y] for y in np.arange(0, 4.0, 0.02) for x in (0.0, 6.0)] +
                              [[3.0, y] for y in np.arange(1.0, 4.0, 0.02)]))
    occ[r, c] = True
    return TrueGrid(occ, origin, res)


def test_goals_are_free_reachable_chained_and_some_hidden():
    tg = _box_world()
    goals = sample_goals(tg, (1.0, 2.0), 10, seed=3, robot_radius=0.2)
    again = sample_goals(tg, (1.0, 2.0), 10, seed=3, robot_radius=0.2)
    other = sample_goals(tg, (1.0, 2.0), 10, seed=4, robot_radius=0.2)
    assert goals == again and goals != other
    prev = np.array([1.0, 2.0])
    for g in goals:
        xy = np.array(g["xy"])
        assert tg.clearance([xy])[0] >= 0.45 - 1e-9
        assert np.linalg.norm(xy - prev) >= 2.0
        assert g["from"] == pytest.approx(prev.tolist())
        assert g["shortest_m"] >= np.linalg.norm(xy - prev) - 0.1   # never shorter than the line
        prev = xy
    hidden = [g["hidden"] for g in goals]
    assert 0 < sum(hidden) < len(goals), hidden
    # a hidden goal's shortest path goes round the wall: longer than the straight line
    for g in goals:
        if g["hidden"]:
            assert g["shortest_m"] > np.linalg.norm(np.subtract(g["xy"], g["from"])) + 0.05


def test_plan_through_occupied_cells_and_clearance():
    grid = np.zeros((40, 40), np.int8)
    grid[:, 20] = 100                          # a wall at x = 1.0 .. 1.05
    grid[5:10, 5:10] = -1                      # unknown: may be crossed
    origin, res = (0.0, 0.0), 0.05
    across = np.array([[0.5, 1.0], [1.5, 1.0]])
    along = np.array([[0.5, 0.2], [0.5, 1.8]])
    assert plan_crosses_occupied(across, grid, origin, res) == 1
    assert plan_crosses_occupied(along, grid, origin, res) == 0
    assert plan_crosses_occupied(np.array([[0.3, 0.3], [0.45, 0.45]]), grid, origin, res) == 0
    assert plan_crosses_occupied(np.array([[-5.0, 1.0], [-4.0, 1.0]]), grid, origin, res) == 0
    tg = TrueGrid(grid == 100, origin, res)
    assert clearance_along(tg, along, 0.2) == pytest.approx(1.0 - 0.5 - 0.2 + 0.025, abs=0.03)
    assert path_length(along) == pytest.approx(1.6)


def test_localization_error_interpolates_the_truth():
    gt_t = np.arange(0.0, 10.0, 0.1)
    gt_xy = np.stack([gt_t * 0.3, np.zeros_like(gt_t)], 1)
    est_t = np.array([0.05, 2.55, 5.0, 20.0])
    est_xy = np.array([[0.015, 0.0], [0.765, 0.04], [1.5, 0.0], [6.0, 0.0]])
    e = localization_errors(est_t, est_xy, gt_t, gt_xy)
    assert len(e) == 3                          # the estimate at 20 s has no truth near it
    np.testing.assert_allclose(e, [0.0, 0.04, 0.0], atol=1e-9)


def test_summary_counts_misses_and_slow_goals():
    recs = [{"reached": True, "time_s": 10.0, "shortest_m": 2.0, "collisions": 0,
             "plans_through_occupied": 0, "max_localization_error_m": 0.05},
            {"reached": True, "time_s": 30.0, "shortest_m": 2.0, "collisions": 1,
             "plans_through_occupied": 2, "max_localization_error_m": 0.2},
            {"reached": False, "time_s": 60.0, "shortest_m": 2.0, "collisions": 0,
             "plans_through_occupied": 0, "max_localization_error_m": None}]
    s = summarise(recs, max_speed=0.4)
    assert s["reached"] == 2 and s["collisions"] == 1 and s["plans_through_occupied"] == 2
    assert s["max_localization_error_m"] == 0.2 and s["slower_than_2x_shortest"] == [1]


def test_map_alignment_takes_out_a_rotated_map():
    """A map rotated by 6 degrees about its start (an early heading error) and shifted: the
    alignment lays it back on the scene (what is left is the pose's error against its own map);
    a trajectory too short to fix a rotation gives the identity."""
    from mdr_slam.eval.navigation import map_alignment
    rng = np.random.default_rng(0)
    true = np.c_[np.linspace(0, 6, 60), 0.5 * np.sin(np.linspace(0, 3, 60))] + [2.0, 3.0]
    a = np.radians(6.0)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    est = (true - true[0]) @ R.T + true[0] + [0.1, -0.05] + rng.normal(0, 0.01, true.shape)
    raw = np.linalg.norm(est - true, axis=1)
    A = map_alignment(est, true)
    left = np.linalg.norm(est @ A[:2, :2].T + A[:2, 2] - true, axis=1)
    assert raw.max() > 0.5 and left.max() < 0.05, (raw.max(), left.max())
    assert np.degrees(np.arctan2(A[1, 0], A[0, 0])) == pytest.approx(-6.0, abs=0.5)
    assert np.array_equal(map_alignment(est[:5], true[:5]), np.eye(3))   # 0.4 m: no rotation
    assert np.array_equal(map_alignment([], []), np.eye(3))


def test_keyframe_trajectory_error_keeps_a_bent_map_and_drops_a_rotated_one():
    """Keyframes of an L-shaped drive: the whole map rotated and shifted (one heading error from
    the start) is aligned away; a map whose second leg a bad loop correction turned by 10 degrees
    about the corner keeps that bend as error; keyframes without a true pose nearby are left out."""
    from mdr_slam.eval.navigation import keyframe_trajectory_error
    gt_t = np.arange(0.0, 40.0, 0.02)
    leg = np.clip(gt_t / 20.0, 0, 1)[:, None] * [10.0, 0.0] + \
        np.clip(gt_t / 20.0 - 1.0, 0, 1)[:, None] * [0.0, 8.0]
    gt_xy = leg + [1.0, 2.0]
    kf_t = np.arange(0.5, 40.0, 1.0)
    truth = np.c_[np.interp(kf_t, gt_t, gt_xy[:, 0]), np.interp(kf_t, gt_t, gt_xy[:, 1])]
    a = np.radians(5.0)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    rotated = truth @ R.T + [0.3, -0.2]
    got = keyframe_trajectory_error(kf_t, rotated, gt_t, gt_xy)
    assert got["keyframes"] == len(kf_t) and got["rmse_m"] < 1e-6
    b = np.radians(10.0)
    Rb = np.array([[np.cos(b), -np.sin(b)], [np.sin(b), np.cos(b)]])
    corner = truth[np.argmin(np.abs(kf_t - 20.0))]
    bent = np.where((kf_t > 20.0)[:, None], (truth - corner) @ Rb.T + corner, truth)
    got = keyframe_trajectory_error(kf_t, bent, gt_t, gt_xy)
    assert 0.3 < got["rmse_m"] < 1.4 and got["max_m"] > 0.5, got
    late = np.r_[kf_t, [100.0, 200.0]]                        # no truth near these stamps
    got = keyframe_trajectory_error(late, np.r_[truth, [[0, 0], [5, 5]]], gt_t, gt_xy)
    assert got["keyframes"] == len(kf_t) and got["rmse_m"] < 1e-6
    assert keyframe_trajectory_error(kf_t[:2], truth[:2], gt_t, gt_xy) is None
