"""Map folders and the map directory.

A map folder holds what a robot keeps of a mapped place: the fusion node's dense map
(``dense_map.ply``) and the pose node's sparse map (``pose_map.npz``: keyframes, map points,
descriptors, covisibility; the bag-of-words database is rebuilt from it on loading). Each file
is written atomically and carries a format version, so the folder is always loadable.

ROS 1 has no authentication: anyone on the graph can call a node's services. A path given to any
service that reads or writes a file (``save_map``, ``load_map``, ``save_trajectory``,
``export_mesh``) is therefore resolved inside the node's ``map_dir``, and one outside it is
refused unless the node allows it (``allow_any_map_path``). Paths in the node's parameters are
the operator's and are not confined.

Autosave generations: a reset (or a replacing load, a bag loop) never overwrites the map that was
there: the autosave folder ``last`` is rotated to ``last.1`` ... ``last.<ROTATE_KEEP>`` when a new
session would write into it (:func:`session_folder`).
"""
from __future__ import annotations

import contextlib
import os

__all__ = ["DENSE_MAP_FILE", "POSE_MAP_FILE", "MapPathError", "default_map_dir", "resolve_map_path",
           "map_files", "SESSION_KEY", "ROTATE_KEEP", "new_session_id", "next_session_id",
           "folder_sessions", "check_folder_sessions", "generation", "rotate_folder", "folder_lock",
           "session_folder", "after_rotation", "find_session", "file_generation", "rotate_file"]

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


# ---------------------------------------------------------------------------- sessions, rotation
# A mapping session is one map being built: it starts with the nodes (a launch gives both the same
# ``session_id``), and a reset, a replacing load or a new timeline (bag loop) starts another. Each
# map file carries its session's id (``session_id``: dense_map.json, pose_map.npz), so a folder's
# parts can be checked to belong together.
SESSION_KEY = "session_id"
ROTATE_KEEP = 3          # autosave generations kept besides the live one: last.1 ... last.3
RUN_MARKER_SUFFIX = ".running"   # the nodes' run markers stay in the live folder on a rotation


def new_session_id() -> str:
    """A fresh session id: UTC time and a random suffix."""
    import time
    import uuid
    return time.strftime("%Y%m%dT%H%M%S", time.gmtime()) + "-" + uuid.uuid4().hex[:8]


def next_session_id(session: str) -> str:
    """The id of the session that follows ``session`` after a reset: ``<base>~<n+1>``. Two nodes
    of one session that each reset once derive the same id without talking to each other."""
    session = str(session or "")
    base, sep, n = session.rpartition("~")
    if sep and n.isdigit():
        return "%s~%d" % (base, int(n) + 1)
    return (session or new_session_id()) + "~1"


def _dense_session(folder: str):
    import json
    meta = os.path.join(folder, os.path.splitext(DENSE_MAP_FILE)[0] + ".json")
    if not os.path.isfile(os.path.join(folder, DENSE_MAP_FILE)) and not os.path.isfile(meta):
        return None
    try:
        with open(meta) as f:
            d = json.load(f)
        return str(d.get(SESSION_KEY) or "") if isinstance(d, dict) else ""
    except (IOError, OSError, ValueError):
        return ""


def _pose_session(folder: str):
    path = os.path.join(folder, POSE_MAP_FILE)
    if not os.path.isfile(path):
        return None
    import numpy as np
    try:
        with np.load(path, allow_pickle=False) as z:   # reads this one member only
            return str(z[SESSION_KEY]) if SESSION_KEY in z.files else ""
    except Exception:   # noqa: BLE001  (truncated, not an archive: no session to tell)
        return ""


def folder_sessions(folder: str) -> dict:
    """``{"dense": id, "pose": id}`` of the map files present in ``folder`` ("" for a file that
    carries no session id: written by an older MDR-SLAM, or unreadable); absent files are left
    out."""
    out = {}
    for part, read in (("dense", _dense_session), ("pose", _pose_session)):
        s = read(folder)
        if s is not None:
            out[part] = s
    return out


def check_folder_sessions(folder: str):
    """Whether a map folder's parts belong to one session: ``(ok, note)``. ``ok`` is False when
    the dense and the sparse map carry different session ids (they were mapped apart: loaded
    together the dense map would not fit the sparse map's frame); ``note`` says why, or warns of
    a part without a session id (older files), else is ""."""
    s = folder_sessions(folder)
    if len(s) < 2:
        return True, ""
    if not s["dense"] or not s["pose"]:
        return True, ("the %s map in %s carries no session id (saved by an older version): "
                      "cannot tell whether its parts belong together"
                      % ("dense" if not s["dense"] else "sparse", folder))
    if s["dense"] != s["pose"]:
        return False, ("the dense map (session %s) and the sparse map (session %s) in %s were "
                       "mapped in different sessions" % (s["dense"], s["pose"], folder))
    return True, ""


def generation(folder: str, k: int) -> str:
    """The ``k``-th older generation of an autosave folder (``last.1``); ``k`` 0: the folder."""
    return folder if k == 0 else "%s.%d" % (folder, k)


def rotate_folder(folder: str, keep: int = ROTATE_KEEP) -> bool:
    """``folder`` -> ``folder.1`` -> ... -> ``folder.<keep>`` (the oldest is deleted), each move
    one ``os.replace`` of a whole folder so both nodes' files move together; ``folder`` is made
    again, empty but for the nodes' run markers (moved back: they belong to the running nodes).
    False (nothing moved) when ``folder`` holds no map file. Call it under :func:`folder_lock`."""
    import shutil
    if not folder_sessions(folder):
        return False
    keep = max(1, int(keep))
    oldest = generation(folder, keep)
    if os.path.isdir(oldest):
        shutil.rmtree(oldest)
    for k in range(keep - 1, 0, -1):
        if os.path.isdir(generation(folder, k)):
            os.replace(generation(folder, k), generation(folder, k + 1))
    os.replace(folder, generation(folder, 1))
    os.makedirs(folder, exist_ok=True)
    old = generation(folder, 1)
    for name in os.listdir(old):
        if name.endswith(RUN_MARKER_SUFFIX):
            try:
                os.replace(os.path.join(old, name), os.path.join(folder, name))
            except OSError:
                pass
    return True


def find_session(folder: str, session: str, part: str, keep: int = ROTATE_KEEP):
    """The generation of the autosave ``folder`` (``folder``, ``folder.1``, ...) whose ``part``
    ("dense", "pose") is of ``session``, or None."""
    if not session:
        return None
    for k in range(0, max(1, int(keep)) + 1):
        if folder_sessions(generation(folder, k)).get(part) == session:
            return generation(folder, k)
    return None


def after_rotation(path: str, folder: str, keep: int = ROTATE_KEEP) -> str:
    """Where ``path`` (a generation of the autosave ``folder``) is after :func:`rotate_folder`."""
    for k in range(max(1, int(keep)) - 1, -1, -1):
        if os.path.abspath(path) == os.path.abspath(generation(folder, k)):
            return generation(folder, k + 1)
    return path


@contextlib.contextmanager
def folder_lock(folder: str):
    """An exclusive lock (``flock`` on ``<folder>.lock`` beside it) shared by the processes that
    write ``folder``'s generations: the pose and fusion nodes choose, rotate and write under it."""
    parent = os.path.dirname(os.path.abspath(folder))
    os.makedirs(parent, exist_ok=True)
    fd = os.open(os.path.abspath(folder) + ".lock", os.O_CREAT | os.O_RDWR, 0o644)
    try:
        try:
            import fcntl
            fcntl.flock(fd, fcntl.LOCK_EX)
        except ImportError:   # not POSIX: no lock (one node per folder)
            pass
        yield
    finally:
        os.close(fd)   # releases the lock


def session_folder(folder: str, session: str, part: str, keep: int = ROTATE_KEEP):
    """Where the ``part`` ("dense" or "pose") of session ``session`` is autosaved, rotating the
    autosave ``folder`` when needed so that no folder mixes sessions and no map is overwritten by
    another session's: returns ``(target, rotated)``. Call it under :func:`folder_lock` and write
    before releasing it.

    - ``folder`` holds nothing, or only files of ``session``: ``folder``;
    - else an older generation ``folder.k`` holds only files of ``session`` (the other node reset
      first and its new session took ``folder``): ``folder.k``, the session's files stay together;
    - else ``folder`` (another session's, or files without id) is rotated to ``folder.1`` and
      ``session`` starts in the emptied ``folder``.
    """
    s = folder_sessions(folder)
    if all(v == session for v in s.values()):
        return folder, False
    for k in range(1, max(1, int(keep)) + 1):
        sk = folder_sessions(generation(folder, k))
        if sk and all(v == session for v in sk.values()):
            return generation(folder, k), False
    return folder, rotate_folder(folder, keep)


def file_generation(path: str, k: int) -> str:
    """The ``k``-th older generation of a map file (``map.1.ply``); ``k`` 0: the file."""
    stem, ext = os.path.splitext(path)
    return path if k == 0 else "%s.%d%s" % (stem, k, ext)


def _file_members(path: str) -> list:
    """A dense map file and its sidecars (fusion.map_io: anchors, metadata)."""
    return [path, path + ".anchors.json", os.path.splitext(path)[0] + ".json"]


def rotate_file(path: str, keep: int = ROTATE_KEEP) -> bool:
    """A map that ``map_path`` names as a file, kept as :func:`rotate_folder` keeps a folder:
    ``map.ply`` -> ``map.1.ply`` -> ... -> ``map.<keep>.ply``, each with its sidecars (the oldest
    deleted). False (nothing moved) when the file does not exist."""
    if not os.path.isfile(path):
        return False
    keep = max(1, int(keep))
    for m in _file_members(file_generation(path, keep)):
        if os.path.exists(m):
            os.remove(m)
    for k in range(keep - 1, -1, -1):
        for src, dst in zip(_file_members(file_generation(path, k)),
                            _file_members(file_generation(path, k + 1))):
            if os.path.exists(src):
                os.replace(src, dst)
    return True
