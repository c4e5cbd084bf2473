"""Depth from the motion between keyframes: the unconverged hypotheses of a new keyframe are
searched along their epipolar segments in earlier keyframes' images, whose baselines (0.3-2.5 m)
are several times the rig's.

With an 11 cm baseline, one frame's sigma_Z/Z passes the filter's ``tau`` only to about 3.5 m, so
a hall's walls never converge from the rig alone. The motion between keyframes is the wider
baseline, as in LSD-SLAM's keyframe stereo and REMODE / SVO's depth filter:

- the search range of a pixel is its hypothesis' mu +- 3 sigma (inverse depth), sampled in inverse
  depth along the epipolar segment in the earlier image (any direction: forward motion needs no
  rectification; near the epipole the segment is short and carries no information, so it is
  skipped);
- the cost is ZNCC of a patch warped by the local affine map of the two views (fronto-parallel at
  the hypothesis), on pre-smoothed images;
- a match counts only when it is an interior, distinct peak (the best minus the best away from it)
  in two earlier keyframes that agree within their uncertainty: a wrong match does not become a
  wall;
- its inverse-depth variance comes from the segment's pixels per unit inverse depth, the matching
  error, the relative pose's rotation and baseline errors and the sampling step.

The result is one measurement per pixel, fused by the same chi-square-gated Kalman update as the
rig's (:meth:`~mdr_slam.depth.filter.DepthFilter._fuse`).
"""
from __future__ import annotations

import warnings
from collections import deque
from typing import Dict, Optional, Tuple

import numpy as np

from ..geometry import inv_T

__all__ = ["MotionStereo"]

MOTION_HISTORY = 8              # earlier keyframes kept (smoothed grey image + pose)
MOTION_MIN_BASELINE = 0.25      # m across the ray: below it the rig's own stereo does as well
MOTION_MAX_BASELINE = 2.5       # m: beyond it the two views of a wall look too different
MOTION_MAX_ANGLE_DEG = 20.0     # deg between the two rays to a point (patch similarity)
MOTION_GRID_STEP = 2            # search every 2nd filter-grid cell in x and y (cost / 4)
MOTION_MAX_PIXELS = 8000        # hypotheses searched per keyframe at most (the first ones given
                                # that two earlier keyframes can see)
MOTION_PATCH = 5                # samples per side of the matching patch ...
MOTION_PATCH_STEP = 2.0         # ... this many px apart: a 9 px window (faint texture needs area)
MOTION_BLUR_SIGMA = 1.0         # px, Gaussian pre-smoothing of both images (sensor noise)
MOTION_STEP_PX = 2.0            # px between inverse-depth samples along a segment (the ZNCC
                                # peak of a 9 px window is wider) ...
MOTION_MIN_SAMPLES = 8          # ... at least this many samples (short segments)
MOTION_SAMPLES = 64             # ... at most this many (MOTION_MAX_SEGMENT_PX / MOTION_STEP_PX)
MOTION_MIN_SEGMENT_PX = 4.0     # shorter segment: this view adds little to the hypothesis
MOTION_MAX_SEGMENT_PX = 128.0   # longer: steps over 2 px would miss the peak (the widest
                                # baselines, the far walls' precision, need the length)
MOTION_MIN_ZNCC = 0.8
MOTION_MIN_PATCH_STD = 1.5      # grey levels: flatter reference patches are not searched
MOTION_MIN_MARGIN = 0.1         # best ZNCC minus the best one away from the peak
MOTION_PEAK_EXCLUSION_PX = 4.0  # px either side of the peak that belong to it
MOTION_VIEWS = 3                # earlier keyframes searched per pixel at most (the widest baselines)
MOTION_MIN_VIEWS = 2            # agreeing views a measurement needs
MOTION_CHI2_AGREE = 6.63        # a view agrees: (rho - median)^2 <= this * (its var + the best var)
MOTION_MATCH_SIGMA_PX = 0.2     # px, matching error floor of a distinct ZNCC peak ...
MOTION_NOISE_GREY = 0.5         # ... plus this (grey levels) over the gradient along the line
MOTION_POSE_SIGMA_DEG = 0.05    # deg, relative rotation error between two keyframes
MOTION_POSE_SIGMA_REL = 0.005   # relative baseline error between two keyframes
MOTION_BORDER_PX = 6.0          # segments must stay this far inside the earlier image


def _smooth(grey: np.ndarray) -> np.ndarray:
    import cv2
    return cv2.GaussianBlur(np.asarray(grey, dtype=np.float32), (0, 0), MOTION_BLUR_SIGMA)


def _sample(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at float positions (..., P) (cv2.remap, whose maps stay under
    32767 rows: taken in blocks of rows)."""
    import cv2
    shape = x.shape
    P = shape[-1]
    mx = np.ascontiguousarray(x, dtype=np.float32).reshape(-1, P)
    my = np.ascontiguousarray(y, dtype=np.float32).reshape(-1, P)
    out = np.empty(mx.shape, np.float32)
    block = 32000
    for i in range(0, len(mx), block):
        out[i:i + block] = cv2.remap(img, mx[i:i + block], my[i:i + block], cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(shape)


def _gradients(img: np.ndarray):
    import cv2
    return (cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) * np.float32(0.125),
            cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) * np.float32(0.125))


def _zncc(ref: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """ZNCC of reference patches (N, P) with candidate patches (N, K, P) -> (N, K), from sums
    (no centred copy of the candidates)."""
    P = ref.shape[1]
    r = ref - ref.mean(axis=1, keepdims=True)
    num = np.einsum("np,nkp->nk", r, cand)          # sum r_c * c = sum r_c * (c - mean c)
    s1 = cand.sum(axis=2)
    s2 = np.einsum("nkp,nkp->nk", cand, cand)
    var_c = np.maximum(s2 - s1 * s1 / P, 0.0)
    den = np.sqrt((r * r).sum(axis=1))[:, None] * np.sqrt(var_c)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = num / den
    return np.where(den > 1e-6, z, -1.0).astype(np.float32)


class MotionStereo:
    """Keeps the last keyframes' images and poses; :meth:`measure` searches a new keyframe's
    hypotheses in them. ORB-SLAM2 has no dense counterpart; this is REMODE's epipolar search with
    LSD-SLAM's variance, between keyframes."""

    def __init__(self, camera, max_depth: float, min_depth: float):
        self.camera = camera
        self.max_depth = float(max_depth)
        self.min_depth = float(min_depth)
        self.history: deque = deque(maxlen=MOTION_HISTORY)   # (T_map_kf, smoothed grey)
        h = MOTION_PATCH // 2
        o = np.arange(-h, h + 1, dtype=np.float32) * np.float32(MOTION_PATCH_STEP)
        ou, ov = np.meshgrid(o, o)
        self._ou, self._ov = ou.ravel(), ov.ravel()

    def reset(self) -> None:
        self.history.clear()

    def correct(self, D: np.ndarray) -> None:
        """A rigid correction ``D`` (map <- map) of the current keyframe (BA, loop closure) applies
        to the earlier ones too, so that their relative poses stay what tracking measured."""
        self.history = deque(((D @ T, g) for T, g in self.history), maxlen=MOTION_HISTORY)

    def remember(self, T_map_kf: np.ndarray, grey: np.ndarray) -> None:
        self.history.append((np.array(T_map_kf, dtype=float), _smooth(grey)))

    # ------------------------------------------------------------------ the search
    def measure(self, T_map_kf: np.ndarray, grey: np.ndarray, u: np.ndarray, v: np.ndarray,
                rx: np.ndarray, ry: np.ndarray, mu: np.ndarray, var: np.ndarray,
                stats: Optional[Dict[str, float]] = None
                ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inverse-depth measurements of hypotheses at keyframe pixels (u, v) (rays rx, ry with
        unit z; inverse depth ``mu`` with variance ``var``), in the order given: the first
        MOTION_MAX_PIXELS that MOTION_MIN_VIEWS earlier keyframes see are searched (choosing
        before the views are known spent most of the budget on pixels no two views see; the
        segments' geometry costs little next to the search). Returns (index into the inputs,
        measurement, its variance) of the pixels matched in MOTION_MIN_VIEWS agreeing earlier
        keyframes."""
        stats = {} if stats is None else stats
        empty = (np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.float32))
        stats.update(motion_searched=0, motion_matched=0)
        if len(self.history) < 2 or len(u) == 0:
            return empty
        ref_img = _smooth(grey)
        sd = np.sqrt(var)
        lo = np.maximum(mu - 3 * sd, 1.0 / self.max_depth).astype(np.float32)
        hi = np.minimum(mu + 3 * sd, 1.0 / self.min_depth).astype(np.float32)
        ok = hi > lo
        # per earlier keyframe: the segment's length in px (0 where the view is unusable)
        views = []
        for T_map_h, img in self.history:
            views.append(self._segments(inv_T(T_map_h) @ T_map_kf, rx, ry, lo, hi, mu) + (img,))
        length = np.stack([v_[0] for v_ in views])          # (H, N)
        length[:, ~ok] = 0
        # the most informative usable views per pixel (longest segments: widest baselines)
        order = np.argsort(-length, axis=0)[:MOTION_VIEWS]
        n_usable = (length > 0).sum(axis=0)
        cand = np.flatnonzero(n_usable >= MOTION_MIN_VIEWS)
        # a patch flatter than the noise cannot reach MOTION_MIN_ZNCC anywhere: not searched
        pu, pv = u[cand, None] + self._ou, v[cand, None] + self._ov
        ref = _sample(ref_img, pu, pv)                                              # (M, P)
        textured = np.flatnonzero(ref.std(axis=1) >= MOTION_MIN_PATCH_STD)
        stats["motion_flat"] = int(len(cand) - len(textured))
        keep = textured[:MOTION_MAX_PIXELS]
        cand, pu, pv, ref = cand[keep], pu[keep], pv[keep], ref[keep]
        stats["motion_searched"] = int(len(cand))
        if len(cand) == 0:
            return empty
        gx, gy = _gradients(ref_img)
        ref_gx, ref_gy = _sample(gx, pu, pv), _sample(gy, pu, pv)
        V = order.shape[0]
        rho = np.full((V, len(cand)), np.nan, np.float32)
        rvar = np.full((V, len(cand)), np.inf, np.float32)
        for k in range(V):
            hsel = order[k, cand]
            live = length[hsel, cand] > 0
            for h in np.unique(hsel[live]):
                m = np.flatnonzero(live & (hsel == h))
                idx = cand[m]
                _, A, Tr, img = views[h]
                g2 = self._epipolar_gradient2(Tr, rx[idx], ry[idx], ref_gx[m], ref_gy[m])
                rho[k, m], rvar[k, m] = self._search(Tr, img, ref[m], rx[idx], ry[idx], lo[idx],
                                                     hi[idx], length[h, idx], A[:, idx], g2)
        # consensus: the views that agree with the median of the matched ones
        found = np.isfinite(rho)
        with warnings.catch_warnings(), np.errstate(invalid="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)      # all-NaN columns: no match
            med = np.nanmedian(np.where(found, rho, np.nan), axis=0)
            vmin = np.where(found, rvar, np.inf).min(axis=0)
            agree = found & ((rho - med) ** 2 <= MOTION_CHI2_AGREE * (rvar + vmin))
        n_agree = agree.sum(axis=0)
        sel = np.flatnonzero(n_agree >= MOTION_MIN_VIEWS)
        w = np.where(agree, 1.0 / rvar, 0.0)[:, sel]
        y = (w * np.nan_to_num(rho[:, sel])).sum(axis=0) / w.sum(axis=0)
        R = 1.0 / w.sum(axis=0)
        stats["motion_matched"] = int(len(sel))
        stats["motion_too_few_views"] = int(np.count_nonzero(found.any(axis=0))) - int(len(sel))
        return cand[sel], y.astype(np.float32), R.astype(np.float32)

    def _project(self, Tr: np.ndarray, rx, ry, rho):
        """Pixel of the keyframe ray (rx, ry, 1) at inverse depth ``rho`` in the view ``Tr``
        (view <- keyframe), and the homogeneous depth (positive in front)."""
        c = self.camera
        R, t = Tr[:3, :3].astype(np.float32), Tr[:3, 3].astype(np.float32)
        ax = R[0, 0] * rx + R[0, 1] * ry + R[0, 2] + t[0] * rho
        ay = R[1, 0] * rx + R[1, 1] * ry + R[1, 2] + t[1] * rho
        az = R[2, 0] * rx + R[2, 1] * ry + R[2, 2] + t[2] * rho
        with np.errstate(divide="ignore", invalid="ignore"):
            return c.fx * ax / az + c.cx, c.fy * ay / az + c.cy, az

    def _segments(self, Tr: np.ndarray, rx, ry, lo, hi, mu):
        """(segment length in px, 0 where unusable; affine patch map (4, N); Tr) of one view."""
        c = self.camera
        w, h = c.size
        b = MOTION_BORDER_PX + MOTION_PATCH_STEP * (MOTION_PATCH // 2) * 1.5
        u0, v0, z0 = self._project(Tr, rx, ry, lo)
        u1, v1, z1 = self._project(Tr, rx, ry, hi)
        length = np.hypot(u1 - u0, v1 - v0)
        inside = (z0 > 0) & (z1 > 0) & (u0 >= b) & (u0 <= w - 1 - b) & (v0 >= b) & \
            (v0 <= h - 1 - b) & (u1 >= b) & (u1 <= w - 1 - b) & (v1 >= b) & (v1 <= h - 1 - b)
        # baseline across the ray and the angle between the two rays at the hypothesis
        t = inv_T(Tr)[:3, 3]                                 # view's centre in the keyframe
        d = np.stack([rx, ry, np.ones_like(rx)], 0)
        d = d / np.linalg.norm(d, axis=0)
        along = t @ d
        b_perp = np.sqrt(np.maximum(float(t @ t) - along ** 2, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            angle = np.degrees(np.arctan2(b_perp * mu, 1.0 - along * mu))
        use = inside & (b_perp >= MOTION_MIN_BASELINE) & (b_perp <= MOTION_MAX_BASELINE) & \
            (angle <= MOTION_MAX_ANGLE_DEG) & (length >= MOTION_MIN_SEGMENT_PX) & \
            (length <= MOTION_MAX_SEGMENT_PX)
        # affine map of keyframe pixel offsets into the view, fronto-parallel at the hypothesis
        um, vm, _ = self._project(Tr, rx, ry, mu)
        uu, vu, _ = self._project(Tr, rx + 1.0 / c.fx, ry, mu)
        uv, vv, _ = self._project(Tr, rx, ry + 1.0 / c.fy, mu)
        A = np.stack([uu - um, uv - um, vu - vm, vv - vm]).astype(np.float32)
        return np.where(use, length, 0.0).astype(np.float32), A, Tr

    def _epipolar_gradient2(self, Tr, rx, ry, gx, gy) -> np.ndarray:
        """Mean squared gradient of the reference patches along their epipolar lines (towards the
        other view's centre), grey levels^2 / px^2."""
        c = inv_T(Tr)[:3, 3].astype(np.float32)      # the view's centre in the keyframe
        dx = (c[0] - c[2] * rx) * np.float32(self.camera.fx)
        dy = (c[1] - c[2] * ry) * np.float32(self.camera.fy)
        n = np.maximum(np.hypot(dx, dy), 1e-9)
        g = gx * (dx / n)[:, None] + gy * (dy / n)[:, None]
        return (g * g).mean(axis=1)

    def _search(self, Tr, img, ref, rx, ry, lo, hi, length, A, g2):
        """Best inverse depth (NaN when no distinct interior peak) and its variance. Samples are
        MOTION_STEP_PX apart along each segment: pixels are searched in groups of the same
        number of samples."""
        K = np.clip(np.ceil(length / MOTION_STEP_PX).astype(np.int64) + 1, MOTION_MIN_SAMPLES,
                    MOTION_SAMPLES)
        K = np.minimum(-(-K // 4) * 4, MOTION_SAMPLES)        # a few group sizes, not one per K
        out = np.full(len(ref), np.nan, np.float32)
        rvar = np.full(len(ref), np.inf, np.float32)
        for k in np.unique(K):
            m = np.flatnonzero(K == k)
            out[m], rvar[m] = self._search_k(int(k), Tr, img, ref[m], rx[m], ry[m], lo[m], hi[m],
                                             length[m], A[:, m], g2[m])
        return out, rvar

    def _search_k(self, K, Tr, img, ref, rx, ry, lo, hi, length, A, g2):
        """:meth:`_search` for pixels searched with ``K`` samples."""
        s = np.linspace(0.0, 1.0, K, dtype=np.float32)
        rho = lo[:, None] + (hi - lo)[:, None] * s[None, :]           # (M, K)
        uc, vc, _ = self._project(Tr, rx[:, None], ry[:, None], rho)
        pu = uc[:, :, None] + (A[0][:, None, None] * self._ou + A[1][:, None, None] * self._ov)
        pv = vc[:, :, None] + (A[2][:, None, None] * self._ou + A[3][:, None, None] * self._ov)
        M = len(ref)
        ar = np.arange(M)
        cost = _zncc(ref, _sample(img, pu, pv))                        # (M, K)
        k = np.argmax(cost, axis=1)
        c0 = cost[ar, k]
        excl = np.ceil(MOTION_PEAK_EXCLUSION_PX * (K - 1) / np.maximum(length, 1e-6))
        far = np.abs(np.arange(K)[None, :] - k[:, None]) > excl[:, None]
        c_other = np.where(far, cost, -1.0).max(axis=1)
        good = (c0 >= MOTION_MIN_ZNCC) & (c0 - c_other >= MOTION_MIN_MARGIN) & (k > 0) & \
            (k < K - 1)
        km, kp = np.maximum(k - 1, 0), np.minimum(k + 1, K - 1)
        cm, cp = cost[ar, km], cost[ar, kp]
        den = cm - 2 * c0 + cp
        with np.errstate(divide="ignore", invalid="ignore"):
            delta = np.clip(np.where(den < 0, 0.5 * (cm - cp) / den, 0.0), -0.5, 0.5)
        step = (hi - lo) / (K - 1)
        out = lo + (k + delta) * step
        # variance: px of error over px per unit inverse depth, plus the baseline's share. The
        # matching error is LSD-SLAM's photometric one: image noise over the gradient along the
        # epipolar line (as the rig's own measurement model, depth.elas_matcher.disparity_sigma)
        slope = length / np.maximum(hi - lo, 1e-9)
        sig_px2 = MOTION_MATCH_SIGMA_PX ** 2 + MOTION_NOISE_GREY ** 2 / np.maximum(g2, 1e-6) + \
            (self.camera.fx * np.radians(MOTION_POSE_SIGMA_DEG)) ** 2
        rvar = sig_px2 / slope ** 2 + (MOTION_POSE_SIGMA_REL * out) ** 2
        out = np.where(good, out, np.nan).astype(np.float32)
        return out, rvar.astype(np.float32)
