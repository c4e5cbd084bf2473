"""Write a simulated sequence: bag + exact ground truth (trajectory, depth, surface map).

Rendering runs in a fork-based multiprocessing pool (frames are independent and each frame's noise
is seeded by its index, so the output does not depend on the number of workers); the parent
writes the bag in frame order and accumulates the ground-truth map.

Outputs in ``out_dir``: ``sequence.bag`` (mono8 stereo + camera_info, /ground_truth/pose, /tf),
``groundtruth.tum``, ``gt_map.ply`` (1 cm cells of every surface the left camera saw within
``max_range``: x y z nx ny nz surface), optional ``gt_depth/%06d.npz`` (depth, surface) and
``scene.yaml`` (camera, scene, seed, segments, laps, label legend, timing). A ``frame_writer`` hook
replaces the bag's content (:mod:`.driver` writes it the way a camera driver records).

Every pose (bag ``/ground_truth/pose`` and ``/tf`` map -> ground_truth_camera, TUM file) is the
RECTIFIED left optical frame in ``map``; with ``distort=True`` the raw left camera is rotated
from it by camera_info R (X_rect = R X_raw), exactly what rectification undoes.
"""
from __future__ import annotations

import ctypes
import multiprocessing
import os
import time
from typing import Callable, Dict, Optional

import cv2
import numpy as np
import yaml

from ..io import Trajectory, points_cloud, write_cloud, write_tum
from ..io.atomic import atomic_write
from .render import Simulator, sim_camera
from .scene import LABELS, Scene, make_scene
from .trajectory import build_trajectory

__all__ = ["generate", "STAMP0"]

STAMP0 = 1.0   # first stamp (s): ROS stamp 0 means "unset"

_STATE: Dict[str, object] = {}   # per-process render state (inherited by forked workers)


class _MapCells:
    """1 cm (``cell``) grid over every rectangle; a flat index per cell for the whole scene."""

    def __init__(self, scene: Scene, cell: float):
        self.cell = float(cell)
        self.na = np.maximum(np.ceil(scene.A / cell), 1).astype(np.int64)
        self.nb = np.maximum(np.ceil(scene.B / cell), 1).astype(np.int64)
        sizes = self.na * self.nb
        self.base = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.total = int(sizes.sum())

    def keys(self, pid, s, r, valid) -> np.ndarray:
        p = pid[valid]
        inv = np.float32(1.0 / self.cell)
        i = np.minimum((s[valid] * inv).astype(np.int64), self.na[p] - 1)
        j = np.minimum((r[valid] * inv).astype(np.int64), self.nb[p] - 1)
        return self.base[p] + np.maximum(i, 0) * self.nb[p] + np.maximum(j, 0)

    def cloud(self, scene: Scene, mark: np.ndarray, close: int):
        """Cell centres of the marked cells, after a morphological closing that fills the
        one-pixel gaps far surfaces leave between pixel footprints (kernel ``close``)."""
        pts, nrm, lab = [], [], []
        kern = np.ones((close, close), np.uint8) if close > 1 else None
        for k, rc in enumerate(scene.rects):
            grid = mark[self.base[k]:self.base[k] + self.na[k] * self.nb[k]].reshape(
                int(self.na[k]), int(self.nb[k]))
            if not grid.any():
                continue
            if kern is not None:
                grid = cv2.morphologyEx(grid.astype(np.uint8), cv2.MORPH_CLOSE, kern) > 0
            i, j = np.nonzero(grid)
            s = np.minimum((i + 0.5) * self.cell, rc.a)
            r = np.minimum((j + 0.5) * self.cell, rc.b)
            pts.append(rc.to_world(s, r))
            nrm.append(np.broadcast_to(rc.normal, (len(i), 3)))
            lab.append(np.full(len(i), rc.label, np.uint8))
        if not pts:
            P = np.zeros((0, 3))
            Nn = np.zeros((0, 3))
            L = np.zeros(0, np.uint8)
        else:
            P, Nn, L = np.concatenate(pts), np.concatenate(nrm), np.concatenate(lab)
        return points_cloud(P.astype(np.float32), nx=Nn[:, 0].astype(np.float32),
                            ny=Nn[:, 1].astype(np.float32), nz=Nn[:, 2].astype(np.float32),
                            surface=L)


class _GroundTruthBagWriter:
    """The default bag: mono8 stereo + camera_info on the default topics, /ground_truth/pose and
    /tf map -> ground_truth_camera at every frame stamp."""

    def __init__(self, bag_path, camera, stamps, Ts, traj):
        # bagio needs rosbag: mdr_slam.sim imports without ROS, only writing a bag needs it
        from ..bagio import StereoBagWriter
        self.bag = StereoBagWriter(bag_path)
        self.camera, self.stamps, self.Ts = camera, stamps, Ts

    def write(self, i: int, left: np.ndarray, right: np.ndarray) -> None:
        self.bag.write_stereo(float(self.stamps[i]), left, right, self.camera)
        self.bag.write_ground_truth(float(self.stamps[i]), self.Ts[i])

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.bag.close()


def _exposure_gains(n: int, rate: float, seed: int, enabled: bool) -> np.ndarray:
    """Per-frame exposure gain: smooth auto-exposure drift (+-20%), deterministic per seed."""
    if not enabled:
        return np.ones(n)
    rng = np.random.default_rng([int(seed), 4242])
    t = np.arange(n) / float(rate)
    ph = rng.uniform(0, 2 * np.pi, 2)
    return np.exp(0.15 * np.sin(2 * np.pi * t / 6.5 + ph[0])
                  + 0.06 * np.sin(2 * np.pi * t / 2.3 + ph[1]))


def _worker_init():
    """Keep freed numpy temporaries in the heap (glibc would otherwise mmap/munmap every
    1-2 MB image-sized array: ~15% of render time went to page faults)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 256 << 20)   # M_MMAP_THRESHOLD
        libc.mallopt(-1, 512 << 20)   # M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        pass


def _render_frame(i: int):
    st = _STATE
    sim: Simulator = st["sim"]
    t0 = time.perf_counter()
    sub = None
    if st["blur"] > 1:
        sub = st["traj"].poses(st["rel"][i] + st["blur_offsets"])
    want_depth = st["depth_every"] > 0 and i % st["depth_every"] == 0
    f = sim.render(st["Ts"][i], raw=st["raw"], index=i, gain=float(st["gains"][i]),
                   sub_poses=sub, depth=want_depth, hits=True)
    cells: _MapCells = st["cells"]
    valid = (f["pid"] >= 0) & (f["z"] <= st["max_range"])
    mark = st["mark"]
    mark[cells.keys(f["pid"], f["s"], f["r"], valid)] = True
    idx = np.flatnonzero(mark)
    mark[idx] = False
    if want_depth:
        np.savez_compressed(os.path.join(st["depth_dir"], "%06d.npz" % i), depth=f["depth"],
                            surface=f["surface"])
    ms = (time.perf_counter() - t0) * 1e3
    return i, f["left"], f["right"], idx.astype(np.int64), ms


def generate(out_dir: str, scene="office", duration: Optional[float] = None, seed: int = 0,
             rate: float = 20.0, distort: bool = False, contrast: float = 4.0,
             specular: bool = True, noise: float = 2.0, save_depth: int = 0,
             max_range: float = 8.0, camera=None, scale: float = 1.0, trajectory=None,
             exposure: bool = False, blur: int = 0, blur_time: float = 0.01,
             workers: Optional[int] = None, map_cell: Optional[float] = None,
             progress: Optional[Callable[[int, int], None]] = None,
             frame_writer: Optional[Callable] = None, laps: int = 1) -> dict:
    """Render a sequence to ``out_dir``; returns a summary dict (paths, counts, timing).

    ``scene`` is a name or a :class:`Scene`; ``trajectory`` a kind (default: the scene's);
    ``save_depth`` = N writes gt_depth for every N-th frame (0: none); ``blur`` = K averages K
    sub-poses over ``blur_time`` s centred on each stamp; ``exposure`` varies the gain;
    ``camera`` overrides the EuRoC-like default (``scale`` shrinks it, ``distort`` = raw images).
    ``map_cell`` is the gt_map spacing (default: the scene's, 1 cm; the floor's 2 cm, since
    its route sees ~1200 m2 of surface: ~2.9M points at 2 cm, ~12M at 1 cm).
    ``duration`` is one lap's (default: 30 s, the floor's route: its whole length at its speed);
    ``laps`` = N patrols a loop trajectory N times (N x duration seconds): the summary's
    ``laps`` gives each lap's stamps ``t0``, ``t1`` and ``frames`` [first, end) (frame
    indices), each segment its ``lap``. Frame noise is seeded by the
    frame index, so every lap gets fresh noise; the gt_map marks a bit per scene cell, so its
    memory does not grow with the laps.

    ``frame_writer(bag_path, camera, stamps, Ts, traj)`` replaces the default bag content
    (images + ground truth, :class:`_GroundTruthBagWriter`): a context manager whose
    ``write(i, left, right)`` gets the rendered frames in order and whose optional ``summary()``
    returns entries that update the returned summary and scene.yaml (see :mod:`.driver`).
    """

    t_start = time.perf_counter()
    out_dir = os.path.abspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    sc = scene if isinstance(scene, Scene) else make_scene(scene, contrast=contrast,
                                                            specular=specular, seed=seed)
    cam = camera if camera is not None else sim_camera(distort=distort, scale=scale)
    raw = not cam.is_rectified
    if distort and not raw:
        raise ValueError("distort=True needs a camera with distortion (sim_camera(distort=True))")
    traj = build_trajectory(trajectory if trajectory is not None else sc, duration, seed,
                            scene=sc, laps=laps)
    stamps = traj.stamps(rate, STAMP0)
    rel = stamps - STAMP0
    Ts = traj.poses(rel)
    n = len(stamps)
    depth_every = int(save_depth or 0)
    depth_dir = os.path.join(out_dir, "gt_depth")
    if depth_every > 0:
        os.makedirs(depth_dir, exist_ok=True)
    if map_cell is None:
        map_cell = float(sc.params.get("map_cell", 0.01))
    cells = _MapCells(sc, map_cell)
    sim = Simulator(sc, cam, seed=seed, noise=noise)
    if raw:
        sim.raw_views     # undistort the pixel grid once, before forking
    sc.atlas()
    _STATE.clear()
    _STATE.update(sim=sim, traj=traj, Ts=Ts, rel=rel, raw=raw, gains=_exposure_gains(
        n, rate, seed, exposure), blur=int(blur), blur_offsets=(np.linspace(
            -0.5, 0.5, int(blur)) * blur_time if blur > 1 else None), depth_every=depth_every,
        depth_dir=depth_dir, cells=cells, mark=np.zeros(cells.total, bool),
        max_range=float(max_range))
    if workers is None:
        workers = min(2, os.cpu_count() or 1)
    workers = max(1, min(int(workers), n))
    mark = np.zeros(cells.total, bool)
    render_ms = np.zeros(n)
    bag_path = os.path.join(out_dir, "sequence.bag")
    t_write = 0.0
    pool = None
    try:
        if workers > 1:
            # One render process per core: the workers must run OpenCV single-threaded (its
            # thread pool on top cost ~40% more CPU on 2 cores). It has to be switched off in
            # the parent BEFORE forking: cv2.setNumThreads inside a forked child deadlocks on
            # the parent's thread pool state. The parent's setting is restored right after.
            n_cv = cv2.getNumThreads()
            cv2.setNumThreads(1)
            try:
                pool = multiprocessing.get_context("fork").Pool(workers,
                                                                initializer=_worker_init)
            finally:
                cv2.setNumThreads(n_cv)
            results = pool.imap(_render_frame, range(n), chunksize=2)
        else:
            results = (_render_frame(i) for i in range(n))
        make_writer = frame_writer if frame_writer is not None else _GroundTruthBagWriter
        with make_writer(bag_path, cam, stamps, Ts, traj) as bag:
            for i, left, right, keys, ms in results:
                tw = time.perf_counter()
                bag.write(i, left, right)
                mark[keys] = True
                render_ms[i] = ms
                t_write += time.perf_counter() - tw
                if progress is not None:
                    progress(i + 1, n)
    except BaseException:
        if pool is not None:      # a worker failed or we were interrupted: stop the rest now
            pool.terminate()
        raise
    finally:
        if pool is not None:
            pool.close()
            pool.join()
        _STATE.clear()
    tum_path = os.path.join(out_dir, "groundtruth.tum")
    write_tum(tum_path, Trajectory.from_matrices(stamps, Ts))
    close = int(np.clip(2 * np.ceil(0.5 * max_range / (cam.fx * map_cell)) + 1, 3, 9))
    cloud = cells.cloud(sc, mark, close)
    map_path = os.path.join(out_dir, "gt_map.ply")
    n_points = write_cloud(map_path, cloud)
    wall = time.perf_counter() - t_start

    W, H = cam.size
    dist = None
    if raw:
        dist = {side: {"model": m.distortion_model, "K": m.K.ravel().tolist(),
                       "D": m.D.tolist(), "R": m.R.ravel().tolist(), "P": m.P.ravel().tolist()}
                for side, m in (("left", cam.left), ("right", cam.right))}
    summary = {
        "scene": sc.name, "seed": int(seed), "duration": float(traj.duration),
        "n_frames": int(n), "trajectory": traj.kind, "stamp0": STAMP0,
        "lap_duration": float(traj.lap_duration),
        "laps": [{"lap": int(k), "t0": float(STAMP0 + a), "t1": float(STAMP0 + b),
                  "frames": [int(np.searchsorted(rel, a - 1e-9)),
                             int(np.searchsorted(rel, b - 1e-9))]}
                 for k, a, b in traj.laps],
        "camera": {"width": int(W), "height": int(H), "fx": cam.fx, "fy": cam.fy, "cx": cam.cx,
                   "cy": cam.cy, "baseline": cam.baseline, "rate": float(rate),
                   "rectified_output": not raw, "distortion": dist},
        "options": {"contrast": float(contrast), "specular": bool(specular),
                    "noise": float(noise), "max_range": float(max_range),
                    "save_depth": depth_every, "exposure": bool(exposure), "blur": int(blur),
                    "blur_time": float(blur_time), "map_cell": float(map_cell)},
        "labels": {int(k): v for k, v in LABELS.items()},
        "ground_truth": {"topic": "/ground_truth/pose", "frame": "map",
                         "child": "rectified left camera optical frame (z fwd, x right, y down)",
                         "depth": "Z along the rectified left optical axis, metres, 0 = none"},
        "segments": [{"name": nme, "t0": float(STAMP0 + a), "t1": float(STAMP0 + b),
                      "lap": int(traj.lap_of(0.5 * (a + b))[0])}
                     for nme, a, b in traj.segments],
        "scene_info": sc.summary(),
        "files": {"bag": "sequence.bag", "groundtruth": "groundtruth.tum",
                  "gt_map": "gt_map.ply", "gt_depth": "gt_depth/%06d.npz" if depth_every else None,
                  "scene": "scene.yaml"},
        "n_map_points": int(n_points),
        "timing": {"wall_s": round(wall, 3), "workers": int(workers),
                   "render_ms_per_frame_mean": round(float(render_ms.mean()), 2),
                   "render_ms_per_frame_median": round(float(np.median(render_ms)), 2),
                   "bag_write_s": round(t_write, 3)},
    }
    extra = getattr(bag, "summary", None)
    if extra is not None:
        summary.update(extra())
    atomic_write(os.path.join(out_dir, "scene.yaml"),
                 yaml.safe_dump(summary, sort_keys=False, default_flow_style=None), "w")
    summary.update(out_dir=out_dir, bag=bag_path, groundtruth=tum_path, gt_map=map_path,
                   depth_dir=depth_dir if depth_every else None,
                   scene_yaml=os.path.join(out_dir, "scene.yaml"))
    return summary
