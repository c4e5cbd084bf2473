"""Weak-texture matching: SGBM on the pixels where ELAS has too little texture."""
from __future__ import annotations

import numpy as np
import pytest

from mdr_slam.camera import StereoCamera
from mdr_slam.config import ConfigError
from mdr_slam.depth import DepthConfig, StereoDepth
from mdr_slam.depth.weak_texture import WINDOW, WeakTextureMatcher, combine_weak_texture

H, W = 240, 376


def weak_pair(disparity, amplitude, noise, seed=0, left_half_textured=False, oversample=8):
    """A fronto-parallel wall of constant (sub-pixel, a multiple of 1/oversample) disparity: smooth
    noise of ``amplitude`` grey levels (texels of 2 px) on grey 170, rendered ``oversample`` times
    finer and averaged into pixels (both images filtered alike), plus ``noise`` of sensor noise."""
    import cv2
    rng = np.random.default_rng(seed)
    big = rng.normal(0, 1, (H // 2 + 2, (W + 200) // 2 + 2)).astype(np.float32)
    hr = cv2.resize(big, None, fx=2 * oversample, fy=2 * oversample,
                    interpolation=cv2.INTER_CUBIC)[:H * oversample]
    hr = hr / hr.std()
    if left_half_textured:
        hr[:, : hr.shape[1] // 2] *= 12.0
    hr = 170.0 + amplitude * hr
    x0, s = 50 * oversample, int(round(disparity * oversample))
    L = cv2.resize(hr[:, x0: x0 + W * oversample], (W, H), interpolation=cv2.INTER_AREA)
    R = cv2.resize(hr[:, x0 + s: x0 + s + W * oversample], (W, H), interpolation=cv2.INTER_AREA)
    L = np.clip(L + rng.normal(0, noise, L.shape), 0, 255).astype(np.uint8)
    R = np.clip(R + rng.normal(0, noise, R.shape), 0, 255).astype(np.uint8)
    return L, R


def interior(d):
    return d[20:-20, 100:-20]


def test_sgbm_on_a_weak_texture_wall_is_sub_pixel_and_unbiased():
    # sub-pixel disparities on a wall of 4 grey levels of texture and 1 of noise: each within a
    # pixel's 0.4, and no bias over a pixel's fractions (a slanted wall has them all)
    matcher = WeakTextureMatcher(64)
    errors = []
    for i, true_d in enumerate(np.arange(20.0, 21.0, 0.125)):
        L, R = weak_pair(true_d, amplitude=4.0, noise=1.0, seed=i)
        ds = interior(matcher.compute(L, R))
        assert ds.shape == interior(L).shape and ds.dtype == np.float32
        ok = ds > 0
        assert ok.mean() > 0.8
        assert np.mean(np.abs(ds[ok] - true_d) < 0.5) > 0.9
        errors.append(np.median(ds[ok]) - true_d)
    assert max(abs(e) for e in errors) <= 0.4
    assert abs(np.mean(errors)) < 0.05


def test_combination_takes_the_weak_matcher_only_on_weak_texture():
    L, _ = weak_pair(20.0, amplitude=4.0, noise=1.0, left_half_textured=True)
    disp = np.full(L.shape, 10.0, np.float32)
    weak = np.full(L.shape, 20.0, np.float32)
    d, s = combine_weak_texture(disp, np.float32(0.5), weak, L, min_gradient=3.0, sigma_d=0.5,
                                texture_k=1.0)
    # the textured half keeps ELAS' disparity and sigma, the weak half gets SGBM's with the
    # variance of its larger window (texture term x (5 / WINDOW)^2)
    assert np.all(d[:, 40:120] == 10.0) and np.all(s[:, 40:120] == np.float32(0.5))
    assert np.mean(d[:, 260:360] == 20.0) > 0.8
    from mdr_slam.depth.elas_matcher import texture_gradient2
    assert np.array_equal(d == 20.0, texture_gradient2(L) < 9.0)    # RMS gradient below 3
    sw = s[:, 260:360][d[:, 260:360] == 20.0]
    assert np.all(sw > 0.5)
    from mdr_slam.depth import disparity_sigma
    s5 = disparity_sigma(L, 0.5, 1.0)[:, 260:360][d[:, 260:360] == 20.0]
    assert np.median(sw) < np.median(s5)


def test_stereo_depth_uses_it_with_the_filter_only():
    cam = StereoCamera.from_rectified(W, H, 230.0, 230.0, W / 2, H / 2, 0.11)
    assert StereoDepth(cam).weak_matcher is not None                     # the default
    assert StereoDepth(cam, {"weak_texture": "off"}).weak_matcher is None
    # the ELAS-only baseline stays ELAS alone
    assert StereoDepth(cam, {"temporal": False}).weak_matcher is None
    L, R = weak_pair(20.5, amplitude=4.0, noise=1.0)
    Z, var, _, t = StereoDepth(cam).measure(L, R, rectified=True)
    assert "weak_texture" in t
    z = interior(Z)
    ok = np.isfinite(z)
    assert ok.mean() > 0.8
    assert abs(230.0 * 0.11 / np.median(z[ok]) - 20.5) < 0.4     # in disparity (px)


def test_config_checks_the_matcher_name():
    with pytest.raises(ConfigError):
        DepthConfig(weak_texture="census")
    assert DepthConfig(weak_texture="off").weak_texture == "off"
    assert WINDOW == 13
