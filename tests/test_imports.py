"""Imports: the ROS-free core imports on a machine without ROS, and every module of the package
imports on its own, whichever is imported first (no import cycles)."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SRC = os.path.join(ROOT, "src", "mdr_slam", "src")

ROS_PACKAGES = ("rospy", "rosbag", "cv_bridge", "tf2_ros", "sensor_msgs", "geometry_msgs")
CORE = ("camera", "geometry", "stereo_sync", "io", "eval", "sim", "pose", "depth", "fusion")

# Runs in a fresh interpreter: argv[1] = JSON {"block": [...], "modules": [...] or null (every
# module of mdr_slam)}. Imports each module with no mdr_slam module loaded before it (the
# package's modules are dropped from sys.modules in between, third-party ones stay), so a cycle
# shows whichever module of it comes first, and prints {module: error or null} as JSON.
_SCRIPT = r"""
import importlib, json, os, pkgutil, sys, traceback
req = json.loads(sys.argv[1])
block = set(req["block"])


class NoRos:
    # a meta path finder ahead of the real ones: the blocked packages are not installed
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in block:
            raise ModuleNotFoundError("No module named %r (blocked by the test)" % name, name=name)
        return None


if block:
    sys.meta_path.insert(0, NoRos())
    for name in [m for m in sys.modules if m.partition(".")[0] in block]:
        del sys.modules[name]


def drop_package():
    for name in [m for m in sys.modules if m == "mdr_slam" or m.startswith("mdr_slam.")]:
        del sys.modules[name]


def walk(path, prefix):
    # pkgutil.walk_packages without importing the packages on the way: a package that fails to
    # import still has its modules listed and tried
    for m in pkgutil.iter_modules(path, prefix):
        yield m.name
        if m.ispkg:
            sub = [os.path.join(p, m.name.rpartition(".")[2]) for p in path]
            yield from walk([p for p in sub if os.path.isdir(p)], m.name + ".")


modules = req["modules"]
if modules is None:
    import mdr_slam
    modules = sorted(set(walk(list(mdr_slam.__path__), "mdr_slam.")))
out = {}
for name in modules:
    drop_package()
    try:
        importlib.import_module(name)
        out[name] = None
    except BaseException:
        out[name] = traceback.format_exc(limit=-4)
print(json.dumps(out))
"""


def _import_each(modules, block=()) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [SRC] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    r = subprocess.run([sys.executable, "-c", _SCRIPT,
                        json.dumps({"block": list(block), "modules": modules})],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def without_ros() -> dict:
    return _import_each(["mdr_slam." + m for m in CORE], ROS_PACKAGES)


@pytest.mark.parametrize("module", CORE)
def test_core_imports_without_ros(without_ros, module):
    """camera, geometry, io, eval, sim and the three algorithm packages need no ROS: only
    conversions, bagio and the nodes may import rospy, rosbag, cv_bridge, tf2_ros or messages
    at module level (a bag writer imports rosbag when it is used)."""
    err = without_ros["mdr_slam." + module]
    assert err is None, "mdr_slam.%s needs ROS to import:\n%s" % (module, err)


def test_the_ros_block_works():
    """The blocked packages really fail to import (else the test above proves nothing)."""
    err = _import_each(["mdr_slam.conversions"], ROS_PACKAGES)["mdr_slam.conversions"]
    assert err is not None and "blocked by the test" in err


def test_every_module_imports_on_its_own():
    """Every module imports as the first module of the package in the process (an import cycle
    breaks only when one of its modules is imported first); ROS is present here."""
    pytest.importorskip("rospy")
    pytest.importorskip("mdr_slam_msgs.msg")
    res = _import_each(None)
    assert len(res) > 40 and "mdr_slam.cli.main_run" in res and "mdr_slam.nodes.common" in res
    bad = {m: e for m, e in res.items() if e is not None}
    assert not bad, "\n".join("%s:\n%s" % kv for kv in sorted(bad.items()))
