"""Per-frame disparity / depth errors against ground truth, and the Middlebury stereo pairs.

Disparity figures follow the Middlebury convention: a pixel is "bad" when its disparity error
exceeds 1 or 2 px; the rate is taken over the pixels where the ground truth is known AND the
method gave an estimate (``bad2``), and separately counting missing estimates as bad
(``bad2_all``), since a sparse method (ELAS leaves holes) must not look better by abstaining;
``density`` is the share of ground-truth-valid pixels with an estimate. The depth variant
(metres) is what the temporal filter is judged on: RMSE, MAE and the share of pixels off by more
than 5 cm.
"""
from __future__ import annotations

import os
from typing import Dict, Optional, Tuple

import cv2
import numpy as np

__all__ = ["depth_metrics", "depth_error_metrics", "load_middlebury", "read_disparity",
           "MIDDLEBURY", "middlebury_root"]

# name -> (left, right, ground-truth disparity of the left image, scale: stored value / scale = px)
MIDDLEBURY = {
    "tsukuba": ("im3.png", "im4.png", "disp3.pgm", 16.0),
    "venus": ("im2.png", "im6.png", "disp2.pgm", 8.0),
    "teddy": ("im2.png", "im6.png", "disp2.png", 4.0),
    "cones": ("im2.png", "im6.png", "disp2.png", 4.0),
}


def _valid(a: np.ndarray) -> np.ndarray:
    return np.isfinite(a) & (a > 0)


def depth_metrics(est_disp: np.ndarray, gt_disp: np.ndarray, mask: Optional[np.ndarray] = None,
                  thresholds=(1.0, 2.0)) -> Dict[str, float]:
    """Disparity errors (px). Ground truth <= 0 or non-finite is unknown; so is an estimate <= 0.

    Returns ``bad1``/``bad2`` (share of pixels with |error| > 1 / 2 px among pixels with both
    ground truth and estimate), ``bad1_all``/``bad2_all`` (missing estimates counted bad),
    ``mae``, ``rmse``, ``density``, ``n_valid`` (ground-truth pixels considered).
    """
    est = np.asarray(est_disp, dtype=np.float64)
    gt = np.asarray(gt_disp, dtype=np.float64)
    if est.shape != gt.shape:
        raise ValueError("estimate %s and ground truth %s differ in shape" % (est.shape, gt.shape))
    g = _valid(gt)
    if mask is not None:
        g &= np.asarray(mask, dtype=bool)
    both = g & _valid(est)
    n_gt, n_both = int(g.sum()), int(both.sum())
    out: Dict[str, float] = {"n_valid": n_gt, "n_estimated": n_both,
                             "density": float(n_both) / n_gt if n_gt else 0.0}
    err = np.abs(est[both] - gt[both])
    for t in thresholds:
        key = "bad%g" % t
        nbad = int(np.count_nonzero(err > t))
        out[key] = nbad / float(n_both) if n_both else float("nan")
        out[key + "_all"] = (nbad + n_gt - n_both) / float(n_gt) if n_gt else float("nan")
    out["mae"] = float(err.mean()) if n_both else float("nan")
    out["rmse"] = float(np.sqrt(np.mean(err ** 2))) if n_both else float("nan")
    return out


def depth_error_metrics(est_depth: np.ndarray, gt_depth: np.ndarray,
                        mask: Optional[np.ndarray] = None, max_error: float = 0.05,
                        max_depth: Optional[float] = None) -> Dict[str, float]:
    """Depth errors (metres): ``rmse``, ``mae``, ``bad`` (share with |error| > ``max_error``,
    5 cm by default), ``abs_rel``, ``density`` (share of ground-truth pixels with an estimate)."""
    est = np.asarray(est_depth, dtype=np.float64)
    gt = np.asarray(gt_depth, dtype=np.float64)
    if est.shape != gt.shape:
        raise ValueError("estimate %s and ground truth %s differ in shape" % (est.shape, gt.shape))
    g = _valid(gt)
    if max_depth is not None:
        g &= gt <= max_depth
    if mask is not None:
        g &= np.asarray(mask, dtype=bool)
    both = g & _valid(est)
    n_gt, n_both = int(g.sum()), int(both.sum())
    err = np.abs(est[both] - gt[both])
    nan = float("nan")
    return {"n_valid": n_gt, "n_estimated": n_both,
            "density": float(n_both) / n_gt if n_gt else 0.0,
            "rmse": float(np.sqrt(np.mean(err ** 2))) if n_both else nan,
            "mae": float(err.mean()) if n_both else nan,
            "abs_rel": float(np.mean(err / gt[both])) if n_both else nan,
            "bad": float(np.mean(err > max_error)) if n_both else nan,
            "max_error": float(max_error)}


def middlebury_root() -> Optional[str]:
    """Where the Middlebury pairs are: ``$MDR_MIDDLEBURY``, ``$MDR_SHARED_DATA/middlebury``,
    or ``shared/data/middlebury`` beside the workspace (the project's evaluation data)."""
    cands = []
    if os.environ.get("MDR_MIDDLEBURY"):
        cands.append(os.environ["MDR_MIDDLEBURY"])
    if os.environ.get("MDR_SHARED_DATA"):
        cands.append(os.path.join(os.environ["MDR_SHARED_DATA"], "middlebury"))
    here = os.path.abspath(__file__)
    ws = here
    for _ in range(6):    # eval/ -> mdr_slam/ -> src/ -> mdr_slam pkg -> src/ -> workspace
        ws = os.path.dirname(ws)
    cands.append(os.path.join(os.path.dirname(ws), "shared", "data", "middlebury"))
    for c in cands:
        if os.path.isdir(c):
            return c
    return None


def read_disparity(path: str, scale: float = 1.0) -> np.ndarray:
    """A disparity (or depth) image as float32 (stored value / ``scale``); .npy, .pfm, PNG/PGM/TIFF."""
    if path.endswith(".npy"):
        return np.load(path).astype(np.float32) / np.float32(scale)
    img = cv2.imread(path, cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
    if img is None:
        raise ValueError("cannot read %s" % path)
    if img.ndim == 3:
        img = img[:, :, 0]
    return img.astype(np.float32) / np.float32(scale)


def load_middlebury(name: str, root: Optional[str] = None,
                    grey: bool = True) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(left, right, ground-truth disparity in px as float32, 0 = unknown) of a Middlebury pair.

    ``name`` is tsukuba, venus, teddy or cones (a folder under ``root``), or a folder path whose
    basename is one of those. Images are grey uint8 unless ``grey=False`` (BGR).
    """
    key = os.path.basename(os.path.normpath(name)).lower()
    if key not in MIDDLEBURY:
        raise ValueError("unknown Middlebury pair %r (one of %s)" % (name, ", ".join(sorted(MIDDLEBURY))))
    if os.path.isdir(name):
        folder = name
    else:
        root = root or middlebury_root()
        if root is None:
            raise FileNotFoundError("Middlebury data not found: give root= or set MDR_MIDDLEBURY")
        folder = os.path.join(root, key)
    lf, rf, gf, scale = MIDDLEBURY[key]
    flag = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR
    left = cv2.imread(os.path.join(folder, lf), flag)
    right = cv2.imread(os.path.join(folder, rf), flag)
    if left is None or right is None:
        raise FileNotFoundError("cannot read %s / %s in %s" % (lf, rf, folder))
    gt = read_disparity(os.path.join(folder, gf), scale)
    return left, right, gt
