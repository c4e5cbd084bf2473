"""Triangle mesh of the map (the paper's Fig. 8a): depth frames fused into Open3D's
ScalableTSDFVolume, marching cubes, PLY.

The fusion node keeps map points, not depth images, so :func:`mesh_from_map` first renders depth
images of the map from a set of viewpoints (the camera poses of the run, a TUM trajectory, or
automatic views inside and around the map) by z-buffer splatting: every point covers a square of
about ``focal * point_size / depth`` pixels, the nearest depth per pixel wins (``np.minimum.at``),
and points whose normal faces away from the camera are culled so the back of a thin wall does not
show through. Those depth images go through the same TSDF as real depth frames
(:func:`tsdf_mesh`, which the offline runner feeds with the depth node's frames).
"""
from __future__ import annotations

from typing import Iterable, List, Optional, Sequence, Tuple

import numpy as np

from ..geometry import inv_T, transform_points

__all__ = ["default_K", "render_depth", "auto_views", "views_from_trajectory", "tsdf_mesh",
           "mesh_from_map", "write_mesh"]


def default_K(width: int = 640, height: int = 480, hfov_deg: float = 90.0) -> np.ndarray:
    """Pinhole intrinsics of a virtual camera with horizontal field of view ``hfov_deg``."""
    f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0, (width - 1) / 2.0], [0, f, (height - 1) / 2.0], [0, 0, 1.0]])


def render_depth(points: np.ndarray, K: np.ndarray, T_map_cam: np.ndarray, width: int, height: int,
                 point_size: float = 0.02, normals: Optional[np.ndarray] = None,
                 intensity: Optional[np.ndarray] = None, max_splat: int = 4, near: float = 0.05,
                 far: float = 50.0) -> Tuple[np.ndarray, np.ndarray]:
    """Z-buffer splat of map points into a (height, width) depth image (metres, 0 = empty).

    Returns ``(depth float32, intensity float32)`` (intensity of the visible point, 0 if none).
    """
    P = transform_points(inv_T(np.asarray(T_map_cam, float)), np.asarray(points, float))
    z = P[:, 2]
    keep = (z > near) & (z < far)
    if normals is not None:
        n_cam = np.asarray(normals, float) @ np.asarray(T_map_cam, float)[:3, :3]
        # back-face culling: the surface must face the camera (n . (0 - p) > 0)
        keep &= np.einsum("ij,ij->i", n_cam, -P) > 0
    P, z = P[keep], z[keep]
    nc = n_cam[keep] if normals is not None else None
    I = np.zeros(len(P)) if intensity is None else np.asarray(intensity, float)[keep]
    u = K[0, 0] * P[:, 0] / z + K[0, 2]
    v = K[1, 1] * P[:, 1] / z + K[1, 2]
    ui, vi = np.round(u).astype(np.int64), np.round(v).astype(np.int64)
    half = np.clip(np.ceil(0.5 * K[0, 0] * point_size / z - 0.5), 0, max_splat).astype(np.int64)
    zbuf = np.full(width * height, np.inf)
    idx_all, z_all, i_all = [], [], []
    hmax = int(half.max()) if len(half) else 0
    for dy in range(-hmax, hmax + 1):          # loop over splat offsets, not over points
        for dx in range(-hmax, hmax + 1):
            r = max(abs(dx), abs(dy))
            sel = half >= r
            uu, vv = ui[sel] + dx, vi[sel] + dy
            ins = (uu >= 0) & (uu < width) & (vv >= 0) & (vv < height)
            idx_all.append(vv[ins] * width + uu[ins])
            zs = z[sel][ins]
            if nc is not None and r > 0:
                # surfel splat: depth of the point's tangent plane along the pixel's ray
                # (z = n.p / n.ray), so oblique surfaces are not pulled towards the camera
                n_s, p_s = nc[sel][ins], P[sel][ins]
                ray = np.stack([(uu[ins] - K[0, 2]) / K[0, 0], (vv[ins] - K[1, 2]) / K[1, 1],
                                np.ones(len(zs))], axis=1)
                num = np.einsum("ij,ij->i", n_s, p_s)
                den = np.einsum("ij,ij->i", n_s, ray)
                with np.errstate(divide="ignore", invalid="ignore"):
                    zp = num / den
                lim = 2.0 * point_size
                zs = np.where(np.isfinite(zp) & (np.abs(zp - zs) < lim), zp, zs)
            z_all.append(zs)
            i_all.append(I[sel][ins])
    if idx_all:
        idx = np.concatenate(idx_all)
        zz = np.concatenate(z_all)
        ii = np.concatenate(i_all)
        np.minimum.at(zbuf, idx, zz)
        win = zz == zbuf[idx]
        ibuf = np.zeros(width * height)
        ibuf[idx[win]] = ii[win]
    else:
        ibuf = np.zeros(width * height)
    depth = np.where(np.isfinite(zbuf), zbuf, 0.0).reshape(height, width).astype(np.float32)
    return depth, ibuf.reshape(height, width).astype(np.float32)


def _look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """T_map_cam of an optical-frame camera (z forward, y down) at ``eye`` looking at ``target``."""
    zc = target - eye
    zc = zc / np.linalg.norm(zc)
    yc = -up - np.dot(-up, zc) * zc
    if np.linalg.norm(yc) < 1e-6:  # looking straight up/down
        yc = np.cross(zc, [1.0, 0, 0]) if abs(zc[0]) < 0.9 else np.cross(zc, [0, 1.0, 0])
    yc = yc / np.linalg.norm(yc)
    xc = np.cross(yc, zc)
    T = np.eye(4)
    T[:3, :3] = np.stack([xc, yc, zc], axis=1)
    T[:3, 3] = eye
    return T


def auto_views(points: np.ndarray, up_axis: str = "z", n_yaw: int = 8,
               inside: bool = True, outside: bool = True) -> List[np.ndarray]:
    """Viewpoints covering a map without a trajectory.

    ``inside``: from the centre of the bounding box looking outwards in ``n_yaw`` directions
    (rooms, corridors); ``outside``: from a circle around the box looking at its centre (objects).
    Back-face culling in :func:`render_depth` keeps each view to the surfaces that face it.
    """
    from .grid import grid_axes
    P = np.asarray(points, float)
    if len(P) == 0:
        return []
    A = grid_axes(up_axis)
    gx, gy, up = A
    lo, hi = np.percentile(P, 1, axis=0), np.percentile(P, 99, axis=0)
    c = 0.5 * (lo + hi)
    radius = 0.75 * float(np.linalg.norm(hi - lo)) + 0.5
    views = []
    for k in range(n_yaw):
        a = 2 * np.pi * k / n_yaw
        d = np.cos(a) * gx + np.sin(a) * gy
        if inside:
            views.append(_look_at(c, c + d, up))
        if outside:
            eye = c + radius * d + 0.3 * radius * up
            views.append(_look_at(eye, c, up))
    return views


def views_from_trajectory(path_or_Ts, min_distance: float = 0.2, min_angle_deg: float = 10.0,
                          max_views: int = 300) -> List[np.ndarray]:
    """Camera poses (T_map_cam) from a trajectory file (TUM/KITTI/EuRoC) or a list of 4x4s,
    keeping a pose only after the camera moved ``min_distance`` or turned ``min_angle_deg``."""
    from ..geometry import relative_motion
    if isinstance(path_or_Ts, str):
        from ..io import read_trajectory
        Ts = read_trajectory(path_or_Ts).matrices()
    else:
        Ts = [np.asarray(T, float) for T in path_or_Ts]
    out = []
    for T in Ts:  # a loop over poses (hundreds), not over points
        if not out:
            out.append(T)
            continue
        d, a = relative_motion(out[-1], T)
        if d >= min_distance or np.degrees(a) >= min_angle_deg:
            out.append(T)
    if len(out) > max_views:
        out = [out[i] for i in np.linspace(0, len(out) - 1, max_views).round().astype(int)]
    return out


def tsdf_mesh(frames: Iterable, voxel_length: float = 0.02, sdf_trunc: Optional[float] = None,
              depth_trunc: float = 8.0):
    """Fuse depth frames into a ScalableTSDFVolume and extract a triangle mesh (Open3D).

    ``frames``: iterable of ``(depth (H, W) metres, K 3x3, T_map_cam)`` or
    ``(depth, K, T_map_cam, intensity (H, W))``; zero/NaN depth is empty. Returns an
    ``open3d.geometry.TriangleMesh`` in ``map`` with vertex normals (and gray colours from the
    intensity when given).
    """
    import open3d as o3d
    vol = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=float(voxel_length),
        sdf_trunc=float(sdf_trunc) if sdf_trunc else 4.0 * float(voxel_length),
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
    for fr in frames:
        depth, K, T = fr[0], np.asarray(fr[1], float), np.asarray(fr[2], float)
        depth = np.ascontiguousarray(np.nan_to_num(np.asarray(depth, np.float32), nan=0.0))
        h, w = depth.shape
        if len(fr) > 3 and fr[3] is not None:
            inten = np.asarray(fr[3], np.float64)
            mx = float(inten.max()) if inten.size else 0.0
            g = (inten / mx * 255.0 if mx > 1.0 else inten * 255.0) if mx > 0 else inten
            g = np.clip(g, 0, 255).astype(np.uint8)
        else:
            g = np.full((h, w), 200, np.uint8)
        color = np.ascontiguousarray(np.repeat(g[:, :, None], 3, axis=2))
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(color), o3d.geometry.Image(depth), depth_scale=1.0,
            depth_trunc=float(depth_trunc), convert_rgb_to_intensity=False)
        intr = o3d.camera.PinholeCameraIntrinsic(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        vol.integrate(rgbd, intr, inv_T(T))
    mesh = vol.extract_triangle_mesh()
    mesh.compute_vertex_normals()
    return mesh


def mesh_from_map(cloud, views: Optional[Sequence[np.ndarray]] = None, K: Optional[np.ndarray] = None,
                  width: int = 640, height: int = 480, voxel_length: float = 0.02,
                  point_size: Optional[float] = None, min_confidence: int = 0,
                  up_axis: str = "z", depth_trunc: float = 8.0, sdf_trunc: Optional[float] = None):
    """Mesh of a map: a :class:`VoxelMap` or a cloud dict (x, y, z[, nx, ny, nz, intensity,
    confidence]). ``views``: T_map_cam list (default :func:`auto_views`); ``K`` default
    :func:`default_K`. Returns ``(mesh, n_views)``."""
    from .voxel_map import VoxelMap
    if isinstance(cloud, VoxelMap):
        point_size = point_size or cloud.voxel_size
        cloud = cloud.to_cloud(min_confidence)
    elif min_confidence and "confidence" in cloud:
        keep = np.asarray(cloud["confidence"]) >= min_confidence
        cloud = {k: np.asarray(v)[keep] for k, v in cloud.items()}
    P = np.stack([cloud["x"], cloud["y"], cloud["z"]], 1).astype(float)
    N = None
    if all(k in cloud for k in ("nx", "ny", "nz")):
        N = np.stack([cloud["nx"], cloud["ny"], cloud["nz"]], 1).astype(float)
        if not np.any(np.linalg.norm(N, axis=1) > 0.5):
            N = None
    I = np.asarray(cloud["intensity"], float) if "intensity" in cloud else None
    K = default_K(width, height) if K is None else np.asarray(K, float)
    point_size = point_size or voxel_length
    views = auto_views(P, up_axis) if views is None else list(views)

    def frames():
        for T in views:
            d, i = render_depth(P, K, T, width, height, 1.5 * point_size, N, I)
            yield d, K, T, i

    mesh = tsdf_mesh(frames(), voxel_length, sdf_trunc, depth_trunc)
    return mesh, len(views)


def write_mesh(path: str, mesh) -> Tuple[int, int]:
    """Write a triangle mesh (PLY, binary) atomically; returns (n_vertices, n_triangles)."""
    import os
    import open3d as o3d
    from ..io import atomic_path
    ext = os.path.splitext(path)[1].lower() or ".ply"
    with atomic_path(path, ext) as tmp:
        if not o3d.io.write_triangle_mesh(tmp, mesh, write_ascii=False):
            raise IOError("Open3D could not write the mesh to %s" % path)
    return len(mesh.vertices), len(mesh.triangles)
