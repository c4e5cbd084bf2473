"""Rigid-body geometry shared by every module: SE(3) matrices, quaternions, point transforms.

Conventions (REP-103): metres, right-handed frames. A pose ``T_a_b`` is the 4x4 matrix that maps
points expressed in frame ``b`` into frame ``a`` (so ``T_map_cam`` is the camera pose in the map).
Quaternions are ``(x, y, z, w)`` as in ROS messages unless a name says ``wxyz``.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "parse_transform", "R_OPTICAL", "T_BASE_OPTICAL", "base_to_camera",
    "make_T", "inv_T", "transform_points", "quat_to_R", "R_to_quat", "T_from_pos_quat",
    "pos_quat_from_T", "is_valid_T", "rotation_angle", "relative_motion", "body_twist",
]


# REP-103: an optical frame (x right, y down, z forward) in its x-forward, y-left, z-up body
# frame; the rotation of tf's static_transform_publisher "-pi/2 0 -pi/2"
R_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (uses R^T, not a general matrix inverse)."""
    R = T[:3, :3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def transform_points(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Apply ``T`` to an (N, 3) array of points, returning (N, 3) in the same dtype."""
    P = np.asarray(P)
    R = T[:3, :3].astype(P.dtype if P.dtype.kind == "f" else float)
    t = T[:3, 3].astype(R.dtype)
    return P @ R.T + t


def quat_to_R(q_xyzw) -> np.ndarray:
    """Rotation matrix from a quaternion (x, y, z, w); the quaternion need not be unit."""
    return Rotation.from_quat(np.asarray(q_xyzw, dtype=float)).as_matrix()


def R_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) with w >= 0 from a rotation matrix."""
    q = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    return q if q[3] >= 0 else -q


def T_from_pos_quat(p, q_xyzw) -> np.ndarray:
    return make_T(quat_to_R(q_xyzw), p)


def pos_quat_from_T(T: np.ndarray):
    """(position (3,), quaternion xyzw (4,)) of a 4x4 transform."""
    return T[:3, 3].copy(), R_to_quat(T[:3, :3])


def interpolate_poses(T0: np.ndarray, T1: np.ndarray, w) -> np.ndarray:
    """Poses a share ``w`` (n,) of the way from ``T0`` to ``T1`` (n, 4, 4): rotations along the
    geodesic (slerp), translations linear."""
    T0, T1 = np.asarray(T0, float).reshape(-1, 4, 4), np.asarray(T1, float).reshape(-1, 4, 4)
    w = np.broadcast_to(np.asarray(w, float), (len(T0),))
    R0 = Rotation.from_matrix(T0[:, :3, :3])
    rel = (R0.inv() * Rotation.from_matrix(T1[:, :3, :3])).as_rotvec()
    out = np.zeros_like(T0)
    out[:, :3, :3] = (R0 * Rotation.from_rotvec(rel * w[:, None])).as_matrix()
    out[:, :3, 3] = (1.0 - w)[:, None] * T0[:, :3, 3] + w[:, None] * T1[:, :3, 3]
    out[:, 3, 3] = 1.0
    return out


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, w: float) -> np.ndarray:
    """Pose a share ``w`` of the way from ``T0`` to ``T1`` (4x4): :func:`interpolate_poses`."""
    return interpolate_poses(T0, T1, w)[0]


def is_valid_T(T, tol: float = 1e-3) -> bool:
    """True when ``T`` is a finite rigid transform (orthonormal rotation, det +1)."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    # plain max-abs tests: np.allclose costs ~20 us a call, and this runs on every published pose
    if np.abs(R @ R.T - _EYE3).max() > tol or abs(np.linalg.det(R) - 1.0) > tol:
        return False
    return bool(np.abs(T[3] - _LAST_ROW).max() <= tol)


_EYE3 = np.eye(3)
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def rotation_angle(R: np.ndarray) -> float:
    """Angle (rad) of a rotation matrix."""
    c = (np.trace(R[:3, :3]) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def relative_motion(T_a: np.ndarray, T_b: np.ndarray):
    """Translation (m) and rotation (rad) between two poses of the same frame."""
    D = inv_T(T_a) @ T_b
    return float(np.linalg.norm(D[:3, 3])), rotation_angle(D[:3, :3])


def body_twist(T0: np.ndarray, T1: np.ndarray, dt: float):
    """Linear (m/s) and angular (rad/s) velocity, in the moving frame, that takes pose ``T0`` to
    ``T1`` in ``dt`` s (nav_msgs/Odometry's twist, given in its child frame)."""
    D = inv_T(T0) @ T1
    w = Rotation.from_matrix(D[:3, :3]).as_rotvec()
    return D[:3, 3] / dt, w / dt


def base_to_camera(text) -> np.ndarray:
    """T_base_cam from the ``base_to_camera`` parameter; empty: :data:`T_BASE_OPTICAL`, a level
    camera at base_link's origin looking along its x, so that a map anchored at base_link is
    z-up (REP-103/105) even when nothing says how the camera is mounted."""
    return parse_transform(text, default=T_BASE_OPTICAL.copy())


def parse_transform(text, default=None) -> np.ndarray:
    """4x4 matrix from "x y z qx qy qz qw" (or "x y z yaw pitch roll"), as static_transform_publisher."""
    if text is None or (isinstance(text, str) and not text.strip()):
        return np.eye(4) if default is None else default
    vals = [float(v) for v in (text.split() if isinstance(text, str) else text)]
    if len(vals) == 7:
        return make_T(quat_to_R(vals[3:]), vals[:3])
    if len(vals) == 6:
        return make_T(Rotation.from_euler("ZYX", vals[3:]).as_matrix(), vals[:3])
    raise ValueError("a transform is 'x y z qx qy qz qw' or 'x y z yaw pitch roll', got %r" % (text,))


# base_link -> camera optical frame of a level, forward-looking camera at base_link's origin
T_BASE_OPTICAL = make_T(R_OPTICAL, [0.0, 0.0, 0.0])
