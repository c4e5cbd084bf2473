"""The paper's metrics: ATE/RPE (reproducing evo's and kitti-odom-eval's published figures), map
accuracy/completeness, disparity/depth errors (OpenCV SGBM on Middlebury) and ``mdr eval``."""
from __future__ import annotations

import json
import os
import subprocess

import numpy as np
import pytest

from conftest import shared_data
from mdr_slam.eval import (ate, depth_error_metrics, depth_metrics, load_middlebury, map_metrics,
                           read_for_eval, rpe)
from mdr_slam.geometry import make_T
from mdr_slam.io.pointcloud import points_cloud, write_cloud
from mdr_slam.io.trajectory import Trajectory, write_tum


def _evo(name):
    return os.path.join(shared_data("trajectories", "evo"), name)


def _koe(*parts):
    return os.path.join(shared_data("trajectories", "kitti_odom_eval"), *parts)


# ------------------------------------------------------------------------------- trajectories
@pytest.mark.parametrize("est,stats", [
    ("KITTI_00_ORB.txt", {"rmse": 1.3034497, "mean": 1.1569971, "median": 1.0656248,
                          "max": 3.5879491, "std": 0.6002823}),
    ("KITTI_00_SPTAM.txt", {"rmse": 3.7384879, "mean": 3.4909766, "median": 3.6425846,
                            "max": 7.7689774}),
])
def test_ate_reproduces_evo_kitti00(est, stats):
    res = ate(read_for_eval(_evo(est)), read_for_eval(_evo("KITTI_00_gt.txt")), "se3")
    print("%s: ATE rmse %.7f m" % (est, res.stats["rmse"]))
    for k, v in stats.items():
        assert abs(res.stats[k] - v) < 1e-4, (k, res.stats[k], v)
    assert res.stats["n"] == 4541 and res.stats["alignment"] == "se3"
    assert len(res.errors) == 4541 and res.est_xyz.shape == res.gt_xyz.shape == (4541, 3)


@pytest.mark.parametrize("seq,expected", [("09", 8.38661922878607), ("10", 6.630158107185018)])
def test_ate_sim3_reproduces_kitti_odom_eval(seq, expected):
    est = read_for_eval(_koe("result", "example_0", seq + ".txt"))       # frame index + 12 values
    gt = read_for_eval(_koe("dataset", "kitti_odom", "gt_poses", seq + ".txt"))
    res = ate(est, gt, "sim3")
    print("kitti-odom-eval example_0 %s: ATE (sim3) %.10f m, scale %.6f"
          % (seq, res.stats["rmse"], res.stats["scale"]))
    assert abs(res.stats["rmse"] - expected) < 1e-4
    assert res.stats["n"] == len(est)     # associated by frame index, not line number


def test_rpe_reproduces_evo_kitti00():
    res = rpe(read_for_eval(_evo("KITTI_00_ORB.txt")), read_for_eval(_evo("KITTI_00_gt.txt")),
              delta=10.0, unit="m", align_mode="none")
    print("KITTI 00 ORB RPE(10 m) rmse %.7f m" % res.stats["rmse"])
    assert abs(res.stats["rmse"] - 0.2262613) < 1e-4


def _synthetic(n=200, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    pos = np.c_[np.cos(t / 3) * 5, np.sin(t / 3) * 5, 0.1 * t]
    from scipy.spatial.transform import Rotation
    q = Rotation.from_euler("z", t / 3).as_quat()
    return Trajectory(t, pos, q), rng


def test_ate_alignment_modes_on_synthetic_trajectories():
    gt, rng = _synthetic()
    T = make_T(np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]), [3, -2, 1])
    moved = Trajectory.from_matrices(gt.stamps + 0.002, T @ gt.matrices())
    assert ate(moved, gt, "se3").stats["rmse"] < 1e-9       # a rigid offset is aligned away
    assert ate(moved, gt, "none").stats["rmse"] > 1.0
    scaled = Trajectory(moved.stamps, 0.5 * moved.positions, moved.quats)
    assert ate(scaled, gt, "se3").stats["rmse"] > 0.5
    r = ate(scaled, gt, "sim3")
    assert r.stats["rmse"] < 1e-9 and r.stats["scale"] == pytest.approx(2.0)
    noisy = Trajectory(gt.stamps, gt.positions + rng.normal(0, 0.01, gt.positions.shape), gt.quats)
    assert 0.012 < ate(noisy, gt, "se3").stats["rmse"] < 0.022   # sqrt(3) * 1 cm
    # association: stamps further apart than max_diff do not match
    with pytest.raises(ValueError):
        ate(Trajectory(gt.stamps + 0.05, gt.positions, gt.quats), gt, "se3", max_diff=0.01)


def test_mdr_eval_ate_cli_prints_json_and_plots(tmp_path):
    png = str(tmp_path / "ate.png")
    r = subprocess.run(["mdr", "eval", "ate", _evo("KITTI_00_ORB.txt"), _evo("KITTI_00_gt.txt"),
                        "--format", "kitti", "--align", "se3", "--plot", png, "--plane", "xz"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    for k in ("rmse", "mean", "median", "std", "min", "max", "n", "path_length", "alignment"):
        assert k in s
    assert abs(s["rmse"] - 1.3034497) < 1e-4 and s["alignment"] == "se3"
    assert os.path.getsize(png) > 20000
    gt, _ = _synthetic()
    write_tum(str(tmp_path / "a.txt"), gt)
    r = subprocess.run(["mdr", "eval", "rpe", str(tmp_path / "a.txt"), str(tmp_path / "a.txt"),
                        "--delta", "1", "--delta-unit", "m"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["rmse"] < 1e-9
    r = subprocess.run(["mdr", "eval", "ate", str(tmp_path / "nope.txt"), str(tmp_path / "a.txt")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "mdr eval ate" in r.stderr


def test_mdr_eval_ate_align_as_scores_a_run_in_an_earlier_runs_map_frame(tmp_path):
    """A run localized in a saved map is scored in that map's frame: aligned with the transform
    that aligns the map's own run to the truth, so an offset of its own is not aligned away."""
    from scipy.spatial.transform import Rotation
    gt, _ = _synthetic()
    T = make_T(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [1.0, -2.0, 0.5])
    moved = [T @ P for P in gt.matrices()]
    off = make_T(np.eye(3), [0.05, 0.0, 0.0])        # the second run 5 cm off in the map frame
    write_tum(str(tmp_path / "gt.txt"), gt)
    write_tum(str(tmp_path / "run1.txt"), Trajectory.from_matrices(gt.stamps, moved))
    write_tum(str(tmp_path / "run2.txt"), Trajectory.from_matrices(gt.stamps, [off @ P for P in moved]))

    def rmse(*extra):
        r = subprocess.run(["mdr", "eval", "ate", str(tmp_path / "run2.txt"), str(tmp_path / "gt.txt"),
                            *extra], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout)["rmse"]
    assert rmse() < 1e-6                                  # its own alignment hides the offset
    assert abs(rmse("--align-as", str(tmp_path / "run1.txt")) - 0.05) < 1e-6


# ------------------------------------------------------------------------------------- maps
def _cloud(step=0.01):
    """A 2 m x 1 m wall sampled every ``step`` (a surface, like a fused map), labelled by x."""
    u, v = np.meshgrid(np.arange(0, 2, step), np.arange(0, 1, step))
    P = np.c_[u.ravel(), v.ravel(), np.full(u.size, 3.0)]
    labels = (1 + (P[:, 0] > 0.7) + (P[:, 0] > 1.4)).astype(np.uint8)
    return P, labels


def test_map_metrics_self_and_shifted():
    P, labels = _cloud()
    m = map_metrics(P, P)
    assert m["accuracy_rmse"] == 0 and m["completeness"] == 1.0 and m["fscore"] == 1.0
    assert set(m["at_threshold"]) == {"0.01", "0.02", "0.05", "0.1"}
    shifted = P + [0, 0, 0.01]                 # 1 cm along the wall's normal
    m = map_metrics(shifted, P, gt_labels=labels)
    print("shifted 1 cm: accuracy RMSE %.5f m, completeness %.3f" % (m["accuracy_rmse"],
                                                                     m["completeness"]))
    assert m["accuracy_rmse"] == pytest.approx(0.01, abs=1e-9)
    assert m["completeness"] > 0.99 and m["at_threshold"]["0.02"]["accuracy"] == 1.0
    assert set(m["per_label"]) == {"low_texture", "textured", "specular"}
    assert sum(b["n_estimate"] for b in m["per_label"].values()) == len(P)
    assert sum(b["n_ground_truth"] for b in m["per_label"].values()) == len(P)


def test_map_metrics_labels_separate_a_bad_region():
    P, labels = _cloud()
    est = P.copy()
    est[labels == 1] += [0, 0, 0.08]            # the low-texture region is 8 cm off
    m = map_metrics(est, P, threshold=0.05, gt_labels=labels)
    lt, tx = m["per_label"]["low_texture"], m["per_label"]["textured"]
    # estimated points take the label of their nearest GT point, so a few displaced low-texture
    # points near the border count as textured: the textured figure is small, not zero
    assert lt["accuracy_rmse"] > 0.03 and tx["accuracy_rmse"] < lt["accuracy_rmse"] / 4
    assert lt["completeness"] < 0.2 and tx["completeness"] == 1.0
    # half-empty estimate: completeness drops, accuracy does not
    m = map_metrics(P[P[:, 0] < 0.995], P)
    assert m["accuracy_rmse"] == 0 and 0.45 < m["completeness"] < 0.55


def test_mdr_eval_map_cli(tmp_path):
    P, labels = _cloud(0.02)
    write_cloud(str(tmp_path / "gt.ply"), points_cloud(P.astype(np.float32), surface=labels))
    write_cloud(str(tmp_path / "est.ply"), points_cloud((P + [0, 0, 0.01]).astype(np.float32)))
    png = str(tmp_path / "map.png")
    r = subprocess.run(["mdr", "eval", "map", str(tmp_path / "est.ply"), str(tmp_path / "gt.ply"),
                        "--threshold", "0.05", "--plot", png], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert abs(s["accuracy_rmse"] - 0.01) < 1e-5 and "per_label" in s and os.path.exists(png)


# ------------------------------------------------------------------------------------ depth
def test_depth_metrics_synthetic():
    gt = np.full((10, 10), 20.0)
    gt[0] = 0                                    # unknown ground truth
    est = gt.copy()
    est[1, :5] += 1.5                            # > 1 px, < 2 px
    est[2, :5] += 3.0                            # > 2 px
    est[3] = np.nan                              # no estimate
    m = depth_metrics(est, gt)
    assert m["n_valid"] == 90 and m["n_estimated"] == 80
    assert m["density"] == pytest.approx(80 / 90)
    assert m["bad2"] == pytest.approx(5 / 80) and m["bad1"] == pytest.approx(10 / 80)
    assert m["bad2_all"] == pytest.approx(15 / 90)
    assert m["mae"] == pytest.approx((5 * 1.5 + 5 * 3.0) / 80)
    dm = depth_error_metrics(np.where(np.isfinite(est), 2.0, np.nan) + (est > 21) * 0.1,
                             np.where(gt > 0, 2.0, 0))
    assert dm["bad"] == pytest.approx(10 / 80) and dm["rmse"] == pytest.approx(np.sqrt(10 / 80) * 0.1)


MIDDLEBURY_SGBM = {"cones": 5.3, "teddy": 6.3, "tsukuba": 4.0, "venus": 1.5}


def sgbm(left, right):
    """The OpenCV SGBM settings that give the README's Middlebury figures (block 5, HH mode,
    64 disparities, P1 = 8*5^2, P2 = 32*5^2, uniqueness 10, speckle 100/2, LR check 1 px)."""
    import cv2
    s = cv2.StereoSGBM_create(minDisparity=0, numDisparities=64, blockSize=5, P1=8 * 25, P2=32 * 25,
                              disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100,
                              speckleRange=2, mode=cv2.STEREO_SGBM_MODE_HH)
    return s.compute(left, right).astype(np.float32) / 16.0


@pytest.mark.parametrize("name", sorted(MIDDLEBURY_SGBM))
def test_middlebury_sgbm_bad_pixel_rates(name):
    shared_data("middlebury", name)
    left, right, gt = load_middlebury(name)
    assert left.shape == right.shape == gt.shape and left.dtype == np.uint8
    assert gt.dtype == np.float32 and 0 < gt.max() < 64
    m = depth_metrics(sgbm(left, right), gt)
    print("Middlebury %s SGBM: bad>2px %.2f %% (README %.1f %%), bad>1px %.2f %%, MAE %.3f px, "
          "density %.3f" % (name, 100 * m["bad2"], MIDDLEBURY_SGBM[name], 100 * m["bad1"], m["mae"],
                            m["density"]))
    assert abs(100 * m["bad2"] - MIDDLEBURY_SGBM[name]) < 1.0
    assert m["bad1"] >= m["bad2"] and m["density"] > 0.75


def test_mdr_eval_depth_cli(tmp_path):
    folder = shared_data("middlebury", "cones")
    left, right, gt = load_middlebury(folder)
    np.save(str(tmp_path / "cones.npy"), sgbm(left, right))
    r = subprocess.run(["mdr", "eval", "depth", str(tmp_path / "cones.npy"), folder],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert abs(100 * s["mean"]["bad2"] - 5.3) < 1.0 and s["n_frames"] == 1


def test_map_alignment_short_path_uses_the_first_pose():
    """A short straight path leaves Umeyama's rotation free: the first pose pair fixes the map."""
    from mdr_slam.eval import map_alignment
    from mdr_slam.io import Trajectory
    from scipy.spatial.transform import Rotation
    T_align = np.eye(4)
    T_align[:3, :3] = Rotation.from_euler("zyx", [70, -20, 10], degrees=True).as_matrix()
    T_align[:3, 3] = [5.0, 3.0, 1.3]
    est = [np.eye(4) for _ in range(10)]
    for i, T in enumerate(est):
        T[0, 3] = 0.01 * i                      # 9 cm along x: positions alone cannot fix a rotation
    gt = [T_align @ T for T in est]
    stamps = np.arange(10) * 0.1
    al = map_alignment(Trajectory.from_matrices(stamps, est), Trajectory.from_matrices(stamps, gt))
    assert al["method"] == "first_pose"
    assert np.allclose(al["rotation"], T_align[:3, :3], atol=1e-9)
    assert np.allclose(al["translation"], T_align[:3, 3], atol=1e-9)
    # a path spread over a room uses Umeyama over all poses
    est2 = []
    for i in range(40):
        T = np.eye(4)
        T[:3, 3] = [np.cos(i / 6.0), np.sin(i / 6.0), 0.0]
        est2.append(T)
    gt2 = [T_align @ T for T in est2]
    stamps2 = np.arange(40) * 0.1
    al2 = map_alignment(Trajectory.from_matrices(stamps2, est2), Trajectory.from_matrices(stamps2, gt2))
    assert al2["method"] == "umeyama_se3"
    assert np.allclose(al2["rotation"], T_align[:3, :3], atol=1e-6)
