"""Map folders and the map directory.

A map folder holds what a robot keeps of a mapped place: the fusion node's dense map
(``dense_map.ply``) and the pose node's sparse map (``pose_map.npz``: keyframes, map points,
descriptors, covisibility; the bag-of-words database is rebuilt from it on loading). Each file
is written atomically and carries a format version, so the folder is always loadable.

ROS 1 has no authentication: anyone on the graph can call a node's services. A path given to a
save or load service is therefore resolved inside the node's ``map_dir``, and one outside it is
refused unless the node allows it (``allow_any_map_path``).
"""
from __future__ import annotations

import os

__all__ = ["DENSE_MAP_FILE", "POSE_MAP_FILE", "MapPathError", "default_map_dir", "resolve_map_path",
           "map_files"]

DENSE_MAP_FILE = "dense_map.ply"
POSE_MAP_FILE = "pose_map.npz"


class MapPathError(ValueError):
    """A map path that is empty or lies outside the map directory."""


def default_map_dir() -> str:
    """``$ROS_HOME/mdr_maps`` (ROS_HOME defaults to ``~/.ros``, as for roslaunch's logs)."""
    home = os.environ.get("ROS_HOME") or os.path.join(os.path.expanduser("~"), ".ros")
    return os.path.join(home, "mdr_maps")


def resolve_map_path(path: str, map_dir: str, allow_outside: bool = False) -> str:
    """The absolute path a service's ``path`` argument names: relative to ``map_dir`` (empty:
    :func:`default_map_dir`) when not absolute (``~`` expanded), symbolic links resolved; outside ``map_dir`` it raises
    :class:`MapPathError` unless ``allow_outside``."""
    if not str(path or "").strip():
        raise MapPathError("no map path given")
    base = os.path.realpath(os.path.expanduser(map_dir or default_map_dir()))
    p = os.path.expanduser(str(path).strip())
    if not os.path.isabs(p):
        p = os.path.join(base, p)
    p = os.path.realpath(p)
    if not allow_outside and os.path.commonpath([base, p]) != base:
        raise MapPathError("%s is outside the map directory %s (set allow_any_map_path to allow "
                           "it)" % (p, base))
    return p


def map_files(folder: str) -> dict:
    """``{"dense": path, "pose": path}`` of a map folder (the files need not exist)."""
    return {"dense": os.path.join(folder, DENSE_MAP_FILE),
            "pose": os.path.join(folder, POSE_MAP_FILE)}
