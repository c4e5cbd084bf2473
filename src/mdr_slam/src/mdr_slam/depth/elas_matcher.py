"""Single-frame stereo depth with libelas (paper section 3.3.1) and its measurement model.

``ElasMatcher`` wraps Geiger's libelas through PyPI ``pyelas`` (module ``elas``): support points on
textured pixels, a Delaunay prior and dense MAP matching. It returns the left disparity image.

``measurement_from_disparity`` turns a disparity into a depth measurement with a variance, the
input of the temporal filter: Z = f*B/d and, from a disparity error of ``sigma_d`` pixels
(first-order propagation of Z = f*B/d), sigma_Z = Z^2 * sigma_d / (f*B). The quadratic growth
with depth is why the filter keeps its state in inverse depth (see ``depth.filter``).
"""
from __future__ import annotations

from typing import Dict, Mapping, Optional, Tuple, Union

import numpy as np

from ..camera import StereoCamera
from .config import ElasConfig

__all__ = ["ElasMatcher", "ELAS_PRESETS", "measurement_from_disparity", "disparity_sigma",
           "texture_gradient2", "to_gray8"]

# libelas' two presets (Elas::parameters(ROBOTICS / MIDDLEBURY) of libelas' elas.h), as data:
# ElasMatcher sets every parameter from the table, then ElasConfig's disp_min, disp_max and
# subsampling (our defaults: a 128 px search covers Z >= f*B/128, 0.4 m for f=450 px, B=0.11 m;
# subsampling pairs with the filter's stride 2, which reads only every 2nd pixel anyway: the same
# filtered accuracy and density on the simulator, scripts/eval_depth_sim.py, and ELAS + filter
# reach 10 Hz on one core at 752x480). tests/depth/test_depth.py checks the tables against pyelas.
ELAS_PRESETS: Dict[str, Dict[str, object]] = {
    "robotics": {
        "support_threshold": 0.85, "support_texture": 10, "candidate_stepsize": 5,
        "incon_window_size": 5, "incon_threshold": 5, "incon_min_support": 5,
        "add_corners": False, "grid_size": 20, "beta": 0.02, "gamma": 3.0, "sigma": 1.0,
        "sradius": 2.0, "match_texture": 1, "lr_threshold": 2, "speckle_sim_threshold": 1.0,
        "speckle_size": 200, "ipol_gap_width": 3, "filter_median": False,
        "filter_adaptive_mean": True, "postprocess_only_left": True,
    },
    "middlebury": {
        "support_threshold": 0.95, "support_texture": 10, "candidate_stepsize": 5,
        "incon_window_size": 5, "incon_threshold": 5, "incon_min_support": 5,
        "add_corners": True, "grid_size": 20, "beta": 0.02, "gamma": 5.0, "sigma": 1.0,
        "sradius": 3.0, "match_texture": 0, "lr_threshold": 2, "speckle_sim_threshold": 1.0,
        "speckle_size": 200, "ipol_gap_width": 5000, "filter_median": True,
        "filter_adaptive_mean": False, "postprocess_only_left": False,
    },
}


def to_gray8(img: np.ndarray, scale: Optional[float] = None) -> np.ndarray:
    """Contiguous uint8 grey image as libelas needs: colour -> grey (BGR order), 16-bit and float
    scaled by ``scale`` (default: 255 / max, so 10/12-bit cameras use the full range)."""
    a = np.asarray(img)
    if a.ndim == 3:
        import cv2
        if a.shape[2] == 1:
            a = a[:, :, 0]
        else:
            a = cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_BGRA2GRAY if a.shape[2] == 4
                             else cv2.COLOR_BGR2GRAY)
    if a.ndim != 2:
        raise ValueError("image must be HxW or HxWxC, got shape %s" % (a.shape,))
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    af = a.astype(np.float32)
    if scale is None:
        m = float(np.nanmax(af)) if af.size else 0.0
        scale = 255.0 / m if m > 0 else 1.0
    return np.ascontiguousarray(np.clip(np.nan_to_num(af) * scale, 0, 255).astype(np.uint8))


class ElasMatcher:
    """libelas with an :class:`~mdr_slam.depth.config.ElasConfig` (or a mapping of its fields):
    the preset's table (:data:`ELAS_PRESETS`), then the config's disparity range and subsampling.
    ``params`` holds every libelas parameter as set (and ``preset``).
    With ``subsampling`` libelas matches every 2nd pixel (about 3x faster); the result is brought
    back to full size (nearest) so callers always get an HxW disparity.
    """

    def __init__(self, config: Union[None, ElasConfig, Mapping] = None):
        import elas
        self.cfg = cfg = ElasConfig.of(config)
        values = dict(ELAS_PRESETS[cfg.preset], disp_min=cfg.disp_min, disp_max=cfg.disp_max,
                      subsampling=cfg.subsampling)
        self._elas = elas.Elas()
        self._buffers = None  # persistent input buffers (see compute)
        for k, v in values.items():
            setattr(self._elas, k, v)
        self.params = {k: getattr(self._elas, k) for k in values}
        self.params["preset"] = cfg.preset

    def compute(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """Left disparity (float32 HxW, pixels; <= 0 invalid) of a rectified grey pair."""
        if left.shape[:2] != right.shape[:2]:
            raise ValueError("left %s and right %s image sizes differ" % (left.shape, right.shape))
        if left.dtype != np.uint8 or right.dtype != np.uint8:
            # one scale for both images, so the pair stays photometrically consistent
            m = max(float(np.nanmax(left)), float(np.nanmax(right)), 1e-9)
            left, right = to_gray8(left, 255.0 / m), to_gray8(right, 255.0 / m)
        else:
            left, right = to_gray8(left), to_gray8(right)
        h, w = left.shape
        # pyelas 1.0.1 takes a reference to its two input arrays on every call and never releases
        # it, so every frame's images would stay in memory for ever (measured: +1 MB per call,
        # the live depth node grew 14 MB/s). Handing it the same two buffers each time bounds the
        # leak to those buffers; the copy costs two memcpy of the image.
        if self._buffers is None or self._buffers[0].shape != (h, w):
            self._buffers = (np.empty((h, w), np.uint8), np.empty((h, w), np.uint8))
        bl, br = self._buffers
        np.copyto(bl, left)
        np.copyto(br, right)
        disp = self._elas.process(bl, br)[0]
        if disp.shape != (h, w):  # subsampling: every 2nd pixel -> nearest back to full size
            import cv2
            disp = cv2.resize(disp, (w, h), interpolation=cv2.INTER_NEAREST)
        return np.asarray(disp, dtype=np.float32)


TEXTURE_WINDOW = 5   # px, window of the texture measure of the measurement model


def texture_gradient2(grey: np.ndarray, window: int = TEXTURE_WINDOW) -> np.ndarray:
    """Mean squared horizontal gradient (grey levels^2/px^2) over a ``window`` box: the texture
    along the epipolar line that a matching window of that size sees."""
    import cv2
    g = np.asarray(grey, dtype=np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) * np.float32(1.0 / 8.0)
    return cv2.boxFilter(gx * gx, -1, (window, window))


def disparity_sigma(grey: np.ndarray, sigma_d: float = 0.5, texture_k: float = 0.0,
                    window: int = TEXTURE_WINDOW, g2: Optional[np.ndarray] = None
                    ) -> Union[float, np.ndarray]:
    """Per-pixel disparity noise (px): sigma_d^2 + (texture_k / g)^2, g = RMS horizontal gradient
    (grey levels/px) over a ``window`` box, the matching window's texture along the epipolar line.

    This is the photometric disparity error of LSD-SLAM (Engel et al. 2013): a matching cost that
    changes by g per pixel of shift localizes the match to sigma_I / g pixels, so on a painted wall
    (g ~ the sensor noise) ELAS' disparity is worth little, on a poster it is sub-pixel. Measured on
    the simulator: textured pixels (g ~ 7) have a 0.2 px median error, low-texture ones (g ~ 1)
    0.7 px with a heavy tail. ``texture_k = 0`` gives the constant ``sigma_d``.
    """
    if texture_k <= 0:
        return float(sigma_d)
    if g2 is None:   # the caller may have it already (texture_gradient2 of grey over window)
        g2 = texture_gradient2(grey, window)
    return np.sqrt(np.float32(sigma_d) ** 2 +
                   np.float32(texture_k) ** 2 / np.maximum(g2, np.float32(1e-4))).astype(np.float32)


def measurement_from_disparity(disp: np.ndarray, camera: StereoCamera,
                               sigma_d: Union[float, np.ndarray] = 0.5, min_depth: float = 0.2,
                               max_depth: float = 10.0) -> Tuple[np.ndarray, np.ndarray]:
    """(Z, var) float32 HxW from a disparity: Z = f*B/(d - doffs), var = (Z^2 * sigma_d / (f*B))^2 (m^2).

    ``sigma_d`` (px) is a constant or an HxW map (:func:`disparity_sigma`). Invalid (d <= 0: no
    match, occluded or left-right inconsistent in libelas) and out-of-range pixels are NaN in
    both. ``max_depth`` matters: beyond it one pixel of disparity is many metres.
    """
    d = np.asarray(disp, dtype=np.float32)
    fB = np.float32(camera.fx * camera.baseline)
    doffs = np.float32(getattr(camera, "doffs", 0.0))   # cx_left - cx_right (StereoCamera.doffs)
    with np.errstate(divide="ignore", invalid="ignore"):
        Z = fB / (d - doffs) if doffs else fB / d
        ok = (d > 0) & (Z > 0) & np.isfinite(Z) & (Z >= min_depth) & (Z <= max_depth)
        Z = np.where(ok, Z, np.float32(np.nan)).astype(np.float32)
        sZ = Z * Z * np.asarray(sigma_d, dtype=np.float32) / fB
    return Z, (sZ * sZ).astype(np.float32)
