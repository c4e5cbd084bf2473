"""mdr_slam.pose.map_io: the pose tracker's sparse map saved to one .npz and loaded into a new
System, which then relocalizes in it; bad files are refused with PoseMapError."""
from __future__ import annotations

import os

import numpy as np
import pytest

from mdr_slam.camera import StereoCamera
from mdr_slam.geometry import make_T
from mdr_slam.pose import Frame, System
from mdr_slam.pose.map_io import (FORMAT_VERSION, MP_FIELDS, PoseMapError, load_pose_map,
                                  save_pose_map)
from mdr_slam.pose.synthetic import BoxRoom, orbit_trajectory
from scipy.spatial.transform import Rotation

CAM = StereoCamera.from_rectified(480, 320, 300.0, 300.0, 240.0, 160.0, 0.12)
# the map frame is not the first camera's: base_link-like, turned and shifted
T_MAP_CAM0 = make_T(Rotation.from_euler("xz", [-90, -90], degrees=True).as_matrix(),
                    [0.3, -0.2, 0.5])
MID = 15   # the frame the second run starts with


@pytest.fixture(scope="module")
def room():
    return BoxRoom((3.0, 1.5, 3.0), tex_size=768, seed=3)


N_FIRST = 30   # frames of the first run; the second run goes on past them into unmapped views


@pytest.fixture(scope="module")
def sequence(room):
    """38 frames on a 1 m circle, 3.2 degrees apart, 0.05 s apart."""
    poses = orbit_trajectory(38, radius=1.0, arc=np.pi / 2 * 38 / 28.0)
    return poses, [room.render_stereo(T, CAM) for T in poses]


@pytest.fixture(scope="module")
def saved(sequence, tmp_path_factory):
    """The first run, tracked over N_FIRST frames, and its map saved."""
    images = sequence[1][:N_FIRST]
    s = System(CAM, threads=False, T_map_cam0=T_MAP_CAM0)
    res = [s.track(0.05 * i, l, r) for i, (l, r) in enumerate(images)]
    assert all(r.state == "OK" for r in res)
    path = str(tmp_path_factory.mktemp("posemap") / "room.posemap.npz")
    summary = save_pose_map(s, path)
    s.shutdown()
    return s, res, path, summary


def _loaded(path, threads=False):
    s = System(CAM, threads=threads)   # identity T_map_cam0: the file's must win
    summary = load_pose_map(s, path)
    return s, summary


def test_saved_map_loads_back_identically(saved):
    s1, _, path, summary = saved
    m1 = s1.map
    assert summary["keyframes"] == len(m1.good_keyframes()) >= 4
    assert summary["points"] == m1.n_points > 1000
    assert summary["images"] == summary["keyframes"]
    assert summary["bytes"] == os.path.getsize(path) > 0
    s2, got = _loaded(path)
    m2 = s2.map
    print("pose map: %d keyframes, %d points, %d bytes, saved in %.3f s, loaded in %.3f s"
          % (summary["keyframes"], summary["points"], summary["bytes"], summary["seconds"],
             got["seconds"]))
    assert (got["keyframes"], got["points"], got["bytes"]) == \
        (summary["keyframes"], summary["points"], summary["bytes"])
    assert m2 is s2.tracking.map is s2.local_mapping.map is s2.loop_closing.map
    assert sorted(m2.keyframes) == sorted(m1.keyframes)
    assert (m2.next_kf_id, m2.n, m2.n_loop_closures) == (m1.next_kf_id, m1.n, m1.n_loop_closures)
    for k, a in m1.keyframes.items():
        b = m2.keyframes[k]
        np.testing.assert_allclose(b.T_cw, a.T_cw, atol=1e-12)
        assert b.connections == a.connections and b.loop_edges == a.loop_edges
        assert (b.parent.id if b.parent else None) == (a.parent.id if a.parent else None)
        assert b.bad == a.bad and (b.frame_id, b.stamp) == (a.frame_id, a.stamp)
        assert (b.T_cp is None) == (a.T_cp is None)
        for name in ("uv", "octave", "angle", "desc", "ur", "depth", "mp_ids", "tex_w",
                     "scale", "inv_level_sigma2"):
            np.testing.assert_array_equal(getattr(b, name), getattr(a, name), err_msg=name)
            assert getattr(b, name).dtype == getattr(a, name).dtype, name
        assert (b.fx, b.cx, b.bf, b.th_depth, b.nlevels, b.width) == \
            (a.fx, a.cx, a.bf, a.th_depth, a.nlevels, a.width)
        np.testing.assert_array_equal(s2.loop_closing.images[k][0], s1.loop_closing.images[k][0])
    good = ~m1.mp_bad[: m1.n]
    np.testing.assert_array_equal(~m2.mp_bad[: m2.n], good)
    for name in MP_FIELDS:
        np.testing.assert_array_equal(getattr(m2, name)[: m2.n], getattr(m1, name)[: m1.n])
    np.testing.assert_allclose(s2.T_map_world, T_MAP_CAM0)
    # the keyframe database answers: each keyframe's own words find it first
    db = s2.loop_closing.db
    assert sorted(db.bows) == sorted(k.id for k in m1.good_keyframes())
    for kf in m2.good_keyframes():
        top = db.query(s2.loop_closing.voc.transform(kf.desc), top=3)
        assert top[0][0] == kf.id
    # tracking waits for a relocalization; frames continue after the saved run's
    assert s2.tracking.state == "LOST" and s2.tracking.velocity is None
    assert s2.tracking.ref_kf is m2.keyframes[max(k.id for k in m2.good_keyframes())]
    assert Frame._next_id > max(k.frame_id for k in m2.keyframes.values())


def test_loaded_map_relocalizes_in_the_saved_frame(saved, sequence):
    _, res1, path, _ = saved
    poses, images = sequence
    s, _ = _loaded(path)
    t0 = 100.0   # a later run: stamps after every saved one
    errs, errs_true, states = [], [], []
    for i in range(MID, len(images)):
        r = s.track(t0 + 0.05 * i, *images[i])
        states.append(r.state)
        assert r.T_map_cam is not None, (i, r.state)
        if i < N_FIRST:   # the view the first run tracked: the same pose in the same map frame
            errs.append(np.linalg.norm(r.T_map_cam[:3, 3] - res1[i].T_map_cam[:3, 3]))
        T_true = T_MAP_CAM0 @ np.linalg.inv(poses[0]) @ poses[i]
        errs_true.append(np.linalg.norm(r.T_map_cam[:3, 3] - T_true[:3, 3]))
    print("relocalization: first frame %.4f m, worst %.4f m from the first run's pose; "
          "worst %.4f m from the truth" % (errs[0], max(errs), max(errs_true)))
    assert states[0] == "RELOCALIZED" and all(st == "OK" for st in states[1:])
    assert errs[0] < 0.03 and max(errs) < 0.03
    assert max(errs_true) < 0.05
    # mapping goes on in the loaded map: new keyframes take the next ids and later frame ids
    old = set(k for k in s.map.keyframes if k < saved[0].map.next_kf_id)
    new = [k for k in s.map.keyframes.values() if k.id not in old]
    assert new and min(k.id for k in new) == saved[0].map.next_kf_id
    assert min(k.frame_id for k in new) > max(s.map.keyframes[k].frame_id for k in old)
    s.shutdown()


def test_threaded_system_loads_and_relocalizes(saved, sequence):
    _, res1, path, _ = saved
    s, _ = _loaded(path, threads=True)
    try:
        r = s.track(100.0, *sequence[1][MID])
        assert r.state == "RELOCALIZED"
        assert np.linalg.norm(r.T_map_cam[:3, 3] - res1[MID].T_map_cam[:3, 3]) < 0.03
    finally:
        s.shutdown()


def test_localization_mode_makes_no_keyframes(saved, sequence):
    """Localization (ORB-SLAM2's localization mode): the loaded map is tracked against and never
    changed, even past the mapped views; mapping mode would add keyframes there."""
    _, _, path, _ = saved
    s, _ = _loaded(path)
    s.localization = True
    n_kfs, n_pts = len(s.map.keyframes), s.map.n
    states = [s.track(100.0 + 0.05 * i, *sequence[1][i]).state for i in range(MID, len(sequence[1]))]
    assert states[0] == "RELOCALIZED" and states.count("LOST") == 0, states
    assert len(s.map.keyframes) == n_kfs and s.map.n == n_pts and s.n_keyframes_created == 0
    s.shutdown()


def test_a_pose_guess_relocalizes_where_bag_of_words_does_not(saved, sequence, monkeypatch):
    """rviz's 2D Pose Estimate (/initialpose): with relocalization by bag of words finding no
    candidate, a guess 10 cm / 3 deg off the true pose brings tracking back."""
    from scipy.spatial.transform import Rotation
    _, res1, path, _ = saved
    s, _ = _loaded(path)
    monkeypatch.setattr(s, "relocalization_candidates", lambda frame: [])
    assert s.track(100.0, *sequence[1][MID]).state == "LOST"
    T = res1[MID + 1].T_map_cam.copy()
    T[:3, :3] = T[:3, :3] @ Rotation.from_euler("y", 3.0, degrees=True).as_matrix()
    T[:3, 3] += [0.1, 0.0, 0.0]
    s.set_pose_guess(T)
    r = s.track(100.05, *sequence[1][MID + 1])
    err = np.linalg.norm(r.T_map_cam[:3, 3] - res1[MID + 1].T_map_cam[:3, 3])
    print("pose guess: %s, %.4f m from the first run's pose" % (r.state, err))
    assert r.state == "RELOCALIZED" and err < 0.03
    s.shutdown()


def _assert_fresh_and_usable(s, images, T_map_world=np.eye(4)):
    """A refused load left the System empty: it starts a map of its own."""
    assert not s.map.keyframes and s.map.n == 0 and s.state == "NOT_INITIALIZED"
    assert not s.loop_closing.db.bows and not s.loop_closing.images
    np.testing.assert_allclose(s.T_map_world, T_map_world)
    r0 = s.track(0.0, *images[0])
    r1 = s.track(0.05, *images[1])
    assert r0.is_keyframe and r0.keyframe_id == 0 and r1.state == "OK"
    np.testing.assert_allclose(r0.T_map_cam, T_map_world, atol=1e-9)


def test_bad_files_are_refused_and_leave_the_system_usable(saved, sequence, tmp_path):
    _, _, path, _ = saved
    _, images = sequence
    blob = open(path, "rb").read()
    bad = {}
    bad["truncated"] = tmp_path / "truncated.npz"
    bad["truncated"].write_bytes(blob[: len(blob) // 2])
    bad["random"] = tmp_path / "random.npz"
    bad["random"].write_bytes(np.random.RandomState(0).bytes(4096))
    with np.load(path) as z:
        entries = {k: z[k] for k in z.files}
    bad["version"] = tmp_path / "version.npz"
    np.savez(str(bad["version"]), **dict(entries, format_version=np.int64(FORMAT_VERSION + 1)))
    bad["magic"] = tmp_path / "magic.npz"
    np.savez(str(bad["magic"]), **dict(entries, magic=np.array("something else")))
    bad["points"] = tmp_path / "points.npz"   # keypoints naming points beyond n_points
    np.savez(str(bad["points"]), **dict(entries, kp_mp_ids=entries["kp_mp_ids"] + 10 ** 6))
    bad["missing"] = tmp_path / "missing.npz"
    np.savez(str(bad["missing"]), **{k: v for k, v in entries.items() if k != "mp_pos"})
    bad["npy"] = tmp_path / "array.npy"
    np.save(str(bad["npy"]), np.zeros(3))
    bad["absent"] = tmp_path / "absent.npz"
    T = make_T(np.eye(3), [1.0, 2.0, 3.0])
    s = System(CAM, threads=False, T_map_cam0=T)
    messages = {}
    for name, p in bad.items():
        with pytest.raises(PoseMapError) as e:
            load_pose_map(s, str(p))
        messages[name] = str(e.value)
    assert "truncated" in messages["truncated"] and "version" in messages["version"]
    assert "not a pose map" in messages["magic"] and "mp_pos" in messages["missing"]
    assert "no pose map" in messages["absent"]
    _assert_fresh_and_usable(s, images, T)
    # another camera (a recalibration counts): refused, naming both cameras
    other = StereoCamera.from_rectified(480, 320, 301.0, 300.0, 240.0, 160.0, 0.12)
    s2 = System(other, threads=False)
    with pytest.raises(PoseMapError, match="another camera.*fx=300.*fx=301"):
        load_pose_map(s2, path)
    assert not s2.map.keyframes and s2.state == "NOT_INITIALIZED"
    with pytest.raises(PoseMapError, match="n_levels 1.2/8.*1.2/6"):   # another ORB pyramid
        load_pose_map(System(CAM, config={"n_levels": 6}, threads=False), path)
    # and a System with a map of its own is not overwritten
    with pytest.raises(PoseMapError, match="fresh"):
        load_pose_map(s, path)
    assert s.map.keyframes[0].T_cw is not None and len(s.map.keyframes) >= 1


def test_save_is_atomic_and_refuses_an_empty_map(saved, tmp_path, monkeypatch):
    s1, _, path, _ = saved
    with pytest.raises(PoseMapError, match="no map"):
        save_pose_map(System(CAM, threads=False), str(tmp_path / "empty.npz"))
    assert not os.listdir(str(tmp_path))
    target = tmp_path / "map.npz"
    save_pose_map(s1, str(target), images=False)
    before = target.read_bytes()

    def crash(f, **entries):   # dies half-way through writing
        f.write(b"PK\x03\x04 partial")
        raise RuntimeError("killed")
    monkeypatch.setattr(np, "savez_compressed", crash)
    with pytest.raises(RuntimeError):
        save_pose_map(s1, str(target))
    assert target.read_bytes() == before          # the old file, whole
    assert os.listdir(str(tmp_path)) == ["map.npz"]   # no temporary left behind
