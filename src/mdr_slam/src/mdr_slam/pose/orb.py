"""ORB features spread over the image, and vectorized Hamming distances (ORBextractor role).

ORB-SLAM2 detects FAST per grid cell on each pyramid level and keeps the strongest corners of an
octree so features cover the whole image; here cv2.FastFeatureDetector finds each level's corners,
a vectorized grid selection keeps each level's share spread over the image, and cv2.ORB computes
the 32-byte rBRIEF descriptors (same goal: tracking needs features everywhere, not only on the most
textured object).
"""
from __future__ import annotations

import operator
from typing import Tuple

import cv2
import numpy as np

__all__ = ["ORBextractor", "hamming", "hamming_matrix", "hamming_knn2", "expand_ranges", "TH_HIGH",
           "TH_LOW"]

TH_HIGH = 100   # ORBmatcher::TH_HIGH: largest Hamming distance accepted for projection search
TH_LOW = 50     # ORBmatcher::TH_LOW: stricter bound for descriptor-only (BoW-like) matching

_RESPONSE = operator.attrgetter("response")
_OCTAVE = operator.attrgetter("octave")
_ANGLE = operator.attrgetter("angle")

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_M8 = np.uint64(0x00FF00FF00FF00FF)
_H0001 = np.uint64(0x0001000100010001)


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distance of two (N, 32) uint8 descriptor arrays.

    The 32 bytes are read as four uint64 words, XORed and counted with the SWAR popcount
    (bit-slicing arithmetic on whole words: ~2x faster than a byte lookup table in numpy)."""
    a = np.asarray(a)
    b = np.asarray(b)
    if a.ndim != 2 or a.shape[1] != 32 or a.dtype != np.uint8 or b.shape != a.shape:
        return _POPCOUNT[np.bitwise_xor(a, b)].sum(axis=-1, dtype=np.int32)
    x = np.bitwise_xor(np.ascontiguousarray(a).view(np.uint64),
                       np.ascontiguousarray(b).view(np.uint64))
    x -= (x >> np.uint64(1)) & _M1
    x = (x & _M2) + ((x >> np.uint64(2)) & _M2)
    x = (x + (x >> np.uint64(4))) & _M4
    x = x[:, 0] + x[:, 1] + x[:, 2] + x[:, 3]   # per-byte counts <= 32: no carry between bytes
    x = (x & _M8) + ((x >> np.uint64(8)) & _M8)  # 16-bit lanes <= 64 (the total, 256, needs 9 bits)
    return ((x * _H0001) >> np.uint64(48)).astype(np.int32)


def hamming_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) Hamming distances as a BLAS product of unpacked bits: |a| + |b| - 2 a.b.

    (cv2.batchDistance's Python binding rejects K=0 in OpenCV 4.10, so no full matrix from it.)
    Meant for small sets (keyframe vs keyframe); frame-to-frame searches use candidate pairs.
    """
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)), dtype=np.int32)
    ua = np.unpackbits(a, axis=1).astype(np.float32)
    ub = np.unpackbits(b, axis=1).astype(np.float32)
    D = ua.sum(1)[:, None] + ub.sum(1)[None, :] - 2.0 * (ua @ ub.T)
    return np.rint(D).astype(np.int32)


def hamming_knn2(a: np.ndarray, b: np.ndarray):
    """Per row of ``a``: the two smallest Hamming distances to rows of ``b`` and their indices,
    ((N, 2) int32, (N, 2) int), ties to the lower index (as np.argmin). cv2.batchDistance with K=2
    counts bits in C++ (4x faster than hamming_matrix's unpacked-bit BLAS product at 700x1500).
    With one row in ``b`` the second distance is 256 and its index -1."""
    n = len(a)
    if n == 0 or len(b) == 0:
        return np.full((n, 2), 256, np.int32), -np.ones((n, 2), np.int64)
    d, i = cv2.batchDistance(np.ascontiguousarray(a), np.ascontiguousarray(b), cv2.CV_32S,
                             normType=cv2.NORM_HAMMING, K=2)
    d, i = d.reshape(n, -1), i.reshape(n, -1).astype(np.int64)
    if d.shape[1] < 2:
        d = np.column_stack([d[:, 0], np.full(n, 256, np.int32)])
        i = np.column_stack([i[:, 0], -np.ones(n, np.int64)])
    return d.astype(np.int32), i


def expand_ranges(lo: np.ndarray, hi: np.ndarray):
    """(owner, index) pairs for the half-open ranges [lo[i], hi[i]) without a Python loop."""
    n = np.maximum(np.asarray(hi) - np.asarray(lo), 0)
    owner = np.repeat(np.arange(len(n)), n)
    start = np.repeat(np.asarray(lo) - np.concatenate([[0], np.cumsum(n)[:-1]]), n)
    return owner, start + np.arange(n.sum())


def _umax(half: int = 15) -> np.ndarray:
    """ORB's circular patch: the largest |u| per row v (cv2 ORB / ORB-SLAM2 ORBextractor)."""
    umax = np.zeros(half + 1, int)
    vmax = int(np.floor(half * np.sqrt(2.0) / 2 + 1))
    vmin = int(np.ceil(half * np.sqrt(2.0) / 2))
    for v in range(vmax + 1):
        umax[v] = int(np.round(np.sqrt(half * half - v * v)))
    v0 = 0
    for v in range(half, vmin - 1, -1):   # make the patch symmetric
        while umax[v0] == umax[v0 + 1]:
            v0 += 1
        umax[v] = v0
        v0 += 1
    return umax


class ORBextractor:
    """ORB-SLAM2's ORBextractor on OpenCV: FAST corners on a scale pyramid, each level's share of
    the budget spread over the image, intensity-centroid orientation, cv2.ORB's rBRIEF
    descriptors; exposes ORB-SLAM2's per-level tables.

    cv2.ORB alone keeps each level's strongest corners by Harris response, which puts them all on
    the most contrasted objects (KITTI: trees and a facade, none on the road and grass near the car
    that fix the trajectory's scale). Here cv2.FastFeatureDetector finds the corners of every level
    (the pyramid as cv2.ORB builds it), :meth:`_distribute` keeps each level's share
    (mnFeaturesPerLevel) spread over a grid, and cv2.ORB describes the kept ones.
    """

    def __init__(self, nfeatures: int = 1500, scale_factor: float = 1.2, nlevels: int = 8,
                 fast_threshold: int = 12, grid: Tuple[int, int] = (12, 8), edge: int = 19,
                 min_fast_threshold: int = 0):
        self.nfeatures = int(nfeatures)
        self.scale_factor = float(scale_factor)
        self.nlevels = int(nlevels)
        self.grid = grid
        self.edge = int(edge)
        self.orb = cv2.ORB_create(nfeatures=self.nfeatures, scaleFactor=self.scale_factor,
                                  nlevels=self.nlevels, edgeThreshold=edge, patchSize=31,
                                  fastThreshold=int(fast_threshold))
        self.fast = cv2.FastFeatureDetector_create(int(fast_threshold), True)
        # ORB-SLAM2 iniThFAST/minThFAST: cells left poor by fast_threshold are re-detected with
        # the lower threshold (low-texture walls); 0 disables the fallback
        self.fast_min = None
        if 0 < int(min_fast_threshold) < int(fast_threshold):
            self.fast_min = cv2.FastFeatureDetector_create(int(min_fast_threshold), True)
        self.scale = self.scale_factor ** np.arange(self.nlevels)          # mvScaleFactor
        # ORB-SLAM2 mnFeaturesPerLevel: a geometric share of the budget per level
        f = 1.0 / self.scale_factor
        share = self.nfeatures * (1 - f) / (1 - f ** self.nlevels) * f ** np.arange(self.nlevels)
        quota = np.round(share).astype(int)
        quota[-1] = max(self.nfeatures - quota[:-1].sum(), 0)
        self.level_quota = quota
        self.level_sigma2 = self.scale ** 2                                 # mvLevelSigma2
        self.inv_level_sigma2 = 1.0 / self.level_sigma2                     # mvInvLevelSigma2
        umax = _umax(15)
        vv, uu = np.mgrid[-15:16, -15:16]
        inside = np.abs(uu) <= umax[np.abs(vv)]
        self._patch_u, self._patch_v = uu[inside], vv[inside]             # IC-angle patch offsets
        self._patch_uv = np.column_stack([self._patch_u, self._patch_v]).astype(np.float32)
        self.n_primary = 0

    def pyramid(self, image: np.ndarray) -> list:
        """The level images as cv2.ORB makes them (each from the previous one, INTER_LINEAR_EXACT,
        size rounded from the full image's), so the corners found here are the ones it describes."""
        h, w = image.shape[:2]
        levels = [image]
        for s in self.scale[1:]:
            sz = (int(np.round(w / s)), int(np.round(h / s)))
            levels.append(cv2.resize(levels[-1], sz, interpolation=cv2.INTER_LINEAR_EXACT))
        return levels

    def _fast(self, detector, levels) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """FAST corners of every level away from the border: level coordinates (N, 2) float32,
        FAST score (N,), level (N,)."""
        xy, resp, lev = [], [], []
        for lv, img in enumerate(levels):
            kps = detector.detect(img, None)
            if not kps:
                continue
            p = cv2.KeyPoint_convert(kps).reshape(-1, 2)
            r = np.fromiter(map(_RESPONSE, kps), np.float32, count=len(kps))
            hh, ww = img.shape[:2]
            e = self.edge
            ok = (p[:, 0] >= e) & (p[:, 0] < ww - e) & (p[:, 1] >= e) & (p[:, 1] < hh - e)
            xy.append(p[ok])
            resp.append(r[ok])
            lev.append(np.full(int(ok.sum()), lv, int))
        if not xy:
            return np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros(0, int)
        return np.concatenate(xy), np.concatenate(resp), np.concatenate(lev)

    def _cell(self, uv: np.ndarray, w: int, h: int) -> np.ndarray:
        gx, gy = self.grid
        return (np.minimum((uv[:, 0] * gx / w).astype(int), gx - 1) * gy +
                np.minimum((uv[:, 1] * gy / h).astype(int), gy - 1))

    def _detect(self, levels):
        """FAST corners at fast_threshold; when the image yields fewer than the budget, cells
        with fewer than half their share take the min_fast_threshold corners instead.
        Returns level coordinates, full-resolution coordinates, score, level."""
        h, w = levels[0].shape[:2]
        xy, resp, lev = self._fast(self.fast, levels)
        self.n_primary = len(xy)   # corners at fast_threshold (Tracking's low-texture test)
        if self.fast_min is not None and len(xy) < self.nfeatures:
            xy2, resp2, lev2 = self._fast(self.fast_min, levels)
            if len(xy2):
                gx, gy = self.grid
                share = max(1, int(np.ceil(self.nfeatures / float(2 * gx * gy))))
                kc = self._cell(xy * self.scale[lev][:, None], w, h)
                poor = np.bincount(kc, minlength=gx * gy) < share
                k1 = ~poor[kc]
                k2 = poor[self._cell(xy2 * self.scale[lev2][:, None], w, h)]
                xy = np.concatenate([xy[k1], xy2[k2]])
                resp = np.concatenate([resp[k1], resp2[k2]])
                lev = np.concatenate([lev[k1], lev2[k2]])
        return xy, xy * self.scale[lev][:, None], resp, lev

    def _distribute(self, uv, resp, level, w, h) -> np.ndarray:
        """Indices of the kept corners, strongest first: each level's share of the budget
        (ORB-SLAM2 mnFeaturesPerLevel) spread over the grid by rounds (the strongest corner of
        every cell that has one, then the second strongest, ...; ORB-SLAM2's octree keeps one per
        node to the same end), the last round by score; levels short of corners leave their share
        to the strongest of the rest."""
        gx, gy = self.grid
        n = self.nfeatures
        # FAST scores are integers (<= 255) and the keys small: 16-bit stable sorts (radix)
        small = np.int16 if self.nlevels * gx * gy < 32768 and self.nlevels <= 8 else np.int32
        key = (level * (gx * gy) + self._cell(uv, w, h)).astype(small)
        by_score = np.argsort((-resp).astype(np.int16), kind="stable")
        order = by_score[np.argsort(key[by_score], kind="stable")]
        k_sorted = key[order]
        rank = np.empty(len(order), np.int32)   # of each corner within its (level, cell) by score
        rank[order] = np.arange(len(order)) - np.searchsorted(k_sorted, k_sorted, side="left")
        # within a level: all rank-0 corners first, then rank 1, ... (ties by score)
        comp = level[by_score] * 4096 + np.minimum(rank[by_score], 4095)
        order = by_score[np.argsort(comp.astype(small), kind="stable")]
        l_sorted = level[order]
        pos = np.arange(len(order)) - np.searchsorted(l_sorted, l_sorted, side="left")
        keep = order[pos < self.level_quota[l_sorted]]
        if len(keep) < n:   # levels short of corners: the strongest of the rest
            free = np.ones(len(uv), bool)
            free[keep] = False
            rest = np.nonzero(free)[0]
            rest = rest[np.argsort(-resp[rest], kind="stable")][: n - len(keep)]
            keep = np.concatenate([keep, rest])
        return keep[np.argsort(-resp[keep], kind="stable")]

    def _angles(self, levels, xy: np.ndarray, level: np.ndarray) -> np.ndarray:
        """Intensity-centroid orientation (degrees, [0, 360)) of each corner on its level image:
        atan2(m01, m10) over ORB's radius-15 circular patch, as cv2.ORB's ICAngles."""
        ang = np.zeros(len(xy), np.float32)
        xi = np.rint(xy).astype(np.int32)
        for lv in np.unique(level):
            sel = np.nonzero(level == lv)[0]
            img = levels[lv]
            base = xi[sel, 1] * img.shape[1] + xi[sel, 0]
            off = (self._patch_v * img.shape[1] + self._patch_u).astype(np.int32)
            m = np.take(img.ravel(), base[:, None] + off[None, :]).astype(np.float32) @ self._patch_uv
            ang[sel] = np.degrees(np.arctan2(m[:, 1], m[:, 0])) % 360.0
        return ang

    def __call__(self, image: np.ndarray):
        """(uv (N, 2) float32, octave (N,) int, angle (N,) float32, descriptors (N, 32) uint8)."""
        empty = (np.zeros((0, 2), np.float32), np.zeros(0, int), np.zeros(0, np.float32),
                 np.zeros((0, 32), np.uint8))
        levels = self.pyramid(image)
        xy, uv, resp, lev = self._detect(levels)
        if len(xy) == 0:
            return empty
        h, w = image.shape[:2]
        keep = self._distribute(uv, resp, lev, w, h)
        xy, uv, resp, lev = xy[keep], uv[keep], resp[keep], lev[keep]
        ang = self._angles(levels, xy, lev)
        size = 31.0 * self.scale
        kps = list(map(cv2.KeyPoint, uv[:, 0].tolist(), uv[:, 1].tolist(), size[lev].tolist(),
                       ang.tolist(), resp.tolist(), lev.tolist()))
        kps, desc = self.orb.compute(image, kps)
        if desc is None or not kps:
            return empty
        uv = cv2.KeyPoint_convert(kps).reshape(-1, 2)
        octave = np.array(list(map(_OCTAVE, kps)), dtype=int)
        # cv2.ORB reports level coordinates times the scale; with cv2.resize's pixel-centre
        # convention the full-resolution position is x*s + (s-1)/2. Without this the offset grows
        # with the octave, and in forward motion (points climbing octaves) it reads as drift.
        uv += (0.5 * (self.scale[octave] - 1.0)).astype(np.float32)[:, None]
        angle = np.array(list(map(_ANGLE, kps)), dtype=np.float32)
        return uv, octave, angle, desc
