"""Optimizer: pose-only optimization (numpy Gauss-Newton), local BA and pose graph (GTSAM).

PoseOptimization follows ORB-SLAM2 Optimizer::PoseOptimization: stereo observations have a 3-D
residual (u_L, v, u_R) and chi2 threshold 7.815 (95 %, 3 dof), monocular ones a 2-D residual and
5.991; information is 1/sigma^2 of the keypoint's octave (sigma = 1.2^octave); four rounds of ten
iterations with a Huber kernel, re-classifying inliers/outliers after each round and dropping the
kernel in the last. It is a 6x6 problem, so a vectorized numpy Gauss-Newton (einsum normal
equations) is faster than building a factor graph per frame.

Local BA and the pose graph are GTSAM (GenericStereoFactor3D / GenericProjectionFactorCal3_S2 with
Huber noise, BetweenFactorPose3, Levenberg-Marquardt), as the brief asks: well-kept sparse solvers.
"""
from __future__ import annotations

import itertools
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np
import scipy.linalg
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from ..geometry import inv_T

__all__ = ["Optimizer", "bundle_adjust", "normalize_pose", "CHI2_MONO", "CHI2_STEREO",
           "project_residuals", "bundle_adjust_sparse", "global_bundle_adjustment"]

CHI2_MONO = 5.991
CHI2_STEREO = 7.815
# wheel odometry between keyframes in the local BA (not in ORB-SLAM2): the motion between two
# keyframes at most ODOM_EDGE_MAX_GAP_S apart, with sigmas SIGMA_M / SIGMA_DEG + REL x the motion's
# translation (m) / rotation: a differential drive is good to a percent or two over a keyframe
# gap, and looser edges let a few weak-texture points turn the newest keyframes by degrees
ODOM_EDGES = True
ODOM_EDGE_SIGMA_M = 0.01
ODOM_EDGE_SIGMA_DEG = 0.2
ODOM_EDGE_SIGMA_REL = 0.02
ODOM_EDGE_MAX_GAP_S = 5.0
ODOM_EDGES_CALIBRATED = True   # ... from the calibrated odometry (OdometryCalibration) where known


def _skew_batch(t: np.ndarray) -> np.ndarray:
    K = np.zeros(t.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -t[..., 2], t[..., 1], -t[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = t[..., 2], -t[..., 1], t[..., 0]
    return K


def _relative_pose_terms(Ts: np.ndarray, edges):
    """Residuals r (E, 6) = [t, rotvec] of Z^-1 T_i T_j^-1 for ``edges`` (i, j, Z (E, 4, 4),
    information (E, 6)) and the Jacobians of r w.r.t. the left updates of T_i (J_i) and T_j
    (-I): J_i = [[R^T, -R^T [t]x], [0, R^T]] for T_i T_j^-1 = [R | t]."""
    ei, ej, Z, _ = edges
    Ti, Tj = Ts[ei], Ts[ej]
    R = Ti[:, :3, :3] @ Tj[:, :3, :3].transpose(0, 2, 1)
    t = Ti[:, :3, 3] - (R @ Tj[:, :3, 3][:, :, None])[:, :, 0]
    ZR = Z[:, :3, :3].transpose(0, 2, 1)
    E_R = ZR @ R
    E_t = (ZR @ (t - Z[:, :3, 3])[:, :, None])[:, :, 0]
    r = np.concatenate([E_t, Rotation.from_matrix(E_R).as_rotvec()], axis=1)
    RT = R.transpose(0, 2, 1)
    Ji = np.zeros((len(ei), 6, 6))
    Ji[:, :3, :3] = RT
    Ji[:, :3, 3:] = -RT @ _skew_batch(t)
    Ji[:, 3:, 3:] = RT
    return r, Ji


def _edge_cost(Ts, edges) -> float:
    if edges is None:
        return 0.0
    r, _ = _relative_pose_terms(Ts, edges)
    return float(np.sum(edges[3] * r * r))


def odometry_motion(ka, kb, calibrated: bool = True) -> np.ndarray:
    """T_a T_b^-1 of two keyframes as the wheels saw it: the calibrated odometry where both carry
    it (OdometryCalibration's chain, with the base's scale and yaw creep taken out) and
    ``calibrated``, else the raw."""
    a, b = (getattr(k, "T_odom_cam_calibrated", None) for k in (ka, kb))
    if a is None or b is None or not calibrated:
        a, b = ka.T_odom_cam, kb.T_odom_cam
    return inv_T(a) @ b


def odometry_edges(kfs, fixed_mask):
    """Wheel-odometry edges (i, j, Z, information) between keyframes of ``kfs`` next to each
    other in time (both with ``T_odom_cam``, at most ODOM_EDGE_MAX_GAP_S apart, not both fixed),
    or None. The motion is the calibrated odometry's where both keyframes carry it: a raw yaw
    creep of a degree per metre is several times the edges' sigma over a keyframe gap, and would
    turn the keyframes of a weakly textured stretch with it."""
    idx = sorted((c for c, k in enumerate(kfs) if getattr(k, "T_odom_cam", None) is not None),
                 key=lambda c: kfs[c].stamp)
    ei, ej, Zs, L = [], [], [], []
    for a, b in zip(idx, idx[1:]):
        if (fixed_mask[a] and fixed_mask[b]) or \
                kfs[b].stamp - kfs[a].stamp > float(ODOM_EDGE_MAX_GAP_S):
            continue
        Z = odometry_motion(kfs[a], kfs[b], ODOM_EDGES_CALIBRATED)
        st = float(ODOM_EDGE_SIGMA_M) + float(ODOM_EDGE_SIGMA_REL) * float(np.linalg.norm(Z[:3, 3]))
        sr = np.radians(float(ODOM_EDGE_SIGMA_DEG)) + float(ODOM_EDGE_SIGMA_REL) * float(
            np.linalg.norm(Rotation.from_matrix(Z[:3, :3]).as_rotvec()))
        ei.append(a)
        ej.append(b)
        Zs.append(Z)
        L.append([1.0 / st ** 2] * 3 + [1.0 / sr ** 2] * 3)
    if not ei:
        return None
    return np.array(ei), np.array(ej), np.array(Zs), np.array(L)


def normalize_pose(T: np.ndarray) -> np.ndarray:
    """Nearest rigid transform (SVD projection of the rotation). Pose chains (velocity, last
    frame re-anchoring) multiply rounding errors that inv_T's R^T amplifies; projecting every
    stored pose keeps them exact rotations."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = T[:3, 3]
    return out


def project_residuals(T_cw: np.ndarray, Pw: np.ndarray, obs: np.ndarray, stereo: np.ndarray,
                      fx, fy, cx, cy, bf):
    """Residuals (N, 3) obs - proj (third column 0 for mono), camera points (N, 3)."""
    Pc = Pw @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = Pc[:, 2]
    iz = 1.0 / np.where(np.abs(z) < 1e-9, 1e-9, z)
    u = fx * Pc[:, 0] * iz + cx
    v = fy * Pc[:, 1] * iz + cy
    ur = u - bf * iz
    e = np.stack([obs[:, 0] - u, obs[:, 1] - v, np.where(stereo, obs[:, 2] - ur, 0.0)], axis=1)
    return e, Pc


def _pose_point_jacobians(Pc, R, stereo, fx, fy, bf):
    """d(residual)/d(pose xi) (n,3,6) and d(residual)/d(point) (n,3,3); residual = obs - proj.
    The projection's Jacobian has two non-zeros per row, so both products are written out per
    entry (a third of the time of the batched 3x3 matrix products they stand for)."""
    X, Y, Z = Pc[:, 0], Pc[:, 1], Pc[:, 2]
    iz = 1.0 / np.where(np.abs(Z) < 1e-9, 1e-9, Z)
    iz2 = iz * iz
    n = len(Pc)
    # rows of d(u, v, u_R)/d(Pc): [a, 0, c0], [0, b, c1], [a, 0, c2] (the last zero for mono)
    a, b = fx * iz, fy * iz
    c0, c1 = -fx * X * iz2, -fy * Y * iz2
    a2 = np.where(stereo, a, 0.0)
    c2 = np.where(stereo, -(fx * X - bf) * iz2, 0.0)
    # d(Pc)/d(xi) = [I | -[Pc]x]; Jc = -(dproj/dPc @ dPc/dxi)
    Jc = np.empty((n, 3, 6))
    Jc[:, 0, 0], Jc[:, 0, 1], Jc[:, 0, 2] = -a, 0.0, -c0
    Jc[:, 1, 0], Jc[:, 1, 1], Jc[:, 1, 2] = 0.0, -b, -c1
    Jc[:, 2, 0], Jc[:, 2, 1], Jc[:, 2, 2] = -a2, 0.0, -c2
    Jc[:, 0, 3], Jc[:, 0, 4], Jc[:, 0, 5] = -c0 * Y, c0 * X - a * Z, a * Y
    Jc[:, 1, 3], Jc[:, 1, 4], Jc[:, 1, 5] = b * Z - c1 * Y, c1 * X, -b * X
    Jc[:, 2, 3], Jc[:, 2, 4], Jc[:, 2, 5] = -c2 * Y, c2 * X - a2 * Z, a2 * Y
    # Jl = -(dproj/dPc @ R)
    R0, R1, R2 = R[:, 0, :], R[:, 1, :], R[:, 2, :]
    Jl = np.empty((n, 3, 3))
    Jl[:, 0, :] = -(a[:, None] * R0 + c0[:, None] * R2)
    Jl[:, 1, :] = -(b[:, None] * R1 + c1[:, None] * R2)
    Jl[:, 2, :] = -(a2[:, None] * R0 + c2[:, None] * R2)
    return Jc, Jl


def _ba_residuals(Ts, P, cam_idx, pt_idx, obs, stereo, intr):
    """Stereo/mono reprojection residuals (n, 3) of BA observations, the points in the camera
    frames (n, 3) and the rotations (n, 3, 3): the third row is the right-image u (0 for mono)."""
    fx, fy, cx, cy, bf = intr
    R = Ts[cam_idx, :3, :3]
    Pc = (R @ P[pt_idx][:, :, None])[:, :, 0] + Ts[cam_idx, :3, 3]
    z = Pc[:, 2]
    iz = 1.0 / np.where(np.abs(z) < 1e-9, 1e-9, z)
    u = fx * Pc[:, 0] * iz + cx
    v = fy * Pc[:, 1] * iz + cy
    e = np.stack([obs[:, 0] - u, obs[:, 1] - v,
                  np.where(stereo, obs[:, 2] - (u - bf * iz), 0.0)], axis=1)
    return e, Pc, R


def _huber_cost(e, info, delta, active):
    """(sum of Huber-robustified chi2 over the active observations, chi2 per observation)."""
    chi2 = info * np.einsum("ij,ij->i", e, e)
    s = np.sqrt(chi2)
    rho = np.where(s <= delta, chi2, 2.0 * delta * s - delta * delta)
    return float(np.sum(rho[active])), chi2


def bundle_adjust(Ts: np.ndarray, fixed: np.ndarray, P: np.ndarray, cam_idx: np.ndarray,
                  pt_idx: np.ndarray, obs: np.ndarray, stereo: np.ndarray, info: np.ndarray,
                  intr, iterations: int = 10, lm_lambda: float = 1e-3, abort=None,
                  tol: float = 0.0, row_w: Optional[np.ndarray] = None, planar=None,
                  pose_edges=None):
    """Robust (Huber) Levenberg-Marquardt bundle adjustment with the Schur complement.

    Poses ``Ts`` (C, 4, 4) T_cw (``fixed`` ones held), points ``P`` (M, 3); observations (u, v, uR)
    with stereo flag and information 1/sigma^2. The point blocks are eliminated (scipy.sparse
    block products), leaving a dense 6C x 6C camera system: the standard BA structure (as g2o in
    ORB-SLAM2), vectorized so a local BA with ~10k observations takes tens of milliseconds.
    Half the iterations run, outliers (chi2 above 95 %) are dropped, the rest run again. With
    ``tol`` > 0 a round ends early once a step lowers the robust cost by less than ``tol`` times
    its value (converged: the remaining iterations would move nothing that matters).
    ``row_w`` (n, 3): weights of each observation's u, v and u_R rows in the cost (texture
    weights, :meth:`Frame.texture_weights`); the outlier test stays on the plain chi2.
    ``planar`` (a :class:`~mdr_slam.pose.planar.PlanarMotion`): the cameras move in the floor's
    plane only (the Schur system projected on each camera's three planar directions).
    ``pose_edges`` (:func:`odometry_edges`): relative-pose terms between cameras (wheel
    odometry), added to the camera blocks of the Schur system.
    """
    Ts, P, _, _ = _robust_lm(Ts, fixed, P, cam_idx, pt_idx, obs, stereo, info, intr, iterations,
                             lm_lambda, abort, tol, sparse=False, row_w=row_w, planar=planar,
                             pose_edges=pose_edges)
    return Ts, P


def _robust_lm(Ts, fixed, P, cam_idx, pt_idx, obs, stereo, info, intr, iterations, lm_lambda,
               abort, tol, sparse, row_w=None, planar=None, pose_edges=None):
    """The LM loop of :func:`bundle_adjust` and :func:`bundle_adjust_sparse`: W (6 C x 3 M) as a
    dense array (few cameras: one BLAS product) or as scipy.sparse (many cameras). Returns
    (Ts, P, active observations, residuals at the result)."""
    fx, fy, cx, cy, bf = intr
    Ts = np.array(Ts, dtype=float)
    P = np.array(P, dtype=float)
    C, M = len(Ts), len(P)
    var = np.nonzero(~np.asarray(fixed, dtype=bool))[0]
    cvar = np.full(C, -1, dtype=np.int64)
    cvar[var] = np.arange(len(var))
    nv = len(var)
    chi2_th = np.where(stereo, CHI2_STEREO, CHI2_MONO)
    delta = np.sqrt(chi2_th)
    active = np.ones(len(obs), dtype=bool)

    def residuals(Ts_, P_):
        return _ba_residuals(Ts_, P_, cam_idx, pt_idx, obs, stereo, intr)

    sq = None if row_w is None else np.sqrt(np.asarray(row_w, dtype=float))

    def robust_cost(e):
        return _huber_cost(e if sq is None else e * sq, info, delta, active)

    lam = lm_lambda
    half = max(1, iterations // 2)
    # fixed structure, built once: observations of variable cameras, and where their (6 x 3)
    # W blocks go in a dense (6 nv, 3 M) W (nv <= ba_covisible + 1: the Schur product W V^-1 W^T
    # is then one BLAS matrix product instead of many sparse or tiny batched products)
    ovi = np.nonzero(cvar[cam_idx] >= 0)[0]
    oc = cvar[cam_idx[ovi]]
    pt_ov = pt_idx[ovi]
    w_flat = ((6 * oc[:, None, None] + np.arange(6)[None, :, None]) * (3 * M) +
              3 * pt_ov[:, None, None] + np.arange(3)[None, None, :]).ravel()
    cam_ar = np.arange(nv)
    sum_pt = _block_summer(pt_idx, M)
    sum_cam = _block_summer(oc, nv)
    if sparse and nv:
        # the CSR pattern of W is the same in every iteration: build it once (sorted unique
        # entries; a point seen twice by one keyframe sums) and fill only the values after
        w_key, w_inv = np.unique(w_flat, return_inverse=True)
        # int32 indices where they fit: scipy keeps them as they are instead of a converted
        # copy per matrix made (two per iteration)
        idt = np.int32 if max(3 * M, len(w_key)) < np.iinfo(np.int32).max else np.int64
        w_cols = (w_key % (3 * M)).astype(idt)
        w_indptr = np.searchsorted(w_key // (3 * M), np.arange(6 * nv + 1)).astype(idt)
        w_flat = w_key = None
        n_key = len(w_cols)

        def w_csr(vals):
            data = np.bincount(w_inv, weights=vals.ravel(), minlength=n_key)
            return sp.csr_matrix((data, w_cols, w_indptr), shape=(6 * nv, 3 * M))

    cur = residuals(Ts, P)
    it = 0
    while it < iterations:
        if abort is not None and it > 0 and abort():
            break   # a new keyframe is waiting (ORB-SLAM2 mbAbortBA): keep the steps taken so far
        e, Pc, R = cur
        # the last iteration's blocks go before this one's are made: two generations of them
        # alive at once were most of a global BA's memory
        Jc = Jl = JlT = JcT = Wb = Wd = WVd = S = S4 = Vinv = nxt = None
        if it == half:   # ORB-SLAM2: optimise, drop outliers, optimise again
            _, chi2 = _huber_cost(e, info, delta, active)
            active &= (chi2 <= chi2_th) & (Pc[:, 2] > 0)
        cost, chi2 = robust_cost(e)
        cost += _edge_cost(Ts, pose_edges)
        s = np.sqrt(np.maximum(chi2, 1e-12))
        w = info * np.where(s > delta, delta / s, 1.0) * active
        Jc, Jl = _pose_point_jacobians(Pc, R, stereo, fx, fy, bf)
        if sq is not None:   # weighted rows: residuals and Jacobians scaled by sqrt(row_w)
            e = e * sq
            Jc = Jc * sq[:, :, None]
            Jl = Jl * sq[:, :, None]
        # point blocks (bincount on flattened block indices: much faster than np.add.at)
        JlT = Jl.transpose(0, 2, 1) * w[:, None, None]
        Hpp = sum_pt(JlT @ Jl)
        bp = sum_pt((JlT @ e[:, :, None])[:, :, 0])
        JcT = Jc[ovi].transpose(0, 2, 1) * w[ovi][:, None, None]
        Hcc = sum_cam(JcT @ Jc[ovi])
        bc = sum_cam((JcT @ e[ovi][:, :, None])[:, :, 0])
        Wb = JcT @ Jl[ovi]                                             # (n, 6, 3)
        Jc = Jl = JlT = JcT = None   # not needed by the damped solves: their memory goes first
        off = []   # (ci, cj, H_ij) of the relative-pose edges between two variable cameras
        if pose_edges is not None and nv:
            r_e, Ji = _relative_pose_terms(Ts, pose_edges)
            L_e = pose_edges[3]
            JiTL = Ji.transpose(0, 2, 1) * L_e[:, None, :]                  # J_i^T Lambda
            for k, (a, b) in enumerate(zip(cvar[pose_edges[0]], cvar[pose_edges[1]])):
                if a >= 0:
                    Hcc[a] += JiTL[k] @ Ji[k]
                    bc[a] += JiTL[k] @ r_e[k]
                if b >= 0:
                    Hcc[b] += np.diag(L_e[k])
                    bc[b] -= L_e[k] * r_e[k]
                if a >= 0 and b >= 0:
                    off.append((a, b, -JiTL[k]))
        if nv:
            if sparse:
                Wd = w_csr(Wb)
            else:
                Wd = np.zeros((6 * nv, 3 * M))
                Wd.ravel()[w_flat] = Wb.ravel()
        improved = False
        for _ in range(6):
            Hpp_d = Hpp + (lam * np.einsum("nii->ni", Hpp) + 1e-9)[:, :, None] * np.eye(3)
            Vinv = _inv3(Hpp_d)
            if nv:
                Hcc_d = Hcc + (lam * np.einsum("nii->ni", Hcc) + 1e-9)[:, :, None] * np.eye(6)
                # Schur complement S = Hcc - W V^-1 W^T (V block diagonal: per-point 3x3)
                if sparse:
                    WVd = w_csr(Wb @ Vinv[pt_ov])
                    S = (WVd @ Wd.T).toarray()
                    np.negative(S, out=S)
                else:
                    WVd = np.zeros((6 * nv, 3 * M))
                    WVd.ravel()[w_flat] = (Wb @ Vinv[pt_ov]).ravel()
                    S = -(WVd @ Wd.T)
                S4 = S.reshape(nv, 6, nv, 6)          # a view: add the 6x6 diagonal blocks
                S4[cam_ar, :, cam_ar, :] += Hcc_d
                for a, b, Hab in off:
                    S4[a, :, b, :] += Hab
                    S4[b, :, a, :] += Hab.T
                rhs = -bc.ravel() + WVd @ bp.ravel()
                try:
                    if planar is None:
                        dc = _solve_spd(S, rhs).reshape(nv, 6)
                    else:   # S and rhs on each camera's planar directions: dc = B xi
                        Bv = np.array([planar.basis(T) for T in Ts[var]])          # (nv, 6, 3)
                        S3 = np.einsum("iab,iajc,jcd->ibjd", Bv, S4, Bv).reshape(3 * nv, 3 * nv)
                        xi = _solve_spd(S3, np.einsum("iab,ia->ib", Bv,
                                                      rhs.reshape(nv, 6)).ravel()).reshape(nv, 3)
                        dc = np.einsum("iab,ib->ia", Bv, xi)
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                dp = -(Vinv @ (bp + (Wd.T @ dc.ravel()).reshape(M, 3))[:, :, None])[:, :, 0]
            else:
                dc = np.zeros((0, 6))
                dp = -(Vinv @ bp[:, :, None])[:, :, 0]
            Ts_try = Ts.copy()
            if nv and planar is not None:   # exactly in the plane
                for c, v in enumerate(var):
                    Ts_try[v] = planar.update(Ts[v], xi[c])
            elif nv:   # left-multiplied update [exp(phi) | rho] T, all cameras at once
                dR = Rotation.from_rotvec(dc[:, 3:]).as_matrix()
                Ts_try[var, :3, :3] = dR @ Ts[var, :3, :3]
                Ts_try[var, :3, 3] = (dR @ Ts[var, :3, 3][:, :, None])[:, :, 0] + dc[:, :3]
            P_try = P + dp
            nxt = residuals(Ts_try, P_try)
            cost2, _ = robust_cost(nxt[0])
            cost2 += _edge_cost(Ts_try, pose_edges)
            if cost2 < cost:
                Ts, P, cur = Ts_try, P_try, nxt
                lam = max(lam / 3.0, 1e-7)
                improved = True
                break
            lam *= 4.0
        if not improved:
            break
        if tol > 0 and cost - cost2 <= tol * cost:
            # converged (relative cost decrease below tol): on to the outlier round, or done
            if it < half:
                it = half
                continue
            break
        it += 1
    return Ts, P, active, cur


def texture_row_weights(obs_list) -> Optional[np.ndarray]:
    """(n, 3) u, v, u_R row weights of BA observations [(keyframe, keypoint index, ...)] from the
    keyframes' texture weights (x for u and u_R, y for v); None when no keyframe has them."""
    if not any(getattr(k, "tex_w", None) is not None for k, *_ in obs_list):
        return None
    w = np.concatenate([k.tex_w[sel] if getattr(k, "tex_w", None) is not None
                        else np.ones((len(sel), 2)) for k, sel, *_ in obs_list])
    return np.column_stack([w[:, 0], w[:, 1], w[:, 0]])


def _solve_spd(S: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve the damped Schur system, symmetric positive definite: Cholesky (about half the
    cost of LU on the global BA's 1000-dimensional systems), LU where rounding makes it fail."""
    try:
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(S, check_finite=False), rhs,
                                      check_finite=False)
    except np.linalg.LinAlgError:
        return np.linalg.solve(S, rhs)


def _block_summer(idx: np.ndarray, n: int):
    """``f(vals)``: out[k] = sum of vals[i] with idx[i] == k, for blocks vals (m, ...) -> (n, ...).
    One sparse one-hot (n x m) product per call, its pattern built once for the solver's fixed
    structure: 5-8x faster than a bincount over flattened block indices."""
    m = len(idx)
    A = sp.csr_matrix((np.ones(m), (np.asarray(idx, dtype=np.int64), np.arange(m))), shape=(n, m))

    def block_sum(vals: np.ndarray) -> np.ndarray:
        if m == 0:
            return np.zeros((n,) + vals.shape[1:])
        return (A @ vals.reshape(m, -1)).reshape((n,) + vals.shape[1:])
    return block_sum


def _inv3(A: np.ndarray) -> np.ndarray:
    """Inverses of (n, 3, 3) matrices by cofactors (vectorized; ~10x np.linalg.inv for 3x3)."""
    a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 0], A[:, 1, 1], A[:, 1, 2]
    g, h, i = A[:, 2, 0], A[:, 2, 1], A[:, 2, 2]
    C = np.empty_like(A)
    C[:, 0, 0] = e * i - f * h
    C[:, 0, 1] = c * h - b * i
    C[:, 0, 2] = b * f - c * e
    C[:, 1, 0] = f * g - d * i
    C[:, 1, 1] = a * i - c * g
    C[:, 1, 2] = c * d - a * f
    C[:, 2, 0] = d * h - e * g
    C[:, 2, 1] = b * g - a * h
    C[:, 2, 2] = a * e - b * d
    det = a * C[:, 0, 0] + b * C[:, 1, 0] + c * C[:, 2, 0]
    return C / det[:, None, None]


def _log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (cv2.Rodrigues: 5 us against 10 for the arccos
    formula in numpy, for a single matrix inside the pose-only Gauss-Newton loop)."""
    return cv2.Rodrigues(np.ascontiguousarray(R, dtype=np.float64))[0].ravel()


def _exp_se3_left(dx: np.ndarray, T: np.ndarray) -> np.ndarray:
    """[R(dx[3:]) | dx[:3]] @ T with R from cv2.Rodrigues (the pose update of the pose-only
    optimization; 16 us against 40 for Rodrigues' formula written in numpy)."""
    R = cv2.Rodrigues(np.ascontiguousarray(dx[3:], dtype=np.float64))[0]
    out = np.empty((4, 4))
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] = R @ T[:3, 3] + dx[:3]
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


class Optimizer:
    """Static-style collection of the optimizations (ORB-SLAM2's Optimizer class)."""

    @staticmethod
    def pose_optimization(frame, map_, rounds: int = 4, iters: int = 10) -> int:
        """Refine ``frame.T_cw`` from its matched map points; sets ``frame.outlier``; returns the
        number of inliers. Rows of the Jacobian are kept as one contiguous (6, 3n) array (u, v
        and u_R blocks) so each iteration writes rows, not strided columns, and H is one GEMM.

        Motion prior (not in ORB-SLAM2): when ``frame.prior`` is set to (T_pred, info6) by
        Tracking (the constant-velocity prediction and the information of [rho, phi]), a residual
        log(T T_pred^-1) weighted by info6 joins the normal equations. It is weak (sigmas of
        centimetres / degrees per frame): a frame seeing many features spread over the image
        ignores it, but when all features lie on one small patch a lateral translation and a yaw
        move them alike, the visual Hessian is nearly singular along that direction and the pose
        then follows the smooth motion instead of drifting along it."""
        idx = np.nonzero(frame.mp_ids >= 0)[0]
        ids = frame.mp_ids[idx]
        good = ~map_.mp_bad[ids]
        idx, ids = idx[good], ids[good]
        frame.outlier[:] = False
        if len(idx) < 3:
            return 0
        n = len(idx)
        PwT = np.ascontiguousarray(map_.mp_pos[ids].T, dtype=float)          # (3, n)
        stereo = frame.ur[idx] >= 0
        st = stereo.astype(float)
        ou = frame.uv[idx, 0].astype(float)
        ov = frame.uv[idx, 1].astype(float)
        our = np.where(stereo, frame.ur[idx], 0.0).astype(float)
        info = frame.inv_level_sigma2[frame.octave[idx]].astype(float)
        tex = frame.texture_weights(idx) if hasattr(frame, "texture_weights") else None
        wx, wy = (1.0, 1.0) if tex is None else (tex[:, 0], tex[:, 1])
        chi2_th = np.where(stereo, CHI2_STEREO, CHI2_MONO)
        delta = np.sqrt(chi2_th)
        planar = getattr(map_, "planar", None)   # PlanarMotion: x, y, yaw of the base only
        T = frame.T_cw.copy() if planar is None else planar.project(frame.T_cw)
        inlier = np.ones(n, dtype=bool)
        fx, fy, cx, cy, bf = frame.fx, frame.fy, frame.cx, frame.cy, frame.bf
        # Jacobian rows (residual = obs - proj, xi = [rho, phi]) as one (6, 3n) array: columns
        # [0, n) are the u rows, [n, 2n) the v rows, [2n, 3n) the u_R rows (zero for mono)
        J = np.zeros((6, 3 * n))
        Ju, Jv, Jr = J[:, :n], J[:, n:2 * n], J[:, 2 * n:]
        e = np.empty(3 * n)
        eu, ev, er = e[:n], e[n:2 * n], e[2 * n:]
        w3 = np.empty(3 * n)
        has_stereo = bool(np.any(stereo))
        eye6 = 1e-9 * np.eye(6)
        prior = getattr(frame, "prior", None)
        if prior is not None:
            T_pinv = inv_T(prior[0])
            L_prior = np.asarray(prior[1], dtype=float)
            eye6 = eye6 + np.diag(L_prior)

        def residuals(T):
            Pc = T[:3, :3] @ PwT + T[:3, 3:4]
            X, Y, Z = Pc
            iz = 1.0 / np.where(np.abs(Z) < 1e-9, 1e-9, Z)
            xz, yz = X * iz, Y * iz
            u = fx * xz + cx
            np.subtract(ou, u, out=eu)
            np.subtract(ov, fy * yz + cy, out=ev)
            np.multiply(our - (u - bf * iz), st, out=er)
            return X, Y, Z, iz, xz, yz

        converged, used = False, None
        for rnd in range(rounds):
            robust = rnd < rounds - 1
            if converged and robust and np.array_equal(inlier, used):
                # the same robust problem as the round before, already at its optimum: the
                # round would end where it starts and classify the same inliers
                continue
            used, converged = inlier, False
            for _ in range(iters):
                X, Y, Z, iz, xz, yz = residuals(T)
                chi2 = info * (eu * eu + ev * ev + er * er)
                w = info * inlier
                if robust:   # Huber weights: sqrt(chi2) > delta -> delta / sqrt(chi2)
                    s = np.sqrt(np.maximum(chi2, 1e-12))
                    w = w * np.where(s > delta, delta / s, 1.0)
                fxz, fyz, xy = fx * iz, fy * iz, xz * yz
                np.negative(fxz, out=Ju[0])
                np.multiply(fxz, xz, out=Ju[2])
                np.multiply(fx, xy, out=Ju[3])
                np.multiply(-fx, 1.0 + xz * xz, out=Ju[4])
                np.multiply(fx, yz, out=Ju[5])
                np.negative(fyz, out=Jv[1])
                np.multiply(fyz, yz, out=Jv[2])
                np.multiply(fy, 1.0 + yz * yz, out=Jv[3])
                np.multiply(-fy, xy, out=Jv[4])
                np.multiply(-fy, xz, out=Jv[5])
                if has_stereo:   # u_R row = u row + d(-bf/Z)/d(xi); zero for mono (st = 0)
                    b2 = bf * iz * iz
                    np.multiply(Ju[0], st, out=Jr[0])
                    np.multiply(Ju[2] - b2, st, out=Jr[2])
                    np.multiply(Ju[3] - b2 * Y, st, out=Jr[3])
                    np.multiply(Ju[4] + b2 * X, st, out=Jr[4])
                    np.multiply(Ju[5], st, out=Jr[5])
                w3[:n] = w * wx
                w3[n:2 * n] = w * wy
                w3[2 * n:] = w * wx
                Jw = J * w3
                H = Jw @ J.T
                g = Jw @ e
                if prior is not None:   # r = [t, rotvec] of T T_pred^-1, dr/dx ~ I
                    D = T @ T_pinv
                    r = np.concatenate([D[:3, 3], _log_so3(D[:3, :3])])
                    g = g + L_prior * r
                try:
                    if planar is None:
                        dx = -np.linalg.solve(H + eye6, g)
                        T = _exp_se3_left(dx, T)
                    else:   # the same normal equations on the plane's three directions
                        B = planar.basis(T)
                        dx = -np.linalg.solve(B.T @ (H + eye6) @ B, B.T @ g)
                        T = planar.update(T, dx)
                except np.linalg.LinAlgError:
                    break
                if np.linalg.norm(dx) < 1e-6:
                    converged = True
                    break
            X, Y, Z, iz, xz, yz = residuals(T)
            chi2 = info * (eu * eu + ev * ev + er * er)
            inlier = (chi2 <= chi2_th) & (Z > 0)
            if np.count_nonzero(inlier) < 10:
                break
        frame.T_cw = normalize_pose(T)
        frame.outlier[idx] = ~inlier
        return int(np.count_nonzero(inlier))

    @staticmethod
    def pose_from_points(cam, T_cw, uv, ur, octave, inv_level_sigma2, Pw, bad=None, prior=None,
                         planar=None):
        """:meth:`pose_optimization` on explicit correspondences (keypoints ``uv``, ``ur``,
        ``octave`` of a frame or keyframe ``cam`` giving fx, fy, cx, cy, bf; world points ``Pw``;
        ``bad`` points are left out), started at ``T_cw``: (refined T_cw, outlier mask, inliers).
        For observations that are not the frame's own map-point matches (a loop's other side,
        optical-flow tracks). ``prior`` and ``planar`` as the frame's and the map's in
        :meth:`pose_optimization`."""
        class _View:
            pass
        n = len(Pw)
        f = _View()
        f.fx, f.fy, f.cx, f.cy, f.bf = cam.fx, cam.fy, cam.cx, cam.cy, cam.bf
        f.uv, f.ur, f.octave, f.inv_level_sigma2 = uv, ur, octave, inv_level_sigma2
        f.mp_ids = np.arange(n)
        f.outlier = np.zeros(n, bool)
        f.T_cw = np.array(T_cw, dtype=float)
        f.prior = prior
        pts = _View()
        pts.mp_pos = np.asarray(Pw, dtype=float)
        pts.mp_bad = np.zeros(n, bool) if bad is None else np.asarray(bad, bool)
        pts.planar = planar
        n_inl = Optimizer.pose_optimization(f, pts)
        return f.T_cw, f.outlier, n_inl

    # ------------------------------------------------------------------ local bundle adjustment
    @staticmethod
    def local_bundle_adjustment(kf, map_, n_covisible: int = 10, iterations: int = 10,
                                abort=None, worker=None,
                                tol: float = 0.0) -> Tuple[List[int], int]:
        """ORB-SLAM2 LocalBundleAdjustment: optimise ``kf`` and its covisible keyframes and every
        point they see; keyframes that see those points but are not local stay fixed. Observations
        with chi2 above threshold after optimization are erased. Returns (moved kf ids, outliers).
        With a ``worker`` (ba_process.BAWorker) the solver runs in its child process. ``tol``: see
        :func:`bundle_adjust` (early end of a converged round).
        """
        with map_.lock:
            local = [kf] + map_.best_covisibles(kf, n_covisible)
            local = [k for k in local if not k.bad]
            local_ids = set(k.id for k in local)
            pts = np.unique(np.concatenate([k.valid_mp_ids(map_.mp_bad) for k in local]))
            if len(pts) == 0:
                return [], 0
            mark = np.zeros(map_.n, dtype=bool)
            mark[pts] = True
            # the first 20 (oldest) keyframes seeing local points: enough anchors (ORB-SLAM2
            # keeps all, but cost grows); the scan stops at 20 instead of visiting every keyframe
            fixed = list(itertools.islice(
                (k for k in map_.good_keyframes() if k.id not in local_ids and
                 np.any(mark[k.mp_ids[k.mp_ids >= 0]])), 20))
            if min(k.id for k in local) == 0 or not fixed:
                first = min(local, key=lambda k: k.id)
                fixed_ids = {first.id}
            else:
                fixed_ids = set()
            kfs = local + fixed
            fixed_ids |= set(k.id for k in fixed)
            pos = map_.mp_pos[pts].copy()
            obs_list = []
            for k in kfs:
                sel = np.nonzero(k.mp_ids >= 0)[0]
                sel = sel[mark[k.mp_ids[sel]]]
                obs_list.append((k, sel, k.mp_ids[sel]))
        Ts = np.array([k.T_cw for k in kfs])
        fixed_mask = np.array([k.id in fixed_ids for k in kfs])
        lookup = np.full(map_.n, -1, dtype=np.int64)
        lookup[pts] = np.arange(len(pts))
        cam_idx = np.concatenate([np.full(len(sel), c) for c, (k, sel, m) in enumerate(obs_list)])
        pt_idx = lookup[np.concatenate([m for _, _, m in obs_list])]
        uv = np.concatenate([k.uv[sel] for k, sel, _ in obs_list]).astype(float)
        urr = np.concatenate([k.ur[sel] for k, sel, _ in obs_list]).astype(float)
        stereo = urr >= 0
        obs = np.column_stack([uv, np.where(stereo, urr, 0.0)])
        info = np.concatenate([k.inv_level_sigma2[k.octave[sel]] for k, sel, _ in obs_list])
        row_w = texture_row_weights(obs_list)
        K0 = kf
        ba_args = (Ts, fixed_mask, pos, cam_idx, pt_idx, obs, stereo, info,
                   (K0.fx, K0.fy, K0.cx, K0.cy, K0.bf), iterations)
        planar = getattr(map_, "planar", None)
        edges = odometry_edges(kfs, fixed_mask) if ODOM_EDGES else None
        if worker is not None:
            Ts_new, pos_new = worker.run(ba_args, {"tol": tol, "row_w": row_w, "planar": planar,
                                                   "pose_edges": edges}, abort=abort)
        else:
            Ts_new, pos_new = bundle_adjust(*ba_args, abort=abort, tol=tol, row_w=row_w,
                                            planar=planar, pose_edges=edges)
        new_pos = pos_new
        new_T = {k.id: inv_T(Ts_new[c]) for c, k in enumerate(kfs)
                 if not fixed_mask[c] and k in local}
        n_out = 0
        with map_.lock:
            for k in local:
                if k.id in new_T and not k.bad:
                    k.set_pose(normalize_pose(inv_T(new_T[k.id])))
            alive = ~map_.mp_bad[pts]
            map_.mp_pos[pts[alive]] = new_pos[alive]
            # erase observations that are outliers after the optimization (chi2 test), all
            # observations at once with the keyframes' poses now; per keyframe only the erasing
            Tc = np.array([k.T_cw for k in kfs])[cam_idx]
            mids_all = np.concatenate([m for _, _, m in obs_list])
            Pc = np.einsum("nij,nj->ni", Tc[:, :3, :3], map_.mp_pos[mids_all]) + Tc[:, :3, 3]
            z = Pc[:, 2]
            iz = 1.0 / np.where(np.abs(z) < 1e-9, 1e-9, z)
            u = K0.fx * Pc[:, 0] * iz + K0.cx
            e = np.stack([obs[:, 0] - u, obs[:, 1] - (K0.fy * Pc[:, 1] * iz + K0.cy),
                          np.where(stereo, obs[:, 2] - (u - K0.bf * iz), 0.0)], axis=1)
            chi2 = info * np.einsum("ij,ij->i", e, e)
            bad_all = (chi2 > np.where(stereo, CHI2_STEREO, CHI2_MONO)) | (z <= 0)
            ends = np.cumsum([len(sel) for _, sel, _ in obs_list])
            for (k, sel, mids), end in zip(obs_list, ends):
                bad = bad_all[end - len(sel):end]
                if k.bad or not np.any(bad):
                    continue
                bad = bad & (k.mp_ids[sel] == mids)   # still the same point at that keypoint
                if np.any(bad):
                    n_out += int(np.count_nonzero(bad))
                    map_.erase_observations(k, sel[bad])
            map_.update_normal_and_depth(pts[~map_.mp_bad[pts]])
        return sorted(new_T), n_out

    # ------------------------------------------------------------------ essential graph
    @staticmethod
    def optimize_essential_graph(poses_wc: Dict[int, np.ndarray], edges: List[Tuple[int, int, np.ndarray]],
                                 fixed: int, iterations: int = 20) -> Dict[int, np.ndarray]:
        """SE(3) pose graph: ``edges`` (i, j, T_i_j measured[, information scale]) as
        BetweenFactorPose3 over keyframe poses T_w_c (stereo: scale is observable, so SE(3)
        instead of ORB-SLAM's Sim(3)). Without a scale every edge has the same sigmas.
        Returns optimised {kf_id: T_w_c}."""
        import gtsam
        from gtsam.symbol_shorthand import X
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        for k, T in poses_wc.items():
            values.insert(X(k), gtsam.Pose3(T))
        graph.add(gtsam.NonlinearEqualityPose3(X(fixed), gtsam.Pose3(poses_wc[fixed])))
        sig = np.array([0.01, 0.01, 0.01, 0.02, 0.02, 0.02])
        noise = gtsam.noiseModel.Diagonal.Sigmas(sig)
        models = {}
        for e in edges:
            i, j, Tij = e[:3]
            model = noise
            if len(e) > 3 and e[3] is not None:   # information scale (e.g. shared points / 100)
                w = float(np.clip(e[3], 0.05, 100.0))
                key = round(w, 3)
                if key not in models:
                    models[key] = gtsam.noiseModel.Diagonal.Sigmas(sig / np.sqrt(key))
                model = models[key]
            graph.add(gtsam.BetweenFactorPose3(X(i), X(j), gtsam.Pose3(Tij), model))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(iterations)
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        return {k: result.atPose3(X(k)).matrix() for k in poses_wc}


def essential_graph_job(poses_wc, edges, fixed: int, iterations: int = 20, abort=None):
    """:meth:`Optimizer.optimize_essential_graph` as a BAWorker child's job (``abort`` unused:
    GTSAM's optimizer runs to the end)."""
    return Optimizer.optimize_essential_graph(poses_wc, edges, fixed, iterations=iterations)


# ---------------------------------------------------------------------- global bundle adjustment
def bundle_adjust_sparse(Ts: np.ndarray, fixed: np.ndarray, P: np.ndarray, cam_idx: np.ndarray,
                         pt_idx: np.ndarray, obs: np.ndarray, stereo: np.ndarray,
                         info: np.ndarray, intr, iterations: int = 10, lm_lambda: float = 1e-3,
                         abort=None, row_w: Optional[np.ndarray] = None, tol: float = 0.0):
    """:func:`bundle_adjust` for many cameras (global BA): the same robust LM with the Schur
    complement and the same outlier rounds, but the (6 C x 3 M) camera-point block matrix W is a
    scipy.sparse matrix, so memory grows with the observations instead of cameras x points (the
    dense W of the local solver would be gigabytes for a whole map). Returns (Ts, P, inlier mask
    of the observations after the last outlier round). ``tol``: as :func:`bundle_adjust`'s."""
    Ts, P, active, (e, Pc, _) = _robust_lm(Ts, fixed, P, cam_idx, pt_idx, obs, stereo, info,
                                           intr, iterations, lm_lambda, abort, tol, sparse=True,
                                           row_w=row_w)
    chi2_th = np.where(stereo, CHI2_STEREO, CHI2_MONO)
    _, chi2 = _huber_cost(e, info, np.sqrt(chi2_th), active)
    inlier = active & (chi2 <= chi2_th) & (Pc[:, 2] > 0)
    return Ts, P, inlier


def global_bundle_adjustment(map_, iterations: int = 10, fixed_id: Optional[int] = None,
                             abort=None, lock_solve: bool = True,
                             min_observers: int = 2, min_kf_points: int = 0,
                             worker=None, tol: float = 0.0) -> Dict[str, object]:
    """ORB-SLAM2 RunGlobalBundleAdjustment: every live keyframe and map point optimised together
    (the first keyframe, or ``fixed_id``, held), then the result written back. Keyframes and
    points created while the solver ran (``lock_solve=False``: the map lock is released during
    the solve, so tracking goes on) follow their spanning-tree ancestor / reference keyframe, as
    ORB-SLAM2 propagates the GBA correction. Observations that are outliers after the solve are
    erased. Keyframes observing fewer than ``min_kf_points`` of the optimised points are left
    out of the solve and follow their ancestor like those added meanwhile: a pose over a handful
    of points is unconstrained (on office_loop seed 1 such a keyframe at the loop junction went
    3 km off and the solve took 36 s), and holding it instead lets its few points bend the loop.
    ``worker`` (a :class:`~mdr_slam.pose.ba_process.BAWorker`) solves in a child process: its
    numpy/scipy steps, some of which hold the GIL for tens of milliseconds, then never stall the
    tracking thread.
    Returns {"moved": kf ids, "outliers": n, "keyframes": n, "points": n, "followers": n}."""
    with map_.lock:
        kfs = sorted(map_.good_keyframes(), key=lambda k: k.id)
        if len(kfs) < 2:
            return {"moved": [], "outliers": 0, "keyframes": len(kfs), "points": 0}
        fid = kfs[0].id if fixed_id is None or fixed_id not in map_.keyframes else fixed_id
        n_pts = map_.n
        obs_list = []
        for c, k in enumerate(kfs):
            sel = np.nonzero(k.mp_ids >= 0)[0]
            ids = k.mp_ids[sel]
            good = ~map_.mp_bad[ids]
            obs_list.append((k, sel[good], ids[good]))
        all_ids = np.concatenate([m for _, _, m in obs_list])
        # points seen by at least min_observers keyframes constrain poses; the rest follow
        cnt = np.bincount(all_ids, minlength=n_pts)
        pts = np.nonzero(cnt >= max(2, int(min_observers)))[0]
        n_follow = 0
        if min_kf_points > 0:
            has = np.zeros(n_pts, dtype=bool)
            has[pts] = True
            strong = [c for c, (k, _, ids) in enumerate(obs_list)
                      if k.id == fid or np.count_nonzero(has[ids]) >= min_kf_points]
            n_follow = len(kfs) - len(strong)
            if n_follow:   # out of the solve; they follow their ancestor below
                kfs = [kfs[c] for c in strong]
                obs_list = [obs_list[c] for c in strong]
                all_ids = np.concatenate([m for _, _, m in obs_list])
                cnt = np.bincount(all_ids, minlength=n_pts)
                pts = np.nonzero(cnt >= max(2, int(min_observers)))[0]
        lookup = np.full(n_pts, -1, dtype=np.int64)
        lookup[pts] = np.arange(len(pts))
        cam_l, pt_l, uv_l, ur_l, inf_l, kp_l = [], [], [], [], [], []
        used = []
        for c, (k, sel, ids) in enumerate(obs_list):
            m = lookup[ids] >= 0
            sel, ids = sel[m], ids[m]
            used.append((k, sel, ids))
            cam_l.append(np.full(len(sel), c))
            pt_l.append(lookup[ids])
            uv_l.append(k.uv[sel])
            ur_l.append(k.ur[sel])
            inf_l.append(k.inv_level_sigma2[k.octave[sel]])
            kp_l.append(sel)
        Ts = np.array([k.T_cw for k in kfs])
        T_used = {k.id: k.T_cw.copy() for k in kfs}
        P0 = map_.mp_pos[pts].copy()
        K0 = kfs[0]
        intr = (K0.fx, K0.fy, K0.cx, K0.cy, K0.bf)
        row_w = texture_row_weights(used)
    if len(pts) == 0:
        return {"moved": [], "outliers": 0, "keyframes": len(kfs), "points": 0}
    cam_idx = np.concatenate(cam_l)
    pt_idx = np.concatenate(pt_l)
    uv = np.concatenate(uv_l).astype(float)
    urr = np.concatenate(ur_l).astype(float)
    stereo = urr >= 0
    obs = np.column_stack([uv, np.where(stereo, urr, 0.0)])
    info = np.concatenate(inf_l).astype(float)
    fixed = np.array([k.id == fid for k in kfs])

    def solve():
        args = (Ts, fixed, P0, cam_idx, pt_idx, obs, stereo, info, intr)
        if worker is not None:
            return worker.run(args, {"iterations": iterations, "row_w": row_w, "tol": tol},
                              abort=abort, solver="bundle_adjust_sparse")
        return bundle_adjust_sparse(*args, iterations=iterations, abort=abort, row_w=row_w,
                                    tol=tol)
    if lock_solve:
        with map_.lock:
            Ts_new, P_new, inlier = solve()
    else:
        Ts_new, P_new, inlier = solve()
    n_out = 0
    with map_.lock:
        new_cw = {k.id: normalize_pose(Ts_new[c]) for c, k in enumerate(kfs)}
        # correction of each optimised keyframe, in world: C = T_wc_new T_cw_used
        # keyframes added meanwhile follow their nearest optimised ancestor
        moved = []
        follow_C = {}
        for k in map_.good_keyframes():
            if k.id in new_cw:
                continue
            a = k.parent
            while a is not None and a.id not in new_cw:
                a = a.parent
            if a is None:
                continue
            C = inv_T(new_cw[a.id]) @ T_used[a.id]
            k.set_pose(k.T_cw @ inv_T(C))
            follow_C[k.id] = C
            moved.append(k.id)
        # points: optimised ones take the solution; the others follow their reference keyframe
        alive = ~map_.mp_bad[pts]
        map_.mp_pos[pts[alive]] = P_new[alive]
        rest = np.nonzero(~map_.mp_bad[: map_.n])[0]
        rest = rest[~np.isin(rest, pts)]
        if len(rest):
            ref = map_.mp_ref_kf[rest]
            for kid in np.unique(ref).tolist():
                if kid not in new_cw and kid not in follow_C:
                    continue
                sel = rest[ref == kid]
                C = inv_T(new_cw[kid]) @ T_used[kid] if kid in new_cw else follow_C[kid]
                map_.mp_pos[sel] = map_.mp_pos[sel] @ C[:3, :3].T + C[:3, 3]
        for c, k in enumerate(kfs):
            if not k.bad:
                k.set_pose(new_cw[k.id])
                moved.append(k.id)
        # erase the observations the solver rejected (still the same point at that keypoint)
        cam_o = cam_idx[~inlier]
        kp_o = np.concatenate(kp_l)[~inlier]
        pid_o = pts[pt_idx[~inlier]]
        for c in np.unique(cam_o).tolist():
            k = kfs[c]
            if k.bad:
                continue
            m = cam_o == c
            kp, pid = kp_o[m], pid_o[m]
            same = k.mp_ids[kp] == pid
            if np.any(same):
                n_out += int(np.count_nonzero(same))
                map_.erase_observations(k, kp[same])
        live = np.nonzero(~map_.mp_bad[: map_.n])[0]
        map_.update_normal_and_depth(live)
    return {"moved": sorted(moved), "outliers": n_out, "keyframes": len(kfs), "points": len(pts),
            "followers": n_follow}
