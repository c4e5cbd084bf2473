"""Trajectory metrics: ATE (absolute trajectory error) and RPE, built on evo.

The paper reports ATE RMSE in metres after aligning the estimate to the ground truth (Umeyama,
SE(3) for stereo since scale is observable, Sim(3) for comparison with monocular results).
evo does the association, the alignment and the statistics, so our figures are the figures
everyone else computes (the tests reproduce evo's and kitti-odom-eval's published numbers).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Dict, Optional

import numpy as np

from ..io.trajectory import Trajectory, read_kitti_poses, read_trajectory

__all__ = ["ALIGNMENTS", "TrajectoryErrors", "to_evo", "from_evo", "associate", "align",
           "alignment_matrix", "transform_trajectory",
           "ate", "rpe", "read_for_eval", "summary_json"]

ALIGNMENTS = ("se3", "sim3", "scale", "none")


@dataclass
class TrajectoryErrors:
    """Per-pose errors and their summary (``stats`` is what ``mdr eval`` prints as JSON)."""

    stats: Dict[str, object]
    errors: np.ndarray                 # (N,) metres
    stamps: np.ndarray                 # (N,) seconds (or frame indices for KITTI files)
    est_xyz: np.ndarray                # (N, 3) aligned estimate
    gt_xyz: np.ndarray                 # (N, 3) ground truth
    alignment: Dict[str, object] = field(default_factory=dict)


def to_evo(traj: Trajectory):
    """mdr Trajectory -> evo PoseTrajectory3D (evo wants quaternions w, x, y, z)."""
    # evo is optional: mdr_slam.eval (map and depth metrics) imports without it
    from evo.core.trajectory import PoseTrajectory3D
    return PoseTrajectory3D(positions_xyz=np.asarray(traj.positions, dtype=float),
                            orientations_quat_wxyz=np.asarray(traj.quats, dtype=float)[:, [3, 0, 1, 2]],
                            timestamps=np.asarray(traj.stamps, dtype=float))


def from_evo(traj) -> Trajectory:
    return Trajectory(traj.timestamps, traj.positions_xyz, traj.orientations_quat_wxyz[:, [1, 2, 3, 0]])


def associate(est: Trajectory, gt: Trajectory, max_diff: float = 0.01, offset: float = 0.0):
    """(gt, est) evo trajectories restricted to pose pairs whose stamps differ by <= ``max_diff``.

    KITTI files without stamps carry the frame index as the stamp (``read_kitti_poses``), so the
    same call associates them by index (an exact match).
    """
    from evo.core import sync
    if len(est) == 0 or len(gt) == 0:
        raise ValueError("empty trajectory (estimate %d poses, ground truth %d)" % (len(est), len(gt)))
    try:
        g, e = sync.associate_trajectories(to_evo(gt), to_evo(est), max_diff=max_diff,
                                           offset_2=offset, first_name="ground truth",
                                           snd_name="estimate")
    except sync.SyncException as err:   # evo's own exception: callers handle ValueError
        raise ValueError("association failed (max_diff %g s): %s" % (max_diff, err))
    if e.num_poses < 2:
        raise ValueError("only %d estimated poses matched the ground truth within %g s"
                         % (e.num_poses, max_diff))
    return g, e


def align(gt_evo, est_evo, mode: str = "se3", n: int = -1) -> Dict[str, object]:
    """Align ``est_evo`` in place onto ``gt_evo`` (Umeyama); returns the transform found.

    ``se3``: rotation + translation (stereo: metric scale is observed); ``sim3``: also scale
    (monocular, or kitti-odom-eval's "7dof"); ``scale``: scale only; ``none``: as estimated.
    ``n`` > 0 aligns on the first n poses only (evo's ``--n_to_align``).
    """
    if mode not in ALIGNMENTS:
        raise ValueError("alignment must be one of %s, got %r" % (", ".join(ALIGNMENTS), mode))
    if mode == "none":
        return {"type": "none"}
    R, t, s = est_evo.align(gt_evo, correct_scale=(mode == "sim3"), correct_only_scale=(mode == "scale"),
                            n=n)
    return {"type": mode, "rotation": np.asarray(R).tolist(), "translation": np.asarray(t).tolist(),
            "scale": float(s)}


def alignment_matrix(al: Dict[str, object]) -> np.ndarray:
    """The 4x4 transform of an alignment as :func:`align` returns it (rotation, translation; a
    scale other than 1 multiplies the rotation part)."""
    T = np.eye(4)
    if al.get("type", "none") != "none":
        T[:3, :3] = float(al.get("scale", 1.0)) * np.asarray(al["rotation"], float)
        T[:3, 3] = np.asarray(al["translation"], float)
    return T


def transform_trajectory(traj: Trajectory, T: np.ndarray) -> Trajectory:
    """``traj`` moved by the rigid transform ``T`` (each pose P becomes T P)."""
    return Trajectory.from_matrices(traj.stamps, [T @ P for P in traj.matrices()])


def _stats(errors: np.ndarray) -> Dict[str, float]:
    e = np.asarray(errors, dtype=float)
    return {"rmse": float(np.sqrt(np.mean(e ** 2))), "mean": float(np.mean(e)),
            "median": float(np.median(e)), "std": float(np.std(e)), "min": float(np.min(e)),
            "max": float(np.max(e)), "sse": float(np.sum(e ** 2))}


def ate(est: Trajectory, gt: Trajectory, align_mode: str = "se3", max_diff: float = 0.01,
        offset: float = 0.0, n_to_align: int = -1) -> TrajectoryErrors:
    """Absolute trajectory error (translation part of evo's APE) after Umeyama alignment.

    Returns per-pose errors and the summary: rmse, mean, median, std, min, max, n,
    path_length (of the associated ground truth), alignment.
    """
    from evo.core import metrics
    g, e = associate(est, gt, max_diff, offset)
    al = align(g, e, align_mode, n_to_align)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((g, e))
    stats = _stats(ape.error)
    # evo's own statistics, so the figures are evo's to the last digit
    stats.update({k: float(v) for k, v in ape.get_all_statistics().items()})
    stats.update({"n": int(e.num_poses), "n_estimate": len(est), "n_ground_truth": len(gt),
                  "path_length": float(g.path_length), "alignment": al["type"]})
    if "scale" in al:
        stats["scale"] = al["scale"]
    return TrajectoryErrors(stats, np.asarray(ape.error), np.asarray(e.timestamps),
                            np.asarray(e.positions_xyz), np.asarray(g.positions_xyz), al)


def rpe(est: Trajectory, gt: Trajectory, delta: float = 10.0, unit: str = "m",
        align_mode: str = "none", max_diff: float = 0.01, offset: float = 0.0,
        all_pairs: bool = False, rotation: bool = False) -> TrajectoryErrors:
    """Relative pose error over ``delta`` (metres ``m`` along the ground truth, or ``frames``).

    Translation part by default (metres); ``rotation=True`` gives the rotation angle (degrees).
    """
    from evo.core import metrics
    from evo.core.units import Unit
    units = {"m": Unit.meters, "meters": Unit.meters, "frames": Unit.frames, "f": Unit.frames}
    if unit not in units:
        raise ValueError("RPE delta unit must be m or frames, got %r" % unit)
    g, e = associate(est, gt, max_diff, offset)
    al = align(g, e, align_mode)
    rel = metrics.PoseRelation.rotation_angle_deg if rotation else metrics.PoseRelation.translation_part
    m = metrics.RPE(rel, delta=delta, delta_unit=units[unit], all_pairs=all_pairs)
    m.process_data((g, e))
    stats = {k: float(v) for k, v in m.get_all_statistics().items()}
    stats.update({"n": int(len(m.error)), "delta": delta, "delta_unit": unit,
                  "path_length": float(g.path_length), "alignment": al["type"],
                  "relation": "rotation_deg" if rotation else "translation_m"})
    idx = np.asarray(getattr(m, "delta_ids", np.arange(len(m.error))), dtype=int)
    idx = idx[idx < e.num_poses] if len(idx) == len(m.error) else np.arange(len(m.error))
    return TrajectoryErrors(stats, np.asarray(m.error), np.asarray(e.timestamps)[idx],
                            np.asarray(e.positions_xyz)[idx], np.asarray(g.positions_xyz)[idx], al)


def read_for_eval(path: str, fmt: Optional[str] = None, times: Optional[str] = None) -> Trajectory:
    """Read a trajectory for evaluation; ``times`` gives stamps (one per line) to a KITTI file."""
    if times:
        stamps = np.loadtxt(times, ndmin=1).reshape(-1)
        tr = read_kitti_poses(path)
        if len(stamps) < len(tr):
            raise ValueError("%s has %d stamps for %d poses" % (times, len(stamps), len(tr)))
        idx = tr.stamps.astype(int)  # frame index (13-column files) or line number
        return Trajectory(stamps[idx], tr.positions, tr.quats)
    return read_trajectory(path, fmt)


def summary_json(stats: Dict[str, object]) -> str:
    return json.dumps(stats, indent=2, sort_keys=True)



def map_alignment(est: Trajectory, gt: Trajectory, max_diff: float = 0.01,
                  min_spread: float = 0.2) -> Dict[str, object]:
    """The rigid transform that moves a map built in ``est``'s frame into ``gt``'s, for scoring a
    map made with estimated poses against a ground-truth map.

    Umeyama SE(3) over all associated positions (as ``ate`` aligns) when they span at least
    ``min_spread`` metres in two directions; otherwise positions alone leave the rotation
    undetermined (a short or straight path), and the first associated pose pair fixes it:
    ``T = T_gt0 inv(T_est0)`` (evo's align_origin).
    """
    g, e = associate(est, gt, max_diff=max_diff)
    xyz = np.asarray(g.positions_xyz)
    sv = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False) / np.sqrt(max(len(xyz), 1))
    if len(xyz) >= 3 and sv[1] >= min_spread:
        out = align(g, e, "se3")
        out["method"] = "umeyama_se3"
        return out
    T = np.asarray(g.poses_se3[0]) @ np.linalg.inv(np.asarray(e.poses_se3[0]))
    return {"type": "se3", "method": "first_pose", "rotation": T[:3, :3].tolist(),
            "translation": T[:3, 3].tolist(), "scale": 1.0}
