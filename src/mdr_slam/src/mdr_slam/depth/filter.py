"""Keyframe-guided Kalman temporal depth filter (paper section 3.3.2), vectorized over pixels.

A keyframe holds one depth hypothesis per pixel (on a grid of ``stride`` pixels). At keyframe
creation every hypothesis is initialized from that frame's ELAS measurement WITH HIGH UNCERTAINTY
(its variance times ``init_var_scale``). Every following frame: the keyframe points are moved by
the relative pose and projected into the current image; the current ELAS measurement is read
there, brought back along the keyframe ray and, when it passes a chi-square gate, fused by a
scalar Kalman update. A point is published only once its uncertainty is below ``tau`` and it has
``min_obs`` observations, so only geometrically stable structure reaches the map.

State: INVERSE depth rho = 1/Z (with its variance). Stereo noise is (close to) Gaussian in
disparity, and disparity is proportional to inverse depth (d = f*B*rho), so in rho the
measurement noise is Gaussian with a depth-independent sigma_d/(f*B), the Kalman update is the
exact Bayesian update, and the large depth errors of far/low-texture pixels stay symmetric
(a Gaussian in Z would be badly skewed). It is also what REMODE/SVO-style depth filters use.

``tau`` is RELATIVE: a point is converged when sigma_Z / Z = sigma_rho / rho <= tau. An absolute
tau (metres) would, with sigma_Z ~ Z^2, admit only near points and never the far walls; a
relative one keeps the same acceptance at every range.
Tau trades density for error: lower tau -> fewer, older, more accurate points (and a delay of
more frames before a new surface appears); higher tau -> denser, earlier, noisier.

Optional planar densification (``densify: plane``, depth/densify.py) also publishes non-converged
pixels of planes fitted on the converged points (flagged with ``n_obs`` = 0).

Loop closures: the state lives in the keyframe's camera frame, so a corrected keyframe pose
(:meth:`DepthFilter.set_keyframe_pose`) moves all its points without touching the filter.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Dict, Mapping, Optional, Union

import numpy as np

from ..camera import StereoCamera
from ..geometry import inv_T, is_valid_T, relative_motion
from .config import DepthConfig
from .densify import plane_fill
from .motion_stereo import MOTION_GRID_STEP, MotionStereo

__all__ = ["DepthFilter", "DepthOutput", "KeyFrameDepth", "render_depth"]

_EPS = 1e-6


@dataclass
class DepthOutput:
    """What one frame produces. Points are in the CURRENT left camera optical frame."""

    points: np.ndarray              # (N, 3) float32
    intensity: np.ndarray           # (N,) float32 (grey value 0..255; 0 when none was given)
    variance: np.ndarray            # (N,) float32 depth variance sigma_Z^2 (m^2)
    n_obs: np.ndarray               # (N,) int32 fused observations (1 for ELAS-only)
    keyframe_id: int = -1
    is_new_keyframe: bool = False
    stats: Dict[str, float] = field(default_factory=dict)
    timings: Dict[str, float] = field(default_factory=dict)   # ms per stage (StereoDepth)
    depth: Optional[np.ndarray] = None  # current frame's measurement Z (HxW, NaN invalid)

    def __len__(self) -> int:
        return int(len(self.points))


@dataclass
class KeyFrameDepth:
    """Per-pixel filter state of one keyframe (arrays over the stride grid, flattened)."""

    id: int
    stamp: float
    T_map_kf: np.ndarray
    mu: np.ndarray           # inverse depth (1/m); NaN = no hypothesis
    var: np.ndarray          # inverse-depth variance
    n_obs: np.ndarray        # accepted observations (int32)
    n_rej: np.ndarray        # gated (rejected) observations (int32)
    intensity: np.ndarray    # grey value of the pixel where the hypothesis was seen
    frames: int = 0          # frames fused since creation
    fill_rho: Optional[np.ndarray] = None   # planar densification (grid; NaN = not filled)
    fill_var: Optional[np.ndarray] = None
    fill_frame: int = -1                    # kf.frames when it was computed


def render_depth(points: np.ndarray, camera: StereoCamera) -> np.ndarray:
    """32FC1 depth image (m, NaN = none) of points in the left optical frame, nearest wins."""
    w, h = camera.size
    img = np.full(h * w, np.nan, dtype=np.float32)
    if len(points) == 0:
        return img.reshape(h, w)
    u, v, z = camera.project(np.asarray(points, dtype=np.float32))
    ui, vi = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    ok = (z > 0) & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    idx, z = vi[ok] * w + ui[ok], z[ok]
    order = np.argsort(-z, kind="stable")      # far first, so the nearest write wins
    img[idx[order]] = z[order]
    return img.reshape(h, w)


def _rotate_rays(T: np.ndarray, rx: np.ndarray, ry: np.ndarray):
    """Components of R @ (rx, ry, 1) for rays with unit z (component-wise: an (N,3)@(3,3) matmul
    is several times slower in numpy for hundreds of thousands of points)."""
    R = T[:3, :3].astype(np.float32)
    return (R[0, 0] * rx + R[0, 1] * ry + R[0, 2], R[1, 0] * rx + R[1, 1] * ry + R[1, 2],
            R[2, 0] * rx + R[2, 1] * ry + R[2, 2])


def _transform_depths(T: np.ndarray, rx: np.ndarray, ry: np.ndarray, z: np.ndarray):
    """(X, Y, Z) of T @ (ray * z): points given by unit-z rays and their depths."""
    a, b, c = _rotate_rays(T, rx, ry)
    t = T[:3, 3].astype(np.float32)
    return a * z + t[0], b * z + t[1], c * z + t[2]


def _zbuffer(idx: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Indices (into idx/z) of the nearest point per target cell: a vectorized z-buffer."""
    if len(idx) == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort((z, idx))               # by cell, then depth
    first = np.ones(len(order), dtype=bool)
    first[1:] = idx[order][1:] != idx[order][:-1]
    return order[first]


class DepthFilter:
    """Keyframe-anchored per-pixel inverse-depth Kalman filter (see the module docstring).

    ``process(stamp, T_map_cam, Z, var, intensity=None, new_keyframe=None, keyframe_id=None)``
    takes one frame's measurement (depth ``Z`` and its variance, HxW float, NaN invalid, as from
    :func:`measurement_from_disparity`) and the left camera pose, and returns a
    :class:`DepthOutput`. ``new_keyframe``: None = decide from the pose (translation, rotation,
    overlap, max frames); True = an external keyframe event (the pose node's); False = do not
    switch unless the keyframe no longer overlaps the image (the filter could not update it).
    ``config``: a :class:`~mdr_slam.depth.config.DepthConfig` or a mapping of its fields.
    """

    def __init__(self, camera: StereoCamera, config: Union[None, DepthConfig, Mapping] = None):
        self.camera = camera
        self.cfg = DepthConfig.of(config)
        w, h = camera.size
        s = self.cfg.stride
        us = np.arange(0, w, s, dtype=np.float32)
        vs = np.arange(0, h, s, dtype=np.float32)
        self.grid_shape = (len(vs), len(us))
        gu, gv = np.meshgrid(us, vs)
        self._u = gu.ravel()
        self._v = gv.ravel()
        self._pix = (gv.astype(np.int64) * w + gu.astype(np.int64)).ravel()  # grid -> image index
        # unit-depth rays of the grid pixels: P = (rx, ry, 1) * Z (Z = depth along the optical axis)
        self._rx = ((self._u - camera.cx) / camera.fx).astype(np.float32)
        self._ry = ((self._v - camera.cy) / camera.fy).astype(np.float32)
        gi, gj = np.meshgrid(np.arange(len(us)), np.arange(len(vs)))
        # the cells motion stereo searches: the same sub-grid in every keyframe, so that what one
        # keyframe measured is carried into the next and refined there
        self._motion_cells = ((gi % MOTION_GRID_STEP == 0) & (gj % MOTION_GRID_STEP == 0)).ravel()
        self.motion = MotionStereo(camera, self.cfg.max_depth, self.cfg.min_depth) \
            if self.cfg.motion_stereo and self.cfg.temporal else None
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget everything (time jump, bag loop, tracking reset)."""
        self.kf: Optional[KeyFrameDepth] = None
        self._planes = []   # densify memory: (n_map, d_map, box_lo, box_hi) per plane, newest last
        self._next_id = 0
        self._last_stamp: Optional[float] = None
        if getattr(self, "motion", None) is not None:
            self.motion.reset()

    @property
    def keyframe(self) -> Optional[KeyFrameDepth]:
        return self.kf

    def set_keyframe_pose(self, T_map_kf: np.ndarray, keyframe_id: Optional[int] = None) -> bool:
        """Replace the current keyframe's pose (loop closure / BA correction). The state is in the
        keyframe frame, so the points follow. Returns False when there is no such keyframe."""
        if self.kf is None or (keyframe_id is not None and int(keyframe_id) != self.kf.id):
            return False
        if not is_valid_T(T_map_kf):
            raise ValueError("keyframe pose is not a finite rigid transform")
        T_new = np.array(T_map_kf, dtype=float)
        if self.motion is not None:
            self.motion.correct(T_new @ inv_T(self.kf.T_map_kf))
        self.kf.T_map_kf = T_new
        return True

    def correct_keyframe(self, T_old: np.ndarray, T_new: np.ndarray,
                         keyframe_id: Optional[int] = None) -> bool:
        """A pose keyframe moved from ``T_old`` to ``T_new`` (loop closure / BA): our keyframe,
        which took that keyframe's event, moves with it rigidly, ``T_new @ inv(T_old) @ T_map_kf``.
        Our keyframe can sit a frame or more after the pose keyframe (the depth node skips
        frames), so its pose is not replaced by ``T_new``: that would put it where the camera was
        at the other frame. Same stamp: the same as :meth:`set_keyframe_pose` with ``T_new``."""
        if self.kf is None or (keyframe_id is not None and int(keyframe_id) != self.kf.id):
            return False
        if not (is_valid_T(T_old) and is_valid_T(T_new)):
            raise ValueError("keyframe pose is not a finite rigid transform")
        return self.set_keyframe_pose(np.asarray(T_new, float) @ inv_T(np.asarray(T_old, float))
                                      @ self.kf.T_map_kf, keyframe_id)

    # ------------------------------------------------------------------ per frame
    def process(self, stamp: float, T_map_cam: np.ndarray, Z: np.ndarray, var: np.ndarray,
                intensity: Optional[np.ndarray] = None, new_keyframe: Optional[bool] = None,
                keyframe_id: Optional[int] = None) -> DepthOutput:
        w, h = self.camera.size
        Zf, Vf, If = self._flat_measurement(Z, var, intensity)
        if not is_valid_T(T_map_cam):
            raise ValueError("camera pose is not a finite rigid transform")
        T_map_cam = np.asarray(T_map_cam, dtype=float)
        stamp = float(stamp)
        stats: Dict[str, float] = {}
        if self._last_stamp is not None and stamp < self._last_stamp:
            self.reset()
            stats["reset"] = 1
        self._last_stamp = stamp
        stats["n_measured"] = int(np.count_nonzero(np.isfinite(Zf)))

        if not self.cfg.temporal:
            return self._elas_only(Zf, Vf, If, stats)

        kf = self.kf
        if kf is None:
            self._new_keyframe(stamp, T_map_cam, Zf, Vf, If, None, keyframe_id, stats,
                               intensity is not None)
            stats["kf_reason"] = "first"
            return self._output(T_map_cam, True, stats)

        # keyframe points in the current camera
        T_cur_kf = inv_T(T_map_cam) @ kf.T_map_kf
        sel = np.flatnonzero(np.isfinite(kf.mu))
        xc, yc, zc = _transform_depths(T_cur_kf, self._rx[sel], self._ry[sel], 1.0 / kf.mu[sel])
        u, v = self._project(xc, yc, zc)
        inimg = (zc > _EPS) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        overlap = float(np.count_nonzero(inimg)) / max(1, len(sel))
        stats["overlap"] = round(overlap, 4)

        reason = self._switch_reason(kf, T_map_cam, overlap, new_keyframe)
        if reason:
            stats["kf_reason"] = reason
            carried = None
            if self.cfg.carry_over:
                carried = (sel, u, v, zc)
            self._new_keyframe(stamp, T_map_cam, Zf, Vf, If, carried, keyframe_id, stats,
                               intensity is not None)
            return self._output(T_map_cam, True, stats)

        # ---- update the keyframe with this frame
        self._add_process_noise(kf)
        s_in = sel[inimg]
        uc, vc = u[inimg], v[inimg]
        Zm, Vm, covered = self._sample(Zf, Vf, uc, vc)
        ok = np.isfinite(Zm)
        s_in, uc, vc, Zm, Vm = s_in[ok], uc[ok], vc[ok], Zm[ok], Vm[ok]
        # back-project along the CURRENT ray through the projected keyframe point, move into the
        # keyframe and take its depth along the keyframe ray (z in the keyframe camera)
        T_kf_cur = inv_T(T_cur_kf)
        R3 = T_kf_cur[2, :3].astype(np.float32)
        g = (R3[0] * (uc - self.camera.cx) / self.camera.fx +
             R3[1] * (vc - self.camera.cy) / self.camera.fy + R3[2])   # dz_kf / dZ_cur
        z_kf = Zm * g + np.float32(T_kf_cur[2, 3])
        good = z_kf > self.cfg.min_depth
        s_in, z_kf, var_z = s_in[good], z_kf[good], (g[good] ** 2) * Vm[good]
        y = 1.0 / z_kf                                  # inverse-depth measurement
        R = var_z * y ** 4                              # var(1/z) = var(z) / z^4
        self._fuse(kf, s_in, y, R, stats)
        kf.frames += 1
        if self.cfg.fill_holes:
            self._fill_holes(kf, T_map_cam, Zf, Vf, If, covered, stats)
        return self._output(T_map_cam, False, stats)

    # ------------------------------------------------------------------ pieces
    def _switch_reason(self, kf: KeyFrameDepth, T_map_cam, overlap: float,
                       new_keyframe: Optional[bool]) -> str:
        p = self.cfg
        if new_keyframe is True:
            return "event"
        if overlap < p.kf_min_overlap:
            return "overlap"
        if new_keyframe is False:
            return ""
        dt, dr = relative_motion(kf.T_map_kf, T_map_cam)
        if dt > p.kf_translation:
            return "translation"
        if np.degrees(dr) > p.kf_rotation_deg:
            return "rotation"
        if kf.frames + 1 >= p.kf_max_frames:
            return "frames"
        return ""

    def _add_process_noise(self, kf: KeyFrameDepth) -> None:
        q = self.cfg.process_noise
        if q > 0:
            kf.var += (np.float32(q) * np.nan_to_num(kf.mu)) ** 2

    def _sample(self, Zf, Vf, uc, vc):
        """Measurement (Z, var) at float pixel positions (the nearest pixel), and the grid
        cells of the current image that keyframe hypotheses project to (see _fill_holes)."""
        w = self.camera.size[0]
        ii = np.rint(vc).astype(np.int64) * w + np.rint(uc).astype(np.int64)
        st = self.cfg.stride
        gh, gw = self.grid_shape
        covered = np.zeros(gh * gw, dtype=bool)
        covered[np.minimum(np.rint(vc / st).astype(np.int64), gh - 1) * gw +
                np.minimum(np.rint(uc / st).astype(np.int64), gw - 1)] = True
        return Zf[ii], Vf[ii], covered

    def _fuse(self, kf: KeyFrameDepth, s: np.ndarray, y: np.ndarray, R: np.ndarray, stats) -> None:
        """Chi-square gated scalar Kalman update of hypotheses ``s`` with measurements ``y`` (R)."""
        p = self.cfg
        mu, P = kf.mu[s], kf.var[s]
        innov = y - mu
        S = P + R
        acc = innov * innov < p.chi2_threshold * S
        K = P[acc] / S[acc]
        kf.mu[s[acc]] = mu[acc] + K * innov[acc]
        kf.var[s[acc]] = P[acc] * R[acc] / S[acc]         # (1 - K) P
        kf.n_obs[s[acc]] += 1
        rej = s[~acc]
        kf.n_rej[rej] += 1
        # a hypothesis contradicted much more often than confirmed was wrong from the start
        # (an ELAS outlier at init, an occluder that moved): start again from this measurement
        bad = (kf.n_rej[rej] >= p.reinit_min_rejections) & \
            (kf.n_rej[rej] > p.reinit_ratio * kf.n_obs[rej])
        rb = rej[bad]
        kf.mu[rb] = y[~acc][bad]
        kf.var[rb] = p.init_var_scale * R[~acc][bad]
        kf.n_obs[rb] = 1
        kf.n_rej[rb] = 0
        stats["n_updated"] = stats.get("n_updated", 0) + int(np.count_nonzero(acc))
        stats["n_gated"] = stats.get("n_gated", 0) + int(len(rej))
        stats["n_reinit"] = stats.get("n_reinit", 0) + int(len(rb))

    def _init_pixels(self, kf: KeyFrameDepth, g: np.ndarray, Zg: np.ndarray, Vg: np.ndarray,
                     Ig: np.ndarray) -> None:
        """New hypotheses at grid cells ``g`` from depth measurements, with inflated variance."""
        y = 1.0 / Zg
        kf.mu[g] = y
        kf.var[g] = self.cfg.init_var_scale * Vg * y ** 4
        kf.n_obs[g] = 1
        kf.n_rej[g] = 0
        kf.intensity[g] = Ig

    def _new_keyframe(self, stamp, T_map_cam, Zf, Vf, If, carried, keyframe_id, stats,
                      have_image: bool = False) -> None:
        n = len(self._u)
        old = self.kf
        kid = int(keyframe_id) if keyframe_id is not None else self._next_id
        self._next_id = max(self._next_id, kid) + 1
        kf = KeyFrameDepth(id=kid, stamp=stamp, T_map_kf=T_map_cam.copy(),
                           mu=np.full(n, np.nan, np.float32), var=np.full(n, np.inf, np.float32),
                           n_obs=np.zeros(n, np.int32), n_rej=np.zeros(n, np.int32),
                           intensity=np.zeros(n, np.float32))
        n_carried = 0
        if carried is not None and old is not None:
            sel, u, v, zc = carried
            # carry the well-observed hypotheses: reproject into the new keyframe (= the current
            # camera) with a z-buffer; variance propagated along the ray (z_new = g*z_old + t_z)
            mu, var = old.mu[sel], old.var[sel]
            rel = np.sqrt(var) / mu
            keep = (old.n_obs[sel] >= self.cfg.min_obs) & (rel <= self.cfg.carry_tau) & \
                (zc > self.cfg.min_depth)
            gi = self._grid_index(u[keep], v[keep], zc[keep])
            ok = gi >= 0
            src = np.flatnonzero(keep)[ok]
            gi = gi[ok]
            win = _zbuffer(gi, zc[src])
            src, gi = src[win], gi[win]
            T_cur_kf = inv_T(T_map_cam) @ old.T_map_kf
            g = _rotate_rays(T_cur_kf, self._rx[sel[src]], self._ry[sel[src]])[2]
            z_old = 1.0 / mu[src]
            var_z_new = g * g * var[src] * z_old ** 4
            z_new = zc[src]
            kf.mu[gi] = 1.0 / z_new
            kf.var[gi] = var_z_new / z_new ** 4
            kf.n_obs[gi] = old.n_obs[sel[src]]
            kf.intensity[gi] = old.intensity[sel[src]]
            n_carried = len(gi)
        self.kf = kf
        # this frame's own measurement: fused into carried hypotheses, initializes the others
        Zg, Vg, Ig = Zf[self._pix], Vf[self._pix], If[self._pix]
        meas = np.isfinite(Zg)
        have = np.isfinite(kf.mu)
        fuse = np.flatnonzero(meas & have)
        if len(fuse):
            y = 1.0 / Zg[fuse]
            self._fuse(kf, fuse, y, Vg[fuse] * y ** 4, stats)
        init = np.flatnonzero(meas & ~have)
        self._init_pixels(kf, init, Zg[init], Vg[init], Ig[init])
        stats["n_carried"] = n_carried
        stats["n_init"] = int(len(init))
        if self.motion is not None and have_image:
            self._motion_update(kf, If.reshape(self.camera.size[1], self.camera.size[0]), stats)

    def _motion_update(self, kf: KeyFrameDepth, grey: np.ndarray, stats) -> None:
        """Depth from the motion between keyframes (depth/motion_stereo.py) for the new
        keyframe's hypotheses the rig has not converged, fused as any measurement; then this
        keyframe's image joins the earlier ones."""
        t0 = time.perf_counter()
        with np.errstate(invalid="ignore"):
            rel = np.sqrt(kf.var) / kf.mu
            cand = np.flatnonzero(self._motion_cells & np.isfinite(kf.mu) & (kf.mu > 0) &
                                  ~self._converged(kf))
        # the most uncertain first: measure() searches the first MOTION_MAX_PIXELS it can
        cand = cand[np.argsort(-rel[cand], kind="stable")]
        idx, y, R = self.motion.measure(kf.T_map_kf, grey, self._u[cand], self._v[cand],
                                        self._rx[cand], self._ry[cand], kf.mu[cand],
                                        kf.var[cand], stats)
        fused: Dict[str, float] = {}
        if len(idx):
            self._fuse(kf, cand[idx], y, R, fused)
        stats["motion_fused"] = int(fused.get("n_updated", 0))
        self.motion.remember(kf.T_map_kf, grey)
        stats["motion_ms"] = round(1e3 * (time.perf_counter() - t0), 1)

    def _project(self, x, y, z):
        c = self.camera
        with np.errstate(divide="ignore", invalid="ignore"):
            return c.fx * x / z + c.cx, c.fy * y / z + c.cy

    def _grid_index(self, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Grid cell (nearest grid pixel) of projected points, -1 outside."""
        s = self.cfg.stride
        gh, gw = self.grid_shape
        if len(u) == 0:
            return np.zeros(0, dtype=np.int64)
        with np.errstate(invalid="ignore"):
            gu = np.rint(u / s)
            gv = np.rint(v / s)
            ok = (z > _EPS) & (gu >= 0) & (gu < gw) & (gv >= 0) & (gv < gh)
        out = np.full(len(u), -1, dtype=np.int64)
        out[ok] = gv[ok].astype(np.int64) * gw + gu[ok].astype(np.int64)
        return out

    def _fill_holes(self, kf: KeyFrameDepth, T_map_cam, Zf, Vf, If, covered, stats) -> None:
        """Start hypotheses for keyframe pixels that had none (ELAS holes at the keyframe, newly
        seen surfaces) from this frame's measurement, splatted into the keyframe with a z-buffer.
        This is what densifies low-texture walls: any frame that matched them contributes.
        Only current pixels no keyframe hypothesis projected to (``covered``) are candidates,
        which keeps this cheap (holes are a small share of the image)."""
        Zg = Zf[self._pix]
        src = np.flatnonzero(np.isfinite(Zg) & ~covered)
        stats["n_filled"] = 0
        if len(src) == 0:
            return
        T_kf_cur = inv_T(kf.T_map_kf) @ T_map_cam
        x, y, z = _transform_depths(T_kf_cur, self._rx[src], self._ry[src], Zg[src])
        u, v = self._project(x, y, z)
        gi = self._grid_index(u, v, z)
        ok = (gi >= 0) & (z > self.cfg.min_depth)
        ok[ok] = np.isnan(kf.mu[gi[ok]])
        src, gi, z = src[ok], gi[ok], z[ok]
        win = _zbuffer(gi, z)
        src, gi, z = src[win], gi[win], z[win]
        g = _rotate_rays(T_kf_cur, self._rx[src], self._ry[src])[2]
        var_z = g * g * Vf[self._pix[src]]
        self._init_pixels(kf, gi, z, var_z, If[self._pix[src]])
        stats["n_filled"] = int(len(gi))

    def _converged(self, kf: KeyFrameDepth) -> np.ndarray:
        p = self.cfg
        with np.errstate(invalid="ignore"):
            sd_rho = np.sqrt(kf.var)
            return np.isfinite(kf.mu) & (kf.n_obs >= p.min_obs) & (sd_rho <= p.tau * kf.mu)

    def _output(self, T_map_cam, is_new: bool, stats) -> DepthOutput:
        kf = self.kf
        conv = self._converged(kf)
        stats["n_valid"] = int(np.count_nonzero(np.isfinite(kf.mu)))
        stats["n_converged"] = int(np.count_nonzero(conv))
        stats["keyframe_frames"] = kf.frames
        rho, var = kf.mu, kf.var
        n_obs = kf.n_obs
        if self.cfg.densify == "plane":
            fill = self._densify(kf, conv, stats)
            if fill is not None:
                conv = conv | fill
                rho = np.where(fill, kf.fill_rho, kf.mu)
                var = np.where(fill, kf.fill_var, kf.var)
                n_obs = np.where(fill, 0, kf.n_obs)     # 0 marks a planar fill
        c = np.flatnonzero(conv)
        z = 1.0 / rho[c]
        if is_new:
            x, y = self._rx[c] * z, self._ry[c] * z
        else:
            x, y, z = _transform_depths(inv_T(T_map_cam) @ kf.T_map_kf, self._rx[c], self._ry[c], z)
            if self.cfg.publish_visible_only:
                w, h = self.camera.size
                u, v = self._project(x, y, z)
                keep = (z > _EPS) & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
                c, x, y, z = c[keep], x[keep], y[keep], z[keep]
        P = np.stack([x, y, z], axis=1)
        # depth variance (m^2) from the inverse-depth one: var_Z = var_rho / rho^4 (first order)
        var_z = var[c] / rho[c] ** 4
        stats["n_published"] = int(len(c))
        return DepthOutput(points=np.ascontiguousarray(P, dtype=np.float32),
                           intensity=kf.intensity[c].astype(np.float32),
                           variance=var_z.astype(np.float32), n_obs=n_obs[c].astype(np.int32),
                           keyframe_id=kf.id, is_new_keyframe=is_new, stats=stats)

    def _densify(self, kf: KeyFrameDepth, conv: np.ndarray, stats) -> Optional[np.ndarray]:
        """Planar fill of the keyframe's non-converged pixels (depth/densify.py), re-fitted every
        ``densify_every`` frames of the keyframe; returns the fill mask (None = nothing)."""
        every = max(1, self.cfg.densify_every)
        if kf.fill_rho is None or kf.frames - kf.fill_frame >= every:
            shape = self.grid_shape
            R, t = kf.T_map_kf[:3, :3], kf.T_map_kf[:3, 3]
            priors = []
            margin = self.cfg.densify_prior_margin
            for n_w, d_w, lo, hi in self._planes:   # map planes -> rho = a x + b y + c here
                d_c = d_w - float(n_w @ t)
                if d_c <= 0.05:
                    continue
                th = (R.T @ n_w) / d_c
                # only inside the map box where the plane was seen with support (+ margin)
                with np.errstate(divide="ignore", invalid="ignore"):
                    z = 1.0 / (th[0] * self._rx + th[1] * self._ry + th[2])
                    Pw = _transform_depths(kf.T_map_kf, self._rx, self._ry, z.astype(np.float32))
                    allowed = np.ones(len(z), bool)
                    for k in range(3):
                        allowed &= (Pw[k] >= lo[k] - margin) & (Pw[k] <= hi[k] + margin)
                if np.count_nonzero(allowed) >= self.cfg.densify_min_pixels:
                    priors.append((th, allowed.reshape(shape)))   # (fewer could fill nothing)
            fill, frho, fvar, st = plane_fill(
                self._rx.reshape(shape), self._ry.reshape(shape), kf.mu.reshape(shape),
                kf.var.reshape(shape), kf.n_obs.reshape(shape), conv.reshape(shape), self.cfg,
                np.random.default_rng(kf.id * 1000 + kf.frames), priors)
            kf.fill_rho, kf.fill_var, kf.fill_frame = frho.ravel(), fvar.ravel(), kf.frames
            stats["densify_planes"] = st["planes"]
            stats["densify_priors"] = st.get("priors_used", 0)
            self._remember_planes(st["new_planes"], st["new_regions"], kf)
        fill = np.isfinite(kf.fill_rho) & ~conv
        with np.errstate(invalid="ignore"):
            zmax = self.cfg.densify_max_depth or self.cfg.max_depth
            fill &= (kf.fill_rho > 1.0 / zmax) & \
                (kf.fill_rho < 1.0 / self.cfg.min_depth)
        stats["n_densified"] = int(np.count_nonzero(fill))
        return fill if stats["n_densified"] else None

    def _remember_planes(self, thetas, regions, kf: KeyFrameDepth) -> None:
        """Keep the planes found in a keyframe for later keyframes: map-frame (normal, offset) and
        the map box of the pixels they filled here; a plane that matches a remembered one (3 deg,
        3 cm) replaces it and their boxes are merged."""
        m = self.cfg.densify_memory
        if m <= 0:
            return
        R, t = kf.T_map_kf[:3, :3], kf.T_map_kf[:3, 3]
        for th, reg in zip(thetas, regions):
            d_c = 1.0 / float(np.linalg.norm(th))
            n_w = R @ (np.asarray(th, dtype=float) * d_c)
            d_w = d_c + float(n_w @ t)
            th32 = np.asarray(th, dtype=np.float32)
            z = 1.0 / (th32[0] * self._rx[reg] + th32[1] * self._ry[reg] + th32[2])
            Pw = np.stack(_transform_depths(kf.T_map_kf, self._rx[reg], self._ry[reg], z), 1)
            if len(Pw) == 0:
                continue
            lo, hi = Pw.min(axis=0), Pw.max(axis=0)
            keep = []
            for n, d, l0, h0 in self._planes:
                if float(n @ n_w) > np.cos(np.radians(3.0)) and abs(d - d_w) < 0.03:
                    lo, hi = np.minimum(lo, l0), np.maximum(hi, h0)
                else:
                    keep.append((n, d, l0, h0))
            self._planes = keep + [(n_w, d_w, lo, hi)]
        del self._planes[:-m]

    def single_frame(self, Z: np.ndarray, var: np.ndarray, intensity: Optional[np.ndarray] = None,
                     max_sigma: float = float("inf")) -> DepthOutput:
        """One measurement's points on the stride grid, in its camera, without a pose and
        without touching the filter's state: what a depth node can still publish for obstacle
        sensing while the tracker is LOST. ``max_sigma`` (m) drops the points whose sigma_Z is
        larger (far or weakly textured pixels, where a single match is least reliable)."""
        Zf, Vf, If = self._flat_measurement(Z, var, intensity)
        stats = {"n_measured": int(np.count_nonzero(np.isfinite(Zf)))}
        return self._elas_only(Zf, Vf, If, stats, max_sigma)

    def _flat_measurement(self, Z, var, intensity):
        """(Z, var, intensity) of one measurement as flat float32 arrays; ValueError when its
        size is not the camera's."""
        w, h = self.camera.size
        if Z.shape != (h, w) or var.shape != (h, w):
            raise ValueError("measurement is %s, camera is %dx%d" % (Z.shape, w, h))
        If = (np.zeros(h * w, np.float32) if intensity is None
              else np.asarray(intensity, dtype=np.float32).reshape(-1))
        return (np.asarray(Z, dtype=np.float32).ravel(), np.asarray(var, dtype=np.float32).ravel(),
                If)

    def _elas_only(self, Zf, Vf, If, stats, max_sigma: float = float("inf")) -> DepthOutput:
        """The ELAS-only baseline: every valid pixel of this frame (on the stride grid) whose
        sigma_Z is at most ``max_sigma``."""
        Zg = Zf[self._pix]
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(Zg) & ~(Vf[self._pix] > np.float32(max_sigma) ** 2)
        c = np.flatnonzero(ok)
        z = Zg[c]
        P = np.stack([self._rx[c] * z, self._ry[c] * z, z], axis=1)
        stats.update(n_valid=int(len(c)), n_converged=int(len(c)), n_published=int(len(c)))
        return DepthOutput(points=np.ascontiguousarray(P, dtype=np.float32),
                           intensity=If[self._pix[c]].astype(np.float32),
                           variance=Vf[self._pix[c]].astype(np.float32),
                           n_obs=np.ones(len(c), np.int32), keyframe_id=-1, is_new_keyframe=False,
                           stats=stats)
