"""Dense-map metrics: accuracy and completeness of a reconstructed cloud against a ground-truth one.

As in the paper's map evaluation (and the usual multi-view-stereo benchmarks):

* accuracy: distance from each ESTIMATED point to its nearest ground-truth point; we report the
  RMS (the paper's "map RMSE"), mean, median and the share of estimated points within a threshold
  (precision);
* completeness: share of GROUND-TRUTH points that have an estimated point within the threshold
  (recall), plus their F-score.

Nearest neighbours come from scipy's cKDTree (``workers=-1``), so a few million points take
seconds. When the ground-truth cloud has a per-point ``surface`` label (1 low-texture, 2 textured,
3 specular), each estimated point takes the label of its nearest ground-truth point and the
figures are also given per label, which is how the paper separates low-texture regions.

Within range of the path: a simulator's ground-truth map holds every surface the camera saw up to
its render range (8 m), while a stereo rig only measures well much closer (depth error grows with
Z^2). With the camera's path (a trajectory's positions), :func:`map_metrics` also scores the part
of both clouds within ``max_range`` of it (block ``in_range``): ground-truth points within range
against the WHOLE estimate (so a surface at the border is not missed for a point just beyond it),
estimated points within range against the WHOLE ground truth (so they are not penalised for a
true surface just beyond it). The whole-map figures stay where they were.
"""
from __future__ import annotations

from typing import Dict, Optional, Sequence

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["map_metrics", "nearest_distances", "within_range", "path_positions",
           "SURFACE_LABELS", "DEFAULT_THRESHOLDS", "DEFAULT_MAX_RANGE"]

SURFACE_LABELS = {1: "low_texture", 2: "textured", 3: "specular"}
DEFAULT_THRESHOLDS = (0.01, 0.02, 0.05, 0.10)
DEFAULT_MAX_RANGE = 4.0   # m from the camera path: where a small-baseline stereo rig maps well


def _kdtree(ref: np.ndarray):
    """cKDTree tuned for millions of 3-D points: small leaves, median-free splits (faster build
    and queries here than the balanced default)."""
    return cKDTree(ref, leafsize=16, balanced_tree=False, compact_nodes=False)


def _spatial_order(P: np.ndarray) -> np.ndarray:
    """Permutation that groups points by a coarse voxel (128 cells along the widest axis).

    Querying neighbouring points one after the other keeps the tree nodes they visit in cache:
    2-3x faster than querying in random order on a few million points.
    """
    if len(P) < 2:
        return np.arange(len(P))
    lo = P.min(axis=0)
    cell = max(float(np.ptp(P, axis=0).max()) / 128.0, 1e-9)
    v = np.clip(((P - lo) / cell).astype(np.int64), 0, 1023)
    return np.argsort((v[:, 0] << 20) | (v[:, 1] << 10) | v[:, 2], kind="stable")


def nearest_distances(query: np.ndarray, ref: np.ndarray, tree=None):
    """(distances, indices) of the nearest ``ref`` point for each ``query`` point."""
    ref = np.asarray(ref, dtype=np.float64).reshape(-1, 3)
    query = np.asarray(query, dtype=np.float64).reshape(-1, 3)
    if tree is None:
        tree = _kdtree(ref)
    order = _spatial_order(query)
    d = np.empty(len(query))
    i = np.empty(len(query), dtype=np.int64)
    d[order], i[order] = tree.query(query[order], k=1, workers=-1)
    return d, i


def path_positions(path) -> np.ndarray:
    """(K, 3) finite camera positions of ``path``: a Trajectory (its ``positions``) or an array."""
    P = np.asarray(getattr(path, "positions", path), dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError("the camera path must be (K, 3) positions, got shape %s" % (P.shape,))
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) == 0:
        raise ValueError("the camera path has no finite positions")
    return P


def within_range(points: np.ndarray, path, max_range: float = DEFAULT_MAX_RANGE) -> np.ndarray:
    """Boolean mask of the (N, 3) ``points`` within ``max_range`` m of a position of ``path``
    (a Trajectory or (K, 3) positions): one KD-tree query over the path's positions."""
    if not max_range > 0:
        raise ValueError("max_range must be > 0, got %r" % (max_range,))
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    tree = cKDTree(path_positions(path))
    d, _ = tree.query(P, k=1, distance_upper_bound=float(max_range), workers=-1)
    return d <= max_range


def _finite(P: np.ndarray, name: str) -> np.ndarray:
    P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) == 0:
        raise ValueError("the %s cloud has no finite points" % name)
    return P


def _block(d_acc: np.ndarray, d_comp: np.ndarray, threshold: float,
           thresholds: Sequence[float]) -> Dict[str, object]:
    out: Dict[str, object] = {"n_estimate": int(len(d_acc)), "n_ground_truth": int(len(d_comp))}
    if len(d_acc):
        out.update({"accuracy_rmse": float(np.sqrt(np.mean(d_acc ** 2))),
                    "accuracy_mean": float(np.mean(d_acc)),
                    "accuracy_median": float(np.median(d_acc)),
                    "accuracy_max": float(np.max(d_acc)),
                    "accuracy": float(np.mean(d_acc <= threshold))})
    if len(d_comp):
        out.update({"completeness": float(np.mean(d_comp <= threshold)),
                    "completeness_mean": float(np.mean(d_comp)),
                    "completeness_median": float(np.median(d_comp))})
    if len(d_acc) and len(d_comp):
        p, r = out["accuracy"], out["completeness"]
        out["fscore"] = float(2 * p * r / (p + r)) if p + r > 0 else 0.0
    per = {}
    for t in thresholds:
        per["%g" % t] = {"accuracy": float(np.mean(d_acc <= t)) if len(d_acc) else None,
                         "completeness": float(np.mean(d_comp <= t)) if len(d_comp) else None}
    out["at_threshold"] = per
    return out


def _per_label(d_acc, d_comp, est_labels, gt_labels, names, threshold, thresholds):
    per = {}
    for lab in names:
        name = SURFACE_LABELS.get(int(lab), "label_%d" % lab)
        per[name] = _block(d_acc[est_labels == lab], d_comp[gt_labels == lab], threshold,
                           thresholds)
        per[name]["label"] = int(lab)
    return per


def map_metrics(est_xyz: np.ndarray, gt_xyz: np.ndarray, threshold: float = 0.05,
                thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
                gt_labels: Optional[np.ndarray] = None,
                return_distances: bool = False, path=None,
                max_range: float = DEFAULT_MAX_RANGE) -> Dict[str, object]:
    """Accuracy / completeness of ``est_xyz`` (N, 3) against ``gt_xyz`` (M, 3), metres.

    ``accuracy_rmse`` is the RMS of estimated-to-ground-truth nearest distances; ``completeness``
    the share of ground-truth points with an estimated point within ``threshold``; ``accuracy``
    the share of estimated points within ``threshold`` of the ground truth. With ``gt_labels``
    (M,) the result has ``per_label`` blocks (estimated points labelled by their nearest
    ground-truth point). ``return_distances`` adds the two distance arrays (``_d_acc``,
    ``_d_comp``) for plotting.

    ``path`` (a Trajectory or (K, 3) camera positions in the clouds' frame) adds the block
    ``in_range``: the same figures (and ``per_label``) for the ground-truth and estimated points
    within ``max_range`` m of the path (see the module docstring); ``accuracy`` there is the
    precision at ``threshold`` and ``fscore`` its harmonic mean with ``completeness``.
    """
    if path is not None:   # bad path or range: fail before the long nearest-neighbour queries
        path = path_positions(path)
        if not max_range > 0:
            raise ValueError("max_range must be > 0, got %r" % (max_range,))
    gt_all = np.asarray(gt_xyz, dtype=np.float64).reshape(-1, 3)
    keep_gt = np.all(np.isfinite(gt_all), axis=1)
    gt = _finite(gt_all, "ground-truth")
    est = _finite(est_xyz, "estimated")
    d_acc, i_acc = nearest_distances(est, gt)
    d_comp, _ = nearest_distances(gt, est)
    out = {"threshold": float(threshold)}
    out.update(_block(d_acc, d_comp, threshold, thresholds))
    labels = est_labels = None
    if gt_labels is not None:
        labels = np.asarray(gt_labels).reshape(-1)
        if len(labels) != len(gt_all):
            raise ValueError("%d ground-truth labels for %d points" % (len(labels), len(gt_all)))
        labels = labels[keep_gt].astype(int)
        est_labels = labels[i_acc]
        out["per_label"] = _per_label(d_acc, d_comp, est_labels, labels, np.unique(labels),
                                      threshold, thresholds)
    if path is not None:
        in_gt = within_range(gt, path, max_range)
        in_est = within_range(est, path, max_range)
        rng = {"max_range_m": float(max_range)}
        rng.update(_block(d_acc[in_est], d_comp[in_gt], threshold, thresholds))
        if "fscore" not in rng:   # no estimated point in range scores 0; no true one: undefined
            rng["fscore"] = 0.0 if in_gt.any() else None
        if labels is not None:
            # every label of the whole map, so a label the path never came near reads as empty
            rng["per_label"] = _per_label(d_acc[in_est], d_comp[in_gt], est_labels[in_est],
                                          labels[in_gt], np.unique(labels), threshold, thresholds)
        out["in_range"] = rng
    if return_distances:
        out["_d_acc"] = d_acc
        out["_d_comp"] = d_comp
    return out
