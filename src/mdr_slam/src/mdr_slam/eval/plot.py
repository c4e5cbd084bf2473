"""Figures (matplotlib, Agg backend: works headless and in CI).

``plot_ate`` is the paper's Fig. 6 layout: the estimated trajectory against the ground truth in
a plane (top) and the translation APE over time (bottom). ``plot_map_errors`` shows the
accuracy distance histogram and the accuracy/completeness curves over the threshold.
"""
from __future__ import annotations

import os
from typing import Optional, Sequence

import numpy as np

from ..io.atomic import atomic_path
from .trajectory import TrajectoryErrors

__all__ = ["plot_ate", "plot_map_errors"]

_AXES = {"x": 0, "y": 1, "z": 2}


def _pyplot():
    # matplotlib: 0.3 s to import and it must get the Agg backend first; only the plots need it
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _plane(gt_xyz: np.ndarray, plane: str) -> str:
    if plane != "auto":
        return plane
    spread = np.ptp(gt_xyz, axis=0)
    a, b = sorted(np.argsort(spread)[-2:])
    return "xyz"[a] + "xyz"[b]


def plot_ate(res: TrajectoryErrors, out: str, plane: str = "xy", title: Optional[str] = None) -> str:
    """Save the trajectory-vs-ground-truth plane plot and APE(t) to ``out`` (PNG/PDF/SVG)."""
    plt = _pyplot()
    plane = _plane(res.gt_xyz, plane)
    i, j = _AXES[plane[0]], _AXES[plane[1]]
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7, 8), gridspec_kw={"height_ratios": [3, 1.4]})
    ax1.plot(res.gt_xyz[:, i], res.gt_xyz[:, j], "k--", lw=1.2, label="ground truth")
    ax1.plot(res.est_xyz[:, i], res.est_xyz[:, j], "b-", lw=1.2,
             label="estimate (%s aligned)" % res.stats.get("alignment", "none"))
    ax1.plot(res.gt_xyz[0, i], res.gt_xyz[0, j], "go", ms=5, label="start")
    ax1.set_xlabel("%s [m]" % plane[0])
    ax1.set_ylabel("%s [m]" % plane[1])
    ax1.set_aspect("equal", adjustable="datalim")
    ax1.legend(loc="best", fontsize=8)
    ax1.grid(alpha=0.3)
    ax1.set_title(title or "ATE RMSE %.4f m (n=%d)" % (res.stats["rmse"], res.stats["n"]))
    t = res.stamps - res.stamps[0]
    ax2.plot(t, res.errors, "r-", lw=1)
    ax2.axhline(res.stats["rmse"], color="k", ls="--", lw=0.8, label="rmse")
    ax2.axhline(res.stats["median"], color="gray", ls=":", lw=0.8, label="median")
    frames = bool(np.all(np.mod(res.stamps, 1.0) == 0))   # KITTI files without stamps
    ax2.set_xlabel("frame" if frames else "time [s]")
    ax2.set_ylabel("APE translation [m]")
    ax2.legend(loc="upper left", fontsize=8)
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    ext = os.path.splitext(out)[1] or ".png"
    with atomic_path(out, ext) as tmp:
        fig.savefig(tmp, dpi=120, format=ext.lstrip("."))
    plt.close(fig)
    return out


def plot_map_errors(d_acc: np.ndarray, d_comp: np.ndarray, out: str,
                    thresholds: Sequence[float] = (0.01, 0.02, 0.05, 0.10)) -> str:
    """Histogram of estimated-to-ground-truth distances and accuracy/completeness vs threshold."""
    plt = _pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    hi = max(float(np.percentile(d_acc, 99)), max(thresholds)) if len(d_acc) else max(thresholds)
    ax1.hist(np.clip(d_acc, 0, hi), bins=60, color="tab:blue")
    ax1.set_xlabel("distance to nearest ground-truth point [m]")
    ax1.set_ylabel("estimated points")
    ax1.set_title("accuracy RMSE %.4f m" % float(np.sqrt(np.mean(d_acc ** 2))))
    ts = np.linspace(0, hi, 100)
    # cumulative shares from sorted distances (one searchsorted, not a pass per threshold)
    for d, label in ((d_acc, "accuracy (precision)"), (d_comp, "completeness (recall)")):
        ax2.plot(ts, np.searchsorted(np.sort(d), ts, side="right") / max(len(d), 1), label=label)
    for t in thresholds:
        ax2.axvline(t, color="gray", lw=0.5, ls=":")
    ax2.set_xlabel("threshold [m]")
    ax2.set_ylim(0, 1.02)
    ax2.legend(loc="lower right")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    ext = os.path.splitext(out)[1] or ".png"
    with atomic_path(out, ext) as tmp:
        fig.savefig(tmp, dpi=110, format=ext.lstrip("."))
    plt.close(fig)
    return out
