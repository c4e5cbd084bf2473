#!/usr/bin/env python3
"""Robustness and accuracy of the pose core (mdr_slam.pose.System) on simulated sequences.

    python scripts/eval_pose_sim.py [--out output/eval_pose_sim] [--sequences office_loop,office_loop@5,...]
                                    [--scale 1.0] [--rate 20] [--json FILE] [--no-compare]
                                    [--jobs 2] [--set KEY=VALUE] [--oracle-loops]
    python scripts/eval_pose_sim.py --sequences all --jobs 2    # docs/benchmarks.md's 13 sequences (7 min on 2 cores)

Every sequence is rendered once by ``mdr_slam.sim.generate`` (752x480 at 20 Hz by default; an
existing ``DIR/<name>/sequence.bag`` rendered with the same settings is reused) and tracked
offline (``System(threads=False)``, the parameters of config/pose.yaml, as ``mdr run``). Per
sequence: frames OK / LOST, LOST events and their recovery time (s from the first LOST frame to
the next tracked one; "never" when the sequence ends first), ATE (evo, SE(3) Umeyama) in metres
and as a share of the ground-truth path length, loop closures, and for loop sequences the ATE
with ``loop_closing: false`` (target: with <= half of without, ATE <= 1 % of the path); the
accepted loops (current, matched keyframe id) and each global BA after a loop (keyframes,
points, outliers, ms).
LOST frames inside each simulator segment (pure_rotation, corner) are counted separately.
Prints a Markdown table and writes JSON (default DIR/eval_pose_sim.json).

``--oracle-loops`` (a diagnostic, for loop sequences): each loop correction is scored against the
simulator's relative pose of the two keyframes (``loop_errors``: kf, matched kf, m, deg), and a
third run replaces every correction by the true one (``oracle``): when that run's ATE is no
better than the measured loops', the loop measurement is not what limits loop closing there.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "src", "mdr_slam", "src"))

# name: (scene, trajectory kind, duration s, seed, compare with loop closing off)
SEQUENCES = {
    "office_loop": ("office", "loop", 30.0, 1, True),
    "office_loop_rotation": ("office", "loop+pure_rotation", 30.0, 0, True),
    "office_pure_rotation": ("office", "pure_rotation", 10.0, 2, False),
    "corridor_corner": ("corridor", "corner", 15.0, 3, False),
    "garage_loop": ("garage", "loop", 30.0, 4, True),
}
DEFAULT = "office_loop,office_loop_rotation,office_pure_rotation,corridor_corner,garage_loop"
# other noise seeds of the same sequences: with the defaults, the 12 sequences (and the pure
# rotation) of the accuracy table in docs/benchmarks.md; chaotic figures need all of them to judge a change
SEEDS = ("office_loop@5,office_loop@6,office_loop@9,office_loop_rotation@7,office_loop_rotation@8,"
         "office_loop_rotation@10,corridor_corner@12,garage_loop@11")
ALIASES = {"default": DEFAULT, "seeds": SEEDS, "all": DEFAULT + "," + SEEDS}
TRACKED = ("OK", "RELOCALIZED")


def render(d: str, scene: str, kind: str, duration: float, seed: int, rate: float,
           scale: float) -> dict:
    """Render the sequence into ``d`` unless a bag with the same settings is already there."""
    import yaml
    from mdr_slam.sim import generate
    meta = os.path.join(d, "scene.yaml")
    want = {"scene": scene, "trajectory": kind, "duration": float(duration), "seed": int(seed)}
    if os.path.exists(os.path.join(d, "sequence.bag")) and os.path.exists(meta):
        with open(meta) as f:
            have = yaml.safe_load(f)
        cam = have.get("camera", {})
        if (all(have.get(k) == v for k, v in want.items()) and
                abs(float(cam.get("rate", 0)) - rate) < 1e-9 and
                int(cam.get("width", 0)) == int(round(752 * scale))):
            return {"rendered": False, "render_s": 0.0}
    t0 = time.perf_counter()
    generate(d, scene=scene, duration=duration, seed=seed, rate=rate, scale=scale,
             trajectory=kind)
    return {"rendered": True, "render_s": time.perf_counter() - t0}


def lost_events(stamps: np.ndarray, states: list) -> list:
    """[(t_start, t_recovered or None, frames)] of every LOST run after initialisation."""
    ev, start, n = [], None, 0
    for t, s in zip(stamps, states):
        if s == "LOST":
            if start is None:
                start, n = t, 0
            n += 1
        elif s in TRACKED and start is not None:
            ev.append((float(start), float(t), n))
            start = None
    if start is not None:
        ev.append((float(start), None, n))
    return ev


def first_pose_errors(est, gt):
    """(pos RMSE m, pos max m, rot RMSE deg, rot max deg) of ``est`` anchored on ``gt`` at the
    first associated pose (no least-squares alignment)."""
    from scipy.spatial.transform import Rotation
    from mdr_slam.pose.evaluate import associate
    i, j = associate(est, gt)
    if len(i) < 2:
        return (float("nan"),) * 4
    E = est.matrices()[i] if callable(est.matrices) else est.matrices[i]
    G = gt.matrices()[j] if callable(gt.matrices) else gt.matrices[j]
    A = G[0] @ np.linalg.inv(E[0])
    Ea = np.einsum("ij,njk->nik", A, E)
    dp = np.linalg.norm(Ea[:, :3, 3] - G[:, :3, 3], axis=1)
    dR = np.einsum("nji,njk->nik", G[:, :3, :3], Ea[:, :3, :3])
    ang = np.degrees(Rotation.from_matrix(dR).magnitude())
    return (float(np.sqrt(np.mean(dp ** 2))), float(dp.max()), float(np.sqrt(np.mean(ang ** 2))),
            float(ang.max()))


class LoopScorer:
    """Scores every loop correction against the simulator's poses, and with ``oracle`` replaces
    it by the true one (a diagnostic: what loop closing gives when the loop itself is exactly
    measured). The correction S moves the current keyframe to cand.T_wc T_ck kf.T_cw; its error
    is that of T_ck (the current keyframe seen from the matched one) against the truth's. Used as
    a context manager around one run (it wraps LoopClosing.correct_loop)."""

    def __init__(self, gt, oracle: bool):
        self.gt_stamps = gt.stamps
        self.gt_T = gt.matrices()
        self.oracle = oracle
        self.loops = []   # [kf id, cand id, error m, error deg]

    def _true(self, stamp):
        return self.gt_T[int(np.argmin(np.abs(self.gt_stamps - stamp)))]

    def __enter__(self):
        from scipy.spatial.transform import Rotation
        from mdr_slam.geometry import inv_T
        from mdr_slam.pose import loop_closing
        self._cls = loop_closing.LoopClosing
        self._orig = orig = self._cls.correct_loop
        scorer = self

        def correct_loop(lc, kf, cand, S, *args, **kw):
            T_true = inv_T(scorer._true(cand.stamp)) @ scorer._true(kf.stamp)
            D = inv_T(T_true) @ (cand.T_cw @ S @ kf.T_wc)
            scorer.loops.append([int(kf.id), int(cand.id), float(np.linalg.norm(D[:3, 3])),
                                 float(np.degrees(Rotation.from_matrix(D[:3, :3]).magnitude()))])
            if scorer.oracle:
                S = cand.T_wc @ T_true @ kf.T_cw
            return orig(lc, kf, cand, S, *args, **kw)

        self._cls.correct_loop = correct_loop
        return self

    def __exit__(self, *exc):
        self._cls.correct_loop = self._orig
        return False


def apply_tuned(values: dict) -> None:
    """``{"tracking.LOST_COAST_S": 0.0}``: the tracker's tuned constants (module of mdr_slam.pose
    and name) set in this process, for experiments with them."""
    import importlib
    for key, v in values.items():
        mod, _, name = key.partition(".")
        m = importlib.import_module("mdr_slam.pose." + mod)
        if not hasattr(m, name):
            raise SystemExit("--set %s: mdr_slam.pose.%s has no constant %s" % (key, mod, name))
        setattr(m, name, v)


def track(bag: str, params: dict, scorer: LoopScorer = None) -> dict:
    import contextlib
    from mdr_slam.pipeline import frames_from_bag
    from mdr_slam.pose import TrackerConfig, make_system
    camera, frames = frames_from_bag(bag)
    apply_tuned({k: v for k, v in params.items() if "." in k})
    # backend=orbslam3: ORB-SLAM3's tracker
    system = make_system(camera, TrackerConfig.pick(params), threads=False)
    stamps, states, ms = [], [], []
    r = None
    with (scorer if scorer is not None else contextlib.nullcontext()):
        try:
            for f in frames:
                r = system.track(f.stamp, f.left, f.right)
                stamps.append(f.stamp)
                states.append(r.state)
                ms.append(r.time_ms)
            traj = system.trajectory()
            mp = getattr(system, "map", None)
            n_loops = int(mp.n_loop_closures) if mp is not None else \
                (int(r.n_loop_closures) if r is not None else 0)
            lc = getattr(system, "loop_closing", None)
            gba = [{k: v for k, v in g.items() if k != "moved"}
                   for g in (getattr(lc, "global_ba_runs", []) if lc is not None else [])]
            loops = [list(x) for x in lc.loops] if lc is not None else []
            prox = [list(x) for x in getattr(lc, "proximity_loops", [])] if lc is not None else []
            n_kfs = len(mp.good_keyframes()) if mp is not None else 0
        finally:
            system.shutdown()
    return {"stamps": np.array(stamps), "states": states, "traj": traj, "loops": n_loops,
            "keyframes": n_kfs, "ms": np.array(ms), "global_ba": gba, "loop_pairs": loops,
            "proximity_loops": prox}


def evaluate(name: str, out: str, rate: float, scale: float, compare: bool,
             overrides: dict = None, oracle: bool = False) -> dict:
    import yaml
    from mdr_slam.eval import ate
    from mdr_slam.io import read_tum, write_tum
    from mdr_slam.pipeline import load_params
    base, _, seed_arg = name.partition("@")
    scene, kind, duration, seed, loop_seq = SEQUENCES[base]
    if seed_arg:   # NAME@SEED: the same sequence rendered with another noise seed
        seed = int(seed_arg)
        name = "%s_seed%d" % (base, seed)
    d = os.path.join(out, name)
    rinfo = render(d, scene, kind, duration, seed, rate, scale)
    with open(os.path.join(d, "scene.yaml")) as f:
        segments = yaml.safe_load(f).get("segments", [])
    gt = read_tum(os.path.join(d, "groundtruth.tum"))
    path = float(gt.path_length()) if callable(gt.path_length) else float(gt.path_length)
    params = dict(load_params("pose"), **(overrides or {}))
    res = {"sequence": name, "scene": scene, "trajectory": kind, "duration_s": duration,
           "seed": seed, "rate_hz": rate, "scale": scale, "path_length_m": path,
           "param_overrides": dict(overrides or {}), **rinfo}
    runs = [("lc", True)] + ([("no_lc", False)] if (compare and loop_seq) else []) + \
        ([("oracle", True)] if (oracle and loop_seq) else [])
    for tag, lc in runs:
        p = dict(params, loop_closing=lc)
        t0 = time.perf_counter()
        scorer = LoopScorer(gt, tag == "oracle") if (oracle and lc) else None
        r = track(os.path.join(d, "sequence.bag"), p, scorer)
        wall = time.perf_counter() - t0
        write_tum(os.path.join(d, "trajectory_%s.tum" % tag), r["traj"])
        states = r["states"]
        n_ok = sum(s in TRACKED for s in states)
        ev = lost_events(r["stamps"], states)
        a = {"rmse": float("nan")}
        if path >= 0.05 and len(r["traj"]) >= 3:
            try:
                a = ate(r["traj"], gt).stats
            except Exception as e:   # evo refuses degenerate alignments
                a = {"rmse": float("nan"), "error": str(e)}
        drift = first_pose_errors(r["traj"], gt)
        seg = []
        for s in segments:
            m = (r["stamps"] >= s["t0"]) & (r["stamps"] < s["t1"])
            seg.append({"name": s["name"], "t0": s["t0"], "t1": s["t1"],
                        "frames": int(np.count_nonzero(m)),
                        "lost": int(sum(st == "LOST" for st, k in zip(states, m) if k))})
        res[tag] = {
            "frames": len(states), "ok": n_ok,
            "lost": sum(s == "LOST" for s in states),
            "not_initialized": sum(s == "NOT_INITIALIZED" for s in states),
            "lost_events": [{"t_lost": a_, "t_recovered": b_, "frames": n_,
                             "recovery_s": (None if b_ is None else b_ - a_)}
                            for a_, b_, n_ in ev],
            "ate_rmse_m": float(a["rmse"]),
            "ate_percent_path": 100.0 * float(a["rmse"]) / path if path > 0 else float("nan"),
            "ate_max_m": float(a.get("max", float("nan"))),
            # anchored at the first tracked pose, no fitting (the figure for pure rotation,
            # where there is no path to align on): position and rotation error, RMSE and max
            "anchored_pos_rmse_m": drift[0], "anchored_pos_max_m": drift[1],
            "anchored_rot_rmse_deg": drift[2], "anchored_rot_max_deg": drift[3],
            "loop_closures": r["loops"], "keyframes": r["keyframes"],
            "loop_keyframe_pairs": r["loop_pairs"], "global_ba": r["global_ba"],
            # loops found by the proximity path (current kf, matched kf, PnP inliers)
            "proximity_loops": r["proximity_loops"],
            "segments": seg, "wall_s": wall,
            "track_ms_median": float(np.median(r["ms"])),
            "track_ms_p90": float(np.percentile(r["ms"], 90)),
        }
        if scorer is not None:   # each loop's error against the simulator's relative pose
            res[tag]["loop_errors"] = scorer.loops
    if "no_lc" in res:
        a1, a0 = res["lc"]["ate_rmse_m"], res["no_lc"]["ate_rmse_m"]
        res["lc_over_no_lc"] = a1 / a0 if a0 > 0 else float("nan")
        if "oracle" in res:
            a2 = res["oracle"]["ate_rmse_m"]
            res["oracle_over_no_lc"] = a2 / a0 if a0 > 0 else float("nan")
    return res


def oracle_table(results: list) -> str:
    """--oracle-loops: ATE with the loops as measured, with the true loops, and without."""
    rows = ["| sequence | loops as measured: error of each (m / deg) | ATE LC m | ATE true loops m | "
            "ATE no LC m | LC / no LC | true loops / no LC |", "|---|---|---|---|---|---|---|"]
    for r in results:
        if "oracle" not in r:
            continue
        errs = ", ".join("%d-%d %.3f / %.2f" % tuple(e) for e in r["lc"].get("loop_errors", []))
        nl = r.get("no_lc")
        rows.append("| %s | %s | %.4f | %.4f | %s | %s | %s |" % (
            r["sequence"], errs or "none", r["lc"]["ate_rmse_m"], r["oracle"]["ate_rmse_m"],
            "%.4f" % nl["ate_rmse_m"] if nl else "-",
            "%.2f" % r["lc_over_no_lc"] if nl else "-",
            "%.2f" % r["oracle_over_no_lc"] if nl else "-"))
    return "\n".join(rows)


def expand_sequences(spec: str) -> list:
    """Sequence names of a --sequences value: comma-separated names, NAME@SEED, and the aliases
    default, seeds and all (default + seeds), in order, each once."""
    names = []
    for item in (x.strip() for x in spec.split(",")):
        for n in (ALIASES[item].split(",") if item in ALIASES else [item]):
            if n and n not in names:
                names.append(n)
    return names


def summary(results: list) -> str:
    """Mean and max ATE (% of the path) over the sequences that have a path, and the loop ratios
    (LC / no LC): the figures to hold a change against over several seeds."""
    pct = [(r["sequence"], r["lc"]["ate_percent_path"]) for r in results
           if np.isfinite(r["lc"]["ate_percent_path"])]
    out = []
    if pct:
        v = np.array([x for _, x in pct])
        worst = max(pct, key=lambda x: x[1])
        out.append("ATE %% of the path over %d sequences: mean %.3f, max %.2f (%s), %d above 1 %%"
                   % (len(v), v.mean(), worst[1], worst[0], int(np.sum(v > 1.0))))
    ratios = [r["lc_over_no_lc"] for r in results if "lc_over_no_lc" in r]
    if ratios:
        out.append("loop closing, ATE with / without: %s (%d of %d at most 0.5)" % (
            ", ".join("%.2f" % x for x in ratios), sum(x <= 0.5 for x in ratios), len(ratios)))
    return "\n".join(out)


def _evaluate_job(args):
    return evaluate(*args)


def _fmt_events(ev: list) -> str:
    if not ev:
        return "0"
    rec = ["never" if e["recovery_s"] is None else "%.2f" % e["recovery_s"] for e in ev]
    return "%d (%s s)" % (len(ev), ", ".join(rec[:4]) + (", ..." if len(rec) > 4 else ""))


def table(results: list) -> str:
    rows = ["| sequence | frames | OK | LOST | LOST events (recovery) | LOST in segments | "
            "ATE m | ATE % path | path m | anchored pos / rot RMSE | loops | ATE no LC m | LC / no LC |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        a = r["lc"]
        segs = ", ".join("%s %d/%d" % (s["name"], s["lost"], s["frames"]) for s in a["segments"]
                         if s["name"] not in ("loop", "drive")) or "-"
        nl = r.get("no_lc")
        rows.append("| %s | %d | %d | %d | %s | %s | %.4f | %.2f | %.2f | %.3f m / %.2f deg | %d | %s | %s |" % (
            r["sequence"], a["frames"], a["ok"], a["lost"], _fmt_events(a["lost_events"]), segs,
            a["ate_rmse_m"], a["ate_percent_path"], r["path_length_m"], a["anchored_pos_rmse_m"],
            a["anchored_rot_rmse_deg"], a["loop_closures"],
            "%.4f" % nl["ate_rmse_m"] if nl else "-",
            "%.2f" % r["lc_over_no_lc"] if nl else "-"))
    return "\n".join(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=os.path.join(ROOT, "output", "eval_pose_sim"))
    ap.add_argument("--sequences", default=DEFAULT,
                    help="comma-separated, of: %s; NAME@SEED renders NAME with another noise "
                    "seed (several seeds give the spread of a chaotic figure); 'seeds' the 8 "
                    "other seeds of the benchmarks table, 'all' the defaults and those"
                    % ", ".join(SEQUENCES))
    ap.add_argument("--jobs", type=int, default=1,
                    help="sequences evaluated at once, one process each (2 on a 2-core machine "
                    "halves the time; the figures are the same, the ms per frame are not)")
    ap.add_argument("--rate", type=float, default=20.0)
    ap.add_argument("--scale", type=float, default=1.0, help="image scale (1: 752x480)")
    ap.add_argument("--no-compare", action="store_true",
                    help="skip the loop_closing: false runs")
    ap.add_argument("--oracle-loops", action="store_true",
                    help="diagnostic: score every loop correction against the simulator's poses "
                    "and add a run whose loop corrections are the true ones (what loop closing "
                    "gives when the loop itself is exactly measured)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a tracker parameter of config/pose.yaml (repeatable), e.g. "
                    "n_features=1000, or a tuned constant, e.g. local_mapping.BA_TOL=0")
    a = ap.parse_args(argv)
    names = expand_sequences(a.sequences)
    bad = [n for n in names if n.partition("@")[0] not in SEQUENCES or
           not (n.partition("@")[2] or "0").isdigit()]
    if bad:
        ap.error("unknown sequences %s (known: %s)" % (bad, ", ".join(SEQUENCES)))
    import yaml
    overrides = {}
    for item in a.set:
        k, sep, v = item.partition("=")
        if not sep:
            ap.error("--set wants KEY=VALUE: %r" % item)
        overrides[k.strip()] = yaml.safe_load(v)
    from mdr_slam.pose import TrackerConfig
    bad = [k for k in overrides if "." not in k and k not in TrackerConfig.keys()]
    if bad:
        ap.error("--set: no tracker parameter %s (known: %s)" % (bad, ", ".join(TrackerConfig.keys())))
    os.makedirs(a.out, exist_ok=True)
    results = []
    jobs = [(n, a.out, a.rate, a.scale, not a.no_compare, overrides, a.oracle_loops)
            for n in names]
    if a.jobs > 1 and len(jobs) > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor
        # not multiprocessing.Pool: its daemonic workers may not start the renderer's processes
        pool = ProcessPoolExecutor(min(a.jobs, len(jobs)), multiprocessing.get_context("spawn"))
        done = pool.map(_evaluate_job, jobs)
    else:
        pool, done = None, map(_evaluate_job, jobs)
    try:
        for n, r in zip(names, done):
            print("== %s" % n, flush=True)
            results.append(r)
            print(json.dumps({k: v for k, v in r["lc"].items() if k != "segments"}), flush=True)
    finally:
        if pool is not None:
            pool.shutdown()
    print()
    print(table(results))
    print()
    print(summary(results))
    if a.oracle_loops:
        print()
        print(oracle_table(results))
    path = a.json or os.path.join(a.out, "eval_pose_sim.json")
    with open(path, "w") as f:
        json.dump(results, f, indent=1)
    print("\nwrote %s" % path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
