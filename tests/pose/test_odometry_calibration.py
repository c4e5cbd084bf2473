"""Online odometry calibration (mdr_slam.pose.odometry_calibration) on the simulated robot's wheel
odometry (mdr_slam.sim.robot.WheelOdometry: scale, rotation scale and yaw drift per metre, plus a
seeded random walk), driven along a route with straights and turns: the fitted errors, and the
pose coasted on the corrected odometry through a stretch without tracking."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mdr_slam.pose.odometry_calibration import MIN_TRAVEL_M, OdometryCalibration
from mdr_slam.sim.robot import WheelOdometry, base_matrix, compose2d

RATE = 50.0          # Hz of the odometry
FRAME_EVERY = 5      # a camera frame every 5 odometry steps (10 Hz)


def _drive(seconds, seed, v=0.4, scale_error=0.02, rot_scale_error=0.01, drift_deg=1.0):
    """(true T_map_base, raw T_odom_base) at 10 Hz along a route of straights and turns (left and
    right, some in place), the odometry integrated at 50 Hz."""
    rng = np.random.default_rng(seed)
    odo = WheelOdometry(scale_error, rot_scale_error, drift_deg, noise_lin=0.01, noise_yaw_deg=0.5,
                        seed=seed)
    x = y = yaw = 0.0
    out = []
    n = int(seconds * RATE)
    w = 0.0
    for i in range(n):
        if i % int(4 * RATE) == 0:       # a new manoeuvre every 4 s
            w = float(rng.choice([0.0, 0.0, 0.3, -0.3, 0.8, -0.8]))
        lin = v if abs(w) < 0.5 else (0.0 if rng.random() < 0.5 else 0.1)
        dt = 1.0 / RATE
        dx, dyaw = lin * dt, w * dt
        odo.update(dx, 0.0, dyaw, dt)
        x, y, yaw = compose2d(x, y, yaw, dx, 0.0, dyaw)
        if i % FRAME_EVERY == 0:
            out.append((i / RATE, base_matrix(x, y, yaw), odo.matrix()))
    return out


def _jitter(T, rng, pos=0.003, deg=0.05):
    """A tracked pose: the truth with the tracker's per-frame noise."""
    c = np.radians(deg) * rng.standard_normal()
    J = base_matrix(pos * rng.standard_normal(), pos * rng.standard_normal(), c)
    return T @ J


def test_fit_recovers_the_simulated_odometry_errors():
    cal = OdometryCalibration()
    rng = np.random.default_rng(3)
    for t, T_true, T_odo in _drive(300, seed=1):
        cal.correct(t, T_odo)
        cal.observe(t, _jitter(T_true, rng))
    assert cal.calibrated and cal.travel > 50
    print(cal.summary())
    assert cal.scale == pytest.approx(1.02, abs=0.005)
    assert cal.rot_scale == pytest.approx(0.01, abs=0.01)
    assert math.degrees(cal.drift) == pytest.approx(1.0, abs=0.25)


def test_coasting_on_the_corrected_odometry_stays_closer_than_on_the_raw_one():
    """Tracked for 200 s, then 30 s (about 10 m) without tracking: the pose carried on by the
    corrected odometry against the one carried on by the raw odometry (what map -> odom held at
    the last tracked frame gives), in three seeded drives."""
    errs_cal, errs_raw = [], []
    for seed in (11, 12, 13):
        cal = OdometryCalibration()
        rng = np.random.default_rng(seed)
        drive = _drive(230, seed=seed)
        split = int(200 * RATE / FRAME_EVERY)
        last = None
        for j, (t, T_true, T_odo) in enumerate(drive):
            cal.correct(t, T_odo)
            if j < split:
                cal.observe(t, _jitter(T_true, rng))
                last = (T_true, T_odo)
            else:
                cal.observe(t, None)
        t, T_true, T_odo = drive[-1]
        coasted = cal.coasted()
        raw = last[0] @ np.linalg.inv(last[1]) @ T_odo
        errs_cal.append(float(np.hypot(*(coasted[:2, 3] - T_true[:2, 3]))))
        errs_raw.append(float(np.hypot(*(raw[:2, 3] - T_true[:2, 3]))))
    print("position error after ~30 s untracked (m): corrected %s, raw %s"
          % (np.round(errs_cal, 3), np.round(errs_raw, 3)))
    assert np.mean(errs_cal) < 0.5 * np.mean(errs_raw) and max(errs_cal) < 0.15


def test_no_correction_before_enough_tracked_travel_and_a_restart_on_a_clock_jump():
    cal = OdometryCalibration()
    drive = _drive(20, seed=5)
    rng = np.random.default_rng(5)
    for t, T_true, T_odo in drive:
        out = cal.correct(t, T_odo)
        if cal.travel < MIN_TRAVEL_M:
            # identity correction: the chain is the raw odometry
            np.testing.assert_allclose(out, T_odo, atol=1e-9)
        cal.observe(t, _jitter(T_true, rng))
    assert cal.calibrated
    assert cal.coasted() is not None
    # the clock went back (a bag loop): the chain restarts at the raw pose, nothing to coast from
    t, _T, T_odo = drive[0]
    np.testing.assert_allclose(cal.correct(t, T_odo), T_odo)
    assert cal.coasted() is None


def test_pairs_across_a_jump_are_left_out():
    """A relocalization or a map correction moves the tracked pose between two frames by far more
    than the wheels moved: that pair says nothing of the odometry."""
    cal = OdometryCalibration()
    rng = np.random.default_rng(8)
    for j, (t, T_true, T_odo) in enumerate(_drive(60, seed=8)):
        cal.correct(t, T_odo)
        T = _jitter(T_true, rng)
        if j >= 300:
            T = base_matrix(0.5, -0.3, 0.2) @ T       # a correction of 0.58 m and 11 degrees
        cal.observe(t, T)
    assert cal.n_refused >= 1
    assert abs(math.degrees(cal.drift)) < 2.0 and abs(cal.scale - 1.02) < 0.01
