#!/usr/bin/env python3
"""Replay a robot's bag through the pose tracker offline, with its wheel odometry, and measure
the localization error of base_link against the ground truth.

The bag is what ``mdr bench --navigate --record`` writes (DIR/SCENE/robot.bag): the stereo pair and
camera_info, ``/odom`` (the wheel odometry), ``/tf_static`` (base_link -> camera) and
``/ground_truth/odom``. The frames get ``T_odom_cam`` as the pose node gives them, and tracking
runs synchronously (``--threads`` for the mapping threads), so a run is repeatable and two
configurations can be compared on the same closed-loop drive. Untracked frames are measured
twice, by the error of the motion since the last tracked frame: the pose coasted on the corrected
odometry, and the raw odometry's (a node that holds map -> odom while LOST). The map is laid on the scene at
the first tracked frame, as ``mdr bench --navigate`` did before it aligned by the trajectory.

    python scripts/replay_robot_bag.py DIR/office/robot.bag
    python scripts/replay_robot_bag.py BAG --set planar_motion=false          # a TrackerConfig field
    python scripts/replay_robot_bag.py BAG --const optimizer.ODOM_EDGES=False  # a pose module constant
    python scripts/replay_robot_bag.py BAG --const system.ODOMETRY_CALIBRATION=False
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import time

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "src", "mdr_slam",
                                "src"))

from mdr_slam.camera import StereoCamera  # noqa: E402
from mdr_slam.conversions import (camera_info_to_model, image_msg_to_mono8,  # noqa: E402
                                  pose_to_matrix, transform_to_matrix)
from mdr_slam.geometry import inv_T  # noqa: E402
from mdr_slam.pose import System, TrackerConfig  # noqa: E402

LEFT, RIGHT = "/stereo/left/image_raw", "/stereo/right/image_raw"
LEFT_INFO, RIGHT_INFO = "/stereo/left/camera_info", "/stereo/right/camera_info"


def _interp(ts, Ts, t):
    i = int(np.searchsorted(ts, t))
    if i <= 0 or i >= len(ts):
        return None
    w = (t - ts[i - 1]) / (ts[i] - ts[i - 1])
    R = Slerp([0.0, 1.0], Rotation.from_matrix([Ts[i - 1][:3, :3], Ts[i][:3, :3]]))([w])
    T = np.eye(4)
    T[:3, :3] = R.as_matrix()[0]
    T[:3, 3] = (1.0 - w) * Ts[i - 1][:3, 3] + w * Ts[i][:3, 3]
    return T


def _static_chain(static, parent, child):
    T, cur = np.eye(4), child
    while cur != parent:
        up = [(p, M) for (p, c), M in static.items() if c == cur]
        if not up:
            raise SystemExit("no %s -> %s in /tf_static" % (parent, child))
        p, M = up[0]
        T, cur = M @ T, p
    return T


def _typed(cfg, key, value):
    cur = getattr(cfg, key)
    if isinstance(cur, bool):
        return value.lower() in ("1", "true", "yes", "on")
    return type(cur)(value) if isinstance(cur, (int, float)) else value


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag")
    ap.add_argument("--threads", action="store_true", help="LocalMapping/LoopClosing in threads")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="a TrackerConfig field")
    ap.add_argument("--const", action="append", default=[], metavar="MODULE.NAME=VALUE",
                    help="a constant of mdr_slam.pose.MODULE (ablations)")
    ap.add_argument("--no-odometry", action="store_true", help="frames without wheel odometry")
    ap.add_argument("--out", default="", help=".npy of (stamp, tracked, error m, x, y) per frame")
    a = ap.parse_args(argv)
    import rosbag
    bag = rosbag.Bag(a.bag)
    static, odom, gt, info = {}, ([], []), ([], []), {}
    for topic, m, _ in bag.read_messages(topics=["/tf_static", "/odom", "/ground_truth/odom",
                                                 LEFT_INFO, RIGHT_INFO]):
        if topic == "/tf_static":
            for tr in m.transforms:
                static[(tr.header.frame_id, tr.child_frame_id)] = transform_to_matrix(tr.transform)
        elif topic in (LEFT_INFO, RIGHT_INFO):
            info.setdefault(topic, m)
        else:
            dst = odom if topic == "/odom" else gt
            dst[0].append(m.header.stamp.to_sec())
            dst[1].append(pose_to_matrix(m.pose.pose))
    odom_t, gt_t = np.array(odom[0]), np.array(gt[0])
    if len(info) < 2 or not len(gt_t):
        raise SystemExit("the bag needs both camera_infos and /ground_truth/odom")
    li, ri = info[LEFT_INFO], info[RIGHT_INFO]
    cam = StereoCamera(camera_info_to_model(li), camera_info_to_model(ri))
    T_base_cam = _static_chain(static, "base_link", li.header.frame_id)
    cfg = TrackerConfig()
    for s in a.set:
        k, v = s.split("=", 1)
        cfg = cfg.replace(**{k: _typed(cfg, k, v)})
    for c in a.const:
        k, v = c.split("=", 1)
        mod, name = k.rsplit(".", 1)
        M = importlib.import_module("mdr_slam.pose." + mod)
        setattr(M, name, type(getattr(M, name))(eval(v)))   # noqa: S307  (a developer's ablation)
    system = System(cam, cfg, threads=a.threads, T_map_cam0=T_base_cam)
    pending, rows = {}, []
    held = None      # the last tracked frame's T_map_odom: a node without a coasted pose keeps it
    last = None      # the last tracked frame's (T_map_base, true T_world_base)
    t0 = time.time()
    for topic, m, _ in bag.read_messages(topics=[LEFT, RIGHT]):
        st = m.header.stamp.to_sec()
        pending.setdefault(st, {})[topic] = m
        if len(pending[st]) < 2:
            continue
        pair = pending.pop(st)
        L, R = cam.rectify(image_msg_to_mono8(pair[LEFT]), image_msg_to_mono8(pair[RIGHT]))
        frame = system.make_frame(st, L, R)
        T_odom_base = None if a.no_odometry else _interp(odom_t, odom[1], st)
        if T_odom_base is not None:
            frame.T_odom_cam = T_odom_base @ T_base_cam
        res = system.track(st, frame=frame)
        T_map_base = None if res.T_map_cam is None else res.T_map_cam @ inv_T(T_base_cam)
        G = _interp(gt_t, gt[1], st)
        lost = None       # untracked: (the coasted pose or None, the raw odometry's, last tracked)
        if T_map_base is not None and T_odom_base is not None:
            held = T_map_base @ inv_T(T_odom_base)
            last = (T_map_base, G)
        elif T_map_base is None and held is not None and T_odom_base is not None:
            c = getattr(res, "T_map_cam_coasted", None)
            lost = (None if c is None else c @ inv_T(T_base_cam), held @ T_odom_base, last)
        rows.append((st, T_map_base, G, lost))
    lc = getattr(system, "loop_closing", None)
    n_loops = len(lc.loops) if lc is not None else 0
    system.shutdown()
    wall = time.time() - t0
    first = next((r for r in rows if r[1] is not None and r[2] is not None), None)
    if first is None:
        raise SystemExit("nothing tracked")
    A = first[2] @ inv_T(first[1])   # the map laid on the scene at the first tracked frame
    out, coast = [], []
    for st, T, G, lost in rows:
        if lost is not None and G is not None and lost[2][1] is not None:
            # the dead reckoning's own error: the motion since the last tracked frame, in its
            # base frame, against the true one (the map's error at that frame left out)
            T0, G0 = lost[2]
            true = (inv_T(G0) @ G)[:2, 3]
            coast.append([np.nan if L is None else float(np.linalg.norm((inv_T(T0) @ L)[:2, 3]
                                                                        - true))
                          for L in lost[:2]])
        if T is None or G is None:
            out.append((st, 0.0, np.nan, np.nan, np.nan))
            continue
        E = A @ T
        out.append((st, 1.0, float(np.linalg.norm(E[:2, 3] - G[:2, 3])), G[0, 3], G[1, 3]))
    out = np.array(out)
    e = out[:, 2]
    ok = ~np.isnan(e)
    print("%s: %d pairs, %d tracked, %d loops, %.0f s; base_link error (m) median %.3f, p90 %.3f, "
          "max %.3f; %d frames over 0.10 m, %d over 0.05 m"
          % (os.path.basename(a.bag), len(out), int(ok.sum()), n_loops, wall, np.median(e[ok]),
             np.percentile(e[ok], 90), e[ok].max(), int(np.sum(e[ok] > 0.10)),
             int(np.sum(e[ok] > 0.05))))
    coast = np.array(coast).reshape(-1, 2)
    for j, what in enumerate(("coasted on the corrected odometry",
                              "map -> odom held, raw odometry")):
        e = coast[:, j]
        e = e[~np.isnan(e)]
        if len(e):
            print("untracked frames, %s: %d, error of the motion since the last tracked frame "
                  "(m) median %.3f, p90 %.3f, max %.3f; %d over 0.10 m" % (what, len(e), np.median(e), np.percentile(e, 90), e.max(),
                              int(np.sum(e > 0.10))))
    cal = getattr(system, "odometry_calibration", None)
    if cal is not None:
        print(cal.summary())
    if a.out:
        np.save(a.out, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
