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
