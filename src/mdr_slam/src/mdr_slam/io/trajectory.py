"""Trajectories: stamped poses, and the TUM, KITTI and EuRoC (ASL CSV) file formats.

Metrics on trajectories live in mdr_slam.eval (built on evo); this module only reads and writes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation

from .atomic import atomic_path


@dataclass
class Trajectory:
    """N stamped poses: ``stamps`` (N,) seconds, ``positions`` (N, 3), ``quats`` (N, 4) xyzw."""

    stamps: np.ndarray
    positions: np.ndarray
    quats: np.ndarray

    def __post_init__(self):
        self.stamps = np.asarray(self.stamps, dtype=float).reshape(-1)
        self.positions = np.asarray(self.positions, dtype=float).reshape(-1, 3)
        self.quats = np.asarray(self.quats, dtype=float).reshape(-1, 4)
        if not (len(self.stamps) == len(self.positions) == len(self.quats)):
            raise ValueError("trajectory arrays differ in length")

    def __len__(self):
        return len(self.stamps)

    @classmethod
    def from_matrices(cls, stamps, Ts) -> "Trajectory":
        Ts = np.asarray(Ts, dtype=float).reshape(-1, 4, 4)
        q = Rotation.from_matrix(Ts[:, :3, :3]).as_quat() if len(Ts) else np.zeros((0, 4))
        q[q[:, 3] < 0] *= -1
        return cls(np.asarray(stamps, dtype=float), Ts[:, :3, 3], q)

    def matrices(self) -> np.ndarray:
        """(N, 4, 4) poses."""
        Ts = np.tile(np.eye(4), (len(self), 1, 1))
        if len(self):
            Ts[:, :3, :3] = Rotation.from_quat(self.quats).as_matrix()
            Ts[:, :3, 3] = self.positions
        return Ts

    def path_length(self) -> float:
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum()) if len(self) > 1 else 0.0


def write_tum(path: str, traj: Trajectory) -> int:
    """TUM RGB-D format: ``stamp tx ty tz qx qy qz qw`` per line."""
    data = np.column_stack([traj.stamps, traj.positions, traj.quats])
    with atomic_path(path, ".txt") as tmp:
        np.savetxt(tmp, data, fmt=["%.9f"] + ["%.9g"] * 7)
    return len(traj)


def read_tum(path: str) -> Trajectory:
    data = np.loadtxt(path, comments="#", ndmin=2)
    if data.shape[1] != 8:
        raise ValueError("%s: a TUM trajectory has 8 columns, found %d" % (path, data.shape[1]))
    return Trajectory(data[:, 0], data[:, 1:4], data[:, 4:8])


def read_kitti_poses(path: str, stamps: Optional[np.ndarray] = None) -> Trajectory:
    """KITTI odometry poses: 12 values (3x4 row-major) per line, optionally after a frame index.

    Without ``stamps`` the frame index (or line number) is used as the time.
    """
    data = np.loadtxt(path, ndmin=2)
    if data.shape[1] == 13:
        idx, data = data[:, 0], data[:, 1:]
    elif data.shape[1] == 12:
        idx = np.arange(len(data), dtype=float)
    else:
        raise ValueError("%s: KITTI poses have 12 values per line, found %d" % (path, data.shape[1]))
    Ts = np.tile(np.eye(4), (len(data), 1, 1))
    Ts[:, :3, :4] = data.reshape(-1, 3, 4)
    return Trajectory.from_matrices(idx if stamps is None else stamps, Ts)


def write_kitti_poses(path: str, traj: Trajectory) -> int:
    Ts = traj.matrices()
    with atomic_path(path, ".txt") as tmp:
        np.savetxt(tmp, Ts[:, :3, :4].reshape(-1, 12), fmt="%.9e")
    return len(traj)


def read_euroc_csv(path: str) -> Trajectory:
    """ASL/EuRoC CSV: ``t[ns], x, y, z, qw, qx, qy, qz[, ...]`` with a ``#`` header."""
    data = np.loadtxt(path, delimiter=",", comments="#", ndmin=2)
    q_wxyz = data[:, 4:8]
    return Trajectory(data[:, 0] * 1e-9, data[:, 1:4], q_wxyz[:, [1, 2, 3, 0]])


def read_trajectory(path: str, fmt: Optional[str] = None) -> Trajectory:
    """Read TUM, KITTI or EuRoC by ``fmt`` or by guessing from the file's content."""
    if fmt is None:
        with open(path) as f:
            first = ""
            for line in f:
                if line.strip() and not line.startswith("#"):
                    first = line
                    break
        if "," in first:
            fmt = "euroc"
        else:
            n = len(first.split())
            fmt = "tum" if n == 8 else "kitti" if n in (12, 13) else None
        if fmt is None:
            raise ValueError("%s: cannot tell the trajectory format" % path)
    return {"tum": read_tum, "kitti": read_kitti_poses, "euroc": read_euroc_csv}[fmt](path)
