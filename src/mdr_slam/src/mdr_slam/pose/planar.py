"""Planar motion: a camera on a ground robot that drives on a flat floor.

The robot's base_link keeps its height and stays level in ``map`` (REP-105: map is z-up, base_link
where tracking started), so of a camera pose's six degrees of freedom three remain: x, y and yaw
of the base. Tracking and the local BA then solve for those three only and every keyframe pose
is kept on the plane. In weak texture, where a few features on one wall leave the height, roll
and pitch nearly free, the out-of-plane error no longer leaks into the map and into x, y and yaw
(RTAB-Map's Reg/Force3DoF; ORB-SLAM2 has no counterpart).

Poses are ``T_cw`` of the tracker's world (the first camera's frame); ``T_map_world`` places that
world in map, and ``T_base_cam`` is the camera's mount on the base (both from tf).
"""
from __future__ import annotations

import numpy as np

from ..geometry import inv_T

__all__ = ["PlanarMotion"]


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def _axis_rotation(n: np.ndarray, theta: float) -> np.ndarray:
    K = _skew(n)
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


class PlanarMotion:
    """The floor plane of a ground robot in the tracker's world, and the poses that keep to it."""

    def __init__(self, T_map_world: np.ndarray, T_base_cam: np.ndarray,
                 base_height: float = 0.0):
        self.T_map_world = np.asarray(T_map_world, float).copy()
        self.T_world_map = inv_T(self.T_map_world)
        self.T_base_cam = np.asarray(T_base_cam, float).copy()
        self.T_cam_base = inv_T(self.T_base_cam)
        self.base_height = float(base_height)
        R_wm = self.T_world_map[:3, :3]
        # map's x, y (in-plane) and z (the floor's normal) axes in the world
        self.u1, self.u2, self.n = R_wm[:, 0].copy(), R_wm[:, 1].copy(), R_wm[:, 2].copy()

    def base_in_map(self, T_cw: np.ndarray) -> np.ndarray:
        """T_map_base of a camera pose."""
        return self.T_map_world @ inv_T(T_cw) @ self.T_cam_base

    def off_plane(self, T_cw: np.ndarray):
        """(height above the plane in m, tilt in rad) of the base at camera pose ``T_cw``."""
        T = self.base_in_map(T_cw)
        return float(T[2, 3] - self.base_height), float(np.arctan2(np.hypot(T[0, 2], T[1, 2]),
                                                                     T[2, 2]))

    def project(self, T_cw: np.ndarray) -> np.ndarray:
        """The nearest planar pose: the base put on the plane, level, with its heading kept."""
        T = self.base_in_map(T_cw)
        x = T[:3, 0]   # the base's forward axis: its heading in the plane
        yaw = np.arctan2(x[1], x[0]) if abs(x[0]) + abs(x[1]) > 1e-9 else \
            np.arctan2(-T[0, 1], T[1, 1])
        c, s = np.cos(yaw), np.sin(yaw)
        P = np.eye(4)
        P[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        P[:2, 3] = T[:2, 3]
        P[2, 3] = self.base_height
        return inv_T(self.T_world_map @ P @ self.T_base_cam)

    def basis(self, T_cw: np.ndarray) -> np.ndarray:
        """(6, 3): the left perturbations [rho, phi] of ``T_cw`` (T <- [exp(phi) | rho] T, the
        optimizers' update) that move the base along map x, along map y and turn it about the
        floor's normal: a world motion G gives T_cw G^-1, whose left form is
        rho = -R v + theta (R n) x t, phi = -theta R n for T_cw = [R | t]."""
        R, t = T_cw[:3, :3], T_cw[:3, 3]
        Rn = R @ self.n
        B = np.zeros((6, 3))
        B[:3, 0] = -R @ self.u1
        B[:3, 1] = -R @ self.u2
        B[:3, 2] = np.cross(Rn, t)
        B[3:, 2] = -Rn
        return B

    def update(self, T_cw: np.ndarray, xi: np.ndarray) -> np.ndarray:
        """``T_cw`` moved by ``xi`` = (x, y, yaw) of :meth:`basis`, exactly in the plane."""
        G = np.eye(4)
        G[:3, :3] = _axis_rotation(self.n, float(xi[2]))
        G[:3, 3] = float(xi[0]) * self.u1 + float(xi[1]) * self.u2
        return T_cw @ inv_T(G)
