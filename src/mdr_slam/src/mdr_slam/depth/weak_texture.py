"""Weak-texture matching: OpenCV's semi-global matcher where ELAS has too little texture.

On a painted wall ELAS' disparity is not only noisy but biased, and the bias repeats from frame to
frame (the same support points, the same Delaunay prior), so the temporal filter averages nothing
away and such pixels never converge. On the simulator's walls ELAS' median disparity error is
-0.28 px (office) and -0.41 px (corridor), this matcher's +0.03 and -0.04. On the weak-texture
pixels (RMS x-gradient below 2 grey levels/px) of the Middlebury pairs: ELAS -0.12, -0.17 and
-0.25 px (venus, teddy, cones), this matcher 0.00, 0.00 and -0.06; it has fewer pixels off by more
than 1 px on tsukuba and venus, more on teddy and cones. :class:`WeakTextureMatcher` runs
StereoSGBM with a larger window than ELAS' (the walls' texture is fine-grained noise that a larger
window integrates) and :func:`combine_weak_texture` takes its disparity on the weak pixels, with
the variance of its larger window.
"""
from __future__ import annotations

from typing import Optional, Tuple, Union

import numpy as np

from .elas_matcher import TEXTURE_WINDOW, texture_gradient2

__all__ = ["WeakTextureMatcher", "combine_weak_texture"]

# StereoSGBM on every 2nd row (each the mean of two image rows: the filter's stride-2 grid reads
# every 2nd row anyway) at full horizontal resolution, where the disparity's precision lies, with
# a BLOCK x BLOCK window (BLOCK x 2 BLOCK px of the image, where the walls' fine-grained texture
# is integrated); smoothness penalties as OpenCV's documentation suggests (8 and 32 x window
# area), a left-right check of 1 px and a uniqueness margin of 5 %. About 27 ms per 752x480 pair
# on one core (ELAS: 23 ms). Half resolution in both directions (8 ms) did as well on the
# simulator but worse than ELAS on the Middlebury pairs: the horizontal resolution is kept.
ROW_SCALE = 0.5
BLOCK = 9
UNIQUENESS = 5
LR_MAX_DIFF = 1
WINDOW = 13   # px, the side of a square of the window's image area (9 x 18): its noise model


class WeakTextureMatcher:
    """StereoSGBM on a rectified grey pair, every 2nd row; ``compute`` returns the left
    disparity of every pixel (float32 HxW, <= 0 invalid), like ElasMatcher."""

    def __init__(self, disp_max: int = 128):
        import cv2
        n = int(np.ceil(max(16, disp_max) / 16.0)) * 16   # SGBM wants a multiple of 16
        self._sgbm = cv2.StereoSGBM_create(
            minDisparity=0, numDisparities=n, blockSize=BLOCK, P1=8 * BLOCK * BLOCK,
            P2=32 * BLOCK * BLOCK, disp12MaxDiff=LR_MAX_DIFF, uniquenessRatio=UNIQUENESS,
            mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)

    def compute(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        import cv2
        h, w = left.shape[:2]
        size = (w, max(1, int(round(h * ROW_SCALE))))
        ls = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
        rs = cv2.resize(right, size, interpolation=cv2.INTER_AREA)
        d = self._sgbm.compute(ls, rs).astype(np.float32) * np.float32(1.0 / 16.0)  # fixed point
        return cv2.resize(d, (w, h), interpolation=cv2.INTER_NEAREST)


def combine_weak_texture(disp: np.ndarray, sigma: Union[float, np.ndarray], weak_disp: np.ndarray,
                         grey: np.ndarray, min_gradient: float, sigma_d: float, texture_k: float,
                         window: int = WINDOW, g2: Optional[np.ndarray] = None
                         ) -> Tuple[np.ndarray, np.ndarray]:
    """``(disparity, sigma)``: ``weak_disp`` and its sigma where the RMS x-gradient over 5x5 is
    below ``min_gradient``, ``disp`` and ``sigma`` elsewhere. The weak matcher's sigma is
    :func:`~mdr_slam.depth.elas_matcher.disparity_sigma`'s model over its own ``window``: the
    gradient energy of window^2 pixels instead of 5^2, so the texture term shrinks by
    (5 / window)^2. ``g2``: :func:`texture_gradient2` of ``grey`` if the caller has it."""
    if g2 is None:
        g2 = texture_gradient2(grey)
    weak = g2 < np.float32(min_gradient) ** 2
    g2w = texture_gradient2(grey, window)
    kw = np.float32(texture_k * TEXTURE_WINDOW / float(window))
    sw = np.sqrt(np.float32(sigma_d) ** 2 + kw * kw / np.maximum(g2w, np.float32(1e-4)))
    d = np.where(weak, weak_disp, disp).astype(np.float32)
    s = np.where(weak, sw, np.asarray(sigma, dtype=np.float32)).astype(np.float32)
    return d, s
