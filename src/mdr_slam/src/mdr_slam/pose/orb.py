"""ORB features spread over the image, and vectorized Hamming distances (ORBextractor role).

ORB-SLAM2 detects FAST per grid cell and keeps the strongest corners of an octree so features cover
the whole image; here cv2.ORB detects 2x the budget over its scale pyramid and a vectorized bucket
selection keeps the strongest ``nfeatures / cells`` per cell (same goal: tracking needs features
everywhere, not only on the most textured object). Descriptors are 32-byte rBRIEF as in ORB-SLAM2.
"""
from __future__ import annotations

import operator
from typing import Tuple

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
    import cv2
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


class ORBextractor:
    """cv2.ORB with a scale pyramid plus grid bucketing; exposes ORB-SLAM2's per-level tables."""

    def __init__(self, nfeatures: int = 1500, scale_factor: float = 1.2, nlevels: int = 8,
                 fast_threshold: int = 12, grid: Tuple[int, int] = (12, 8), edge: int = 19,
                 min_fast_threshold: int = 0):
        import cv2
        self.nfeatures = int(nfeatures)
        self.scale_factor = float(scale_factor)
        self.nlevels = int(nlevels)
        self.grid = grid
        self.orb = cv2.ORB_create(nfeatures=2 * self.nfeatures, scaleFactor=self.scale_factor,
                                  nlevels=self.nlevels, edgeThreshold=edge, patchSize=31,
                                  fastThreshold=int(fast_threshold))
        # ORB-SLAM2 iniThFAST/minThFAST: cells left poor by fast_threshold are re-detected with
        # the lower threshold (low-texture walls); 0 disables the fallback
        self.orb_min = None
        if 0 < int(min_fast_threshold) < int(fast_threshold):
            self.orb_min = cv2.ORB_create(nfeatures=2 * self.nfeatures, scaleFactor=self.scale_factor,
                                          nlevels=self.nlevels, edgeThreshold=edge, patchSize=31,
                                          fastThreshold=int(min_fast_threshold))
        self.scale = self.scale_factor ** np.arange(self.nlevels)          # mvScaleFactor
        self.level_sigma2 = self.scale ** 2                                 # mvLevelSigma2
        self.inv_level_sigma2 = 1.0 / self.level_sigma2                     # mvInvLevelSigma2

    def _cells(self, kps, shape) -> np.ndarray:
        import cv2
        h, w = shape[:2]
        gx, gy = self.grid
        uv = cv2.KeyPoint_convert(kps).reshape(-1, 2) if kps else np.zeros((0, 2), np.float32)
        return (np.minimum((uv[:, 0] * gx / w).astype(int), gx - 1) * gy +
                np.minimum((uv[:, 1] * gy / h).astype(int), gy - 1))

    def _detect(self, image: np.ndarray) -> list:
        """FAST corners at fast_threshold; when the image yields fewer than the budget, cells
        with fewer than half their share take the min_fast_threshold corners instead."""
        kps = self.orb.detect(image, None)
        self.n_primary = len(kps)   # corners at fast_threshold (Tracking's low-texture test)
        if self.orb_min is None or len(kps) >= self.nfeatures:
            return kps
        extra = self.orb_min.detect(image, None)
        if not extra:
            return kps
        gx, gy = self.grid
        share = max(1, int(np.ceil(self.nfeatures / float(2 * gx * gy))))
        kc = self._cells(kps, image.shape)
        poor = np.bincount(kc, minlength=gx * gy) < share
        ec = self._cells(extra, image.shape)
        return ([kps[i] for i in np.nonzero(~poor[kc])[0]] +
                [extra[i] for i in np.nonzero(poor[ec])[0]])

    def __call__(self, image: np.ndarray):
        """(uv (N, 2) float32, octave (N,) int, angle (N,) float32, descriptors (N, 32) uint8)."""
        kps = self._detect(image)
        if not kps:
            return (np.zeros((0, 2), np.float32), np.zeros(0, int), np.zeros(0, np.float32),
                    np.zeros((0, 32), np.uint8))
        import cv2
        h, w = image.shape[:2]
        # cv2.KeyPoint_convert and map(attrgetter) instead of per-keypoint Python expressions
        uv = cv2.KeyPoint_convert(kps).reshape(-1, 2)
        resp = np.array(list(map(_RESPONSE, kps)), dtype=np.float32)
        gx, gy = self.grid
        cell = (np.minimum((uv[:, 0] * gx / w).astype(int), gx - 1) * gy +
                np.minimum((uv[:, 1] * gy / h).astype(int), gy - 1))
        # rank within cell by response (two stable argsorts: by response, then by cell), keep
        # the best per cell
        order = np.argsort(-resp, kind="stable")
        order = order[np.argsort(cell[order], kind="stable")]
        c_sorted = cell[order]
        first = np.searchsorted(c_sorted, c_sorted, side="left")
        rank = np.arange(len(order)) - first
        per_cell = max(2, int(np.ceil(self.nfeatures / float(gx * gy))))
        keep = order[rank < per_cell]
        if len(keep) < self.nfeatures:   # textureless cells: refill with the strongest of the rest
            free = np.ones(len(kps), bool)
            free[keep] = False
            rest = np.nonzero(free)[0]
            rest = rest[np.argsort(-resp[rest])][: self.nfeatures - len(keep)]
            keep = np.concatenate([keep, rest])
        keep = keep[np.argsort(-resp[keep])][: self.nfeatures]
        kps = list(map(kps.__getitem__, keep.tolist()))
        kps, desc = self.orb.compute(image, kps)
        if desc is None or not kps:
            return (np.zeros((0, 2), np.float32), np.zeros(0, int), np.zeros(0, np.float32),
                    np.zeros((0, 32), np.uint8))
        uv = cv2.KeyPoint_convert(kps).reshape(-1, 2)
        octave = np.array(list(map(_OCTAVE, kps)), dtype=int)
        # cv2.ORB reports level coordinates times the scale; with cv2.resize's pixel-centre
        # convention the full-resolution position is x*s + (s-1)/2. Without this the offset grows
        # with the octave, and in forward motion (points climbing octaves) it reads as drift.
        uv += (0.5 * (self.scale[octave] - 1.0)).astype(np.float32)[:, None]
        angle = np.array(list(map(_ANGLE, kps)), dtype=np.float32)
        return uv, octave, angle, desc
