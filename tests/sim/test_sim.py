"""mdr_slam.sim: scenes, trajectories, exact ground truth, bag output, the ``mdr sim`` command."""
from __future__ import annotations

import os
import subprocess

import numpy as np
import pytest

from mdr_slam.geometry import inv_T, is_valid_T, transform_points
from mdr_slam.sim import (LABEL_LOW_TEXTURE, LABEL_SPECULAR, LABEL_TEXTURED, Simulator,
                          build_trajectory, generate, make_scene, make_trajectory, sim_camera)
from mdr_slam.sim.trajectory import camera_rotation


def _bilinear(img, u, v):
    import cv2
    from mdr_slam.sim.render import _sample
    return _sample(img.astype(np.float32), np.asarray(u, np.float32), np.asarray(v, np.float32),
                   cv2.BORDER_REPLICATE)


@pytest.fixture(scope="module")
def office():
    return make_scene("office", seed=0)


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("sim_small"))
    s = generate(out, scene="office", duration=0.5, seed=3, scale=0.25, save_depth=2, workers=2)
    return out, s


def _look_at(pos, yaw, pitch=0.0):
    T = np.eye(4)
    T[:3, :3] = camera_rotation(np.array([yaw]), np.array([pitch]))[0]
    T[:3, 3] = pos
    return T


# ------------------------------------------------------------------------------------ scenes
@pytest.mark.parametrize("name", ["office", "corridor", "garage", "floor"])
def test_scenes_have_every_label_and_exact_depth(name):
    sc = make_scene(name, seed=1)
    labels = {r.label for r in sc.rects}
    assert labels == {LABEL_LOW_TEXTURE, LABEL_TEXTURED, LABEL_SPECULAR}
    assert LABEL_SPECULAR not in {r.label for r in make_scene(name, specular=False).rects}
    # large low-texture surfaces dominate, as in the paper's indoor scenes
    area = sc.summary()["area_m2_per_label"]
    assert area["low_texture"] > 3 * area["textured"]


def test_depth_is_exact_on_a_known_wall(office):
    """Camera 2 m in front of the west wall looking at it: the centre ray hits the whiteboard
    (6 mm proud of the wall), every ray's depth is the plane's exact Z."""
    cam = sim_camera(scale=0.5)
    sim = Simulator(office, cam, noise=0.0)
    f = sim.render(_look_at([2.0, 2.7, 1.5], np.pi))
    H, W = f["depth"].shape
    cy, cx = int(round(cam.cy)), int(round(cam.cx))
    assert f["depth"][cy, cx] == pytest.approx(2.0 - 0.006, abs=1e-4)
    assert f["surface"][cy, cx] == LABEL_LOW_TEXTURE
    # every pixel's 3-D point lies on some scene surface
    v, u = np.mgrid[0:H:7, 0:W:7]
    Z = f["depth"][v, u]
    P = cam.backproject(u.ravel(), v.ravel(), Z.ravel())
    Pm = transform_points(_look_at([2.0, 2.7, 1.5], np.pi), P.astype(np.float64))
    assert np.all(Z > 0)
    assert np.max(office.distance_to_surfaces(Pm)) < 2e-4


def test_contrast_parameter_changes_low_texture(office):
    cam = sim_camera(scale=0.5)
    T = _look_at([4.0, 3.0, 1.3], -np.pi / 2 + 0.3, 0.1)
    stds = []
    for c in (2.0, 25.0):
        f = Simulator(make_scene("office", contrast=c), cam, noise=0.0).render(T)
        import cv2
        # inside low-texture surfaces (eroded: no edges), high-passed (no smooth lighting)
        m = cv2.erode((f["surface"] == LABEL_LOW_TEXTURE).astype(np.uint8),
                      np.ones((11, 11), np.uint8)) > 0
        assert m.sum() > 10000
        img = f["left"].astype(np.float32)
        hp = img - cv2.GaussianBlur(img, (0, 0), 6)
        stds.append(np.std(hp[m]))
    assert stds[0] < 5.0 and stds[1] > 2 * stds[0], stds


# ------------------------------------------------------------------------------- trajectories
@pytest.mark.parametrize("name", ["office", "corridor", "garage", "floor"])
def test_default_trajectories_stay_inside_and_are_smooth(name):
    sc = make_scene(name)
    stamps, Ts = make_trajectory(sc, duration=30.0, rate=20.0, seed=2)
    assert len(stamps) == 600 and np.allclose(np.diff(stamps), 0.05)
    assert all(is_valid_T(T) for T in Ts[::25])
    P = Ts[:, :3, 3]
    d = sc.distance_to_surfaces(P[::5])
    assert d.min() > 0.4, d.min()
    lo, hi = sc.bounds
    assert np.all(P > lo) and np.all(P < hi)
    assert np.abs(Ts[:, 2, 2]).max() < 0.2            # optical axis about horizontal
    step = np.linalg.norm(np.diff(P, axis=0), axis=1)
    assert step.max() < 0.08                           # < 1.6 m/s, no jumps
    again = make_trajectory(sc, duration=30.0, rate=20.0, seed=2)[1]
    np.testing.assert_array_equal(Ts, again)


def test_loop_returns_to_start_and_has_pure_rotation():
    tr = build_trajectory("office", duration=20.0, seed=0)
    assert [s[0] for s in tr.segments] == ["loop", "pure_rotation", "loop"]
    T0, T1 = tr.poses([0.0, 20.0])
    assert np.allclose(T0, T1, atol=1e-9)
    _, ta, tb = tr.segments[1]
    Ts = tr.poses(np.linspace(ta, tb, 40))
    assert np.ptp(Ts[:, :3, 3], axis=0).max() < 1e-6     # the camera stands still...
    yaw = np.arctan2(Ts[:, 1, 2], Ts[:, 0, 2])
    assert np.ptp(np.unwrap(yaw)) > 1.0                  # ...and turns by more than 57 degrees


def test_corner_turns_fast():
    tr = build_trajectory("corridor", duration=30.0, seed=0)
    names = [s[0] for s in tr.segments]
    assert "corner" in names
    t = np.arange(0, 30.0, 0.05)
    Ts = tr.poses(t)
    yaw = np.unwrap(np.arctan2(Ts[:, 1, 2], Ts[:, 0, 2]))
    assert abs(yaw[-1] - yaw[0]) == pytest.approx(np.pi / 2, abs=0.2)
    assert np.degrees(np.abs(np.diff(yaw)).max() / 0.05) > 40.0


# ------------------------------------------------------------------------ ground truth checks
def _textured_view(sim, tr, t_candidates):
    for t in t_candidates:
        T = tr.poses([t])[0]
        f = sim.render(T, index=0)
        if (f["surface"] == LABEL_TEXTURED).sum() > 2000:
            return t, T, f
    raise AssertionError("no textured surface in view")


def test_reprojection_with_gt_poses_is_photometrically_consistent(office):
    """Back-project frame k's GT depth on textured pixels, move it with the GT poses into
    frame k+1: the intensities agree; a 3 cm pose error makes them disagree."""
    cam = sim_camera(scale=0.5)
    sim = Simulator(office, cam, noise=0.0)
    tr = build_trajectory(office, duration=30.0, seed=0)
    t, T0, f0 = _textured_view(sim, tr, np.arange(0.0, 30.0, 1.3))
    T1 = tr.poses([t + 0.05])[0]
    f1 = sim.render(T1)
    v, u = np.nonzero(f0["surface"] == LABEL_TEXTURED)
    Z = f0["depth"][v, u]
    P0 = cam.backproject(u, v, Z).astype(np.float64)

    def err(T_target):
        P1 = transform_points(inv_T(T_target) @ T0, P0)
        u1, v1, z1 = cam.project(P1)
        W, H = cam.size
        ok = (u1 > 1) & (u1 < W - 2) & (v1 > 1) & (v1 < H - 2)
        # drop points occluded in the target view (GT depth there is nearer)
        zt = _bilinear(f1["depth"], u1[ok], v1[ok])
        vis = np.abs(zt - z1[ok]) < 0.02 * z1[ok]
        e = np.abs(_bilinear(f1["left"], u1[ok], v1[ok])[vis] - f0["left"][v[ok], u[ok]][vis])
        assert vis.sum() > 1000
        return e

    e = err(T1)
    assert np.median(e) < 2.0 and np.percentile(e, 90) < 8.0, (np.median(e), np.percentile(e, 90))
    Tbad = T1.copy()
    Tbad[:3, 3] += T1[:3, 0] * 0.03
    assert np.median(err(Tbad)) > 3 * max(np.median(e), 1.0)


def test_stereo_pair_matches_gt_disparity(office):
    """A left pixel with GT depth Z is at u - fx*B/Z in the right image (textured surfaces)."""
    cam = sim_camera(scale=0.5)
    sim = Simulator(office, cam, noise=0.0)
    tr = build_trajectory(office, duration=30.0, seed=0)
    _, _, f = _textured_view(sim, tr, np.arange(0.5, 30.0, 1.7))
    v, u = np.nonzero(f["surface"] == LABEL_TEXTURED)
    Z = f["depth"][v, u]
    ur = u - cam.fx * cam.baseline / Z
    ok = ur > 2
    right = _bilinear(f["right"], ur[ok], v[ok].astype(np.float32))
    e = np.abs(right - f["left"][v[ok], u[ok]])
    assert np.median(e) < 2.0 and np.percentile(e, 90) < 8.0
    shifted = _bilinear(f["right"], ur[ok] + 3.0, v[ok].astype(np.float32))
    assert np.median(np.abs(shifted - f["left"][v[ok], u[ok]])) > 3 * max(np.median(e), 1.0)


def test_specular_band_is_bright_and_view_dependent(office):
    cam = sim_camera(scale=0.5)
    sim = Simulator(office, cam, noise=0.0)
    T = _look_at([4.0, 3.0, 1.3], np.pi / 2)          # facing the north wall and its band
    f = sim.render(T)
    band = f["surface"] == LABEL_SPECULAR
    assert band.sum() > 2000
    assert f["left"][band].max() >= 250                  # nearly saturated highlight
    T2 = T.copy()
    T2[2, 3] += 0.25                                      # raise the camera: the stripe moves
    g = sim.render(T2)
    rows = lambda img, m: np.argmax(np.where(m, img, 0).astype(float).mean(axis=1))
    assert rows(f["left"], band) != rows(g["left"], g["surface"] == LABEL_SPECULAR)


def test_distorted_raw_images_rectify_back(office):
    """Raw images rendered through (K, D, R) and rectified with StereoCamera.rectify (OpenCV
    initUndistortRectifyMap) match the directly rendered rectified pair."""
    cam = sim_camera(scale=0.5, distort=True)
    assert not cam.is_rectified and abs(cam.left.D[0] + 0.283) < 1e-2
    sim = Simulator(office, cam, noise=0.0)
    tr = build_trajectory(office, duration=30.0, seed=0)
    T = tr.poses([3.0])[0]
    raw = sim.render(T, raw=True)
    rect = sim.render(T, raw=False)
    rl, rr = cam.rectify(raw["left"], raw["right"])
    W, H = cam.size
    inner = np.zeros((H, W), bool)
    inner[12:-12, 12:-12] = True
    for got, want in ((rl, rect["left"]), (rr, rect["right"])):
        d = np.abs(got.astype(float) - want.astype(float))[inner]
        assert np.median(d) < 1.5 and np.percentile(d, 95) < 10, \
            (np.median(d), np.percentile(d, 95))
    # and the raw image really is distorted (the test can fail)
    assert np.percentile(np.abs(raw["left"].astype(float) - rect["left"])[inner], 75) > 5


# ---------------------------------------------------------------------------- files and bag
def test_generate_is_deterministic_and_bag_is_readable(small_run, tmp_path):
    import rosbag
    from mdr_slam.bagio import read_stereo_frames
    from mdr_slam.io import read_tum
    out, s = small_run
    assert s["n_frames"] == 10
    with rosbag.Bag(s["bag"]) as bag:
        topics = bag.get_type_and_topic_info().topics
    for t in ("/stereo/left/image_raw", "/stereo/right/image_raw", "/stereo/left/camera_info",
              "/stereo/right/camera_info", "/ground_truth/pose", "/tf"):
        assert topics[t].message_count == 10, t
    frames = list(read_stereo_frames(s["bag"], with_ground_truth=True))
    assert len(frames) == 10
    gt = read_tum(s["groundtruth"]).matrices()
    for fr, T in zip(frames, gt):
        assert fr.left.shape == (120, 188) and fr.left.dtype == np.uint8
        assert fr.left_info is not None and fr.left_info.is_rectified
        np.testing.assert_allclose(fr.T_map_cam_gt, T, atol=1e-6)
    # same seed, one worker instead of two: byte-identical images; another seed differs
    again = generate(str(tmp_path / "a"), scene="office", duration=0.5, seed=3, scale=0.25,
                     workers=1)
    other = generate(str(tmp_path / "b"), scene="office", duration=0.5, seed=4, scale=0.25,
                     workers=1)
    f2 = list(read_stereo_frames(again["bag"]))
    f3 = list(read_stereo_frames(other["bag"]))
    for a, b in zip(frames, f2):
        np.testing.assert_array_equal(a.left, b.left)
        np.testing.assert_array_equal(a.right, b.right)
        assert a.stamp == b.stamp
    assert not np.array_equal(frames[0].left, f3[0].left)


def test_gt_depth_files(small_run, office):
    out, s = small_run
    files = sorted(os.listdir(os.path.join(out, "gt_depth")))
    assert files == ["%06d.npz" % i for i in range(0, 10, 2)]
    d = np.load(os.path.join(out, "gt_depth", files[1]))
    assert d["depth"].dtype == np.float32 and d["depth"].shape == (120, 188)
    assert d["surface"].dtype == np.uint8 and set(np.unique(d["surface"])) <= {0, 1, 2, 3}
    assert (d["depth"] > 0).all() and d["depth"].max() < 10.5


def test_gt_map_lies_on_surfaces_with_1cm_spacing(small_run):
    from scipy.spatial import cKDTree
    from mdr_slam.io import read_cloud, cloud_xyz
    out, s = small_run
    c = read_cloud(os.path.join(out, "gt_map.ply"))
    assert set(c) >= {"x", "y", "z", "nx", "ny", "nz", "surface"}
    P = cloud_xyz(c).astype(np.float64)
    assert len(P) > 50000 and len(P) == s["n_map_points"]
    assert set(np.unique(c["surface"])) <= {1, 2, 3}
    sc = make_scene("office", seed=3)
    rng = np.random.default_rng(0)
    sub = P[rng.choice(len(P), 4000, replace=False)]
    assert sc.distance_to_surfaces(sub).max() < 1e-4
    N = np.stack([c["nx"], c["ny"], c["nz"]], 1)
    assert np.allclose(np.linalg.norm(N, axis=1), 1.0, atol=1e-5)
    dist, _ = cKDTree(P).query(sub, k=2)
    assert np.median(dist[:, 1]) == pytest.approx(0.01, abs=0.0015)
    # everything mapped was within max range of some left-camera position
    from mdr_slam.io import read_tum
    cams = read_tum(s["groundtruth"]).positions
    dmin = cKDTree(cams).query(sub)[0]
    assert dmin.max() < 8.0 * 1.6


def test_scene_yaml(small_run):
    import yaml
    out, s = small_run
    y = yaml.safe_load(open(os.path.join(out, "scene.yaml")))
    assert y["camera"]["width"] == 188 and y["camera"]["baseline"] == pytest.approx(0.11)
    assert y["n_frames"] == 10 and y["seed"] == 3 and y["scene"] == "office"
    assert y["labels"] == {0: "nothing", 1: "low_texture", 2: "textured", 3: "specular"}
    assert [g["name"] for g in y["segments"]] == ["loop", "pure_rotation", "loop"]
    assert y["segments"][0]["t0"] == pytest.approx(1.0)
    assert y["timing"]["render_ms_per_frame_median"] > 0


def test_distorted_bag_camera_info_round_trips(tmp_path):
    from mdr_slam.bagio import read_stereo_frames
    from mdr_slam.camera import StereoCamera
    s = generate(str(tmp_path), scene="corridor", duration=0.15, scale=0.25, distort=True,
                 workers=1)
    fr = next(iter(read_stereo_frames(s["bag"])))
    cam = StereoCamera(fr.left_info, fr.right_info)
    ref = sim_camera(scale=0.25, distort=True)
    for a, b in ((cam.left, ref.left), (cam.right, ref.right)):
        for M in ("K", "D", "R", "P"):
            np.testing.assert_allclose(getattr(a, M), getattr(b, M), atol=1e-9)
    assert not cam.is_rectified and cam.baseline == pytest.approx(0.11)
    assert s["camera"]["distortion"]["left"]["D"][0] == pytest.approx(-0.2834, abs=1e-3)


# ------------------------------------------------------------------------------------- CLI
def test_mdr_sim_help():
    r = subprocess.run(["mdr", "sim", "--help"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for opt in ("--scene", "--duration", "--out", "--distort", "--contrast", "--no-specular",
                "--noise", "--save-depth", "--max-range", "--seed", "--rate"):
        assert opt in r.stdout


def test_mdr_sim_tiny_run_writes_everything(tmp_path):
    out = tmp_path / "corr"
    r = subprocess.run(["mdr", "sim", "--scene", "corridor", "--duration", "0.3", "--scale",
                        "0.25", "--out", str(out), "--save-depth", "3", "--no-specular",
                        "--quiet"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for f in ("sequence.bag", "groundtruth.tum", "gt_map.ply", "scene.yaml",
              "gt_depth/000000.npz", "gt_depth/000003.npz"):
        assert (out / f).exists(), f
    assert not (out / "gt_depth" / "000001.npz").exists()
    import yaml
    y = yaml.safe_load((out / "scene.yaml").read_text())
    assert y["n_frames"] == 6 and y["options"]["specular"] is False
    assert "corner" in [g["name"] for g in y["segments"]] or \
        {g["name"] for g in y["segments"]} <= {"drive", "corner"}
    r = subprocess.run(["mdr", "sim", "--out", str(out), "--duration", "-1"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "positive" in r.stderr
