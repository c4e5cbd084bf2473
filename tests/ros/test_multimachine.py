"""Multi-machine: ROS 1 is the distributed engine, so the depth node can run on
another processing unit. The launch file places nodes by argument (machine tags) and ships an
env-loader; a test runs the depth node in its own network namespace (a second "computer" joined to
the first by a veth pair, addresses only inside the test's two namespaces) and the pipeline maps
across it.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest

from conftest import ROOT

pytestmark = pytest.mark.ros

LAUNCH = os.path.join(ROOT, "launch", "mdr.launch")
ENV_LOADER = os.path.join(ROOT, "src", "mdr_slam", "scripts", "env_loader.sh")


def _load(argv):
    """The roslaunch config of mdr.launch with ``argv``, machines assigned (no ssh, no master)."""
    import roslaunch.config
    return roslaunch.config.load_config_default([(LAUNCH, list(argv))], None, verbose=False)


def test_machine_args_place_nodes(tmp_path):
    """*_machine args put a node on a declared machine (address, user, env-loader from args or
    from an included machines_file); empty means this computer; start_*:=false leaves one out."""
    cfg = _load(["depth_machine:=remote", "machine_address:=192.0.2.5", "machine_user:=robot"])
    m = {n.name: n.machine for n in cfg.nodes}
    assert m["depth_node"].address == "192.0.2.5" and m["depth_node"].user == "robot"
    assert os.path.realpath(m["depth_node"].env_loader) == os.path.realpath(ENV_LOADER)
    assert m["pose_node"].address == m["fusion_node"].address == "localhost"
    assert cfg.has_remote_nodes()

    mfile = tmp_path / "machines.launch"
    mfile.write_text('<launch><machine name="gpu" address="192.0.2.7" user="me" '
                     'env-loader="/opt/ws/src/mdr_slam/scripts/env_loader.sh" timeout="20"/></launch>')
    cfg = _load(["machines_file:=%s" % mfile, "depth_machine:=gpu", "fusion_machine:=gpu"])
    m = {n.name: n.machine for n in cfg.nodes}
    assert m["depth_node"].address == m["fusion_node"].address == "192.0.2.7"
    assert m["fusion_node"].env_loader == "/opt/ws/src/mdr_slam/scripts/env_loader.sh"
    assert m["fusion_node"].timeout == 20.0 and m["pose_node"].address == "localhost"

    cfg = _load([])
    assert not cfg.has_remote_nodes() and len(cfg.nodes) == 3
    names = {n.name for n in _load(["start_depth:=false", "bag:=/tmp/x.bag"]).nodes}
    assert names == {"pose_node", "fusion_node", "bag_player"}
    names = {n.name for n in _load(["start_pose:=false", "start_fusion:=false"]).nodes}
    assert names == {"depth_node"}
    with pytest.raises(Exception):   # a machine nobody declared is an error, not a silent local run
        _load(["depth_machine:=nowhere"])


def test_env_loader_sources_the_workspace_from_a_bare_environment(tmp_path):
    """What roslaunch does over ssh: env_loader.sh COMMAND in a login-less environment finds the
    workspace, so mdr_slam, its messages and the package path resolve; no command is an error."""
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    code = "import mdr_slam, mdr_slam_msgs.msg, rospkg; print(rospkg.RosPack().get_path('mdr_slam'))"
    r = subprocess.run([ENV_LOADER, "python", "-c", code], env=env, cwd=str(tmp_path),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert os.path.realpath(r.stdout.strip()) == os.path.realpath(os.path.join(ROOT, "src", "mdr_slam"))
    r = subprocess.run([ENV_LOADER], env=env, capture_output=True, text=True, timeout=30)
    assert r.returncode != 0 and "usage" in r.stderr
    assert os.access(ENV_LOADER, os.X_OK)


# ------------------------------------------------------------------ two network namespaces

CHECK = r'''
import json, sys, time
import rosgraph
cmd, timeout = sys.argv[1], float(sys.argv[2])
master = rosgraph.Master("/mm_check")
deadline = time.time() + timeout

def up(f):
    while time.time() < deadline:
        try:
            if f():
                return True
        except Exception:
            pass
        time.sleep(0.3)
    return False

if cmd == "master":
    sys.exit(0 if up(master.getPid) else 1)
if cmd == "node":
    sys.exit(0 if up(lambda: master.lookupNode(sys.argv[3])) else 1)
# watch: the fusion node's diagnostics until the map has points from several clouds
import rospy
from diagnostic_msgs.msg import DiagnosticArray
seen = {}
def diag(msg):
    for st in msg.status:
        if "fusion" in st.name:
            seen.update({kv.key: kv.value for kv in st.values})
rospy.init_node("mm_check", disable_signals=True)
rospy.Subscriber("/diagnostics", DiagnosticArray, diag, queue_size=20)
up(lambda: int(seen.get("map points", 0)) > 0 and int(seen.get("clouds integrated", 0)) >= 3)
out = {"fusion": dict(seen)}
try:
    out["depth_uri"] = master.lookupNode("/depth_node")
    out["fusion_uri"] = master.lookupNode("/fusion_node")
    pubs, subs, _ = master.getSystemState()
    out["publishers"] = {t: n for t, n in pubs if t.startswith("/mdr/") or t.startswith("/stereo/")}
    from xmlrpc.client import ServerProxy
    code, _, bus = ServerProxy(out["fusion_uri"]).getBusInfo("/mm_check")
    out["fusion_bus"] = [[str(x) for x in c] for c in bus]
except Exception as e:
    out["error"] = repr(e)
print("RESULT " + json.dumps(out))
'''


def _netns_available():
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return "needs root (ip netns)"
    if not shutil.which("ip"):
        return "no ip command"
    if subprocess.run(["ip", "netns", "list"], capture_output=True).returncode != 0:
        return "ip netns unavailable"
    return None


def _ip(*args):
    r = subprocess.run(["ip"] + list(args), capture_output=True, text=True, timeout=20)
    if r.returncode != 0:
        raise RuntimeError("ip %s: %s" % (" ".join(args), r.stderr.strip()))
    return r.stdout


@pytest.fixture
def two_machines():
    """Namespaces "host" (master, pose, fusion, bag) and "depth" joined by a veth pair with
    10.200.N.1/24 and .2/24; everything (processes still inside, the namespaces, the veths) is
    removed afterwards, also on failure."""
    why = _netns_available()
    if why:
        pytest.skip(why)
    tag = "%d" % (os.getpid() % 100000)
    net = 10 + os.getpid() % 240
    m = {"host": "mdrh" + tag, "depth": "mdrd" + tag, "host_if": "mdrvh" + tag,
         "depth_if": "mdrvd" + tag, "host_ip": "10.200.%d.1" % net, "depth_ip": "10.200.%d.2" % net}
    try:
        try:
            _ip("netns", "add", m["host"])
            _ip("netns", "add", m["depth"])
        except RuntimeError as e:
            pytest.skip("cannot create network namespaces: %s" % e)
        _ip("link", "add", m["host_if"], "netns", m["host"], "type", "veth",
            "peer", "name", m["depth_if"], "netns", m["depth"])
        for side in ("host", "depth"):
            ns, dev, ip = m[side], m[side + "_if"], m[side + "_ip"]
            _ip("-n", ns, "addr", "add", ip + "/24", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        yield m
    finally:
        for side in ("host", "depth"):
            r = subprocess.run(["ip", "netns", "pids", m[side]], capture_output=True, text=True)
            for pid in r.stdout.split():      # only processes this test started live in there
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (OSError, ValueError):
                    pass
        for side in ("host", "depth"):
            subprocess.run(["ip", "netns", "del", m[side]], capture_output=True)
        left = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
        assert m["host"] not in left and m["depth"] not in left, left


def _veth_bytes(ns, dev):
    st = json.loads(_ip("-j", "-s", "-n", ns, "link", "show", dev))[0]["stats64"]
    return st["tx"]["bytes"], st["rx"]["bytes"]


def test_depth_node_on_another_machine_feeds_the_map(two_machines, tmp_path):
    """The depth node runs in its own network namespace, started the way roslaunch starts a node on
    a remote machine (a bare environment + env_loader.sh + roslaunch with the machine tag); master,
    bag, pose relay and fusion run on the host side. The fusion map grows from depth clouds that
    crossed the veth: the /mdr/depth/points publisher lives at the depth namespace's address and
    the fusion node's subscription is connected to it."""
    from mdr_slam.sim import generate
    m = two_machines
    sim = str(tmp_path / "sim")
    generate(sim, scene="office", duration=15.0, seed=1, rate=10.0, scale=0.5, workers=2,
             map_cell=0.05)
    bag = os.path.join(sim, "sequence.bag")
    master = "http://%s:11311" % m["host_ip"]
    # half resolution: one disparity step is twice the depth, so loosen tau (as tests/cli/test_pipeline.py)
    import yaml
    from mdr_slam.pipeline import config_dir
    dparams = yaml.safe_load(open(os.path.join(config_dir(), "depth.yaml")))
    dparams["tau"] = 0.02
    dyaml = tmp_path / "depth.yaml"
    dyaml.write_text(yaml.safe_dump(dparams))
    check_py = tmp_path / "check.py"
    check_py.write_text(CHECK)
    logs = tmp_path / "logs"
    logs.mkdir()

    host_env = dict(os.environ, ROS_MASTER_URI=master, ROS_IP=m["host_ip"], HOME=str(tmp_path),
                    ROS_LOG_DIR=str(logs / "host"))
    host_env.pop("ROS_HOSTNAME", None)
    # the remote side: nothing inherited but PATH and the ROS network settings of that machine
    depth_env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "ROS_MASTER_URI": master,
                 "ROS_IP": m["depth_ip"], "ROS_LOG_DIR": str(logs / "depth")}
    procs = []

    def start(ns, cmd, env, name):
        p = subprocess.Popen(["ip", "netns", "exec", ns] + cmd, env=env, start_new_session=True,
                             stdout=open(str(logs / (name + ".log")), "wb"), stderr=subprocess.STDOUT)
        procs.append((name, p))
        return p

    def check(*args, timeout=60):
        return subprocess.run(["ip", "netns", "exec", m["host"], sys.executable, str(check_py)] +
                              [str(a) for a in args], env=host_env, capture_output=True, text=True,
                              timeout=timeout + 30)

    def logs_text():
        return "\n".join("---- %s\n%s" % (n, open(str(logs / (n + ".log")), errors="replace")
                                          .read()[-3000:]) for n, _ in procs)

    t0 = time.time()
    try:
        start(m["host"], ["roscore", "-p", "11311"], host_env, "roscore")
        assert check("master", 30).returncode == 0, "no master on %s\n%s" % (master, logs_text())
        # depth "machine": env-loader + roslaunch, the node placed by depth_machine on the machine
        # declared with its own address (local to it, so roslaunch needs no ssh here)
        start(m["depth"], [ENV_LOADER, "roslaunch", "mdr_slam", "mdr.launch", "start_pose:=false",
                           "start_fusion:=false", "use_sim_time:=true", "respawn:=false",
                           "depth_machine:=depthbox", "machine_name:=depthbox",
                           "machine_address:=" + m["depth_ip"], "depth_params:=%s" % dyaml],
              depth_env, "depth_side")
        assert check("node", 60, "/depth_node").returncode == 0, logs_text()
        start(m["host"], ["roslaunch", "mdr_slam", "mdr.launch", "bag:=" + bag,
                          "pose_source:=groundtruth", "start_depth:=false", "respawn:=false",
                          "delay:=3.0"], host_env, "host_side")
        tx0 = _veth_bytes(m["host"], m["host_if"])
        r = check("watch", 60)
        line = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")]
        assert line, r.stdout + r.stderr + logs_text()
        res = json.loads(line[-1][len("RESULT "):])
        tx1, rx1 = _veth_bytes(m["host"], m["host_if"])
        print("multi-machine: %.1f s to a map of %s points from %s clouds; host->depth %.1f MB, "
              "depth->host %.1f MB over the veth" % (
                  time.time() - t0, res["fusion"].get("map points"),
                  res["fusion"].get("clouds integrated"), (tx1 - tx0[0]) / 1e6, rx1 / 1e6))
        assert "error" not in res, res
        # the cloud publisher is the depth node, reachable only at the depth namespace's address
        assert res["publishers"].get("/mdr/depth/points") == ["/depth_node"], res["publishers"]
        assert "//%s:" % m["depth_ip"] in res["depth_uri"], res["depth_uri"]
        assert "//%s:" % m["host_ip"] in res["fusion_uri"], res["fusion_uri"]
        # fusion's inbound /mdr/depth/points connection goes to that publisher (rospy getBusInfo:
        # [id, publisher URI, direction, transport, topic, connected, ...])
        conns = [c for c in res["fusion_bus"] if c[4] == "/mdr/depth/points"]
        assert conns and all(c[2] == "i" and m["depth_ip"] in c[1] for c in conns), res["fusion_bus"]
        assert int(res["fusion"]["map points"]) > 0, res["fusion"]
        assert int(res["fusion"]["clouds integrated"]) >= 3, res["fusion"]
        # images went out to the depth machine and clouds came back over the veth (one 376x240
        # stereo pair is 180 kB: more than 1 MB is several pairs, far above ROS's control traffic)
        assert tx1 - tx0[0] > 1e6 and rx1 > 1e5, (tx1, rx1)
        for name, p in procs:
            assert p.poll() is None, "%s exited\n%s" % (name, logs_text())
    finally:
        for name, p in reversed(procs):
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGINT)
                except OSError:
                    pass
        for name, p in reversed(procs):
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
