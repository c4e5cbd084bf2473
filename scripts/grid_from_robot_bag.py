#!/usr/bin/env python3
"""Map a robot's bag again offline, frame by frame, and set its grid beside the live one: was a
miss the map's doing, and which depth setting would have mapped what the robot hit?

The bag is what ``mdr bench --navigate --record`` writes (DIR/SCENE/robot.bag): the stereo pair and
camera_info, ``/tf`` (the pose node's ``map -> odom -> base_link``), ``/tf_static``,
``/ground_truth/odom``, ``/mdr/keyframes`` and the live ``/mdr/map/nav_grid``. Every pair from
``--from`` to ``--until`` goes through the depth filter (:class:`mdr_slam.depth.StereoDepth`,
config/depth.yaml and ``--set depth.NAME=VALUE``) and the voxel map (config/fusion.yaml), posed as
the live depth node posed it (``--poses live``: the recorded tf at the image stamp) or by the
truth (``--poses truth``, in the map frame the live one had at ``--from``), with a new depth
keyframe wherever the tracker made one (its ``/mdr/keyframes`` events) unless ``--own-keyframes``
or the bag has none.
At each ``--at`` time it prints the points per cloud and in the map and writes
``OUT/grid_<t>.png``: the live grid of that moment and the offline one, in ``map``. With
``scene.json`` beside the bag (the benchmark writes it) it scores against the scene's surfaces the
depth clouds, each posed by the truth (so the depth's error alone), and the offline map (the share
within 5 cm, as the benchmark scores the live map).

    python scripts/grid_from_robot_bag.py BAG --from 20 --until 42 --at 41.5 --out DIR
    python scripts/grid_from_robot_bag.py BAG --from 20 --until 42 --at 41.5 --out DIR \\
        --set depth.weak_texture=off
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src", "mdr_slam", "src"))
sys.path.insert(0, HERE)

from replay_robot_bag import _interp, _static_chain  # noqa: E402

SCORE_DIST = 0.05   # m: a point within this of a true surface is right (the benchmark's measure)


def _read(bag_path):
    """tf chains, ground truth, tracker keyframe stamps and live grids of a recorded bag."""
    import rosbag
    from mdr_slam.conversions import pose_to_matrix, transform_to_matrix
    static, keyframes, grids = {}, [], []
    tf = {("map", "odom"): ([], []), ("odom", "base_link"): ([], [])}
    gt = ([], [])
    with rosbag.Bag(bag_path) as bag:
        for topic, m, _ in bag.read_messages(topics=["/tf", "/tf_static", "/ground_truth/odom",
                                                     "/mdr/keyframes", "/mdr/map/nav_grid"]):
            if topic == "/tf_static":
                for tr in m.transforms:
                    static[(tr.header.frame_id, tr.child_frame_id)] = \
                        transform_to_matrix(tr.transform)
            elif topic == "/tf":
                for tr in m.transforms:
                    k = (tr.header.frame_id, tr.child_frame_id)
                    if k in tf:
                        tf[k][0].append(tr.header.stamp.to_sec())
                        tf[k][1].append(transform_to_matrix(tr.transform))
            elif topic == "/ground_truth/odom":
                gt[0].append(m.header.stamp.to_sec())
                gt[1].append(pose_to_matrix(m.pose.pose))
            elif topic == "/mdr/keyframes":
                if m.reason == m.NEW_KEYFRAME:
                    keyframes.extend(k.stamp.to_sec() for k in m.keyframes)
            else:
                data = np.array(m.data, np.int16).reshape(m.info.height, m.info.width)
                grids.append((m.header.stamp.to_sec(), data, (m.info.origin.position.x,
                              m.info.origin.position.y), m.info.resolution))
    tf = {k: (np.array(v[0]), v[1]) for k, v in tf.items()}
    return static, tf, (np.array(gt[0]), gt[1]), np.sort(keyframes), grids


def _show(ax, data, origin, res, title):
    H, W = data.shape
    img = np.where(data == 100, 0.0, np.where(data == 0, 1.0, 0.6))
    ax.imshow(img, origin="lower", cmap="gray", vmin=0, vmax=1, interpolation="nearest",
              extent=[origin[0], origin[0] + W * res, origin[1], origin[1] + H * res])
    ax.set_title(title, fontsize=9)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bag")
    ap.add_argument("--from", dest="t0", type=float, default=0.0, help="first stamp (s)")
    ap.add_argument("--until", type=float, required=True, help="last stamp (s)")
    ap.add_argument("--at", type=float, action="append", required=True,
                    help="stamp (s) of a grid to compare; repeat for more")
    ap.add_argument("--poses", choices=("live", "truth"), default="live")
    ap.add_argument("--own-keyframes", action="store_true",
                    help="the depth filter's own keyframe rule instead of the tracker's events")
    ap.add_argument("--set", action="append", default=[], metavar="depth.NAME=VALUE",
                    help="a depth or fusion parameter (depth.weak_texture=off)")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mdr_slam.cli.main_run import _overrides
    from mdr_slam.config import split_known
    from mdr_slam.depth import DepthConfig, StereoDepth
    from mdr_slam.geometry import transform_points
    from mdr_slam.io import cloud_xyz
    from mdr_slam.fusion import VoxelMap, VoxelMapConfig
    from mdr_slam.nav import map_min_confidence, map_products
    from mdr_slam.nodes import node_configs
    from mdr_slam.pipeline import frames_from_bag, load_params

    over = _overrides(a.set)
    static, tf, (gt_t, gt_T), kf_stamps, grids = _read(a.bag)
    if not len(tf[("odom", "base_link")][0]) or not len(gt_t):
        raise SystemExit("the bag needs /tf (map -> odom -> base_link) and /ground_truth/odom")
    camera, frames = frames_from_bag(a.bag)
    T_base_cam = _static_chain(static, "base_link", camera_frame(static))
    _, dp = split_known(load_params("depth"), *node_configs("depth"))
    dp.update(over["depth"])
    depth = StereoDepth(camera, DepthConfig.from_dict(dp))
    _, fp = split_known(load_params("fusion"), *node_configs("fusion"))
    fp.update(over["fusion"])
    vmap = VoxelMap(VoxelMapConfig.from_dict(fp))
    products = dict(load_params("fusion"), **over["fusion"])

    def live(t):
        A = _interp(*tf[("map", "odom")], t) if len(tf[("map", "odom")][0]) > 1 else np.eye(4)
        B = _interp(*tf[("odom", "base_link")], t)
        return None if A is None or B is None else A @ B

    scene = _scene_beside(a.bag)
    cloud_prec = []
    own = a.own_keyframes or not len(kf_stamps)
    if own and not a.own_keyframes:
        print("no /mdr/keyframes in the bag: the depth filter's own keyframe rule")
    map_from_world = None
    os.makedirs(a.out, exist_ok=True)
    at = sorted(a.at)
    points, last = [], None
    for f in frames:
        t = f.stamp
        if t < a.t0:
            continue
        if t > a.until:
            break
        T_map_base = live(t)
        G = _interp(gt_t, gt_T, t)
        if T_map_base is None or G is None:
            continue
        if map_from_world is None:       # the truth in the live map frame, as it was at --from
            map_from_world = T_map_base @ np.linalg.inv(G)
        if a.poses == "truth":
            T_map_base = map_from_world @ G
        T = T_map_base @ T_base_cam
        kf = None if own else bool(
            last is not None and np.any((kf_stamps > last) & (kf_stamps <= t + 1e-4)))
        last = t
        left, right = camera.rectify(f.left, f.right)
        out = depth.process(t, left, right, T, rectified=True, new_keyframe=kf)
        points.append(len(out.points))
        if len(out.points):
            vmap.integrate(out.points, T, t, intensity=out.intensity)
            if scene is not None:
                d = scene.distance_to_surfaces(transform_points(G @ T_base_cam, out.points))
                cloud_prec.append(float(np.mean(d < SCORE_DIST)))
        while at and t >= at[0] - 1e-6:
            mark = at.pop(0)
            cloud = vmap.to_cloud(min(map_min_confidence(products)))
            _, (data, origin, res) = map_products(cloud, products)
            print("t %.1f: %d clouds, points per cloud median %.0f; map %d points; grid %d "
                  "occupied cells" % (t, len(points), np.median(points), len(vmap),
                                      int((data == 100).sum())), flush=True)
            if scene is not None:
                d = scene.distance_to_surfaces(transform_points(
                    np.linalg.inv(map_from_world), cloud_xyz(cloud)))
                print("  within %.0f cm of the scene: clouds (truth poses) median %.1f %%, "
                      "map %.1f %%" % (100 * SCORE_DIST, 100 * np.median(cloud_prec),
                                       100 * np.mean(d < SCORE_DIST)), flush=True)
            before = [g for g in grids if g[0] <= mark]
            fig, axes = plt.subplots(1, 2 if before else 1, figsize=(14 if before else 7, 6),
                                     squeeze=False)
            if before:
                g = before[-1]
                _show(axes[0, 0], g[1], g[2], g[3], "live /mdr/map/nav_grid at %.1f s" % g[0])
            _show(axes[0, -1], np.where(data < 0, 10, data), origin, res,
                  "offline at %.1f s (%s poses%s)" % (t, a.poses, "; " + ", ".join(a.set)
                                                     if a.set else ""))
            for ax in axes[0]:
                ax.set_xlim(origin[0], origin[0] + data.shape[1] * res)
                ax.set_ylim(origin[1], origin[1] + data.shape[0] * res)
            fig.tight_layout()
            fig.savefig(os.path.join(a.out, "grid_%.1f.png" % mark), dpi=80)
            plt.close(fig)
    if at:
        print("no frames reached %s" % ", ".join("%.1f" % t for t in at))
    return 0


def _scene_beside(bag_path):
    """The simulator scene named in the benchmark's ``scene.json`` beside the bag, or None."""
    import json
    path = os.path.join(os.path.dirname(os.path.abspath(bag_path)), "scene.json")
    if not os.path.exists(path):
        return None
    from mdr_slam.sim import make_scene
    with open(path) as f:
        info = json.load(f)
    return make_scene(info["scene"], seed=info["seed"])


def camera_frame(static) -> str:
    """The left camera's optical frame in /tf_static."""
    left = [c for (_, c) in static if "left" in c and "optical" in c]
    if not left:
        raise SystemExit("no left optical frame in /tf_static")
    return left[0]


if __name__ == "__main__":
    sys.exit(main())
