"""Exact per-pixel ray casting of a :class:`~mdr_slam.sim.scene.Scene` into a stereo pair.

Vectorized numpy (float32): every primitive is intersected with all pixel rays of its screen
bounding box (found by clipping the rectangle to the view frustum and projecting it), the nearest
hit is kept in a z-buffer (t along rays with z = 1, i.e. the depth Z itself). Shading is deferred:
each visible primitive is shaded once over its winning pixels (trilinear mip-mapped texture at the
hit's surface coordinate x baked diffuse light map, + the view-dependent highlight on specular
bands). Rendering the RAW distorted images uses the same caster with per-pixel rays obtained by
undistorting every raw pixel with the camera's (K, D) and rotating by its rectification R, so the
calibration written to camera_info rectifies them back exactly (cv2.initUndistortRectifyMap).
"""
from __future__ import annotations

from typing import Dict, List, Optional, Sequence

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import CameraModel, StereoCamera
from ..geometry import inv_T, make_T
from .scene import LABEL_SPECULAR, LIGHTMAP_STEP, TILE, Scene

__all__ = ["Simulator", "sim_camera", "distort_points"]

# EuRoC MAV cam0/cam1 (rounded): raw intrinsics and radial-tangential distortion
_EUROC_RAW = (
    (np.array([458.654, 457.296, 367.215, 248.375]),
     np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0]),
     np.array([0.0035, -0.0105, 0.0012])),
    (np.array([457.587, 456.134, 379.999, 255.238]),
     np.array([-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05, 0.0]),
     np.array([0.0030, -0.0088, 0.0016])),
)


def sim_camera(width: int = 752, height: int = 480, fx: float = 458.0, fy: float = 458.0,
               cx: float = 367.0, cy: float = 248.0, baseline: float = 0.11,
               distort: bool = False, scale: float = 1.0) -> StereoCamera:
    """EuRoC-like stereo camera (752x480, f = 458, B = 0.11 m by default).

    ``scale`` shrinks everything (``scale=0.25`` gives a fast 188x120 camera for tests).
    ``distort=True`` gives RAW cameras with EuRoC's radial-tangential distortion and small
    rectification rotations; their P matrices are the rectified pinhole pair above.
    """
    s = float(scale)
    W, H = int(round(width * s)), int(round(height * s))
    fx, fy = fx * s, fy * s
    cx, cy = (cx + 0.5) * s - 0.5, (cy + 0.5) * s - 0.5
    if not distort:
        return StereoCamera.from_rectified(W, H, fx, fy, cx, cy, baseline)
    K_rect = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    models = []
    for i, (k, D, rv) in enumerate(_EUROC_RAW):
        kfx, kfy, kcx, kcy = k
        K = np.array([[kfx * s, 0, (kcx + 0.5) * s - 0.5], [0, kfy * s, (kcy + 0.5) * s - 0.5],
                      [0, 0, 1.0]])
        P = np.hstack([K_rect, np.zeros((3, 1))])
        if i == 1:
            P[0, 3] = -fx * baseline
        models.append(CameraModel(W, H, K, D.copy(), Rotation.from_rotvec(rv).as_matrix(), P))
    return StereoCamera(models[0], models[1])


def distort_points(x: np.ndarray, y: np.ndarray, D: np.ndarray):
    """Plumb-bob (radial-tangential k1, k2, p1, p2, k3) distortion of normalized coordinates."""
    k1, k2, p1, p2 = D[:4]
    k3 = D[4] if len(D) > 4 else 0.0
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


class _View:
    """Pixel rays of one camera in its own frame (z = 1 so the ray parameter t IS the depth Z),
    plus where that frame sits in the rectified left frame (``T_left_view``)."""

    def __init__(self, width: int, height: int, K: np.ndarray, D: Optional[np.ndarray],
                 T_left_view: np.ndarray):
        self.W, self.H = int(width), int(height)
        self.K = np.asarray(K, float)
        self.D = None if D is None or not np.any(D) else np.asarray(D, float)
        self.T_left_view = T_left_view
        self.f = float(self.K[0, 0])
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        u = np.arange(self.W, dtype=np.float64)
        v = np.arange(self.H, dtype=np.float64)
        if self.D is None:
            # rectified pinhole: rays are separable, kept as (1, W) and (H, 1) for broadcasting
            self.dx = ((u - cx) / fx).astype(np.float32)[None, :]
            self.dy = ((v - cy) / fy).astype(np.float32)[:, None]
        else:
            self.dx, self.dy = self._undistort_grid(u, v)
        self.d2 = (self.dx ** 2 + self.dy ** 2 + 1.0).astype(np.float32)   # |d|^2, (H, W)
        self.dnorm = np.sqrt(self.d2)
        m = 0.02
        self.xlim = (float(self.dx.min()) - m, float(self.dx.max()) + m)
        self.ylim = (float(self.dy.min()) - m, float(self.dy.max()) + m)

    def _undistort_grid(self, u, v):
        """Normalized undistorted coordinates of every raw pixel: cv2.undistortPointsIter
        (many iterations: k1 = -0.28 needs them at the corners), then Newton polish against
        :func:`distort_points` so the rays match OpenCV's forward model to ~1e-6 px."""
        uu, vv = np.meshgrid(u, v)
        pts = np.stack([uu.ravel(), vv.ravel()], -1).reshape(-1, 1, 2)
        und = cv2.undistortPointsIter(pts, self.K, self.D, None, None,
                                      (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-12))
        x, y = und[:, 0, 0].astype(np.float64), und[:, 0, 1].astype(np.float64)
        xt = (uu.ravel() - self.K[0, 2]) / self.K[0, 0]
        yt = (vv.ravel() - self.K[1, 2]) / self.K[1, 1]
        for _ in range(3):   # Newton on the 2x2 Jacobian (numerical, vectorized)
            xd, yd = distort_points(x, y, self.D)
            e = 1e-6
            xdx, ydx = distort_points(x + e, y, self.D)
            xdy, ydy = distort_points(x, y + e, self.D)
            a, b, c, d = (xdx - xd) / e, (xdy - xd) / e, (ydx - yd) / e, (ydy - yd) / e
            det = a * d - b * c
            rx, ry = xt - xd, yt - yd
            x = x + (d * rx - b * ry) / det
            y = y + (-c * rx + a * ry) / det
        return (x.reshape(self.H, self.W).astype(np.float32),
                y.reshape(self.H, self.W).astype(np.float32))

    def project(self, P: np.ndarray):
        """Pixel coordinates of (M, 3) points in the view frame (distorted for raw views)."""
        x, y = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
        if self.D is not None:
            x, y = distort_points(x, y, self.D)
        return self.K[0, 0] * x + self.K[0, 2], self.K[1, 1] * y + self.K[1, 2]

    def rays(self, r0, r1, c0, c1):
        dx = self.dx[:, c0:c1] if self.dx.shape[0] == 1 else self.dx[r0:r1, c0:c1]
        dy = self.dy[r0:r1, :] if self.dy.shape[1] == 1 else self.dy[r0:r1, c0:c1]
        return dx, dy


def _clip_polygon(poly: List[np.ndarray], planes: Sequence[np.ndarray]) -> List[np.ndarray]:
    """Sutherland-Hodgman clipping of a convex polygon against half-spaces ``p . x >= 0``
    (x homogeneous-free: planes through the origin plus the near plane as (a, b, c, d))."""
    for pl in planes:
        if not poly:
            break
        out = []
        n = len(poly)
        for i in range(n):
            P, Q = poly[i], poly[(i + 1) % n]
            fp = pl[0] * P[0] + pl[1] * P[1] + pl[2] * P[2] + pl[3]
            fq = pl[0] * Q[0] + pl[1] * Q[1] + pl[2] * Q[2] + pl[3]
            if fp >= 0:
                out.append(P)
            if (fp >= 0) != (fq >= 0):
                out.append(P + (Q - P) * (fp / (fp - fq)))
        poly = out
    return poly


class Simulator:
    """Renders rectified (or raw distorted) stereo pairs of a scene with exact ground truth.

    ``noise`` is the Gaussian sensor noise sigma (grey levels). The noise of frame ``index`` is
    seeded by ``(seed, index)``, so a frame renders identically in any process and any order.
    """

    def __init__(self, scene: Scene, camera: Optional[StereoCamera] = None, seed: int = 0,
                 noise: float = 2.0, near: float = 0.05, spec_power: float = 80.0,
                 spec_gain: float = 110.0):
        self.scene = scene
        self.camera = camera if camera is not None else sim_camera()
        self.seed = int(seed)
        self.noise = float(noise)
        self.near = float(near)
        self.spec_power = float(spec_power)
        self.spec_gain = float(spec_gain)
        cam = self.camera
        W, H = cam.size
        B = cam.baseline
        self.rect_views = (_View(W, H, cam.K_rect, None, np.eye(4)),
                           _View(W, H, cam.K_rect, None, make_T(np.eye(3), [B, 0, 0])))
        self._raw_views = None

    @property
    def raw_views(self):
        """Raw (distorted, unrectified) views, built on first use (undistorting the grid)."""
        if self._raw_views is None:
            cam = self.camera
            B = cam.baseline
            self._raw_views = (
                _View(cam.left.width, cam.left.height, cam.left.K, cam.left.D,
                      make_T(cam.left.R, [0, 0, 0])),
                _View(cam.right.width, cam.right.height, cam.right.K, cam.right.D,
                      make_T(cam.right.R, [B, 0, 0])))
        return self._raw_views

    # ------------------------------------------------------------------------ ray casting
    def cast(self, view: _View, T_map_view: np.ndarray, keep_sr: bool = True) -> dict:
        """Nearest hit per pixel, as a G-buffer dict: ``z`` (t along the z = 1 ray = depth, inf
        for none), ``pid`` (primitive, -1 for none), ``s``, ``r`` (surface coordinates, m),
        ``nd`` (|n . d|), texture/light-map coordinates and the primitive's shading constants
        (written per primitive window with np.copyto: cheaper than per-pixel table lookups)."""
        sc = self.scene
        at = sc.atlas()
        Tvm = inv_T(T_map_view)
        Rv, tv = Tvm[:3, :3], Tvm[:3, 3]
        O = sc.O @ Rv.T + tv
        U = sc.U @ Rv.T
        V = sc.V @ Rv.T
        N = sc.N @ Rv.T
        nO = np.einsum("ij,ij->i", N, O)
        uO = np.einsum("ij,ij->i", U, O)
        vO = np.einsum("ij,ij->i", V, O)
        C4 = np.stack([O, O + sc.A[:, None] * U, O + sc.A[:, None] * U + sc.B[:, None] * V,
                       O + sc.B[:, None] * V], 1)                      # (P, 4, 3)
        (x0, x1), (y0, y1) = view.xlim, view.ylim
        planes = np.array([[0, 0, 1, -self.near], [-1, 0, x1, 0], [1, 0, -x0, 0],
                           [0, -1, y1, 0], [0, 1, -y0, 0]], float)
        side = C4 @ planes[:, :3].T + planes[:, 3]                    # (P, 4, 5)
        # front-facing (camera on the normal side) and not entirely outside one frustum plane
        cand = np.flatnonzero((nO < -1e-9) & ~np.any(np.all(side < 0, axis=1), axis=1))
        H, W = view.H, view.W
        f32 = np.float32
        g = {"z": np.full((H, W), np.inf, f32), "pid": np.full((H, W), -1, np.int32)}
        for name in ("s", "r", "tx", "ty", "lx", "ly", "lt", "cx", "base", "amp"):
            g[name] = np.zeros((H, W), f32)
        g["nd"] = np.ones((H, W), f32)
        windows = []
        inv_step = f32(1.0 / LIGHTMAP_STEP)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for k in cand:
                if np.all(side[k] >= 0):
                    poly = C4[k]
                else:
                    poly = _clip_polygon(list(C4[k]), planes)
                    if len(poly) < 3:
                        continue
                    poly = np.array(poly)
                if view.D is not None:   # curved edges: sample them densely
                    w = np.linspace(0, 1, 12, endpoint=False)[:, None, None]
                    poly = (poly[None] * (1 - w) + np.roll(poly, -1, 0)[None] * w).reshape(-1, 3)
                pu, pv = view.project(poly)
                m = 1 if view.D is None else 2
                c0 = max(int(np.floor(pu.min())) - m, 0)
                c1 = min(int(np.ceil(pu.max())) + m + 1, W)
                r0 = max(int(np.floor(pv.min())) - m, 0)
                r1 = min(int(np.ceil(pv.max())) + m + 1, H)
                if c1 <= c0 or r1 <= r0:
                    continue
                dx, dy = view.rays(r0, r1, c0, c1)
                n, u, v = N[k].astype(f32), U[k].astype(f32), V[k].astype(f32)
                den = n[0] * dx + n[1] * dy + n[2]
                t = f32(nO[k]) / den
                s = t * (u[0] * dx + u[1] * dy + u[2]) - f32(uO[k])
                r = t * (v[0] * dx + v[1] * dy + v[2]) - f32(vO[k])
                win = (slice(r0, r1), slice(c0, c1))
                hit = (t > self.near) & (t < g["z"][win]) & (s >= 0) & (s <= sc.A[k]) & \
                    (r >= 0) & (r <= sc.B[k])
                if not hit.any():
                    continue
                it = at["inv_texel"][k]
                for name, val in (("z", t), ("pid", k), ("nd", -den),
                                  ("tx", s * it + at["off"][k, 0]),
                                  ("ty", r * it + at["off"][k, 1]),
                                  ("lx", s * inv_step + at["light_off"][k, 0]),
                                  ("ly", r * inv_step + at["light_off"][k, 1]),
                                  ("lt", at["log2_inv_texel"][k]), ("cx", at["col_x"][k]),
                                  ("base", at["base"][k]), ("amp", at["amp"][k])):
                    np.copyto(g[name][win], val, where=hit)
                if keep_sr:   # metric surface coordinates: only the GT map needs them
                    np.copyto(g["s"][win], s, where=hit)
                    np.copyto(g["r"][win], r, where=hit)
                windows.append((k, r0, r1, c0, c1))
        g["windows"] = windows
        g["frame"] = (Rv, tv, N)
        return g

    # ----------------------------------------------------------------------------- shading
    def shade(self, view: _View, g: dict) -> np.ndarray:
        """Noise-free float32 image of a cast (grey levels, may exceed 255 on highlights).

        Deferred and full-frame: the texture is sampled with trilinear mip-mapping (levels
        floor(L) and floor(L)+1 of the atlas, L = log2(pixel footprint / texel), footprint =
        distance / (f cos(incidence)) with cos clamped at 0.25 so grazing floors blur rather
        than alias), times the baked light map, + the specular bands' view-dependent highlight.
        """
        at = self.scene.atlas()
        f32 = np.float32
        pid = g["pid"]
        hit = pid >= 0
        t = np.where(hit, g["z"], f32(1.0))
        foot = t * view.d2 / (f32(view.f) * np.maximum(g["nd"], f32(0.25) * view.dnorm))
        L = np.log2(np.maximum(foot, f32(1e-6)))
        L += g["lt"]
        np.clip(L, f32(0.0), at["max_level"], out=L)
        l0 = np.floor(L)
        frac = L - l0
        # wrap the level-0 texel coordinates into [0, TILE) once; level l is then x / 2^l
        tx, ty = g["tx"], g["ty"]
        tx = tx - np.floor(tx * f32(1.0 / TILE)) * f32(TILE)
        ty = ty - np.floor(ty * f32(1.0 / TILE)) * f32(TILE)
        val = None
        for lev, w in ((l0, f32(1.0) - frac), (np.minimum(l0 + 1, at["max_level"]), frac)):
            sc = np.exp2(-lev)
            # texel c of level l is at atlas column cx + 1 + c (wrap border), centre c + 0.5
            mx = tx * sc + (g["cx"] + f32(0.5))
            my = ty * sc + (f32(2 * TILE) * (f32(1.0) - sc) + f32(2.0) * lev + f32(0.5))
            smp = cv2.remap(at["tex"], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            val = smp * w if val is None else val + smp * w
        light = cv2.remap(at["light"], g["lx"], g["ly"], cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)
        img = (g["base"] + g["amp"] * val) * light
        img[~hit] = 0
        Rv, tv, N = g["frame"]
        for k, r0, r1, c0, c1 in g["windows"]:
            rc = self.scene.rects[k]
            if rc.label != LABEL_SPECULAR or rc.spec_light is None:
                continue
            m = pid[r0:r1, c0:c1] == k
            if not m.any():
                continue
            dx, dy = view.rays(r0, r1, c0, c1)
            dx = np.broadcast_to(dx, m.shape)[m]
            dy = np.broadcast_to(dy, m.shape)[m]
            img[r0:r1, c0:c1][m] += self._highlight(rc, g["z"][r0:r1, c0:c1][m], dx, dy,
                                                    N[k].astype(f32), Rv, tv)
        return img

    def _highlight(self, rc, t, dx, dy, n, Rv, tv) -> np.ndarray:
        """Phong lobe of a line light (tube) parallel to the band, in the plane orthogonal to
        the tube: the mirror direction of the view ray vs. the direction to the tube. View
        dependent, so it moves with the camera and between the two cameras of the pair."""
        f32 = np.float32
        lp, la = rc.spec_light
        Lp = (Rv @ lp + tv).astype(f32)
        a = (Rv @ la).astype(f32)
        # hit point P = t * (dx, dy, 1); unit vector towards the camera wo = -d / |d|
        inv = f32(-1.0) / np.sqrt(dx * dx + dy * dy + f32(1.0))
        wx, wy, wz = dx * inv, dy * inv, inv
        k = f32(2.0) * (wx * n[0] + wy * n[1] + wz * n[2])
        rx, ry, rz = k * n[0] - wx, k * n[1] - wy, k * n[2] - wz        # mirror direction
        lx, ly, lz = Lp[0] - t * dx, Lp[1] - t * dy, Lp[2] - t           # towards the tube
        ra = rx * a[0] + ry * a[1] + rz * a[2]
        la_ = lx * a[0] + ly * a[1] + lz * a[2]
        rx, ry, rz = rx - ra * a[0], ry - ra * a[1], rz - ra * a[2]      # drop the tube axis
        lx, ly, lz = lx - la_ * a[0], ly - la_ * a[1], lz - la_ * a[2]
        c = (rx * lx + ry * ly + rz * lz) / np.maximum(
            np.sqrt((rx * rx + ry * ry + rz * rz) * (lx * lx + ly * ly + lz * lz)), f32(1e-9))
        return f32(self.spec_gain) * np.maximum(c, f32(0)) ** f32(self.spec_power)

    # ------------------------------------------------------------------------------- frames
    def render(self, T_map_cam: np.ndarray, raw: bool = False, index: int = 0, gain: float = 1.0,
               sub_poses: Optional[Sequence[np.ndarray]] = None, depth: bool = True,
               hits: bool = False) -> Dict[str, np.ndarray]:
        """One stereo pair at pose ``T_map_cam`` (left RECTIFIED optical frame in map).

        Returns ``left``, ``right`` (uint8 HxW; raw distorted images when ``raw``), ``depth``
        (float32 Z of the rectified left camera, 0 = no surface) and ``surface`` (uint8 labels).
        ``sub_poses`` (motion blur) are averaged; ``gain`` scales exposure; ``index`` seeds the
        noise. ``hits=True`` adds the left view's ``pid``, ``s``, ``r``, ``z`` (for the GT map).
        """
        views = self.raw_views if raw else self.rect_views
        if sub_poses is not None and len(sub_poses) == 0:
            sub_poses = None
        poses = list(sub_poses) if sub_poses is not None else [T_map_cam]
        left_main = None      # the left view's cast at T_map_cam, reused for depth/hits
        imgs = []
        for i, view in enumerate(views):
            acc = None   # motion blur: mean of the noise-free renders at the sub-poses
            for T in poses:
                c = self.cast(view, T @ view.T_left_view, keep_sr=(hits and i == 0))
                if i == 0 and sub_poses is None:
                    left_main = c
                im = self.shade(view, c)
                acc = im if acc is None else acc + im
            imgs.append(acc if len(poses) == 1 else acc / np.float32(len(poses)))
        out = {}
        for side, (name, im) in enumerate(zip(("left", "right"), imgs)):
            if gain != 1.0:
                im = im * np.float32(gain)
            if self.noise > 0:
                # cv2.randn is ~4x faster than numpy's generator; seeded per (seed, frame, side)
                # so any process renders the same frame identically
                cv2.setRNGSeed((self.seed * 1000003 + int(index) * 2 + side) % (2 ** 31 - 1) + 1)
                nz = np.empty(im.shape, np.float32)
                cv2.randn(nz, 0.0, self.noise)
                im = im + nz
            np.clip(im, 0.0, 255.0, out=im)
            out[name] = (im + np.float32(0.5)).astype(np.uint8)
        if hits:
            hc = left_main if left_main is not None else \
                self.cast(views[0], T_map_cam @ views[0].T_left_view)
            out["pid"], out["s"], out["r"] = hc["pid"], hc["s"], hc["r"]
            out["z"] = np.where(np.isfinite(hc["z"]), hc["z"], 0).astype(np.float32)
        if depth:
            g = left_main if (left_main is not None and not raw) else \
                self.cast(self.rect_views[0], T_map_cam)
            out["depth"] = np.where(np.isfinite(g["z"]), g["z"], 0).astype(np.float32)
            out["surface"] = self.scene.label_lut[g["pid"]]
        return out


def _sample(img: np.ndarray, x: np.ndarray, y: np.ndarray, border: int) -> np.ndarray:
    """Bilinear samples of ``img`` at 1-D float32 coordinates (cv2.remap wants 2-D maps with
    sides < 32767, so the coordinates are folded into rows of 1024)."""
    n = len(x)
    if n == 0:
        return np.zeros(0, np.float32)
    w = 1024 if n > 1024 else n
    h = -(-n // w)
    pad = h * w - n
    if pad:
        x = np.concatenate([x, np.zeros(pad, np.float32)])
        y = np.concatenate([y, np.zeros(pad, np.float32)])
    out = cv2.remap(img, x.reshape(h, w).astype(np.float32, copy=False),
                    y.reshape(h, w).astype(np.float32, copy=False), cv2.INTER_LINEAR,
                    borderMode=border)
    return out.reshape(-1)[:n]
