"""``mdr demo``: the README's first command. Maps the built-in sample sequence and leaves the map,
a report and pictures under ``--out`` (default ``output/``):

    output/sample/          the sample sequence (rendered by ``mdr sim`` when absent)
    output/demo/map.ply     the fused global map (PLY: x y z intensity confidence ...)
    output/demo/report.md   what ran, how fast, and how good (map RMSE/completeness, ATE)
    output/demo/map_top.png, map_perspective.png, trajectory.png
    output/demo/map_rviz.png  rviz (shipped config) showing the map the fusion node publishes,
                            rendered under Xvfb (when rviz is installed; --no-rviz skips it)

By default the ORB tracker (node 1's core) poses the frames, as on a robot, and the map is in the
tracker's ``map`` frame (base_link where tracking starts); to score it, it is moved into the ground truth's
frame by the SE(3) alignment of the trajectory (Umeyama), as evo aligns trajectories. With
``--pose-source groundtruth`` the sample's true poses place the depth (the launch file's
``pose_source:=groundtruth``), so the map shows what depth and fusion alone make of the sequence.
``--pose-source`` is passed to ``mdr run`` explicitly, as are the bag input options
(``--left-image`` ... ``--rectified``, as ``mdr run`` takes them: the rendered sample uses the
default topics; a bag of your own placed at ``output/sample/sequence.bag`` may use others; it is
then scored against ``groundtruth.tum`` and ``gt_map.ply`` beside it).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import time

import numpy as np

from ..eval import ate, map_alignment, map_metrics
from ..eval.plot import plot_ate
from ..io import cloud_xyz, read_cloud, read_tum
from ..viz import save_map_pictures
from . import mdr_command
from .main_run import add_bag_input_arguments, bag_input_argv


def add_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="output")
    p.add_argument("--scene", default="office", help="sample scene (office, corridor, garage)")
    p.add_argument("--duration", type=float, default=30.0)
    p.add_argument("--pose-source", choices=("orb", "groundtruth"), default="orb",
                   help="orb (default): track, as on a robot; groundtruth: the sample's true poses")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--scale", type=float, default=1.0,
                   help="image scale of the rendered sample (tests use 0.5)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.KEY=VALUE",
                   help="parameter override for mdr run")
    p.add_argument("--no-rviz", action="store_true",
                   help="skip the rviz screenshot (taken under Xvfb when rviz is installed)")
    add_bag_input_arguments(p)
    p.set_defaults(func=run)
    return p



def _step(text):
    print("[mdr demo] %s" % text, flush=True)


def run(args) -> int:
    t_start = time.time()
    sample = os.path.join(args.out, "sample" if args.scene == "office" else "sample_" + args.scene)
    demo = os.path.join(args.out, "demo")
    os.makedirs(demo, exist_ok=True)
    bag = os.path.join(sample, "sequence.bag")
    if not os.path.exists(bag):
        _step("1/4 rendering the sample sequence (%s, %.0f s) into %s" % (args.scene, args.duration,
                                                                          sample))
        r = subprocess.run(mdr_command() + ["sim", "--scene", args.scene, "--duration", str(args.duration),
                                     "--scale", str(args.scale), "--out", sample])
        if r.returncode != 0:
            return r.returncode
    else:
        _step("1/4 sample sequence: %s (present)" % bag)
    _step("2/4 mapping it: pose (%s) -> depth (ELAS + temporal filter) -> fusion" % args.pose_source)
    cmd = mdr_command() + ["run", bag, "--out", demo, "--pose-source", args.pose_source]
    cmd += bag_input_argv(args)
    if args.max_frames:
        cmd += ["--max-frames", str(args.max_frames)]
    for kv in args.set:
        cmd += ["--set", kv]
    r = subprocess.run(cmd)
    if r.returncode != 0:
        return r.returncode
    _step("3/4 scoring against the simulator's exact ground truth")
    summary = json.load(open(os.path.join(demo, "summary.json")))
    cloud = read_cloud(os.path.join(demo, "map.ply"))
    xyz = cloud_xyz(cloud).astype(np.float64)
    gt_traj = read_tum(os.path.join(sample, "groundtruth.tum"))
    est_traj = read_tum(os.path.join(demo, "trajectory.tum"))
    traj_res = ate(est_traj, gt_traj, "se3") if len(est_traj) > 2 else None
    if traj_res is not None and args.pose_source == "orb":
        al = map_alignment(est_traj, gt_traj)
        xyz = xyz @ np.asarray(al["rotation"]).T + np.asarray(al["translation"])
    gt_map = read_cloud(os.path.join(sample, "gt_map.ply"))
    m = map_metrics(xyz, cloud_xyz(gt_map), gt_labels=gt_map.get("surface")) if len(xyz) else None
    _step("4/4 pictures and report")
    conf = cloud.get("confidence")
    top, persp = save_map_pictures(xyz, os.path.join(demo, "map"),
                                   title="MDR-SLAM map (%s sample)" % args.scene)
    rviz_png = None
    if not args.no_rviz:
        # the rviz screenshot when it is taken: `mdr --help` imports this module
        from .rviz_shot import rviz_screenshot
        try:
            shot = rviz_screenshot(os.path.join(demo, "map.ply"), os.path.join(demo, "map_rviz.png"),
                                   trajectory=os.path.join(demo, "trajectory.tum"))
            rviz_png = shot["path"]
            _step("rviz screenshot (fusion node publishing the saved map, rviz under Xvfb): %s"
                  % rviz_png)
        except RuntimeError as e:
            _step("no rviz screenshot: %s" % str(e).splitlines()[0])
    traj_png = None
    if traj_res is not None:
        traj_png = plot_ate(traj_res, os.path.join(demo, "trajectory.png"),
                            title="trajectory vs ground truth (SE(3)-aligned)")
    report = _report(args, summary, m, traj_res, conf, time.time() - t_start,
                     [top, persp] + [p for p in (rviz_png, traj_png) if p])
    with open(os.path.join(demo, "report.md"), "w") as f:
        f.write(report)
    print(report)
    _step("done in %.0f s: %s" % (time.time() - t_start, demo))
    return 0


def _report(args, s, m, traj, conf, wall, pictures) -> str:
    t = s["timing"]
    fps = s["frames_in"] / max(s.get("wall_s", 1e-9), 1e-9)
    lines = ["# MDR-SLAM demo: the %s sample sequence" % args.scene, "",
             "Pose source: **%s**; temporal filter: %s; confidence fusion: %s." % (
                 s["pose_source"], "on" if s["temporal"] else "off",
                 "on" if s["confidence"] else "off"), "",
             "| | |", "|---|---|",
             "| frames in / posed / integrated / lost | %d / %d / %d / %d |" % (
                 s["frames_in"], s["frames_posed"], s["frames_integrated"], s["frames_lost"]),
             "| map points | %d |" % s["map_points"],
             "| offline throughput (one process, every frame) | %.1f frames/s |" % fps]
    for stage in ("pose", "depth.elas", "depth.filter", "fusion", "frame"):
        if stage in t:
            lines.append("| %s time per frame, median / p90 | %.1f / %.1f ms |" % (
                stage, t[stage]["median_ms"], t[stage]["p90_ms"]))
    if m is not None:
        lines.append("| map RMSE (estimated point to nearest true surface point) | %.4f m |"
                     % m["accuracy_rmse"])
        lines.append("| map completeness (true points with an estimate within 5 cm) | %.1f %% |"
                     % (100 * m["completeness"]))
        for k, v in m.get("per_label", {}).items():
            if v.get("accuracy_rmse") is not None:
                lines.append("| map RMSE / completeness on %s surfaces | %.4f m / %.1f %% |" % (
                    k.replace("_", "-"), v["accuracy_rmse"], 100 * v["completeness"]))
    if traj is not None and s["pose_source"] != "groundtruth":  # with true poses it is 0 by design
        st = traj.stats
        lines.append("| ATE RMSE (SE(3)-aligned) over %.1f m of path | %.4f m (%.2f %% of the path) |"
                     % (st["path_length"], st["rmse"], 100 * st["rmse"] / max(st["path_length"], 1e-9)))
    if conf is not None and len(conf):
        lines.append("| map point confidence, median / max | %d / %d |" % (
            int(np.median(conf)), int(np.max(conf))))
    lines.append("| demo wall time | %.0f s |" % wall)
    lines += ["", "Pictures: " + ", ".join("`%s`" % os.path.basename(p) for p in pictures), ""]
    return "\n".join(lines) + "\n"
