"""Measures for weak-texture walls: map figures within range of the camera path and per label,
the occupancy grid against the true one (one cell of tolerance, route cells), and the SGBM + TSDF
peer map."""
from __future__ import annotations

import json
import os
import subprocess

import numpy as np
import pytest

from mdr_slam.eval import (cells_near, grid_metrics, map_metrics, obstacle_cells, route_cells,
                           within_range)
from mdr_slam.io.pointcloud import points_cloud, write_cloud
from mdr_slam.io.trajectory import Trajectory, write_tum


def _wall(x0, x1, y=3.0, step=0.02, z1=1.0):
    """A vertical wall y = const, x in [x0, x1), z in [0, z1), sampled every ``step``."""
    x, z = np.meshgrid(np.arange(x0, x1, step), np.arange(0.0, z1, step))
    return np.c_[x.ravel(), np.full(x.size, y), z.ravel()]


def _path(x0=0.0, x1=2.0, n=41):
    """Camera positions along x at y = 0, 0.5 m high."""
    x = np.linspace(x0, x1, n)
    return np.c_[x, np.zeros(n), np.full(n, 0.5)]


# --------------------------------------------------------------------------- within range
def test_within_range_keeps_what_the_rig_can_see():
    gt = _wall(-10, 12)
    path = _path()
    mask = within_range(gt, path, 4.0)
    # exact: distance to the nearest sampled position
    d = np.min(np.linalg.norm(gt[:, None, :] - path[None], axis=2), axis=1)
    np.testing.assert_array_equal(mask, d <= 4.0)
    assert 0 < mask.sum() < len(gt) / 2
    assert not mask[gt[:, 0] < -3].any() and not mask[gt[:, 0] > 5].any()
    # a Trajectory works as well as its positions
    traj = Trajectory(np.arange(len(path)), path, np.tile([0, 0, 0, 1.0], (len(path), 1)))
    np.testing.assert_array_equal(within_range(gt, traj, 4.0), mask)
    with pytest.raises(ValueError):
        within_range(gt, path, 0.0)
    with pytest.raises(ValueError):
        within_range(gt, np.zeros((0, 3)), 4.0)


def test_map_metrics_in_range_ignores_what_the_rig_could_not_see():
    gt = _wall(-10, 12)
    near = gt[(gt[:, 0] >= -3) & (gt[:, 0] < 5)]     # every true point within 4 m of the path
    far_junk = _wall(-5, 5, y=20.0, step=0.05)        # wrong points, all beyond range
    est = np.vstack([near, far_junk])
    m = map_metrics(est, gt, threshold=0.05, path=_path(), max_range=4.0)
    # the whole-map figures stay as they were: most of the wall is missing, much is junk
    # (plus the true points within 5 cm of the cut: two columns on either side)
    assert m["completeness"] == pytest.approx((len(near) + 4 * 50) / len(gt), abs=1e-9)
    assert m["accuracy"] == pytest.approx(len(near) / len(est), abs=1e-9)
    r = m["in_range"]
    assert r["max_range_m"] == 4.0
    assert r["n_ground_truth"] == int(within_range(gt, _path(), 4.0).sum())
    assert r["n_estimate"] == int(within_range(est, _path(), 4.0).sum()) < len(near)
    assert r["completeness"] == 1.0 and r["accuracy"] == 1.0 and r["fscore"] == 1.0
    # without the path there is no in_range block
    assert "in_range" not in map_metrics(est, gt)


def test_per_label_fscore_in_range():
    gt = _wall(0, 2, step=0.02)
    labels = np.where(gt[:, 0] < 1.0, 1, 2).astype(np.uint8)
    lt = gt[labels == 1]
    tx = gt[labels == 2]
    # low texture: the lower half of the wall only, exact -> precision 1, completeness ~0.5;
    # textured: all of it, plus as many points 10 cm in front of it -> precision 0.5, completeness 1
    est = np.vstack([lt[lt[:, 2] < 0.49], tx, tx - [0, 0.10, 0]])
    m = map_metrics(est, gt, threshold=0.05, gt_labels=labels, path=_path(0, 2), max_range=10.0)
    per = m["in_range"]["per_label"]
    assert set(per) == {"low_texture", "textured"}
    c_lt = per["low_texture"]["completeness"]
    assert 0.5 < c_lt < 0.6 and per["low_texture"]["accuracy"] == 1.0   # + points near the cuts
    assert per["low_texture"]["fscore"] == pytest.approx(2 * c_lt / (1 + c_lt), abs=1e-9)
    assert per["textured"]["completeness"] == 1.0
    assert per["textured"]["accuracy"] == pytest.approx(0.5, abs=1e-9)
    assert per["textured"]["fscore"] == pytest.approx(2 / 3, abs=1e-9)
    # with everything in range the block agrees with the whole-map per-label figures
    assert per["textured"]["fscore"] == pytest.approx(m["per_label"]["textured"]["fscore"])


# --------------------------------------------------------------------------------- the grid
RES = 0.05


def _grid_wall(row=10, c0=0, c1=20, heights=(0.3, 0.8)):
    """Obstacle points at the centres of cells (c, row), c in [c0, c1), at the given heights."""
    c = np.arange(c0, c1)
    pts = [np.c_[(c + 0.5) * RES, np.full(len(c), (row + 0.5) * RES), np.full(len(c), h)]
           for h in heights]
    return np.vstack(pts)


def test_obstacle_cells_are_the_fusion_grids_cells():
    wall = _grid_wall()
    floor = np.c_[np.random.default_rng(0).uniform(0, 1, (200, 2)), np.zeros(200)]
    cells = obstacle_cells(np.vstack([wall, floor]), RES)
    assert sorted(map(tuple, cells)) == [(c, 10) for c in range(20)]
    # a negative origin stays on the same lattice
    cells = obstacle_cells(wall - [1.0, 2.0, 0.0], RES)
    assert sorted(map(tuple, cells)) == [(c - 20, 10 - 40) for c in range(20)]


def test_grid_recall_precision_one_cell_tolerance():
    gt = _grid_wall()
    for shift, expect in ((0, 1.0), (1, 1.0), (2, 0.0), (-2, 0.0)):
        est = gt + [0, shift * RES, 0]
        g = grid_metrics(est, gt, resolution=RES)
        assert g["recall"] == expect and g["precision"] == expect, (shift, g)
    # a diagonal one-cell shift counts too (Chebyshev distance)
    g = grid_metrics(gt + [RES, RES, 0], gt, resolution=RES)
    assert g["recall"] == 1.0 and g["precision"] == 1.0
    # half the wall: recall about half (one more cell for the tolerance), precision 1
    g = grid_metrics(_grid_wall(c0=0, c1=10), gt, resolution=RES)
    assert g["recall"] == pytest.approx(11 / 20) and g["precision"] == 1.0
    assert g["n_true_cells"] == 20 and g["n_est_cells"] == 10
    # a phantom far from any wall costs precision only
    phantom = np.array([[0.525, 1.525, 0.5]])
    g = grid_metrics(np.vstack([gt, phantom]), gt, resolution=RES)
    assert g["recall"] == 1.0 and g["precision"] == pytest.approx(20 / 21)
    # below the obstacle band (floor) or above it: no obstacle
    g = grid_metrics(np.vstack([gt, phantom * [1, 1, 0.1], phantom + [0, 0, 2.0]]), gt,
                     resolution=RES)
    assert g["precision"] == 1.0
    assert cells_near(np.zeros((0, 2)), np.ones((3, 2))).shape == (0,)


def test_grid_confidence_and_labels():
    gt = _grid_wall()
    labels = np.where(gt[:, 0] < 0.5, 1, 2)
    est = np.vstack([gt[gt[:, 0] < 0.5], gt[gt[:, 0] >= 0.5]])
    conf = np.r_[np.full(int((gt[:, 0] < 0.5).sum()), 5), np.full(int((gt[:, 0] >= 0.5).sum()), 1)]
    g = grid_metrics(est, gt, labels, est_confidence=conf, min_confidence=3, resolution=RES)
    # the textured half's points are too young for the grid: only the low-texture half is found
    assert g["per_label"]["low_texture"]["recall"] == 1.0
    assert g["per_label"]["textured"]["recall"] == pytest.approx(1 / 10)   # tolerance cell
    assert g["min_confidence"] == 3 and g["n_est_points"] == int((conf >= 3).sum())
    g = grid_metrics(est, gt, labels, est_confidence=conf, min_confidence=0, resolution=RES)
    assert g["recall"] == 1.0
    with pytest.raises(ValueError):
        grid_metrics(est, gt, est_confidence=conf[:5], resolution=RES)
    with pytest.raises(ValueError):   # no true obstacle at all
        grid_metrics(est, gt * [1, 1, 0], resolution=RES)


def test_route_cells():
    # two positions 1 m apart: every cell in between, none skipped
    path = np.array([[0.525, 0.0, 1.0], [0.525, 1.0, 1.0]])
    cells = route_cells(path, RES)
    assert sorted(map(tuple, cells)) == [(10, j) for j in range(21)]
    # up axis -y: the grid spans (x, z), so moving along y stays in one cell
    vertical = np.array([[0.525, 0.0, 0.525], [0.525, -1.0, 0.525]])
    assert route_cells(vertical, RES, "-y").shape == (1, 2)
    # the camera crosses where the estimate has an obstacle: one occupied route cell; the truth
    # has none on the route
    gt = _grid_wall(row=10, c0=0, c1=5)          # a wall at x < 0.25 m; the path is at x 0.525
    est = np.vstack([gt, [[0.525, 0.525, 0.6]]])   # a phantom on the route
    g = grid_metrics(est, gt, path=path, resolution=RES, max_range=4.0)
    assert g["route"] == {"n_cells": 21, "occupied_est": 1, "occupied_true": 0}
    assert g["in_range"]["recall"] == 1.0
    g = grid_metrics(gt, gt, path=path, resolution=RES)
    assert g["route"]["occupied_est"] == 0 and "in_range" not in g


def test_grid_precision_within_range_of_the_path():
    # a wall along x at y = 0.525 m; the camera path runs along it, 0.5 m high, x in [0, 2] m
    gt = _grid_wall(row=10, c0=-200, c1=200)           # x in [-10, 10) m
    path = _path(0.0, 2.0)
    far = np.array([[8.025, 3.025, 0.5]])              # a phantom ~6.8 m from the path
    near = np.array([[1.025, 2.025, 0.5]])             # a phantom 1.5 m from it
    est = np.vstack([gt[np.abs(gt[:, 0] - 1.0) < 5.0], far])
    g = grid_metrics(est, gt, path=path, resolution=RES, max_range=4.0)
    assert g["precision"] < 1.0                        # the far phantom counts in the whole grid
    rng = g["in_range"]
    assert rng["precision"] == 1.0 and rng["recall"] == 1.0
    # the estimated cells within range: those of the wall's points within 4 m of the path
    in4 = within_range(est, path, 4.0)
    assert rng["n_est_cells"] == len(obstacle_cells(est[in4], RES)) < g["n_est_cells"]
    g = grid_metrics(np.vstack([est, near]), gt, path=path, resolution=RES, max_range=4.0)
    assert g["in_range"]["precision"] == pytest.approx(1 - 1 / (rng["n_est_cells"] + 1))
    # no estimated point within range: no precision there (None), recall 0
    g = grid_metrics(far, gt, path=path, resolution=RES, max_range=4.0)
    assert g["in_range"]["n_est_cells"] == 0 and g["in_range"]["precision"] is None
    assert g["in_range"]["recall"] == 0.0


# ---------------------------------------------------------------------------------- the CLI
def test_mdr_eval_map_trajectory_and_grid_cli(tmp_path):
    gt = _wall(-10, 12, step=0.05)
    labels = np.where(gt[:, 0] < 1.0, 1, 2).astype(np.uint8)
    near = (gt[:, 0] >= -3) & (gt[:, 0] < 5)
    write_cloud(str(tmp_path / "gt.ply"), points_cloud(gt.astype(np.float32), surface=labels))
    est = gt[near]
    conf = np.full(len(est), 5, np.int32)
    conf[est[:, 0] >= 1.0] = 1                  # the textured part is not confident
    os.makedirs(str(tmp_path / "run"))
    write_cloud(str(tmp_path / "run" / "map.ply"),
                points_cloud(est.astype(np.float32), confidence=conf))
    path = _path()
    write_tum(str(tmp_path / "gt.tum"),
              Trajectory(np.arange(len(path)) * 0.1, path, np.tile([0, 0, 0, 1.0], (len(path), 1))))
    base = ["mdr", "eval"]
    r = subprocess.run(base + ["map", str(tmp_path / "run" / "map.ply"), str(tmp_path / "gt.ply"),
                               "--trajectory", str(tmp_path / "gt.tum"), "--max-range", "4"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["completeness"] < 0.5 and s["in_range"]["completeness"] == 1.0
    assert s["in_range"]["per_label"]["low_texture"]["fscore"] == 1.0

    def grid(*extra):
        r = subprocess.run(base + ["grid", str(tmp_path / "run" / "map.ply"),
                                   str(tmp_path / "gt.ply"), "--trajectory",
                                   str(tmp_path / "gt.tum")] + list(extra),
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout)
    g = grid()               # grid_min_confidence 3: only the low-texture part marks cells
    assert g["min_confidence"] == 3 and g["precision"] == 1.0
    rng = g["in_range"]["per_label"]      # the estimate covers what is within range
    assert rng["low_texture"]["recall"] > 0.9 > 0.2 > rng["textured"]["recall"]
    assert g["per_label"]["low_texture"]["recall"] < 0.5   # the whole wall: 11 m, 4 m mapped
    assert g["route"]["occupied_est"] == 0 and g["in_range"]["max_range_m"] == 4.0
    assert grid("--min-confidence", "0")["in_range"]["per_label"]["textured"]["recall"] > 0.9
    # a plain map written by `mdr run --confidence off`: all its points mark cells
    with open(str(tmp_path / "run" / "summary.json"), "w") as f:
        json.dump({"confidence": False}, f)
    g0 = grid()
    assert g0["min_confidence"] == 0 and g0["n_est_cells"] > g["n_est_cells"]
    r = subprocess.run(base + ["grid", str(tmp_path / "missing.ply"), str(tmp_path / "gt.ply")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "mdr eval grid" in r.stderr


# ------------------------------------------------------------------------------------ the peer
def test_sgbm_tsdf_peer_map_lands_on_the_true_surfaces(tmp_path):
    from mdr_slam.eval import nearest_distances
    from mdr_slam.eval.peer import sgbm_tsdf_map
    from mdr_slam.io import cloud_xyz, read_cloud
    from mdr_slam.sim import generate
    d = str(tmp_path / "sim")
    generate(d, scene="office", duration=0.5, scale=0.25, workers=1)
    out = str(tmp_path / "peer.ply")
    # a quarter-resolution image (188 px wide) has no room for 128 disparities, and a 3 m depth
    # limit keeps the TSDF small: seconds
    s = sgbm_tsdf_map(os.path.join(d, "sequence.bag"), out, max_frames=5, num_disparities=32,
                      max_depth=3.0)
    assert s["frames_in"] == s["frames_posed"] == s["frames_integrated"] == 5
    assert s["timing"]["frame"]["n"] == 5 and s["timing"]["frame"]["median_ms"] > 0
    P = cloud_xyz(read_cloud(out))
    assert len(P) == s["map_points"] > 10000
    dist, _ = nearest_distances(P, cloud_xyz(read_cloud(os.path.join(d, "gt_map.ply"))))
    # one disparity step is ~15 cm of depth at 2 m at this resolution: a loose bound, but a wrong
    # pose convention or unit puts the cloud metres away
    print("peer: %d points, distance to the truth median %.3f m, within 10 cm %.2f"
          % (len(P), np.median(dist), np.mean(dist < 0.1)))
    assert np.median(dist) < 0.15 and np.mean(dist < 0.1) > 0.4
