"""Planar motion (a ground robot on a flat floor) and the wheel-odometry check of loops."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mdr_slam.camera import StereoCamera
from mdr_slam.geometry import inv_T, make_T
from mdr_slam.pose import System
from mdr_slam.pose.loop_closing import LoopClosing
from mdr_slam.pose.optimizer import bundle_adjust
from mdr_slam.pose.planar import PlanarMotion
from mdr_slam.pose.synthetic import BoxRoom, orbit_trajectory

CAM = StereoCamera.from_rectified(480, 320, 300.0, 300.0, 240.0, 160.0, 0.12)
FX, FY, CX, CY, BF, W, H = 300.0, 300.0, 240.0, 160.0, 300.0 * 0.12, 480, 320
# REP-103: the optical frame (z forward, x right, y down) on a base (x forward, y left, z up),
# 0.4 m up and pitched down 3 degrees
R_BC = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
T_BASE_CAM = make_T(Rotation.from_euler("y", 3.0, degrees=True).as_matrix() @ R_BC,
                    np.array([0.1, 0.0, 0.4]))
T_BASE_CAM_LEVEL = make_T(R_BC, np.array([0.1, 0.0, 0.4]))   # the orbit's camera is level


def _exp_left(dx, T):
    X = make_T(Rotation.from_rotvec(dx[3:]).as_matrix(), dx[:3])
    return X @ T


def test_planar_basis_update_and_projection():
    """The three planar directions are the optimizers' left perturbations of the base's x, y and
    yaw; updates stay on the plane exactly; projection removes height and tilt, keeps heading."""
    pm = PlanarMotion(T_BASE_CAM, T_BASE_CAM)
    rng = np.random.default_rng(0)
    T = np.eye(4)   # the first camera: the base at map's origin
    assert np.allclose(pm.off_plane(T), (0.0, 0.0), atol=1e-12)
    for _ in range(5):
        T = pm.update(T, rng.normal(size=3))
        assert np.allclose(pm.off_plane(T), (0.0, 0.0), atol=1e-9)
        assert np.allclose(pm.project(T), T, atol=1e-9)
    B = pm.basis(T)
    for i in range(3):
        xi = np.zeros(3)
        xi[i] = 1e-6
        assert np.allclose(pm.update(T, xi), _exp_left(B @ xi, T), atol=1e-11)
    # the base moved 2 cm along map x: the camera's world position moves along map x too
    T1 = pm.update(T, np.array([0.02, 0.0, 0.0]))
    d_map = pm.base_in_map(T1)[:3, 3] - pm.base_in_map(T)[:3, 3]
    assert np.allclose(d_map, [0.02, 0.0, 0.0], atol=1e-12)
    # off the plane (3 cm up, 1-2 degrees of tilt) -> back on it, yaw kept
    Tp = _exp_left(np.array([0.01, -0.03, 0.02, 0.02, 0.01, -0.01]), T)
    h, tilt = pm.off_plane(Tp)
    assert abs(h) > 0.005 and tilt > 0.01
    P = pm.project(Tp)
    assert np.allclose(pm.off_plane(P), (0.0, 0.0), atol=1e-9)
    yaw = [np.arctan2(pm.base_in_map(X)[1, 0], pm.base_in_map(X)[0, 0]) for X in (Tp, P)]
    assert abs(yaw[0] - yaw[1]) < 1e-9


def _points_and_views(rng, Ts, n=300):
    P = rng.uniform([-2.0, -0.8, 2.0], [2.0, 0.8, 5.0], size=(n, 3))
    cam_idx, pt_idx, obs = [], [], []
    for c, T in enumerate(Ts):
        Pc = P @ T[:3, :3].T + T[:3, 3]
        u = FX * Pc[:, 0] / Pc[:, 2] + CX
        v = FY * Pc[:, 1] / Pc[:, 2] + CY
        ur = u - BF / Pc[:, 2]
        ok = (Pc[:, 2] > 0.3) & (u > 0) & (u < W) & (v > 0) & (v < H)
        for j in np.nonzero(ok)[0]:
            cam_idx.append(c)
            pt_idx.append(j)
            obs.append((u[j], v[j], ur[j]))
    obs = np.array(obs) + rng.normal(0.0, 0.5, size=(len(obs), 3))
    return P, np.array(cam_idx), np.array(pt_idx), obs


def test_bundle_adjustment_keeps_cameras_on_the_plane():
    """A local BA with planar: cameras start on the plane with errors in x, y and yaw and come out
    on the plane (to rounding) and nearer the truth; without it the same noisy problem leaves
    them off the plane."""
    pm = PlanarMotion(T_BASE_CAM, T_BASE_CAM)
    rng = np.random.default_rng(3)
    truth = [np.eye(4)]
    for _ in range(5):
        truth.append(pm.update(truth[-1], np.array([0.15, 0.03, 0.05])))
    P, cam_idx, pt_idx, obs = _points_and_views(rng, truth)
    start = [truth[0]] + [pm.update(T, rng.normal(0.0, [0.02, 0.02, 0.01])) for T in truth[1:]]
    P0 = P + rng.normal(0.0, 0.02, size=P.shape)
    fixed = np.array([True] + [False] * 5)
    intr = (FX, FY, CX, CY, BF)
    args = (np.array(start), fixed, P0, cam_idx, pt_idx, obs, np.ones(len(obs), bool),
            np.ones(len(obs)), intr, 10)
    err = {}
    for planar in (None, pm):
        Ts, _ = bundle_adjust(*args, planar=planar)
        off = max(abs(pm.off_plane(T)[0]) + pm.off_plane(T)[1] for T in Ts)
        err[planar is not None] = (off, max(np.linalg.norm(inv_T(T)[:3, 3] - inv_T(G)[:3, 3])
                                            for T, G in zip(Ts, truth)))
    assert err[True][0] < 1e-9, err
    assert err[False][0] > 1e-4, err          # the unconstrained BA moves them off the plane
    assert err[True][1] < 0.01, err


@pytest.fixture(scope="module")
def planar_run():
    """The test_pose orbit (a level camera turning on a 1 m circle) tracked with wheel odometry
    (a base under the camera, translations read 2 % long): planar_motion auto, true and false."""
    room = BoxRoom((3.0, 1.5, 3.0), tex_size=768, seed=3)
    poses = orbit_trajectory(28, radius=1.0, arc=np.pi / 2)
    images = [room.render_stereo(T, CAM) for T in poses]
    out = {}
    for mode in ("auto", "true", "false", "auto-no-odometry"):
        s = System(CAM, config={"planar_motion": mode.split("-")[0]}, threads=False,
                   T_map_cam0=T_BASE_CAM_LEVEL)
        res = []
        for i, (l, r) in enumerate(images):
            f = s.make_frame(0.05 * i, l, r)
            if mode != "auto-no-odometry":
                T = inv_T(poses[0]) @ poses[i]
                T[:3, 3] *= 1.02
                f.T_odom_cam = T_BASE_CAM_LEVEL @ T
            res.append(s.track(f.stamp, frame=f))
        s.shutdown()
        out[mode] = (s, res, poses)
    return out


def test_tracking_with_planar_motion_keeps_every_pose_on_the_floor(planar_run):
    """planar_motion auto (wheel odometry present) or true: every tracked pose and keyframe has
    the base at its height and level in map; false, or auto without odometry, leaves the
    six degrees of freedom (the poses then leave the plane by the tracker's noise)."""
    pm = PlanarMotion(T_BASE_CAM_LEVEL, T_BASE_CAM_LEVEL)

    def worst(s, res):
        Ts = [inv_T(inv_T(T_BASE_CAM_LEVEL) @ r.T_map_cam) for r in res if r.T_map_cam is not None]
        Ts += [k.T_cw for k in s.map.good_keyframes()]
        return max(abs(pm.off_plane(T)[0]) + pm.off_plane(T)[1] for T in Ts)
    got = {}
    for mode, (s, res, poses) in planar_run.items():
        assert [r.state for r in res].count("OK") == len(res), mode
        got[mode] = (s.map.planar is not None, worst(s, res))
    assert got["auto"][0] and got["true"][0], got
    assert not got["false"][0] and not got["auto-no-odometry"][0], got
    assert got["auto"][1] < 1e-9 and got["true"][1] < 1e-9, got
    assert got["false"][1] > 1e-5, got
    # and x, y, yaw as accurate as the free tracker's (the true path is on the plane)
    for mode in ("true", "false"):
        s, res, poses = planar_run[mode]
        T_true = inv_T(poses[0]) @ poses[-1]
        T_est = inv_T(T_BASE_CAM_LEVEL) @ res[-1].T_map_cam
        assert np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) < 0.03, mode


def _odometry_stub():
    """LoopClosing's odometry check on two keyframes 2 m apart along the camera's z."""
    def kf(i, T_wc, T_odom_cam):
        return SimpleNamespace(id=i, T_cw=inv_T(T_wc), T_odom_cam=T_odom_cam, bad=False)
    cand = kf(0, np.eye(4), np.eye(4))
    cur = kf(1, make_T(np.eye(3), [0.0, 0.0, 2.0]), make_T(np.eye(3), [0.0, 0.0, 2.0]))
    stub = SimpleNamespace(map=SimpleNamespace(keyframes={0: cand, 1: cur}), odom_checks=[])
    stub._odometry_path = lambda a, b: LoopClosing._odometry_path(stub, a, b)
    return stub, cur, cand


def test_a_loop_the_wheel_odometry_contradicts_is_refused():
    """A loop correction that leaves the current keyframe 0.5 m from where the odometry puts it
    relative to the loop keyframe (2 m of travel: allowed 0.1 + 0.05 x 2 = 0.2 m) is refused;
    one of 0.1 m is accepted; one that brings a map 0.5 m off the odometry back to it is
    accepted; without odometry every loop passes."""
    stub, cur, cand = _odometry_stub()
    check = LoopClosing.odometry_agrees
    shift = lambda d: make_T(np.eye(3), [d, 0.0, 0.0])   # S moves the keyframe by d along x
    assert not check(stub, cur, cand, shift(0.5))
    assert check(stub, cur, cand, shift(0.1))
    # a turn of 10 degrees about the keyframe: allowed 2 + 1.5 x 2 = 5 degrees
    C = inv_T(cur.T_cw)[:3, 3]
    R = Rotation.from_euler("y", 10.0, degrees=True).as_matrix()
    S_rot = make_T(R, C - R @ C)
    assert not check(stub, cur, cand, S_rot)
    assert stub.odom_checks[0][-1] is False and stub.odom_checks[0][2] == pytest.approx(2.0)
    # the map had the keyframe 0.5 m off the odometry: a loop that brings it back passes
    cur.T_cw = inv_T(make_T(np.eye(3), [0.5, 0.0, 2.0]))
    assert check(stub, cur, cand, shift(-0.5))
    cur.T_odom_cam = None
    assert check(stub, cur, cand, shift(3.0))


def test_a_loop_may_not_move_the_map_away_from_the_odometry():
    """Back 0.5 m from the loop keyframe after 30 m of odometry (bounds 1.6 m and 47 deg), the
    odometry's heading is 5 deg off the map's. Within those bounds, a loop that turns the map
    3 deg further from it is refused, and so is one that moves the keyframe 0.5 m away from the
    odometry's place (allowed 0.1 + 0.01 x 30 = 0.4 m); turning it 3 deg towards the odometry,
    1.5 deg away (a right loop where the odometry drifted the way the map did), or moving it
    0.2 m pass."""
    stub, cur, cand = _odometry_stub()
    stub._odometry_path = lambda a, b: 30.0
    Ry = lambda deg: Rotation.from_euler("y", deg, degrees=True).as_matrix()   # noqa: E731
    C = np.array([0.0, 0.0, 0.5])
    cur.T_cw = inv_T(make_T(np.eye(3), C))
    cur.T_odom_cam = make_T(Ry(5.0), C)

    def turn(deg):   # S turns the map by deg about the keyframe
        return make_T(Ry(deg), C - Ry(deg) @ C)
    check = LoopClosing.odometry_agrees
    assert not check(stub, cur, cand, turn(-3.0))
    _, _, _, _, _, a0, a1, ok = stub.odom_checks[-1]
    assert (a0, a1, ok) == (pytest.approx(5.0), pytest.approx(8.0), False)
    assert check(stub, cur, cand, turn(3.0))
    assert check(stub, cur, cand, turn(-1.5))
    assert not check(stub, cur, cand, make_T(np.eye(3), [0.5, 0.0, 0.0]))
    _, _, _, e0, e1, _, _, _ = stub.odom_checks[-1]
    assert e1 - e0 == pytest.approx(0.5, abs=0.01) and e1 < 1.6
    assert check(stub, cur, cand, make_T(np.eye(3), [0.2, 0.0, 0.0]))


def test_a_loop_is_checked_against_the_calibrated_odometry():
    """The raw odometry's yaw creep has put the current keyframe, 30 m on, 3 m to the side of
    where the map (right) has it; its calibrated chain agrees with the map. A look-alike loop
    that moves the keyframe 6 m brings it nearer the raw odometry's place (3 m off, before and
    after) and would pass on the raw odometry; against the calibrated one it goes from 0 to 6 m
    off and is refused. The loop that undoes a drifted map's 0.5 m passes either way."""
    def kf(i, T_wc, T_odom_cam, T_cal):
        return SimpleNamespace(id=i, T_cw=inv_T(T_wc), T_odom_cam=T_odom_cam,
                               T_odom_cam_calibrated=T_cal, bad=False)
    at = lambda x, z: make_T(np.eye(3), [x, 0.0, z])   # noqa: E731
    cand = kf(0, np.eye(4), np.eye(4), np.eye(4))
    cur = kf(1, at(0.0, 30.0), at(3.0, 30.0), at(0.0, 30.0))
    stub = SimpleNamespace(map=SimpleNamespace(keyframes={0: cand, 1: cur}), odom_checks=[])
    stub._odometry_path = lambda a, b: 30.0
    check = LoopClosing.odometry_agrees
    look_alike = at(6.0, 0.0)                            # S moves the keyframe 6 m along x
    assert not check(stub, cur, cand, look_alike)
    _, _, _, e0, e1, _, _, ok = stub.odom_checks[-1]
    assert (e0, e1, ok) == (pytest.approx(0.0), pytest.approx(6.0), False)
    raw = SimpleNamespace(**{**vars(cur), "T_odom_cam_calibrated": None})
    stub.map.keyframes[1] = raw
    assert check(stub, raw, cand, look_alike)            # 3 m off before and after: "no worse"
    cur.T_cw = inv_T(at(0.5, 30.0))                      # the map drifted 0.5 m
    assert check(stub, cur, cand, at(-0.5, 0.0))


def test_odometry_edge_jacobians_match_finite_differences():
    """The relative-pose residual's Jacobians (left updates of both poses) against central
    differences."""
    from mdr_slam.pose.optimizer import _relative_pose_terms
    rng = np.random.default_rng(1)
    Ts = np.array([_exp_left(rng.normal(0, 0.5, 6), np.eye(4)) for _ in range(2)])
    Z = _exp_left(np.r_[0.05, -0.02, 0.01, 0.02, -0.01, 0.03], Ts[0] @ inv_T(Ts[1]))
    edges = (np.array([0]), np.array([1]), Z[None], np.ones((1, 6)))
    r0, Ji = _relative_pose_terms(Ts, edges)
    for cam, J in ((0, Ji[0]), (1, -np.eye(6))):
        num = np.zeros((6, 6))
        for d in range(6):
            dx = np.zeros(6)
            dx[d] = 1e-6
            Tp, Tm = Ts.copy(), Ts.copy()
            Tp[cam] = _exp_left(dx, Ts[cam])
            Tm[cam] = _exp_left(-dx, Ts[cam])
            num[:, d] = (_relative_pose_terms(Tp, edges)[0][0] -
                         _relative_pose_terms(Tm, edges)[0][0]) / 2e-6
        # first order in the residual (r0 is a few cm / degrees): agree to a few percent
        assert np.abs(num - J).max() < 0.05, (cam, num, J)


def test_odometry_edges_hold_what_the_images_leave_free():
    """Two cameras seeing a handful of points on one small far patch: alone, the BA lets the
    second camera slide along the patch's ambiguity (lateral shift vs yaw); with a wheel-odometry
    edge between the two it stays within a few millimetres of the odometry's motion."""
    from mdr_slam.pose.optimizer import odometry_edges
    rng = np.random.default_rng(7)
    truth = [np.eye(4), _exp_left(np.r_[-0.3, 0.0, 0.0, 0.0, 0.0, 0.0], np.eye(4))]
    P = rng.uniform([-0.15, -0.15, 6.0], [0.15, 0.15, 6.3], size=(12, 3))
    cam_idx, pt_idx, obs = [], [], []
    for c, T in enumerate(truth):
        Pc = P @ T[:3, :3].T + T[:3, 3]
        for j, X in enumerate(Pc):
            cam_idx.append(c)
            pt_idx.append(j)
            obs.append((FX * X[0] / X[2] + CX, FY * X[1] / X[2] + CY, FX * X[0] / X[2] + CX - BF / X[2]))
    obs = np.array(obs) + rng.normal(0.0, 0.3, size=(len(obs), 3))
    start = [truth[0], _exp_left(np.r_[0.04, 0.0, 0.0, 0.0, 0.01, 0.0], truth[1])]
    kfs = [SimpleNamespace(stamp=float(c), T_odom_cam=inv_T(T)) for c, T in enumerate(truth)]
    fixed = np.array([True, False])
    edges = odometry_edges(kfs, fixed)
    assert edges is not None and len(edges[0]) == 1
    intr = (FX, FY, CX, CY, BF)
    args = (np.array(start), fixed, P + rng.normal(0.0, 0.05, size=P.shape), np.array(cam_idx),
            np.array(pt_idx), obs, np.ones(len(obs), bool), np.ones(len(obs)), intr, 10)
    err = {}
    for use in (False, True):
        Ts, _ = bundle_adjust(*args, pose_edges=edges if use else None)
        err[use] = float(np.linalg.norm(inv_T(Ts[1])[:3, 3] - inv_T(truth[1])[:3, 3]))
    print("second camera's error (m), without / with the odometry edge:", err)
    assert err[True] < 0.01 and err[True] < 0.5 * err[False], err


def test_odometry_edges_take_the_calibrated_odometry_where_both_keyframes_carry_it():
    """A base whose raw odometry creeps 1 deg/m in yaw: over a 0.5 m keyframe gap the raw edge
    turns the second keyframe by 0.5 deg, 2.5 x the edge's rotation sigma on a straight drive.
    The edge is the calibrated odometry's motion where both keyframes carry it, the raw one's
    where either does not."""
    from scipy.spatial.transform import Rotation as R_
    from mdr_slam.pose.optimizer import ODOM_EDGE_SIGMA_DEG, odometry_edges
    yaw = np.radians(0.5)          # about the camera's y axis (down): the base's yaw
    creep = make_T(R_.from_rotvec([0.0, yaw, 0.0]).as_matrix(), np.array([0.0, 0.0, 0.5]))
    true = make_T(np.eye(3), np.array([0.0, 0.0, 0.5]))
    kfs = [SimpleNamespace(stamp=0.0, T_odom_cam=np.eye(4), T_odom_cam_calibrated=np.eye(4)),
           SimpleNamespace(stamp=1.0, T_odom_cam=creep, T_odom_cam_calibrated=true)]
    fixed = np.array([True, False])
    Z = odometry_edges(kfs, fixed)[2]
    assert np.allclose(Z[0], true)
    assert np.degrees(yaw) > 2.0 * ODOM_EDGE_SIGMA_DEG
    kfs[1].T_odom_cam_calibrated = None       # made before the calibration applied: the raw motion
    Z = odometry_edges(kfs, fixed)[2]
    assert np.allclose(Z[0], creep)


def test_a_tracked_drift_the_wheel_odometry_contradicts_is_refused():
    """Under planar motion, the pose tracked now against the one about ODOMETRY_WINDOW_S ago
    (kept on its keyframe) must agree with the wheel odometry's motion in between to 0.1 m + 10 %
    of the odometry's path: a 1 m straight drive tracked 0.3 m off is refused, 0.05 m off is not,
    and nothing is checked without planar motion or once a relocalization started anew."""
    from mdr_slam.pose import tracking as tr
    kf = SimpleNamespace(bad=False, parent=None, T_cw=np.eye(4))   # the anchor's keyframe
    T_odom_cam = [make_T(np.eye(3), np.array([0.0, 0.0, 0.1 * i])) for i in range(11)]
    planar_map = SimpleNamespace(planar=object())
    t = SimpleNamespace(map=planar_map, state=tr.OK, ref_kf=kf, odom_window=[], records=[])

    def frame(i, err=0.0):
        # the camera (z forward) drives 0.1 m per frame; err: tracked this far sideways (x)
        C = np.array([err, 0.0, 0.1 * i])
        return SimpleNamespace(stamp=0.1 * i, T_odom_cam=T_odom_cam[i],
                               T_cw=make_T(np.eye(3), -C), mp_ids=np.zeros(3, int))
    for i in range(5):     # tracked OK, on the odometry: the window fills
        f = frame(i)
        t.records.append((f.stamp, kf, f.T_cw @ inv_T(kf.T_cw), False, f.T_cw))
        tr.Tracking._update_odometry_window(t, f)
    assert len(t.odom_window) == 5 and t.odom_window[0][0] == 0.0
    agrees = tr.Tracking.odometry_window_agrees
    assert agrees(t, frame(10, 0.05))          # 1 m of odometry: 0.2 m allowed
    assert not agrees(t, frame(10, 0.3))
    assert not agrees(t, frame(5, 0.2))        # 0.5 m: 0.15 m allowed
    t.map = SimpleNamespace(planar=None)       # six degrees of freedom: the camera may bob
    assert agrees(t, frame(10, 0.3))
    t.map, t.state = planar_map, tr.RELOCALIZED
    tr.Tracking._update_odometry_window(t, frame(5))
    assert t.odom_window == [] and agrees(t, frame(10, 0.3))
    # the window keeps about ODOMETRY_WINDOW_S: its anchor is the newest frame that old
    t.state = tr.OK
    for i in range(30):
        f = SimpleNamespace(stamp=0.1 * i, T_odom_cam=np.eye(4), T_cw=np.eye(4))
        t.records.append((f.stamp, kf, np.eye(4), False, f.T_cw))
        tr.Tracking._update_odometry_window(t, f)
    assert t.odom_window[0][0] == pytest.approx(2.9 - tr.ODOMETRY_WINDOW_S)


def test_a_tracked_step_the_wheel_odometry_contradicts_is_refused():
    """A pose tracked within ODOMETRY_STEP_S of the last tracked frame must follow the wheel
    odometry's step: 0.03 m + 15 % of its translation and 1 deg + 15 % of its turn. The base drove
    0.1 m and turned 3 deg in 0.1 s: a pose 1.8 deg further round or 5 cm to the side is refused,
    one 0.5 deg or 1 cm off is not; after a second's gap only the wide gate (15 deg, 0.5 m) holds."""
    from mdr_slam.pose import tracking as tr
    yaw = lambda deg: Rotation.from_euler("y", deg, degrees=True).as_matrix()   # optical frame
    odo = make_T(yaw(3.0), [0.0, 0.0, 0.1])          # T_odom_cam of the frame: turned, driven on

    def pose(deg, side=0.0):
        return inv_T(make_T(yaw(deg), [side, 0.0, 0.1]))   # T_cw: the camera's pose in map
    last = SimpleNamespace(stamp=0.0, T_odom_cam=np.eye(4), T_cw=np.eye(4))
    t = SimpleNamespace(last_frame=last, n_odom_step_refused=0, last_odom_refusal=None,
                        _update_last_frame=lambda: None)
    t.odometry_motion = lambda f: tr.Tracking.odometry_motion(t, f)
    t.calibrated_odometry_motion = lambda f: None
    agrees = lambda T_cw, stamp=0.1: tr.Tracking.odometry_agrees(t, SimpleNamespace(
        stamp=stamp, T_odom_cam=odo, T_cw=T_cw, mp_ids=np.zeros(3, int)))
    assert agrees(pose(3.0)) and agrees(pose(3.5)) and agrees(pose(3.0, 0.01))
    assert t.n_odom_step_refused == 0 and t.last_odom_refusal is None
    assert not agrees(pose(4.8))
    assert not agrees(pose(3.0, 0.05))
    assert t.n_odom_step_refused == 2 and t.last_odom_refusal[0] == pytest.approx(0.1)
    assert t.last_odom_refusal[-1] == "step"
    last.stamp = -1.0                              # a second since the last tracked frame
    assert agrees(pose(4.8)) and agrees(pose(3.0, 0.05))
    assert not agrees(pose(20.0))
    # the check itself, without counting (the one-patch refinement asks it)
    last.stamp = 0.0
    n = t.n_odom_step_refused
    assert not tr.Tracking.odometry_agrees(t, SimpleNamespace(
        stamp=0.1, T_odom_cam=odo, T_cw=pose(4.8), mp_ids=np.zeros(3, int)), record=False)
    assert t.n_odom_step_refused == n


def test_a_relocalization_is_gated_about_the_calibrated_odometry():
    """After 20 s LOST over 4 m, the raw odometry reads 2 % long and has crept 4 deg; the
    calibrated chain has those taken out. Before the calibration applies, the wide gate about the
    raw odometry (0.5 m + 20 % of 4 m) lets a relocalization 0.6 m to the side of the true pose
    through; once it applies, the gate about the calibrated chain (0.15 m + 5 %) refuses it, and
    keeps one 10 cm off."""
    from mdr_slam.pose import tracking as tr
    yaw = lambda deg: Rotation.from_euler("y", deg, degrees=True).as_matrix()   # optical frame
    true = make_T(np.eye(3), [0.0, 0.0, 4.0])               # T_odom_cam: 4 m straight on
    raw = make_T(yaw(4.0), [0.0, 0.0, 4.08])
    calib = SimpleNamespace(calibrated=False)
    last = SimpleNamespace(stamp=0.0, T_odom_cam=np.eye(4), T_odom_cam_calibrated=np.eye(4),
                           T_cw=np.eye(4))
    t = SimpleNamespace(last_frame=last, n_odom_step_refused=0, last_odom_refusal=None,
                        _update_last_frame=lambda: None,
                        system=SimpleNamespace(odometry_calibration=calib))
    t.odometry_motion = lambda f: tr.Tracking.odometry_motion(t, f)
    t.calibrated_odometry_motion = lambda f: tr.Tracking.calibrated_odometry_motion(t, f)

    def agrees(side):
        T_wc = true.copy()
        T_wc[0, 3] = side
        return tr.Tracking.odometry_agrees(t, SimpleNamespace(
            stamp=20.0, T_odom_cam=raw, T_odom_cam_calibrated=true, T_cw=inv_T(T_wc),
            mp_ids=np.zeros(3, int)))
    assert agrees(0.6) and agrees(0.1)
    calib.calibrated = True
    assert not agrees(0.6)
    assert t.last_odom_refusal[1] == pytest.approx(0.6, abs=1e-6)
    assert t.last_odom_refusal[-1] == "calibrated odometry"
    assert agrees(0.1)
    # a frame without the calibrated chain (none computed): the raw gate
    last.T_odom_cam_calibrated = None
    assert agrees(0.6)


def _track_with_odometry(poses, blank):
    """Track the orbit ``poses`` in the textured room with planar_motion auto and wheel odometry
    (translations read 2 % long), the images of frames ``i`` with ``blank(i)`` blank; returns the
    (shut down) System and its results."""
    room = BoxRoom((3.0, 1.5, 3.0), tex_size=768, seed=3)
    s = System(CAM, config={"planar_motion": "auto"}, threads=False, T_map_cam0=T_BASE_CAM_LEVEL)
    res = []
    for i, T_wc in enumerate(poses):
        l, r = room.render_stereo(T_wc, CAM)
        if blank(i):
            l, r = np.full_like(l, 128), np.full_like(r, 128)
        f = s.make_frame(0.05 * i, l, r)
        T = inv_T(poses[0]) @ T_wc
        T[:3, 3] *= 1.02
        f.T_odom_cam = T_BASE_CAM_LEVEL @ T
        res.append(s.track(f.stamp, frame=f))
    s.shutdown()
    return s, res


def test_lost_frames_carry_the_pose_on_by_the_wheel_odometry():
    """Tracked, then blank images (LOST) while the wheels go on: the result has no tracked pose
    but the last tracked one carried on by the odometry (T_map_cam_coasted), where the base truly
    is to within the odometry's 2 % error."""
    poses = orbit_trajectory(28, radius=1.0, arc=np.pi / 2)
    s, res = _track_with_odometry(poses, lambda i: i >= 22)
    assert [r.state for r in res[:22]].count("OK") == 22
    # the keyframes keep the odometry (the loop check and the local BA's edges use it); the
    # calibrated one only once the calibration applies, after more driving than these 1.6 m
    assert all(k.T_odom_cam is not None for k in s.map.keyframes.values())
    assert not s.odometry_calibration.calibrated
    assert all(k.T_odom_cam_calibrated is None for k in s.map.keyframes.values())
    assert [r.state for r in res[24:]] == ["LOST"] * 4, [r.state for r in res]
    for r, T_wc in zip(res[24:], poses[24:]):
        assert r.T_map_cam is None and r.T_map_cam_coasted is not None
        truth = T_BASE_CAM_LEVEL @ inv_T(poses[0]) @ T_wc
        assert np.linalg.norm(r.T_map_cam_coasted[:3, 3] - truth[:3, 3]) < 0.02
    assert all(r.T_map_cam_coasted is None for r in res[:22])


def test_frames_carry_the_calibrated_odometry_once_the_calibration_applies(monkeypatch):
    """Before OdometryCalibration has seen enough driving its chain is the raw odometry, whose
    yaw creep the local BA's tight calibrated edges must not take for the calibrated motion: the
    first keyframes carry no calibrated odometry, the ones after the calibration applies do."""
    from mdr_slam.pose import odometry_calibration
    monkeypatch.setattr(odometry_calibration, "MIN_TRAVEL_M", 0.6)
    poses = orbit_trajectory(28, radius=1.0, arc=np.pi / 2)
    s, res = _track_with_odometry(poses, lambda i: False)
    assert s.odometry_calibration.calibrated
    kfs = sorted(s.map.keyframes.values(), key=lambda k: k.stamp)
    carry = [k.T_odom_cam_calibrated is not None for k in kfs]
    assert not carry[0] and carry[-1] and carry == sorted(carry), carry


def test_a_map_reset_starts_where_the_wheel_odometry_carried_the_base():
    """A young map LOST (blank images) is thrown away and a new one started (ORB-SLAM2 Reset).
    With wheel odometry the new map's first camera is put where the odometry carried the base,
    so map stays put: the poses after the reset are where the base truly is, not back at the
    start pose turned by what the base turned meanwhile."""
    poses = orbit_trajectory(28, radius=1.0, arc=np.pi / 2)[:14]
    s, res = _track_with_odometry(poses, lambda i: 2 <= i < 8)
    assert s.n_keyframes_created > len(s.map.keyframes), "no reset"     # a map was thrown away
    after = [(r, T_wc) for r, T_wc in zip(res[8:], poses[8:]) if r.T_map_cam is not None]
    assert len(after) >= 4, [r.state for r in res]
    moved = inv_T(poses[0]) @ poses[8]
    turned = np.degrees(Rotation.from_matrix(moved[:3, :3]).magnitude())
    assert np.linalg.norm(moved[:3, 3]) > 0.2 and turned > 10     # a reset at the start is wrong
    for r, T_wc in after:
        truth = T_BASE_CAM_LEVEL @ inv_T(poses[0]) @ T_wc
        err_deg = np.degrees(Rotation.from_matrix(truth[:3, :3].T @ r.T_map_cam[:3, :3]).magnitude())
        assert np.linalg.norm(r.T_map_cam[:3, 3] - truth[:3, 3]) < 0.03 and err_deg < 1.0, \
            (r.stamp, r.T_map_cam[:3, 3], truth[:3, 3], err_deg)
