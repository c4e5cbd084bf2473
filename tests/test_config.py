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
