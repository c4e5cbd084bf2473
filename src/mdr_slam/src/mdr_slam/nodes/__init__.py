"""Thin rospy shells around the core: parameters, subscriptions, conversions, publishing.

Each module has a ``main()`` that the executables in ``src/mdr_slam/nodes/`` call. No algorithm
lives here: a node converts messages with mdr_slam.conversions, calls the core, and publishes.
"""


def node_defaults(node: str) -> dict:
    """Every parameter a node reads, with its default: ``pose``, ``depth`` or ``fusion`` (the
    node's own keys and those of the core class it drives). The shipped config/<node>.yaml
    only overrides these; a key outside them is a typo."""
    if node == "pose":
        from ..pose.params import DEFAULT_PARAMS
        from .pose_node import DEFAULTS
        return dict(DEFAULTS, **DEFAULT_PARAMS)
    if node == "depth":
        from ..depth import DEPTH_DEFAULTS
        from .depth_node import DEFAULTS
        return dict(DEFAULTS, **DEPTH_DEFAULTS)
    if node == "fusion":
        from .fusion_node import DEFAULTS
        return dict(DEFAULTS)
    raise ValueError("node must be pose, depth or fusion, got %r" % node)
