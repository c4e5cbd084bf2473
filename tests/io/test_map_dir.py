"""mdr_slam.io.map_dir: the path rule of every writing service, session ids of a map folder's
parts, and the rotation of the autosave folder (last -> last.1 -> ...)."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from mdr_slam.io.map_dir import (ROTATE_KEEP, MapPathError, check_folder_sessions, folder_lock,
                                 folder_sessions, generation, next_session_id, resolve_map_path,
                                 rotate_folder, session_folder)


def _dense(folder, session, points=1):
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "dense_map.ply"), "w") as f:
        f.write("ply %d\n" % points)
    meta = {"format": "mdr_slam dense map", "format_version": 1, "points": points}
    if session is not None:
        meta["session_id"] = session
    with open(os.path.join(folder, "dense_map.json"), "w") as f:
        json.dump(meta, f)


def _pose(folder, session):
    os.makedirs(folder, exist_ok=True)
    d = {"magic": np.array("mdr_slam pose map")}
    if session is not None:
        d["session_id"] = np.array(session)
    with open(os.path.join(folder, "pose_map.npz"), "wb") as f:
        np.savez(f, **d)


@pytest.mark.parametrize("path", ["../x.txt", "/tmp/x.txt", "a/../../x", "~/x.ply", "..",
                                  "a/../../../etc/passwd"])
def test_escaping_paths_are_refused(tmp_path, path):
    base = tmp_path / "maps"
    with pytest.raises(MapPathError, match="outside the map directory"):
        resolve_map_path(path, str(base))
    # allowed only when the node says so
    assert resolve_map_path(path, str(base), allow_outside=True)


def test_symlink_out_of_map_dir_is_refused(tmp_path):
    base = tmp_path / "maps"
    base.mkdir()
    os.symlink(str(tmp_path), str(base / "link"))
    with pytest.raises(MapPathError):
        resolve_map_path("link/x.ply", str(base))
    assert resolve_map_path("sub/x.ply", str(base)) == str(base / "sub" / "x.ply")


def test_next_session_id_is_shared_by_nodes_that_reset_alike():
    assert next_session_id("abc") == "abc~1"
    assert next_session_id("abc~1") == "abc~2"
    assert next_session_id(next_session_id("run")) == "run~2"
    assert next_session_id("")   # a fresh id


def test_folder_sessions_and_consistency(tmp_path):
    f = str(tmp_path / "m")
    assert folder_sessions(f) == {} and check_folder_sessions(f) == (True, "")
    _dense(f, "A")
    _pose(f, "A")
    assert folder_sessions(f) == {"dense": "A", "pose": "A"}
    assert check_folder_sessions(f) == (True, "")
    _pose(f, "B")
    ok, why = check_folder_sessions(f)
    assert not ok and "different sessions" in why and "A" in why and "B" in why
    _pose(f, None)   # an older file without id: loadable, with a note
    ok, why = check_folder_sessions(f)
    assert ok and "no session id" in why


def test_rotation_keeps_generations_and_run_markers(tmp_path):
    last = str(tmp_path / "last")
    assert not rotate_folder(last)           # nothing to rotate
    for i in range(ROTATE_KEEP + 2):
        _dense(last, "S%d" % i)
        _pose(last, "S%d" % i)
        with open(os.path.join(last, "pose_node.running"), "w") as f:
            f.write("run 1 S%d\n" % i)
        assert rotate_folder(last)
        assert folder_sessions(last) == {}   # emptied ...
        assert os.path.exists(os.path.join(last, "pose_node.running"))   # ... but the marker stays
        assert folder_sessions(generation(last, 1)) == {"dense": "S%d" % i, "pose": "S%d" % i}
    for k in range(1, ROTATE_KEEP + 1):      # the newest ROTATE_KEEP sessions, newest first
        i = ROTATE_KEEP + 2 - k
        assert folder_sessions(generation(last, k))["dense"] == "S%d" % i
    assert not os.path.exists(generation(last, ROTATE_KEEP + 1))


def test_session_folder_two_nodes_reset_one_after_the_other(tmp_path):
    """Both nodes autosave session A into last; the fusion node resets (A~1) and autosaves: last
    rotates to last.1 (both A files together); the pose node, still in A, then saves into last.1;
    it resets too (A~1) and its new map joins last. Every folder holds one session's maps."""
    last = str(tmp_path / "last")
    with folder_lock(last):
        assert session_folder(last, "A", "dense") == (last, False)
        _dense(last, "A", 787)
        assert session_folder(last, "A", "pose") == (last, False)
        _pose(last, "A")
        # fusion: keep its map before the reset (same session: same folder), then A~1
        assert session_folder(last, "A", "dense") == (last, False)
        assert session_folder(last, "A~1", "dense") == (last, True)
        _dense(last, "A~1", 127)
        assert folder_sessions(generation(last, 1)) == {"dense": "A", "pose": "A"}
        # pose, still in A: its autosave goes where A is
        assert session_folder(last, "A", "pose") == (generation(last, 1), False)
        _pose(generation(last, 1), "A")
        # pose resets: A~1 joins the fusion node's new map, nothing rotates
        assert session_folder(last, "A~1", "pose") == (last, False)
        _pose(last, "A~1")
    assert check_folder_sessions(last) == (True, "")
    assert check_folder_sessions(generation(last, 1)) == (True, "")
    assert not os.path.exists(generation(last, 2))


def test_session_folder_rotates_files_without_session(tmp_path):
    """Files of an older version (no id) are another session's: rotated, never overwritten."""
    last = str(tmp_path / "last")
    _dense(last, None)
    with folder_lock(last):
        assert session_folder(last, "B", "dense") == (last, True)
    assert folder_sessions(generation(last, 1)) == {"dense": ""}


def test_a_map_file_is_rotated_with_its_sidecars(tmp_path):
    """A map_path naming a file (map.ply) is kept as a folder is: map.ply -> map.1.ply ... with
    its anchors and metadata sidecars, the oldest generation dropped."""
    from mdr_slam.io.map_dir import file_generation, rotate_file
    p = str(tmp_path / "map.ply")
    assert not rotate_file(p, keep=2)
    for gen in range(3):
        for suffix in ("", ".anchors.json"):
            with open(p + suffix, "w") as f:
                f.write("gen%d" % gen)
        with open(str(tmp_path / "map.json"), "w") as f:
            f.write("meta%d" % gen)
        assert rotate_file(p, keep=2)
        assert not os.path.exists(p)
    assert file_generation(p, 1) == str(tmp_path / "map.1.ply")
    assert open(str(tmp_path / "map.1.ply")).read() == "gen2"
    assert open(str(tmp_path / "map.1.ply.anchors.json")).read() == "gen2"
    assert open(str(tmp_path / "map.1.json")).read() == "meta2"
    assert open(str(tmp_path / "map.2.ply")).read() == "gen1"
    assert not os.path.exists(str(tmp_path / "map.3.ply"))
