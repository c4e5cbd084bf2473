"""Shared fixtures: import path, shared data location, a private roscore for tests that need one."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SRC = os.path.join(ROOT, "src", "mdr_slam", "src")
if SRC not in sys.path:  # core tests run without sourcing setup.bash too
    sys.path.insert(0, SRC)

SHARED_DATA = os.environ.get("MDR_SHARED_DATA", os.path.join(os.path.dirname(ROOT), "shared", "data"))


def shared_data(*parts) -> str:
    """Path under ../shared/data, or skip the test when that data is absent (a user's machine)."""
    p = os.path.join(SHARED_DATA, *parts)
    if not os.path.exists(p):
        pytest.skip("shared data %s is absent" % p)
    return p


@pytest.fixture(autouse=True)
def _own_ros_home(tmp_path, monkeypatch):
    """Every test's nodes get their own ROS_HOME: their map autosaves (ROS_HOME/mdr_maps) never
    touch the user's ~/.ros, and a node a test killed leaves nothing another test would resume."""
    monkeypatch.setenv("ROS_HOME", str(tmp_path / "ros_home"))


@pytest.fixture(scope="session")
def root_dir():
    return ROOT


@pytest.fixture(scope="session")
def sample_bag(tmp_path_factory):
    """The README demo's sample bag itself (office loop, 752x480, 20 Hz, 30 s, 600 stereo pairs),
    rendered once per test session exactly as ``mdr demo`` does (``mdr sim --scene office
    --duration 30``: the same bytes as output/sample/sequence.bag; ~30 s on two cores). Returns the
    directory (sequence.bag, groundtruth.tum, gt_map.ply, scene.yaml)."""
    from mdr_slam.sim import generate
    d = str(tmp_path_factory.mktemp("sample"))
    generate(d, scene="office", duration=30.0)
    return d


@pytest.fixture(scope="session")
def small_sim(tmp_path_factory):
    """The office loop at half resolution (376x240) and 10 Hz, of which the runs use the first 60
    frames (6 s: a shorter sequence would make the one-lap loop unrealistically fast)."""
    from mdr_slam.sim import generate
    d = str(tmp_path_factory.mktemp("sim_office"))
    generate(d, scene="office", duration=30.0, seed=1, rate=10.0, scale=0.5, workers=2,
             map_cell=0.02)
    return d


def serialize_roundtrip(msg):
    """A ROS message serialized and deserialized as rospy and rosbag do (data becomes bytes)."""
    import io
    buf = io.BytesIO()
    msg.serialize(buf)
    out = type(msg)()
    out.deserialize(buf.getvalue())
    return out


def _free_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


@pytest.fixture(scope="session")
def roscore(tmp_path_factory):
    """A private roscore on a free port for the whole session; yields its ROS_MASTER_URI.

    The URI is put into os.environ, so subprocesses (roslaunch, rosrun, rostopic) and the in-process
    rospy client use this master and never a user's running one.
    """
    port = _free_port()
    uri = "http://127.0.0.1:%d" % port
    env = dict(os.environ, ROS_MASTER_URI=uri, ROS_IP="127.0.0.1",
               ROS_LOG_DIR=str(tmp_path_factory.mktemp("roslog")))
    env.pop("ROS_HOSTNAME", None)
    proc = subprocess.Popen(["roscore", "-p", str(port)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    import rosgraph
    deadline = time.time() + 30
    while True:
        try:
            rosgraph.Master("/pytest", master_uri=uri).getPid()
            break
        except Exception:
            if time.time() > deadline or proc.poll() is not None:
                os.killpg(proc.pid, signal.SIGKILL)
                pytest.fail("roscore did not come up on port %d" % port)
            time.sleep(0.2)
    old = {k: os.environ.get(k) for k in ("ROS_MASTER_URI", "ROS_IP", "ROS_LOG_DIR")}
    os.environ.update(ROS_MASTER_URI=uri, ROS_IP="127.0.0.1", ROS_LOG_DIR=env["ROS_LOG_DIR"])
    yield uri
    os.killpg(proc.pid, signal.SIGINT)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(scope="session")
def rospy_client(roscore):
    """This test process as a rospy node (rospy allows one init per process, so session scope)."""
    import rospy
    rospy.init_node("pytest_client", anonymous=True, disable_signals=True)
    yield rospy


class NodeProcess:
    """A node or launch file started as a subprocess in its own process group."""

    def __init__(self, cmd, env=None, log=None):
        self.log = log
        self.proc = subprocess.Popen(cmd, env=env or os.environ.copy(), start_new_session=True,
                                     stdout=open(log, "wb") if log else subprocess.DEVNULL,
                                     stderr=subprocess.STDOUT)

    def stop(self, sig=signal.SIGINT, timeout=15):
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        return self.proc.returncode

    def output(self) -> str:
        return open(self.log, errors="replace").read() if self.log else ""


def registered_nodes(master_uri) -> list:
    """Names of the nodes that have a publication, subscription or service on the master."""
    import rosgraph
    state = rosgraph.Master("/pytest_cleanup", master_uri=master_uri).getSystemState()
    return sorted({n for group in state for _, nodes in group for n in nodes})


def forget_nodes(master_uri, names):
    """Drop stopped nodes' registrations from the shared master.

    A node that was killed, or that shut down before it could unregister, stays registered under
    its XML-RPC port. When a later test starts a node of the same name, the master tells the old
    port to shut down, and by then the port may belong to another process (a ``rosbag play``
    that then quits before playing). Registering each name once more from a dead address makes
    the master drop everything the old node held (parameter subscriptions included); the
    master's shutdown call then goes to the dead address, and unregistering that empties the node.
    """
    import xmlrpc.client
    master = xmlrpc.client.ServerProxy(master_uri)
    dead = "http://127.0.0.1:1/"     # port 1: nothing listens there
    for name in names:
        if name in ("/rosout",) or name.startswith("/pytest"):
            continue
        try:
            master.registerPublisher(name, "/pytest_forget", "std_msgs/Empty", dead)
            master.unregisterPublisher(name, "/pytest_forget", dead)
        except Exception:
            pass


@pytest.fixture
def start_process(roscore, tmp_path):
    """Start commands against the private master; all are stopped after the test."""
    procs = []

    def start(cmd, name="proc"):
        p = NodeProcess(cmd, log=str(tmp_path / ("%s.log" % name)))
        procs.append(p)
        return p

    import rosgraph
    before = set(registered_nodes(roscore))
    yield start
    for p in procs:
        p.stop()
    forget_nodes(roscore, set(registered_nodes(roscore)) - before)
    # a launch file with a bag sets /use_sim_time on the shared master: later tests' nodes would
    # wait for a /clock nobody publishes
    try:
        master = rosgraph.Master("/pytest_cleanup", master_uri=roscore)
        if master.hasParam("/use_sim_time"):
            master.deleteParam("/use_sim_time")
    except Exception:
        pass


def wait_for(predicate, timeout=20.0, period=0.05):
    """Poll ``predicate`` until it is truthy or ``timeout`` passes; returns its last value."""
    deadline = time.time() + timeout
    while True:
        v = predicate()
        if v or time.time() > deadline:
            return v
        time.sleep(period)
