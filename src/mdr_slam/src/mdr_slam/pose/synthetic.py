"""A tiny ray caster of a textured box room, for tests and benchmarks of the tracker.

Every pixel's ray is intersected with the room's six axis-aligned walls (vectorized: the exit
distance of a ray from a box is the smallest positive per-axis distance) and the wall texture is
sampled with cv2.remap from an atlas of multi-scale random block textures (blocks give ORB corners
at several pyramid levels). Exact ground truth, deterministic, no download. The project simulator
(mdr_slam.sim) is the full-featured renderer; this one exists so the pose tests do not depend on it.
"""
from __future__ import annotations

from typing import List, Tuple

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import make_T

__all__ = ["BoxRoom", "orbit_trajectory"]


class BoxRoom:
    def __init__(self, half_extent=(5.0, 2.0, 5.0), tex_size: int = 1024, seed: int = 0):
        self.h = np.asarray(half_extent, dtype=float)
        rng = np.random.RandomState(seed)
        faces = []
        for _ in range(6):
            t = np.zeros((tex_size, tex_size), np.float32)
            for cells, amp in ((24, 0.5), (96, 0.3), (384, 0.2)):
                blocks = rng.rand(cells, cells).astype(np.float32)
                t += amp * cv2.resize(blocks, (tex_size, tex_size), interpolation=cv2.INTER_NEAREST)
            t = cv2.GaussianBlur(t, (3, 3), 0.8)
            faces.append(np.clip(t * 255.0, 0, 255).astype(np.float32))
        self.tex_size = tex_size
        self.atlas = np.concatenate(faces, axis=1)   # faces side by side

    def render(self, T_wc: np.ndarray, fx, fy, cx, cy, width, height) -> np.ndarray:
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        d = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1) @ T_wc[:3, :3].T
        o = T_wc[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            t_axes = (np.sign(d) * self.h - o) / d                    # (H, W, 3), exit per axis
        t_axes = np.where(np.isfinite(t_axes) & (t_axes > 0), t_axes, np.inf)
        axis = np.argmin(t_axes, axis=-1)
        t = np.take_along_axis(t_axes, axis[..., None], -1)[..., 0]
        p = o + d * t[..., None]
        face = axis * 2 + (np.take_along_axis(d, axis[..., None], -1)[..., 0] > 0)
        a1 = np.where(axis == 0, 1, 0)
        a2 = np.where(axis == 2, 1, 2)
        s1 = np.take_along_axis(p, a1[..., None], -1)[..., 0]
        s2 = np.take_along_axis(p, a2[..., None], -1)[..., 0]
        h1, h2 = self.h[a1], self.h[a2]
        ts = self.tex_size - 1
        mx = ((s1 + h1) / (2 * h1) * ts + face * self.tex_size).astype(np.float32)
        my = ((s2 + h2) / (2 * h2) * ts).astype(np.float32)
        img = cv2.remap(self.atlas, mx, my, cv2.INTER_LINEAR)
        return np.clip(img, 0, 255).astype(np.uint8)

    def render_stereo(self, T_wc, camera) -> Tuple[np.ndarray, np.ndarray]:
        w, h = camera.size
        args = (camera.fx, camera.fy, camera.cx, camera.cy, w, h)
        left = self.render(T_wc, *args)
        # the right camera's own principal point (StereoCamera.doffs = cx_left - cx_right)
        args_r = (camera.fx, camera.fy, camera.cx - getattr(camera, "doffs", 0.0), camera.cy, w, h)
        right = self.render(T_wc @ make_T(np.eye(3), [camera.baseline, 0, 0]), *args_r)
        return left, right


def orbit_trajectory(n: int, radius: float = 1.5, arc: float = 2 * np.pi, height: float = 0.0,
                     yaw_offset: float = 0.0) -> List[np.ndarray]:
    """Camera poses T_wc on a horizontal circle (y is down in the optical frame), looking along
    the tangent plus ``yaw_offset``; ``arc`` = 2 pi closes the loop."""
    out = []
    for k in range(n):
        a = arc * k / max(1, n)
        pos = np.array([radius * np.sin(a), height, radius * np.cos(a) - radius])
        R = Rotation.from_euler("y", a + np.pi / 2 + yaw_offset).as_matrix()
        out.append(make_T(R, pos))
    return out
