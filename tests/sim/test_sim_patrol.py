"""mdr_slam.sim patrols (``laps``) and the ``floor`` scene's long route."""
from __future__ import annotations

import subprocess

import numpy as np
import pytest
import yaml

from mdr_slam.sim import Simulator, build_trajectory, generate, make_scene, sim_camera
from mdr_slam.sim.generate import _MapCells

SMALL = dict(scale=0.25, workers=1, map_cell=0.05)


def _rot_angle(Ra, Rb):
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def _yaw(Ts):
    return np.unwrap(np.arctan2(Ts[:, 1, 2], Ts[:, 0, 2]))


@pytest.fixture(scope="module")
def scenes():
    return {name: make_scene(name) for name in ("office", "garage", "floor")}


# ------------------------------------------------------------------------------------ laps
@pytest.mark.parametrize("name,duration", [("office", 20.0), ("garage", 30.0), ("floor", None)])
def test_lap0_is_the_single_lap_trajectory(scenes, name, duration):
    one = build_trajectory(scenes[name], duration, seed=3)
    three = build_trajectory(scenes[name], duration, seed=3, laps=3)
    D = one.duration
    assert three.duration == pytest.approx(3 * D) and three.lap_duration == pytest.approx(D)
    assert [(k, pytest.approx(a), pytest.approx(b)) for k, a, b in three.laps] == \
        [(k, k * D, (k + 1) * D) for k in range(3)]
    t = np.linspace(0.0, D, 301)[:-1]
    np.testing.assert_array_equal(three.poses(t), one.poses(t))
    # segments: lap 0's are the single lap's, every lap has the same names shifted by D
    n = len(one.segments)
    assert three.segments[:n] == one.segments and len(three.segments) == 3 * n
    for k in (1, 2):
        for (na, a0, a1), (nb, b0, b1) in zip(one.segments, three.segments[k * n:(k + 1) * n]):
            assert na == nb and b0 == pytest.approx(a0 + k * D) and b1 == pytest.approx(a1 + k * D)


@pytest.mark.parametrize("name,duration", [("office", 20.0), ("floor", None)])
def test_laps_are_continuous_at_lap_boundaries(scenes, name, duration):
    tr = build_trajectory(scenes[name], duration, seed=1, laps=3)
    D = tr.lap_duration
    dt = 0.05
    t = np.arange(0.0, 3 * D, dt)
    Ts = tr.poses(t)
    step = np.linalg.norm(np.diff(Ts[:, :3, 3], axis=0), axis=1)
    turn = np.array([_rot_angle(Ts[i, :3, :3], Ts[i + 1, :3, :3]) for i in range(len(Ts) - 1)])
    for k in (1, 2):
        # the lap boundary itself: the end of lap k-1 is the start of lap k
        a, b = tr.poses([k * D - 1e-9, k * D])
        assert np.abs(a - b).max() < 1e-6
        # steps across the boundary look like the steps around it (no jump, no kink)
        near = tr.poses(k * D + dt * np.arange(-3, 4))
        s = np.linalg.norm(np.diff(near[:, :3, 3], axis=0), axis=1)
        r = [_rot_angle(near[i, :3, :3], near[i + 1, :3, :3]) for i in range(6)]
        assert max(s) <= 1.2 * step.max() + 1e-9 and max(r) <= 1.2 * turn.max() + 1e-9
        assert np.ptp(s) < 0.2 * step.mean() + 0.005          # speed continuous too
    # every lap starts at the same pose
    starts = tr.poses([0.0, D, 2 * D])
    assert np.abs(starts - starts[0]).max() < 1e-9


@pytest.mark.parametrize("name,duration", [("office", 20.0), ("garage", 30.0), ("floor", None)])
def test_laps_differ_slightly_and_stay_clear_of_walls(scenes, name, duration):
    sc = scenes[name]
    tr = build_trajectory(sc, duration, seed=2, laps=3)
    D = tr.lap_duration
    t = np.linspace(0.0, D, 400)
    laps = [tr.poses(t + k * D) for k in range(3)]
    for a, b in ((0, 1), (1, 2), (0, 2)):
        dp = np.linalg.norm(laps[a][:, :3, 3] - laps[b][:, :3, 3], axis=1)
        dyaw = _yaw(laps[a]) - _yaw(laps[b])
        dyaw = np.degrees(np.abs(dyaw - dyaw[0]))
        assert 0.02 < dp.max() < 0.3, (a, b, dp.max())        # a few cm up to ~0.15-0.25 m
        assert 0.3 < dyaw.max() < 12.0, (a, b, dyaw.max())    # a few degrees of swing
        assert dp[0] < 1e-9 and dp[-1] < 1e-6                 # same start and end pose
    P = np.concatenate([L[:, :3, 3] for L in laps])
    assert sc.distance_to_surfaces(P[::3]).min() > 0.3
    # a different seed gives different later laps, the same seed the same ones
    again = build_trajectory(sc, duration, seed=2, laps=3).poses(t + D)
    np.testing.assert_array_equal(again, laps[1])
    other = build_trajectory(sc, duration, seed=5, laps=2)
    assert not np.allclose(other.poses(t + D)[:, :3, 3] - other.poses(t)[:, :3, 3],
                           laps[1][:, :3, 3] - laps[0][:, :3, 3])


def test_corridor_and_pure_rotation_refuse_laps():
    with pytest.raises(ValueError, match="loop"):
        build_trajectory("corridor", 20.0, laps=2)
    with pytest.raises(ValueError, match="loop"):
        build_trajectory("pure_rotation", 20.0, laps=2)
    with pytest.raises(ValueError, match="laps"):
        build_trajectory("office", 20.0, laps=0)
    assert build_trajectory("corridor", 20.0, laps=1).kind == "corner"
    # the floor's route walked only in part is not a loop either
    with pytest.raises(ValueError, match="at least"):
        build_trajectory("floor", 30.0, laps=2)


@pytest.fixture(scope="module")
def patrol(tmp_path_factory):
    root = tmp_path_factory.mktemp("patrol")
    two = generate(str(root / "two"), scene="office", duration=0.5, seed=3, laps=2, **SMALL)
    one = generate(str(root / "one"), scene="office", duration=0.5, seed=3, **SMALL)
    return one, two


def test_patrol_summary_records_laps(patrol):
    one, two = patrol
    assert two["n_frames"] == 20 and two["duration"] == pytest.approx(1.0)
    assert two["lap_duration"] == pytest.approx(0.5)
    assert [(L["lap"], L["t0"], L["t1"], L["frames"]) for L in two["laps"]] == \
        [(0, pytest.approx(1.0), pytest.approx(1.5), [0, 10]),
         (1, pytest.approx(1.5), pytest.approx(2.0), [10, 20])]
    assert [(g["name"], g["lap"]) for g in two["segments"]] == \
        [("loop", 0), ("pure_rotation", 0), ("loop", 0), ("loop", 1), ("pure_rotation", 1),
         ("loop", 1)]
    y = yaml.safe_load(open(two["scene_yaml"]))
    assert y["laps"] == two["laps"] and y["segments"] == two["segments"]
    assert len(one["laps"]) == 1 and one["laps"][0]["frames"] == [0, 10]
    assert [g["lap"] for g in one["segments"]] == [0, 0, 0]


def test_patrol_gets_fresh_noise_per_lap(patrol):
    """Frames 0 and 10 are both at the lap start pose: the same scene content, other noise."""
    from mdr_slam.bagio import read_stereo_frames
    from mdr_slam.io import read_tum
    one, two = patrol
    gt = read_tum(two["groundtruth"]).matrices()
    np.testing.assert_allclose(gt[0], gt[10], atol=1e-6)
    frames = list(read_stereo_frames(two["bag"]))
    ref = list(read_stereo_frames(one["bag"]))
    for i in range(10):     # lap 0 is the single-lap sequence, byte for byte
        np.testing.assert_array_equal(frames[i].left, ref[i].left)
    for side in ("left", "right"):
        a = getattr(frames[0], side).astype(float)
        b = getattr(frames[10], side).astype(float)
        d = (a - b)[(a > 10) & (a < 245)]
        assert np.mean(d != 0) > 0.5                           # the noise differs...
        assert abs(d.mean()) < 0.5 and 2.0 < d.std() < 4.0     # ...and only the noise (2 * sqrt 2)


def test_patrol_gt_map_memory_does_not_grow_with_laps(patrol, scenes):
    one, two = patrol
    # one bit per scene cell whatever the laps; both laps see the same room
    assert _MapCells(scenes["office"], 0.05).total < 200000
    assert one["n_map_points"] <= two["n_map_points"] < 1.3 * one["n_map_points"]


def test_driver_bag_with_laps(tmp_path):
    import rosbag
    from mdr_slam.sim import generate_driver
    s = generate_driver(str(tmp_path), "realsense", compressed="png", scene="office",
                        duration=0.5, seed=1, laps=2, **SMALL)
    assert s["n_frames"] == 20 and len(s["laps"]) == 2
    with rosbag.Bag(s["bag"]) as bag:
        info = bag.get_type_and_topic_info().topics
        odom = [m for _, m, _ in bag.read_messages(topics=["/odom"])]
    assert info["/camera/infra1/image_rect_raw/compressed"].message_count == 20
    t = np.array([m.header.stamp.to_sec() for m in odom])
    assert t[0] == pytest.approx(1.0) and t[-1] == pytest.approx(1.95, abs=0.021)
    p = np.array([[m.pose.pose.position.x, m.pose.pose.position.y] for m in odom])
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    k = int(np.argmin(np.abs(t - 1.5)))       # the lap boundary: no jump in the odometry
    assert step[k - 2:k + 2].max() < 1.5 * np.median(step) + 1e-3


# ---------------------------------------------------------------------------------- floor
def test_floor_route_is_long_smooth_closed_and_clear_of_walls(scenes):
    sc = scenes["floor"]
    assert len(sc.rects) < 130        # render cost grows with the rects in view
    tr = build_trajectory(sc, None)
    g = tr.route
    assert g.length >= 100.0 and tr.closed
    dt = 0.05
    t = np.arange(0.0, tr.duration + 1e-9, dt)
    Ts = tr.poses(t)
    P = Ts[:, :3, 3]
    walked = np.linalg.norm(np.diff(P, axis=0), axis=1).sum()
    assert walked >= 100.0
    assert np.abs(np.diff(tr.poses([0.0, tr.duration]), axis=0)).max() < 1e-9   # closes
    assert sc.distance_to_surfaces(P[::2]).min() > 0.3
    speed = np.linalg.norm(np.diff(P, axis=0), axis=1) / dt
    assert speed.max() < 1.05 and 0.7 < walked / tr.duration < 1.0
    yaw_rate = np.degrees(np.abs(np.diff(_yaw(Ts)))) / dt
    assert yaw_rate.max() < 45.0
    assert np.all(np.abs(P[:, 2] - 1.3) < 0.05) and np.abs(Ts[:, 2, 2]).max() < 0.15
    # looks forward along the path
    fwd = Ts[:-1, :2, 2] / np.linalg.norm(Ts[:-1, :2, 2], axis=1)[:, None]
    move = np.diff(P[:, :2], axis=0) / np.maximum(speed[:, None] * dt, 1e-9)
    assert np.median(np.sum(fwd * move, axis=1)) > 0.97
    names = [s[0] for s in tr.segments]
    assert names == ["corridor", "lab", "corridor", "meeting", "corridor"]


def test_floor_route_views_have_texture(scenes):
    sc = scenes["floor"]
    tr = build_trajectory(sc, None)
    sim = Simulator(sc, sim_camera(scale=0.25), noise=0.0)
    for t in np.linspace(0.0, tr.duration, 9)[:-1] + 3.0:
        f = sim.render(tr.poses([t])[0])
        im = f["left"].astype(np.float32)
        grad = np.abs(np.diff(im, axis=1)).mean() + np.abs(np.diff(im, axis=0)).mean()
        assert grad > 1.5, (t, grad)
        assert np.median(f["depth"]) > 1.0, t        # not staring at a wall from up close
        assert (f["depth"] > 0).all()


def test_floor_short_duration_walks_the_route_start(scenes):
    tr = build_trajectory(scenes["floor"], 10.0)
    assert not tr.closed and tr.duration == 10.0
    P = tr.poses(np.arange(0.0, 10.0, 0.05))[:, :3, 3]
    assert 7.0 < np.linalg.norm(np.diff(P, axis=0), axis=1).sum() < 9.5   # ~0.9 m/s


def test_mdr_sim_floor_and_laps_cli(tmp_path):
    out = tmp_path / "floor"
    r = subprocess.run(["mdr", "sim", "--scene", "floor", "--scale", "0.25", "--duration", "2",
                        "--workers", "1", "--quiet", "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    from mdr_slam.bagio import read_stereo_frames
    frames = list(read_stereo_frames(str(out / "sequence.bag"), with_ground_truth=True))
    assert len(frames) == 40 and frames[0].left.shape == (120, 188)
    y = yaml.safe_load((out / "scene.yaml").read_text())
    assert y["scene"] == "floor" and y["trajectory"] == "route" and y["n_frames"] == 40
    assert y["options"]["map_cell"] == 0.02 and y["n_map_points"] > 10000
    assert y["laps"][0]["frames"] == [0, 40] and y["scene_info"]["n_rects"] == len(
        make_scene("floor").rects)
    r = subprocess.run(["mdr", "sim", "--scene", "corridor", "--laps", "2", "--duration", "1",
                        "--out", str(tmp_path / "c")], capture_output=True, text=True)
    assert r.returncode == 2 and "not return to its start" in r.stderr
    r = subprocess.run(["mdr", "sim", "--laps", "0", "--out", str(tmp_path / "z")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "positive" in r.stderr
    r = subprocess.run(["mdr", "sim", "--help"], capture_output=True, text=True)
    assert "--laps" in r.stdout and "floor" in r.stdout and "ONE lap" in r.stdout
