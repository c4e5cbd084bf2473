"""Trajectory error for the pose tests and benchmark: ATE RMSE after Umeyama SE(3) alignment.

(mdr_slam.eval wraps evo for the project's reports; this small numpy version keeps the pose
package's tests independent of it.)
"""
from __future__ import annotations

import numpy as np

__all__ = ["umeyama_se3", "ate_rmse", "associate"]


def umeyama_se3(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """4x4 rigid T minimizing sum |dst - T src|^2 (Umeyama 1991, scale fixed to 1)."""
    ms, md = src.mean(0), dst.mean(0)
    C = (dst - md).T @ (src - ms) / len(src)
    U, _, Vt = np.linalg.svd(C)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = md - R @ ms
    return T


def associate(est, gt, max_dt: float = 0.01):
    """Index pairs of equal stamps (nearest within ``max_dt``)."""
    j = np.searchsorted(gt.stamps, est.stamps)
    j = np.clip(j, 1, max(1, len(gt.stamps) - 1))
    left = np.abs(gt.stamps[j - 1] - est.stamps) <= np.abs(gt.stamps[np.minimum(j, len(gt) - 1)] - est.stamps)
    j = np.where(left, j - 1, j)
    j = np.clip(j, 0, len(gt) - 1)
    ok = np.abs(gt.stamps[j] - est.stamps) <= max_dt
    return np.nonzero(ok)[0], j[ok]


def ate_rmse(est, gt, max_dt: float = 0.01) -> float:
    """RMSE (m) of positions after SE(3) Umeyama alignment of ``est`` onto ``gt``."""
    i, j = associate(est, gt, max_dt)
    if len(i) < 3:
        return float("nan")
    A, B = est.positions[i], gt.positions[j]
    T = umeyama_se3(A, B)
    err = B - (A @ T[:3, :3].T + T[:3, 3])
    return float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))
