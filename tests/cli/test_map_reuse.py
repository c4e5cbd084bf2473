"""Map once, navigate many times (offline): map folders, the map directory, and `mdr run --map
--localization` on a map made by an earlier run. The nodes' side (launch file, respawn, services)
is tests/test_map_reuse_e2e.py."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from mdr_slam.fusion import VoxelMap
from mdr_slam.fusion.map_io import load_dense_map, save_dense_map
from mdr_slam.io import read_tum
from mdr_slam.io.map_dir import MapPathError, map_files, resolve_map_path

MDR = [sys.executable, "-c", "import sys; from mdr_slam.cli import main; sys.exit(main())"]


# ---------------------------------------------------------------------- the map directory
def test_map_paths_stay_inside_the_map_directory(tmp_path):
    base = tmp_path / "maps"
    base.mkdir()
    assert resolve_map_path("m1", str(base)) == str(base / "m1")
    assert resolve_map_path(str(base / "a" / "b"), str(base)) == str(base / "a" / "b")
    for bad in ("../escape", str(tmp_path / "elsewhere"), "/etc", "a/../../x"):
        with pytest.raises(MapPathError, match="outside the map directory"):
            resolve_map_path(bad, str(base))
    (base / "link").symlink_to(tmp_path)          # a link inside that leads outside
    with pytest.raises(MapPathError):
        resolve_map_path("link/x", str(base))
    with pytest.raises(MapPathError, match="no map path"):
        resolve_map_path("  ", str(base))
    assert resolve_map_path("/tmp/x", str(base), allow_outside=True) == os.path.realpath("/tmp/x")


# ---------------------------------------------------------------------- dense map folders
def _small_map():
    rng = np.random.RandomState(3)
    m = VoxelMap(voxel_size=0.05)
    for i in range(4):    # four sightings of one wall: the points come of age
        P = np.column_stack([rng.uniform(-1, 1, 400), rng.uniform(-1, 1, 400), np.full(400, 2.0)])
        m.integrate(P, np.eye(4), 0.1 * i, anchor_id=0, T_map_anchor=np.eye(4))
    return m


def test_dense_map_folder_round_trip(tmp_path):
    m = _small_map()
    folder = str(tmp_path / "map")
    n = save_dense_map(m, folder)
    assert n == len(m) > 100
    meta = json.load(open(os.path.join(folder, "dense_map.json")))
    assert meta["format_version"] == 1 and meta["points"] == n
    m2 = VoxelMap(voxel_size=0.05)
    assert load_dense_map(m2, folder) == n
    a, b = m.to_cloud(), m2.to_cloud()
    np.testing.assert_allclose(np.sort(a["x"]), np.sort(b["x"]))
    assert sorted(m2.anchors) == sorted(m.anchors)


@pytest.mark.parametrize("damage", ["truncated", "random", "version", "no_description"])
def test_a_bad_dense_map_is_refused_and_the_map_kept(tmp_path, damage):
    folder = str(tmp_path / "map")
    save_dense_map(_small_map(), folder)
    ply, meta = map_files(folder)["dense"], os.path.join(folder, "dense_map.json")
    if damage == "truncated":
        data = open(ply, "rb").read()
        open(ply, "wb").write(data[: len(data) // 2])
    elif damage == "random":
        open(ply, "wb").write(np.random.RandomState(0).bytes(5000))
    elif damage == "version":
        d = json.load(open(meta))
        d["format_version"] = 99
        json.dump(d, open(meta, "w"))
    else:
        os.unlink(meta)
    keep = _small_map()
    n = len(keep)
    with pytest.raises(ValueError) as e:
        load_dense_map(keep, folder)
    print(damage, "->", e.value)
    assert len(keep) == n                         # the map it would have replaced is untouched
    if damage == "version":
        assert "version 99" in str(e.value)


# ---------------------------------------------------------------------- mdr run --map
def _mdr(*args):
    r = subprocess.run(MDR + list(args), capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    return r


def test_mdr_run_localizes_in_the_map_of_an_earlier_run(small_sim, tmp_path):
    """Run 1 maps the first 8 s with ORB poses and writes DIR/map; run 2 starts 3 s into the
    same bag with --map DIR/map --localization: it relocalizes at once, makes no keyframe, its
    poses are in run 1's map frame (on run 1's poses at the same stamps), its clouds land on
    run 1's dense map, and run 1's map files are not changed."""
    bag = os.path.join(small_sim, "sequence.bag")
    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    # ELAS on every pixel: the clouds-on-the-map median below measures the alignment with the
    # textured surfaces' precise points (weak-texture points at tau 0.02 on this quarter-size
    # camera scatter about 3 cm, whichever map they land on)
    small = ["--quiet", "--set", "depth.tau=0.02", "--set", "depth.weak_texture=off"]
    _mdr("run", bag, "--out", a, "--max-frames", "80", *small)
    s1 = json.load(open(os.path.join(a, "summary.json")))
    folder = os.path.join(a, "map")
    assert os.path.isfile(map_files(folder)["pose"]) and os.path.isfile(map_files(folder)["dense"])
    assert s1["keyframes_created"] > 3 and not s1["map_loaded"]
    before = {f: os.stat(os.path.join(folder, f)).st_mtime_ns for f in os.listdir(folder)}
    _mdr("run", bag, "--out", b, "--max-frames", "50", "--start", "3", "--map", folder,
         "--localization", *small)
    s2 = json.load(open(os.path.join(b, "summary.json")))
    t1, t2 = read_tum(os.path.join(a, "trajectory.tum")), read_tum(os.path.join(b, "trajectory.tum"))
    start = t1.stamps[0] + 3.0
    print("run 2: %d/%d frames posed, relocalized at +%.2f s, %d keyframes created; of its cloud "
          "points %.0f %% lie within 25 cm of run 1's dense map, at a median %.4f m"
          % (s2["frames_posed"], s2["frames_in"], s2["relocalized_at"] - start,
             s2["keyframes_created"], 100 * s2["clouds_on_loaded_surfaces"],
             s2["clouds_to_loaded_map_median_m"]))
    assert s2["map_loaded"] and s2["localization"]
    assert s2["frames_posed"] >= 0.9 * s2["frames_in"]
    assert s2["relocalized_at"] is not None and s2["relocalized_at"] - start <= 1.0
    assert s2["keyframes_created"] == 0
    assert s2["clouds_on_loaded_surfaces"] > 0.2 and s2["clouds_to_loaded_map_median_m"] <= 0.02
    # the poses of the common stamps: run 2 in run 1's map frame
    common = [t for t in t2.stamps if np.min(np.abs(t1.stamps - t)) < 1e-6]
    assert len(common) > 20
    p1 = np.array([t1.positions[np.argmin(np.abs(t1.stamps - t))] for t in common])
    p2 = np.array([t2.positions[np.argmin(np.abs(t2.stamps - t))] for t in common])
    d = np.linalg.norm(p1 - p2, axis=1)
    print("run 2 against run 1 at %d common stamps: median %.4f m, max %.4f m"
          % (len(common), np.median(d), d.max()))
    assert np.median(d) < 0.03
    after = {f: os.stat(os.path.join(folder, f)).st_mtime_ns for f in os.listdir(folder)}
    assert after == before


def test_a_bad_map_folder_starts_mdr_run_empty(small_sim, tmp_path):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "dense_map.json").write_text("{not json")
    out = str(tmp_path / "out")
    r = _mdr("run", os.path.join(small_sim, "sequence.bag"), "--out", out, "--max-frames", "15",
             "--quiet", "--map", str(bad))
    assert "could not load the map" in r.stderr
    s = json.load(open(os.path.join(out, "summary.json")))
    assert not s["map_loaded"] and s["map_load_error"] and s["frames_posed"] > 0
