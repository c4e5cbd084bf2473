"""Node 2 core: ELAS single-frame depth, the measurement model and the keyframe Kalman filter."""
from __future__ import annotations

import numpy as np
import pytest

from mdr_slam.camera import StereoCamera
from mdr_slam.config import ConfigError
from mdr_slam.depth import (DepthConfig, DepthFilter, ElasConfig, ElasMatcher, StereoDepth,
                            measurement_from_disparity, render_depth)
from mdr_slam.geometry import inv_T, make_T, transform_points

PLANE_Z = 2.0   # a wall facing the camera at z = 2 m in map


def tiny_camera():
    # f*B = 30 px*m: at 2 m the disparity is 15 px, so one measurement has sigma_Z/Z = 0.3/15 = 2 %
    return StereoCamera.from_rectified(64, 48, 50.0, 50.0, 31.5, 23.5, 0.6)


def plane_depth(cam, T_map_cam):
    """True depth image of the plane z_map = PLANE_Z seen from T_map_cam."""
    w, h = cam.size
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    ray = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], axis=-1)
    rm = ray @ T_map_cam[:3, :3].T
    return (PLANE_Z - T_map_cam[2, 3]) / rm[..., 2]


def noisy_measurement(cam, T_map_cam, rng, sigma_d=0.3):
    Z = plane_depth(cam, T_map_cam)
    fB = cam.fx * cam.baseline
    d = fB / Z + rng.normal(0.0, sigma_d, Z.shape)
    return measurement_from_disparity(d.astype(np.float32), cam, sigma_d, 0.2, 20.0)


def pose(x=0.0, y=0.0, z=0.0, yaw_deg=0.0):
    a = np.radians(yaw_deg)   # about the camera y axis (down): a pan
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    return make_T(R, [x, y, z])


def map_z(out, T_map_cam):
    return transform_points(T_map_cam, out.points.astype(float))[:, 2]


# ------------------------------------------------------------------ measurement model
def test_measurement_variance_formula_and_masking():
    cam = tiny_camera()
    fB = cam.fx * cam.baseline
    disp = np.full((48, 64), 15.0, np.float32)
    disp[0, 0] = -10.0        # libelas invalid
    disp[0, 1] = 0.0
    disp[0, 2] = 1.0          # Z = 30 m > max_depth
    disp[0, 3] = 300.0        # Z = 0.1 m < min_depth
    disp[0, 4] = np.nan
    Z, var = measurement_from_disparity(disp, cam, sigma_d=0.5, min_depth=0.2, max_depth=10.0)
    assert Z.dtype == np.float32 and var.dtype == np.float32
    assert np.all(np.isnan(Z[0, :5])) and np.all(np.isnan(var[0, :5]))
    assert np.isclose(Z[5, 5], fB / 15.0)
    # sigma_Z = Z^2 sigma_d / (f B)
    assert np.isclose(np.sqrt(var[5, 5]), (fB / 15.0) ** 2 * 0.5 / fB, rtol=1e-5)
    # the same as propagating the disparity noise numerically
    dz = fB / (15.0 - 0.5) - fB / (15.0 + 0.5)
    assert np.isclose(np.sqrt(var[5, 5]), dz / 2, rtol=0.01)


# ------------------------------------------------------------------ ELAS
def test_elas_recovers_known_disparity_of_textured_pair():
    import cv2
    rng = np.random.default_rng(1)
    h, w, d = 120, 160, 12
    tex = cv2.GaussianBlur((rng.random((h, w + 40)) * 255).astype(np.uint8), (3, 3), 0)
    left = np.ascontiguousarray(tex[:, 20:20 + w])
    right = np.ascontiguousarray(tex[:, 20 + d:20 + d + w])   # left(x) = right(x - d)
    m = ElasMatcher({"preset": "robotics", "disp_max": 64, "subsampling": False})
    disp = m.compute(left, right)
    assert disp.shape == (h, w) and disp.dtype == np.float32
    valid = disp > 0
    assert valid.mean() > 0.7
    assert abs(float(np.median(disp[valid])) - d) < 0.25
    assert np.mean(np.abs(disp[valid] - d) < 1.0) > 0.95
    # the parameters reach libelas, and unknown ones are refused
    assert m.params["disp_max"] == 64 and m.params["preset"] == "robotics"
    with pytest.raises(ValueError):
        ElasMatcher({"disp_maxx": 3})
    # subsampling still returns a full-size disparity
    ds = ElasMatcher({"subsampling": True, "disp_max": 64}).compute(left, right)
    assert ds.shape == (h, w) and abs(float(np.median(ds[ds > 0])) - d) < 0.5


@pytest.mark.parametrize("preset", ["robotics", "middlebury"])
def test_elas_preset_tables_are_libelas_presets(preset):
    """ELAS_PRESETS holds libelas' own presets: every parameter as Elas::setPreset sets it, the
    disparity range and subsampling from ElasConfig."""
    import elas
    from mdr_slam.depth import ELAS_PRESETS
    ref = elas.Elas()
    ref.set_preset(elas.PRESET_ROBOTICS if preset == "robotics" else elas.PRESET_MIDDLEBURY)
    m = ElasMatcher(ElasConfig(preset=preset.upper(), disp_min=2, disp_max=96, subsampling=False))
    assert m.params["preset"] == preset
    assert set(ELAS_PRESETS[preset]) | {"disp_min", "disp_max", "subsampling", "preset"} == \
        set(m.params)
    for k, v in m.params.items():
        want = {"disp_min": 2, "disp_max": 96, "subsampling": False, "preset": preset}.get(
            k, getattr(ref, k, None))
        assert v == pytest.approx(want), k
    with pytest.raises(ConfigError):
        ElasConfig(preset="kitti")
    with pytest.raises(ConfigError):
        ElasConfig(disp_min=64, disp_max=64)


# ------------------------------------------------------------------ filter
def test_static_scene_converges_with_shrinking_variance():
    cam = tiny_camera()
    rng = np.random.default_rng(0)
    f = DepthFilter(cam, {"stride": 1, "process_noise": 0.0, "tau": 0.01, "min_obs": 3,
                          "kf_max_frames": 100, "kf_translation": 10.0})
    T = pose()
    Z1, _ = noisy_measurement(cam, T, rng)
    single_rmse = np.sqrt(np.nanmean((Z1 - PLANE_Z) ** 2))
    sds, errs = [], []
    for i in range(20):
        Z, var = noisy_measurement(cam, T, rng)
        out = f.process(0.1 * i, T, Z, var)
        if i < 2:   # init (inflated variance) + 1 update: not converged yet
            assert len(out) == 0
        assert out.keyframe_id == 0 and out.is_new_keyframe == (i == 0)
        sds.append(np.sqrt(np.nanmedian(f.keyframe.var)))
        if len(out):
            errs.append(np.sqrt(np.mean((out.points[:, 2] - PLANE_Z) ** 2)))
    assert all(b < a for a, b in zip(sds, sds[1:])), "variance must shrink with every frame"
    assert out.stats["n_converged"] > 0.9 * 64 * 48
    # the published error is far below one ELAS frame's and consistent with the filter's variance
    assert errs[-1] < 0.35 * single_rmse
    assert errs[-1] < 2.0 * np.sqrt(np.median(out.variance))
    assert np.all(np.sqrt(out.variance) <= 0.01 * out.points[:, 2] + 1e-6)   # tau is relative
    assert np.all(out.n_obs >= 3)


def test_outlier_is_gated_counted_and_not_fused():
    cam = tiny_camera()
    rng = np.random.default_rng(2)
    f = DepthFilter(cam, {"stride": 1, "process_noise": 0.0, "kf_translation": 10.0, "kf_max_frames": 100})
    T = pose()
    for i in range(6):
        f.process(0.1 * i, T, *noisy_measurement(cam, T, rng, sigma_d=0.0001))
    mu_before = f.keyframe.mu.copy()
    n_obs_before = f.keyframe.n_obs.copy()
    n_rej_before = f.keyframe.n_rej.copy()
    Z = np.full((48, 64), np.nan, np.float32)
    var = np.full((48, 64), np.nan, np.float32)
    Z[10:20, 10:20] = 1.0               # an ELAS outlier blob 1 m in front of the wall
    var[10:20, 10:20] = 1e-4
    out = f.process(1.0, T, Z, var)
    assert out.stats["n_gated"] == 100
    assert out.stats["n_updated"] == 0
    blob = (np.arange(48)[:, None] >= 10) & (np.arange(48)[:, None] < 20) & \
        (np.arange(64)[None, :] >= 10) & (np.arange(64)[None, :] < 20)
    blob = blob.ravel()
    np.testing.assert_array_equal(f.keyframe.mu, mu_before)   # nothing was fused
    dn = f.keyframe.n_rej - n_rej_before
    assert np.all(dn[blob] == 1) and np.all(dn[~blob] == 0)
    np.testing.assert_array_equal(f.keyframe.n_obs, n_obs_before)
    # a pixel rejected far more often than accepted is re-initialized from the new evidence
    f2 = DepthFilter(cam, {"stride": 1, "process_noise": 0.0, "reinit_min_rejections": 3, "reinit_ratio": 2.0,
                           "kf_translation": 10.0, "kf_max_frames": 100})
    f2.process(0.0, T, *noisy_measurement(cam, T, rng, sigma_d=0.0001))
    for i in range(1, 4):
        out = f2.process(0.1 * i, T, Z, var)
    assert out.stats["n_reinit"] == 100
    assert np.allclose(1.0 / f2.keyframe.mu[blob], 1.0, atol=1e-4)
    assert np.all(f2.keyframe.n_obs[blob] == 1)


def test_keyframe_switch_carries_converged_points_reprojected():
    cam = tiny_camera()
    rng = np.random.default_rng(3)
    f = DepthFilter(cam, {"stride": 1, "process_noise": 0.0, "tau": 0.01, "kf_translation": 10.0,
                          "kf_max_frames": 100, "carry_tau": 0.01})
    T0 = pose()
    for i in range(12):
        out = f.process(0.1 * i, T0, *noisy_measurement(cam, T0, rng, sigma_d=0.1))
    n_conv = out.stats["n_converged"]
    assert n_conv > 2500
    # a forced (external) keyframe from a moved, turned camera, with NO new measurement: what is
    # published can only come from the carried state
    T1 = pose(x=0.15, y=-0.05, z=0.2, yaw_deg=4.0)
    empty = np.full((48, 64), np.nan, np.float32)
    out = f.process(2.0, T1, empty, empty, new_keyframe=True, keyframe_id=42)
    assert out.is_new_keyframe and out.keyframe_id == 42 and f.keyframe.id == 42
    assert out.stats["kf_reason"] == "event"
    assert out.stats["n_carried"] > 0.6 * n_conv
    assert len(out) == out.stats["n_carried"]
    # correctly reprojected: on the wall in map, at the new camera's pixels, with their history
    np.testing.assert_allclose(map_z(out, T1), PLANE_Z, atol=0.03)
    Ztrue = plane_depth(cam, T1).ravel()[np.flatnonzero(np.isfinite(f.keyframe.mu))]
    np.testing.assert_allclose(out.points[:, 2], Ztrue, rtol=0.02)
    assert np.median(out.n_obs) == 12 and np.all(out.n_obs >= 3)   # history kept (min_obs 3)
    # and the next frame keeps refining the carried state in the new keyframe
    out2 = f.process(2.1, T1, *noisy_measurement(cam, T1, rng, sigma_d=0.1))
    assert out2.keyframe_id == 42 and not out2.is_new_keyframe
    assert out2.stats["n_updated"] > 0.9 * out.stats["n_carried"]


def test_automatic_keyframe_selection_and_pose_correction():
    cam = tiny_camera()
    rng = np.random.default_rng(4)
    f = DepthFilter(cam, {"stride": 1, "kf_translation": 0.1, "kf_rotation_deg": 5.0, "kf_max_frames": 5,
                          "kf_min_overlap": 0.5})
    T = pose()
    ids = [f.process(0.1 * i, T, *noisy_measurement(cam, T, rng)).keyframe_id for i in range(11)]
    assert ids == [0] * 5 + [1] * 5 + [2]                          # max frames per keyframe
    out = f.process(1.2, pose(x=0.12), *noisy_measurement(cam, pose(x=0.12), rng))
    assert out.is_new_keyframe and out.stats["kf_reason"] == "translation"
    out = f.process(1.3, pose(x=0.12, yaw_deg=6), *noisy_measurement(cam, pose(x=0.12, yaw_deg=6), rng))
    assert out.stats["kf_reason"] == "rotation"
    out = f.process(1.4, pose(x=1.5, yaw_deg=6), *noisy_measurement(cam, pose(x=1.5, yaw_deg=6), rng),
                    new_keyframe=False)
    assert out.stats["kf_reason"] == "overlap"                     # even when told not to
    # external "no keyframe" is obeyed otherwise
    out = f.process(1.5, pose(x=1.6, yaw_deg=6), *noisy_measurement(cam, pose(x=1.6, yaw_deg=6), rng),
                    new_keyframe=False)
    assert not out.is_new_keyframe
    # loop closure: replacing the keyframe pose moves its points with it
    kid = f.keyframe.id
    assert not f.set_keyframe_pose(np.eye(4), keyframe_id=kid + 7)
    T_new = f.keyframe.T_map_kf.copy()
    T_new[0, 3] += 0.5
    assert f.set_keyframe_pose(T_new, keyframe_id=kid)
    np.testing.assert_allclose(f.keyframe.T_map_kf, T_new)
    # time going backwards resets the filter
    out = f.process(0.0, T, *noisy_measurement(cam, T, rng))
    assert out.stats.get("reset") == 1 and out.is_new_keyframe


def test_keyframe_correction_moves_a_later_keyframe_rigidly_with_the_pose_keyframe():
    """The depth node skips frames, so the depth keyframe that takes a pose keyframe's event can sit
    a frame later. A loop closure moving that pose keyframe (T_old -> T_new) must move ours by the
    same rigid correction, not give it T_new (the pose of the other frame): its points would jump
    by the camera's motion between the two frames."""
    from mdr_slam.geometry import make_T
    from scipy.spatial.transform import Rotation
    cam = tiny_camera()
    rng = np.random.default_rng(5)
    f = DepthFilter(cam, {"stride": 1})
    T_event = pose(x=0.0)                    # the pose keyframe (a frame the depth node skipped)
    T_ours = pose(x=0.06, yaw_deg=2.0)       # the next frame: where our keyframe starts
    for i in range(5):
        f.process(0.1 * i, T_ours, *noisy_measurement(cam, T_ours, rng), new_keyframe=(i == 0),
                  keyframe_id=7 if i == 0 else None)
    assert f.keyframe.id == 7
    C = make_T(Rotation.from_euler("z", 3.0, degrees=True).as_matrix(), [0.2, -0.1, 0.05])
    assert not f.correct_keyframe(T_event, C @ T_event, keyframe_id=8)     # not ours
    assert f.correct_keyframe(T_event, C @ T_event, keyframe_id=7)
    np.testing.assert_allclose(f.keyframe.T_map_kf, C @ T_ours, atol=1e-9)
    # replacing the pose instead (the old behaviour) would be off by the motion between the frames
    assert np.linalg.norm((C @ T_event)[:3, 3] - (C @ T_ours)[:3, 3]) > 0.05
    # same frame: identical to replacing the pose
    g = DepthFilter(cam, {"stride": 1})
    g.process(0.0, T_event, *noisy_measurement(cam, T_event, rng), new_keyframe=True, keyframe_id=3)
    g.correct_keyframe(T_event, C @ T_event, keyframe_id=3)
    np.testing.assert_allclose(g.keyframe.T_map_kf, C @ T_event, atol=1e-9)


def test_fill_holes_initializes_empty_keyframe_pixels():
    cam = tiny_camera()
    rng = np.random.default_rng(5)
    f = DepthFilter(cam, {"stride": 1, "kf_translation": 10.0, "kf_max_frames": 100})
    T = pose()
    Z, var = noisy_measurement(cam, T, rng, sigma_d=0.05)
    Z[:, 20:40] = np.nan                       # a low-texture hole at the keyframe
    f.process(0.0, T, Z, var)
    assert np.count_nonzero(np.isfinite(f.keyframe.mu)) == 48 * 44
    # a 0.3 px shift (an exact half pixel would make the nearest-pixel splat collide by rounding)
    out = f.process(0.1, pose(x=0.012), *noisy_measurement(cam, pose(x=0.012), rng, sigma_d=0.05))
    assert out.stats["n_filled"] > 0.9 * 48 * 20
    filled = np.isfinite(f.keyframe.mu.reshape(48, 64)[:, 22:38])
    assert filled.mean() > 0.95
    np.testing.assert_allclose(1.0 / f.keyframe.mu.reshape(48, 64)[:, 22:38][filled], PLANE_Z,
                               rtol=0.02)


def test_elas_only_baseline_returns_every_valid_pixel():
    cam = tiny_camera()
    rng = np.random.default_rng(6)
    Z, var = noisy_measurement(cam, pose(), rng)
    Z[rng.random(Z.shape) < 0.3] = np.nan
    inten = rng.integers(0, 255, Z.shape).astype(np.uint8)
    f = DepthFilter(cam, {"stride": 1, "temporal": False})
    for i in range(2):
        out = f.process(0.1 * i, pose(), Z, var, intensity=inten)
        n = int(np.count_nonzero(np.isfinite(Z)))
        assert len(out) == n and out.stats["n_published"] == n
        assert np.all(out.n_obs == 1) and not out.is_new_keyframe
    v, u = np.nonzero(np.isfinite(Z))
    np.testing.assert_allclose(out.points, cam.backproject(u, v, Z[v, u]), rtol=1e-5)
    np.testing.assert_array_equal(out.intensity, inten[v, u])
    np.testing.assert_allclose(out.variance, var[v, u])
    # render_depth is the inverse
    np.testing.assert_allclose(render_depth(out.points, cam)[v, u], Z[v, u], rtol=1e-5)


def test_single_frame_points_need_no_pose_and_leave_the_filter_alone():
    """While the tracker is LOST the depth node publishes one measurement's points for obstacle
    sensing: those of sigma_Z <= max_sigma, in the camera, the filter's keyframe untouched."""
    cam = tiny_camera()
    rng = np.random.default_rng(7)
    f = DepthFilter(cam, {"stride": 1})
    for i in range(4):
        f.process(0.1 * i, pose(), *noisy_measurement(cam, pose(), rng))
    kf, mu = f.keyframe, f.keyframe.mu.copy()
    Z, var = noisy_measurement(cam, pose(), rng)
    Z[:, :32] *= 1.6                       # the left half farther away: larger sigma_Z
    var[:, :32] *= 1.6 ** 4
    smax = float(np.sqrt(np.nanmax(var[:, 32:]))) * 1.01
    assert smax < float(np.sqrt(np.nanmin(var[:, :32])))
    out = f.single_frame(Z, var, max_sigma=smax)
    v, u = np.nonzero(np.isfinite(Z) & (var <= smax ** 2))
    assert len(out) == len(u) == Z.shape[0] * 32
    np.testing.assert_allclose(out.points, cam.backproject(u, v, Z[v, u]), rtol=1e-5)
    assert np.all(out.n_obs == 1) and len(f.single_frame(Z, var)) == Z.size
    assert f.keyframe is kf and np.array_equal(f.keyframe.mu, mu, equal_nan=True)
    with pytest.raises(ValueError):
        f.single_frame(Z[:, :10], var[:, :10])


def test_stride_option_and_refused_parameters():
    cam = tiny_camera()
    rng = np.random.default_rng(7)
    f = DepthFilter(cam, {"stride": 2, "tau": 0.02, "kf_translation": 10.0, "kf_max_frames": 100})
    for i in range(8):
        T = pose(x=0.01 * i)
        out = f.process(0.1 * i, T, *noisy_measurement(cam, T, rng, sigma_d=0.1))
    assert f.keyframe.mu.size == 24 * 32
    assert len(out) > 0.8 * 24 * 32
    np.testing.assert_allclose(map_z(out, T), PLANE_Z, atol=0.05)
    # a value out of range, an unknown mode, a removed or misspelt parameter: a clear error
    for bad in ({"stride": 0}, {"densify": "planes"}, {"densify": False}, {"interpolation": "nearest"},
                {"tua": 0.02}, {"tau": "x"}):
        with pytest.raises(ConfigError):
            DepthFilter(cam, bad)
    with pytest.raises(ValueError):
        f.process(1.0, np.full((4, 4), np.nan), *noisy_measurement(cam, T, rng))
    with pytest.raises(ValueError):
        f.process(1.0, T, np.zeros((10, 10), np.float32), np.zeros((10, 10), np.float32))


# ------------------------------------------------------------------ StereoDepth
def _textured_pair(h, w, d, seed=0):
    import cv2
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur((rng.random((h, w + 2 * d + 8)) * 255).astype(np.uint8), (3, 3), 0)
    return np.ascontiguousarray(tex[:, 4:4 + w]), np.ascontiguousarray(tex[:, 4 + d:4 + d + w])


def test_stereo_depth_end_to_end_on_a_synthetic_wall():
    w, h, d = 160, 120, 16
    cam = StereoCamera.from_rectified(w, h, 100.0, 100.0, 79.5, 59.5, 0.2)   # Z = 20/16 = 1.25 m
    sd = StereoDepth(cam, {"elas": {"disp_max": 64, "subsampling": False}, "tau": 0.02, "stride": 1})
    left, right = _textured_pair(h, w, d)
    for i in range(5):
        out = sd.process(0.1 * i, left, right, np.eye(4))
    assert set(out.timings) >= {"rectify", "elas", "measurement", "filter", "total"}
    assert out.depth.shape == (h, w)
    assert len(out) > 0.5 * w * h
    np.testing.assert_allclose(np.median(out.points[:, 2]), 1.25, rtol=0.01)
    assert out.intensity.max() > 0
    # colour (bgr8) and 16-bit inputs are accepted; a wrong size is refused clearly
    import cv2
    out = sd.process(1.0, cv2.cvtColor(left, cv2.COLOR_GRAY2BGR), cv2.cvtColor(right, cv2.COLOR_GRAY2BGR),
                     np.eye(4))
    assert len(out) > 0
    out = sd.process(1.1, left.astype(np.uint16) * 16, right.astype(np.uint16) * 16, np.eye(4))
    assert len(out) > 0
    with pytest.raises(ValueError, match="calibration"):
        sd.process(1.2, left[:100], right[:100], np.eye(4))
    # measure (ELAS, no pose) then update (filter, with the pose) == process: the node matches
    # a pair while its pose is still being tracked
    sa = StereoDepth(cam, {"elas": {"disp_max": 64, "subsampling": False}, "tau": 0.02, "stride": 1})
    sb = StereoDepth(cam, {"elas": {"disp_max": 64, "subsampling": False}, "tau": 0.02, "stride": 1})
    for i in range(3):
        T = make_T(np.eye(3), [0.01 * i, 0, 0])
        oa = sa.process(0.1 * i, left, right, T)
        ob = sb.update(0.1 * i, sb.measure(left, right), T)
        np.testing.assert_array_equal(oa.points, ob.points)
        np.testing.assert_array_equal(oa.variance, ob.variance)
    assert ob.timings["total"] >= ob.timings["elas"] + ob.timings["filter"] - 1e-9
    # ELAS-only through the same entry point; a DepthConfig as well as a mapping
    sd0 = StereoDepth(cam, DepthConfig(temporal=False, stride=1, elas=ElasConfig(disp_max=48)))
    assert sd0.matcher.params["disp_max"] == 48 and sd0.matcher.params["subsampling"]
    out0 = sd0.process(0.0, left, right, np.eye(4))
    assert len(out0) == int(np.count_nonzero(np.isfinite(out0.depth)))


def test_stereo_depth_rectifies_raw_images():
    """A camera pair that needs rectification: the remap tables are applied before ELAS."""
    from mdr_slam.camera import CameraModel
    w, h = 160, 120
    K = np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]])
    D = np.array([0.05, 0, 0, 0, 0])
    Pl = np.hstack([K, np.zeros((3, 1))])
    Pr = Pl.copy()
    Pr[0, 3] = -100.0 * 0.2
    cam = StereoCamera(CameraModel(w, h, K, D, np.eye(3), Pl), CameraModel(w, h, K, D, np.eye(3), Pr))
    assert not cam.is_rectified
    left, right = _textured_pair(h, w, 16, seed=3)
    sd = StereoDepth(cam, {"temporal": False, "elas": {"disp_max": 64}, "stride": 1})
    Z, var, grey, t = sd.measure(left, right)
    rl, rr = cam.rectify(left, right)
    np.testing.assert_array_equal(grey, rl)
    Z2, _, grey2, _ = sd.measure(rl, rr, rectified=True)
    np.testing.assert_array_equal(grey2, rl)
    np.testing.assert_array_equal(np.isfinite(Z), np.isfinite(Z2))


def test_texture_dependent_disparity_noise():
    from mdr_slam.depth import disparity_sigma
    rng = np.random.default_rng(8)
    grey = np.full((48, 64), 128, np.uint8)
    grey[:, 32:] = rng.integers(0, 255, (48, 32))            # right half textured
    s = disparity_sigma(grey, sigma_d=0.3, texture_k=1.0)
    assert s.shape == grey.shape and np.all(s >= 0.3 - 1e-6)
    assert np.median(s[:, 40:60]) < 0.35                        # textured: ~ sigma_d
    assert np.median(s[:, 5:25]) > 10.0                         # flat: matching is worth little
    assert disparity_sigma(grey, 0.3, 0.0) == 0.3
    cam = tiny_camera()
    Z, var = measurement_from_disparity(np.full((48, 64), 15.0, np.float32), cam, s)
    np.testing.assert_allclose(np.sqrt(var), Z ** 2 * s / (cam.fx * cam.baseline), rtol=1e-5)


def test_pose_cache_interpolates_and_never_extrapolates():
    from mdr_slam.depth import PoseCache
    from mdr_slam.geometry import rotation_angle
    c = PoseCache(max_age=5.0, max_gap=0.25)
    c.add(1.0, pose(x=0.0))
    c.add(1.2, pose(x=0.2, yaw_deg=10.0))
    np.testing.assert_allclose(c.lookup(1.0), pose(x=0.0))
    T = c.lookup(1.1)
    np.testing.assert_allclose(T[:3, 3], [0.1, 0, 0], atol=1e-9)
    assert np.isclose(np.degrees(rotation_angle(T[:3, :3])), 5.0)
    assert c.lookup(1.3) is None and c.lookup(0.9) is None      # outside: no extrapolation
    c.add(2.0, pose(x=1.0))
    assert c.lookup(1.6) is None                                 # gap 0.8 s > max_gap
    c.add(9.0, pose())
    assert len(c) == 1                                           # older than max_age dropped


def test_discontinuity_mask_drops_flying_pixels_only():
    """A box edge in front of a wall: the ramp ELAS interpolates between them is dropped, the
    smooth (even slanted) surfaces on either side are kept."""
    from mdr_slam.depth.stereo_depth import mask_discontinuities
    d = np.tile(np.linspace(20.0, 22.0, 60, dtype=np.float32), (40, 1))  # slanted wall
    d[:, 30:] += 15.0                                                     # a box in front
    d[:, 29] = 27.0                                                       # interpolated ramp
    d[0, 0] = -1.0                                                        # invalid stays invalid
    out = mask_discontinuities(d, max_step=3.0, radius=2)
    assert np.all(out[:, 27:32] < 0)          # within 2 px of the edge: removed
    assert np.all(out[1:, :25] > 0) and np.all(out[:, 32:] > 0)
    np.testing.assert_array_equal(out[1:, :25], d[1:, :25])
    assert out[0, 0] < 0


def test_elas_matcher_does_not_keep_its_inputs():
    """pyelas keeps a reference to every array it is given; the matcher must not hand it the
    caller's images, or every frame stays in memory (the live node grew 14 MB/s)."""
    import sys
    from mdr_slam.depth import ElasMatcher
    rng = np.random.default_rng(0)
    m = ElasMatcher({"subsampling": True})
    left = rng.integers(0, 255, (120, 160), dtype=np.uint8)
    right = np.roll(left, -5, axis=1)
    before = (sys.getrefcount(left), sys.getrefcount(right))
    for _ in range(3):
        m.compute(left, right)
    assert (sys.getrefcount(left), sys.getrefcount(right)) == before


def test_error_correlation_tells_noise_from_a_surface_bias():
    """scripts/eval_depth_sim.py --correlation: independent per-frame disparity noise has ~0
    frame-to-frame correlation and the two-frame mean shrinks by ~sqrt(2); an error attached to
    the surface (what ELAS's interpolation does on weak texture) correlates ~1 across frames and
    no temporal average removes it."""
    import os
    import sys
    from conftest import ROOT
    sys.path.insert(0, os.path.join(ROOT, "scripts"))
    from eval_depth_sim import error_correlation
    cam = tiny_camera()
    w, h = cam.size
    fB = cam.fx * cam.baseline
    rng = np.random.default_rng(3)
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))

    def frames(bias):
        out = []
        for i in range(12):
            T = pose(x=0.01 * i)
            Z = plane_depth(cam, T)
            if bias:   # a fixed pattern on the wall (a function of the map x, y of the pixel)
                xm = (u - cam.cx) / cam.fx * Z + T[0, 3]
                ym = (v - cam.cy) / cam.fy * Z
                e = 0.8 * np.sin(7.0 * xm) * np.cos(5.0 * ym)
            else:
                e = rng.normal(0.0, 0.8, Z.shape)
            disp = (fB / Z + e).astype(np.float32)
            out.append((T, disp, np.zeros((h, w), np.uint8), Z.astype(np.float32),
                        np.ones((h, w), np.uint8)))
        return out

    noise = error_correlation(cam, frames(False), 1, lags=(1, 5), starts=(0,), stride=1)
    bias = error_correlation(cam, frames(True), 1, lags=(1, 5), starts=(0,), stride=1)
    assert len(noise) == 2 and len(bias) == 2
    for _, _, n, c, rms1, rms2 in noise:
        assert n > 1000 and abs(c) < 0.1 and rms2 < 0.8 * rms1
    for _, _, n, c, rms1, rms2 in bias:
        assert n > 1000 and c > 0.9 and rms2 > 0.95 * rms1


def test_depth_honours_the_principal_point_difference():
    """A right camera whose cx differs from the left's (ROS CameraInfo allows it; KITTI's calib
    is 0.2 px off): a measured disparity d means Z = f*B / (d - doffs) (image_geometry getZ)."""
    base = tiny_camera()
    cam = base.with_doffs(0.5)
    assert cam.doffs == pytest.approx(0.5) and base.doffs == 0.0
    assert cam.is_rectified and cam.right.K[0, 2] == pytest.approx(base.cx - 0.5)
    fB = cam.fx * cam.baseline
    disp = np.full((48, 64), 15.5, np.float32)
    disp[0, 0] = -10.0        # libelas invalid stays invalid
    disp[0, 1] = 0.4          # positive, but at or behind infinity once corrected
    Z, var = measurement_from_disparity(disp, cam, sigma_d=0.5, min_depth=0.2, max_depth=100.0)
    assert np.isclose(Z[5, 5], fB / 15.0)
    assert np.all(np.isnan(Z[0, :2])) and np.all(np.isnan(var[0, :2]))
    Z2 = cam.disparity_to_depth(disp)
    assert np.isclose(Z2[5, 5], fB / 15.0) and np.all(np.isnan(Z2[0, :2]))
    assert np.isclose(base.disparity_to_depth(disp)[5, 5], fB / 15.5)
