"""Calibration loaders (EuRoC, Kalibr, camera_info YAML, KITTI) and the EuRoC/KITTI importers."""
from __future__ import annotations

import os
import subprocess

import numpy as np
import pytest
import yaml

from conftest import shared_data
from mdr_slam.calib import (CalibrationError, load_camera_info_pair, load_euroc_calibration,
                            load_kalibr_calibration, load_kitti_calibration,
                            load_stereo_calibration)
from mdr_slam.geometry import inv_T
from mdr_slam.io.datasets import interpolate_poses, load_euroc, load_kitti
from mdr_slam.io.trajectory import Trajectory, read_euroc_csv

EUROC_GT = "V101_GT_left_cam_ORB_SLAM3_clip.txt"


def _euroc():
    return shared_data("euroc_v101_clip")


def _T_BS(path):
    txt = "".join(l for l in open(path) if not l.startswith("%"))
    return np.array(yaml.safe_load(txt)["T_BS"]["data"], dtype=float).reshape(4, 4)


def _check_rectified_pair(cam, size):
    assert cam.size == size
    for m in (cam.left, cam.right):
        assert np.allclose(m.R @ m.R.T, np.eye(3), atol=1e-9)
        assert np.isclose(np.linalg.det(m.R), 1.0)
    # ROS convention: same rectified intrinsics, P_right[0, 3] = -fx * B, no vertical offset
    assert np.allclose(cam.left.P[:, :3], cam.right.P[:, :3])
    assert cam.left.P[0, 3] == 0
    assert np.isclose(cam.right.P[0, 3], -cam.fx * cam.baseline)
    assert cam.right.P[1, 3] == 0


# ----------------------------------------------------------------------------- calibration
def test_euroc_calibration_rectifies_with_the_sensor_yaml_baseline():
    d = _euroc()
    cam = load_euroc_calibration(d)
    _check_rectified_pair(cam, (752, 480))
    T0 = _T_BS(os.path.join(d, "mav0", "cam0", "sensor.yaml"))
    T1 = _T_BS(os.path.join(d, "mav0", "cam1", "sensor.yaml"))
    B = np.linalg.norm((inv_T(T1) @ T0)[:3, 3])
    assert abs(cam.baseline - B) < 1e-9 and 0.10 < B < 0.12        # EuRoC's ~11 cm
    assert np.allclose(cam.left.K, [[458.654, 0, 367.215], [0, 457.296, 248.375], [0, 0, 1]])
    assert np.allclose(cam.left.D[:4], [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05])
    assert not cam.is_rectified
    # the loader guesses the format from a folder, either sensor.yaml, or a pair
    for arg in (os.path.join(d, "mav0"), os.path.join(d, "mav0", "cam1", "sensor.yaml"),
                [os.path.join(d, "mav0", "cam0", "sensor.yaml"),
                 os.path.join(d, "mav0", "cam1", "sensor.yaml")]):
        other = load_stereo_calibration(arg)
        assert np.allclose(other.right.P, cam.right.P) and np.allclose(other.left.R, cam.left.R)


def _camchain(tmp_path, model="radtan"):
    d = _euroc()
    out = {}
    T = []
    for i in (0, 1):
        p = os.path.join(d, "mav0", "cam%d" % i, "sensor.yaml")
        s = yaml.safe_load("".join(l for l in open(p) if not l.startswith("%")))
        T.append(np.array(s["T_BS"]["data"]).reshape(4, 4))
        D = s["distortion_coefficients"] if model == "radtan" else [0.01, -0.002, 0.0003, -0.0001]
        out["cam%d" % i] = {"camera_model": "pinhole", "intrinsics": s["intrinsics"],
                            "distortion_model": model, "distortion_coeffs": D,
                            "resolution": s["resolution"], "rostopic": "/cam%d/image_raw" % i}
    out["cam1"]["T_cn_cnm1"] = (inv_T(T[1]) @ T[0]).tolist()
    path = tmp_path / ("camchain_%s.yaml" % model)
    path.write_text(yaml.safe_dump(out))
    return str(path)


def test_kalibr_camchain_matches_the_euroc_loader(tmp_path):
    cam = load_kalibr_calibration(_camchain(tmp_path))
    ref = load_euroc_calibration(_euroc())
    for a, b in ((cam.left, ref.left), (cam.right, ref.right)):
        assert np.allclose(a.P, b.P, atol=1e-6) and np.allclose(a.R, b.R, atol=1e-9)
    assert load_stereo_calibration(_camchain(tmp_path)).baseline == pytest.approx(ref.baseline)


def test_kalibr_equidistant_uses_the_fisheye_model(tmp_path):
    cam = load_stereo_calibration(_camchain(tmp_path, "equidistant"))
    assert cam.left.distortion_model == "equidistant" and len(cam.left.D) == 4
    _check_rectified_pair(cam, (752, 480))
    assert 0.10 < cam.baseline < 0.12
    l1, l2 = cam.rectify_maps()[0]
    assert l1.shape[:2] == (480, 752)


def _info_dict(m):
    return {"image_width": m.width, "image_height": m.height, "camera_name": "x",
            "camera_matrix": {"rows": 3, "cols": 3, "data": m.K.ravel().tolist()},
            "distortion_model": m.distortion_model,
            "distortion_coefficients": {"rows": 1, "cols": len(m.D), "data": m.D.tolist()},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": m.R.ravel().tolist()},
            "projection_matrix": {"rows": 3, "cols": 4, "data": m.P.ravel().tolist()}}


def test_camera_info_yaml_pair_and_single_file(tmp_path):
    ref = load_euroc_calibration(_euroc())
    lp, rp, both = tmp_path / "left.yaml", tmp_path / "right.yaml", tmp_path / "stereo.yaml"
    lp.write_text(yaml.safe_dump(_info_dict(ref.left)))
    rp.write_text(yaml.safe_dump(_info_dict(ref.right)))
    both.write_text(yaml.safe_dump({"left": _info_dict(ref.left), "right": _info_dict(ref.right)}))
    for cam in (load_camera_info_pair(str(lp), str(rp)), load_stereo_calibration([str(lp), str(rp)]),
                load_stereo_calibration("%s,%s" % (lp, rp)), load_stereo_calibration(str(both))):
        for a, b in ((cam.left, ref.left), (cam.right, ref.right)):
            for k in "KDRP":
                assert np.allclose(getattr(a, k), getattr(b, k)), k
    with pytest.raises(CalibrationError, match="left.*right"):
        load_stereo_calibration(str(lp))


def test_calibration_errors_are_clear(tmp_path):
    ref = load_euroc_calibration(_euroc())
    bad = _info_dict(ref.left)
    del bad["camera_matrix"]
    p = tmp_path / "s.yaml"
    p.write_text(yaml.safe_dump({"left": bad, "right": _info_dict(ref.right)}))
    with pytest.raises(CalibrationError, match="camera_matrix"):
        load_stereo_calibration(str(p))
    zero = _info_dict(ref.left)
    zero["projection_matrix"]["data"] = [0.0] * 12
    p.write_text(yaml.safe_dump({"left": zero, "right": _info_dict(ref.right)}))
    with pytest.raises(CalibrationError, match="focal"):
        load_stereo_calibration(str(p))
    chain = yaml.safe_load(open(_camchain(tmp_path)))
    chain["cam0"]["intrinsics"] = [0.0, 0.0, 300.0, 200.0]
    p.write_text(yaml.safe_dump(chain))
    with pytest.raises(CalibrationError, match="focal length is zero"):
        load_stereo_calibration(str(p))
    del chain["cam1"]["T_cn_cnm1"]
    chain["cam0"]["intrinsics"] = [400.0, 400.0, 300.0, 200.0]
    p.write_text(yaml.safe_dump(chain))
    with pytest.raises(CalibrationError, match="T_cn_cnm1"):
        load_stereo_calibration(str(p))
    with pytest.raises(CalibrationError, match="does not exist"):
        load_stereo_calibration(str(tmp_path / "nope.yaml"))
    p.write_text("foo: 1\n")
    with pytest.raises(CalibrationError, match="unknown calibration format"):
        load_stereo_calibration(str(p))


def test_kitti_calibration_with_and_without_prefixes(tmp_path):
    d = shared_data("kitti06_clip")
    cam = load_stereo_calibration(os.path.join(d, "calib.txt"))
    print("KITTI 06 baseline from calib.txt: %.6f m" % cam.baseline)
    assert cam.baseline == pytest.approx(0.5372, abs=1e-4)
    assert (cam.fx, cam.cx, cam.cy) == pytest.approx((707.0912, 601.8873, 183.1104))
    assert cam.size == (1226, 370) and cam.is_rectified
    rows = [l.split() for l in open(os.path.join(d, "calib.txt")) if l.strip()]
    p = tmp_path / "calib.txt"
    p.write_text("".join("P%d: %s\n" % (i, " ".join(r)) for i, r in enumerate(rows + rows))
                 + "Tr: " + " ".join(["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0"]) + "\n")
    cam2 = load_kitti_calibration(str(p), (1226, 370))
    assert np.allclose(cam2.right.P, cam.right.P)
    assert cam.doffs == 0.0     # calib.txt: the same cx for both cameras
    cam3 = load_kitti_calibration(str(p), (1226, 370), doffs=-0.2)
    assert cam3.doffs == pytest.approx(-0.2) and cam3.is_rectified
    assert cam3.baseline == pytest.approx(cam.baseline) and cam3.cx == cam.cx
    p.write_text("P0: 1 2 3\n")
    with pytest.raises(CalibrationError, match="P0"):
        load_kitti_calibration(str(p), (10, 10))


# ---------------------------------------------------------------------------------- datasets
def test_euroc_reader_pairs_by_stamp_and_skips_missing_images():
    d = _euroc()
    notes = []
    ds = load_euroc(d, ground_truth=os.path.join(d, EUROC_GT), on_skip=notes.append)
    assert len(ds) == 95
    assert any("cam1" in n and "4 listed stamps" in n for n in notes), notes
    stamps = [f[0] for f in ds.frames]
    assert np.all(np.diff(stamps) > 0)
    stamp, left, right = next(iter(ds))
    assert stamp == stamps[0] and left.shape == right.shape == (480, 752) and left.dtype == np.uint8
    gt = ds.ground_truth_at()
    assert len(gt) == 74           # the ORB-SLAM3 clip ground truth covers frames 21-95
    assert ds.ground_truth is not None and len(ds.ground_truth) == 74


def test_euroc_body_ground_truth_is_moved_to_the_left_camera(tmp_path):
    """state_groundtruth_estimate0 is the body (IMU) pose: T_W_C0 = T_W_B T_BS(cam0)."""
    d = _euroc()
    root = tmp_path / "seq" / "mav0"
    root.mkdir(parents=True)
    for cam in ("cam0", "cam1"):
        os.symlink(os.path.join(d, "mav0", cam), str(root / cam))
    cam_gt = read_euroc_csv(os.path.join(d, EUROC_GT))
    T_BS = _T_BS(os.path.join(d, "mav0", "cam0", "sensor.yaml"))
    body = Trajectory.from_matrices(cam_gt.stamps, cam_gt.matrices() @ inv_T(T_BS))
    (root / "state_groundtruth_estimate0").mkdir()
    q = body.quats[:, [3, 0, 1, 2]]
    rows = ["%d,%s" % (int(round(t * 1e9)), ",".join("%.12f" % v for v in np.r_[p, qq]))
            for t, p, qq in zip(body.stamps, body.positions, q)]
    (root / "state_groundtruth_estimate0" / "data.csv").write_text(
        "#timestamp,x,y,z,qw,qx,qy,qz\n" + "\n".join(rows) + "\n")
    ds = load_euroc(str(tmp_path / "seq"))
    assert np.allclose(ds.ground_truth.matrices(), cam_gt.matrices(), atol=1e-6)


def test_interpolate_poses_slerps_between_samples():
    from scipy.spatial.transform import Rotation
    R = Rotation.from_euler("z", [0, 90], degrees=True).as_quat()
    tr = Trajectory([0.0, 1.0], [[0, 0, 0], [2, 0, 0]], R)
    Ts, ok = interpolate_poses(tr, np.array([-0.5, 0.0, 0.5, 1.0, 1.5]), max_gap=2.0)
    assert ok.tolist() == [False, True, True, True, False]
    assert np.allclose(Ts[2][:3, 3], [1, 0, 0])
    assert np.isclose(Rotation.from_matrix(Ts[2][:3, :3]).as_euler("xyz", degrees=True)[2], 45)
    _, ok = interpolate_poses(tr, np.array([0.5]), max_gap=0.5)
    assert not ok[0]


def test_kitti_reader_stamps_and_poses():
    ds = load_kitti(shared_data("kitti06_clip"))
    assert len(ds) == 51 and len(ds.ground_truth) == 51
    assert ds.frames[1][0] == pytest.approx(0.1044989)
    assert ds.ground_truth.path_length() == pytest.approx(59.9, abs=0.1)
    assert np.allclose(ds.ground_truth.matrices()[0], np.eye(4), atol=1e-9)
    stamp, left, right = next(iter(ds))
    assert left.shape == (370, 1226) and stamp == 0.0


# ---------------------------------------------------------------------------------- importers
def _row_offsets(left, right):
    """|v_left - v_right| of SIFT matches (ratio test 0.75, RANSAC on F) between two images.

    SIFT rather than ORB: its keypoints are sub-pixel, so the median row offset measures the
    rectification (ORB's integer level-0 corners give a median of exactly 0 or 1).
    """
    import cv2
    sift = cv2.SIFT_create(1500)
    k1, d1 = sift.detectAndCompute(left, None)
    k2, d2 = sift.detectAndCompute(right, None)
    matches = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [m for m, n in (p for p in matches if len(p) == 2) if m.distance < 0.75 * n.distance]
    p1 = np.float32([k1[m.queryIdx].pt for m in good])
    p2 = np.float32([k2[m.trainIdx].pt for m in good])
    _, inl = cv2.findFundamentalMat(p1, p2, cv2.FM_RANSAC, 1.0, 0.999)
    inl = inl.ravel().astype(bool)
    return np.abs(p1[inl, 1] - p2[inl, 1])


def test_import_euroc_bag_is_readable_and_rectifies_rows(tmp_path):
    from mdr_slam.bagio import read_stereo_frames
    from mdr_slam.camera import StereoCamera
    d = _euroc()
    out = str(tmp_path / "euroc.bag")
    r = subprocess.run(["mdr", "import", "euroc", d, out, "--gt", os.path.join(d, EUROC_GT)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "no image" in r.stderr and "95 stereo pairs, 74 ground-truth poses" in r.stderr
    frames = list(read_stereo_frames(out, with_ground_truth=True))
    assert len(frames) == 95
    assert all(f.left_info is not None and f.right_info is not None for f in frames)
    assert sum(f.T_map_cam_gt is not None for f in frames) == 74
    cam = StereoCamera(frames[0].left_info, frames[0].right_info)
    ref = load_euroc_calibration(d)
    for k in "DKRP":
        assert np.allclose(getattr(cam.left, k), getattr(ref.left, k))
        assert np.allclose(getattr(cam.right, k), getattr(ref.right, k))
    raw, rect = [], []
    for f in frames[::30]:
        raw.append(_row_offsets(f.left, f.right))
        rect.append(_row_offsets(*cam.rectify(f.left, f.right)))
    raw, rect = np.concatenate(raw), np.concatenate(rect)
    print("EuRoC V101 clip: median |row difference| raw %.3f px, rectified %.3f px (%d matches)"
          % (np.median(raw), np.median(rect), len(rect)))
    assert len(rect) > 200
    assert np.median(rect) < 0.5
    assert np.median(raw) > np.median(rect)


def test_import_kitti_bag(tmp_path):
    from mdr_slam.bagio import read_stereo_frames
    from mdr_slam.camera import StereoCamera
    d = shared_data("kitti06_clip")
    out = str(tmp_path / "kitti.bag")
    r = subprocess.run(["mdr", "import", "kitti", d, out, "--max-frames", "20",
                        "--doffs", "-0.2"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    frames = list(read_stereo_frames(out, with_ground_truth=True))
    assert len(frames) == 20
    assert frames[0].stamp == pytest.approx(1.0) and frames[1].stamp == pytest.approx(1.1044989)
    cam = StereoCamera(frames[0].left_info, frames[0].right_info)
    assert cam.baseline == pytest.approx(0.5372, abs=1e-4) and cam.is_rectified
    assert cam.doffs == pytest.approx(-0.2)      # the right camera_info carries the correction
    assert all(f.T_map_cam_gt is not None for f in frames)
    assert np.allclose(frames[0].T_map_cam_gt, np.eye(4), atol=1e-6)
    r = subprocess.run(["mdr", "import", "kitti", str(tmp_path), str(tmp_path / "x.bag")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "not a KITTI" in r.stderr
