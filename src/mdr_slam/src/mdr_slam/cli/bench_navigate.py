"""``mdr bench --navigate``: the robot in the loop. For each scene, a private roscore, the
simulated robot (``sim_robot.launch``: a differential-drive base following ``cmd_vel``, its
stereo camera, wheel odometry, ``/clock``) and ``navigation.launch move_base:=true`` with the
default arguments (ORB poses, the three nodes, move_base on the fusion node's grid). The scene is
unknown to the stack: the map starts empty. Seeded goals (mdr_slam.eval.navigation: chained,
about half out of sight of the previous one) go to move_base's action server one after the other.

Per goal: ``reached`` (move_base SUCCEEDED and the true base within ``REACHED_SLACK`` m of the
goal), ``time_s`` (sim time), ``path_m`` (true path) against ``shortest_m`` (the true grid, disc
robot, from where the robot really was when the goal was sent), ``collisions`` (the robot's
footprint against the scene), ``min_clearance_m`` (footprint to the true obstacles),
``plans_through_occupied`` (global plans crossing a cell the last grid before them marked
occupied), ``max_localization_error_m`` (tf ``map -> base_link`` against the true base, the map
laid on the scene by the trajectory up to the goal: the pose's error against its own map; goals are
placed on the map the same way, as a user picks them on its walls) and ``max_error_from_start_m``
(the map fixed to the scene at the first tracked frame). Then the final map and grid against the
scene (map points within 5 cm of a true surface; occupied grid cells within one cell of a true
obstacle; true obstacle cells within ``RECALL_RANGE`` m of the path the grid holds), the map's
keyframe trajectory against the truth (``keyframe_trajectory``: aligned RMSE and max, after the
pose node's corrections and as first published), the stack's CPU and RSS (every process, move_base
included: median and max), and a top view. Writes ``DIR/navigation.json``, ``DIR/navigation.md``,
``DIR/<scene>/top.png`` and, for each missed goal k, move_base's global and local costmaps then
(``DIR/<scene>/miss_<k>_costmap.npz``, ``miss_<k>_local_costmap.npz`` and ``.png``); each scene's
launch logs in ``DIR/<scene>/``.
"""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections import OrderedDict
from typing import Dict, List, Optional

import numpy as np
import psutil

from ..eval.navigation import (keyframe_trajectory_error, localization_errors, map_alignment,
                               plan_crosses_occupied, sample_goals,
                               score_goal, summarise, true_grid)
from ..nav import plan_path
from .bench_live import _NodeUsage, _free_port

REACHED_SLACK = 0.30      # m: true base to goal for "reached" (goal tolerance + localization)
RECALL_RANGE = 3.0        # m from the path: the true obstacle cells the grid should hold
TRACKING_WAIT = 240.0     # wall s for the first map -> base_link (nodes starting, first frames)
GOAL_WALL_FACTOR = 8.0    # wall s per sim s of a goal's time limit (a slow machine still ends)
PLAN_TOPICS = ("move_base/GlobalPlanner/plan", "move_base/NavfnROS/plan")
MAX_SPEED = 0.4           # m/s: navigation/move_base.yaml's max_vel_x (the 2x-time target)
# m from the goal (tf map -> base_link) beyond which a SUCCEEDED is move_base's back-to-back race
# (DWA's xy_goal_tolerance is 0.15 m): the goal is sent again, once
FALSE_SUCCESS_DIST = 0.5


# the robot's own topics (sim_robot.launch, layout stereo), the pose node's state, and what the
# planners were given (the depth cloud the local costmap marks, the grid and map, the plans)
RECORD_TOPICS = ("/stereo/left/image_raw", "/stereo/right/image_raw", "/stereo/left/camera_info",
                 "/stereo/right/camera_info", "/odom", "/tf", "/tf_static", "/ground_truth/odom",
                 "/cmd_vel", "/mdr/tracking_state", "/move_base/current_goal",
                 "/move_base/GlobalPlanner/plan", "/move_base/DWAPlannerROS/local_plan",
                 "/bumper/points", "/mdr/map/nav_grid", "/mdr/map/points", "/mdr/depth/points",
                 "/mdr/depth/raw_points", "/mdr/keyframes")


def _planar(T: np.ndarray):
    return float(T[0, 3]), float(T[1, 3]), float(math.atan2(T[1, 0], T[0, 0]))


def _se2(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def _lift(A: np.ndarray) -> np.ndarray:
    """A planar rigid transform (3x3) as a 4x4 one about the z axis."""
    T = np.eye(4)
    T[:2, :2], T[:2, 3] = A[:2, :2], A[:2, 2]
    return T


def _stop(p, sig=signal.SIGINT, wait=30.0) -> None:
    if p is None or p.poll() is not None:
        return
    try:
        os.killpg(p.pid, sig)
        p.wait(wait)
    except (subprocess.TimeoutExpired, ProcessLookupError):
        try:
            os.killpg(p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def _run_scene_process(cmd, cleanup_s: float = 60.0) -> int:
    """Run one scene's process to its end. On Ctrl-C it has had the SIGINT too (same process
    group) and is stopping its launches, roscore and recorder: wait for that rather than kill it
    (subprocess.call would SIGKILL it and leave them running), then stop."""
    p = subprocess.Popen(cmd)
    try:
        return p.wait()
    except KeyboardInterrupt:
        try:
            p.wait(cleanup_s)
        except subprocess.TimeoutExpired:
            p.kill()
        raise


def _drive_to(client, goal, succeeded: int, give_up, distance) -> tuple:
    """Send ``goal`` to move_base's action server and wait for its result; ``(state, resent)``.

    move_base (noetic-devel, ros-planning/navigation#949) can report a goal SUCCEEDED at once when
    its plan thread delivered a plan for the previous goal just as that one was reached: the new
    goal's first control cycle takes the old plan, whose end the base stands on. A user's goal
    sender sees that from tf; so does this one: a SUCCEEDED with ``distance()`` (the base's
    estimated distance to the goal, None if unknown) above FALSE_SUCCESS_DIST sends the goal again,
    once (the stale plan is spent by then). ``give_up()`` True cancels (state ``"timeout"``)."""
    resent = 0
    client.send_goal(goal)
    while True:
        if client.wait_for_result(_duration(0.5)):
            state = client.get_state()
            d = distance() if state == succeeded else None
            if d is not None and d > FALSE_SUCCESS_DIST and resent == 0:
                resent += 1
                client.send_goal(goal)
                continue
            return state, resent
        if give_up():
            client.cancel_goal()
            return "timeout", resent


def _duration(s: float):
    import rospy
    return rospy.Duration(s)


def _keyframe_trajectory(watch, buf, rospy) -> Optional[dict]:
    """The map's keyframes against the truth (keyframe_trajectory_error): as the pose node last
    published them (``final``, loop and BA corrections in) and as it first published each
    (``as_created``). None without the camera's mount in tf or without keyframes."""
    import tf2_ros
    from ..conversions import transform_stamped_to_matrix
    if not watch.camera_frame:
        return None
    try:
        T_base_cam = transform_stamped_to_matrix(buf.lookup_transform(
            "base_link", watch.camera_frame, rospy.Time(0)))
    except tf2_ros.TransformException:
        return None
    T_cam_base = np.linalg.inv(T_base_cam)
    with watch.lock:
        gt = list(watch.gt)
        kfs = {name: list(d.values())
               for name, d in (("final", watch.kf_last), ("as_created", watch.kf_first))}
        loops = list(watch.loops)
    gt_t = [t for t, _T in gt]
    gt_xy = [T[:2, 3] for _t, T in gt]

    def ate(v):
        v = sorted(v, key=lambda e: e[0])
        return keyframe_trajectory_error([t for t, _T in v],
                                         [(T @ T_cam_base)[:2, 3] for _t, T in v], gt_t, gt_xy)
    out = {name: ate(v) for name, v in kfs.items()}
    # each loop correction (a closure, or the global BA after it): the keyframes it found, against
    # the truth before and after it
    out["loops"] = [{"stamp": round(st, 2), "keyframes_moved": n, "before": ate(b.values()),
                     "after": ate(a.values())} for st, n, b, a in loops]
    return out if out["final"] else None


class _Watch:
    """What the bench hears: true base poses, collisions, grids, global plans."""

    def __init__(self, rospy):
        from nav_msgs.msg import OccupancyGrid, Odometry, Path
        from std_msgs.msg import UInt32
        from ..conversions import pose_to_matrix
        self.lock = threading.Lock()
        self.gt: List[tuple] = []            # (sim t, T_world_base)
        self.collisions = 0
        self.grid = None                      # (grid, origin, res) of the last /mdr/map/grid
        self.plans: List[tuple] = []          # (sim t, plan xy (N, 2) in map, crossed cells)
        self._pose_to_matrix = pose_to_matrix
        self.subs = [rospy.Subscriber("ground_truth/odom", Odometry, self.on_gt, queue_size=200),
                     rospy.Subscriber("collisions", UInt32, self.on_coll, queue_size=5),
                     rospy.Subscriber("mdr/map/grid", OccupancyGrid, self.on_grid, queue_size=2,
                                      buff_size=1 << 24)]
        self.subs += [rospy.Subscriber(t, Path, self.on_plan, queue_size=20) for t in PLAN_TOPICS]
        from diagnostic_msgs.msg import DiagnosticArray
        from mdr_slam_msgs.msg import TrackingState
        self.diag: Dict[str, dict] = {}       # status name -> its last key/values
        self.states: List[tuple] = []         # (sim t, tracking state)
        self.subs += [rospy.Subscriber("/diagnostics", DiagnosticArray, self.on_diag, queue_size=20),
                      rospy.Subscriber("mdr/tracking_state", TrackingState, self.on_state,
                                       queue_size=50)]
        from mdr_slam_msgs.msg import KeyFrameArray
        from sensor_msgs.msg import CameraInfo
        # the map's keyframes (T_map_camera) as first published and after every correction
        self.kf_first: Dict[int, tuple] = {}
        self.kf_last: Dict[int, tuple] = {}
        self.camera_frame = None              # the left camera's optical frame (the keyframes')
        self.loops: List[tuple] = []          # (stamp, keyframes moved, before, after) per loop
        self.subs += [rospy.Subscriber("mdr/keyframes", KeyFrameArray, self.on_keyframes,
                                       queue_size=50),
                      rospy.Subscriber(RECORD_TOPICS[2], CameraInfo, self.on_info, queue_size=1)]

    def on_keyframes(self, m):
        with self.lock:
            before = dict(self.kf_last) if m.reason == m.LOOP_CLOSURE else None
            for kf in m.keyframes:
                v = (kf.stamp.to_sec(), self._pose_to_matrix(kf.pose))
                self.kf_first.setdefault(int(kf.id), v)
                self.kf_last[int(kf.id)] = v
            if before is not None:   # the keyframes just before and after a loop's correction
                self.loops.append((m.header.stamp.to_sec(), len(m.keyframes), before,
                                   {k: self.kf_last[k] for k in before}))

    def on_info(self, m):
        self.camera_frame = m.header.frame_id or self.camera_frame

    def on_diag(self, m):
        for st in m.status:
            self.diag[st.name] = {kv.key: kv.value for kv in st.values}

    def on_state(self, m):
        with self.lock:
            self.states.append((m.header.stamp.to_sec(), int(m.state)))

    def on_gt(self, m):
        T = self._pose_to_matrix(m.pose.pose)
        with self.lock:
            self.gt.append((m.header.stamp.to_sec(), T))

    def on_coll(self, m):
        self.collisions = int(m.data)

    def on_grid(self, m):
        from ..nav import grid_from_msg
        try:
            g = grid_from_msg(m)
        except ValueError:
            return
        with self.lock:
            self.grid = g

    def on_plan(self, m):
        xy = np.array([[p.pose.position.x, p.pose.position.y] for p in m.poses]).reshape(-1, 2)
        with self.lock:
            g = self.grid
        crossed = plan_crosses_occupied(xy, *g) if g is not None and len(xy) else 0
        with self.lock:
            self.plans.append((m.header.stamp.to_sec(), xy, crossed))


class _Usage:
    """CPU % and RSS of every node under the launches (move_base, the robot, the three nodes)."""

    def __init__(self, launches):
        self.launches = launches
        self.procs: Dict[str, _NodeUsage] = {}
        self.rows: List[dict] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self.stop.wait(1.0):
            for lp in self.launches:
                try:
                    kids = psutil.Process(lp.pid).children(recursive=False)
                except psutil.Error:
                    continue
                for p in kids:
                    try:
                        name = [a.split(":=", 1)[1] for a in p.cmdline() if a.startswith("__name:=")]
                    except psutil.Error:
                        continue
                    if name and (name[0] not in self.procs or self.procs[name[0]].pid != p.pid):
                        self.procs[name[0]] = _NodeUsage(p)
            row = {}
            for n, u in list(self.procs.items()):
                s = u.sample()
                if s is not None:
                    row[n] = s
            if row:
                self.rows.append(row)

    def summary(self) -> dict:
        self.stop.set()
        out = OrderedDict()
        names = sorted({n for r in self.rows for n in r})
        for n in names + ["total"]:
            cpu = [sum(v["cpu"] for v in r.values()) if n == "total" else r[n]["cpu"]
                   for r in self.rows if n == "total" or n in r]
            rss = [sum(v["rss_mb"] for v in r.values()) if n == "total" else r[n]["rss_mb"]
                   for r in self.rows if n == "total" or n in r]
            if cpu:
                out[n] = {"cpu_percent_median": round(float(np.median(cpu)), 1),
                          "cpu_percent_max": round(float(np.max(cpu)), 1),
                          "rss_mb_median": round(float(np.median(rss)), 1),
                          "rss_mb_max": round(float(np.max(rss)), 1)}
        return out


def _roscore(out_dir: str):
    port = _free_port()
    # ROS_HOME in the output: the nodes' autosaves and map files ($ROS_HOME/mdr_maps) stay there
    env = dict(os.environ, ROS_MASTER_URI="http://127.0.0.1:%d" % port, ROS_IP="127.0.0.1",
               ROS_LOG_DIR=os.path.join(out_dir, "roslog"), ROS_HOME=os.path.join(out_dir, "ros"))
    env.pop("ROS_HOSTNAME", None)
    os.environ.update(ROS_MASTER_URI=env["ROS_MASTER_URI"], ROS_IP="127.0.0.1",
                      ROS_LOG_DIR=env["ROS_LOG_DIR"], ROS_HOME=env["ROS_HOME"])
    core = subprocess.Popen(["roscore", "-p", str(port)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    import rosgraph
    t0 = time.time()
    while True:
        try:
            rosgraph.Master("/mdr_bench_nav", master_uri=env["ROS_MASTER_URI"]).getPid()
            return core, env
        except Exception:
            if time.time() - t0 > 30:
                _stop(core)
                raise RuntimeError("roscore did not start")
            time.sleep(0.2)


def _map_score(ply: str, scene, T_world_map: np.ndarray) -> dict:
    """Map points against the scene's exact surfaces (a random 100k of them)."""
    from ..geometry import transform_points
    from ..io import cloud_xyz, read_cloud
    if not os.path.exists(ply):
        return {}
    P = cloud_xyz(read_cloud(ply))
    if not len(P):
        return {"points": 0}
    rng = np.random.default_rng(0)
    Q = P[rng.choice(len(P), min(len(P), 100000), replace=False)]
    d = scene.distance_to_surfaces(transform_points(T_world_map, Q))
    return {"points": int(len(P)), "precision_5cm": round(float(np.mean(d < 0.05)), 3),
            "rmse_m": round(float(np.sqrt(np.mean(np.minimum(d, 0.5) ** 2))), 3)}


def _grid_score(grid, tg, T_world_map: np.ndarray, path_xy: np.ndarray) -> dict:
    """Occupied cells of the final grid against the true obstacles (one cell of tolerance) and
    recall of the true obstacle cells within RECALL_RANGE m of the true path."""
    from scipy.ndimage import binary_dilation, distance_transform_edt
    from ..nav import cell_to_world
    if grid is None:
        return {}
    g, origin, res = grid
    occ = np.argwhere(g >= 100)
    if not len(occ):
        return {"occupied_cells": 0}
    xy = cell_to_world(occ, origin, res)
    wxy = xy @ T_world_map[:2, :2].T + T_world_map[:2, 3]
    near_true = binary_dilation(tg.occ, np.ones((3, 3), bool))
    r, c = tg.cells(wxy)
    precision = float(np.mean(near_true[r, c]))
    est = np.zeros_like(tg.occ)
    est[r, c] = True
    est = binary_dilation(est, np.ones((3, 3), bool))
    if len(path_xy):
        pr, pc = tg.cells(path_xy)
        on_path = np.zeros_like(tg.occ)
        on_path[pr, pc] = True
        near_path = distance_transform_edt(~on_path) * tg.resolution <= RECALL_RANGE
    else:
        near_path = np.zeros_like(tg.occ)
    truth = tg.occ & near_path
    recall = float(np.mean(est[truth])) if truth.any() else float("nan")
    return {"occupied_cells": int(len(occ)), "precision": round(precision, 3),
            "recall_within_%gm" % RECALL_RANGE: round(recall, 3)}


def _costmap_at_miss(rospy, path: str, tf_buffer, base_frame: str, which: str = "global",
                     timeout: float = 15.0) -> Optional[str]:
    """Save one of move_base's costmaps (``which``: global, in map, or local, in odom) as it was
    when a goal was missed, with the base's estimated pose in its frame
    (``DIR/<scene>/miss_<k>_costmap.npz`` / ``miss_<k>_local_costmap.npz`` and ``.png``): a miss
    then shows whether the base stood walled in by cost for the planner (global) or for DWA
    (local). costmap_2d sends the whole costmap to each new subscriber, so one subscription is
    one snapshot."""
    from nav_msgs.msg import OccupancyGrid
    got = []
    done = threading.Event()

    def on_costmap(m):
        if not got:
            got.append(m)
            done.set()
    sub = rospy.Subscriber("move_base/%s_costmap/costmap" % which, OccupancyGrid, on_costmap,
                           queue_size=1, buff_size=1 << 24)
    done.wait(timeout)
    sub.unregister()
    if not got:
        return None
    from ..nav import grid_from_msg
    m = got[0]
    import tf2_ros
    from ..conversions import transform_stamped_to_matrix
    try:   # the base in the costmap's own frame (map for the global one, odom for the local one)
        T_frame_base = transform_stamped_to_matrix(tf_buffer.lookup_transform(
            m.header.frame_id, base_frame, rospy.Time(0)))
    except tf2_ros.TransformException:   # the picture without the base
        T_frame_base = None
    cost, origin, res = grid_from_msg(m)
    origin = np.asarray(origin, float)
    base = np.asarray(T_frame_base[:2, 3], float) if T_frame_base is not None else None
    np.savez(path + ".npz", cost=cost, origin=origin, resolution=res,
             frame=m.header.frame_id, base_xy=base if base is not None else np.zeros(0))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 6))
    ext = (origin[0], origin[0] + cost.shape[1] * res, origin[1], origin[1] + cost.shape[0] * res)
    ax.imshow(np.where(cost < 0, np.nan, cost), origin="lower", extent=ext, cmap="viridis",
              vmin=0, vmax=100)
    if base is not None:
        ax.plot(*base, "r+", ms=12)
        ax.set_xlim(base[0] - 2.0, base[0] + 2.0)
        ax.set_ylim(base[1] - 2.0, base[1] + 2.0)
    ax.set_title("%s costmap at the miss (0-100; robot +)" % which)
    fig.tight_layout()
    fig.savefig(path + ".png", dpi=100)
    plt.close(fig)
    return path + ".npz"


def _top_view(path: str, scene_name: str, tg, grid, T_world_map, true_xy, goals, records):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from ..nav import cell_to_world
    fig, ax = plt.subplots(figsize=(8, 8 * tg.occ.shape[0] / max(tg.occ.shape[1], 1) + 0.8))
    ext = (tg.origin[0], tg.origin[0] + tg.occ.shape[1] * tg.resolution,
           tg.origin[1], tg.origin[1] + tg.occ.shape[0] * tg.resolution)
    ax.imshow(np.where(tg.occ, 0.0, 1.0), origin="lower", extent=ext, cmap="gray", vmin=0, vmax=1)
    if grid is not None:
        g, origin, res = grid
        for val, col, lab in ((100, "tab:red", "grid: occupied"), (0, "tab:cyan", "grid: free")):
            cells = np.argwhere(g == val)
            if len(cells):
                xy = cell_to_world(cells, origin, res) @ T_world_map[:2, :2].T + T_world_map[:2, 3]
                ax.scatter(xy[:, 0], xy[:, 1], s=0.3, c=col, label=lab, alpha=0.5 if val else 0.15)
    if len(true_xy):
        ax.plot(true_xy[:, 0], true_xy[:, 1], "-", c="tab:blue", lw=1.2, label="true path")
    for i, (gl, rec) in enumerate(zip(goals, records)):
        ok = rec is not None and rec["reached"]
        ax.plot(*gl["xy"], "o", c="tab:green" if ok else "tab:red", ms=8)
        ax.annotate(str(i), gl["xy"], textcoords="offset points", xytext=(5, 5))
    ax.set_title("%s: true obstacles (black), grid, path, goals (green reached)" % scene_name)
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=7, markerscale=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_scene(args, scene_name: str, out_dir: str) -> dict:
    from ..sim import make_scene
    from ..sim.robot import RobotConfig, scene_start
    os.makedirs(out_dir, exist_ok=True)
    scene = make_scene(scene_name, seed=args.seed)
    cfg = RobotConfig()      # sim_robot.launch's defaults: footprint, mount
    radius = float(cfg.footprint_radius)
    tg = true_grid(scene)
    _h, _p, (x0, y0, _yaw0) = scene_start(scene, cfg.camera_forward)
    goals = sample_goals(tg, (x0, y0), args.goals, args.seed, robot_radius=radius)
    core, env = _roscore(out_dir)
    launches, recorder = [], None
    result: dict = {"scene": scene_name, "seed": args.seed, "goals": []}
    try:
        logs = []
        for name, cmd in (
                ("robot", ["roslaunch", "mdr_slam", "sim_robot.launch", "scene:=" + scene_name,
                           "seed:=%d" % args.seed, "map_frame:=world"]
                 + list(getattr(args, "robot_arg", None) or [])),
                ("navigation", ["roslaunch", "mdr_slam", "navigation.launch", "move_base:=true",
                                "use_sim_time:=true", "respawn:=false",
                                "session_id:=navigate_%s_%d" % (scene_name, args.seed)]
                 + list(args.launch_arg or []))):
            log = open(os.path.join(out_dir, name + ".log"), "wb")
            logs.append(log)
            launches.append(subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT,
                                             start_new_session=True))
            time.sleep(3.0)   # /use_sim_time is set before the next process starts
        if getattr(args, "record", False):   # what the robot published: replayed offline later
            log = open(os.path.join(out_dir, "record.log"), "wb")
            logs.append(log)
            recorder = subprocess.Popen(   # not in launches: the stack's CPU and RSS leave it out
                ["rosbag", "record", "--tcpnodelay", "-O", os.path.join(out_dir, "robot.bag")] +
                list(RECORD_TOPICS), env=env, stdout=log, stderr=subprocess.STDOUT,
                start_new_session=True)
        import actionlib
        import rospy
        import tf2_ros
        from move_base_msgs.msg import MoveBaseAction, MoveBaseGoal
        from actionlib_msgs.msg import GoalStatus
        from ..conversions import matrix_to_pose, transform_stamped_to_matrix
        rospy.init_node("mdr_bench_navigate", anonymous=True, disable_signals=True)
        usage = _Usage(launches)
        watch = _Watch(rospy)
        buf = tf2_ros.Buffer(cache_time=rospy.Duration(3600.0))
        tf2_ros.TransformListener(buf)
        # the map frame in the scene: the pose at the first tracked frame against the truth
        t_wall = time.time()
        T_world_map = None
        while T_world_map is None and time.time() - t_wall < TRACKING_WAIT:
            time.sleep(0.5)
            with watch.lock:
                gt = list(watch.gt[-20:])
            for t, T_wb in reversed(gt):
                try:
                    T_mb = transform_stamped_to_matrix(buf.lookup_transform(
                        "map", "base_link", rospy.Time.from_sec(t)))
                except tf2_ros.TransformException:
                    continue
                T_world_map = T_wb @ np.linalg.inv(T_mb)
                break
            if any(lp.poll() is not None for lp in launches):
                break
        if T_world_map is None:
            result["error"] = "no map -> base_link within %.0f s (tracking never started)" % \
                TRACKING_WAIT
            return result
        T_map_world = np.linalg.inv(T_world_map)
        client = actionlib.SimpleActionClient("move_base", MoveBaseAction)
        if not client.wait_for_server(rospy.Duration(120.0)):
            result["error"] = "move_base's action server did not come up"
            return result
        records, all_true, trace = [], [], []   # trace: (t, true x, y, estimated x, y)
        pairs_est, pairs_true = [], []   # base positions so far: the map's (first-frame anchor), true
        for k, gl in enumerate(goals):
            # the map as a user sees it: laid on the scene by the trajectory so far, so a goal
            # lies where the map shows that place (an early heading error rotates both)
            A = _lift(map_alignment(pairs_est, pairs_true))
            T_map_world = np.linalg.inv(A @ T_world_map)
            T_goal = T_map_world @ _se2(gl["xy"][0], gl["xy"][1], gl["yaw"])
            T_goal[:3, :3] = _se2(0, 0, _planar(T_goal)[2])[:3, :3]   # level in map
            goal = MoveBaseGoal()
            goal.target_pose.header.frame_id = "map"
            goal.target_pose.header.stamp = rospy.Time.now()
            goal.target_pose.pose = matrix_to_pose(T_goal)
            with watch.lock:   # where the robot really is (a missed goal leaves it elsewhere)
                here = watch.gt[-1][1][:2, 3] if watch.gt else np.asarray(gl["from"])
            plan = plan_path(tg.grid, here, gl["xy"], tg.resolution, tg.origin, radius) \
                if tg.clearance([here])[0] > radius else None
            if plan is not None:
                gl = dict(gl, shortest_m=round(plan.length, 3), **{"from": [float(v) for v in here]})
            limit = max(60.0, 3.0 * gl["shortest_m"] / MAX_SPEED + 30.0)
            coll0 = watch.collisions
            t0 = rospy.Time.now().to_sec()
            n_plans0 = len(watch.plans)
            wall0 = time.time()

            def give_up():
                return rospy.Time.now().to_sec() - t0 > limit or \
                    time.time() - wall0 > GOAL_WALL_FACTOR * limit or \
                    any(lp.poll() is not None for lp in launches)

            def distance():
                try:
                    T_mb = transform_stamped_to_matrix(buf.lookup_transform(
                        "map", "base_link", rospy.Time(0)))
                except tf2_ros.TransformException:
                    return None
                return float(np.linalg.norm(T_mb[:2, 3] - T_goal[:2, 3]))

            state, resent = _drive_to(client, goal, GoalStatus.SUCCEEDED, give_up, distance)
            t1 = rospy.Time.now().to_sec()
            with watch.lock:
                seg = [(t, T) for t, T in watch.gt if t0 <= t <= t1]
                plans = watch.plans[n_plans0:]
            true_xy = np.array([T[:2, 3] for _t, T in seg]).reshape(-1, 2)
            all_true.append(true_xy)
            est_t, est_xy = [], []
            for t, _T in seg[::2]:
                try:
                    T_mb = transform_stamped_to_matrix(buf.lookup_transform(
                        "map", "base_link", rospy.Time.from_sec(t)))
                except tf2_ros.TransformException:
                    continue
                est_t.append(t)
                est_xy.append((T_world_map @ T_mb)[:2, 3])
            est_xy = np.asarray(est_xy, float).reshape(-1, 2)
            aligned = est_xy @ A[:2, :2].T + A[:2, 3]
            loc = localization_errors(est_t, aligned, [t for t, _ in seg], true_xy)
            from_start = localization_errors(est_t, est_xy, [t for t, _ in seg], true_xy)
            gt_by_t = {t: T[:2, 3] for t, T in seg}
            trace += [(t, *gt_by_t[t], *e) for t, e in zip(est_t, aligned)]
            pairs_est += list(est_xy)
            pairs_true += [gt_by_t[t] for t in est_t]
            end_d = float(np.linalg.norm(true_xy[-1] - gl["xy"])) if len(true_xy) else float("inf")
            reached = state == GoalStatus.SUCCEEDED and end_d <= REACHED_SLACK
            rec = score_goal(gl, reached, t1 - t0, true_xy, tg, radius,
                             watch.collisions - coll0, sum(1 for p in plans if p[2] > 0), loc,
                             from_start)
            rec.update(move_base_state=(GoalStatus.to_string(state) if state != "timeout"
                                        else "timeout"),
                       true_goal_distance_m=round(end_d, 3), plans=len(plans),
                       time_limit_s=round(limit, 1), resent=resent)
            if not reached:
                for which, name in (("global", "costmap"), ("local", "local_costmap")):
                    snap = _costmap_at_miss(rospy, os.path.join(out_dir, "miss_%d_%s" % (k, name)),
                                            buf, "base_link", which)
                    if snap:
                        rec[name + "_at_miss"] = os.path.relpath(snap, os.path.dirname(out_dir))
            records.append(rec)
            verdict = ("reached" if reached else "MISSED (%s, %.2f m off)" % (
                rec["move_base_state"], end_d)) + (" (sent twice: move_base's back-to-back race)"
                                                   if resent else "")
            print("  %s goal %d/%d: %s in %.1f s (path %.1f m, shortest %.1f m), %d collisions, "
                  "clearance %.2f m, %d/%d plans through occupied, loc err %s (from the start "
                  "%s)" % (
                      scene_name, k + 1, len(goals), verdict, rec["time_s"],
                      rec["path_m"], rec["shortest_m"], rec["collisions"],
                      rec["min_clearance_m"], rec["plans_through_occupied"], len(plans),
                      rec["max_localization_error_m"], rec["max_error_from_start_m"]),
                  file=sys.stderr, flush=True)
        result["goals"] = records
        result["summary"] = summarise(records, MAX_SPEED)
        with watch.lock:
            st = np.array([s for _t, s in watch.states], int)
            np.savez(os.path.join(out_dir, "trace.npz"), pose=np.array(trace).reshape(-1, 5),
                     states=np.array(watch.states).reshape(-1, 2))
        result["tracking_states"] = {name: int(np.sum(st == v)) for name, v in (
            ("not_initialized", 0), ("ok", 1), ("lost", 2), ("relocalized", 3))}
        result["diagnostics"] = dict(watch.diag)
        result["keyframe_trajectory"] = _keyframe_trajectory(watch, buf, rospy)
        result["resources"] = usage.summary()
        # the final map and grid
        from mdr_slam_msgs.srv import SaveMap
        ply = os.path.join(env["ROS_HOME"], "mdr_maps", "navigation_map.ply")
        try:
            rospy.wait_for_service("/fusion_node/save_map", 30)
            rospy.ServiceProxy("/fusion_node/save_map", SaveMap)(os.path.basename(ply), "")
        except (rospy.ROSException, rospy.ServiceException) as e:
            result["map_error"] = str(e)
        path_xy = np.vstack(all_true) if all_true else np.zeros((0, 2))
        result["map"] = _map_score(ply, scene, T_world_map)
        with watch.lock:
            grid = watch.grid
        result["grid"] = _grid_score(grid, tg, T_world_map, path_xy)
        _top_view(os.path.join(out_dir, "top.png"), scene_name, tg, grid, T_world_map, path_xy,
                  goals, records)
        return result
    finally:
        _stop(recorder)   # first: the bag is closed while its topics still flow
        for lp in reversed(launches):
            _stop(lp)
        _stop(core)
        try:
            import rospy
            rospy.signal_shutdown("scene done")
        except Exception:
            pass


def _markdown(report: dict) -> str:
    lines = ["# Navigation benchmark: move_base on MDR-SLAM's map, the robot in the loop", "",
             "Seed %d, %d goals per scene; reached = move_base SUCCEEDED and the true base within "
             "%.2f m of the goal. Time in sim seconds." % (report["seed"], report["goals_per_scene"],
                                                           REACHED_SLACK), ""]
    for sc in report["scenes"]:
        s = sc.get("summary", {})
        lines += ["## %s" % sc["scene"], ""]
        if sc.get("error"):
            lines += ["Not run to the end: %s" % sc["error"], ""]
        if s:
            lines += ["%d/%d reached, %d collisions, %d plans through occupied cells, worst "
                      "localization error %s m (from the start %s m), slower than 2x shortest: %s"
                      % (s["reached"], s["goals"], s["collisions"], s["plans_through_occupied"],
                         s["max_localization_error_m"], s.get("max_error_from_start_m"),
                         s["slower_than_2x_shortest"] or "none"),
                      ""]
        lines += ["| goal | hidden | reached | state | time s | path m | shortest m | collisions "
                  "| min clearance m | plans through occupied | max loc. error m | max error from "
                  "the start m |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for i, r in enumerate(sc.get("goals", [])):
            lines.append("| %d | %s | %s | %s | %.1f | %.2f | %.2f | %d | %.2f | %d/%d | %s | %s |" % (
                i, "yes" if r["hidden"] else "", "yes" if r["reached"] else "**no**",
                r["move_base_state"] + (" (resent)" if r.get("resent") else ""), r["time_s"],
                r["path_m"], r["shortest_m"], r["collisions"],
                r["min_clearance_m"], r["plans_through_occupied"], r["plans"],
                r["max_localization_error_m"], r.get("max_error_from_start_m")))
        lines.append("")
        if sc.get("map"):
            lines.append("Map: %s. Grid: %s." % (
                ", ".join("%s %s" % kv for kv in sc["map"].items()),
                ", ".join("%s %s" % kv for kv in sc.get("grid", {}).items())))
        kt = sc.get("keyframe_trajectory") or {}
        if kt.get("final"):
            lines += ["", "Keyframe trajectory against the truth (aligned): RMSE %s m, max %s m "
                      "over %d keyframes, corrections included; as each was first published: %s."
                      % (kt["final"]["rmse_m"], kt["final"]["max_m"], kt["final"]["keyframes"],
                         "RMSE %s m, max %s m" % (kt["as_created"]["rmse_m"],
                                                  kt["as_created"]["max_m"])
                         if kt.get("as_created") else "-")]
            for lp in kt.get("loops", []):
                if lp["before"] and lp["after"]:
                    lines.append("Loop correction at %.1f s (%d keyframes moved): keyframe RMSE %s -> "
                                 "%s m, max %s -> %s m." % (
                                     lp["stamp"], lp["keyframes_moved"], lp["before"]["rmse_m"],
                                     lp["after"]["rmse_m"], lp["before"]["max_m"],
                                     lp["after"]["max_m"]))
        res = sc.get("resources", {})
        if res:
            lines += ["", "| process | CPU % median | CPU % max | RSS MB median | RSS MB max |",
                      "|---|---|---|---|---|"]
            for n, u in res.items():
                lines.append("| %s | %.0f | %.0f | %.0f | %.0f |" % (
                    n, u["cpu_percent_median"], u["cpu_percent_max"], u["rss_mb_median"],
                    u["rss_mb_max"]))
        lines.append("")
    return "\n".join(lines)


def run_navigate(args) -> int:
    """Each scene in a process of its own (a ROS node lives once per process, and each scene
    has its own roscore)."""
    from . import mdr_command
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    if getattr(args, "navigate_scene", None):       # the child: one scene
        name = args.navigate_scene
        try:
            r = run_scene(args, name, os.path.join(out, name))
        except Exception as e:   # reported in the scene's record, the other scenes still run
            r = {"scene": name, "seed": args.seed, "error": repr(e), "goals": []}
        with open(os.path.join(out, name, "scene.json"), "w") as f:
            json.dump(r, f, indent=2)
        return 0
    scenes = [s for s in (args.scenes or "office,corridor,garage").split(",") if s]
    report = {"seed": args.seed, "goals_per_scene": args.goals, "scenes": []}
    for name in scenes:
        print("mdr bench --navigate: %s, seed %d, %d goals" % (name, args.seed, args.goals),
              file=sys.stderr, flush=True)
        os.makedirs(os.path.join(out, name), exist_ok=True)
        cmd = mdr_command() + ["bench", "--navigate", "--navigate-scene", name, "--out", out,
                               "--seed", str(args.seed), "--goals", str(args.goals)]
        for a in args.launch_arg or []:
            cmd += ["--launch-arg", a]
        for a in getattr(args, "robot_arg", None) or []:
            cmd += ["--robot-arg", a]
        if getattr(args, "record", False):
            cmd.append("--record")
        _run_scene_process(cmd)
        try:
            with open(os.path.join(out, name, "scene.json")) as f:
                r = json.load(f)
        except (OSError, ValueError) as e:
            r = {"scene": name, "seed": args.seed, "error": "no result: %r" % (e,), "goals": []}
        report["scenes"].append(r)
        with open(os.path.join(out, "navigation.json"), "w") as f:
            json.dump(report, f, indent=2)
    md = _markdown(report)
    with open(os.path.join(out, "navigation.md"), "w") as f:
        f.write(md)
    print(md)
    return 0
