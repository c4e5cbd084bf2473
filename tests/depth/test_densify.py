"""Planar densification (depth/densify.py) on synthetic inverse-depth grids with known planes."""
from __future__ import annotations

import numpy as np

from mdr_slam.camera import StereoCamera
from mdr_slam.depth import DepthFilter
from mdr_slam.depth.densify import plane_fill

GH, GW = 120, 160
F = 150.0


def grid():
    u, v = np.meshgrid(np.arange(GW, dtype=float), np.arange(GH, dtype=float))
    return (u - GW / 2) / F, (v - GH / 2) / F


def plane_rho(rx, ry, n, d):
    """Inverse depth of the plane n.P = d along the rays (rx, ry, 1)."""
    return (n[0] * rx + n[1] * ry + n[2]) / d


def noisy_state(rho_true, rel_sigma, rng, n_obs=5):
    """A non-converged filter state: inverse depth with relative noise rel_sigma, that variance."""
    rho = rho_true * (1 + rng.normal(0, rel_sigma, rho_true.shape))
    var = (rel_sigma * rho_true) ** 2
    return (rho.astype(np.float32), var.astype(np.float32),
            np.full(rho_true.shape, n_obs, np.int32))


def converge_some(rho, var, rho_true, rng, share=0.1, rel_sigma=0.003):
    """A random ``share`` of the pixels converged (texture here and there): accurate to
    ``rel_sigma``. They are the planes' support; returns their mask."""
    conv = rng.random(rho_true.shape) < share
    rho[conv] = rho_true[conv] * (1 + rng.normal(0, rel_sigma, conv.sum()))
    var[conv] = (rel_sigma * rho_true[conv]) ** 2
    return conv


def test_noisy_wall_with_a_hole_is_filled_with_the_plane():
    rx, ry = grid()
    rng = np.random.default_rng(1)
    n = np.array([0.3, -0.1, 1.0])
    n /= np.linalg.norm(n)
    truth = plane_rho(rx, ry, n, 3.0)                 # a slanted wall about 3 m away
    rho, var, nobs = noisy_state(truth, 0.04, rng)    # 4 % per pixel: far from tau = 1 %
    conv = converge_some(rho, var, truth, rng)        # the support: a converged tenth
    hole = np.zeros((GH, GW), bool)
    hole[50:60, 70:82] = True                         # no hypothesis at all there (ELAS hole)
    rho[hole], var[hole], nobs[hole], conv[hole] = np.nan, np.inf, 0, False
    fill, rf, vf, st = plane_fill(rx, ry, rho, var, nobs, conv)
    assert st["planes"] >= 1
    assert fill[~conv].mean() > 0.9, "a noisy planar wall must be filled almost everywhere"
    assert fill[hole].mean() > 0.9, "small holes inside the plane's region are filled"
    z_err = np.abs(1 / rf[fill] - 1 / truth[fill]) / (1 / truth[fill])
    assert np.percentile(z_err, 99) < 0.01, "the plane is far more accurate than one pixel (4 %)"
    # the filled variance is honest: relative sigma of the filled depth at least the floor
    assert np.all(np.sqrt(vf[fill]) / rf[fill] >= 0.0099)
    # converged pixels are never overwritten
    assert not np.any(fill & conv)
    # without converged support nothing is filled: the non-converged hypotheses carry ELAS's
    # interpolation errors, planar in inverse depth too
    fill0, _, _, st0 = plane_fill(rx, ry, rho, var, nobs, np.zeros((GH, GW), bool))
    assert not fill0.any() and st0["planes"] == 0


def test_plane_from_converged_support_fills_around_it_and_priors_fill_without_it():
    rx, ry = grid()
    rng = np.random.default_rng(5)
    truth = plane_rho(rx, ry, np.array([-0.2, 0.0, 1.0]) / np.hypot(0.2, 1.0), 3.5)
    rho, var, nobs = noisy_state(truth, 0.03, rng)
    conv = np.zeros((GH, GW), bool)
    conv[40:70, 60:90] = True                     # a textured poster: converged, accurate
    rho[conv] = truth[conv] * (1 + rng.normal(0, 0.003, conv.sum()))
    var[conv] = (0.003 * truth[conv]) ** 2
    params = {"densify_max_dist": 30}
    fill, rf, vf, st = plane_fill(rx, ry, rho, var, nobs, conv, params)
    assert st["planes"] == 1 and len(st["new_planes"]) == 1
    rel = np.abs(rf[fill] / truth[fill] - 1)
    assert np.percentile(rel, 99) < 0.01
    # filled around the poster up to max_dist cells, not beyond
    yy, xx = np.mgrid[0:GH, 0:GW]
    near = (np.maximum(np.maximum(40 - yy, yy - 69), 0) ** 2 +
            np.maximum(np.maximum(60 - xx, xx - 89), 0) ** 2) <= 25 ** 2
    assert fill[near & ~conv].mean() > 0.9
    far = (np.abs(yy - 55) > 50) | (np.abs(xx - 75) > 50)
    assert not fill[far].any()
    # no converged pixel at all: nothing is filled, unless a remembered plane agrees
    conv0 = np.zeros((GH, GW), bool)
    rho0, var0, nobs0 = noisy_state(truth, 0.03, rng)
    fill0, _, _, st0 = plane_fill(rx, ry, rho0, var0, nobs0, conv0, params)
    assert not fill0.any()
    fill1, rf1, _, st1 = plane_fill(rx, ry, rho0, var0, nobs0, conv0, params,
                                    priors=st["new_planes"])
    assert st1.get("priors_used") == 1 and fill1.mean() > 0.9
    assert np.percentile(np.abs(rf1[fill1] / truth[fill1] - 1), 99) < 0.01
    # a remembered plane that this keyframe's estimates contradict fills nothing
    wrong = [np.asarray(st["new_planes"][0]) * 1.2]   # the same wall 20 % nearer
    fill2, _, _, _ = plane_fill(rx, ry, rho0, var0, nobs0, conv0, params, priors=wrong)
    assert fill2.mean() < 0.02


def test_two_planes_and_a_depth_step_are_not_merged():
    rx, ry = grid()
    rng = np.random.default_rng(2)
    wall = plane_rho(rx, ry, np.array([0.0, 0.0, 1.0]), 4.0)          # wall at 4 m
    box = plane_rho(rx, ry, np.array([0.0, 0.0, 1.0]), 2.5)           # box face at 2.5 m
    floor_n = np.array([0.0, -1.0, 0.0])                               # floor 1 m below (y down)
    with np.errstate(divide="ignore", invalid="ignore"):
        floor = plane_rho(rx, ry, floor_n, -1.0)
    truth = wall.copy()
    low = ry > 0.25                                 # lower image: the floor, in front of the wall
    truth[low] = np.maximum(floor[low], wall[low])
    boxm = (np.abs(rx) < 0.15) & (np.abs(ry + 0.1) < 0.12)
    truth[boxm] = box[boxm]
    rho, var, nobs = noisy_state(truth, 0.03, rng)
    conv = converge_some(rho, var, truth, rng)
    fill, rf, vf, st = plane_fill(rx, ry, rho, var, nobs, conv)
    assert st["planes"] >= 2
    assert fill[~conv].mean() > 0.7
    z = 1 / rf[fill]
    zt = 1 / truth[fill]
    rel = np.abs(z - zt) / zt
    # nothing is filled with the wrong plane: no pixel of the box gets the wall's depth or back
    assert np.percentile(rel, 99.5) < 0.04, np.percentile(rel, 99.5)
    assert np.max(rel) < 0.10
    # the step itself (box border): where filled, within tolerance (checked above) -- and the
    # box face is filled with its own plane
    assert fill[boxm].mean() > 0.6


def test_non_planar_region_is_not_filled():
    rx, ry = grid()
    rng = np.random.default_rng(3)
    # a bumpy surface: depth varies by +-15 % in a pattern no plane explains, with small variance
    truth = 1 / (3.0 * (1 + 0.15 * np.sin(rx * 80) * np.cos(ry * 70)))
    rho, var, nobs = noisy_state(truth, 0.01, rng)
    conv = converge_some(rho, var, truth, rng)
    fill, rf, vf, st = plane_fill(rx, ry, rho, var, nobs, conv)
    if fill.any():
        rel = np.abs(1 / rf[fill] - 1 / truth[fill]) * truth[fill]
        assert np.percentile(rel, 95) < 0.04
    assert fill.mean() < 0.2


def test_filter_publishes_planar_fills_flagged_with_zero_observations():
    # a wall 3 m away, textured only in a patch: elsewhere the disparity noise is large and the
    # pixels do not converge on their own in 6 frames; the plane the patch converges on fills them
    cam = StereoCamera.from_rectified(160, 120, F, F, 79.5, 59.5, 0.1)   # f*B = 15 px*m
    fB = cam.fx * cam.baseline
    Z_true = np.full((120, 160), 3.0)
    sigma_d = np.full(Z_true.shape, 0.4)                     # 8 % per frame
    sigma_d[40:80, 60:100] = 0.02                            # the textured patch: 0.4 %
    params = {"tau": 0.01, "min_obs": 3, "process_noise": 0.0, "kf_max_frames": 100,
              "densify_every": 1, "densify_max_dist": 0, "stride": 1}
    outs = {}
    for mode in ("off", "plane"):
        f = DepthFilter(cam, dict(params, densify=mode))
        r = np.random.default_rng(4)
        for i in range(6):
            d = fB / Z_true + r.normal(0, 1, Z_true.shape) * sigma_d
            Z = (fB / d).astype(np.float32)
            var = ((Z ** 2) * sigma_d / fB) ** 2
            out = f.process(0.1 * i, np.eye(4), Z, var.astype(np.float32))
        outs[mode] = out
    n = 160 * 120
    assert 0.07 * n < len(outs["off"]) < 0.1 * n            # the patch alone converges
    dense = outs["plane"]
    filled = dense.n_obs == 0
    assert filled.sum() > 0.8 * n                            # 0: no limit to the distance
    assert np.all(np.abs(dense.points[filled, 2] - 3.0) < 0.05)
    assert dense.stats["n_densified"] == int(filled.sum())
