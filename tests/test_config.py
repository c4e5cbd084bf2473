"""The shipped parameter files and the code's defaults: one source of truth. Each node's YAML
may only override keys the code knows, and the values it ships are the code's defaults (so a
run without the YAML, a test of a core class, and the launch file compute the same thing)."""
from __future__ import annotations

import os

import pytest
import yaml

from conftest import ROOT

CONFIG = os.path.join(ROOT, "src", "mdr_slam", "config")


def _defaults(node):
    from mdr_slam.nodes import node_defaults
    return node_defaults(node)


def _same(a, b):
    if isinstance(a, dict) and isinstance(b, dict):
        return all(k in b and _same(v, b[k]) for k, v in a.items())
    if isinstance(a, bool) or isinstance(b, bool):
        return a == b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return float(a) == float(b)
    return a == b


@pytest.mark.parametrize("node", ["pose", "depth", "fusion"])
def test_shipped_yaml_agrees_with_the_code_defaults(node):
    shipped = yaml.safe_load(open(os.path.join(CONFIG, node + ".yaml")))
    defaults = _defaults(node)
    unknown = sorted(set(shipped) - set(defaults))
    assert not unknown, "%s.yaml has keys the code does not read: %s" % (node, unknown)
    differ = {k: (v, defaults[k]) for k, v in shipped.items() if not _same(v, defaults[k])}
    assert not differ, "%s.yaml (shipped, code): %s" % (node, differ)


def test_pose_yaml_lists_only_the_keys_a_user_tunes():
    """config/pose.yaml is the short list; the rest live, commented, in the code's defaults."""
    shipped = yaml.safe_load(open(os.path.join(CONFIG, "pose.yaml")))
    assert len(shipped) <= 25, sorted(shipped)
    for key in ("source", "backend", "n_features", "calib", "trajectory_path"):
        assert key in shipped, key


def _comment_blocks(path):
    """(first line number, length) of each comment: a run of comment-only lines, counting the
    line before it when that line ends in a comment the run continues."""
    blocks, start, n = [], None, 0
    prev_inline = False
    for i, line in enumerate(open(path).read().splitlines(), 1):
        if line.strip().startswith("#"):
            if start is None:
                start, n = (i - 1, 1) if prev_inline else (i, 0)
            n += 1
        else:
            if start is not None:
                blocks.append((start, n))
            start = None
        prev_inline = not line.strip().startswith("#") and " #" in line
    if start is not None:
        blocks.append((start, n))
    return blocks


@pytest.mark.parametrize("node", ["pose", "depth", "fusion"])
def test_yaml_comments_are_short(node):
    """Measurements behind a default belong in docs/experiments.md, not in the parameter file."""
    path = os.path.join(CONFIG, node + ".yaml")
    long = [(line, n) for line, n in _comment_blocks(path) if n > 4]
    assert not long, "%s.yaml comment blocks (first line, lines) longer than 4: %s" % (node, long)


def test_comment_block_counter():
    import tempfile
    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as f:
        f.write("# a\n# b\nx: 1   # c\n     # d\n     # e\ny: 2\n\n# f\n")
    try:
        assert _comment_blocks(f.name) == [(1, 2), (3, 3), (8, 1)]
    finally:
        os.unlink(f.name)


@pytest.mark.parametrize("preset", ["sample", "euroc", "kitti"])
def test_preset_files_override_known_keys_only(preset):
    for node in ("pose", "depth", "fusion"):
        path = os.path.join(CONFIG, preset, node + ".yaml")
        if os.path.exists(path):
            keys = set(yaml.safe_load(open(path)) or {})
            assert not keys - set(_defaults(node)), (path, keys - set(_defaults(node)))


def test_unknown_keys_are_refused_by_mdr_run():
    from mdr_slam.cli.main_run import _overrides
    assert _overrides(["depth.tau=0.02", "pose.n_features=1000"])["depth"] == {"tau": 0.02}
    with pytest.raises(SystemExit, match="no parameter 'tua'"):
        _overrides(["depth.tua=0.02"])


def test_config_refuses_unknown_keys_and_wrong_types():
    from mdr_slam.config import ConfigError
    from mdr_slam.pose import TrackerConfig
    assert TrackerConfig.from_dict({"n_features": 1000.0, "th_depth": 40}) == \
        TrackerConfig(n_features=1000, th_depth=40.0)
    for bad in ({"n_featurs": 1000}, {"n_features": "many"}, {"n_features": 10.5},
                {"loop_closing": 1}, {"lost_coast_s": 0.0}):   # a tuned constant is not a parameter
        with pytest.raises(ConfigError):
            TrackerConfig.from_dict(bad)
    assert TrackerConfig.pick({"n_features": 800, "map_frame": "world"}).n_features == 800
    assert TrackerConfig().replace(backend="orbslam3").backend == "orbslam3"


@pytest.mark.parametrize("node", ["pose", "depth", "fusion"])
def test_each_parameter_belongs_to_one_component(node):
    from mdr_slam.nodes import node_configs
    seen = {}
    for c in node_configs(node):
        for k in c.keys():
            assert k not in seen, "%s in both %s and %s" % (k, seen[k], c.__name__)
            seen[k] = c.__name__


def test_pose_parameters_are_few():
    """The tracker's tuned internals are constants in code; its configuration is what ORB-SLAM2's
    settings file holds, plus the switches of the system's threads and loops."""
    from mdr_slam.nodes import node_configs
    node, tracker = node_configs("pose")
    assert len(tracker.keys()) <= 15, tracker.keys()


def test_a_bad_value_in_mdr_run_set_is_refused():
    from mdr_slam.cli.main_run import _overrides
    with pytest.raises(SystemExit, match="n_features"):
        _overrides(["pose.n_features=many"])


@pytest.mark.ros
def test_a_node_names_its_unknown_parameters(roscore, start_process):
    """A typo in a node's parameters is logged as an error naming it (it would be ignored in
    silence otherwise); the node stays up."""
    from conftest import wait_for
    node = start_process(["rosrun", "mdr_slam", "fusion_node", "__name:=cfg_fusion",
                          "_voxel_sise:=0.05", "_autosave:=false", "_resume:=false",
                          "/mdr/map/points:=/cfg/map", "/mdr/map/grid:=/cfg/grid"], "fusion")
    assert wait_for(lambda: "unknown parameters" in node.output(), 30), node.output()
    line = [ln for ln in node.output().splitlines() if "unknown parameters" in ln][0]
    assert "~voxel_sise" in line and "voxel_size" not in line.replace("voxel_sise", ""), line
    assert node.proc.poll() is None


# ---------------------------------------------------------------- depth and fusion configurations
def test_depth_and_map_configs_refuse_wrong_types_and_unknown_keys():
    from mdr_slam.config import ConfigError
    from mdr_slam.depth import DepthConfig, ElasConfig
    from mdr_slam.fusion import VoxelMapConfig
    for cls, good, bad_type, unknown in (
            (DepthConfig, {"tau": 0.02}, {"tau": "x"}, {"tua": 0.02}),
            (ElasConfig, {"disp_max": 64}, {"disp_max": 64.5}, {"disp_maxx": 64}),
            (VoxelMapConfig, {"grace": 2}, {"grace": "x"}, {"gracee": 2.0})):
        assert cls.from_dict(good).to_dict() == dict(cls.defaults(), **good)
        with pytest.raises(ConfigError, match=list(bad_type)[0]):
            cls.from_dict(bad_type)
        with pytest.raises(ConfigError, match=list(unknown)[0]):
            cls.from_dict(unknown)
    # nested: the elas mapping is checked as an ElasConfig
    assert DepthConfig.from_dict({"elas": {"disp_max": 64}}).elas.subsampling is True
    with pytest.raises(ConfigError, match="disp_maxx"):
        DepthConfig.from_dict({"elas": {"disp_maxx": 64}})
    with pytest.raises(ConfigError, match="densify"):
        DepthConfig.from_dict({"densify": False})   # a bare off in YAML


def test_core_objects_built_without_arguments_use_the_shipped_yaml_values():
    """VoxelMap() and StereoDepth(camera) compute what the nodes compute with config/*.yaml."""
    from mdr_slam.camera import StereoCamera
    from mdr_slam.config import split_known
    from mdr_slam.depth import DepthConfig, StereoDepth
    from mdr_slam.fusion import VoxelMap, VoxelMapConfig
    from mdr_slam.nodes import node_configs
    fusion = yaml.safe_load(open(os.path.join(CONFIG, "fusion.yaml")))
    _, shipped = split_known(fusion, *node_configs("fusion"))
    m = VoxelMap()
    assert m.cfg == VoxelMapConfig.from_dict(shipped)
    assert {k: getattr(m.cfg, k) for k in shipped} == shipped
    assert m.max_depth == fusion["max_depth"] and m.voxel_size == fusion["voxel_size"]
    depth = yaml.safe_load(open(os.path.join(CONFIG, "depth.yaml")))
    _, shipped = split_known(depth, *node_configs("depth"))
    sd = StereoDepth(StereoCamera.from_rectified(64, 48, 50.0, 50.0, 31.5, 23.5, 0.1))
    assert sd.cfg == DepthConfig.from_dict(shipped)
    assert sd.filter.cfg is sd.cfg and sd.matcher.cfg == DepthConfig.from_dict(shipped).elas
