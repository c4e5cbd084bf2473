"""Thin rospy shells around the core: parameters, subscriptions, conversions, publishing.

Each module has a ``main()`` that the executables in ``src/mdr_slam/nodes/`` call. No algorithm
lives here: a node converts messages with mdr_slam.conversions, calls the core, and publishes.
"""


def node_configs(node: str) -> tuple:
    """The Config classes of a node, ``pose``, ``depth`` or ``fusion``: its own parameters first,
    then those of the core classes it drives. The node's private parameters, its shipped
    config/<node>.yaml and ``mdr run --set NODE.KEY=...`` override their fields."""
    from .config import NODE_CONFIGS
    if node not in NODE_CONFIGS:
        raise ValueError("node must be pose, depth or fusion, got %r" % node)
    return NODE_CONFIGS[node]


def node_defaults(node: str) -> dict:
    """Every parameter a node reads, with its default (see :func:`node_configs`); a key outside
    them is a typo."""
    out = {}
    for c in node_configs(node):
        out.update(c.defaults())
    return out
