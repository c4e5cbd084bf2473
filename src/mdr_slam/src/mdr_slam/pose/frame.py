"""Frame: ORB features of a rectified stereo pair with a depth per matched keypoint (ORB-SLAM2 Frame).

Stereo matching follows ORB-SLAM2's Frame::ComputeStereoMatches: for every left keypoint, right
keypoints on the same row band (+-2 px times the octave scale), within the disparity range and of
a neighbouring octave are candidates; the best Hamming distance below (TH_HIGH+TH_LOW)/2 wins, then
an 11x11 SAD patch search over +-5 px and a parabola through the three SAD values around the minimum
give a sub-pixel disparity; matches whose SAD exceeds 2.1x the median are dropped (repetitive
texture). Everything is vectorized: candidate pairs from per-octave row buckets (sorted rows +
searchsorted), Hamming distances on those pairs only, one sort for the best pair per keypoint,
and the 11 SAD shifts of all matches as int16 arrays, one shift at a time (tests/pose/test_pose_speed.py
checks the result against a plain per-keypoint loop).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Optional

import numpy as np

from ..geometry import inv_T, transform_points
from .optimizer import normalize_pose
from .orb import TH_HIGH, TH_LOW, ORBextractor, expand_ranges, hamming

__all__ = ["Frame", "FeatureGrid", "compute_stereo_matches", "stereo_features", "stereo_features_job"]

_POOL = None


def _pool():
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ORBright")
    return _POOL


_W = 5   # SAD half window (11x11 patch, as ORB-SLAM2)
_L = 5   # SAD search half range (+-5 px)


def compute_stereo_matches(left: np.ndarray, right: np.ndarray, uv_l, oct_l, desc_l, uv_r, oct_r,
                           desc_r, scale: np.ndarray, fx: float, baseline: float,
                           min_depth: Optional[float] = None, doffs: float = 0.0):
    """Right u coordinate (N,) (-1 when unmatched) and depth (N,) (-1 when unmatched) per left kp.

    ``doffs`` (px, :attr:`StereoCamera.doffs`): the principal point difference; the disparity
    is ``u_left - u_right - doffs``, and the right coordinate returned is ``u_left - disparity``
    (the right camera's as if it had the left cx: what the optimizer's ``u - bf/z`` predicts).
    """
    n = len(uv_l)
    ur = -np.ones(n, dtype=np.float32)
    depth = -np.ones(n, dtype=np.float32)
    if n == 0 or len(uv_r) == 0:
        return ur, depth
    bf = fx * baseline
    min_z = baseline if min_depth is None else min_depth
    max_d = bf / min_z   # ORB-SLAM2: minZ = b, so maxD = fx
    # candidate pairs (the row index of ORB-SLAM2's vRowIndices), per right octave o: right
    # keypoints of octave o sorted by row, left keypoints of octaves o-1..o+1 looked up within
    # +-2*scale[o] rows. This yields exactly the pairs passing the row and octave tests, instead
    # of a band sized for the coarsest octave that is mostly thrown away.
    vl = uv_l[:, 1]
    nlev = len(scale)
    oct_r = np.minimum(np.asarray(oct_r), nlev - 1)
    oct_l = np.asarray(oct_l)
    # right keypoints sorted by (octave, row) (stable: ties in right-index order); one lookup per
    # (left keypoint, octave o-1..o+1) in the combined key octave * span + row
    span = float(max(np.max(uv_r[:, 1]), np.max(vl)) + 4.0 * scale[-1] + 8.0)
    key_r = oct_r * span + uv_r[:, 1]
    r_sorted = np.argsort(key_r, kind="stable")
    key_sorted = key_r[r_sorted]
    present = np.zeros(nlev, bool)
    present[oct_r] = True
    lq = np.repeat(np.arange(n), 3)
    oq = np.repeat(oct_l, 3) + np.tile(np.array([-1, 0, 1]), n)
    valid = (oq >= 0) & (oq < nlev)
    valid[valid] = present[oq[valid]]
    lq, oq = lq[valid], oq[valid]
    rad = 2.0 * scale[oq]
    lo = np.searchsorted(key_sorted, oq * span + (vl[lq] - (rad + 0.01)), side="left")
    hi = np.searchsorted(key_sorted, oq * span + (vl[lq] + (rad + 0.01)), side="right")
    a, b = expand_ranges(lo, hi)
    pl_, pr_ = lq[a], r_sorted[b]
    keep = np.abs(vl[pl_] - uv_r[pr_, 1]) <= rad[a]   # the exact (float32) row test
    pl_, pr_ = pl_[keep], pr_[keep]
    du = uv_l[pl_, 0] - uv_r[pr_, 0] - doffs
    ok = (du >= 0) & (du <= max_d)
    pl_, pr_ = pl_[ok], pr_[ok]
    if len(pl_) == 0:
        return ur, depth
    dist = hamming(desc_l[pl_], desc_r[pr_])
    # best pair per left keypoint: one sort on (left, distance, right row rank); ties go to the
    # right keypoint first in row order, as ORB-SLAM2's scan of its row index
    row_sorted = np.argsort(uv_r[:, 1], kind="stable")
    rank = np.empty(len(row_sorted), np.int64)
    rank[row_sorted] = np.arange(len(row_sorted))
    nr = len(row_sorted)
    o = np.argsort((pl_.astype(np.int64) * 257 + dist) * nr + rank[pr_], kind="stable")
    pl_, pr_, dist = pl_[o], pr_[o], dist[o]
    first = np.r_[True, pl_[1:] != pl_[:-1]]
    pl_, pr_, dist = pl_[first], pr_[first], dist[first]
    sel = dist < (TH_HIGH + TH_LOW) // 2
    il, ir = pl_[sel], pr_[sel]
    if len(il) == 0:
        return ur, depth
    # --- sub-pixel refinement by SAD on the full-resolution rows (vectorized gathers)
    h, w = left.shape[:2]
    uL = np.round(uv_l[il, 0]).astype(int)
    vL = np.round(uv_l[il, 1]).astype(int)
    uR0 = np.round(uv_r[ir, 0]).astype(int)
    inb = ((vL - _W >= 0) & (vL + _W < h) & (uL - _W >= 0) & (uL + _W < w) &
           (uR0 - _W - _L >= 0) & (uR0 + _W + _L < w))
    il, ir, uL, vL, uR0 = il[inb], ir[inb], uL[inb], vL[inb], uR0[inb]
    if len(il) == 0:
        return ur, depth
    # patches gathered as whole windows of a strided view (4x cheaper than per-pixel indices),
    # then laid out match-last: (11, 11, M) and (11, 21, M), so each shifted window below is one
    # contiguous block and the SAD a sum over leading axes (half the time of summing 121-pixel
    # rows per match)
    win_view = np.lib.stride_tricks.sliding_window_view
    pl = win_view(left, (2 * _W + 1, 2 * _W + 1))[vL - _W, uL - _W].astype(np.int16)  # (M,11,11)
    pl -= left[vL, uL].astype(np.int16)[:, None, None]                  # ORB-SLAM2: minus centre
    pl = np.ascontiguousarray(pl.transpose(1, 2, 0))                    # (11, 11, M)
    strip = np.ascontiguousarray(win_view(right, (2 * _W + 1, 2 * (_W + _L) + 1))[
        vL - _W, uR0 - _W - _L].astype(np.int16).transpose(1, 2, 0))    # (11, 21, M)
    shifts = np.arange(-_L, _L + 1)
    # the 11 shifted windows, each minus its centre pixel, in int16 (|differences| <= 510), one
    # (11, 11, M) buffer reused per shift; the sums (<= 121 * 510 < 2^16) in uint16
    M = len(il)
    sad_k = np.empty((2 * _L + 1, M), np.uint16)
    centre = strip[_W, _W:_W + 2 * _L + 1]                              # (11, M)
    buf = np.empty((2 * _W + 1, 2 * _W + 1, M), np.int16)
    absd = buf.reshape(-1, M).view(np.uint16)
    for k in range(2 * _L + 1):
        np.subtract(strip[:, k:k + 2 * _W + 1], pl, out=buf)
        buf -= centre[k]
        np.abs(buf, out=buf)
        np.add.reduce(absd, axis=0, dtype=np.uint16, out=sad_k[k])
    sad = sad_k.T.astype(np.float32)                                    # (M, 11)
    k = np.argmin(sad, axis=1)
    interior = (k > 0) & (k < 2 * _L)
    m = np.arange(len(k))
    k1 = np.clip(k, 1, 2 * _L - 1)
    d1, d2, d3 = sad[m, k1 - 1], sad[m, k1], sad[m, k1 + 1]
    denom = 2.0 * (d1 + d3 - 2.0 * d2)
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = (d1 - d3) / denom
    good = interior & np.isfinite(delta) & (np.abs(delta) < 1.0)
    best_sad = sad[m, k]
    u_right = uR0 + shifts[k] + np.where(good, delta, 0.0)
    disp = uL - u_right - doffs   # the SAD patch is centred on round(uL): measured from there
    good &= (disp >= 0) & (disp < max_d)
    disp = np.where(disp <= 0, 0.01, disp)
    il, disp, best_sad = il[good], disp[good], best_sad[good]
    u_right = uv_l[il, 0] - disp
    if len(il) == 0:
        return ur, depth
    # floor of one grey level per pixel: noise-free (synthetic) images have a zero median SAD
    thr = max(1.5 * 1.4 * float(np.median(best_sad)), float((2 * _W + 1) ** 2))
    keep = best_sad <= thr
    il = il[keep]
    ur[il] = u_right[keep]
    depth[il] = bf / disp[keep]
    return ur, depth


def gradient_energy(image: np.ndarray, uv: np.ndarray, half: int = 3) -> np.ndarray:
    """(n, 2) mean squared central-difference gradients along x and y over the (2 half + 1)^2
    window around each point (grey levels^2): how well the patch pins the point along each axis
    (a horizontal edge: y large, x at the noise level)."""
    H, W = image.shape[:2]
    n = len(uv)
    if n == 0:
        return np.zeros((0, 2), np.float32)
    u = np.clip(np.rint(uv[:, 0]).astype(np.int64), half + 1, W - half - 2)
    v = np.clip(np.rint(uv[:, 1]).astype(np.int64), half + 1, H - half - 2)
    offs = np.arange(-half, half + 1)
    rows = v[:, None, None] + offs[None, :, None]
    cols = u[:, None, None] + offs[None, None, :]
    img = image.astype(np.float32) if image.dtype != np.float32 else image
    gx = (img[rows, cols + 1] - img[rows, cols - 1]) * 0.5
    gy = (img[rows + 1, cols] - img[rows - 1, cols]) * 0.5
    return np.stack([np.mean(gx * gx, axis=(1, 2)), np.mean(gy * gy, axis=(1, 2))], axis=1)


def stereo_features(left: np.ndarray, right: np.ndarray, extractor: ORBextractor,
                    extractor_right: Optional[ORBextractor], fx: float, baseline: float,
                    doffs: float = 0.0) -> tuple:
    """What a Frame is made of: ORB on both images and the stereo matches,
    ``(uv, octave, angle, desc, ur, depth, n_primary, grad)`` (``n_primary``: the left image's
    corners at the first FAST threshold, Tracking's low-texture test; ``grad``: the keypoints'
    :func:`gradient_energy`, for the texture weights, made here so that a frame made in a worker
    process leaves the tracking thread nothing per pixel to do). With a second extractor the right
    image is extracted in a worker thread while this one does the left (cv2 releases the GIL
    inside detect/compute; two cv2.ORB objects: they are not re-entrant)."""
    if extractor_right is not None and extractor_right is not extractor:
        fut = _pool().submit(extractor_right, right)
        uv, octave, angle, desc = extractor(left)
        uv_r, oct_r, _, desc_r = fut.result()
    else:
        uv, octave, angle, desc = extractor(left)
        n_primary = getattr(extractor, "n_primary", len(uv))
        uv_r, oct_r, _, desc_r = extractor(right)
        extractor.n_primary = n_primary   # the left image's, as with two extractors
    ur, depth = compute_stereo_matches(left, right, uv, octave, desc, uv_r, oct_r, desc_r,
                                       extractor.scale, fx, baseline, doffs=doffs)
    return (uv, octave, angle, desc, ur, depth, int(getattr(extractor, "n_primary", len(uv))),
            gradient_energy(left, uv))


_JOB_EXTRACTORS: dict = {}


def stereo_features_job(orb_params: tuple, left: np.ndarray, right: np.ndarray, fx: float,
                        baseline: float, doffs: float = 0.0, abort=None) -> tuple:
    """:func:`stereo_features` with extractors made from ``orb_params`` (ORBextractor's
    nfeatures, scale_factor, nlevels, fast_threshold, min_fast_threshold) and kept for the next
    call: the frame job of a worker process (``ba_process.BAWorker``). ``abort`` is unused."""
    ex = _JOB_EXTRACTORS.get(tuple(orb_params))
    if ex is None:
        n, sf, nl, fast, fast_min = orb_params
        ex = tuple(ORBextractor(n, sf, nl, fast, min_fast_threshold=fast_min) for _ in range(2))
        _JOB_EXTRACTORS[tuple(orb_params)] = ex
    return stereo_features(left, right, ex[0], ex[1], fx, baseline, doffs)


class FeatureGrid:
    """Keypoints bucketed in square cells (ORB-SLAM2's Frame::mGrid and GetFeaturesInArea),
    answering every (projection, keypoint) pair within a per-projection radius at once.

    The keypoints are sorted by cell (row-major), so the cells of one grid row that a search
    circle overlaps are one contiguous run: per projection and overlapped row, two
    ``searchsorted`` give the run, ``expand_ranges`` the candidate pairs, and the exact radius
    test keeps the pairs inside. No Python loop. Cells of 10 px (ORB-SLAM2's 64 columns over
    640 px). On the sample bag's projection searches: 1.5 ms per search against 2.2 ms for a
    k-d tree ``sparse_distance_matrix`` at the largest radius, which also leaves 3x the pairs
    for the matcher's masks.
    """

    def __init__(self, uv: np.ndarray, cell: float = 10.0):
        self.uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        self.x, self.y = self.uv[:, 0].copy(), self.uv[:, 1].copy()   # contiguous for gathers
        self.cell = float(cell)
        if len(self.uv):
            c = np.floor(self.uv / self.cell).astype(np.int64)
            c = np.maximum(c, 0)
            self.ncols = int(c[:, 0].max()) + 1
            self.nrows = int(c[:, 1].max()) + 1
            key = c[:, 1] * self.ncols + c[:, 0]
        else:
            self.ncols = self.nrows = 0
            key = np.zeros(0, np.int64)
        self.order = np.argsort(key, kind="stable")
        self.keys = key[self.order]

    def pairs_within(self, u, v, radius):
        """(point index i, keypoint index j, distance) for every keypoint within ``radius[i]``
        px of (u[i], v[i]); non-finite projections have none."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        r = np.broadcast_to(np.asarray(radius, dtype=np.float64), u.shape)
        none = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
        if len(u) == 0 or len(self.keys) == 0:
            return none
        ok = np.isfinite(u) & np.isfinite(v) & np.isfinite(r) & (r >= 0)
        g = self.cell
        with np.errstate(invalid="ignore"):
            cx0 = np.clip(np.floor((u - r) / g), 0, self.ncols - 1)
            cx1 = np.clip(np.floor((u + r) / g), -1, self.ncols - 1)
            cy0 = np.clip(np.floor((v - r) / g), 0, self.nrows)
            cy1 = np.clip(np.floor((v + r) / g), -1, self.nrows - 1)
        ok &= (cx1 >= cx0) & (cy1 >= cy0)
        pts = np.nonzero(ok)[0]
        if len(pts) == 0:
            return none
        cx0, cx1 = cx0[pts].astype(np.int64), cx1[pts].astype(np.int64)
        cy0, cy1 = cy0[pts].astype(np.int64), cy1[pts].astype(np.int64)
        owner, row = expand_ranges(cy0, cy1 + 1)            # (point, grid row) per overlapped row
        base = row * self.ncols
        lo = np.searchsorted(self.keys, base + cx0[owner], side="left")
        hi = np.searchsorted(self.keys, base + cx1[owner], side="right")
        which, pos = expand_ranges(lo, hi)
        i = pts[owner[which]]
        j = self.order[pos]
        dx = self.x[j] - u[i]
        dy = self.y[j] - v[i]
        d2 = dx * dx + dy * dy
        rr = r[i]
        keep = d2 <= rr * rr
        return i[keep], j[keep], np.sqrt(d2[keep])


class Frame:
    """One stereo frame: left keypoints, descriptors, right coordinates and depths, pose, matches."""

    _next_id = 0

    def __init__(self, stamp: float, left: np.ndarray, right: np.ndarray, camera,
                 extractor: ORBextractor, extractor_right: Optional[ORBextractor] = None,
                 th_depth_factor: float = 35.0, features: Optional[tuple] = None):
        """``features``: the pair's :func:`stereo_features` when made elsewhere (a worker
        process); else they are computed here with the extractors."""
        self.id = Frame._next_id
        Frame._next_id += 1
        self.stamp = float(stamp)
        self.camera = camera
        self.fx, self.fy, self.cx, self.cy = camera.fx, camera.fy, camera.cx, camera.cy
        self.baseline = camera.baseline
        self.bf = self.fx * self.baseline
        self.doffs = float(getattr(camera, "doffs", 0.0))   # cx_left - cx_right (px)
        self.width, self.height = camera.size
        self.th_depth = th_depth_factor * self.baseline   # "close" points (ORB-SLAM2 mThDepth)
        self.scale = extractor.scale
        self.inv_level_sigma2 = extractor.inv_level_sigma2
        self.log_scale = np.log(extractor.scale_factor)
        self.nlevels = extractor.nlevels
        if features is None:
            features = stereo_features(left, right, extractor, extractor_right, self.fx,
                                       self.baseline, self.doffs)
        self.uv, self.octave, self.angle, self.desc, self.ur, self.depth, self.n_primary = \
            features[:7]
        self._grad = features[7] if len(features) > 7 else None   # gradient_energy of the keypoints
        self.N = len(self.uv)
        # the images, for the optical-flow fallback (only the last frame is kept by Tracking)
        self.image, self.right_image = left, right
        self.mp_ids = -np.ones(self.N, dtype=np.int64)     # matched MapPoint id per keypoint
        self.outlier = np.zeros(self.N, dtype=bool)
        self.T_cw: Optional[np.ndarray] = None
        # the camera in the robot's odometry frame at this stamp (wheel odometry), when known:
        # the motion between two frames then comes from it instead of a constant velocity
        self.T_odom_cam: Optional[np.ndarray] = None
        # ... and with the odometry's fitted errors taken out, once they are (System:
        # OdometryCalibration.calibrated)
        self.T_odom_cam_calibrated: Optional[np.ndarray] = None
        self.ref_kf = None
        self._grid = None
        self.build_ms = self.build_cpu_ms = 0.0   # wall and CPU time of making it (System.make_frame)
        self.texture_tau = 0.0   # > 0: per-axis keypoint weights (texture_weights)
        self._tex_w = None

    # --- the keypoint grid: radius queries for all projections at once
    @property
    def grid(self) -> FeatureGrid:
        if self._grid is None:
            self._grid = FeatureGrid(self.uv)
        return self._grid

    def set_pose(self, T_cw: np.ndarray) -> None:
        self.T_cw = normalize_pose(np.asarray(T_cw, dtype=float))

    def append_keypoints(self, uv, octave, angle, desc, ur, depth) -> np.ndarray:
        """Add keypoints found by other means than detection (optical-flow tracks of the last
        frame's map points); returns their indices. They are unmatched and inliers."""
        n = len(uv)
        idx = np.arange(self.N, self.N + n)
        self.uv = np.concatenate([self.uv, np.asarray(uv, np.float32).reshape(-1, 2)])
        self.octave = np.concatenate([self.octave, np.asarray(octave, self.octave.dtype)])
        self.angle = np.concatenate([self.angle, np.asarray(angle, self.angle.dtype)])
        self.desc = np.concatenate([self.desc, np.asarray(desc, np.uint8).reshape(-1, 32)])
        self.ur = np.concatenate([self.ur, np.asarray(ur, self.ur.dtype)])
        self.depth = np.concatenate([self.depth, np.asarray(depth, self.depth.dtype)])
        self.mp_ids = np.concatenate([self.mp_ids, -np.ones(n, self.mp_ids.dtype)])
        self.outlier = np.concatenate([self.outlier, np.zeros(n, bool)])
        self.N += n
        self._grid = None
        return idx

    def texture_weights(self, idx: np.ndarray):
        """(len(idx), 2) weights of keypoints' x (u and u_R) and y residuals: the gradient
        energy of their patch along that axis over ``texture_tau``, at most 1; None when off."""
        if self.texture_tau <= 0.0:
            return None
        if self._grad is None or len(self._grad) < self.N:   # keypoints appended since
            done = 0 if self._grad is None else len(self._grad)
            new = gradient_energy(self.image, self.uv[done:])
            self._grad = new if self._grad is None else np.concatenate([self._grad, new])
        if self._tex_w is None or len(self._tex_w) != len(self._grad):
            self._tex_w = np.minimum(self._grad / self.texture_tau, 1.0)
        return self._tex_w[idx]

    @property
    def T_wc(self) -> np.ndarray:
        return inv_T(self.T_cw)

    def stereo_points_camera(self, idx: Optional[np.ndarray] = None) -> np.ndarray:
        """Camera-frame 3-D points of keypoints with depth (UnprojectStereo, before the pose)."""
        idx = np.nonzero(self.depth > 0)[0] if idx is None else idx
        z = self.depth[idx].astype(float)
        x = (self.uv[idx, 0] - self.cx) * z / self.fx
        y = (self.uv[idx, 1] - self.cy) * z / self.fy
        return np.stack([x, y, z], axis=1)

    def unproject_stereo(self, idx: np.ndarray) -> np.ndarray:
        """World points of keypoints ``idx`` (their depth must be > 0)."""
        return transform_points(self.T_wc, self.stereo_points_camera(idx))
