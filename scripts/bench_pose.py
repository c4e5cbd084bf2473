#!/usr/bin/env python3
"""Benchmark of the pose node core (mdr_slam.pose.System): tracking time per frame and ATE.

    python scripts/bench_pose.py [--runs 3] [--frames 60] [--kitti DIR] [--no-synthetic]

* synthetic: a 752x480 ray-cast textured room (mdr_slam.pose.synthetic), orbit of 60 frames;
* KITTI: the 1226x370 clip in /work/shared/data/kitti06_clip (51 frames, poses.txt), ATE after
  Umeyama SE(3) alignment (ORB-SLAM3's C++ stereo tracker: 0.070 m on this clip).

Each configuration runs ``--runs`` times; per-frame tracking time is TrackResult.time_ms. With
``threads=True`` (live mode) it is the tracking thread's time only, frames are fed at the stream
rate (20 Hz synthetic, 10 Hz KITTI) so LocalMapping works between frames as live; with
``threads=False`` (offline runner) it includes LocalMapping. Prints median, p90, max and ATE.
"tracking CPU ms" is the CPU time of tracking alone (calling thread + right-image ORB worker,
without synchronous mapping): the one-core cost, far less inflated by a loaded machine than wall
time. ``--bag BAG --bag-frames N``: also the first N frames of a stereo bag with ground truth
(e.g. output/sample/sequence.bag, 752x480 at 20 Hz).
"whole-process CPU" adds every thread of the process (LocalMapping, LoopClosing, BLAS, the
right-image ORB worker): the pose node's CPU per frame, the figure to hold against the 20 Hz
budget. ``--drop`` feeds the threaded mode as a live stream to pose_node, which keeps only the
newest pair: frames that arrive while tracking is busy are skipped and counted.
Figures depend on the machine's load: run it on an idle machine for real numbers.
"""
from __future__ import annotations

import argparse
import glob
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "src", "mdr_slam", "src"))

import mdr_slam  # noqa: E402,F401  (before numpy, as in the node: picks OpenBLAS's kernels)
import numpy as np  # noqa: E402
from mdr_slam.camera import StereoCamera  # noqa: E402
from mdr_slam.geometry import inv_T  # noqa: E402
from mdr_slam.io import Trajectory  # noqa: E402
from mdr_slam.pose import System  # noqa: E402
from mdr_slam.pose.evaluate import ate_rmse  # noqa: E402


def synthetic(n):
    from mdr_slam.pose.synthetic import BoxRoom, orbit_trajectory
    cam = StereoCamera.from_rectified(752, 480, 458.0, 458.0, 376.0, 240.0, 0.11)
    room = BoxRoom((4.0, 2.0, 4.0), seed=1)
    poses = orbit_trajectory(n, radius=1.0, arc=2 * np.pi * n / 120.0)
    frames = [room.render_stereo(T, cam) for T in poses]
    stamps = 0.05 * np.arange(n)
    gt = Trajectory.from_matrices(stamps, [inv_T(poses[0]) @ T for T in poses])
    return cam, frames, stamps, gt, 0.05


def kitti(d):
    import cv2
    P = np.loadtxt(os.path.join(d, "calib.txt")).reshape(-1, 3, 4)
    fl = sorted(glob.glob(os.path.join(d, "image_l", "*.png")))
    fr = sorted(glob.glob(os.path.join(d, "image_r", "*.png")))
    frames = [(cv2.imread(a, 0), cv2.imread(b, 0)) for a, b in zip(fl, fr)]
    h, w = frames[0][0].shape
    cam = StereoCamera.from_rectified(w, h, P[0, 0, 0], P[0, 1, 1], P[0, 0, 2], P[0, 1, 2],
                                      -P[1, 0, 3] / P[1, 0, 0])
    stamps = np.loadtxt(os.path.join(d, "times.txt"))[: len(frames)]
    from mdr_slam.io.trajectory import read_kitti_poses
    gt = read_kitti_poses(os.path.join(d, "poses.txt"), stamps)
    return cam, frames, stamps, gt, 0.1


def bag_frames(path, n):
    from mdr_slam.pipeline import frames_from_bag
    cam, it = frames_from_bag(path, max_frames=n, ground_truth=True)
    frames, stamps, Ts = [], [], []
    for f in it:
        if f.T_map_cam_gt is None:
            continue
        frames.append(cam.rectify(f.left, f.right))
        stamps.append(f.stamp)
        Ts.append(f.T_map_cam_gt)
    stamps = np.array(stamps)
    period = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.05
    return cam, frames, stamps, Trajectory.from_matrices(stamps, np.array(Ts)), period


def loop_scene(per_turn=90, turns=1.25):
    """A 480x320 camera on 1.25 turns of a 1 m circle in a 6 m room: the last quarter revisits
    the start, so loop closing can correct the drift."""
    from mdr_slam.pose.synthetic import BoxRoom, orbit_trajectory
    cam = StereoCamera.from_rectified(480, 320, 300.0, 300.0, 240.0, 160.0, 0.12)
    room = BoxRoom((3.0, 1.5, 3.0), tex_size=768, seed=3)
    n = int(per_turn * turns)
    poses = orbit_trajectory(n, radius=1.0, arc=2 * np.pi * n / per_turn)
    frames = [room.render_stereo(T, cam) for T in poses]
    stamps = 0.05 * np.arange(n)
    gt = Trajectory.from_matrices(stamps, [inv_T(poses[0]) @ T for T in poses])
    return cam, frames, stamps, gt, 0.05


def report_loop(cam, frames, stamps, gt, period):
    for lc in (False, True):
        s = System(cam, config={"loop_closing": lc}, threads=False)
        for t, (l, r) in zip(stamps, frames):
            s.track(float(t), l, r)
        s.shutdown()
        traj = s.trajectory()
        print("loop scene (1.25 turns)      loop_closing=%-5s frames=%d tracked=%d loops=%s "
              "ATE %.3f m" % (lc, len(frames), len(traj),
                              s.loop_closing.loops if s.loop_closing else "-", ate_rmse(traj, gt)))
        sys.stdout.flush()


class _CpuTimed:
    """Wraps a callable and adds the CPU time of the thread that runs it to ``acc`` (ms)."""

    def __init__(self, fn, acc):
        self.fn, self.acc = fn, acc

    def __getattr__(self, name):   # an extractor's tables (scale, nlevels, ...) pass through
        return getattr(self.fn, name)

    def __call__(self, *a, **k):
        c0 = time.thread_time()
        try:
            return self.fn(*a, **k)
        finally:
            self.acc.append(1000.0 * (time.thread_time() - c0))


def _process_cpu():
    import resource
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def run(cam, frames, stamps, gt, period, threads, params, drop=False):
    """Per frame: System's wall time (time_ms, track_ms) and the tracking CPU time (the calling
    thread plus the right-image ORB worker, without synchronous LocalMapping/LoopClosing): the
    one-core cost, which a loaded machine inflates much less than wall time. Also the CPU of the
    whole process (every thread: mapping, loop closing, BLAS) per frame fed. ``drop`` (threads):
    a live stream to a node that keeps only the newest frame: frames that arrived while tracking
    was busy are skipped (counted), as pose_node does."""
    s = System(cam, config=params, threads=threads)
    right, mapping = [], []
    s.extractor_right = _CpuTimed(s.extractor_right, right)   # runs in Frame's worker thread
    if not threads:
        s.local_mapping.spin_sync = _CpuTimed(s.local_mapping.spin_sync, mapping)
        if s.loop_closing is not None:
            s.loop_closing.spin_sync = _CpuTimed(s.loop_closing.spin_sync, mapping)
    ms, tms, cpu, states, pcpu = [], [], [], [], []
    p_start, w_start = _process_cpu(), time.perf_counter()
    i, drops = 0, 0
    while i < len(frames):
        t0 = time.perf_counter()
        if threads and drop:   # the newest frame that has arrived by now
            newest = min(int((t0 - w_start) / period), len(frames) - 1)
            if newest < i:
                time.sleep(i * period - (t0 - w_start))
                continue
            drops += newest - i
            i = newest
        t, (l, r) = stamps[i], frames[i]
        c0, nr, nm, p0 = time.thread_time(), len(right), len(mapping), _process_cpu()
        res = s.track(float(t), l, r)
        cpu.append(1000.0 * (time.thread_time() - c0) + sum(right[nr:]) - sum(mapping[nm:]))
        pcpu.append(1000.0 * (_process_cpu() - p0))
        ms.append(res.time_ms)
        tms.append(res.track_ms)
        states.append(res.state)
        i += 1
        if threads and not drop:   # feed at the stream rate, as a live camera would
            time.sleep(max(0.0, period - (time.perf_counter() - t0)))
    s.shutdown()
    proc_total = 1000.0 * (_process_cpu() - p_start) / len(frames)
    traj = s.trajectory()
    return (np.array(ms), np.array(tms), np.array(cpu), states, ate_rmse(traj, gt), len(traj),
            np.array(pcpu), proc_total, drops)


def report(name, cam, frames, stamps, gt, period, runs, params, drop=False):
    modes = [m for m in (True, False) if not (m and NO_THREADS) and not (not m and ONLY_THREADS)]
    for threads in modes:
        all_ms, all_t, all_c, all_p, ates, totals, drops, lost = [], [], [], [], [], [], [], []
        for _ in range(runs):
            ms, tms, cpu, states, ate, n, pcpu, total, nd = run(
                cam, frames, stamps, gt, period, threads, params, drop=drop)
            all_ms.append(ms[1:])   # frame 0 is initialisation
            all_t.append(tms[1:])
            all_c.append(cpu[1:])
            all_p.append(pcpu[1:])
            ates.append(ate)
            totals.append(total)
            drops.append(nd)
            lost.append(states.count("LOST"))
        ms = np.concatenate(all_ms)
        tm = np.concatenate(all_t)
        cp = np.concatenate(all_c)
        pc = np.concatenate(all_p)
        print("%-16s threads=%-5s %dx%d frames=%d runs=%d | tracking ms: median %.1f p90 %.1f "
              "max %.1f | tracking CPU ms: median %.1f p90 %.1f min %.1f | per call incl. sync "
              "mapping: median %.1f p90 %.1f | tracked %d/%d | ATE %.3f m (runs: %s) | "
              "load %.1f" % (
                  name, threads, cam.size[0], cam.size[1], len(frames), runs, np.median(tm),
                  np.percentile(tm, 90), tm.max(), np.median(cp), np.percentile(cp, 90), cp.min(),
                  np.median(ms), np.percentile(ms, 90), n, len(frames), float(np.median(ates)),
                  " ".join("%.3f" % a for a in ates), os.getloadavg()[0]))
        print("%-16s threads=%-5s whole-process CPU ms per tracked frame: mean %.1f median %.1f "
              "p90 %.1f | process CPU per input frame %.1f ms | dropped (newest kept) %s | "
              "LOST %s" % (name, threads, pc.mean(), np.median(pc), np.percentile(pc, 90),
                           float(np.mean(totals)), drops if (threads and drop) else "-", lost))
        sys.stdout.flush()


NO_THREADS = ONLY_THREADS = False


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--kitti", default=os.path.join(os.path.dirname(ROOT), "shared", "data",
                                                   "kitti06_clip"))
    ap.add_argument("--no-synthetic", action="store_true")
    ap.add_argument("--no-kitti", action="store_true")
    ap.add_argument("--loop", action="store_true", help="also the loop-closing scene (slow)")
    ap.add_argument("--bag", default="", help="also a stereo bag with ground truth")
    ap.add_argument("--bag-frames", type=int, default=200)
    ap.add_argument("--drop", action="store_true",
                    help="threads: live feed keeping the newest frame (pose_node), count drops")
    ap.add_argument("--no-threads", action="store_true", help="only the synchronous mode")
    ap.add_argument("--only-threads", action="store_true", help="only the threaded mode")
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="BLAS threads, as pose_node's blas_threads (0: the library's default)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="tracker parameter override for the bag runs (repeatable), e.g. n_features=1000")
    args = ap.parse_args(argv)
    import yaml
    overrides = {}
    for kv in args.set:
        k, _, v = kv.partition("=")
        overrides[k.strip()] = yaml.safe_load(v)
    if args.blas_threads > 0:
        from threadpoolctl import threadpool_limits
        threadpool_limits(limits=args.blas_threads, user_api="blas")
    global NO_THREADS, ONLY_THREADS
    NO_THREADS, ONLY_THREADS = args.no_threads, args.only_threads
    print("load average at start: %.2f %.2f %.2f (2-core machine shared: figures are indicative)"
          % os.getloadavg())
    if not args.no_synthetic:
        report("synthetic room", *synthetic(args.frames), args.runs, None, args.drop)
    if not args.no_kitti and os.path.isdir(args.kitti):
        report("KITTI 06 clip", *kitti(args.kitti), args.runs, {"max_frames": 10}, args.drop)
    if args.bag:
        report(os.path.basename(args.bag), *bag_frames(args.bag, args.bag_frames), args.runs,
               overrides or None, args.drop)
    if args.loop:
        report_loop(*loop_scene())
    return 0


if __name__ == "__main__":
    sys.exit(main())
