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
    python scripts/replay_robot_bag.py BAG --threads --loops   # each verified loop against the truth
    python scripts/replay_robot_bag.py BAG --until 80          # the first 80 s only

``--loops`` prints every loop candidate that passed the geometric verification: its figures
(correction, keyframe path, map and odometry checks), whether it closed, and how far the map's
relative pose between the two keyframes is from the true one before and after the correction.
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


def _rel_error(A, B):
    D = inv_T(A) @ B
    return float(np.linalg.norm(D[:3, 3])), float(np.degrees(Rotation.from_matrix(
        D[:3, :3]).magnitude()))


def _print_loops(verified, lc, gt_t, gt_T, T_base_cam):
    """One line per verified loop candidate: the relative pose cand -> kf of the map, before and
    after the correction, against the truth's (m, deg)."""
    closed = {(c["found"], c["cand"]): c for c in lc.closed}
    unconfirmed = {u[:2]: u[2] for u in lc.unconfirmed}
    mapc = {c[:2]: c for c in lc.correction_checks}
    odoc = {c[:2]: c for c in lc.odom_checks}
    print("verified loop candidates (kf, cand, source): correction m/deg, keyframe path m; "
          "map check n0 -> n1 (px); odometry check m before -> after over path; "
          "map vs truth m/deg before -> after; verdict")
    for v in verified:
        Gk, Gc = (_interp(gt_t, gt_T, t) for t in (v["kf_t"], v["cand_t"]))
        if Gk is None or Gc is None:
            continue
        true = inv_T(Gc @ T_base_cam) @ (Gk @ T_base_cam)
        before = inv_T(v["cand_wc"]) @ v["kf_wc"]
        after = inv_T(v["cand_wc"]) @ v["S"] @ v["kf_wc"]
        e0, r0 = _rel_error(before, true)
        e1, r1 = _rel_error(after, true)
        key = (v["kf"], v["cand"])
        c = closed.get(key)
        mc, oc = mapc.get(key), odoc.get(key)
        closing = any((x["kf"], x["cand"]) == key and x["found"] != x["kf"] for x in lc.closed)
        verdict = ("confirmed it: CLOSED" if closing else
                   "CLOSED" if c is not None and c["kf"] == v["kf"] else
                   "CLOSED at %d" % c["kf"] if c is not None else
                   "unconfirmed (%d)" % unconfirmed[key] if key in unconfirmed else
                   "refused: drift" if not v["plausible"] and (oc is None or oc[-1]) else
                   "refused: odometry" if not v["plausible"] else
                   "refused: map check" if mc is not None and not mc[-1] else "refused: other")
        print("  %4d %4d %-9s %5.2f m %5.1f deg over %6.1f m; map %s; odo %s; truth %.2f m "
              "%.1f deg -> %.2f m %.1f deg: %s, %s"
              % (v["kf"], v["cand"], "" if c is None else c["source"], v["moved"], v["turned"],
                 v["path"], "-" if mc is None else "%d -> %d (%.1f px)" % mc[2:5],
                 "-" if oc is None else "%.2f m %.1f deg -> %.2f m %.1f deg over %.1f m"
                 % (oc[3], oc[5], oc[4], oc[6], oc[2]),
                 e0, r0, e1, r1, verdict,
                 "better" if e1 + 0.05 * r1 < e0 + 0.05 * r0 else "WORSE"))
    h = np.array(lc.held_ms)
    if len(h):
        print("  map lock held per keyframe by LoopClosing (s): median %.3f, p90 %.3f, max %.2f "
              "over %d keyframes" % (np.median(h) / 1e3, np.percentile(h, 90) / 1e3,
                                     h.max() / 1e3, len(h)))
    for c in lc.closed:
        if c.get("held_ms") is not None:
            graph = "unfinished" if c.get("graph_ms") is None else "%.2f s" % (c["graph_ms"] / 1e3)
            print("  loop %d-%d: map lock held %.2f s, pose graph %s (%d edges)"
                  % (c["kf"], c["cand"], c["held_ms"] / 1000.0, graph, c["graph_edges"]))


def _print_gated(gated, gt_t, gt_T, T_base_cam, A):
    """One line per pose the odometry gate judged after a gap: the tracker's motion since the last
    tracked frame, the raw and the corrected odometry's, each against the true motion (m, deg)."""
    print("gated poses after a gap: t, gap s, travel m; error (m/deg) of the pose, the raw "
          "odometry's, the corrected odometry's; pose vs raw, pose vs corrected (m/deg); "
          "base_link error in the scene (m) of the last tracked frame, the pose, the corrected "
          "odometry's; verdict")
    for g in gated:
        G0, G = (_interp(gt_t, gt_T, t) for t in (g["t0"], g["t"]))
        if G0 is None or G is None:
            continue
        true = inv_T(G0 @ T_base_cam) @ (G @ T_base_cam)
        pose = inv_T(g["T0"]) @ g["T"]
        raw = inv_T(g["raw0"]) @ g["raw"]
        cal = None if g["cal0"] is None or g["cal"] is None else inv_T(g["cal0"]) @ g["cal"]
        ep, rp = _rel_error(pose, true)
        er, rr = _rel_error(raw, true)
        ec, rc = (np.nan, np.nan) if cal is None else _rel_error(cal, true)
        dr, ar = _rel_error(pose, raw)
        dc, ac = (np.nan, np.nan) if cal is None else _rel_error(pose, cal)
        ab = [float(np.linalg.norm((A @ M @ inv_T(T_base_cam))[:2, 3] - Gt[:2, 3]))
              if M is not None else np.nan
              for M, Gt in ((g["T0"], G0), (g["T"], G),
                            (None if cal is None else g["T0"] @ cal, G))]
        print("  %7.2f %5.1f %5.2f; pose %.2f/%.1f raw %.2f/%.1f cal %.2f/%.1f; vs raw %.2f/%.1f "
              "vs cal %.2f/%.1f; scene %.2f %.2f %.2f; %s"
              % (g["t"], g["gap"], float(np.linalg.norm(true[:3, 3])), ep, rp, er, rr, ec, rc,
                 dr, ar, dc, ac, ab[0], ab[1], ab[2], "kept" if g["ok"] else "refused"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag")
    ap.add_argument("--threads", action="store_true", help="LocalMapping/LoopClosing in threads")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="a TrackerConfig field")
    ap.add_argument("--const", action="append", default=[], metavar="MODULE.NAME=VALUE",
                    help="a constant of mdr_slam.pose.MODULE (ablations)")
    ap.add_argument("--no-odometry", action="store_true", help="frames without wheel odometry")
    ap.add_argument("--loops", action="store_true",
                    help="each verified loop candidate's figures against the truth")
    ap.add_argument("--gate", type=float, default=0.0, metavar="S",
                    help="every pose put to the tracker's odometry gate more than S s after the "
                         "last tracked frame: its error and the raw and corrected odometry's")
    ap.add_argument("--until", type=float, default=0.0, metavar="S",
                    help="stop S s (bag time) after the first stereo pair")
    ap.add_argument("--out", default="", help=".npy per frame: stamp, tracked, error (m), true x, y (m), "
                    "error along and across the true heading (m), yaw error (deg), error of the "
                    "pose in use (tracked, else coasted; m)")
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
    verified = []
    if a.loops and system.loop_closing is not None:
        lc_ = system.loop_closing
        gate = lc_.plausible_correction

        def plausible(kf, cand, S):   # every verified candidate passes here first
            ok = gate(kf, cand, S)
            verified.append(dict(kf=kf.id, cand=cand.id, S=S.copy(), kf_wc=kf.T_wc.copy(),
                                 cand_wc=cand.T_wc.copy(), kf_t=kf.stamp, cand_t=cand.stamp,
                                 moved=lc_.last_correction[0], turned=lc_.last_correction[1],
                                 path=lc_._last_path, plausible=ok))
            return ok
        lc_.plausible_correction = plausible
    gated = []
    if a.gate > 0:
        tr_ = system.tracking
        agrees_ = tr_.odometry_agrees

        def odometry_agrees(frame, record=True):
            ok = agrees_(frame, record)
            last_ = tr_.last_frame
            if record and last_ is not None and frame.T_cw is not None and \
                    frame.stamp - last_.stamp > a.gate and last_.T_cw is not None:
                gated.append(dict(t=frame.stamp, gap=frame.stamp - last_.stamp, ok=ok,
                                  t0=last_.stamp, T0=inv_T(last_.T_cw), T=inv_T(frame.T_cw),
                                  raw0=last_.T_odom_cam, raw=frame.T_odom_cam,
                                  cal0=getattr(last_, "T_odom_cam_calibrated", None),
                                  cal=getattr(frame, "T_odom_cam_calibrated", None)))
            return ok
        tr_.odometry_agrees = odometry_agrees
    pending, rows = {}, []
    held = None      # the last tracked frame's T_map_odom: a node without a coasted pose keeps it
    last = None      # the last tracked frame's (T_map_base, true T_world_base)
    t0, t_first = time.time(), None
    for topic, m, _ in bag.read_messages(topics=[LEFT, RIGHT]):
        st = m.header.stamp.to_sec()
        t_first = st if t_first is None else t_first
        if a.until > 0 and st - t_first > a.until:
            break
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
        # the pose the robot goes by: the tracked one, or the coasted one while untracked
        used = T if T is not None else (None if lost is None else lost[0])
        e_used = np.nan if used is None or G is None else \
            float(np.linalg.norm((A @ used)[:2, 3] - G[:2, 3]))
        if T is None or G is None:
            out.append((st, 0.0, np.nan, np.nan, np.nan, np.nan, np.nan, np.nan, e_used))
            continue
        E = A @ T
        D = inv_T(G) @ E
        out.append((st, 1.0, float(np.linalg.norm(E[:2, 3] - G[:2, 3])), G[0, 3], G[1, 3],
                    D[0, 3], D[1, 3], np.degrees(np.arctan2(D[1, 0], D[0, 0])), e_used))
    out = np.array(out)
    e = out[:, 2]
    ok = ~np.isnan(e)
    print("%s: %d pairs, %d tracked, %d loops, %.0f s; base_link error (m) median %.3f, p90 %.3f, "
          "max %.3f; %d frames over 0.10 m, %d over 0.05 m"
          % (os.path.basename(a.bag), len(out), int(ok.sum()), n_loops, wall, np.median(e[ok]),
             np.percentile(e[ok], 90), e[ok].max(), int(np.sum(e[ok] > 0.10)),
             int(np.sum(e[ok] > 0.05))))
    e = out[:, 8]
    ok = ~np.isnan(e)
    if ok.any():
        print("the pose in use (tracked, else coasted on the corrected odometry): %d of %d pairs; "
              "error (m) median %.3f, p90 %.3f, max %.3f; %d frames over 0.10 m"
              % (int(ok.sum()), len(out), np.median(e[ok]), np.percentile(e[ok], 90), e[ok].max(),
                 int(np.sum(e[ok] > 0.10))))
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
    if verified:
        _print_loops(verified, lc, gt_t, gt[1], T_base_cam)
    if gated:
        _print_gated(gated, gt_t, gt[1], T_base_cam, A)
    if a.out:
        np.save(a.out, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
