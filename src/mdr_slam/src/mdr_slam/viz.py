"""Pictures of a map a person would rather look at than read: a top view and a perspective view,
coloured by height (or any per-point value), rendered by vectorized z-buffer splatting (no GUI, no
OpenGL: works on a headless robot computer and in CI).
"""
from __future__ import annotations

from typing import Optional, Sequence, Tuple

import cv2
import numpy as np

__all__ = ["top_view_image", "perspective_image", "save_map_pictures", "look_at", "drop_ceiling"]


def drop_ceiling(xyz: np.ndarray, up_axis: int = 2, band: float = 0.25, share: float = 0.08):
    """Mask of the points to draw: indoor maps have a ceiling that hides everything from above, so
    when more than ``share`` of the points lie within ``band`` metres of the top height, that layer
    is left out of the pictures (the map itself keeps it)."""
    h = np.asarray(xyz)[:, up_axis]
    if len(h) == 0:
        return np.ones(0, bool)
    top = np.percentile(h, 99.5)
    ceiling = h > top - band
    return ~ceiling if ceiling.mean() > share else np.ones(len(h), bool)


def _colormap(values: np.ndarray, lo: float, hi: float, name: str = "turbo") -> np.ndarray:
    """(N, 3) uint8 RGB of ``values`` through a matplotlib colormap."""
    # matplotlib (0.1 s, with pyplot 0.3 s, to import) only where a picture is drawn
    from matplotlib import colormaps
    t = np.clip((values - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    return (colormaps[name](t)[:, :3] * 255).astype(np.uint8)


def _robust_range(v: np.ndarray) -> Tuple[float, float]:
    if len(v) == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(v, [2, 98])
    return float(lo), float(hi if hi > lo else lo + 1.0)


def top_view_image(xyz: np.ndarray, values: Optional[np.ndarray] = None, resolution: float = 0.02,
                   up_axis: int = 2, margin: int = 10, max_size: int = 2000):
    """Orthographic view from above: per cell the highest point, coloured by ``values`` (default:
    height). Returns (RGB uint8 image, (x0, y0) of the image's lower-left corner, resolution)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    axes = [a for a in range(3) if a != up_axis]
    h = xyz[:, up_axis]
    vals = h if values is None else np.asarray(values, dtype=np.float64)
    if len(xyz) == 0:
        return np.full((64, 64, 3), 255, np.uint8), (0.0, 0.0), resolution
    lo_xy = xyz[:, axes].min(axis=0)
    span = xyz[:, axes].max(axis=0) - lo_xy
    resolution = max(resolution, float(span.max()) / max_size)
    ij = np.floor((xyz[:, axes] - lo_xy) / resolution).astype(np.int64) + margin
    W, H = int(ij[:, 0].max()) + margin + 1, int(ij[:, 1].max()) + margin + 1
    order = np.argsort(h, kind="stable")  # highest written last: it wins the cell
    img = np.full((H, W, 3), 255, np.uint8)
    lo, hi = _robust_range(vals)
    rgb = _colormap(vals[order], lo, hi)
    rows = H - 1 - ij[order, 1]           # image rows grow downwards, y grows upwards
    img[rows, ij[order, 0]] = rgb
    return img, (float(lo_xy[0] - margin * resolution), float(lo_xy[1] - margin * resolution)), \
        resolution


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0, 0, 1)):
    """T_world_cam of an optical-frame camera (z forward, y down) at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, dtype=float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0, 1, 0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def perspective_image(xyz: np.ndarray, values: Optional[np.ndarray] = None,
                      T_world_cam: Optional[np.ndarray] = None, size: Tuple[int, int] = (1280, 800),
                      fov_deg: float = 60.0, point_px: int = 2, up_axis: int = 2) -> np.ndarray:
    """Pinhole rendering with a z-buffer (nearest point wins), coloured by ``values`` (default:
    height) and darkened with distance for depth cues. Default view: from above and behind the
    map's centre, looking down at 55 degrees."""
    xyz = np.asarray(xyz, dtype=np.float64)
    W, H = size
    img = np.full((H, W, 3), 255, np.uint8)
    if len(xyz) == 0:
        return img
    vals = xyz[:, up_axis] if values is None else np.asarray(values, dtype=np.float64)
    if T_world_cam is None:
        c = np.median(xyz, axis=0)
        ext = np.percentile(xyz, 98, axis=0) - np.percentile(xyz, 2, axis=0)
        r = float(np.linalg.norm(ext)) * 1.0 + 1.0
        up = np.eye(3)[up_axis]
        horiz = np.eye(3)[[a for a in range(3) if a != up_axis][1]]
        eye = c - horiz * r * np.cos(np.radians(55)) + up * r * np.sin(np.radians(55))
        T_world_cam = look_at(eye, c, up)
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    P = (xyz - t) @ R                      # world -> camera: R^T (p - t)
    f = 0.5 * W / np.tan(np.radians(fov_deg) / 2)
    keep = P[:, 2] > 0.05
    P, vals = P[keep], vals[keep]
    u = np.round(f * P[:, 0] / P[:, 2] + W / 2).astype(np.int64)
    v = np.round(f * P[:, 1] / P[:, 2] + H / 2).astype(np.int64)
    lo, hi = _robust_range(vals)
    rgb = _colormap(vals, lo, hi).astype(np.float32)
    d = P[:, 2]
    shade = 1.0 - 0.5 * np.clip((d - d.min()) / max(np.ptp(d), 1e-9), 0, 1)
    rgb = (rgb * shade[:, None]).astype(np.uint8)
    order = np.argsort(-d, kind="stable")  # far first, near last: the nearest wins each pixel
    u, v, rgb = u[order], v[order], rgb[order]
    for du in range(point_px):
        for dv in range(point_px):
            uu, vv = u + du, v + dv
            ok = (uu >= 0) & (uu < W) & (vv >= 0) & (vv < H)
            img[vv[ok], uu[ok]] = rgb[ok]
    return img


def save_map_pictures(xyz: np.ndarray, out_prefix: str, values: Optional[np.ndarray] = None,
                      label: str = "height [m]", up_axis: int = 2, title: str = "MDR-SLAM map"):
    """Write ``<prefix>_top.png`` (with metric axes and a colour bar) and
    ``<prefix>_perspective.png``; returns the two paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    xyz = np.asarray(xyz)
    keep = drop_ceiling(xyz, up_axis)
    xyz = xyz[keep]
    values = None if values is None else np.asarray(values)[keep]
    img, (x0, y0), res = top_view_image(xyz, values, up_axis=up_axis)
    vals = xyz[:, up_axis] if values is None else np.asarray(values)
    lo, hi = _robust_range(vals)
    fig, ax = plt.subplots(figsize=(9, 7), dpi=110)
    ax.imshow(img, extent=(x0, x0 + img.shape[1] * res, y0, y0 + img.shape[0] * res),
              interpolation="nearest")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("%s: top view (%d points)" % (title, len(xyz)))
    fig.colorbar(ScalarMappable(Normalize(lo, hi), "turbo"), ax=ax, label=label, shrink=0.8)
    top = out_prefix + "_top.png"
    fig.savefig(top, bbox_inches="tight")
    plt.close(fig)
    persp = out_prefix + "_perspective.png"
    cv2.imwrite(persp, perspective_image(xyz, values, up_axis=up_axis)[:, :, ::-1])
    return top, persp


def read_xwd(path: str) -> np.ndarray:
    """An X Window Dump (what ``Xvfb -fbdir`` keeps its screen in) as an HxWx3 uint8 RGB image.

    TrueColor ZPixmap dumps of 24 or 32 bits per pixel, either byte order (Xvfb's own format);
    raises ValueError on anything else.
    """
    raw = np.fromfile(path, dtype=np.uint8)
    if raw.size < 100:
        raise ValueError("%s: not an XWD file (too short)" % path)
    h = raw[:100].view(">u4")
    header_size, version, fmt = int(h[0]), int(h[1]), int(h[2])
    width, height, byte_order = int(h[4]), int(h[5]), int(h[7])
    bpp, bytes_per_line = int(h[11]), int(h[12])
    masks = [int(m) for m in h[14:17]]
    ncolors = int(h[19])
    if version != 7 or fmt != 2 or bpp not in (24, 32):
        raise ValueError("%s: unsupported XWD (version %d, format %d, %d bits per pixel)"
                         % (path, version, fmt, bpp))
    start = header_size + 12 * ncolors
    size = height * bytes_per_line
    if raw.size < start + size:
        raise ValueError("%s: truncated XWD (%d of %d bytes)" % (path, raw.size, start + size))
    rows = raw[start:start + size].reshape(height, bytes_per_line)
    step = bpp // 8
    px = rows[:, :width * step].reshape(height, width, step).astype(np.uint32)
    if step == 3:
        px = np.concatenate([px, np.zeros((height, width, 1), np.uint32)], axis=2)
    order = [0, 1, 2, 3] if byte_order == 0 else [3, 2, 1, 0]   # 0: LSBFirst
    value = sum(px[:, :, i] << np.uint32(8 * k) for k, i in enumerate(order))
    out = np.empty((height, width, 3), np.uint8)
    for c, m in enumerate(masks):
        shift = (m & -m).bit_length() - 1
        out[:, :, c] = ((value & np.uint32(m)) >> np.uint32(shift)).astype(np.uint8)
    return out


def colourful_share(rgb: np.ndarray, min_saturation: int = 60) -> float:
    """Share of pixels with a saturated colour (max - min channel >= ``min_saturation``): how much of
    an rviz screenshot shows the height-coloured map rather than its grey background and grid."""
    c = rgb.astype(np.int16)
    return float(np.mean(c.max(axis=2) - c.min(axis=2) >= min_saturation))
