"""Node 2's whole per-frame computation in one call: rectify -> ELAS (and SGBM on weak texture) ->
measurement -> filter.

Both the depth node and the offline runner (``mdr run``) call :class:`StereoDepth`, so the live
and the offline figures describe the same computation.
"""
from __future__ import annotations

import time
from typing import Mapping, Optional, Union

import numpy as np

from ..camera import StereoCamera
from .config import DepthConfig
from .elas_matcher import (ElasMatcher, disparity_sigma, measurement_from_disparity,
                           texture_gradient2, to_gray8)
from .filter import DepthFilter, DepthOutput
from .weak_texture import WeakTextureMatcher, combine_weak_texture

__all__ = ["StereoDepth", "mask_discontinuities"]


def mask_discontinuities(disp: np.ndarray, max_step: float, radius: int = 2) -> np.ndarray:
    """``disp`` with pixels near a depth discontinuity set invalid (-1).

    ELAS interpolates its support-point triangulation across object borders, so pixels between a
    foreground edge and the background get disparities of neither ("flying pixels"). They are
    consistent from frame to frame, so the temporal filter cannot average them away and they
    would land in the map as veils. A pixel whose (2r+1)^2 neighbourhood spans more than
    ``max_step`` pixels of disparity is dropped (min/max filters, vectorized).
    """
    import cv2
    valid = disp > 0
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    dmax = cv2.dilate(np.where(valid, disp, 0).astype(np.float32), k)
    dmin = cv2.erode(np.where(valid, disp, np.float32(1e6)).astype(np.float32), k)
    out = np.array(disp, dtype=np.float32, copy=True)
    out[valid & (dmax - dmin > max_step)] = -1.0
    return out


class StereoDepth:
    """Rectify -> ELAS -> (Z, var) -> DepthFilter, with per-stage timings (ms) in ``timings``.

    With ``weak_texture: sgbm`` and the temporal filter on, a second matcher
    (:class:`~mdr_slam.depth.weak_texture.WeakTextureMatcher`) gives the weak-texture pixels'
    disparities; the ELAS-only baseline (``temporal: false``) stays ELAS alone.

    ``config``: a :class:`~mdr_slam.depth.config.DepthConfig` or a mapping of its fields
    (``StereoDepth(camera, {"tau": 0.02, "elas": {"disp_max": 64}})``); None: the defaults."""

    def __init__(self, camera: StereoCamera,
                 config: Union[None, DepthConfig, Mapping] = None):
        self.camera = camera
        self.cfg = DepthConfig.of(config)
        self.matcher = ElasMatcher(self.cfg.elas)
        self.weak_matcher = WeakTextureMatcher(self.cfg.elas.disp_max) \
            if self.cfg.temporal and self.cfg.weak_texture == "sgbm" else None
        self.filter = DepthFilter(camera, self.cfg)
        if not camera.is_rectified:
            camera.rectify_maps()   # remap tables computed once, up front

    def reset(self) -> None:
        self.filter.reset()

    def set_keyframe_pose(self, T_map_kf: np.ndarray, keyframe_id: Optional[int] = None) -> bool:
        return self.filter.set_keyframe_pose(T_map_kf, keyframe_id)

    def correct_keyframe(self, T_old: np.ndarray, T_new: np.ndarray,
                         keyframe_id: Optional[int] = None) -> bool:
        return self.filter.correct_keyframe(T_old, T_new, keyframe_id)

    def measure(self, left: np.ndarray, right: np.ndarray, rectified: bool = False):
        """(Z, var, left_rectified_grey, timings) of one pair, without the filter."""
        w, h = self.camera.size
        if left.shape[:2] != (h, w) or right.shape[:2] != (h, w):
            raise ValueError("images are %s and %s, the calibration says %dx%d"
                             % (left.shape[:2][::-1], right.shape[:2][::-1], w, h))
        t = {}
        t0 = time.perf_counter()
        if left.dtype != np.uint8 or right.dtype != np.uint8 or left.ndim == 3 or right.ndim == 3:
            m = max(float(np.nanmax(left)), float(np.nanmax(right)), 1e-9)
            s = None if (left.dtype == np.uint8 and right.dtype == np.uint8) else 255.0 / m
            left, right = to_gray8(left, s), to_gray8(right, s)
        if not rectified:
            left, right = self.camera.rectify(left, right)
        t1 = time.perf_counter()
        disp = self.matcher.compute(left, right)
        t2 = time.perf_counter()
        weak = self.weak_matcher.compute(left, right) if self.weak_matcher is not None else None
        t3 = time.perf_counter()
        Z, var = self.measurement(disp, left, weak)
        t4 = time.perf_counter()
        t["rectify"] = 1e3 * (t1 - t0)
        t["elas"] = 1e3 * (t2 - t1)
        if weak is not None:
            t["weak_texture"] = 1e3 * (t3 - t2)
        t["measurement"] = 1e3 * (t4 - t3)
        return Z, var, left, t

    def measurement(self, disp: np.ndarray, grey: np.ndarray,
                    weak_disp: Optional[np.ndarray] = None):
        """(Z, var) of a disparity with this configuration's noise model; ``weak_disp``: the
        weak-texture matcher's disparity, taken on the weak-texture pixels."""
        c = self.cfg
        if c.max_disparity_step > 0:
            disp = mask_discontinuities(disp, c.max_disparity_step, c.discontinuity_radius)
            if weak_disp is not None:
                weak_disp = mask_discontinuities(weak_disp, c.max_disparity_step,
                                                 c.discontinuity_radius)
        g2 = texture_gradient2(grey) if weak_disp is not None else None
        sigma = disparity_sigma(grey, c.sigma_d, c.sigma_d_texture, g2=g2)
        if weak_disp is not None:
            disp, sigma = combine_weak_texture(disp, sigma, weak_disp, grey,
                                               c.weak_texture_gradient, c.sigma_d,
                                               c.sigma_d_texture, g2=g2)
        return measurement_from_disparity(disp, self.camera, sigma, c.min_depth, c.max_depth)

    def single_frame(self, measurement: tuple, max_sigma: float = float("inf")) -> DepthOutput:
        """``measure``'s result as points in the left camera, without a pose or the filter
        (:meth:`DepthFilter.single_frame`): obstacle sensing while the tracker is LOST."""
        Z, var, grey, t = measurement
        out = self.filter.single_frame(Z, var, grey, max_sigma)
        out.timings = dict(t)
        out.depth = Z
        return out

    def process(self, stamp: float, left: np.ndarray, right: np.ndarray, T_map_cam: np.ndarray,
                rectified: bool = False, new_keyframe: Optional[bool] = None,
                keyframe_id: Optional[int] = None) -> DepthOutput:
        """One stereo pair with the left camera pose -> DepthOutput (points in the left camera)."""
        return self.update(stamp, self.measure(left, right, rectified), T_map_cam, new_keyframe,
                           keyframe_id)

    def update(self, stamp: float, measurement: tuple, T_map_cam: np.ndarray,
               new_keyframe: Optional[bool] = None,
               keyframe_id: Optional[int] = None) -> DepthOutput:
        """The temporal filter's step on ``measure``'s result: ELAS needs no pose, so a node can
        match a pair while the pose of that frame is still being tracked."""
        Z, var, grey, t = measurement
        t = dict(t)
        t1 = time.perf_counter()
        out = self.filter.process(stamp, T_map_cam, Z, var, grey, new_keyframe, keyframe_id)
        t["filter"] = 1e3 * (time.perf_counter() - t1)
        t["total"] = t.get("rectify", 0.0) + t.get("elas", 0.0) + t.get("weak_texture", 0.0) + \
            t.get("measurement", 0.0) + t["filter"]
        out.timings = t
        out.depth = Z
        return out
