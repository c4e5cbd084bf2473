#!/usr/bin/env python3
"""The sparse map on a long patrol, offline, fed by the simulator directly (no bag to store).

The office loop driven lap after lap (``make_trajectory(..., laps=N)``: each lap's path a little
different, fresh sensor noise), tracked by ``System(threads=False)`` as ``mdr run`` tracks, with
the default pose configuration. Per lap: frames tracked, keyframes alive and created, loops closed,
global BAs, BoW database entries, process RSS, tracking CPU (thread time of ``track()``) and its
median / p90 per frame; at the end each lap's ATE, the first lap's ATE as a one-lap run has it,
and the whole run's. A JSON line per lap as it ends, the whole in ``--out``.

    python scripts/patrol_laps.py --laps 60 --seed 6 --scale 0.5 --out patrol.json   # 30 minutes
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "src", "mdr_slam", "src"))

import numpy as np  # noqa: E402

from mdr_slam.eval.timeline import process_rss_mb  # noqa: E402
from mdr_slam.io import Trajectory  # noqa: E402
from mdr_slam.pipeline import load_params  # noqa: E402
from mdr_slam.pose import System, TrackerConfig  # noqa: E402
from mdr_slam.pose.evaluate import ate_rmse  # noqa: E402
from mdr_slam.sim.render import Simulator, sim_camera  # noqa: E402
from mdr_slam.sim.scene import make_scene  # noqa: E402
from mdr_slam.sim.trajectory import make_trajectory  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--laps", type=int, default=10)
    ap.add_argument("--lap-s", type=float, default=30.0, help="seconds per lap (default 30)")
    ap.add_argument("--seed", type=int, default=6, help="scene, path and noise seed (default 6)")
    ap.add_argument("--scale", type=float, default=1.0,
                    help="image scale (0.5: 376x240, renders in about real time on one core)")
    ap.add_argument("--rate", type=float, default=20.0)
    ap.add_argument("--out", default="patrol_laps.json")
    a = ap.parse_args(argv)
    scene = make_scene("office", seed=a.seed)
    cam = sim_camera(scale=a.scale)
    stamps, poses = make_trajectory(scene, a.lap_s, a.rate, seed=a.seed, scene=scene, laps=a.laps)
    sim = Simulator(scene, cam, seed=a.seed, noise=2.0)
    s = System(cam, config=TrackerConfig.pick(load_params("pose")), threads=False)
    n_lap = int(round(a.lap_s * a.rate))
    gt = Trajectory.from_matrices(stamps, poses)
    out = dict(seed=a.seed, scale=a.scale, lap_s=a.lap_s, laps=[])
    tracked, cpu, ms, w0 = 0, 0.0, [], time.perf_counter()
    for i, (t, T) in enumerate(zip(stamps, poses)):
        im = sim.render(T, index=i, depth=False)
        c0 = time.thread_time()
        res = s.track(float(t), im["left"], im["right"])
        c1 = time.thread_time()
        cpu += c1 - c0
        ms.append(1000.0 * (c1 - c0))
        tracked += res.state in ("OK", "RELOCALIZED")
        if (i + 1) % n_lap:
            continue
        mp, lc = s.map, s.loop_closing
        lap = dict(lap=len(out["laps"]) + 1, frames=n_lap, tracked=tracked,
                   alive=len(mp.good_keyframes()), created=mp.next_kf_id,
                   loops=mp.n_loop_closures, global_bas=len(lc.global_ba_runs) if lc else 0,
                   bow_db=len(lc.db.bows) if lc else 0, rss_mb=round(process_rss_mb(), 1),
                   track_cpu_s=round(cpu, 2), track_ms_median=round(float(np.median(ms)), 1),
                   track_ms_p90=round(float(np.percentile(ms, 90)), 1),
                   wall_s=round(time.perf_counter() - w0, 1))
        out["laps"].append(lap)
        if lap["lap"] == 1:   # the tracker is causal: this is a one-lap run's trajectory
            out["lap1_alone_ate_m"] = ate_rmse(s.trajectory(), gt)
        print(json.dumps(lap), flush=True)
        tracked, cpu, ms, w0 = 0, 0.0, [], time.perf_counter()
    traj = s.trajectory()
    s.shutdown()
    ts = traj.stamps
    for k, lap in enumerate(out["laps"]):
        sel = (ts >= stamps[k * n_lap]) & (ts <= stamps[(k + 1) * n_lap - 1])
        lap["ate_m"] = ate_rmse(Trajectory.from_matrices(ts[sel], traj.matrices()[sel]), gt) \
            if np.any(sel) else None
    out["whole_ate_m"] = ate_rmse(traj, gt)
    with open(a.out, "w") as f:
        json.dump(out, f, indent=1)
    print("lap ATE (m):", [None if l["ate_m"] is None else round(l["ate_m"], 3)
                           for l in out["laps"]])
    print("first lap alone %.3f m, whole run %.3f m -> %s" % (
        out["lap1_alone_ate_m"], out["whole_ate_m"], a.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
