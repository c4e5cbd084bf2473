"""The live half of ``mdr bench``: the three nodes under roslaunch on a bag at real-time rate,
measured from outside the way a user would (psutil per node process, topic counts,
``/diagnostics``). See ``mdr bench --help``.
"""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import OrderedDict
from typing import Dict, List, Optional

import numpy as np
import psutil
import yaml

from ..bagio import image_topics, read_ground_truth
from ..conversions import ConversionError, pose_stamped_to_matrix
from ..eval.timeline import Series, Tracked, plot_timeline, timeline_md, window_bounds
from ..eval.trajectory import ate
from ..io import Trajectory
from ..io.trajectory import write_tum
from ..pipeline import load_params
from .main_run import _overrides

NODES = ("pose_node", "depth_node", "fusion_node")


def _free_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def _bag_duration(path: str) -> float:
    # the live run's ROS side (rosbag, rospy, rosgraph, messages) where it runs: mdr's
    # modules import without rospy and rosbag
    import rosbag
    with rosbag.Bag(path) as b:
        return float(b.get_end_time() - b.get_start_time())


def _stereo_pairs(path: str, args=None) -> int:
    """Left images in the bag on the topic the nodes read (the options of ``mdr bench``)."""
    import rosbag
    topics = {k: getattr(args, k) for k in ("left_image", "right_image")
              if getattr(args, k, None)}
    left = image_topics(topics, getattr(args, "image_transport", None) or "raw")["left"]
    with rosbag.Bag(path) as b:
        info = b.get_type_and_topic_info().topics
    return int(info[left].message_count) if left in info else 0


def _node_processes(launch_pid: int) -> Dict[str, "object"]:
    """{node name: psutil.Process} among roslaunch's children (their argv has __name:=<node>)."""
    out = {}
    try:
        for p in psutil.Process(launch_pid).children(recursive=True):
            try:
                cmd = " ".join(p.cmdline())
            except psutil.Error:
                continue
            for n in NODES:
                if "__name:=" + n in cmd:
                    out[n] = p
    except psutil.Error:
        pass
    return out


class _NodeUsage:
    """CPU % and memory of one node's process together with its child processes (recursively:
    the pose node may run bundle adjustment in a child). CPU: seconds of user and system time
    of the process and its live descendants, each with its reaped children's, between two
    samples; a child that ends moves its time into its parent's reaped-children count, so the
    sum carries on (never counted down, so a child between its exit and its reaping is not
    counted twice)."""

    def __init__(self, proc):
        self.proc = proc
        self.pid = proc.pid
        self.t_prev = time.time()
        self.cpu_prev = self._cpu_s(self._members())

    def _members(self) -> list:
        try:
            return [self.proc] + self.proc.children(recursive=True)
        except psutil.Error:
            return [self.proc]

    @staticmethod
    def _cpu_s(procs) -> float:
        total = 0.0
        for q in procs:
            try:
                t = q.cpu_times()
            except psutil.Error:   # ended since it was listed
                continue
            total += t.user + t.system + t.children_user + t.children_system
        return total

    def sample(self) -> Optional[dict]:
        """{"cpu": %, "rss_mb", "anon_mb"} since the last sample; None when the node is gone."""
        if not self.proc.is_running():
            return None
        procs = self._members()
        now = time.time()
        cpu_s = self._cpu_s(procs)
        dt = now - self.t_prev
        cpu = 100.0 * max(0.0, cpu_s - self.cpu_prev) / dt if dt > 0.05 else 0.0
        self.cpu_prev = max(self.cpu_prev, cpu_s)
        self.t_prev = now
        rss = anon = 0.0
        for q in procs:
            try:
                mi = q.memory_info()
            except psutil.Error:
                if q is self.proc:
                    return None
                continue
            rss += mi.rss
            # anonymous memory (heap, arrays): RSS without resident file pages (shared
            # libraries), which the kernel may drop under memory pressure at any time
            anon += mi.rss - getattr(mi, "shared", 0)
        return {"cpu": cpu, "rss_mb": rss / 1e6, "anon_mb": anon / 1e6}


def _live_ate(bag: str, poses, out_dir: Optional[str] = None,
              topic: Optional[str] = None) -> Optional[dict]:
    """ATE of the pose node's poses as it published them (before later BA and loop corrections
    of the past) against the bag's ground-truth topic; None when the bag has none. The poses are
    written to ``out_dir/live_trajectory.tum`` (TUM format) when given."""
    if len(poses) == 0:
        return None
    poses = sorted(poses, key=lambda p: p[0])
    est = Trajectory.from_matrices(np.array([p[0] for p in poses]), np.array([p[1] for p in poses]))
    if out_dir:
        write_tum(os.path.join(out_dir, "live_trajectory.tum"), est)
    try:
        gt = read_ground_truth(bag, topic) if topic else read_ground_truth(bag)
    except Exception:
        return None
    if len(gt) < 2 or len(poses) < 3:
        return None
    ref = Trajectory.from_matrices(np.asarray(gt.stamps), np.asarray(gt.Ts))
    try:
        e = ate(est, ref)
    except Exception:
        return None
    # path_m: the ground truth at the published poses' stamps; gt_path_m: the bag's whole
    # ground-truth path (what ATE is given as a share of)
    return {"rmse_m": round(e.stats["rmse"], 4), "max_m": round(e.stats["max"], 4),
            "n": int(e.stats["n"]), "path_m": round(e.stats["path_length"], 3),
            "gt_path_m": round(ref.path_length(), 3)}


class _Listener:
    """Counts and latencies from the nodes' topics and diagnostics (callbacks on rospy threads)."""

    def __init__(self):
        import rospy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import PointCloud2
        from mdr_slam_msgs.msg import TrackingState
        self.lock = threading.Lock()
        self.n_pose = 0
        self.n_depth = 0
        self.states: Dict[int, int] = {}
        self.tracking_ms: List[float] = []   # wall time per tracked pair (pose node)
        # per TrackingState, for the long-run windows: (wall time, state, tracking ms), and
        # (wall time, keyframes alive), (wall time, loop closures so far)
        self.tracked: List[tuple] = []
        self.keyframes: List[tuple] = []
        self.loop_closures: List[tuple] = []
        self.sparse_points: List[tuple] = []   # (wall time, pose's "sparse_map_points")
        self.diag: Dict[str, Dict[str, str]] = {}
        self.diag_time: Dict[str, float] = {}   # wall time of each status's last report
        self.latency_s: List[float] = []
        self.depth_latency_s: List[float] = []
        self.t_pose: List[float] = []       # wall receipt times, for rates over the active window
        self.poses: List[tuple] = []        # (stamp, T_map_cam) as published: the live trajectory
        self.t_depth: List[float] = []
        self.n_depth_empty = 0
        self.integrated: List[tuple] = []   # (wall time, fusion's "clouds integrated")
        self.map_points: List[tuple] = []   # (wall time, fusion's "map points")
        self.subs = [
            rospy.Subscriber("/mdr/pose", PoseStamped, self._pose, queue_size=100),
            rospy.Subscriber("/mdr/depth/points", PointCloud2, self._depth, queue_size=10,
                             buff_size=2 ** 26),
            rospy.Subscriber("/mdr/tracking_state", TrackingState, self._state, queue_size=100),
            rospy.Subscriber("/diagnostics", DiagnosticArray, self._diag, queue_size=20),
        ]

    def _pose(self, msg):
        try:
            T = pose_stamped_to_matrix(msg)
        except ConversionError:
            T = None
        with self.lock:
            self.n_pose += 1
            self.t_pose.append(time.time())
            if T is not None:
                self.poses.append((msg.header.stamp.to_sec(), T))

    def _depth(self, msg):
        import rospy
        lat = (rospy.Time.now() - msg.header.stamp).to_sec()
        with self.lock:
            self.n_depth += 1
            self.n_depth_empty += int(msg.width * msg.height == 0)
            self.t_depth.append(time.time())
            if 0 <= lat < 60:
                self.depth_latency_s.append(lat)

    def _state(self, msg):
        now = time.time()
        with self.lock:
            self.states[msg.state] = self.states.get(msg.state, 0) + 1
            self.tracking_ms.append(float(msg.tracking_time_ms))
            self.tracked.append((now, int(msg.state), float(msg.tracking_time_ms)))
            self.keyframes.append((now, int(msg.n_keyframes)))
            self.loop_closures.append((now, int(msg.n_loop_closures)))

    def _diag(self, msg):
        with self.lock:
            for st in msg.status:
                vals = {kv.key: kv.value for kv in st.values}
                self.diag[st.name] = vals
                self.diag_time[st.name] = time.time()
                for k, v in vals.items():
                    try:
                        f = float(v)
                    except ValueError:
                        continue
                    if k.startswith("last latency stamp->map") and np.isfinite(f):
                        self.latency_s.append(f)
                    elif k == "clouds integrated":
                        self.integrated.append((time.time(), f))
                    elif k == "map points" and "fusion" in st.name:
                        self.map_points.append((time.time(), f))
                    elif k == "sparse_map_points":
                        self.sparse_points.append((time.time(), f))

    def diag_value(self, node: str, key: str, default=None):
        with self.lock:
            for name, vals in self.diag.items():
                if node in name and key in vals:
                    return vals[key]
        return default


def _stats(v) -> Dict[str, float]:
    a = np.asarray(v, dtype=float)
    if len(a) == 0:
        return {"median": None, "max": None, "p90": None}
    return {"median": round(float(np.median(a)), 2), "p90": round(float(np.percentile(a, 90)), 2),
            "max": round(float(a.max()), 2)}


def _param_files(args) -> list:
    """``--set NODE.KEY=VALUE`` for the live nodes: each overridden node gets its config file (with
    the dataset preset) plus the overrides written to ``DIR/<node>.yaml``, passed to the launch."""
    out = []
    preset = getattr(args, "preset", None)
    if preset:
        out.append("preset:=" + preset)
    for node, ov in _overrides(getattr(args, "set", []) or []).items():
        if not ov:
            continue
        params = load_params(node, preset)
        params.update(ov)
        if node == "depth" and "weak_texture" in ov:   # the launch sets it after the file
            out.append("weak_texture:=%s" % ov["weak_texture"])
        path = os.path.abspath(os.path.join(args.out, "%s.yaml" % node))
        with open(path, "w") as f:
            yaml.safe_dump(params, f)
        out.append("%s_params:=%s" % (node, path))
    return out


def run_live(args) -> int:
    os.makedirs(args.out, exist_ok=True)
    bag = os.path.abspath(args.bag)
    dur_bag = _bag_duration(bag)
    duration = args.live_duration or (dur_bag / args.rate + 15.0)
    port = _free_port()
    env = dict(os.environ, ROS_MASTER_URI="http://127.0.0.1:%d" % port, ROS_IP="127.0.0.1",
               ROS_LOG_DIR=os.path.join(os.path.abspath(args.out), "roslog"))
    env.pop("ROS_HOSTNAME", None)
    os.environ.update(ROS_MASTER_URI=env["ROS_MASTER_URI"], ROS_IP="127.0.0.1",
                      ROS_LOG_DIR=env["ROS_LOG_DIR"])
    core = subprocess.Popen(["roscore", "-p", str(port)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    launch = None
    try:
        import rosgraph
        t0 = time.time()
        while True:
            try:
                rosgraph.Master("/mdr_bench", master_uri=env["ROS_MASTER_URI"]).getPid()
                break
            except Exception:
                if time.time() - t0 > 30:
                    print("mdr bench: roscore did not start", file=sys.stderr)
                    return 1
                time.sleep(0.2)
        pose_source = args.pose_source or "orb"
        cmd = ["roslaunch", "mdr_slam", "mdr.launch", "bag:=" + bag, "rate:=%g" % args.rate,
               "pose_source:=" + pose_source, "loop:=%s" % ("true" if args.loop else "false"),
               "delay:=3.0"]
        cmd += _param_files(args)
        cmd += list(getattr(args, "launch_arg", None) or [])
        log = open(os.path.join(args.out, "launch.log"), "wb")
        launch = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT,
                                  start_new_session=True)
        time.sleep(2.0)  # the launch sets /use_sim_time before this process becomes a node
        import rospy
        rospy.init_node("mdr_bench", anonymous=True, disable_signals=True)
        listener = _Listener()
        listener.t_start = time.time()
        print("mdr bench: %s, %s poses, %.0f s (bag %.1f s at %gx%s)" % (
            os.path.basename(bag), pose_source, duration, dur_bag, args.rate,
            ", looped" if args.loop else ""), file=sys.stderr)
        samples: List[dict] = []
        procs: Dict[str, _NodeUsage] = {}
        t_start = listener.t_start = time.time()
        while time.time() - t_start < duration:
            time.sleep(1.0)
            for n, p in _node_processes(launch.pid).items():
                if n not in procs or procs[n].pid != p.pid:   # new or respawned node
                    procs[n] = _NodeUsage(p)
            row = {"t": round(time.time() - t_start, 2)}
            for n, u in procs.items():
                use = u.sample()   # the node with its child processes
                if use is not None:
                    for k, v in use.items():
                        row[n + "." + k] = v
            has_nodes = len(row) > 1
            with listener.lock:       # the map's size next to the memory, for the long-run plot
                if listener.map_points:
                    row["map_points"] = listener.map_points[-1][1]
                if listener.integrated:
                    row["clouds_integrated"] = listener.integrated[-1][1]
            if has_nodes:
                samples.append(row)
            if not getattr(args, "quiet", False):
                print("\r  t=%4.0fs  pose %d  depth %d  map %s points" % (
                    row["t"], listener.n_pose, listener.n_depth,
                    listener.diag_value("fusion", "map points", "?")), end="", file=sys.stderr,
                    flush=True)
            if launch.poll() is not None:
                break
        elapsed = time.time() - t_start
        print("", file=sys.stderr)
        result = _summarize(args, bag, listener, samples, elapsed, pose_source)
    finally:
        if launch is not None and launch.poll() is None:
            os.killpg(launch.pid, signal.SIGINT)
            try:
                launch.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(launch.pid, signal.SIGKILL)
        os.killpg(core.pid, signal.SIGINT)
        try:
            core.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(core.pid, signal.SIGKILL)
    with open(os.path.join(args.out, "bench.json"), "w") as f:
        json.dump(result, f, indent=2)
    with open(os.path.join(args.out, "samples.json"), "w") as f:
        json.dump(samples, f)
    _plot(samples, os.path.join(args.out, "resources.png"), result.get("timeline"))
    plot_timeline(result.get("timeline"), os.path.join(args.out, "timeline.png"),
                  title="mdr bench %s (%g s windows)" % (os.path.basename(bag),
                                                          result["timeline_window_s"]),
                  nodes=NODES)
    md = _report_md(result)
    with open(os.path.join(args.out, "report.md"), "w") as f:
        f.write(md)
    print(md)
    return 0


def _rate(times) -> float:
    """Messages per second over the window they arrived in (idle time before and after the bag
    does not dilute it)."""
    if len(times) < 2:
        return 0.0
    return (len(times) - 1) / max(times[-1] - times[0], 1e-9)


def _integration_rate(samples) -> float:
    """Map integrations per second from the fusion node's cumulative counter while it grows."""
    grow = [(t, c) for i, (t, c) in enumerate(samples) if i == 0 or c != samples[i - 1][1]]
    if len(grow) < 2:
        return 0.0
    return (grow[-1][1] - grow[0][1]) / max(grow[-1][0] - grow[0][0], 1e-9)


def _slope_per_min(t, y):
    """Least-squares slope of y(t) (t in s) per minute over the second half of the time span
    (after start-up and the first pass over the scene), or None with too few samples."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    ok = np.isfinite(t) & np.isfinite(y)
    t, y = t[ok], y[ok]
    if len(t) < 4:
        return None
    late = t >= 0.5 * (t.min() + t.max())
    if late.sum() < 3 or np.ptp(t[late]) <= 0:
        return None
    return round(float(np.polyfit(t[late], y[late], 1)[0]) * 60.0, 3)


def timeline_window(elapsed: float) -> float:
    """Per-minute windows for long runs; about six windows for short ones."""
    return 60.0 if elapsed >= 300 else float(max(5.0, round(elapsed / 6.0)))


def _timeline(lst: "_Listener", samples, elapsed: float, window: float) -> List[dict]:
    """Rates (per minute), map sizes, tracking and per-node resources in consecutive windows of
    the run (mdr_slam.eval.timeline: the same windows and names as ``mdr run --window``)."""
    ts = lst.t_start
    with lst.lock:   # the subscribers' threads still run

        def rel(series):
            return [(t - ts,) + tuple(x) for t, *x in series]
        pose = Series([t - ts for t in lst.t_pose])
        depth = Series([t - ts for t in lst.t_depth])
        integrated = Series(rel(lst.integrated))
        map_points = Series(rel(lst.map_points))
        tracked = Tracked(rel(lst.tracked))
        keyframes = Series(rel(lst.keyframes))
        loops = Series(rel(lst.loop_closures))
        sparse = Series(rel(lst.sparse_points))
    st = np.asarray([s["t"] for s in samples], dtype=float)
    bounds = window_bounds(elapsed, window, min_len=1.0)   # a handful of windows, not per sample
    rows = []
    for i, (a, b) in enumerate(bounds):
        last = i == len(bounds) - 1
        per_min = 60.0 / (b - a)
        row = OrderedDict(t0=round(float(a), 1), t1=round(float(b), 1))
        row["poses_per_min"] = round(pose.count(a, b, last) * per_min, 1)
        row["depth_clouds_per_min"] = round(depth.count(a, b, last) * per_min, 1)
        n_int = integrated.increase(a, b, last)
        row["integrations_per_min"] = round(n_int * per_min, 1)
        row["map_hz"] = round(n_int / (b - a), 2)
        # reports at the end itself belong to the next window (but the last's)
        mp = map_points.at(b, last)
        row["map_points"] = int(mp) if mp is not None else None
        row["dense_map_points"] = row["map_points"]
        row.update(tracked.figures(a, b, last))
        kf, sp, lc = keyframes.at(b, last), sparse.at(b, last), loops.at(b, last)
        row["keyframes"] = int(kf) if kf is not None else None
        row["sparse_map_points"] = int(sp) if sp is not None else None
        row["loop_closures"] = int(loops.increase(a, b, last))
        row["loop_closures_total"] = int(lc) if lc is not None else None
        inw = [samples[k] for k in np.nonzero((st >= a) & ((st <= b) if last else (st < b)))[0]]
        rss, cpu = OrderedDict(), OrderedDict()
        anon = OrderedDict()
        for n in NODES:
            m = [x[n + ".rss_mb"] for x in inw if n + ".rss_mb" in x]
            h = [x[n + ".anon_mb"] for x in inw if n + ".anon_mb" in x]
            c = [x[n + ".cpu"] for x in inw if n + ".cpu" in x]
            rss[n] = round(float(np.mean(m)), 1) if m else None
            anon[n] = round(float(np.mean(h)), 1) if h else None
            cpu[n] = round(float(np.mean(c)), 1) if c else None
        for key, d in (("rss_mb", rss), ("anon_mb", anon)):
            full = [sum(x[n + "." + key] for n in NODES) for x in inw
                    if all(n + "." + key in x for n in NODES)]
            d["total"] = round(float(np.mean(full)), 1) if full else None
        row["rss_mb"] = rss
        row["anon_mb"] = anon
        row["cpu_percent"] = cpu
        rows.append(row)
    return rows


def _summarize(args, bag, lst: "_Listener", samples, elapsed, pose_source) -> dict:
    def fdiag(node, key):
        v = lst.diag_value(node, key)
        try:
            return float(v)
        except (TypeError, ValueError):
            return None
    integrated = fdiag("fusion", "clouds integrated")
    received = fdiag("depth", "received")
    pairs = _stereo_pairs(bag, args)
    r = OrderedDict()
    r["bag"] = bag
    r["pose_source"] = pose_source
    r["rate"] = args.rate
    r["loop"] = bool(args.loop)
    r["elapsed_s"] = round(elapsed, 1)
    r["frames_in"] = int(received) if received is not None else None
    r["frames_in_bag"] = pairs
    r["frames_tracked"] = int(lst.states.get(1, 0) + lst.states.get(3, 0)) if pose_source == "orb" \
        else lst.n_pose
    r["tracking_states"] = {{0: "NOT_INITIALIZED", 1: "OK", 2: "LOST", 3: "RELOCALIZED"}.get(k, k): v
                            for k, v in lst.states.items()}
    r["tracking_ms"] = {k: (None if v is None else round(v, 1))
                        for k, v in _stats(lst.tracking_ms).items()}
    r["pose_hz"] = round(_rate(lst.t_pose), 2)
    r["live_ate"] = _live_ate(bag, lst.poses, args.out, getattr(args, "ground_truth_pose", None))   # groundtruth relay: ~0 (a check of the chain)
    r["depth_hz"] = round(_rate(lst.t_depth), 2)
    r["map_integration_hz"] = round(_integration_rate(lst.integrated), 2)
    r["clouds_integrated"] = int(integrated) if integrated is not None else None
    received_f = fdiag("fusion", "clouds received")
    r["clouds_received_by_fusion"] = int(received_f) if received_f is not None else None
    r["depth_clouds"] = int(lst.n_depth)             # as received by the benchmark's subscriber
    r["depth_clouds_empty"] = int(lst.n_depth_empty)  # nothing converged yet (blank walls)
    r["latency_ms"] = {k: (None if v is None else round(1e3 * v, 1))
                       for k, v in _stats(lst.latency_s).items()}
    r["depth_latency_ms"] = {k: (None if v is None else round(1e3 * v, 1))
                             for k, v in _stats(lst.depth_latency_s).items()}
    # resources while data flowed (from the first to the last depth cloud)
    t0 = lst.t_depth[0] - lst.t_start if lst.t_depth else 0.0
    t1 = lst.t_depth[-1] - lst.t_start if lst.t_depth else elapsed
    all_samples = samples
    samples = [s for s in samples if t0 <= s["t"] <= t1 + 1.0] or samples
    r["depth_dropped"] = fdiag("depth", "dropped")
    r["depth_throttled"] = fdiag("depth", "throttled")   # skipped by max_rate, before any work
    r["depth_paused_lost"] = fdiag("depth", "paused_lost")   # skipped while tracking was LOST
    r["depth_cpu_ms_per_cloud"] = {k: fdiag("depth", "cpu_ms_%s_per_cloud" % k)
                                   for k in ("match", "filter")}
    r["pose_dropped_busy"] = fdiag("pose", "frames_dropped_busy")   # newest pair kept
    # the pose node's stages, median ms over its last frames (PoseRelay.STAGES)
    r["pose_stage_ms"] = OrderedDict((k, fdiag("pose", "median_ms: " + k)) for k in
                                     ("odometry_wait", "frame", "tracking", "tracking_cpu",
                                      "map_lock_wait"))
    r["pose_keyframes"] = fdiag("pose", "keyframes")
    r["pose_loop_closures"] = fdiag("pose", "loop_closures")
    r["pose_visual_odometry"] = fdiag("pose", "frames_visual_odometry")
    r["map_points"] = fdiag("fusion", "map points")
    cpu, rss = OrderedDict(), OrderedDict()
    tot_cpu = np.zeros(len(samples))
    tot_rss = np.zeros(len(samples))
    for n in NODES:
        c = [s.get(n + ".cpu", np.nan) for s in samples]
        m = [s.get(n + ".rss_mb", np.nan) for s in samples]
        cpu[n] = _stats([x for x in c if np.isfinite(x)])
        rss[n] = _stats([x for x in m if np.isfinite(x)])
        tot_cpu += np.nan_to_num(np.asarray(c, dtype=float))
        tot_rss += np.nan_to_num(np.asarray(m, dtype=float))
    cpu["total"] = _stats(tot_cpu)
    rss["total"] = _stats(tot_rss)
    r["cpu_percent"] = cpu
    r["rss_mb"] = rss
    r["rss_mb_at_end"] = {n: (round(samples[-1].get(n + ".rss_mb", float("nan")), 1)
                              if samples else None) for n in NODES}
    # long runs: memory growth (least squares over the second half of the active window, MB per
    # minute) next to the map's growth, and rates/resources per window over the whole run
    t = [s["t"] for s in samples]
    for kind in ("rss", "anon"):
        slope = OrderedDict()
        for n in NODES:
            slope[n] = _slope_per_min(t, [s.get(n + "." + kind + "_mb", np.nan) for s in samples])
        full = [s for s in samples if all(n + "." + kind + "_mb" in s for n in NODES)]
        slope["total"] = _slope_per_min([s["t"] for s in full],
                                        [sum(s[n + "." + kind + "_mb"] for n in NODES) for s in full])
        r[kind + "_slope_mb_per_min"] = slope
    r["rss_slope_fit_s"] = ([round(0.5 * (t[0] + t[-1]), 1), round(t[-1], 1)]
                            if len(t) >= 2 else None)
    mp = [(tt - lst.t_start, v) for tt, v in lst.map_points if t0 <= tt - lst.t_start <= t1 + 1.0]
    r["map_points_slope_per_min"] = _slope_per_min([a for a, _ in mp], [v for _, v in mp])
    r["map_points_max"] = int(max(v for _, v in lst.map_points)) if lst.map_points else None
    r["timeline_window_s"] = float(getattr(args, "window", None) or timeline_window(elapsed))
    r["timeline"] = _timeline(lst, all_samples, elapsed, r["timeline_window_s"])
    # seconds since each status last reported at the end: a stale one means that node's
    # diagnostics stopped (its counters above, e.g. map points, are then frozen)
    r["diagnostics_age_s"] = {k: round(lst.t_start + elapsed - v, 1)
                              for k, v in sorted(lst.diag_time.items())}
    return r


def _report_md(r) -> str:
    lines = ["# MDR-SLAM live benchmark", "",
             "`%s`, %s poses, rosbag play at %gx%s, %.0f s." % (
                 os.path.basename(r["bag"]), r["pose_source"], r["rate"],
                 " (looped)" if r["loop"] else "", r["elapsed_s"]), "",
             "| | |", "|---|---|",
             "| map integrations per second | %s Hz |" % r["map_integration_hz"],
             "| depth clouds per second | %s Hz |" % r["depth_hz"],
             "| poses per second | %s Hz |" % r["pose_hz"],
             "| depth clouds (empty: nothing converged) / received by fusion / integrated | "
             "%s (%s) / %s / %s |" % (r["depth_clouds"], r["depth_clouds_empty"],
                                      r["clouds_received_by_fusion"], r["clouds_integrated"]),
             "| stereo pairs received by depth / in the bag | %s / %s |" % (r["frames_in"],
                                                                          r["frames_in_bag"]),
             "| frames tracked; LOST | %s; %s |" % (r["frames_tracked"],
                                                   r["tracking_states"].get("LOST", 0)),
             "| keyframes; loop closures; frames tracked frame to frame, the map behind (pose "
             "node) | %s; %s; %s |" % (r.get("pose_keyframes"), r.get("pose_loop_closures"),
                                       r.get("pose_visual_odometry")),
             "| live ATE (poses as published, SE(3) aligned to the bag's ground truth): RMSE / "
             "max / poses | %s |" % ("-" if not r["live_ate"] else "%.3f m / %.3f m / %d" % (
                 r["live_ate"]["rmse_m"], r["live_ate"]["max_m"], r["live_ate"]["n"])),
             "| pose node: frames skipped while busy; tracking wall ms median / p90 / max | "
             "%s; %s / %s / %s |" % (r["pose_dropped_busy"], r["tracking_ms"]["median"],
                                     r["tracking_ms"]["p90"], r["tracking_ms"]["max"]),
             "| pose node stages at the end, median ms of its last 200 frames: odometry wait / "
             "frame (ORB, stereo matching) / tracking / its thread's CPU / map lock wait within "
             "tracking | "
             "%s |" % " / ".join("-" if v is None else "%.1f" % v
                                 for v in r.get("pose_stage_ms", {}).values()),
             "| latency image stamp -> map, median / p90 | %s / %s ms |" % (
                 r["latency_ms"]["median"], r["latency_ms"]["p90"]),
             "| latency image stamp -> depth cloud, median / p90 | %s / %s ms |" % (
                 r["depth_latency_ms"]["median"], r["depth_latency_ms"]["p90"]),
             "", "CPU and RSS sampled once a second while data flowed (each node with its "
             "child processes):", "",
             "| node | CPU % median / max | RSS MB median / max |", "|---|---|---|"]
    for n in list(NODES) + ["total"]:
        lines.append("| %s | %s / %s | %s / %s |" % (n, r["cpu_percent"][n]["median"],
                                                     r["cpu_percent"][n]["max"],
                                                     r["rss_mb"][n]["median"], r["rss_mb"][n]["max"]))
    fit = r.get("rss_slope_fit_s")
    if fit:
        lines += ["", "Memory growth: least-squares RSS slope over the second half of that window "
                  "(%s to %s s); the map size beside it, since the fusion node's memory should "
                  "follow the mapped surface, not the run's length:" % (fit[0], fit[1]), "",
                  "| | RSS MB per minute | anonymous (heap) MB per minute |", "|---|---|---|"]
        for n in list(NODES) + ["total"]:
            lines.append("| %s | %s | %s |" % (n, r["rss_slope_mb_per_min"][n],
                                                r["anon_slope_mb_per_min"][n]))
        lines.append("| map points (max %s) | %s points per minute | |" % (
            r["map_points_max"], r["map_points_slope_per_min"]))
    stale = {k: v for k, v in r.get("diagnostics_age_s", {}).items() if v > 10}
    if stale:
        lines += ["", "WARNING: diagnostics stopped before the end (seconds since the last "
                  "report: %s); their counters (map points, integrations) are frozen from then."
                  % ", ".join("%s %s" % kv for kv in stale.items())]
    if r.get("timeline"):
        lines += ["", "Over time (%g s windows): poses and depth clouds per minute; RSS: the "
                  "window's mean; keyframes (alive), sparse and dense map points: at its end; "
                  "loop closures: closed in it; tracking ms: the pose node's per stereo pair; "
                  "frames tracked: OK or RELOCALIZED of the states it published; map Hz: "
                  "integrations per second. Plotted in timeline.png." % r["timeline_window_s"],
                  ""]
        lines += timeline_md(r["timeline"], NODES,
                             extra=(("poses", lambda w: w.get("poses_per_min")),
                                    ("depth clouds", lambda w: w.get("depth_clouds_per_min"))),
                             labels=[n.replace("_node", "") for n in NODES])
    return "\n".join(lines) + "\n"


def _plot(samples, path, timeline=None):
    if not samples:
        return
    # matplotlib: 0.3 s to import and it must get the Agg backend first; only the plot needs it
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    t = [s["t"] for s in samples]
    fig, axes = plt.subplots(3, 1, figsize=(9, 8.5), dpi=100, sharex=True)
    for n in NODES:
        axes[0].plot(t, [s.get(n + ".cpu", np.nan) for s in samples], label=n)
        line, = axes[1].plot(t, [s.get(n + ".rss_mb", np.nan) for s in samples], label=n)
        axes[1].plot(t, [s.get(n + ".anon_mb", np.nan) for s in samples], "--",
                     color=line.get_color())
    axes[0].set_ylabel("CPU %")
    axes[1].set_ylabel("RSS, dashed: anonymous (MB)")
    axes[2].plot(t, [s.get("map_points", np.nan) for s in samples], color="k", label="map points")
    axes[2].set_ylabel("map points")
    if timeline:
        ax = axes[2].twinx()
        ax.step([w["t0"] for w in timeline] + [timeline[-1]["t1"]],
                [w["integrations_per_min"] for w in timeline] +
                [timeline[-1]["integrations_per_min"]], where="post", color="tab:red",
                label="integrations / min")
        ax.set_ylabel("integrations / min", color="tab:red")
    axes[2].set_xlabel("time (s)")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
