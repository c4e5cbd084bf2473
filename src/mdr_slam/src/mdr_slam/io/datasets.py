"""Public stereo datasets on disk (no ROS): EuRoC (ASL layout) and KITTI odometry.

A :class:`StereoDataset` is what the offline runner and ``mdr import`` consume: iterating it
yields ``(stamp, left, right)`` (seconds, grey uint8 images as stored: raw for EuRoC, rectified
for KITTI); ``camera`` is the :class:`~mdr_slam.camera.StereoCamera` (for EuRoC with the
rectification R, P from ``cv2.stereoRectify``); ``ground_truth`` is the left-camera trajectory
``T_map_cam`` (a :class:`~mdr_slam.io.trajectory.Trajectory`) or None. Images are read lazily,
one pair at a time, so a long sequence never sits in memory.
"""
from __future__ import annotations

import csv
import glob
import os
from dataclasses import dataclass, field
from typing import Callable, Iterator, List, Optional, Tuple

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..calib import euroc_T_BS, load_euroc_calibration, load_kitti_calibration
from ..camera import StereoCamera
from .trajectory import Trajectory, read_euroc_csv, read_kitti_poses

__all__ = ["StereoDataset", "load_euroc", "load_kitti", "iter_euroc", "iter_kitti",
           "euroc_body_to_camera", "interpolate_poses", "DatasetError"]


class DatasetError(ValueError):
    """A dataset folder that cannot be read (missing files, nothing to pair)."""


@dataclass
class StereoDataset:
    """A stereo sequence on disk: frames (stamp, left path, right path), camera, ground truth."""

    name: str
    camera: StereoCamera
    frames: List[Tuple[float, str, str]]
    ground_truth: Optional[Trajectory] = None
    skipped: List[str] = field(default_factory=list)   # why some listed images were left out

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[Tuple[float, np.ndarray, np.ndarray]]:
        for stamp, lpath, rpath in self.frames:
            yield (stamp,) + self.read_pair(lpath, rpath)

    @staticmethod
    def read_pair(lpath: str, rpath: str) -> Tuple[np.ndarray, np.ndarray]:
        out = []
        for p in (lpath, rpath):
            img = cv2.imread(p, cv2.IMREAD_UNCHANGED)
            if img is None:
                raise DatasetError("cannot read image %s" % p)
            if img.ndim == 3:  # the pipeline is grey (ORB and ELAS work on intensity)
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
            out.append(img)
        return out[0], out[1]

    def ground_truth_at(self, max_gap: float = 0.2) -> List[Tuple[float, np.ndarray]]:
        """(stamp, T_map_cam) for every frame the ground truth covers.

        Ground truth (200 Hz for EuRoC) rarely shares the camera stamps: positions are linearly
        interpolated and rotations SLERPed between the two neighbouring samples, as
        bagio.PoseTimeline does, but vectorized and without ROS; frames outside the covered time
        or across a gap longer than ``max_gap`` seconds get none.
        """
        if self.ground_truth is None or len(self.ground_truth) == 0:
            return []
        stamps = np.array([f[0] for f in self.frames])
        Ts, ok = interpolate_poses(self.ground_truth, stamps, max_gap)
        return [(float(t), T) for t, T, k in zip(stamps, Ts, ok) if k]


def interpolate_poses(traj: Trajectory, stamps: np.ndarray, max_gap: float = 0.2):
    """(N, 4, 4) poses of ``traj`` at ``stamps`` and an (N,) validity mask (vectorized SLERP)."""
    order = np.argsort(traj.stamps)
    s = traj.stamps[order]
    p = traj.positions[order]
    q = traj.quats[order]
    t = np.asarray(stamps, dtype=float)
    eps = 1e-6
    i = np.clip(np.searchsorted(s, t - eps), 1, max(len(s) - 1, 1))
    i0 = i - 1
    if len(s) == 1:
        i = i0 = np.zeros(len(t), dtype=int)
    dt = s[i] - s[i0]
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(dt > 0, (t - s[i0]) / dt, 0.0)
    w = np.clip(w, 0.0, 1.0)
    ok = (t >= s[0] - eps) & (t <= s[-1] + eps) & ((dt <= max_gap) | (np.abs(t - s[i0]) < eps)
                                                    | (np.abs(t - s[i]) < eps))
    r0 = Rotation.from_quat(q[i0])
    rel = (r0.inv() * Rotation.from_quat(q[i])).as_rotvec()
    R = (r0 * Rotation.from_rotvec(rel * w[:, None])).as_matrix()
    Ts = np.tile(np.eye(4), (len(t), 1, 1))
    Ts[:, :3, :3] = R
    Ts[:, :3, 3] = (1 - w)[:, None] * p[i0] + w[:, None] * p[i]
    return Ts, ok


# ------------------------------------------------------------------------------------ EuRoC
def _euroc_root(path: str) -> str:
    for base in (os.path.join(path, "mav0"), path):
        if os.path.isdir(os.path.join(base, "cam0")):
            return base
    raise DatasetError("%s: not an EuRoC (ASL) folder: no mav0/cam0" % path)


def _euroc_list(cam_dir: str) -> List[Tuple[int, str]]:
    """(stamp ns, filename) rows of an ASL ``data.csv``."""
    csv_path = os.path.join(cam_dir, "data.csv")
    if not os.path.isfile(csv_path):
        raise DatasetError("%s is missing" % csv_path)
    rows = []
    with open(csv_path) as f:
        for row in csv.reader(f):
            if not row or row[0].lstrip().startswith("#"):
                continue
            rows.append((int(row[0].strip()), row[1].strip() if len(row) > 1 else row[0].strip() + ".png"))
    return rows


def euroc_body_to_camera(body: Trajectory, T_BS: np.ndarray) -> Trajectory:
    """World-from-camera poses from world-from-body ones: T_W_C = T_W_B T_B_S (EuRoC's T_BS)."""
    Ts = body.matrices() @ T_BS
    return Trajectory.from_matrices(body.stamps, Ts)


def load_euroc(path: str, ground_truth: Optional[str] = None,
               on_skip: Optional[Callable[[str], None]] = None) -> StereoDataset:
    """EuRoC / ASL sequence folder (``DIR/mav0/cam0/data.csv``, ``data/*.png``, ``sensor.yaml``).

    Left and right images are paired by exact timestamp; listed stamps without an image file or
    without a partner are skipped and reported through ``on_skip``. Ground truth: ``ground_truth``
    (a left-camera CSV ``t[ns],x,y,z,qw,qx,qy,qz`` such as ORB-SLAM3's ``*_GT.txt``) when given,
    else ``state_groundtruth_estimate0/data.csv`` (the body/IMU pose) moved to the left camera
    with cam0's ``T_BS``, else None.
    """
    root = _euroc_root(path)
    skip = on_skip or (lambda msg: None)
    camera = load_euroc_calibration(os.path.join(root, "cam0", "sensor.yaml"),
                                    os.path.join(root, "cam1", "sensor.yaml"))
    skipped: List[str] = []

    def note(msg):
        skipped.append(msg)
        skip(msg)

    sides = []
    for cam in ("cam0", "cam1"):
        d = os.path.join(root, cam)
        existing = set(os.listdir(os.path.join(d, "data"))) if os.path.isdir(os.path.join(d, "data")) else set()
        listed = _euroc_list(d)
        present = {}
        missing = [ns for ns, name in listed if name not in existing]
        for ns, name in listed:
            if name in existing:
                present[ns] = os.path.join(d, "data", name)
        if missing:
            note("%s: %d listed stamps have no image (e.g. %d): skipped" % (cam, len(missing), missing[0]))
        sides.append(present)
    left, right = sides
    common = sorted(set(left) & set(right))
    only = len(set(left) ^ set(right))
    if only:
        note("%d images have no partner with the same stamp: skipped" % only)
    if not common:
        raise DatasetError("%s: no left/right image pairs with equal stamps" % path)
    frames = [(ns * 1e-9, left[ns], right[ns]) for ns in common]

    gt = None
    if ground_truth:
        gt = read_euroc_csv(ground_truth)
    else:
        body_csv = os.path.join(root, "state_groundtruth_estimate0", "data.csv")
        if os.path.isfile(body_csv):
            gt = euroc_body_to_camera(read_euroc_csv(body_csv),
                                      euroc_T_BS(os.path.join(root, "cam0", "sensor.yaml")))
    return StereoDataset(os.path.basename(os.path.abspath(path)), camera, frames, gt, skipped)


# ------------------------------------------------------------------------------------ KITTI
def load_kitti(path: str, poses: Optional[str] = None, rate_hz: float = 10.0,
               on_skip: Optional[Callable[[str], None]] = None,
               doffs: Optional[float] = None) -> StereoDataset:
    """KITTI odometry sequence: ``image_0``/``image_1`` (or ``image_l``/``image_r``), ``calib.txt``,
    ``times.txt`` (else ``rate_hz``) and ``poses.txt`` (cam0-to-world 3x4 rows) when present.

    ``poses`` may point at the ground truth elsewhere (``dataset/poses/06.txt``). ``doffs``
    corrects calib.txt's principal point difference (:func:`mdr_slam.calib.load_kitti_calibration`).
    """
    skip = on_skip or (lambda msg: None)
    for ln, rn in (("image_0", "image_1"), ("image_l", "image_r")):
        if os.path.isdir(os.path.join(path, ln)):
            break
    else:
        raise DatasetError("%s: not a KITTI odometry folder: no image_0/ or image_l/" % path)
    lfiles = sorted(glob.glob(os.path.join(path, ln, "*.png")))
    rdir = os.path.join(path, rn)
    skipped: List[str] = []
    pairs = []
    for i, lf in enumerate(lfiles):
        rf = os.path.join(rdir, os.path.basename(lf))
        if os.path.isfile(rf):
            pairs.append((i, lf, rf))
        else:
            skipped.append("%s has no right image: skipped" % os.path.basename(lf))
            skip(skipped[-1])
    if not pairs:
        raise DatasetError("%s: no stereo pairs in %s/ and %s/" % (path, ln, rn))
    first = cv2.imread(pairs[0][1], cv2.IMREAD_UNCHANGED)
    if first is None:
        raise DatasetError("cannot read image %s" % pairs[0][1])
    camera = load_kitti_calibration(os.path.join(path, "calib.txt"), (first.shape[1], first.shape[0]),
                                    doffs=doffs)

    times_path = os.path.join(path, "times.txt")
    n_files = len(lfiles)
    if os.path.isfile(times_path):
        times = np.loadtxt(times_path, ndmin=1).reshape(-1)
        if len(times) < n_files:
            raise DatasetError("%s has %d stamps for %d images" % (times_path, len(times), n_files))
    else:
        times = np.arange(n_files) / float(rate_hz)
    # Frame index = the file's number (000123.png), so clips that start late keep their stamps.
    idx = [_frame_number(lf, i) for i, lf, _ in pairs]
    if max(idx) >= len(times):
        idx = [i for i, _, _ in pairs]
    frames = [(float(times[k]), lf, rf) for k, (_, lf, rf) in zip(idx, pairs)]

    gt = None
    poses = poses or (os.path.join(path, "poses.txt") if os.path.isfile(os.path.join(path, "poses.txt")) else None)
    if poses:
        g = read_kitti_poses(poses)
        n = min(len(g), len(times))
        gt = Trajectory(times[:n], g.positions[:n], g.quats[:n])
    return StereoDataset(os.path.basename(os.path.abspath(path)), camera, frames, gt, skipped)


def _frame_number(path: str, default: int) -> int:
    stem = os.path.splitext(os.path.basename(path))[0]
    return int(stem) if stem.isdigit() else default


# The offline runner iterates these directly: ``for stamp, left, right in iter_kitti(d)``; the
# returned dataset also carries ``.camera`` and ``.ground_truth``.
iter_euroc = load_euroc
iter_kitti = load_kitti
