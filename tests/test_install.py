"""The install space: `catkin_make install` of src/ into a temporary prefix, then roslaunch from it.

The build uses its own build, devel and install folders under a temporary directory (the
repository's build/ and devel/ are left alone). The launch runs in an environment where only that
install space is sourced: the repository's src/ and devel space are scrubbed from the ROS, CMake
and Python paths first, while the venv's python stays on PATH (the pip dependencies live there).
Also checks that package.xml names a rosdep key for every module the package imports, and that
the keys rosdistro does not know are defined in the shipped rosdep YAML.
"""
from __future__ import annotations

import ast
import filecmp
import glob
import os
import re
import subprocess
import sys
import time
import xmlrpc.client

import pytest
import yaml

from conftest import NodeProcess, wait_for

pytestmark = [pytest.mark.ros, pytest.mark.slow]

ROOT = os.path.realpath(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PKG = os.path.join(ROOT, "src", "mdr_slam")
ROSDEP_YAML = os.path.join(PKG, "rosdep", "mdr_slam.yaml")
NODES = ("pose_node", "depth_node", "fusion_node")
# the workspace's own spaces: nothing may be found through them when only the install is sourced
REPO_SPACES = [os.path.join(ROOT, d) for d in ("src", "devel", "build", "install")]
PATH_VARS = ("PATH", "PYTHONPATH", "ROS_PACKAGE_PATH", "CMAKE_PREFIX_PATH", "LD_LIBRARY_PATH",
             "PKG_CONFIG_PATH", "ROSLISP_PACKAGE_DIRECTORIES")

# rosdep keys resolved by rosdistro itself: ROS packages (noetic/distribution.yaml) and system
# packages (rosdep/python.yaml); any other key must come from the shipped YAML
ROS_KEYS = {"catkin", "rospy", "rosbag", "roslaunch", "rosbash", "rosgraph", "genpy",
            "message_filters", "tf2_ros", "tf2_msgs", "std_msgs", "std_srvs", "sensor_msgs",
            "geometry_msgs", "nav_msgs", "rosgraph_msgs", "diagnostic_msgs", "diagnostic_updater",
            "message_generation", "message_runtime", "actionlib", "actionlib_msgs",
            "move_base_msgs"}
SYSTEM_KEYS = {"python3-setuptools", "python3-rospkg", "python3-numpy", "python3-scipy",
               "python3-opencv", "python3-yaml", "python3-psutil", "python3-matplotlib",
               "python3-pil", "python3-pandas"}
# imported module -> rosdep key, where they differ (ROS modules are named as their packages)
MODULE_KEYS = {"numpy": "python3-numpy", "scipy": "python3-scipy", "cv2": "python3-opencv",
               "yaml": "python3-yaml", "psutil": "python3-psutil",
               "matplotlib": "python3-matplotlib", "PIL": "python3-pil",
               "rospkg": "python3-rospkg", "elas": "python3-pyelas-pip",
               "open3d": "python3-open3d-cpu-pip", "gtsam": "python3-gtsam-pip",
               "evo": "python3-evo-pip", "threadpoolctl": "python3-threadpoolctl-pip"}
# imported only by the optional pose backend, guarded by an ImportError check
OPTIONAL_MODULES = {"pyorbslam3": "python3-pyorbslam3-pip"}
STDLIB = frozenset(getattr(sys, "stdlib_module_names", ()))


def _inside(path: str, dirs) -> bool:
    p = os.path.realpath(path)
    return any(p == d or p.startswith(d + os.sep) for d in dirs)


def _scrubbed_env() -> dict:
    """os.environ without the workspace's src/, devel/ (and build/, install/) on any search path;
    the running python's folder (the venv) first on PATH."""
    env = dict(os.environ)
    for var in PATH_VARS:
        if var in env:
            kept = [p for p in env[var].split(os.pathsep) if p and not _inside(p, REPO_SPACES)]
            if kept:
                env[var] = os.pathsep.join(kept)
            else:
                del env[var]
    env["PATH"] = os.pathsep.join([os.path.dirname(sys.executable),
                                   env.get("PATH", "/usr/bin:/bin")])
    return env


def _sourced_env(setup_bash: str, base: dict) -> dict:
    """The environment after `source setup_bash` in bash, starting from ``base``."""
    r = subprocess.run(["bash", "-c", 'source "$1" >/dev/null && env -0', "_", setup_bash],
                       env=base, capture_output=True, timeout=60)
    assert r.returncode == 0, r.stderr.decode(errors="replace")
    env = {}
    for item in r.stdout.decode().split("\0"):
        if "=" in item:
            k, v = item.split("=", 1)
            env[k] = v
    return env


def _nul_list(path: str) -> list:
    """A /proc file of NUL-separated strings (cmdline, environ)."""
    with open(path, "rb") as f:
        return [x for x in f.read().decode(errors="replace").split("\0") if x]


def _files(top: str) -> set:
    """Relative paths of the files below ``top`` (following symlinks, as a user's copy would)."""
    out = set()
    for d, _, fs in os.walk(top, followlinks=True):
        out.update(os.path.relpath(os.path.join(d, f), top) for f in fs)
    return out


@pytest.fixture(scope="module")
def install_space(tmp_path_factory):
    """catkin_make install of the repository's src/ into a temporary workspace; its root."""
    ws = str(tmp_path_factory.mktemp("install_ws"))
    log = os.path.join(ws, "catkin_make.log")
    cmd = ["nice", "-n", "10", "catkin_make", "-C", ws, "--source", os.path.join(ROOT, "src"),
           "-DPYTHON_EXECUTABLE=" + sys.executable, "-DCATKIN_ENABLE_TESTING=0",
           "-DCMAKE_BUILD_TYPE=Release", "install", "-j2"]
    with open(log, "wb") as f:
        r = subprocess.run(cmd, env=_scrubbed_env(), cwd=ws, stdout=f, stderr=subprocess.STDOUT,
                           timeout=900)
    if r.returncode != 0:
        pytest.fail("catkin_make install failed:\n" + open(log, errors="replace").read()[-4000:])
    return ws


def test_install_space_has_the_package_files(install_space):
    prefix = os.path.join(install_space, "install")
    share = os.path.join(prefix, "share", "mdr_slam")
    for rel in ("launch/mdr.launch", "config/pose.yaml", "config/sample/pose.yaml",
                "rviz/mdr.rviz", "data/orb_vocab.npz", "scripts/env_loader.sh",
                "rosdep/mdr_slam.yaml", "package.xml"):
        p = os.path.join(share, rel)
        assert os.path.isfile(p) and not os.path.islink(p), "%s is not a real file" % p
    # every file of the source folders (launch/ and rviz/ are symlinks there) is installed
    for d in ("launch", "rviz", "config"):
        assert _files(os.path.join(PKG, d)) == _files(os.path.join(share, d)), d
    assert filecmp.cmp(os.path.join(PKG, "data", "orb_vocab.npz"),
                       os.path.join(share, "data", "orb_vocab.npz"), shallow=False)
    # the install must stand alone: no dangling link, none into the source tree
    for d, dirs, fs in os.walk(prefix):
        for name in dirs + fs:
            p = os.path.join(d, name)
            if os.path.islink(p):
                assert os.path.exists(p), "broken symlink %s -> %s" % (p, os.readlink(p))
                assert _inside(p, [os.path.realpath(prefix)]), \
                    "%s links out of the install prefix to %s" % (p, os.path.realpath(p))
    for exe in NODES + ("sim_robot_node", "mdr"):
        p = os.path.join(prefix, "lib", "mdr_slam", exe)
        assert os.path.isfile(p) and os.access(p, os.X_OK), p
    assert os.access(os.path.join(prefix, "bin", "mdr"), os.X_OK)
    assert glob.glob(os.path.join(prefix, "lib", "python*", "*-packages", "mdr_slam", "pose",
                                  "vocabulary.py"))
    assert glob.glob(os.path.join(prefix, "lib", "python*", "*-packages", "mdr_slam_msgs", "msg",
                                  "_KeyFrame.py"))


# the package's files as the library finds them: module, config folder, vocabulary
_WHERE = ("import os, mdr_slam, mdr_slam.pipeline as p, mdr_slam.pose.vocabulary as v; "
          "print(os.path.realpath(mdr_slam.__file__)); print(p.config_dir()); "
          "print(v.default_vocabulary_path())")


def _where(env: dict, cwd: str):
    r = subprocess.run(["python3", "-c", _WHERE], env=env, cwd=cwd, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout.split("\n")[:3]


def test_launch_runs_from_the_install_space_alone(install_space, roscore, tmp_path):
    prefix = os.path.realpath(os.path.join(install_space, "install"))
    env = _sourced_env(os.path.join(prefix, "setup.bash"), _scrubbed_env())
    for k in ("ROS_MASTER_URI", "ROS_IP", "ROS_LOG_DIR"):   # the private master of the fixture
        env[k] = os.environ[k]
    for var in PATH_VARS:
        leaked = [p for p in env.get(var, "").split(os.pathsep) if p and _inside(p, REPO_SPACES)]
        assert not leaked, "%s still points into the workspace: %s" % (var, leaked)

    r = subprocess.run(["rospack", "find", "mdr_slam"], env=env, capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() == os.path.join(prefix, "share", "mdr_slam"), \
        r.stdout + r.stderr
    r = subprocess.run(["roslaunch", "--files", "mdr_slam", "mdr.launch"], env=env,
                       capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.split() == \
        [os.path.join(prefix, "share", "mdr_slam", "launch", "mdr.launch")], r.stdout + r.stderr
    module, config, vocab = _where(env, str(tmp_path))
    assert _inside(module, [prefix]), module
    assert config == os.path.join(prefix, "share", "mdr_slam", "config")
    assert vocab == os.path.join(prefix, "share", "mdr_slam", "data", "orb_vocab.npz")

    import rosgraph
    master = rosgraph.Master("/test_install", master_uri=env["ROS_MASTER_URI"])

    def node_uri(name):
        """The URI of a live /name (a node of an earlier test killed without unregistering
        leaves a stale one until this launch's node takes the name over)."""
        try:
            uri = master.lookupNode("/" + name)
            xmlrpc.client.ServerProxy(uri).getPid("/test_install")
            return uri
        except Exception:
            return None

    launch = NodeProcess(["roslaunch", "mdr_slam", "mdr.launch"], env=env,
                         log=str(tmp_path / "roslaunch.log"))
    try:
        up = wait_for(lambda: all(node_uri(n) for n in NODES), timeout=60, period=0.5)
        assert up, "nodes did not register:\n" + launch.output()[-4000:]
        pid = xmlrpc.client.ServerProxy(node_uri("pose_node")).getPid("/test_install")[2]
        cmdline = _nul_list("/proc/%d/cmdline" % pid)
        assert os.path.join(prefix, "lib", "mdr_slam", "pose_node") in cmdline, cmdline
        # the node's own environment finds the package in the install prefix only
        node_env = dict(item.split("=", 1) for item in _nul_list("/proc/%d/environ" % pid)
                        if "=" in item)
        module, config, vocab = _where(node_env, str(tmp_path))
        assert _inside(module, [prefix]) and _inside(config, [prefix]) and \
            _inside(vocab, [prefix]), (module, config, vocab)
        time.sleep(3.0)     # a node that fails after registering would be reported by now
        out = launch.output()
        assert launch.proc.poll() is None, out[-4000:]
        assert "has died" not in out and "Traceback" not in out, out[-4000:]
    finally:
        launch.stop()
        # the session's master is shared: leave no launch parameters for later tests' nodes
        for name in ("/use_sim_time",) + tuple("/" + n for n in NODES):
            try:
                master.deleteParam(name)
            except Exception:
                pass


def test_vocabulary_path_outside_the_source_tree(tmp_path):
    """An installed copy of the library finds the vocabulary through the ROS package path, and
    without ROS falls back to the user cache (never to a folder beside the module)."""
    import shutil
    lib = tmp_path / "lib" / "python3" / "dist-packages"
    shutil.copytree(os.path.join(PKG, "src", "mdr_slam"), str(lib / "mdr_slam"),
                    ignore=shutil.ignore_patterns("__pycache__"))
    share = tmp_path / "share" / "mdr_slam"
    share.mkdir(parents=True)
    shutil.copy(os.path.join(PKG, "package.xml"), str(share))
    code = "from mdr_slam.pose.vocabulary import default_vocabulary_path as d; print(d())"
    env = _scrubbed_env()
    env.update(PYTHONPATH=str(lib), ROS_PACKAGE_PATH=str(tmp_path / "share"),
               HOME=str(tmp_path / "home"))
    r = subprocess.run([sys.executable, "-c", code], env=env, cwd=str(tmp_path),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(share / "data" / "orb_vocab.npz")
    del env["ROS_PACKAGE_PATH"]
    r = subprocess.run([sys.executable, "-c", code], env=env, cwd=str(tmp_path),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(tmp_path / "home" / ".cache" / "mdr_slam" / "orb_vocab.npz")


def _imported_modules() -> dict:
    """Top-level third-party modules imported anywhere in the package's code -> importing files."""
    files = [os.path.join(PKG, "nodes", f) for f in os.listdir(os.path.join(PKG, "nodes"))]
    for d, _, fs in os.walk(os.path.join(PKG, "src")):
        files += [os.path.join(d, f) for f in fs if f.endswith(".py")]
    out: dict = {}
    for path in files:
        with open(path) as f:
            tree = ast.parse(f.read(), path)
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in STDLIB and top != "mdr_slam":
                    out.setdefault(top, set()).add(os.path.relpath(path, PKG))
    return out


def _requirement_names() -> set:
    names = set()
    for line in open(os.path.join(ROOT, "requirements.txt")):
        m = re.match(r"\s*([A-Za-z0-9_.-]+)", line.split("#")[0])
        if m:
            names.add(m.group(1).lower())
    return names


@pytest.mark.skipif(not STDLIB, reason="needs sys.stdlib_module_names (Python 3.10)")
def test_package_xml_declares_rosdep_keys_for_every_import():
    from catkin_pkg.package import parse_package
    warnings: list = []
    pkg = parse_package(os.path.join(PKG, "package.xml"), warnings=warnings)
    pkg.validate(warnings=warnings)
    assert not warnings, warnings
    assert pkg.licenses == ["GPL-3.0-or-later"]
    pkg.evaluate_conditions(os.environ)
    run_keys = {d.name for d in pkg.exec_depends + pkg.build_export_depends
                if d.evaluated_condition is not False}
    missing = {}
    for mod, files in _imported_modules().items():
        if mod in OPTIONAL_MODULES:
            continue
        key = MODULE_KEYS.get(mod, mod)
        if key not in run_keys:
            missing[mod] = (key, sorted(files))
    assert not missing, "imported but not in package.xml (module: key, files): %s" % missing

    with open(ROSDEP_YAML) as f:
        rules = yaml.safe_load(f)
    workspace = {os.path.basename(os.path.dirname(p))
                 for p in glob.glob(os.path.join(ROOT, "src", "*", "package.xml"))}
    all_keys = {d.name for d in pkg.buildtool_depends + pkg.build_depends + pkg.exec_depends +
                pkg.build_export_depends + pkg.test_depends}
    undefined = sorted(k for k in all_keys - workspace - ROS_KEYS - SYSTEM_KEYS if k not in rules)
    assert not undefined, "keys neither standard nor in %s: %s" % (ROSDEP_YAML, undefined)

    # every shipped key installs a pinned requirement with pip on Debian and Ubuntu
    requirements = _requirement_names()
    shipped = {k for k in all_keys if k.endswith("-pip")} | set(OPTIONAL_MODULES.values())
    assert set(rules) >= shipped
    for key, rule in rules.items():
        for os_name in ("debian", "ubuntu"):
            pip = rule[os_name]["pip"]["packages"]
            assert pip and all(p.lower() in requirements for p in pip), (key, os_name, pip)


def test_env_loader_activates_the_venv_of_an_install_space(tmp_path):
    """A node started on another machine from an install space: catkin's setup.bash there does
    not know the venv of the pip dependencies, MDR_VENV names it."""
    scripts = tmp_path / "share" / "mdr_slam" / "scripts"
    scripts.mkdir(parents=True)
    loader = scripts / "env_loader.sh"
    loader.write_text(open(os.path.join(ROOT, "src", "mdr_slam", "scripts", "env_loader.sh")).read())
    (tmp_path / "setup.bash").write_text("# catkin's install-space setup.bash stands here\n")
    venv = sys.prefix   # the test's own venv
    cmd = ["bash", str(loader), "python3", "-c", "import sys; print(sys.prefix)"]
    bare = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    r = subprocess.run(cmd, env=dict(bare, MDR_VENV=venv), capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() == venv, r.stderr
    r = subprocess.run(cmd, env=bare, capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() != venv
    r = subprocess.run(cmd, env=dict(bare, MDR_VENV=str(tmp_path / "none")), capture_output=True,
                       text=True)
    assert r.returncode == 1 and "MDR_VENV" in r.stderr
