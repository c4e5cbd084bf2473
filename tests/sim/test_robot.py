"""mdr_slam.sim.robot: the simulated differential-drive robot's core (kinematics with limits,
wheel odometry drift, footprint collisions, the camera on its mast), without ROS."""
from __future__ import annotations

import numpy as np
import pytest

from mdr_slam.config import ConfigError
from mdr_slam.sim import make_scene
from mdr_slam.sim.driver import R_OPTICAL
from mdr_slam.sim.robot import (CONTACT_MARGIN, DiffDrive, Footprint, ObstacleMap, RobotConfig,
                                SimRobot, WheelOdometry, base_matrix, camera_pose,
                                mount_transform, parse_footprint, scene_start)

NO_NOISE = dict(odom_noise_lin=0.0, odom_noise_yaw=0.0)


@pytest.fixture(scope="module")
def scenes():
    made = {}

    def get(name):
        if name not in made:
            made[name] = make_scene(name)
        return made[name]
    return get


def robot(scenes, scene="garage", **kw):
    cfg = RobotConfig(scene=scene, scale=0.25, **kw)
    return SimRobot(cfg, scenes(scene))


def drive(r, v, w, seconds, vy=0.0):
    """Command (v, w) continuously (a fresh command every 0.1 s) for ``seconds``; returns the
    true (v, w) and pose after every 0.01 s physics step."""
    out = []
    for _ in range(int(round(seconds / 0.1))):
        r.command(v, vy, w)
        for _ in range(10):
            r.step(0.01)
            out.append((r.drive.v, r.drive.w, r.x, r.y, r.yaw))
    return np.array(out)


def test_kinematics_obey_velocity_and_acceleration_limits(scenes):
    # the garage's middle: 3 m of free floor in every direction
    r = robot(scenes, start_pose="12 8 0", max_vel_x=0.5, min_vel_x=-0.2, max_vel_theta=1.0,
              acc_lim_x=1.0, acc_lim_theta=2.0)
    tr = drive(r, 3.0, -5.0, 1.5)             # far beyond the limits
    v, w = tr[:, 0], tr[:, 1]
    assert v.max() == pytest.approx(0.5) and np.all(v <= 0.5 + 1e-12)
    assert w.min() == pytest.approx(-1.0) and np.all(w >= -1.0 - 1e-12)
    dv = np.diff(np.concatenate([[0.0], v])) / 0.01
    dw = np.diff(np.concatenate([[0.0], w])) / 0.01
    assert np.all(np.abs(dv) <= 1.0 + 1e-9) and np.all(np.abs(dw) <= 2.0 + 1e-9)
    # full speed after max / acc: 0.5 s for v, 0.5 s for w
    assert v[48] < 0.5 and v[49] == pytest.approx(0.5)
    assert w[48] > -1.0 and w[49] == pytest.approx(-1.0)
    # the pose follows the limited velocities (exact arcs): path length = integral of v
    steps = np.hypot(np.diff(tr[:, 2]), np.diff(tr[:, 3]))
    assert steps.sum() == pytest.approx(np.sum(v[1:]) * 0.01, rel=1e-3)
    assert r.distance == pytest.approx(np.sum(v) * 0.01, rel=1e-3)
    # reverse is limited too, and braking obeys the acceleration limit
    tr = drive(r, -3.0, 0.0, 1.0)
    assert tr[:, 0].min() == pytest.approx(-0.2)
    assert np.all(np.abs(np.diff(tr[:, 0])) <= 0.01 + 1e-9)
    assert r.n_collisions == 0


def test_command_timeout_stops_and_lateral_velocity_is_ignored(scenes):
    r = robot(scenes, start_pose="12 8 0", cmd_timeout=0.5)
    y0 = r.y
    r.command(0.3, 0.4, 0.0)          # a holonomic planner's strafe: no sideways motion
    for _ in range(40):               # 0.4 s: within the timeout, still driving
        r.step(0.01)
    assert r.drive.v == pytest.approx(0.3)
    assert abs(r.y - y0) < 1e-9 and r.lateral_commands == 1
    for _ in range(150):              # no new command: zero after 0.5 s, braking at acc_lim_x
        r.step(0.01)
    assert r.drive.v == 0.0
    r.command(0.2, 0.0, 0.0)
    assert r.lateral_commands == 1
    with pytest.raises(ValueError):
        r.command(float("nan"), 0.0, 0.0)


def test_diff_drive_arc_is_exact():
    dx, dy, dth = DiffDrive.increment(0.5, 1.0, np.pi)     # half a circle of radius 0.5
    assert (dx, dy, dth) == pytest.approx((0.0, 1.0, np.pi), abs=1e-12)
    assert DiffDrive.increment(0.5, 0.0, 2.0) == (1.0, 0.0, 0.0)


def test_odometry_drifts_as_configured(scenes):
    # systematic errors alone: a straight 2.25 m (ramps at 1 m/s^2 included) reads 2 % long
    # and turns left 1 deg per metre
    r = robot(scenes, start_pose="9 8 0", odom_scale_error=0.02, odom_yaw_drift=1.0,
              odom_rot_scale_error=0.05, **NO_NOISE)
    drive(r, 0.5, 0.0, 4.5)
    drive(r, 0.0, 0.0, 1.0)
    d = r.distance
    assert d == pytest.approx(2.25, abs=1e-6)
    assert r.odom.yaw == pytest.approx(np.deg2rad(1.0) * d, rel=1e-6)
    assert np.hypot(r.odom.x, r.odom.y) == pytest.approx(1.02 * d, rel=1e-4)
    # turning in place: the rotation reads 5 % large, no translation
    yaw0, odom_yaw0, x0 = r.yaw, r.odom.yaw, r.odom.x
    drive(r, 0.0, 0.5, 3.0)
    drive(r, 0.0, 0.0, 1.0)
    turned = np.angle(np.exp(1j * (r.yaw - yaw0)))
    assert turned > 1.0
    assert np.angle(np.exp(1j * (r.odom.yaw - odom_yaw0))) == pytest.approx(1.05 * turned, rel=1e-6)
    assert r.odom.x == pytest.approx(x0, abs=1e-12)
    # no error configured: odometry is the true motion from the start pose
    r = robot(scenes, start_pose="9 8 0.3", odom_scale_error=0.0, odom_yaw_drift=0.0,
              odom_rot_scale_error=0.0, **NO_NOISE)
    drive(r, 0.4, 0.3, 3.0)
    T_true = np.linalg.inv(base_matrix(9, 8, 0.3)) @ r.T_map_base()
    np.testing.assert_allclose(r.odom.matrix(), T_true, atol=1e-9)


def _noisy_run(scenes, seed, physics_rate=100.0):
    r = robot(scenes, start_pose="9 8 0", seed=seed, physics_rate=physics_rate,
              odom_scale_error=0.0, odom_yaw_drift=0.0, odom_rot_scale_error=0.0,
              odom_noise_lin=0.02, odom_noise_yaw=2.0)
    odo = []
    for _ in range(30):
        r.command(0.4, 0.0, 0.2)
        odo += [T for _, T, _, _ in r.advance(0.1)]
    return r, np.array(odo)


def test_odometry_noise_is_reproducible_with_a_seed(scenes):
    r1, a = _noisy_run(scenes, seed=5)
    r2, b = _noisy_run(scenes, seed=5)
    r3, c = _noisy_run(scenes, seed=6)
    assert len(a) == 150                  # 50 Hz over 3 s
    np.testing.assert_array_equal(a, b)
    assert np.abs(a[-1] - c[-1]).max() > 1e-4     # another seed drifts differently
    # the truth is the same whatever the seed: the noise is the odometry's only
    assert (r1.x, r1.y, r1.yaw) == (r3.x, r3.y, r3.yaw)
    T_true = np.linalg.inv(base_matrix(9, 8, 0)) @ r1.T_map_base()
    assert np.abs(a[-1][:2, 3] - T_true[:2, 3]).max() > 1e-4


def test_odometry_noise_grows_with_the_square_root_of_travel():
    """The random walk's spread matches its parameters and does not depend on the step size."""
    for dt in (0.01, 0.05):
        ends = []
        for seed in range(300):
            o = WheelOdometry(0.0, 0.0, 0.0, noise_lin=0.02, noise_yaw_deg=0.0, seed=seed)
            for _ in range(int(round(4.0 / dt))):     # 2 m straight at 0.5 m/s
                o.update(0.5 * dt, 0.0, 0.0, dt)
            ends.append(o.x - 2.0)
        # std of the along-track error: 0.02 m per sqrt(m) x sqrt(2 m) = 0.028 m
        assert np.std(ends) == pytest.approx(0.02 * np.sqrt(2.0), rel=0.15), dt
        assert abs(np.mean(ends)) < 0.006


def test_a_wall_stops_the_base_and_is_counted(scenes):
    # office: base at (4, 3) facing the east wall (x = 8), plain wall at y = 3; no back-off
    r = robot(scenes, "office", start_pose="4 3 0", backoff_distance=0.0, **NO_NOISE)
    assert r.n_collisions == 0
    tr = drive(r, 0.5, 0.0, 12.0)        # 3.8 m of floor to the wall, then keep pushing
    assert r.n_collisions == 1, r.collisions
    c = r.collisions[0]
    assert c.obstacle == "office_wall_x1"
    # the footprint never crossed into the wall; it stopped within a few mm of it
    assert np.all(tr[:, 2] <= 8.0 - 0.2 + 1e-9)
    assert 8.0 - 0.2 - r.x < 0.01
    assert r.clearance() < 0.01 and r.obstacles.collides(r.footprint, r.x, r.y, r.yaw) is None
    assert r.velocity == (0.0, 0.0) or r.drive.v < 0.02   # stopped, re-accelerating into it
    # pushing on is the same contact, not a new collision
    drive(r, 0.5, 0.0, 2.0)
    assert r.n_collisions == 1 and r.in_contact
    # back off, come again: a second collision
    drive(r, -0.2, 0.0, 1.0)
    assert not r.in_contact and r.clearance() > CONTACT_MARGIN
    drive(r, 0.3, 0.0, 3.0)
    assert r.n_collisions == 2
    # turning in place with a circular footprint touching the wall is free
    yaw = r.yaw
    drive(r, 0.0, 1.0, 1.0)
    assert r.n_collisions == 2 and abs(r.yaw - yaw) > 0.5


def test_the_bumper_marks_the_wall_the_base_is_pressed_against(scenes):
    """bumper/points: nothing until the base touches the wall; then points just outside the
    footprint towards the wall (the blocked motion's side), in the obstacle band; nothing once the
    base has backed off."""
    from mdr_slam.sim.robot import BUMPER_Z
    r = robot(scenes, "office", start_pose="4 3 0", backoff_distance=0.0, **NO_NOISE)
    drive(r, 0.5, 0.0, 2.0)
    assert len(r.bumper_points()) == 0
    drive(r, 0.5, 0.0, 10.0)
    P = r.bumper_points()
    assert r.in_contact and len(P) >= 3
    # in the map: beyond the footprint's front, at the wall (x = 8) within a few cm
    wx = r.x + np.cos(r.yaw) * P[:, 0] - np.sin(r.yaw) * P[:, 1]
    assert np.all(P[:, 0] > r.footprint.radius * 0.7) and np.all(np.abs(wx - 8.0) < 0.06), wx
    assert np.allclose(P[:, 2], BUMPER_Z) and 0.1 < BUMPER_Z < 1.5
    drive(r, -0.2, 0.0, 1.0)             # backing off: the contact is over
    assert len(r.bumper_points()) == 0
    # reversing into something puts the points behind
    r2 = robot(scenes, "office", start_pose="4 3 3.14159", backoff_distance=0.0, **NO_NOISE)
    drive(r2, -0.3, 0.0, 16.0)
    assert r2.in_contact and np.all(r2.bumper_points()[:, 0] < 0)


def test_the_base_backs_off_a_contact_whatever_it_is_commanded(scenes):
    """The safety back-off: after a contact the base reverses backoff_distance straight away from
    it at backoff_speed, forward commands ignored meanwhile; the bumper points stay where the wall
    was while it does; then the commands drive it again (into the wall: a second collision)."""
    r = robot(scenes, "office", start_pose="4 3 0", **NO_NOISE)
    assert r.cfg.backoff_distance == pytest.approx(0.15)
    tr = drive(r, 0.5, 0.0, 8.5)        # 3.8 m to the wall at 0.5 m/s, then 0.9 s pushing
    assert r.n_collisions == 1
    x_contact = np.max(tr[:, 2])
    assert 8.0 - 0.2 - x_contact < 0.01
    assert r.backoff_left > 0 and r.drive.v < 0 and r.x < x_contact    # reversing, pushed or not
    P = r.bumper_points()
    wx = r.x + np.cos(r.yaw) * P[:, 0] - np.sin(r.yaw) * P[:, 1]
    assert len(P) >= 3 and np.all(np.abs(wx - 8.0) < 0.06), wx
    tr = drive(r, 0.5, 0.0, 2.0)
    back = x_contact - np.min(tr[:, 2])
    assert back == pytest.approx(0.15, abs=0.02), back
    assert np.all(np.abs(tr[:, 1]) < 1e-9)       # straight back: no turning
    assert r.n_collisions == 2                   # the commands took over and hit the wall again
    # reversing into a wall: the back-off is forwards
    r2 = robot(scenes, "office", start_pose="4 3 3.14159", **NO_NOISE)
    tr = drive(r2, -0.3, 0.0, 16.0)
    assert r2.n_collisions >= 1
    k = np.argmax(tr[:, 2])
    assert 8.0 - 0.2 - tr[k, 2] < 0.01
    assert tr[k, 2] - np.min(tr[k:, 2]) == pytest.approx(0.15, abs=0.02)


def test_a_polygon_footprint_cannot_turn_into_a_wall(scenes):
    square = "[[0.3, 0.3], [-0.3, 0.3], [-0.3, -0.3], [0.3, -0.3]]"
    # 0.35 m from the wall: the square's corners (0.42 m out) sweep into it when turning
    r = robot(scenes, "office", start_pose="7.65 2.5 0", footprint=square, **NO_NOISE)
    assert not r.footprint.is_circle
    drive(r, 0.0, 1.0, 1.0)
    assert r.n_collisions == 1 and abs(r.yaw) < 0.2
    corners = (base_matrix(r.x, r.y, r.yaw) @ np.array(
        [[0.3, 0.3, 0, 1], [0.3, -0.3, 0, 1]]).T)[:2].T
    assert np.all(corners[:, 0] < 8.0)
    # the same square in the open turns freely
    r = robot(scenes, "office", start_pose="4 3 0", footprint=square, **NO_NOISE)
    drive(r, 0.0, 1.0, 2.0)
    assert r.n_collisions == 0


def test_obstacles_are_what_lies_between_the_floor_and_the_robot_height(scenes):
    office = scenes("office")
    fp = Footprint(0.2)
    obs = ObstacleMap(office, 0.03, 1.5)
    assert "floor_mat" not in obs.names and "office_floor" not in obs.names
    assert "office_ceiling" not in obs.names
    assert obs.collides(fp, 3.5, 2.5, 0.0) is None          # on the floor mat: free
    assert obs.collides(fp, 6.6, 0.75, 0.0).startswith(("desk", "monitor"))   # on a desk
    assert obs.collides(fp, 6.6, 1.3, 0.0) == "desk+y"      # its edge
    assert obs.clearance(fp, 6.6, 1.5, 0.0) == pytest.approx(1.5 - 1.15 - 0.2, abs=1e-9)
    # a doorway of the floor scene: passable under the lintel (2.1 m), not for a taller robot
    floor = scenes("floor")
    assert ObstacleMap(floor, 0.03, 1.5).collides(fp, 9.5, 2.4, np.pi / 2) is None
    assert ObstacleMap(floor, 0.03, 2.5).collides(fp, 9.5, 2.4, np.pi / 2) is not None
    # the start pose must be free
    with pytest.raises(ConfigError, match="overlaps"):
        robot(scenes, "office", start_pose="6.6 0.75 0")


def test_camera_pose_is_forward_looking_at_the_mast_height(scenes):
    h, p, fwd = 1.3, 0.05, 0.1
    T_base_cam = mount_transform(h, p, fwd) @ np.block([[R_OPTICAL, np.zeros((3, 1))],
                                                       [np.zeros((1, 3)), np.ones((1, 1))]])
    # REP-103: the optical z (forward) is the robot's x, tilted down by the pitch; x is right
    np.testing.assert_allclose(T_base_cam[:3, 2], [np.cos(p), 0, -np.sin(p)], atol=1e-12)
    np.testing.assert_allclose(T_base_cam[:3, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(T_base_cam[:3, 3], [fwd, 0, h], atol=1e-12)
    for yaw in (0.0, 1.0, -2.5):
        T = camera_pose(base_matrix(2.0, -1.0, yaw), T_base_cam)
        np.testing.assert_allclose(T[:3, 3], [2 + fwd * np.cos(yaw), -1 + fwd * np.sin(yaw), h],
                                   atol=1e-12)
        np.testing.assert_allclose(T[:3, 2], [np.cos(p) * np.cos(yaw), np.cos(p) * np.sin(yaw),
                                              -np.sin(p)], atol=1e-12)
    # the robot's camera: the scene trajectory's height and pitch (as the driver bags mount it)
    for name in ("office", "corridor", "garage", "floor"):
        r = robot(scenes, name)
        sh, sp, start = scene_start(scenes(name))
        assert (r.height, r.pitch) == (sh, sp)
        assert 1.25 <= r.height <= 1.4 and 0.0 < r.pitch < 0.1
        T = r.T_map_cam()
        assert T[2, 3] == pytest.approx(r.height)
        assert T[2, 2] == pytest.approx(-np.sin(r.pitch))
        assert np.arctan2(T[1, 2], T[0, 2]) == pytest.approx(r.yaw)
        assert r.clearance() > 0.1, name                     # the start is free
    # driver layouts: the left optical frame is where the rendered camera is, per the tf tree
    for layout in ("zed", "realsense", "stereo_image_proc"):
        r = robot(scenes, "office", layout=layout, start_pose="4 3 0")
        assert r.T_base_cam[:3, 2] == pytest.approx([np.cos(r.pitch), 0, -np.sin(r.pitch)])
        assert r.layout.static[0][0] == "base_link"


def test_the_rendered_pair_sees_the_wall_ahead(scenes):
    """Base facing the office's east wall: the depth on the optical axis is the distance from
    the mast's camera to the wall along its pitched axis."""
    r = robot(scenes, "office", start_pose="4 3 0", camera_height=1.3, camera_pitch=0.04)
    T = r.T_map_cam()
    f = r.sim.render(T, depth=True)
    H, W = f["depth"].shape
    assert f["left"].shape == (H, W) == (120, 188) and f["left"].dtype == np.uint8
    cx, cy = r.camera.cx, r.camera.cy
    z = f["depth"][int(round(cy)), int(round(cx))]
    assert z == pytest.approx((8.0 - 4.1) / np.cos(0.04), abs=0.02)
    pair = r.render(0)
    assert set(pair) >= {"left", "right"} and pair["left"].std() > 5


def test_config_is_checked():
    with pytest.raises(ConfigError, match="real_time_factor"):
        RobotConfig(real_time_factor=2.0).validate()
    with pytest.raises(ConfigError, match="scene"):
        RobotConfig(scene="moon").validate()
    with pytest.raises(ConfigError, match="start_pose"):
        RobotConfig(start_pose="1 2").validate()
    with pytest.raises(ConfigError):
        RobotConfig(footprint="[[0, 0], [1, 1]]").validate()
    with pytest.raises(ConfigError, match="physics_rate"):
        RobotConfig(physics_rate=10.0, max_vel_x=2.0).validate()
    assert parse_footprint("", 0.3).radius == 0.3
    fp = parse_footprint([[0.2, 0.1], [-0.2, 0.1], [-0.2, -0.1], [0.2, -0.1]], 0.3)
    assert not fp.is_circle and fp.radius == pytest.approx(np.hypot(0.2, 0.1))
