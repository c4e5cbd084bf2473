"""Workspace contract: Python 3.8 compatibility, licence, CLI, launch file, custom messages."""
from __future__ import annotations

import glob
import os
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest
import yaml

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _python_files():
    files = glob.glob(os.path.join(ROOT, "src", "mdr_slam", "src", "**", "*.py"), recursive=True)
    files += [f for f in glob.glob(os.path.join(ROOT, "src", "mdr_slam", "nodes", "*"))]
    files += glob.glob(os.path.join(ROOT, "tests", "**", "*.py"), recursive=True)
    files += glob.glob(os.path.join(ROOT, "scripts", "**", "*.py"), recursive=True)
    return sorted(files)


def test_code_is_python38_compatible():
    """ROS Noetic robots run Python 3.8: vermin must find nothing that needs a newer Python."""
    files = _python_files()
    assert len(files) > 10
    r = subprocess.run([os.path.join(os.path.dirname(sys.executable), "vermin"), "--no-tips", "--violations",
                        "--target=3.8-", "--eval-annotations", "--backport", "dataclasses",
                        "--no-parse-comments"] + files, capture_output=True, text=True)
    assert r.returncode == 0, "code needs a Python newer than 3.8:\n" + r.stdout + r.stderr


def test_licence_is_consistent():
    assert "GNU GENERAL PUBLIC LICENSE" in open(os.path.join(ROOT, "LICENSE")).read(2000)
    assert "Version 3" in open(os.path.join(ROOT, "LICENSE")).read(2000)
    for pkg in ("mdr_slam", "mdr_slam_msgs"):
        tree = ET.parse(os.path.join(ROOT, "src", pkg, "package.xml"))
        assert tree.getroot().get("format") == "2"
        assert tree.getroot().find("license").text == "GPL-3.0-or-later"


def test_mdr_cli_lists_subcommands():
    r = subprocess.run(["mdr", "--help"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for cmd in ("sim", "import", "run", "eval", "bench"):
        assert "\n    %s " % cmd in r.stdout, r.stdout
    r = subprocess.run(["rosrun", "mdr_slam", "mdr", "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and "mdr_slam" in r.stdout, r.stderr


def test_launch_lists_three_nodes():
    r = subprocess.run(["roslaunch", "--nodes", "mdr_slam", "mdr.launch"], capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr
    nodes = set(r.stdout.split())
    assert {"/pose_node", "/depth_node", "/fusion_node"} <= nodes
    r = subprocess.run(["roslaunch", "--nodes", "mdr_slam", "mdr.launch", "bag:=/tmp/x.bag",
                        "rviz:=true"], capture_output=True, text=True)
    assert {"/bag_player", "/rviz"} <= set(r.stdout.split()), r.stdout + r.stderr


def test_launch_args_reach_the_nodes():
    r = subprocess.run(["roslaunch", "--dump-params", "mdr_slam", "mdr.launch", "bag:=/tmp/x.bag",
                        "pose_source:=groundtruth", "calib:=/tmp/c.yaml"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    import yaml
    params = yaml.safe_load(r.stdout)
    assert params["/use_sim_time"] is True
    assert params["/pose_node/source"] == "groundtruth"
    assert params["/depth_node/calib"] == "/tmp/c.yaml"
    r = subprocess.run(["roslaunch", "--dump-params", "mdr_slam", "mdr.launch"], capture_output=True,
                       text=True)
    # live: not set at all, so an including launch file's value stands
    assert "/use_sim_time" not in yaml.safe_load(r.stdout)


def test_bag_path_is_taken_from_the_callers_directory(tmp_path):
    """roslaunch runs rosbag play in ~/.ros: a relative bag:= must be made absolute from where
    the user typed the command, an absolute one kept."""
    def player(bag, cwd):
        env = dict(os.environ, PWD=str(cwd))   # what the shell sets
        r = subprocess.run(["roslaunch", "--args", "/bag_player", "mdr_slam", "mdr.launch",
                            "bag:=" + bag], capture_output=True, text=True, cwd=str(cwd), env=env)
        assert r.returncode == 0, r.stderr
        return [a for a in r.stdout.split() if a.endswith(".bag")][-1]
    assert player("output/sample/sequence.bag", tmp_path) == \
        os.path.join(str(tmp_path), "output/sample/sequence.bag")
    assert player("/data/x.bag", tmp_path) == "/data/x.bag"


def test_launch_prefix_args_reach_the_node_command():
    """pose_prefix / depth_prefix / fusion_prefix put a command in front of that node only."""
    def command(node, *args):
        r = subprocess.run(["roslaunch", "--args", node, "mdr_slam", "mdr.launch"] + list(args),
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        return r.stdout.strip().splitlines()[-1]
    # by default depth and fusion yield the CPU to the tracker
    assert command("/depth_node").startswith("nice -n 10 ")
    assert command("/fusion_node").startswith("nice -n 10 ")
    assert command("/pose_node").split()[0].endswith("/pose_node")
    assert command("/depth_node", "mapping_nice:=0").split()[0].endswith("/depth_node")
    assert command("/fusion_node", "mapping_nice:=5").startswith("nice -n 5 ")
    assert command("/depth_node", "depth_prefix:=nice -n 5").startswith("nice -n 5 ")
    assert not command("/pose_node", "depth_prefix:=nice -n 5").startswith("nice")
    assert command("/fusion_node", "fusion_prefix:=taskset -c 1").startswith("taskset -c 1 ")


def test_the_weak_texture_argument_sets_the_live_depth_node():
    """Live, the weak-texture matcher is off unless weak_texture:=sgbm (mdr run keeps the
    default, sgbm)."""
    def params(*args):
        r = subprocess.run(["roslaunch", "--dump-params", "mdr_slam", "mdr.launch"] + list(args),
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        return yaml.safe_load(r.stdout)
    assert params()["/depth_node/weak_texture"] == "off"
    assert params("weak_texture:=sgbm")["/depth_node/weak_texture"] == "sgbm"


@pytest.mark.parametrize("preset", ["sample", "euroc", "kitti"])
def test_dataset_presets_overlay_every_node(preset):
    """config/<preset>/{pose,depth,fusion}.yaml exist and launch's preset:= loads them over the
    defaults (the same overlay mdr run --preset applies)."""
    import yaml
    from mdr_slam.pipeline import config_dir, load_params
    r = subprocess.run(["roslaunch", "--dump-params", "mdr_slam", "mdr.launch", "preset:=" + preset],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    params = yaml.safe_load(r.stdout)
    for node in ("pose", "depth", "fusion"):
        path = os.path.join(config_dir(), preset, node + ".yaml")
        overlay = yaml.safe_load(open(path)) or {}
        merged = load_params(node, preset)
        for key, value in overlay.items():
            assert params["/%s_node/%s" % (node, key)] == value == merged[key], (node, key)
    if preset == "kitti":
        assert params["/depth_node/max_depth"] == 30.0


@pytest.mark.parametrize("kind,name", [
    ("msg", "TrackingState"), ("msg", "KeyFrame"), ("msg", "KeyFrameArray"),
    ("srv", "SaveMap"), ("srv", "LoadMap"), ("srv", "ExportMesh"), ("srv", "SaveTrajectory"),
])
def test_custom_messages_are_built(kind, name):
    tool = "rosmsg" if kind == "msg" else "rossrv"
    r = subprocess.run([tool, "show", "mdr_slam_msgs/" + name], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip(), r.stderr
    files = glob.glob(os.path.join(ROOT, "src", "mdr_slam_msgs", kind, "*." + kind))
    assert len(files) == (3 if kind == "msg" else 4)


def test_core_imports_without_ros():
    """The core library must not import rospy (nodes and conversions may)."""
    code = ("import sys, importlib, pkgutil, mdr_slam\n"
            "skip = ('mdr_slam.nodes', 'mdr_slam.conversions', 'mdr_slam.bagio')\n"
            "for m in pkgutil.walk_packages(mdr_slam.__path__, 'mdr_slam.'):\n"
            "    if not m.name.startswith(skip): importlib.import_module(m.name)\n"
            "bad = [m for m in ('rospy', 'rosbag', 'tf2_ros') if m in sys.modules]\n"
            "print(bad); sys.exit(1 if bad else 0)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_openblas_coretype_follows_the_cpu_flags(tmp_path, monkeypatch):
    """mdr_slam picks OpenBLAS's kernel family from /proc/cpuinfo flags (numpy's OpenBLAS falls
    back to AVX-less 'Prescott' kernels on CPUs newer than it), never overriding the user's."""
    import mdr_slam
    monkeypatch.delenv("OPENBLAS_CORETYPE", raising=False)
    monkeypatch.delenv("MDR_OPENBLAS_CORETYPE", raising=False)
    cases = {"fpu sse2 avx avx2 fma avx512f avx512dq avx512bw avx512vl": "SkylakeX",
             "fpu sse2 avx avx2 fma": "Haswell", "fpu sse2 sse4_2": None}
    for flags, want in cases.items():
        f = tmp_path / "cpuinfo"
        f.write_text("processor\t: 0\nflags\t\t: %s\n" % flags)
        assert mdr_slam._openblas_coretype(str(f)) == want, flags
    assert mdr_slam._openblas_coretype(str(tmp_path / "missing")) is None
    monkeypatch.setenv("OPENBLAS_CORETYPE", "Haswell")
    assert mdr_slam._openblas_coretype(str(f)) is None
    # in a fresh interpreter that imports mdr_slam before numpy, OpenBLAS loads the chosen kernels
    code = ("import os, mdr_slam, numpy\n"
            "from threadpoolctl import threadpool_info\n"
            "arch = [i.get('architecture') for i in threadpool_info() if i['internal_api'] == 'openblas']\n"
            "print(os.environ.get('OPENBLAS_CORETYPE'), arch)\n")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    chosen, arch = r.stdout.split(" ", 1)
    if chosen != "None" and "[]" not in arch:
        assert chosen in arch, r.stdout
