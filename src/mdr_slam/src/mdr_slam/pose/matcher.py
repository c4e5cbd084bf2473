"""ORBmatcher: projection search and descriptor matching, vectorized (ORB-SLAM2 ORBmatcher).

ORB-SLAM2 loops over map points and asks the frame's cell grid for keypoints near each
projection. Here all projections are answered at once: the frame's FeatureGrid gives every
(point, keypoint) pair within each point's radius (vectorized, frame.FeatureGrid.pairs_within),
and masks apply the pyramid-level window, right-image check and "keypoint still free" test. Distances are Hamming on
the candidate pairs only; best/second-best per point and one point per keypoint are resolved with
sorts, not loops.
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

from ..geometry import transform_points
from .orb import TH_HIGH, TH_LOW, expand_ranges, hamming, hamming_knn2

__all__ = ["ORBmatcher"]

HISTO_LENGTH = 30


def _best_two(owner: np.ndarray, dist: np.ndarray, other: np.ndarray):
    """Per owner: index (into the pair arrays) of its best pair, and its second-best distance
    (integer distances below 65536, as Hamming; ``other`` >= 0)."""
    if len(owner) == 0:
        z = np.zeros(0, dtype=np.int64)
        return z, z, z
    # one sort on (owner, distance, other): ties go to the lower ``other`` whatever the pair order
    o = np.argsort((owner.astype(np.int64) * 65536 + dist) * (int(other.max()) + 1) + other)
    ow = owner[o]
    first = np.r_[True, ow[1:] != ow[:-1]]
    best = o[first]
    # second best: the element after the first in each group, if same owner
    pos = np.nonzero(first)[0]
    nxt = pos + 1
    has2 = nxt < len(o)
    has2[has2] = ow[nxt[has2]] == ow[pos[has2]]
    second = np.full(len(best), np.iinfo(np.int32).max, dtype=np.int64)
    second[has2] = dist[o[nxt[has2]]]
    second_other = np.full(len(best), -1, dtype=np.int64)
    second_other[has2] = other[o[nxt[has2]]]
    return best, second, second_other


def _unique_by(key: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Indices keeping, for each distinct ``key``, the element with the smallest ``dist``."""
    if len(key) == 0:
        return np.zeros(0, dtype=np.int64)
    o = np.lexsort((dist, key))
    k = key[o]
    return o[np.r_[True, k[1:] != k[:-1]]]


def rotation_consistency(angle_a: np.ndarray, angle_b: np.ndarray) -> np.ndarray:
    """Mask of matches whose keypoint-angle change falls in the 3 most populated of 30 histogram
    bins (ORB-SLAM2 ComputeThreeMaxima): rejects matches inconsistent with the image rotation."""
    rot = np.mod(angle_a - angle_b, 360.0)
    b = np.minimum((rot * HISTO_LENGTH / 360.0).astype(int), HISTO_LENGTH - 1)
    counts = np.bincount(b, minlength=HISTO_LENGTH)
    top = np.argsort(-counts)[:3]
    keep_bins = [top[0]]
    for t in top[1:]:   # ORB-SLAM2 drops the 2nd/3rd maxima when < 10% of the first
        if counts[t] > 0.1 * counts[top[0]]:
            keep_bins.append(t)
    return np.isin(b, keep_bins)


class ORBmatcher:
    def __init__(self, nn_ratio: float = 0.6, check_orientation: bool = True):
        self.nn_ratio = nn_ratio
        self.check_orientation = check_orientation

    def match_projections(self, frame, u, v, radius, desc, lvl_lo, lvl_hi, ur=None,
                          th_dist: int = TH_HIGH, ratio: Optional[float] = None,
                          angle=None, free_only: bool = True
                          ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(point index, keypoint index, distance) for projections (u, v) searched in ``frame``.

        ``radius`` per point (px); keypoint octave must lie in [lvl_lo, lvl_hi]; when ``ur`` is
        given, a keypoint with a right coordinate must also match it within the radius. Only free
        keypoints (frame.mp_ids < 0) are candidates, unless ``free_only`` is false (fusion).
        """
        P = len(u)
        empty = (np.zeros(0, np.int64),) * 2 + (np.zeros(0, np.int32),)
        if P == 0 or frame.N == 0:
            return empty
        i, j, _ = frame.grid.pairs_within(u, v, radius)
        if len(i) == 0:
            return empty
        ok = frame.mp_ids[j] == -1 if free_only else np.ones(len(j), dtype=bool)
        oc = frame.octave[j]
        ok &= (oc >= lvl_lo[i]) & (oc <= lvl_hi[i])
        if ur is not None:
            has_r = frame.ur[j] >= 0
            ok &= ~has_r | (np.abs(ur[i] - frame.ur[j]) <= radius[i])
        i, j = i[ok], j[ok]
        if len(i) == 0:
            return empty
        d = hamming(desc[i], frame.desc[j])
        keep = d <= th_dist
        i, j, d = i[keep], j[keep], d[keep]
        if len(i) == 0:
            return empty
        best, second, second_j = _best_two(i, d, j)
        bi, bj, bd = i[best], j[best], d[best]
        if ratio is not None:   # ambiguous at the same level -> reject (SearchByProjection)
            same_lvl = (second_j >= 0) & (frame.octave[np.maximum(second_j, 0)] == frame.octave[bj])
            ok = ~(same_lvl & (bd > ratio * second))
            bi, bj, bd = bi[ok], bj[ok], bd[ok]
        u_ = _unique_by(bj, bd)
        bi, bj, bd = bi[u_], bj[u_], bd[u_]
        if angle is not None and self.check_orientation and len(bi) > 0:
            ok = rotation_consistency(angle[bi], frame.angle[bj])
            bi, bj, bd = bi[ok], bj[ok], bd[ok]
        return bi, bj, bd

    # ------------------------------------------------------------------ tracking searches
    def search_by_projection_last(self, frame, last, map_, th: float) -> int:
        """Project the last frame's map points with the predicted pose (motion model)."""
        sel = np.nonzero((last.mp_ids >= 0) & ~last.outlier)[0]
        if len(sel) == 0:
            return 0
        ids = last.mp_ids[sel]
        good = ~map_.mp_bad[ids]
        sel, ids = sel[good], ids[good]
        Pc = transform_points(frame.T_cw, map_.mp_pos[ids])
        z = Pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = frame.fx * Pc[:, 0] / z + frame.cx
            v = frame.fy * Pc[:, 1] / z + frame.cy
        inimg = (z > 0) & (u >= 0) & (u < frame.width) & (v >= 0) & (v < frame.height)
        sel, ids, u, v, z = sel[inimg], ids[inimg], u[inimg], v[inimg], z[inimg]
        oc = last.octave[sel]
        radius = th * frame.scale[oc]
        # ORB-SLAM2 also restricts the level by the forward/backward motion; +-1 octave suffices
        i, j, _ = self.match_projections(frame, u, v, radius, map_.mp_desc[ids], oc - 1, oc + 1,
                                         ur=u - frame.bf / z, angle=last.angle[sel])
        frame.mp_ids[j] = ids[i]
        frame.outlier[j] = False
        return len(i)

    def search_local_points(self, frame, map_, ids: np.ndarray, th: float) -> Tuple[int, np.ndarray]:
        """SearchByProjection for local map points ``ids`` (frustum test included).

        Returns (matches, ids that were in the frustum) so the caller increases their 'visible'."""
        if len(ids) == 0:
            return 0, ids
        Twc = frame.T_wc
        Pw = map_.mp_pos[ids]
        Pc = transform_points(frame.T_cw, Pw)
        z = Pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = frame.fx * Pc[:, 0] / z + frame.cx
            v = frame.fy * Pc[:, 1] / z + frame.cy
        PO = Pw - Twc[:3, 3]
        dist = np.linalg.norm(PO, axis=1)
        view_cos = np.einsum("ij,ij->i", PO, map_.mp_normal[ids]) / np.maximum(dist, 1e-9)
        ok = ((z > 0) & (u >= 0) & (u < frame.width) & (v >= 0) & (v < frame.height) &
              (dist >= 0.8 * map_.mp_min_dist[ids]) & (dist <= 1.2 * map_.mp_max_dist[ids]) &
              (view_cos >= 0.5))
        ids, u, v, z, dist, view_cos = ids[ok], u[ok], v[ok], z[ok], dist[ok], view_cos[ok]
        if len(ids) == 0:
            return 0, ids
        lvl = map_.predict_scale(ids, dist, frame.log_scale, frame.nlevels)
        r = np.where(view_cos > 0.998, 2.5, 4.0) * th * frame.scale[lvl]
        i, j, _ = self.match_projections(frame, u, v, r, map_.mp_desc[ids], lvl - 1, lvl,
                                         ur=u - frame.bf / z, ratio=0.8)
        frame.mp_ids[j] = ids[i]
        frame.outlier[j] = False
        return len(i), ids

    def fuse(self, kf, map_, ids: np.ndarray, T_cw: Optional[np.ndarray] = None,
             th: float = 3.0) -> Tuple[np.ndarray, np.ndarray]:
        """ORB-SLAM2 ORBmatcher::Fuse: project map points ``ids`` into keyframe ``kf`` (at
        ``T_cw``, default its own pose) and match each to a keypoint near its projection at the
        predicted level, free or not, within TH_LOW and the reprojection chi2 (stereo where the
        keypoint has a right coordinate). Points ``kf`` already sees are skipped. Returns
        (point ids, keypoint indices), one point per keypoint (the closest descriptor); the
        caller adds the observation or fuses the two points (Map.fuse_points)."""
        none = np.zeros(0, np.int64), np.zeros(0, np.int64)
        ids = np.asarray(ids, dtype=np.int64)
        ids = ids[~map_.mp_bad[ids]]
        if len(ids) == 0 or kf.N == 0:
            return none
        seen = np.zeros(map_.n + 1, dtype=bool)
        seen[kf.mp_ids] = True      # index -1 (no point) lands in the spare slot
        ids = ids[~seen[ids]]
        if len(ids) == 0:
            return none
        T_cw = kf.T_cw if T_cw is None else T_cw
        Pw = map_.mp_pos[ids]
        Pc = transform_points(T_cw, Pw)
        z = Pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = kf.fx * Pc[:, 0] / z + kf.cx
            v = kf.fy * Pc[:, 1] / z + kf.cy
        PO = Pw + T_cw[:3, :3].T @ T_cw[:3, 3]     # Pw - camera centre
        dist = np.linalg.norm(PO, axis=1)
        view_cos = np.einsum("ij,ij->i", PO, map_.mp_normal[ids]) / np.maximum(dist, 1e-9)
        ok = ((z > 0) & (u >= 0) & (u < kf.width) & (v >= 0) & (v < kf.height) &
              (dist >= 0.8 * map_.mp_min_dist[ids]) & (dist <= 1.2 * map_.mp_max_dist[ids]) &
              (view_cos >= 0.5))
        ids, u, v, z, dist = ids[ok], u[ok], v[ok], z[ok], dist[ok]
        if len(ids) == 0:
            return none
        lvl = map_.predict_scale(ids, dist, kf.log_scale, kf.nlevels)
        ur = u - kf.bf / z
        i, j, _ = self.match_projections(kf, u, v, th * kf.scale[lvl], map_.mp_desc[ids],
                                         lvl - 1, lvl, th_dist=TH_LOW, free_only=False)
        if len(i) == 0:
            return none
        # reprojection error of the point at the keypoint (ORB-SLAM2: chi2 at 95 %)
        e2 = (u[i] - kf.uv[j, 0]) ** 2 + (v[i] - kf.uv[j, 1]) ** 2
        st = kf.ur[j] >= 0
        e2 = e2 + np.where(st, (ur[i] - kf.ur[j]) ** 2, 0.0)
        good = e2 * kf.inv_level_sigma2[kf.octave[j]] <= np.where(st, 7.8, 5.99)
        return ids[i[good]], j[good].astype(np.int64)

    @staticmethod
    def search_by_bow(desc1: np.ndarray, node1: np.ndarray, desc2: np.ndarray, node2: np.ndarray,
                      ratio: float, th: int = TH_LOW) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """ORB-SLAM2 SearchByBoW (keyframe to keyframe): a descriptor of set 1 is compared only with
        those of set 2 under the same vocabulary node (``node1``, ``node2``: the direct index,
        ORBVocabulary.node_of_words); its best match is kept when within ``th`` and below
        ``ratio`` x the second best of that node, one per descriptor of set 2 (the closest).
        Returns (index in set 1, index in set 2, distance). About a hundredth of the pairs of a
        brute-force search with 100 nodes."""
        none = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int32))
        if len(desc1) == 0 or len(desc2) == 0:
            return none
        o2 = np.argsort(node2, kind="stable")
        n2 = np.asarray(node2)[o2]
        own, pos = expand_ranges(np.searchsorted(n2, node1, side="left"),
                                 np.searchsorted(n2, node1, side="right"))
        if len(own) == 0:
            return none
        j = o2[pos]
        d = hamming(desc1[own], desc2[j])
        best, second, _ = _best_two(own, d, j)
        bi, bj, bd = own[best], j[best], d[best]
        ok = (bd <= th) & (bd < ratio * second)
        bi, bj, bd = bi[ok], bj[ok], bd[ok]
        u_ = _unique_by(bj, bd)
        return bi[u_], bj[u_], bd[u_]

    def search_by_descriptors(self, kf, frame, map_, ratio: float = 0.7,
                              th: int = TH_LOW) -> Tuple[np.ndarray, np.ndarray]:
        """Brute-force matching of ``kf``'s map-point keypoints against the frame's free keypoints
        (stands in for SearchByBoW: two nearest by cv2.batchDistance, ratio test, mutual uniqueness, rotation
        histogram). Returns (frame keypoint indices, map point ids)."""
        sel = np.nonzero(kf.mp_ids >= 0)[0]
        sel = sel[~map_.mp_bad[kf.mp_ids[sel]]]
        free = np.nonzero(frame.mp_ids < 0)[0]
        if len(sel) == 0 or len(free) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        d12, b12 = hamming_knn2(kf.desc[sel], frame.desc[free])
        d1, d2, b = d12[:, 0], d12[:, 1], b12[:, 0]
        ok = (d1 <= th) & (d1 < ratio * d2)
        ia, jb, dd = np.nonzero(ok)[0], b[ok], d1[ok]
        u_ = _unique_by(jb, dd)
        ia, jb = ia[u_], jb[u_]
        if self.check_orientation and len(ia):
            keep = rotation_consistency(kf.angle[sel[ia]], frame.angle[free[jb]])
            ia, jb = ia[keep], jb[keep]
        return free[jb], kf.mp_ids[sel[ia]]
