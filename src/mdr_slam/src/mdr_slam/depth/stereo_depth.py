"""Node 2's whole per-frame computation in one call: rectify -> ELAS -> measurement -> filter.

Both the depth node and the offline runner (``mdr run``) call :class:`StereoDepth`, so the live
and the offline figures describe the same computation.
"""
from __future__ import annotations

import time
from typing import Dict, Optional

import numpy as np

from ..camera import StereoCamera
from .elas_matcher import (ELAS_DEFAULTS, ElasMatcher, disparity_sigma, measurement_from_disparity,
                           to_gray8)
from .filter import FILTER_DEFAULTS, DepthFilter, DepthOutput

__all__ = ["StereoDepth", "DEPTH_DEFAULTS", "mask_discontinuities"]

# Flat parameters (config/depth.yaml); ``elas`` is the dict of libelas parameters.
DEPTH_DEFAULTS: Dict[str, object] = dict(FILTER_DEFAULTS)
DEPTH_DEFAULTS.update({
    "sigma_d": 0.5,             # disparity noise (px) of an ELAS match -> measurement variance
    "sigma_d_texture": 1.0,     # > 0: add (k / local gradient)^2 (low texture = worse match)
    "max_disparity_step": 3.0,  # px; > 0: mask pixels near depth discontinuities (see below)
    "discontinuity_radius": 2,  # px; the neighbourhood of that test ((2r+1)^2 window)
    "elas": dict(ELAS_DEFAULTS),
})


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


def split_params(params: Optional[dict]):
    """(ELAS dict, measurement+filter dict) from the flat parameters; ``elas_<name>`` keys
    override ``elas: {<name>: ...}`` so one value can be changed from the command line."""
    params = dict(params or {})
    elas_p = dict(params.pop("elas", None) or {})
    for k in list(params):
        if k.startswith("elas_"):
            elas_p[k[5:]] = params.pop(k)
    return elas_p, params


class StereoDepth:
    """Rectify -> ELAS -> (Z, var) -> DepthFilter, with per-stage timings (ms) in ``timings``."""

    def __init__(self, camera: StereoCamera, params: Optional[dict] = None):
        self.camera = camera
        elas_p, p = split_params(params)
        self.params = dict(DEPTH_DEFAULTS)
        self.params.update(p)
        self.matcher = ElasMatcher(elas_p)
        self.params["elas"] = dict(self.matcher.params)
        self.filter = DepthFilter(camera, self.params)
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
        p = self.params
        Z, var = self.measurement(disp, left)
        t3 = time.perf_counter()
        t["rectify"] = 1e3 * (t1 - t0)
        t["elas"] = 1e3 * (t2 - t1)
        t["measurement"] = 1e3 * (t3 - t2)
        return Z, var, left, t

    def measurement(self, disp: np.ndarray, grey: np.ndarray):
        """(Z, var) of a disparity with this configuration's noise model."""
        p = self.params
        if p["max_disparity_step"] > 0:
            disp = mask_discontinuities(disp, p["max_disparity_step"], p["discontinuity_radius"])
        sigma = disparity_sigma(grey, p["sigma_d"], p["sigma_d_texture"])
        return measurement_from_disparity(disp, self.camera, sigma, p["min_depth"], p["max_depth"])

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
        t["total"] = t.get("rectify", 0.0) + t.get("elas", 0.0) + t.get("measurement", 0.0) + \
            t["filter"]
        out.timings = t
        out.depth = Z
        return out
