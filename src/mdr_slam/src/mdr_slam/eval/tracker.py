"""Tracker benchmark: the built-in tracker (``mdr``) against ORB-SLAM3 (``orbslam3``, pyorbslam3).

What ``mdr bench --compare`` holds the built-in tracker to, on the same input in the same call.

Offline (:func:`compare_trackers`): each backend over the same frames, read and rectified first
so the clock covers the tracker only, with the BLAS and OpenCV thread limits of the pose node
(:func:`mdr_slam.pose.factory.library_threads`). Per run:

- CPU per frame of the whole process while it tracks, every thread and child process included
  (ORB extraction, tracking, LocalMapping, LoopClosing, the built-in tracker's worker
  processes; ``getrusage``), from the first frame to the end of ``shutdown`` (which waits for
  the mapping threads and the children). It is not split into tracking and
  mapping: ORB-SLAM3 extracts ORB in threads of its own, so such a split would not compare.
  ORB-SLAM3 always runs its mapping threads. The built-in tracker runs twice: as ``mdr run`` runs
  it (``mdr``: ``threads=False``, mapping inside ``track`` after every frame, so it makes every
  keyframe its rules ask for; frames back to back) and as the pose node and ORB-SLAM3 run
  (``mdr-threads``: LocalMapping and LoopClosing in their threads, so a keyframe is skipped while
  mapping is busy, as ORB-SLAM2's NeedNewKeyFrame does). The threaded trackers get their frames
  at the stream rate (the stamps), as ORB-SLAM3's example programs feed it: a frame is passed
  when its time has come or, when tracking lags, as soon as the previous one is done. The CPU comparison with
  ORB-SLAM3 is made between the two threaded runs; the live ATE is held to ``mdr``'s.
- wall milliseconds per ``track`` call (median, p90);
- frames tracked, frames LOST, and ATE (evo, SE(3) Umeyama) of the poses as returned frame by
  frame (what the pose node publishes on /mdr/pose) and of the final trajectory (after later
  local BA and loop corrections: what ``mdr run`` saves), in metres and as a share of the
  ground-truth path.

Live (:func:`live_summary`, :func:`compare_targets`): the figures of ``mdr bench BAG`` runs
(their ``bench.json``) per backend, median and spread over the runs, the live ATE against the
same backend's offline ATE, and the built-in tracker's targets (:data:`TARGETS`).
:func:`compare_report_markdown` writes the whole comparison.
"""
from __future__ import annotations

import os
import pickle
import resource
import subprocess
import sys
import time
from collections import OrderedDict
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..io import Trajectory
from ..pipeline import frames_from_bag, frames_from_dataset, load_params
from ..pose import TrackerConfig, make_system
from ..pose.factory import library_threads
from ..pose.orbslam3 import available as orbslam3_available, import_error as orbslam3_error
from .trajectory import ate

__all__ = ["load_sequence", "run_tracker", "compare_trackers", "compare_markdown", "BACKENDS",
           "available_backends", "live_run_figures", "live_summary", "compare_targets",
           "compare_report_markdown", "TARGETS"]

BACKENDS = ("mdr", "orbslam3")
MDR_THREADS = "mdr-threads"   # the built-in tracker with its mapping threads (run with ``mdr``)


def available_backends(backends: Sequence[str] = BACKENDS) -> Tuple[List[str], List[str]]:
    """``(backends that can run, notes on those that cannot)``: ``orbslam3`` needs pyorbslam3."""
    ok, notes = [], []
    for b in backends:
        if b == "orbslam3" and not orbslam3_available():
            notes.append("pyorbslam3 is missing (%s): ORB-SLAM3 (`orbslam3`) was not run"
                         % orbslam3_error())
            continue
        ok.append(b)
    return ok, notes


def load_sequence(source: str, kind: str = "bag", max_frames: Optional[int] = None,
                  bag_options: Optional[dict] = None):
    """``(camera, stamps, frames, ground truth, preset)`` of a bag (with its ground-truth pose
    topic) or a KITTI / EuRoC folder: the frames rectified, in memory. ``preset``: the dataset's
    parameter overlay (config/<preset>/pose.yaml), None for a bag. ``bag_options``: keyword
    arguments of :func:`mdr_slam.pipeline.frames_from_bag` (``topics``, ``image_transport``,
    ``sync_tolerance``, ``rectified``)."""
    if kind == "bag":
        camera, it = frames_from_bag(source, max_frames=max_frames, ground_truth=True,
                                     **(bag_options or {}))
        preset = None
    elif kind in ("kitti", "euroc"):
        camera, it = frames_from_dataset(kind, source, max_frames)
        preset = kind
    else:
        raise ValueError("kind must be bag, kitti or euroc, not %r" % (kind,))
    stamps, frames, gts, gt_stamps = [], [], [], []
    for f in it:
        stamps.append(float(f.stamp))
        frames.append(camera.rectify(f.left, f.right))
        if f.T_map_cam_gt is not None:
            gt_stamps.append(float(f.stamp))
            gts.append(np.asarray(f.T_map_cam_gt, float))
    if not frames:
        raise ValueError("%s: no stereo frame" % source)
    gt = Trajectory.from_matrices(np.array(gt_stamps), np.array(gts)) if len(gts) >= 3 else None
    return camera, np.array(stamps), frames, gt, preset


def _ate(traj: Trajectory, gt: Optional[Trajectory]) -> Optional[float]:
    if gt is None or len(traj) < 3:
        return None
    try:
        return float(ate(traj, gt, max_diff=0.02).stats["rmse"])
    except Exception:   # noqa: BLE001 - too few associated poses, degenerate alignment
        return None


def _cpu_seconds() -> float:
    """CPU seconds of this process and of its ended children (the built-in tracker's frame and
    bundle-adjustment worker processes, once ``shutdown`` has waited for them)."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def run_tracker(camera, stamps, frames, gt=None, backend: str = "mdr",
                params: Optional[dict] = None, preset: Optional[str] = None,
                threads: bool = False) -> Dict[str, object]:
    """Track ``frames`` (rectified pairs) with one backend; the figures of the module docstring.
    ``params``: pose.yaml overrides (tracker keys); ``threads``: the built-in tracker's mapping
    in its threads (ORB-SLAM3 always runs them)."""
    pp = load_params("pose", preset)
    pp.update(params or {})
    pp["backend"] = backend
    system = make_system(camera, TrackerConfig.pick(pp), threads=bool(threads))
    pub_t, pub_T, states, wall = [], [], [], []
    p0 = _cpu_seconds()
    w0 = time.perf_counter()
    for stamp, (left, right) in zip(stamps, frames):
        t0 = time.perf_counter()
        if threads or backend != "mdr":
            # a threaded tracker gets its frames at the stream rate, as ORB-SLAM3's example
            # programs feed it (a frame back to back would leave its mapping threads behind)
            wait = (float(stamp) - float(stamps[0])) - (t0 - w0)
            if wait > 0:
                time.sleep(wait)
                t0 = time.perf_counter()
        res = system.track(float(stamp), left, right)
        wall.append(1000.0 * (time.perf_counter() - t0))
        states.append(str(res.state))
        if res.T_map_cam is not None:
            pub_t.append(float(stamp))
            pub_T.append(np.asarray(res.T_map_cam, float))
    system.shutdown()   # waits for its child processes, so their CPU is counted below
    cpu_total = 1000.0 * (_cpu_seconds() - p0)
    elapsed = time.perf_counter() - w0
    n = len(frames)
    published = Trajectory.from_matrices(np.array(pub_t), np.array(pub_T)) if pub_t else None
    final = system.trajectory()
    path = float(gt.path_length()) if gt is not None else None
    out = OrderedDict()
    out["backend"] = MDR_THREADS if (backend == "mdr" and threads) else backend
    out["frames"] = n
    out["tracked"] = int(sum(s in ("OK", "RELOCALIZED") for s in states))
    out["lost"] = int(sum(s == "LOST" for s in states))
    out["cpu_ms_per_frame"] = cpu_total / n
    out["track_wall_ms"] = {"median": float(np.median(wall)), "p90": float(np.percentile(wall, 90))}
    out["elapsed_s"] = elapsed
    out["path_m"] = path
    out["ate_published_m"] = _ate(published, gt) if published is not None else None
    out["ate_final_m"] = _ate(final, gt)
    for k in ("published", "final"):
        a = out["ate_%s_m" % k]
        out["ate_%s_pct" % k] = 100.0 * a / path if (a is not None and path) else None
    return out


def run_tracker_in_child(source: str, kind: str, max_frames: Optional[int],
                         bag_options: Optional[dict], backend: str, params: Optional[dict],
                         threads: bool) -> Dict[str, object]:
    """:func:`run_tracker` in a fresh Python process that reads the sequence itself, with the
    pose node's thread limits. ORB-SLAM3 keeps process-wide state from its first camera (its
    Frame's image bounds and grid are computed once, ids are static counters), so a second
    ORB-SLAM3 with another image size in the same process loses track; one process per run also
    leaves nothing behind in the caller. A plain ``python -c`` child, not multiprocessing, so the
    caller's main script is never re-imported."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([p for p in sys.path if p] + [env.get("PYTHONPATH", "")])
    job = pickle.dumps((source, kind, max_frames, bag_options, backend, params, threads))
    proc = subprocess.run([sys.executable, "-c",
                           "from mdr_slam.eval.tracker import _child_main; _child_main()"],
                          input=job, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    if proc.returncode != 0:
        raise RuntimeError("%s tracker run failed (exit %d): %s" % (
            backend, proc.returncode, proc.stderr.decode(errors="replace")[-2000:]))
    return pickle.loads(proc.stdout)


def _child_main() -> None:
    """The child of :func:`run_tracker_in_child`: the job on stdin, the result on stdout (the
    trackers' own prints go to stderr)."""
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    source, kind, max_frames, bag_options, backend, params, threads = pickle.load(sys.stdin.buffer)
    with library_threads():
        camera, stamps, frames, gt, preset = load_sequence(source, kind, max_frames, bag_options)
        r = run_tracker(camera, stamps, frames, gt, backend=backend, params=params,
                        preset=preset, threads=threads)
    pickle.dump(r, out, protocol=pickle.HIGHEST_PROTOCOL)
    out.flush()


def _spread(values: Sequence[Optional[float]]) -> Dict[str, Optional[float]]:
    v = np.array([x for x in values if x is not None], float)
    if len(v) == 0:
        return {"median": None, "min": None, "max": None}
    return {"median": float(np.median(v)), "min": float(v.min()), "max": float(v.max())}


FIGURES = ("cpu_ms_per_frame", "ate_published_m", "ate_final_m", "ate_published_pct",
           "ate_final_pct")


def compare_trackers(source: str, kind: str = "bag", backends: Sequence[str] = BACKENDS,
                     runs: int = 3, max_frames: Optional[int] = None,
                     params: Optional[dict] = None, log=None,
                     bag_options: Optional[dict] = None) -> Dict[str, object]:
    """Every backend ``runs`` times on the same frames, alternating (a load spike on a shared
    machine then falls on both); per backend each figure's median, min and max over the runs,
    and the ratios of the built-in tracker's medians to ORB-SLAM3's. A backend that cannot run
    (``orbslam3`` without pyorbslam3) is left out and ``notes`` says why. While it runs, this
    process's BLAS and OpenCV threads are limited as the pose node limits them, so the CPU per
    frame is the node's; the previous limits are restored after. Each ORB-SLAM3 run is a process
    of its own (:func:`run_tracker_in_child`). ``params``: pose.yaml overrides; ``bag_options``:
    see :func:`load_sequence`."""
    if int(runs) < 1:
        raise ValueError("runs must be at least 1, not %r" % (runs,))
    backends, notes = available_backends(backends)
    if not backends:
        raise ValueError("no pose backend to run")
    with library_threads() as why:
        if why:
            notes.append("BLAS threads not limited (%s): the pose node would warn the same" % why)
        return _compare(source, kind, backends, notes, runs, max_frames, params, log,
                        bag_options)


def _compare(source, kind, backends, notes, runs, max_frames, params, log, bag_options):
    camera, stamps, frames, gt, preset = load_sequence(source, kind, max_frames, bag_options)
    params = dict(params or {})
    params.pop("backend", None)   # each run names its own
    modes = []   # (name, backend, threads)
    for b in backends:
        modes.append((b, b, b != "mdr"))
        if b == "mdr":
            modes.append((MDR_THREADS, "mdr", True))
    per: Dict[str, List[dict]] = {name: [] for name, _, _ in modes}
    for i in range(int(runs)):
        for name, b, threads in modes:
            if b == "orbslam3":   # a process of its own per run (see run_tracker_in_child)
                r = run_tracker_in_child(source, kind, max_frames, bag_options, b, params,
                                         threads)
            else:
                r = run_tracker(camera, stamps, frames, gt, backend=b, params=params,
                                preset=preset, threads=threads)
            per[name].append(r)
            if log is not None:
                log("  %s run %d/%d: CPU %.1f ms/frame, ATE published %s, final %s, tracked %d/%d"
                    % (name, i + 1, runs, r["cpu_ms_per_frame"], _m(r["ate_published_m"]),
                       _m(r["ate_final_m"]), r["tracked"], r["frames"]))
    rep = OrderedDict()
    rep["source"] = source
    rep["kind"] = kind
    rep["frames"] = len(frames)
    rep["path_m"] = float(gt.path_length()) if gt is not None else None
    rep["runs"] = int(runs)
    rep["notes"] = notes
    rep["backends"] = OrderedDict()
    for b, rs in per.items():
        s = OrderedDict((k, _spread([r[k] for r in rs])) for k in FIGURES)
        s["track_wall_ms_median"] = _spread([r["track_wall_ms"]["median"] for r in rs])
        s["tracked"] = [r["tracked"] for r in rs]
        s["lost"] = [r["lost"] for r in rs]
        rep["backends"][b] = s
    if "mdr" in per and "orbslam3" in per:
        # CPU: both with their mapping threads; ATE: mdr run's synchronous tracker
        rep["ratio_mdr_to_orbslam3"] = OrderedDict(
            (k, _ratio(rep["backends"][MDR_THREADS if k == "cpu_ms_per_frame" else "mdr"][k]
                       ["median"], rep["backends"]["orbslam3"][k]["median"]))
            for k in ("cpu_ms_per_frame", "ate_published_m", "ate_final_m"))
    rep["per_run"] = per
    return rep


def _ratio(a, b) -> Optional[float]:
    return float(a) / float(b) if (a is not None and b) else None


def _m(v) -> str:
    return "-" if v is None else "%.3f m" % v


def _cell(s: Dict[str, Optional[float]], fmt: str) -> str:
    if s["median"] is None:
        return "-"
    if fmt % s["min"] == fmt % s["max"]:   # no spread at this precision
        return fmt % s["median"]
    return (fmt + " (" + fmt + "-" + fmt + ")") % (s["median"], s["min"], s["max"])


def compare_markdown(rep: Dict[str, object]) -> str:
    """The comparison table of :func:`compare_trackers`: median (min-max) over the runs."""
    bs = list(rep["backends"])
    lines = ["Offline tracking of `%s` (%d frames, ground-truth path %s), %d run%s per backend, "
             "median (min-max):" % (rep["source"], rep["frames"],
                                    "-" if rep["path_m"] is None else "%.2f m" % rep["path_m"],
                                    rep["runs"], "" if rep["runs"] == 1 else "s"), "",
             "| | " + " | ".join("`%s`" % b for b in bs) + " |",
             "|---|" + "---|" * len(bs)]
    rows = [("CPU ms per frame, whole process", "cpu_ms_per_frame", "%.1f"),
            ("track call wall ms, median", "track_wall_ms_median", "%.1f"),
            ("ATE of the poses as published, m", "ate_published_m", "%.3f"),
            ("ATE of the poses as published, % of the path", "ate_published_pct", "%.2f"),
            ("ATE of the final trajectory, m", "ate_final_m", "%.3f"),
            ("ATE of the final trajectory, % of the path", "ate_final_pct", "%.2f")]
    for name, k, fmt in rows:
        lines.append("| %s | %s |" % (name, " | ".join(_cell(rep["backends"][b][k], fmt) for b in bs)))
    lines.append("| frames tracked (per run) / LOST | %s |" % " | ".join(
        "%s / %s" % (",".join(map(str, rep["backends"][b]["tracked"])),
                     ",".join(map(str, rep["backends"][b]["lost"]))) for b in bs))
    ratio = rep.get("ratio_mdr_to_orbslam3")
    if ratio:
        lines += ["", "`%s` / `orbslam3` CPU per frame (medians; both with their mapping "
                  "threads): %s. `mdr` / `orbslam3`: ATE as published %s, final ATE %s."
                  % ((MDR_THREADS,) + tuple("-" if ratio[k] is None else "%.2fx" % ratio[k]
                                                  for k in ("cpu_ms_per_frame", "ate_published_m",
                                                            "ate_final_m")))]
    for note in rep.get("notes") or []:
        lines += ["", "Note: %s." % note]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------- live runs and targets
# (figure key, row label, format) of the live table; each cell: median (min-max) over the runs
LIVE_ROWS = (
    ("frames_tracked", "frames tracked", "%.0f"),
    ("tracked_pct", "frames tracked, % of the bag's stereo pairs", "%.1f"),
    ("lost", "frames LOST", "%.0f"),
    ("live_ate_m", "live ATE (poses as published), m", "%.3f"),
    ("live_ate_pct", "live ATE, % of the ground-truth path", "%.2f"),
    ("map_hz", "map integrations, Hz", "%.2f"),
    ("latency_ms_median", "latency image stamp -> map, median ms", "%.0f"),
    ("rss_mb_total_max", "RSS of the three nodes, max MB", "%.0f"),
    ("cpu_percent_total_median", "CPU % of the three nodes, median", "%.0f"),
)

# the built-in tracker's targets: key -> (what, comparison, limit, unit); the figure is the
# median over the runs, except LOST frames: the worst run
TARGETS = OrderedDict([
    ("tracked_pct", ("frames tracked, % of the bag's stereo pairs", ">=", 95.0, " %")),
    ("lost", ("frames LOST (worst run)", "<=", 0, "")),
    ("live_ate_pct", ("live ATE, % of the ground-truth path", "<=", 1.5, " %")),
    ("live_to_offline_published", ("live ATE / offline ATE as published", "<=", 1.5, "x")),
    ("map_hz", ("map integrations", ">=", 5.0, " Hz")),
    ("latency_ms_median", ("latency image stamp -> map, median", "<=", 250.0, " ms")),
    ("rss_mb_total_max", ("RSS of the three nodes, max (1 GB = 1000 MB)", "<=", 1000.0, " MB")),
    ("cpu_percent_total_median", ("CPU of the three nodes, median", "<=", 190.0, " %")),
    ("offline_cpu_to_orbslam3", ("offline CPU per frame / ORB-SLAM3's (both with mapping threads)", "<=",
                                1.5, "x")),
])


def _get(d, *keys):
    for k in keys:
        if not isinstance(d, dict) or d.get(k) is None:
            return None
        d = d[k]
    return d


def live_run_figures(bench: dict, path_m: Optional[float] = None) -> Dict[str, Optional[float]]:
    """The figures of one live run (its ``bench.json``) that the comparison reports. ``path_m``:
    the ground-truth path length when the run has none of its own (``live_ate.gt_path_m``)."""
    out = OrderedDict()
    pairs = bench.get("frames_in_bag")
    tracked = bench.get("frames_tracked")
    out["pairs"] = pairs
    out["frames_tracked"] = tracked
    out["tracked_pct"] = (100.0 * tracked / pairs) if (tracked is not None and pairs) else None
    out["lost"] = int((bench.get("tracking_states") or {}).get("LOST", 0))
    rmse = _get(bench, "live_ate", "rmse_m")
    path = _get(bench, "live_ate", "gt_path_m") or path_m
    out["live_ate_m"] = rmse
    out["gt_path_m"] = path
    out["live_ate_pct"] = (100.0 * rmse / path) if (rmse is not None and path) else None
    out["map_hz"] = bench.get("map_integration_hz")
    out["latency_ms_median"] = _get(bench, "latency_ms", "median")
    out["rss_mb_total_max"] = _get(bench, "rss_mb", "total", "max")
    out["cpu_percent_total_median"] = _get(bench, "cpu_percent", "total", "median")
    return out


def live_summary(runs: Dict[str, List[Optional[dict]]],
                 offline: Optional[dict] = None) -> Dict[str, object]:
    """Per backend, from its live runs (``bench.json`` dicts; None for a run that failed): each
    figure's median, min and max over the runs that succeeded, and the median live ATE over the
    same backend's median offline ATE, as published and final (``offline``: a
    :func:`compare_trackers` report of the same input)."""
    path_m = offline.get("path_m") if offline else None
    out = OrderedDict()
    for b, benches in runs.items():
        figs = [live_run_figures(x, path_m) for x in benches if x is not None]
        s = OrderedDict()
        s["runs"] = len(figs)
        s["failed"] = len(benches) - len(figs)
        s["pairs"] = figs[0]["pairs"] if figs else None
        for k, _, _ in LIVE_ROWS:
            s[k] = _spread([f[k] for f in figs])
        s["lost_per_run"] = [f["lost"] for f in figs]
        off = _get(offline, "backends", b) if offline else None
        live = s["live_ate_m"]["median"]
        s["live_to_offline_published"] = _ratio(live, _get(off, "ate_published_m", "median"))
        s["live_to_offline_final"] = _ratio(live, _get(off, "ate_final_m", "median"))
        out[b] = s
    return out


def compare_targets(live: Optional[dict], offline: Optional[dict],
                    backend: str = "mdr") -> List[Dict[str, object]]:
    """The built-in tracker's targets (:data:`TARGETS`): per target its figure, the limit and
    whether it is met (None: not measured)."""
    s = (live or {}).get(backend)
    vals = {}
    if s:
        for k in ("tracked_pct", "live_ate_pct", "map_hz", "latency_ms_median",
                  "rss_mb_total_max", "cpu_percent_total_median"):
            vals[k] = s[k]["median"]
        vals["lost"] = s["lost"]["max"]
        vals["live_to_offline_published"] = s["live_to_offline_published"]
    vals["offline_cpu_to_orbslam3"] = _get(offline, "ratio_mdr_to_orbslam3", "cpu_ms_per_frame") \
        if backend == "mdr" else None
    out = []
    for k, (what, op, limit, unit) in TARGETS.items():
        v = vals.get(k)
        ok = None if v is None else bool(v >= limit if op == ">=" else v <= limit)
        out.append(OrderedDict([("key", k), ("what", what), ("value", v), ("op", op),
                                ("limit", limit), ("unit", unit), ("ok", ok)]))
    return out


def _num(v, unit: str) -> str:
    if v is None:
        return "not measured"
    if unit == "x":
        return "%.2f%s" % (v, unit)
    return ("%.0f" % v if unit == " MB" else "%g" % round(float(v), 2)) + unit


def targets_markdown(targets: List[Dict[str, object]], backend: str = "mdr") -> str:
    """One line per target: the figure, the limit, yes/no."""
    lines = ["Targets of `%s` (medians over the runs; live ATE against the offline ATE of the "
             "poses as published):" % backend, ""]
    for t in targets:
        lines.append("- %s: %s (target %s %s): %s" % (
            t["what"], _num(t["value"], t["unit"]), t["op"], _num(t["limit"], t["unit"]),
            {True: "yes", False: "no", None: "-"}[t["ok"]]))
    return "\n".join(lines) + "\n"


def live_markdown(live: Dict[str, object]) -> str:
    """The live table: median (min-max) over each backend's runs."""
    bs = list(live)
    n = max((live[b]["runs"] + live[b]["failed"] for b in bs), default=0)
    pairs = next((live[b]["pairs"] for b in bs if live[b]["pairs"]), None)
    lines = ["Live (`mdr bench BAG`: the three nodes under roslaunch), %d run%s per backend, "
             "median (min-max); the bag has %s stereo pairs:" % (
                 n, "" if n == 1 else "s", pairs if pairs else "-"), "",
             "| | " + " | ".join("`%s`" % b for b in bs) + " |", "|---|" + "---|" * len(bs)]
    for k, name, fmt in LIVE_ROWS:
        lines.append("| %s | %s |" % (name, " | ".join(_cell(live[b][k], fmt) for b in bs)))
    for k, name in (("live_to_offline_published", "live ATE / offline ATE as published (medians)"),
                    ("live_to_offline_final", "live ATE / offline final ATE (medians)")):
        lines.append("| %s | %s |" % (name, " | ".join(
            "-" if live[b][k] is None else "%.2fx" % live[b][k] for b in bs)))
    lines.append("| runs that failed | %s |" % " | ".join(str(live[b]["failed"]) for b in bs))
    return "\n".join(lines) + "\n"


def compare_report_markdown(report: Dict[str, object]) -> str:
    """``compare.md``: the offline table, the live table and the built-in tracker's targets of a
    comparison report (``offline``: :func:`compare_trackers`; ``live``: :func:`live_summary`;
    ``targets``: :func:`compare_targets`; ``notes``: lines to show first)."""
    lines = ["# Pose trackers: `mdr` (built-in) and `orbslam3` (ORB-SLAM3)", ""]
    for note in report.get("notes") or []:
        lines += ["Note: %s." % note, ""]
    if report.get("offline"):
        lines += ["## Offline", "", compare_markdown(report["offline"])]
    if report.get("live"):
        lines += ["## Live", "", live_markdown(report["live"])]
    else:
        lines += ["## Live", "", "Not run (%s)." % (report.get("live_skipped") or "--no-live"), ""]
    if report.get("targets"):
        lines += ["## Targets", "", targets_markdown(report["targets"])]
    return "\n".join(lines).rstrip("\n") + "\n"
