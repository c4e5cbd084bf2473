"""Depth from the motion between keyframes: the epipolar search of a keyframe's hypotheses in
earlier keyframes' images (depth/motion_stereo.py) and its place in the filter."""
from __future__ import annotations

import numpy as np

from mdr_slam.camera import StereoCamera
from mdr_slam.depth import DepthConfig, DepthFilter
from mdr_slam.depth.motion_stereo import MotionStereo
from mdr_slam.geometry import make_T

WALL_Z = 6.0      # a wall facing the camera 6 m away: beyond what the rig's stereo converges


def camera():
    # the simulator's rig: f = 458 px, B = 0.11 m (one px of disparity at 6 m: 12 %)
    return StereoCamera.from_rectified(752, 480, 458.0, 458.0, 375.5, 239.5, 0.11)


def texture(rng, n=2048, amplitude=40.0):
    """A smooth random albedo (grey levels) on the wall, 1 texel = 1 cm."""
    import cv2
    t = cv2.GaussianBlur(rng.normal(0, 1, (n, n)).astype(np.float32), (0, 0), 3.0)
    return (128 + amplitude * t / t.std()).astype(np.float32)


def render(cam, T_map_cam, tex, rng, noise=2.0):
    """Grey image of the wall z_map = WALL_Z (texture centred on x = y = 0) from T_map_cam."""
    import cv2
    w, h = cam.size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    ray = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)
    rm = ray @ T_map_cam[:3, :3].T
    s = (WALL_Z - T_map_cam[2, 3]) / rm[..., 2]
    X = T_map_cam[:3, 3] + rm * s[..., None]
    n = tex.shape[0]
    mx = (X[..., 0] * 100 + n / 2).astype(np.float32)
    my = (X[..., 1] * 100 + n / 2).astype(np.float32)
    img = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return img + rng.normal(0, noise, img.shape).astype(np.float32)


def grid(cam, step=12, margin=60):
    w, h = cam.size
    u, v = np.meshgrid(np.arange(margin, w - margin, step, dtype=np.float32),
                       np.arange(margin, h - margin, step, dtype=np.float32))
    u, v = u.ravel(), v.ravel()
    return u, v, (u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy


def searched(tex_amplitude, rng, prior_error=0.05, noise=2.0):
    """The keyframe at x = 1.2 m, earlier keyframes at x = 0, 0.4, 0.8 m (a robot driving along
    the wall); hypotheses 5 % off the truth with a 10 % sigma, as one frame of the rig gives."""
    cam = camera()
    tex = texture(rng, amplitude=tex_amplitude)
    ms = MotionStereo(cam, max_depth=20.0, min_depth=0.3)
    for x in (0.0, 0.4, 0.8):
        T = make_T(np.eye(3), [x, 0.0, 0.0])
        ms.remember(T, render(cam, T, tex, rng, noise))
    T_kf = make_T(np.eye(3), [1.2, 0.0, 0.0])
    u, v, rx, ry = grid(cam)
    rho_true = np.full(len(u), 1.0 / WALL_Z, np.float32)
    mu = (rho_true * (1 + prior_error)).astype(np.float32)
    var = ((0.10 * mu) ** 2).astype(np.float32)
    stats = {}
    idx, y, R = ms.measure(T_kf, render(cam, T_kf, tex, rng, noise), u, v, rx, ry, mu, var,
                           stats)
    return idx, y, R, rho_true, stats, len(u)


def test_a_textured_far_wall_is_measured_within_its_uncertainty():
    rng = np.random.default_rng(3)
    idx, y, R, rho_true, stats, n = searched(40.0, rng)
    assert len(idx) > 0.8 * n, stats
    z = (y - rho_true[idx]) / np.sqrt(R)
    # a wide baseline: sigma_Z/Z about 1 % at 6 m, where one frame of the rig gives about 16 %
    assert np.median(np.sqrt(R) / y) < 0.02
    assert np.median(np.abs(y - rho_true[idx]) / rho_true[idx]) < 0.01
    assert np.mean(np.abs(z) > 3) < 0.02
    assert np.median(np.abs(z)) < 0.67      # the variance is not too small (on strong texture,
    #                                         the matching error is below the model's)


def test_a_faint_far_wall_is_measured_where_it_can_be_and_within_its_uncertainty():
    """A painted wall: 4 grey levels of albedo under 2 of sensor noise."""
    rng = np.random.default_rng(7)
    idx, y, R, rho_true, stats, n = searched(4.0, rng)
    print("faint wall: %d of %d measured, %s" % (len(idx), n, stats))
    assert len(idx) > 0.3 * n, stats
    z = (y - rho_true[idx]) / np.sqrt(R)
    assert np.mean(np.abs(z) > 3) < 0.03
    assert np.median(np.abs(z)) < 0.9


def test_segments_of_different_lengths_are_each_measured_at_their_own_depth():
    """Hypotheses of different certainty (segments of 10-60 px: searched with different numbers
    of samples) on a wall seen obliquely (depths 5-9.6 m across the image): every measurement is
    its own pixel's depth, whatever group it was searched in."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(11)
    cam = camera()
    tex = texture(rng, amplitude=40.0)
    R = Rotation.from_euler("y", 25.0, degrees=True).as_matrix()
    ms = MotionStereo(cam, max_depth=20.0, min_depth=0.3)
    for x in (0.0, 0.4, 0.8):
        T = make_T(R, [x, 0.0, 0.0])
        ms.remember(T, render(cam, T, tex, rng))
    T_kf = make_T(R, [1.2, 0.0, 0.0])
    u, v, rx, ry = grid(cam)
    rz = R[2, 0] * rx + R[2, 1] * ry + R[2, 2]
    rho_true = (rz / (WALL_Z - T_kf[2, 3])).astype(np.float32)     # 1 / depth along the axis
    assert 1 / rho_true.max() < 5.5 and 1 / rho_true.min() > 9.0
    rel_sigma = np.linspace(0.03, 0.15, len(u)).astype(np.float32)
    rng.shuffle(rel_sigma)
    mu = (rho_true * (1 + rel_sigma * rng.uniform(-1, 1, len(u)))).astype(np.float32)
    var = ((rel_sigma * mu) ** 2).astype(np.float32)
    stats = {}
    idx, y, Rv = ms.measure(T_kf, render(cam, T_kf, tex, rng), u, v, rx, ry, mu, var, stats)
    assert len(idx) > 0.6 * len(u), stats
    assert len(np.unique(np.round(rel_sigma[idx], 2))) > 5         # short and long segments
    rel_err = np.abs(y - rho_true[idx]) / rho_true[idx]
    assert np.median(rel_err) < 0.01 and np.percentile(rel_err, 99) < 0.05
    z = (y - rho_true[idx]) / np.sqrt(Rv)
    assert np.mean(np.abs(z) > 3) < 0.03


def test_a_blank_wall_gives_no_measurement():
    rng = np.random.default_rng(4)
    idx, y, R, rho_true, stats, n = searched(0.0, rng)     # sensor noise only
    assert len(idx) <= 0.01 * n, stats


def test_a_blank_wall_is_not_searched():
    """Patches flatter than the noise cannot match: they cost nothing."""
    rng = np.random.default_rng(4)
    *_, stats, n = searched(0.0, rng, noise=0.5)
    assert stats["motion_flat"] > 0.9 * n and stats["motion_searched"] == 0, stats


def test_the_budget_goes_to_pixels_that_two_earlier_views_see(monkeypatch):
    """The first MOTION_MAX_PIXELS hypotheses that can be searched are, whatever comes before
    them: pixels outside the earlier views (the robot drove to the left along the wall: the
    left of the keyframe's image is wall the earlier keyframes did not see) do not use up the
    budget."""
    import mdr_slam.depth.motion_stereo as ms_module
    cam = camera()
    rng = np.random.default_rng(6)
    tex = texture(rng)
    ms = MotionStereo(cam, max_depth=20.0, min_depth=0.3)
    for x in (2.4, 2.0, 1.6):
        T = make_T(np.eye(3), [x, 0.0, 0.0])
        ms.remember(T, render(cam, T, tex, rng))
    T_kf = make_T(np.eye(3), [0.0, 0.0, 0.0])
    u, v, rx, ry = grid(cam, step=8)
    outside = u < 140          # at most one earlier view saw the wall there
    order = np.concatenate([np.flatnonzero(outside), np.flatnonzero(~outside)])
    u, v, rx, ry = u[order], v[order], rx[order], ry[order]
    mu = np.full(len(u), 1.0 / WALL_Z, np.float32)
    budget = int(min(outside.sum(), (~outside).sum()) // 2)
    monkeypatch.setattr(ms_module, "MOTION_MAX_PIXELS", budget)
    stats = {}
    idx, y, _ = ms.measure(T_kf, render(cam, T_kf, tex, rng), u, v, rx, ry, mu,
                           (0.1 * mu) ** 2, stats)
    assert stats["motion_searched"] == budget, stats
    assert len(idx) > 0.8 * budget and idx.min() >= outside.sum()
    assert np.median(np.abs(y * WALL_Z - 1)) < 0.01


def test_without_two_earlier_views_nothing_is_searched():
    cam = camera()
    rng = np.random.default_rng(5)
    tex = texture(rng)
    ms = MotionStereo(cam, max_depth=20.0, min_depth=0.3)
    T0 = make_T(np.eye(3), [0.0, 0.0, 0.0])
    ms.remember(T0, render(cam, T0, tex, rng))
    T_kf = make_T(np.eye(3), [1.0, 0.0, 0.0])
    u, v, rx, ry = grid(cam)
    mu = np.full(len(u), 1.0 / WALL_Z, np.float32)
    idx, _, _ = ms.measure(T_kf, render(cam, T_kf, tex, rng), u, v, rx, ry, mu, (0.1 * mu) ** 2)
    assert len(idx) == 0


def test_a_correction_moves_the_earlier_keyframes_with_the_current_one():
    """A loop closure moves the keyframe: the earlier ones keep their poses relative to it."""
    cam = camera()
    ms = MotionStereo(cam, max_depth=20.0, min_depth=0.3)
    T0 = make_T(np.eye(3), [0.0, 0.0, 0.0])
    ms.remember(T0, np.zeros((240, 320), np.float32))
    D = make_T(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), [2.0, 1.0, 0.0])
    ms.correct(D)
    np.testing.assert_allclose(ms.history[0][0], D @ T0)


def test_the_filter_converges_a_far_wall_with_motion_stereo_only():
    """The filter on the wall 6 m away, moving along it at half resolution: the rig's own
    measurements (one px of disparity noise: 24 % at 6 m) never converge to tau; with motion
    stereo the wall's pixels do, close to the truth."""
    cam = StereoCamera.from_rectified(376, 240, 229.0, 229.0, 187.5, 119.5, 0.11)   # half size
    rng = np.random.default_rng(6)
    tex = texture(rng)
    fB = cam.fx * cam.baseline

    def run(motion):
        f = DepthFilter(cam, DepthConfig(motion_stereo=motion, kf_translation=0.3,
                                         sigma_d_texture=0.0, sigma_d=1.0))
        z = []
        for i in range(24):
            T = make_T(np.eye(3), [0.1 * i, 0.0, 0.0])
            grey = render(cam, T, tex, rng)
            d = fB / WALL_Z + rng.normal(0, 1.0, grey.shape)
            Z = (fB / d).astype(np.float32)
            var = ((Z ** 2 / fB) ** 2).astype(np.float32)      # sigma_d = 1 px
            z.append(f.process(0.1 * i, T, Z, var, grey).points[:, 2])
        return np.concatenate(z)

    without, z = run(False), run(True)
    print("published over the run: %d without motion stereo, %d with" % (len(without), len(z)))
    assert len(without) < 0.01 * len(z)
    assert len(z) > 1000
    assert np.median(np.abs(z - WALL_Z)) < 0.05
    assert np.mean(np.abs(z - WALL_Z) > 0.3) < 0.01
