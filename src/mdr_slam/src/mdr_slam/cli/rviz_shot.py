"""A screenshot of rviz showing a saved map, rendered off-screen under Xvfb.

The real ROS path end to end: a private roscore, the fusion node started with ``load_map`` (it
publishes the latched ``/mdr/map/points`` and ``/mdr/map/grid`` as on a robot), the trajectory as a
latched ``/mdr/path``, and rviz with the shipped ``rviz/mdr.rviz`` (its orbit view pointed at the
map), on an Xvfb screen whose frame buffer (``-fbdir``, an XWD file) is read back and saved as PNG.

    python -m mdr_slam.cli.rviz_shot MAP.ply OUT.png [--trajectory TRAJ.tum]

``rviz_screenshot`` returns a dict (path, size, colourful share, seconds) or raises RuntimeError with
the reason (no rviz/Xvfb, a process died, nothing drawn before the timeout).
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from typing import List, Optional

import numpy as np
import yaml
from PIL import Image

from ..io import cloud_xyz, read_cloud, read_tum
from ..pipeline import config_dir
from ..viz import colourful_share, read_xwd
from .bench_live import _free_port


def _start(cmd, env, log) -> subprocess.Popen:
    return subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)


def _stop(procs: List[subprocess.Popen]) -> None:
    for p in reversed(procs):
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGINT)
                p.wait(8)
            except (subprocess.TimeoutExpired, ProcessLookupError):
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait(3)
                except (ProcessLookupError, subprocess.TimeoutExpired):
                    pass


def _start_xvfb(size, fbdir: str, log, procs: List[subprocess.Popen]) -> str:
    """Xvfb on the first free display number from 90 (its lock file absent); its screen is the
    XWD file ``fbdir/Xvfb_screen0``. Returns the display number."""
    for n in range(90, 190):
        if os.path.exists("/tmp/.X%d-lock" % n) or os.path.exists("/tmp/.X11-unix/X%d" % n):
            continue
        p = subprocess.Popen(["Xvfb", ":%d" % n, "-screen", "0", "%dx%dx24" % tuple(size),
                              "-fbdir", fbdir, "-nolisten", "tcp"], stdout=log,
                             stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.time() + 10
        while p.poll() is None and time.time() < deadline:
            if os.path.exists("/tmp/.X11-unix/X%d" % n) and os.path.exists(
                    os.path.join(fbdir, "Xvfb_screen0")):
                procs.append(p)
                return str(n)
            time.sleep(0.1)
        if p.poll() is None:
            p.kill()
            p.wait()
    raise RuntimeError("Xvfb did not start")


def _rviz_config(template: str, out: str, center, distance: float) -> str:
    """The shipped rviz config with its orbit view aimed at the map."""
    cfg = yaml.safe_load(open(template))
    view = cfg["Visualization Manager"]["Views"]["Current"]
    view["Focal Point"] = {"X": float(center[0]), "Y": float(center[1]), "Z": float(center[2])}
    view["Distance"] = float(distance)
    for d in cfg["Visualization Manager"]["Displays"]:
        if d.get("Class") == "rviz/PointCloud2" and d.get("Topic") == "/mdr/map/points":
            d["Size (Pixels)"] = 3
    with open(out, "w") as f:
        yaml.safe_dump(cfg, f, default_flow_style=False)
    return out


def _publish_path_main(argv=None) -> int:
    """``--publish-path TRAJ.tum``: a latched nav_msgs/Path in ``map`` and a static map->base_link
    identity transform (so rviz's fixed frame exists), until interrupted."""
    # ROS (rospy, tf2_ros, rosgraph, messages) where it is used: mdr's modules import
    # without rospy and tf2_ros
    import rospy
    import tf2_ros
    from geometry_msgs.msg import PoseStamped, TransformStamped
    from nav_msgs.msg import Path
    ap = argparse.ArgumentParser()
    ap.add_argument("--publish-path", required=True)
    a = ap.parse_args(argv)
    rospy.init_node("mdr_rviz_path", anonymous=True)
    pub = rospy.Publisher("/mdr/path", Path, queue_size=1, latch=True)
    path = Path()
    path.header.frame_id = "map"
    if a.publish_path:
        traj = read_tum(a.publish_path)
        for t, xyz, q in zip(traj.stamps, traj.positions, traj.quats):
            ps = PoseStamped()
            ps.header.frame_id = "map"
            ps.header.stamp = rospy.Time.from_sec(float(t))
            ps.pose.position.x, ps.pose.position.y, ps.pose.position.z = (float(v) for v in xyz)
            o = ps.pose.orientation
            o.x, o.y, o.z, o.w = (float(v) for v in q)
            path.poses.append(ps)
    pub.publish(path)
    st = tf2_ros.StaticTransformBroadcaster()
    tf = TransformStamped()
    tf.header.frame_id, tf.child_frame_id = "map", "base_link"
    tf.transform.rotation.w = 1.0
    st.sendTransform(tf)
    rospy.spin()
    return 0


def rviz_screenshot(map_ply: str, out_png: str, trajectory: Optional[str] = None,
                    rviz_config: Optional[str] = None, size=(1200, 800), timeout: float = 90.0,
                    log_dir: Optional[str] = None) -> dict:
    for exe in ("rviz", "Xvfb", "roscore"):
        if shutil.which(exe) is None:
            raise RuntimeError("%s is not installed" % exe)
    if rviz_config is None:
        rviz_config = os.path.join(os.path.dirname(config_dir()), "rviz", "mdr.rviz")
    xyz = cloud_xyz(read_cloud(map_ply))
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if len(xyz) == 0:
        raise RuntimeError("%s has no points" % map_ply)
    lo, hi = np.percentile(xyz, 2, axis=0), np.percentile(xyz, 98, axis=0)
    center = (lo + hi) / 2.0
    center[2] = lo[2]
    distance = 1.1 * float(np.linalg.norm(hi - lo)) + 1.0

    tmp = tempfile.mkdtemp(prefix="mdr_rviz_")
    log = open(os.path.join(log_dir or tmp, "rviz_shot.log"), "ab")
    procs: List[subprocess.Popen] = []
    t0 = time.time()
    try:
        display = _start_xvfb(size, tmp, log, procs)
        port = _free_port()
        env = dict(os.environ, DISPLAY=":" + display, ROS_MASTER_URI="http://127.0.0.1:%d" % port,
                   ROS_IP="127.0.0.1", ROS_LOG_DIR=os.path.join(tmp, "roslog"),
                   LIBGL_ALWAYS_SOFTWARE="1")
        env.pop("ROS_HOSTNAME", None)
        procs.append(_start(["roscore", "-p", str(port)], env, log))
        import rosgraph
        deadline = time.time() + 30
        while True:
            try:
                rosgraph.Master("/mdr_rviz_shot", master_uri=env["ROS_MASTER_URI"]).getPid()
                break
            except Exception:
                if time.time() > deadline:
                    raise RuntimeError("roscore did not start")
                time.sleep(0.2)
        procs.append(_start(["rosrun", "mdr_slam", "fusion_node", "_load_map:=" + os.path.abspath(map_ply),
                             "_autosave:=false", "_map_path:=" + os.path.join(tmp, "unused.ply"),
                             "_display_voxel:=0.02", "_display_min_confidence:=1",
                             "_publish_rate:=1.0"], env, log))
        procs.append(_start([sys.executable, "-m", "mdr_slam.cli.rviz_shot", "--publish-path",
                             os.path.abspath(trajectory) if trajectory else ""], env, log))
        cfg = _rviz_config(rviz_config, os.path.join(tmp, "view.rviz"), center, distance)
        procs.append(_start(["rviz", "-d", cfg], env, log))
        fb = os.path.join(tmp, "Xvfb_screen0")
        last, stable_since, img = -1.0, None, None
        while time.time() - t0 < timeout:
            time.sleep(1.0)
            for p in procs:
                if p.poll() is not None:
                    raise RuntimeError("%s exited (code %s; see %s)" % (p.args[0], p.returncode, log.name))
            try:
                img = read_xwd(fb)
            except (OSError, ValueError):
                continue
            share = colourful_share(img)
            if share > 0.005 and abs(share - last) < 0.002:
                stable_since = stable_since or time.time()
                if time.time() - stable_since >= 2.0:
                    break
            else:
                stable_since = None
            last = share
        else:
            raise RuntimeError("rviz drew no map within %.0f s (colourful share %.4f)" % (timeout, last))
        os.makedirs(os.path.dirname(os.path.abspath(out_png)), exist_ok=True)
        part = out_png + ".part.png"
        Image.fromarray(img).save(part)
        os.replace(part, out_png)
        return {"path": out_png, "size": [int(img.shape[1]), int(img.shape[0])],
                "colourful_share": round(colourful_share(img), 4), "seconds": round(time.time() - t0, 1)}
    except RuntimeError as e:
        log.flush()
        tail = open(log.name, errors="replace").read().strip().splitlines()[-12:]
        raise RuntimeError("%s\n  %s" % (e, "\n  ".join(tail))) from None
    finally:
        _stop(procs)
        log.close()
        shutil.rmtree(tmp, ignore_errors=True)


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv and argv[0] == "--publish-path":
        return _publish_path_main(argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("map")
    ap.add_argument("out")
    ap.add_argument("--trajectory", default=None)
    ap.add_argument("--timeout", type=float, default=90.0)
    a = ap.parse_args(argv)
    try:
        r = rviz_screenshot(a.map, a.out, a.trajectory, timeout=a.timeout)
    except RuntimeError as e:
        print("rviz screenshot: %s" % e, file=sys.stderr)
        return 1
    print("rviz screenshot: %s (%dx%d, %.1f %% map pixels, %.1f s)"
          % (r["path"], r["size"][0], r["size"][1], 100 * r["colourful_share"], r["seconds"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
