"""Diagnostics (issue 8 item 6): the three nodes report rate, latency, drops, CPU % and RSS (and
the pose node its tracking state) on /diagnostics through diagnostic_updater, on a live run of
mdr.launch over a small simulated bag."""
from __future__ import annotations

import math
import os

import pytest
import yaml

from conftest import ROOT, wait_for

pytestmark = pytest.mark.ros

COMMON = ("rate_hz", "latency_s", "drops", "cpu_percent", "rss_mb")


@pytest.fixture(scope="module")
def diag_sim(tmp_path_factory):
    """12 s of the office loop at half resolution and 10 Hz (enough frames for every node)."""
    from mdr_slam.sim import generate
    d = str(tmp_path_factory.mktemp("diag_office"))
    generate(d, scene="office", duration=12.0, seed=1, rate=10.0, scale=0.5, workers=2,
             map_cell=0.05)
    return d


def test_every_node_reports_health_on_diagnostics(diag_sim, rospy_client, start_process, tmp_path):
    rospy = rospy_client
    from diagnostic_msgs.msg import DiagnosticArray
    fusion = yaml.safe_load(open(os.path.join(ROOT, "src", "mdr_slam", "config", "fusion.yaml")))
    fusion.update(map_path=str(tmp_path / "map.ply"), autosave=False)
    fparams = tmp_path / "fusion.yaml"
    fparams.write_text(yaml.safe_dump(fusion))
    latest = {}   # status name -> {key: value}, from the newest message naming it

    def on_diag(msg):
        for st in msg.status:
            latest[st.name] = (st.level, st.message, {kv.key: kv.value for kv in st.values})
    sub = rospy.Subscriber("/diagnostics", DiagnosticArray, on_diag, queue_size=50)
    launch = start_process(["roslaunch", os.path.join(ROOT, "launch", "mdr.launch"),
                            "bag:=" + os.path.join(diag_sim, "sequence.bag"),
                            "pose_source:=groundtruth", "rate:=2", "respawn:=false", "delay:=3",
                            "fusion_params:=%s" % fparams], "mdr_launch")

    def status(node):
        hits = [v for k, v in latest.items() if k.startswith(node + ":")]
        return hits[0] if hits else None

    def working():
        out = {}
        for node in ("pose_node", "depth_node", "fusion_node"):
            s = status(node)
            if s is None or not all(k in s[2] for k in COMMON):
                return None
            try:
                if float(s[2]["rate_hz"]) <= 0:
                    return None
            except ValueError:
                return None
            out[node] = s
        return out
    try:
        got = wait_for(working, 75, 0.5)
        assert got, "diagnostics so far: %s\n%s" % ({k: v[2] for k, v in latest.items()},
                                                      launch.output()[-3000:])
        for node, (level, text, kv) in got.items():
            rate, lat = float(kv["rate_hz"]), float(kv["latency_s"])
            cpu, rss, drops = float(kv["cpu_percent"]), float(kv["rss_mb"]), int(kv["drops"])
            print("%s: %s | rate %.2f Hz, latency %.3f s, drops %d, CPU %.1f %%, RSS %.0f MB%s"
                  % (node, text, rate, lat, drops, cpu, rss,
                     ", tracking %s" % kv["tracking_state"] if "tracking_state" in kv else ""))
            assert 0 < rate < 100, (node, kv)
            assert math.isfinite(lat) and -1.0 < lat < 30.0, (node, kv)
            assert drops >= 0 and 0 <= cpu <= 400, (node, kv)
            assert rss > 30, (node, kv)
        kv = got["pose_node"][2]
        assert kv["tracking_state"] == "GROUNDTRUTH"
        assert int(kv["poses_published"]) > 0 and int(kv["frames_lost"]) == 0
        assert int(got["depth_node"][2]["processed"]) > 0
        assert int(got["fusion_node"][2]["clouds integrated"]) > 0
    finally:
        sub.unregister()
        launch.stop()
