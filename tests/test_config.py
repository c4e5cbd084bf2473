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
    if node == "pose":
        from mdr_slam.nodes.pose_node import DEFAULTS
        from mdr_slam.pose.system import DEFAULT_PARAMS
        return dict(DEFAULTS, **DEFAULT_PARAMS)
    if node == "depth":
        from mdr_slam.depth import DEPTH_DEFAULTS
        from mdr_slam.nodes.depth_node import DEFAULTS
        return dict(DEFAULTS, **DEPTH_DEFAULTS)
    from mdr_slam.nodes.fusion_node import DEFAULTS
    return dict(DEFAULTS)


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
