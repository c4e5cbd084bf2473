"""Planar densification of a keyframe's inverse-depth state (our addition beyond the paper).

Low-texture walls, floors and ceilings rarely converge in the temporal filter: every single ELAS
match there is noisy (large variance from the texture model), so no pixel reaches ``tau`` on its
own. In inverse depth a plane is exactly linear in the normalized image coordinates:

    n . P = d,  P = (x, y, 1) Z   =>   1/Z = (n_x x + n_y y + n_z) / d = a x + b y + c

so a plane is a weighted linear least-squares fit of rho = 1/Z on (x, y, 1).

:func:`plane_fill` finds planes by sequential RANSAC (hypotheses from weighted least-squares fits
of random image patches, scored on a sample, refined on all) on the SUPPORT pixels, the converged
ones (the non-converged hypotheses carry ELAS's interpolation errors, which are planar in inverse
depth too: planes fitted on them filled those errors, office map RMSE 0.60 m). A plane's region
is the connected image regions of its inliers among all hypotheses (own estimate within
chi-square of the plane), closed, with small enclosed holes, holding enough support and mostly
inliers, and within
``densify_max_dist`` cells of the support. Its pixels get the plane's inverse depth, except where
the pixel's own estimate contradicts the plane (a box in front of the wall, a depth step), where
the ray grazes the plane, or where another plane fits the neighbourhood better (corners). The
filled depth's variance is the plane's prediction variance (least-squares covariance scaled by the
fit's reduced chi-square) plus a relative floor (``densify_var_floor``). ``priors`` (planes of
earlier keyframes, see :class:`~mdr_slam.depth.DepthFilter`) fill where the current estimates
agree with them without support in view.

Vectorized: one loop iteration per plane (a handful per keyframe), never per pixel.
"""
from __future__ import annotations

from typing import Dict, Mapping, Optional, Tuple, Union

import numpy as np

from .config import DepthConfig

__all__ = ["plane_fill"]


def _lsq(x, y, r, w):
    """Weighted least squares of r = a x + b y + c (arrays (..., n)); returns (theta, ATA)."""
    sx, sy, s1 = (w * x).sum(-1), (w * y).sum(-1), w.sum(-1)
    sxx, syy, sxy = (w * x * x).sum(-1), (w * y * y).sum(-1), (w * x * y).sum(-1)
    ATA = np.stack([np.stack([sxx, sxy, sx], -1), np.stack([sxy, syy, sy], -1),
                    np.stack([sx, sy, s1], -1)], -2)
    ATb = np.stack([(w * x * r).sum(-1), (w * y * r).sum(-1), (w * r).sum(-1)], -1)
    ATA = ATA + np.eye(3) * 1e-9 * (np.trace(ATA, axis1=-2, axis2=-1)[..., None, None] + 1e-12)
    theta = np.linalg.solve(ATA, ATb[..., None])[..., 0]
    return theta, ATA


def _inliers(theta, x, y, r, var, chi2, max_dev):
    pred = theta[..., 0:1] * x + theta[..., 1:2] * y + theta[..., 2:3] if theta.ndim > 1 \
        else theta[0] * x + theta[1] * y + theta[2]
    e = r - pred
    return (e * e <= chi2 * var) & (np.abs(e) <= max_dev * r)


def plane_fill(rx: np.ndarray, ry: np.ndarray, rho: np.ndarray, var: np.ndarray,
               n_obs: np.ndarray, converged: np.ndarray,
               config: Union[None, DepthConfig, Mapping] = None,
               rng: Optional[np.random.Generator] = None, priors=()
               ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, Dict[str, float]]:
    """Planar fill of a grid of inverse-depth hypotheses (all arrays of the grid's 2-D shape).

    ``rx, ry``: normalized image coordinates of the grid pixels; ``rho, var``: inverse depth and
    its variance (NaN = no hypothesis); ``n_obs``: observations; ``converged``: pixels already
    published on their own (they support the fit and are never overwritten).
    Returns ``(fill, rho_fill, var_fill, stats)``: the mask of filled (non-converged) pixels with
    their inverse depth and inverse-depth variance (NaN elsewhere). ``config``: a
    :class:`~mdr_slam.depth.config.DepthConfig` (its ``densify_*`` fields) or a mapping of fields.
    ``priors``: planes (a, b, c) known from earlier keyframes (in this grid's parametrization);
    each fills the regions where this keyframe's own estimates agree with it (no support
    needed); an item may also be ``(theta, allowed)`` with a grid mask of where it may fill.
    ``stats["new_planes"]`` lists the (a, b, c) of the planes found here and
    ``stats["new_regions"]`` the flat grid indices each of them filled or was supported by.
    """
    import cv2
    p = DepthConfig.of(config)
    rng = rng if rng is not None else np.random.default_rng(0)
    gh, gw = rho.shape
    n = gh * gw
    X, Y = rx.ravel().astype(np.float64), ry.ravel().astype(np.float64)
    R = rho.ravel().astype(np.float64)
    V = var.ravel().astype(np.float64)
    conv = converged.ravel().astype(bool)
    with np.errstate(invalid="ignore"):
        have = np.isfinite(R) & np.isfinite(V) & (R > 0) & (V > 0)
        own = have & (n_obs.ravel() >= p.densify_min_obs)
        cand = (own & (np.sqrt(V) <= p.densify_max_rel * R)) | (have & conv)
    chi2, max_dev = float(p.densify_chi2), float(p.densify_max_dev)
    min_pix = int(p.densify_min_pixels)
    K, h = int(p.densify_hypotheses), int(p.densify_patch)
    # patch offsets (every 2nd cell of a (2h+1)^2 window)
    o = np.arange(-h, h + 1, 2)
    odr, odc = [a.ravel() for a in np.meshgrid(o, o, indexing="ij")]
    src = have & conv
    min_sup = p.densify_min_support
    remaining = src.copy()
    label = np.full(n, -1, np.int32)
    fill_rho = np.full(n, np.nan)
    fill_var = np.full(n, np.nan)
    kclose = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * int(p.densify_close) + 1,) * 2)
    stats = {"planes": 0, "candidates": int(cand.sum())}
    planes = []

    def consistent(th):
        pred = th[0] * X + th[1] * Y + th[2]
        with np.errstate(invalid="ignore"):
            contra = own & ((R - pred) ** 2 > chi2 * V)    # statistically inconsistent
        return pred, contra

    def region_of(th, need_sup):
        """Connected regions of the plane's inliers (among all candidates) with enough inliers
        and support, closed, with small enclosed holes filled."""
        # the plane's region: its inliers among ALL candidates (a pixel near the intersection
        # of two planes may belong to both; the competition below decides)
        ci = np.flatnonzero(cand | src)
        inl = ci[_inliers(th, X[ci], Y[ci], R[ci], V[ci], chi2, max_dev)]
        mask = np.zeros(n, np.uint8)
        mask[inl] = 1
        closed = cv2.morphologyEx(mask.reshape(gh, gw), cv2.MORPH_CLOSE, kclose)
        ncomp, lab, st, _ = cv2.connectedComponentsWithStats(closed, connectivity=8)
        # a region needs min_pix inliers that make up most of it (closing must not turn a
        # sprinkle of noise-tail inliers into a region)
        n_in = np.bincount(lab.ravel()[inl], minlength=ncomp)
        n_sup = np.bincount(lab.ravel()[inl[src[inl]]], minlength=ncomp)
        big = np.flatnonzero((n_in[1:] >= min_pix) & (n_sup[1:] >= need_sup) &
                             (n_in[1:] >= p.densify_min_density * st[1:, cv2.CC_STAT_AREA])) + 1
        # pixels of the kept regions that are inliers: the plane's support
        keep_lab = np.zeros(ncomp, bool)
        keep_lab[big] = True
        region = keep_lab[lab.ravel()]
        if p.densify_max_hole > 0 and region.any():
            # enclosed holes (not touching the border) of the region, up to densify_max_hole
            nh, hl, hs, _ = cv2.connectedComponentsWithStats((~region).reshape(gh, gw).astype(
                np.uint8), connectivity=4)
            x0, y0 = hs[:, cv2.CC_STAT_LEFT], hs[:, cv2.CC_STAT_TOP]
            inner = (x0 > 0) & (y0 > 0) & (x0 + hs[:, cv2.CC_STAT_WIDTH] < gw) & \
                (y0 + hs[:, cv2.CC_STAT_HEIGHT] < gh) & \
                (hs[:, cv2.CC_STAT_AREA] <= p.densify_max_hole)
            inner[0] = False
            region |= inner[hl.ravel()]
        return region, inl

    # planes of earlier keyframes: fill where this keyframe's estimates agree with them
    for item in priors:
        allowed = None
        if isinstance(item, tuple) and len(item) == 2:
            item, allowed = item
        th = np.asarray(item, dtype=np.float64)
        region, inl = region_of(th, 0)
        if allowed is not None:
            region &= np.asarray(allowed, bool).ravel()
        if np.count_nonzero(region) < min_pix:
            continue
        pred, contra = consistent(th)
        take = region & ~contra & (pred > 0)
        planes.append((th, np.zeros((3, 3)), take))
        remaining &= ~take
        stats["priors_used"] = stats.get("priors_used", 0) + 1
    stats["new_planes"] = []
    stats["new_regions"] = []
    fails = 0
    for j in range(int(p.densify_max_planes)):
        idx = np.flatnonzero(remaining)
        if len(idx) < min_sup or fails >= 2:
            break
        # hypotheses: weighted LS fits of K random patches of remaining candidates
        c0 = rng.choice(idx, size=K)
        rr = np.clip(c0[:, None] // gw + odr[None, :], 0, gh - 1)
        cc = np.clip(c0[:, None] % gw + odc[None, :], 0, gw - 1)
        pi = rr * gw + cc
        wt = np.where(remaining[pi], 1.0 / np.where(have[pi], V[pi], 1.0), 0.0)
        theta, _ = _lsq(X[pi], Y[pi], np.nan_to_num(R[pi]), wt)
        okh = (remaining[pi].sum(1) >= 6) & np.all(np.isfinite(theta), axis=1)
        if not okh.any():
            fails += 1
            continue
        theta = theta[okh]
        sidx = idx if len(idx) <= 4000 else rng.choice(idx, size=4000, replace=False)
        score = _inliers(theta, X[sidx][None], Y[sidx][None], R[sidx][None], V[sidx][None],
                         chi2, max_dev).sum(1)
        th = theta[int(np.argmax(score))]
        # refine on all remaining candidates
        for _ in range(3):
            inl = idx[_inliers(th, X[idx], Y[idx], R[idx], V[idx], chi2, max_dev)]
            if len(inl) < 3:
                break
            th, ATA = _lsq(X[inl], Y[inl], R[inl], 1.0 / V[inl])
        remaining[idx[_inliers(th, X[idx], Y[idx], R[idx], V[idx], chi2, max_dev)]] = False
        region, inl = region_of(th, min_sup)
        support = inl[region[inl] & src[inl]]
        if len(support) < min_sup:
            fails += 1
            continue
        th, ATA = _lsq(X[support], Y[support], R[support], 1.0 / V[support])
        e = R[support] - (th[0] * X[support] + th[1] * Y[support] + th[2])
        rchi2 = float(np.mean(e * e / V[support]))
        if not np.isfinite(rchi2) or rchi2 > p.densify_max_rchi2:
            fails += 1
            continue
        fails = 0
        # the region: inliers + holes closed inside it, minus pixels whose own estimate
        # contradicts the plane and pixels another plane already took
        pred, contra = consistent(th)
        take = region & ~contra & (pred > 0)
        if p.densify_max_dist > 0:
            sm = np.ones(n, np.uint8)
            sm[support] = 0
            dist = cv2.distanceTransform(sm.reshape(gh, gw), cv2.DIST_L2, 3).ravel()
            take &= dist <= p.densify_max_dist
        planes.append((th, np.linalg.inv(ATA) * max(1.0, rchi2), take))
        remaining &= ~take
        stats["planes"] += 1
        stats["new_planes"].append(th)
        stats["new_regions"].append(np.flatnonzero(take))
    if planes:
        # each pixel goes to the plane that its neighbourhood's own estimates fit best: the
        # normalized squared residual averaged over a window (one noisy pixel does not decide)
        cost = np.full((len(planes), n), np.inf, np.float32)
        kw = 2 * int(p.densify_close) + 3
        with np.errstate(invalid="ignore"):
            for j, (th, _, take) in enumerate(planes):
                pred = th[0] * X + th[1] * Y + th[2]
                c = np.where(own, np.minimum((R - pred) ** 2 / V, 4 * chi2), 1.0)
                c = np.where(np.isfinite(c), c, 1.0).astype(np.float32).reshape(gh, gw)
                c = cv2.blur(c, (kw, kw)).ravel() + np.float32(1e-3 * j)
                cost[j] = np.where(take, c, np.inf)
        best = np.argmin(cost, axis=0)
        # and only where that neighbourhood agrees with it (mean normalized residual^2 of an
        # inlier neighbourhood is ~1): a pixel between two surfaces is left alone
        label = np.where(cost.min(axis=0) <= p.densify_max_rchi2, best, -1).astype(np.int32)
        # never at grazing incidence, where the plane's depth along the ray is ill-conditioned
        cos_min = np.cos(np.radians(float(p.densify_max_incidence_deg)))
        for j, (th, _, _) in enumerate(planes):
            sel = np.flatnonzero(label == j)
            cos_i = np.abs(th[0] * X[sel] + th[1] * Y[sel] + th[2]) / (
                np.linalg.norm(th) * np.sqrt(X[sel] ** 2 + Y[sel] ** 2 + 1.0))
            label[sel[cos_i < cos_min]] = -1
        for j, (th, Cov, _) in enumerate(planes):
            take_i = np.flatnonzero(label == j)
            A = np.stack([X[take_i], Y[take_i], np.ones(len(take_i))], 1)
            pred = A @ th
            fill_rho[take_i] = pred
            fill_var[take_i] = np.einsum("ni,ij,nj->n", A, Cov, A) + \
                (p.densify_var_floor * pred) ** 2
    fill = (label >= 0) & ~conv
    fill_rho[~fill] = np.nan
    fill_var[~fill] = np.nan
    stats["filled"] = int(fill.sum())
    return (fill.reshape(gh, gw), fill_rho.reshape(gh, gw).astype(np.float32),
            fill_var.reshape(gh, gw).astype(np.float32), stats)
