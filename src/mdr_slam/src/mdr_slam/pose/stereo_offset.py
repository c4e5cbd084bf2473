"""Check of the stereo disparity offset (the principal point difference ``doffs``) against
reference poses.

A rectified pair whose calibration puts the right principal point a fraction of a pixel off
measures every disparity shifted by that much: ``d_measured = f*B/Z + e``. Depth is then biased,
most at long range (0.2 px is 1 % at 20 px of disparity), and so is the scale of the trajectory,
which stereo SLAM takes from those depths. Stereo alone cannot see it; motion can: a map point
seen from several keyframes is triangulated from its left-image observations only, with the
keyframes' poses held, and its stereo observations then compare the measured disparity with
``f*B/Z`` of that triangulation. Over points at many depths

    d_measured = a * d_triangulated + e

separates the offset ``e`` (constant in pixels) from a scale ``a`` (focal length or baseline off,
or the reference's own scale). The two are told apart only over a wide range of depths
(KITTI's road, a corridor); in a small room they trade off, so the fit with ``a`` held at 1 is
given too: a trustworthy offset is one on which both agree.

The poses must not come from the same stereo: a tracker's own poses were fitted to the biased
disparities and absorb much of ``e`` (KITTI 06: -0.08 px from the tracker's poses against -0.16
to -0.21 px from the ground truth; on simulated sequences with a known injected offset,
estimates from the tracker's own poses, even after a left-image-only bundle adjustment,
scattered by +-0.2 px and sometimes had the wrong sign). So this is a check with ground truth (``scripts/
check_stereo_offset.py``), not a self-calibration: its result goes into the calibration as the
right camera's principal point (``StereoCamera.doffs``), which every node honours.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np

from .optimizer import bundle_adjust

__all__ = ["OffsetFit", "estimate_disparity_offset"]


@dataclass
class OffsetFit:
    offset: float          # e (px): measured minus triangulated disparity at zero disparity
    scale: float           # a
    offset_sigma: float    # standard error of e (px)
    offset_unit_scale: float        # e with a held at 1 (the reference poses' scale is right)
    offset_unit_scale_sigma: float
    n_points: int          # map points triangulated from >= min_views keyframes
    n_obs: int             # their stereo observations used in the fit
    residual_mad: float    # robust spread of the fit's residuals (px)

    def as_dict(self) -> dict:
        return {"offset_px": self.offset, "scale": self.scale, "offset_sigma_px": self.offset_sigma,
                "offset_unit_scale_px": self.offset_unit_scale,
                "offset_unit_scale_sigma_px": self.offset_unit_scale_sigma,
                "points": self.n_points, "observations": self.n_obs,
                "residual_mad_px": self.residual_mad}


def _observations(map_, min_views: int, kf_ids=None):
    """Flattened observations (keyframe index, point index, u, v, ur, octave) of the good map
    points seen by at least ``min_views`` good keyframes (of ``kf_ids`` when given), and the
    keyframes."""
    kfs = [k for k in map_.good_keyframes() if kf_ids is None or k.id in kf_ids]
    cams, mids, sels = [], [], []
    for c, k in enumerate(kfs):
        sel = np.nonzero(k.mp_ids >= 0)[0]
        m = k.mp_ids[sel]
        keep = ~map_.mp_bad[m]
        sel, m = sel[keep], m[keep]
        cams.append(np.full(len(sel), c))
        mids.append(m)
        sels.append(sel)
    if not kfs:
        return kfs, None
    cam = np.concatenate(cams)
    mid = np.concatenate(mids)
    counts = np.bincount(mid, minlength=map_.n)
    keep = counts[mid] >= min_views
    uv = np.concatenate([k.uv[s] for k, s in zip(kfs, sels)]).astype(float)
    ur = np.concatenate([k.ur[s] for k, s in zip(kfs, sels)]).astype(float)
    octv = np.concatenate([k.octave[s] for k, s in zip(kfs, sels)])
    return kfs, (cam[keep], mid[keep], uv[keep], ur[keep], octv[keep])


def estimate_disparity_offset(map_, poses: Optional[Dict[int, np.ndarray]] = None,
                              min_views: int = 3, min_parallax_deg: float = 1.0,
                              disparity_range: Tuple[float, float] = (1.0, 80.0),
                              iterations: int = 10) -> Optional[OffsetFit]:
    """The disparity offset of a tracked map (``System.map``) against reference ``poses``
    (keyframe id -> T_cw in the map's world: the ground truth moved into the tracker's first
    camera frame; keyframes without one are left out; None: the keyframes' own poses, biased
    as the module says). Each map point seen by at least ``min_views`` of those keyframes whose
    rays span ``min_parallax_deg`` is triangulated from its left-image observations alone (the
    robust Gauss-Newton of the bundle adjustment with every camera fixed and no stereo term);
    its stereo observations are then fitted by robust (Huber) least squares
    ``u - ur = a * f*B/Z + e``. None when fewer than 30 observations qualify."""
    with map_.lock:
        kfs, obs = _observations(map_, min_views, None if poses is None else set(poses))
        if obs is None or len(obs[0]) == 0:
            return None
        cam, mid, uv, ur, octv = obs
        Ts = np.array([k.T_cw if poses is None else poses[k.id] for k in kfs])
        pts, pt_idx = np.unique(mid, return_inverse=True)
        P0 = map_.mp_pos[pts].copy()
        k0 = kfs[0]
        intr = (k0.fx, k0.fy, k0.cx, k0.cy, k0.bf)
        info = k0.inv_level_sigma2[octv]
    mono = np.zeros(len(cam), bool)
    obs3 = np.column_stack([uv, np.zeros(len(cam))])
    _, P = bundle_adjust(Ts, np.ones(len(Ts), bool), P0, cam, pt_idx, obs3, mono, info, intr,
                         iterations=iterations)
    # parallax: the widest angle between the rays of a point's observations, from the camera
    # centres (per point: max over its observations of the angle to the mean ray)
    centres = np.einsum("nji,nj->ni", Ts[:, :3, :3], -Ts[:, :3, 3])   # R^T (-t)
    rays = P[pt_idx] - centres[cam]
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    mean = np.zeros((len(P), 3))
    np.add.at(mean, pt_idx, rays)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    cosang = np.einsum("ij,ij->i", rays, mean[pt_idx])
    worst = np.full(len(P), 1.0)
    np.minimum.at(worst, pt_idx, cosang)
    wide = worst < np.cos(np.radians(0.5 * min_parallax_deg))
    # reprojection check of the triangulation (left image only)
    fx, fy, cx, cy, bf = intr
    R = Ts[cam, :3, :3]
    Pc = np.einsum("nij,nj->ni", R, P[pt_idx]) + Ts[cam, :3, 3]
    z = Pc[:, 2]
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    e2 = (uv[:, 0] - (fx * Pc[:, 0] / zs + cx)) ** 2 + (uv[:, 1] - (fy * Pc[:, 1] / zs + cy)) ** 2
    good_obs = front & (e2 * info <= 5.991)
    bad_pt = np.zeros(len(P), bool)
    np.logical_or.at(bad_pt, pt_idx, ~good_obs)
    sel = (wide[pt_idx] & ~bad_pt[pt_idx] & (ur >= 0))
    d_tri = bf / zs
    d_meas = uv[:, 0] - ur
    sel &= (d_tri >= disparity_range[0]) & (d_tri <= disparity_range[1])
    if np.count_nonzero(sel) < 30:
        return None
    x, y = d_tri[sel], d_meas[sel]
    coef, cov, s = _huber_line(np.column_stack([x, np.ones(len(x))]), y)
    c1, cov1, _ = _huber_line(np.ones((len(x), 1)), y - x)
    return OffsetFit(offset=float(coef[1]), scale=float(coef[0]),
                     offset_sigma=float(np.sqrt(cov[1, 1])), offset_unit_scale=float(c1[0]),
                     offset_unit_scale_sigma=float(np.sqrt(cov1[0, 0])),
                     n_points=int(np.count_nonzero(wide & ~bad_pt)), n_obs=int(len(x)),
                     residual_mad=s)


def _huber_line(A: np.ndarray, y: np.ndarray, rounds: int = 10):
    """Iteratively reweighted least squares with Huber weights at 1.345 robust sigmas:
    (coefficients, their covariance, robust sigma of the residuals)."""
    coef = np.linalg.lstsq(A, y, rcond=None)[0]
    w = np.ones(len(y))
    for _ in range(rounds):
        r = y - A @ coef
        s = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1e-3)
        w = np.minimum(1.0, 1.345 * s / np.maximum(np.abs(r), 1e-12))
        coef = np.linalg.lstsq(A * np.sqrt(w)[:, None], y * np.sqrt(w), rcond=None)[0]
    r = y - A @ coef
    s = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1e-3)
    return coef, s * s * np.linalg.inv((A * w[:, None]).T @ A), s
