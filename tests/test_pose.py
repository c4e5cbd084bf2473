"""mdr_slam.pose: stereo matching, pose-only optimization, BA, PnP relocalization and end-to-end
tracking on a ray-cast textured room with exact ground truth."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mdr_slam.camera import StereoCamera
from mdr_slam.geometry import inv_T, make_T
from mdr_slam.pose import Frame, Map, ORBextractor, Optimizer, System
from mdr_slam.pose.evaluate import ate_rmse, umeyama_se3
from mdr_slam.pose.optimizer import bundle_adjust
from mdr_slam.pose.orb import expand_ranges, hamming, hamming_matrix
from mdr_slam.pose.synthetic import BoxRoom, orbit_trajectory

CAM = StereoCamera.from_rectified(480, 320, 300.0, 300.0, 240.0, 160.0, 0.12)


@pytest.fixture(scope="module")
def room():
    return BoxRoom((3.0, 1.5, 3.0), tex_size=768, seed=3)


@pytest.fixture(scope="module")
def sequence(room):
    """28 frames on a quarter of a 1 m circle (turning ~90 degrees), 0.05 s apart."""
    poses = orbit_trajectory(28, radius=1.0, arc=np.pi / 2 * 28 / 28.0)
    images = [room.render_stereo(T, CAM) for T in poses]
    return poses, images


def _true_depth(room, T_wc, uv):
    d = np.column_stack([(uv[:, 0] - CAM.cx) / CAM.fx, (uv[:, 1] - CAM.cy) / CAM.fy,
                         np.ones(len(uv))]) @ T_wc[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (np.sign(d) * room.h - T_wc[:3, 3]) / d
    t[~(t > 0)] = np.inf
    return t.min(axis=1)   # the ray has unit z in the camera, so t is the depth


def test_hamming_and_ranges():
    rng = np.random.RandomState(0)
    a = rng.randint(0, 256, (40, 32)).astype(np.uint8)
    b = rng.randint(0, 256, (30, 32)).astype(np.uint8)
    ref = np.unpackbits(a[:, None] ^ b[None], axis=2).sum(axis=2)
    np.testing.assert_array_equal(hamming_matrix(a, b), ref)
    np.testing.assert_array_equal(hamming(a[:30], b), ref[np.arange(30), np.arange(30)])
    owner, idx = expand_ranges(np.array([2, 5, 0]), np.array([4, 5, 3]))
    np.testing.assert_array_equal(owner, [0, 0, 2, 2, 2])
    np.testing.assert_array_equal(idx, [2, 3, 0, 1, 2])


def test_stereo_matching_gives_subpixel_depth(room, sequence):
    poses, images = sequence
    f = Frame(0.0, images[0][0], images[0][1], CAM, ORBextractor(1000))
    idx = np.nonzero(f.depth > 0)[0]
    assert len(idx) > 0.4 * f.N
    z_true = _true_depth(room, poses[0], f.uv[idx])
    d_true = CAM.fx * CAM.baseline / z_true
    d_meas = f.uv[idx, 0] - f.ur[idx]
    err = d_meas - d_true
    assert np.median(np.abs(err)) < 0.2          # sub-pixel refinement works
    assert abs(np.median(err)) < 0.1             # and is not biased
    assert np.mean(np.abs(err) < 1.0) > 0.95     # few wrong stereo matches survive


def _synthetic_points(rng, n=400):
    return rng.uniform([-3, -2, 3], [3, 2, 9], (n, 3))


def test_pose_optimization_with_outliers():
    rng = np.random.RandomState(1)
    Pw = _synthetic_points(rng)
    T_true = inv_T(make_T(Rotation.from_rotvec([0.02, 0.1, -0.01]).as_matrix(), [0.3, -0.05, 0.4]))
    Pc = Pw @ T_true[:3, :3].T + T_true[:3, 3]
    u = CAM.fx * Pc[:, 0] / Pc[:, 2] + CAM.cx
    v = CAM.fy * Pc[:, 1] / Pc[:, 2] + CAM.cy
    ur = u - CAM.fx * CAM.baseline / Pc[:, 2]

    class F:   # the Frame fields pose_optimization reads
        pass
    f = F()
    f.fx, f.fy, f.cx, f.cy, f.bf = CAM.fx, CAM.fy, CAM.cx, CAM.cy, CAM.fx * CAM.baseline
    n = len(Pw)
    f.uv = np.column_stack([u, v]) + rng.randn(n, 2) * 0.3
    f.ur = np.where(np.arange(n) % 2 == 0, ur + rng.randn(n) * 0.3, -1.0)   # half mono
    outl = rng.rand(n) < 0.2
    f.uv[outl] += rng.uniform(-40, 40, (outl.sum(), 2))
    f.octave = np.zeros(n, int)
    f.inv_level_sigma2 = np.ones(8)
    f.mp_ids = np.arange(n)
    f.outlier = np.zeros(n, bool)
    f.T_cw = make_T(Rotation.from_rotvec([0.0, 0.05, 0.0]).as_matrix(), [0.1, 0.0, -0.1]) @ T_true
    mp = Map()

    class KF:
        id = 0
        ur = np.full(n, -1.0)
        mp_ids = -np.ones(n, dtype=np.int64)
    mp.mp_pos = np.asarray(Pw, dtype=float)
    mp.mp_bad = np.zeros(n, bool)
    mp.n = n
    n_in = Optimizer.pose_optimization(f, mp)
    err_t = np.linalg.norm(inv_T(f.T_cw)[:3, 3] - inv_T(T_true)[:3, 3])
    assert err_t < 0.01
    assert n_in > 0.75 * n
    # gross outliers are flagged
    assert np.mean(f.outlier[outl & (np.abs(f.uv - np.column_stack([u, v])).max(1) > 10)]) > 0.9


def test_bundle_adjust_recovers_structure_and_motion():
    rng = np.random.RandomState(2)
    P = _synthetic_points(rng, 300)
    Ts = np.array([inv_T(make_T(Rotation.from_rotvec([0, 0.03 * c, 0]).as_matrix(),
                                [0.3 * c, 0, 0.2 * c])) for c in range(5)])
    ci = np.repeat(np.arange(5), len(P))
    pi = np.tile(np.arange(len(P)), 5)
    Pc = (Ts[ci, :3, :3] @ P[pi][:, :, None])[:, :, 0] + Ts[ci, :3, 3]
    bf = CAM.fx * CAM.baseline
    u = CAM.fx * Pc[:, 0] / Pc[:, 2] + CAM.cx
    v = CAM.fy * Pc[:, 1] / Pc[:, 2] + CAM.cy
    stereo = rng.rand(len(u)) < 0.5
    obs = np.column_stack([u, v, np.where(stereo, u - bf / Pc[:, 2], 0.0)])
    Tn = Ts.copy()
    for c in range(1, 5):
        Tn[c] = make_T(Rotation.from_rotvec(rng.randn(3) * 0.01).as_matrix(), rng.randn(3) * 0.05) @ Ts[c]
    Pn = P + rng.randn(*P.shape) * 0.1
    fixed = np.array([True, False, False, False, False])
    Tr, Pr = bundle_adjust(Tn, fixed, Pn, ci, pi, obs, stereo, np.ones(len(u)),
                           (CAM.fx, CAM.fy, CAM.cx, CAM.cy, bf), 10)
    for c in range(5):
        assert np.linalg.norm(inv_T(Tr[c])[:3, 3] - inv_T(Ts[c])[:3, 3]) < 1e-6
    assert np.abs(Pr - P).max() < 1e-6


def _run(images, threads=False, params=None):
    s = System(CAM, params=params, threads=threads)
    results = []
    for i, (l, r) in enumerate(images):
        results.append(s.track(0.05 * i, l, r))
        if threads:   # give the mapping thread the frame period a live stream would give it
            import time
            time.sleep(0.05)
    s.shutdown()
    return s, results


def _ate(s, poses):
    from mdr_slam.io import Trajectory
    gt = Trajectory.from_matrices(0.05 * np.arange(len(poses)),
                                  [inv_T(poses[0]) @ T for T in poses])
    return ate_rmse(s.trajectory(), gt)


def test_sequence_tracked_end_to_end(sequence):
    poses, images = sequence
    s, res = _run(images, threads=False)
    assert [r.state for r in res].count("OK") == len(res)
    assert res[0].is_keyframe and res[0].keyframe_id == 0
    kfs = [r for r in res if r.is_keyframe]
    assert 2 <= len(kfs) < len(res)
    assert all(r.T_map_cam is not None and r.n_tracked > 50 for r in res)
    corr = [r.corrections for r in res if r.corrections is not None]
    assert corr and corr[0][0] == "local_ba"
    assert all(isinstance(T, np.ndarray) and T.shape == (4, 4)
               for c in corr for (_, T) in c[2].values())
    ids = [c[1] for c in corr]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    traj = s.trajectory()
    assert len(traj) == len(res)
    ate = _ate(s, poses)
    assert ate < 0.03, ate          # 1.5 m path around a 90 degree turn
    # the last pose is the identity-anchored truth (first frame = map origin), no alignment
    T_last = inv_T(poses[0]) @ poses[-1]
    assert np.linalg.norm(res[-1].T_map_cam[:3, 3] - T_last[:3, 3]) < 0.06


def test_threaded_mode_tracks_and_shuts_down(sequence):
    poses, images = sequence
    s, res = _run(images[:16], threads=True)
    assert all(r.state == "OK" for r in res)
    assert not s.local_mapping.thread.is_alive()
    assert _ate(s, poses[:16]) < 0.03


def test_relocalization_after_lost(sequence):
    poses, images = sequence
    s = System(CAM, threads=False)
    for i in range(12):
        s.track(0.05 * i, *images[i])
    s.tracking.state = "LOST"     # as if the camera had been covered
    s.tracking.velocity = None
    r = s.track(0.05 * 12, *images[8])   # revisit: PnP RANSAC against the keyframes
    assert r.state == "RELOCALIZED"
    T_true = inv_T(poses[0]) @ poses[8]
    assert np.linalg.norm(r.T_map_cam[:3, 3] - T_true[:3, 3]) < 0.03
    r = s.track(0.05 * 13, *images[9])
    assert r.state == "OK"
    s.shutdown()


def test_blank_images_do_not_initialise():
    s = System(CAM, threads=False)
    z = np.zeros((320, 480), np.uint8)
    r = s.track(0.0, z, z)
    assert r.state == "NOT_INITIALIZED" and r.T_map_cam is None and r.n_tracked == 0
    assert len(s.trajectory()) == 0
    with pytest.raises(ValueError):
        System(CAM, params={"no_such_parameter": 1}, threads=False)


def test_umeyama_recovers_rigid_transform():
    rng = np.random.RandomState(4)
    A = rng.randn(50, 3)
    T = make_T(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), [1, 2, 3])
    B = A @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(umeyama_se3(A, B), T, atol=1e-9)


# ---------------------------------------------------------------------- loop closing pieces
def test_vocabulary_scores_same_place_higher(room, sequence):
    from mdr_slam.pose.vocabulary import bow_score, load_vocabulary
    voc = load_vocabulary()
    assert voc.n_words >= 1000
    ex = ORBextractor(800)
    poses, images = sequence
    d0 = ex(images[0][0])[3]
    d1 = ex(images[1][0])[3]          # 3 degrees later: same place
    d_far = ex(images[-1][0])[3]      # 90 degrees later: other walls
    b0, b1, bf = voc.transform(d0), voc.transform(d1), voc.transform(d_far)
    assert abs(bow_score(b0, b0) - 1.0) < 1e-5
    assert bow_score(b0, b1) > 1.5 * bow_score(b0, bf)
    w = voc.transform_words(d0[:5])
    assert np.all((w >= 0) & (w < voc.n_words))


def test_ransac_se3_with_outliers():
    from mdr_slam.pose.loop_closing import ransac_se3
    rng = np.random.RandomState(5)
    A = rng.uniform(-3, 3, (120, 3))
    T = make_T(Rotation.from_rotvec([0.05, -0.3, 0.1]).as_matrix(), [0.4, -0.2, 1.0])
    B = A @ T[:3, :3].T + T[:3, 3] + rng.randn(120, 3) * 0.005
    out = rng.rand(120) < 0.3
    B[out] += rng.uniform(-2, 2, (out.sum(), 3))
    T_est, mask = ransac_se3(A, B, np.full(120, 0.05))
    assert np.abs(T_est - T).max() < 0.02
    assert np.mean(mask[~out]) > 0.95 and np.mean(mask[out]) < 0.1


def test_essential_graph_spreads_loop_error():
    """A square of 4 m sides with a 0.4 m drift: the loop edge pulls the end onto the start."""
    steps = [make_T(Rotation.from_euler("y", 0 if i % 4 else 90, degrees=True).as_matrix(),
                    [0, 0, 1.0]) for i in range(16)]
    true = [np.eye(4)]
    for s_ in steps:
        true.append(true[-1] @ s_)
    drift = make_T(Rotation.from_euler("y", 1.0, degrees=True).as_matrix(), [0.0, 0.0, 0.02])
    est = [np.eye(4)]
    for s_ in steps:
        est.append(est[-1] @ s_ @ drift)
    poses = {i: T for i, T in enumerate(est)}
    edges = [(i, i + 1, inv_T(est[i]) @ est[i + 1]) for i in range(16)]
    edges.append((0, 16, inv_T(true[0]) @ true[16]))   # loop: end == start
    out = Optimizer.optimize_essential_graph(poses, edges, fixed=0)
    assert np.linalg.norm(est[16][:3, 3] - true[16][:3, 3]) > 0.3
    assert np.linalg.norm(out[16][:3, 3] - true[16][:3, 3]) < 0.05
    err_mid_before = np.linalg.norm(est[8][:3, 3] - true[8][:3, 3])
    assert np.linalg.norm(out[8][:3, 3] - true[8][:3, 3]) < err_mid_before


def test_mdr_vocab_trains_on_a_folder(tmp_path, sequence):
    import cv2
    from mdr_slam.cli import main as mdr_main
    from mdr_slam.pose.vocabulary import ORBVocabulary
    _, images = sequence
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in range(0, 28, 4):
        cv2.imwrite(str(folder / ("%02d.png" % i)), images[i][0])
    out = str(tmp_path / "voc.npz")
    assert mdr_main(["vocab", str(folder), "-o", out, "-k", "4", "-L", "3", "--no-builtin",
                     "--features", "300"]) == 0
    voc = ORBVocabulary.load(out)
    assert voc.n_words == 64 and len(voc.levels) == 3 and voc.levels[2].shape == (64, 32)
    words, w = voc.transform(ORBextractor(300)(images[0][0])[3])
    assert len(words) > 10 and abs(float(w.sum()) - 1.0) < 1e-5
    assert mdr_main(["vocab", str(tmp_path / "missing"), "-o", out]) == 2


@pytest.fixture(scope="module")
def office_low_texture():
    """The office sample's hard stretch at half resolution (376x240, 20 Hz): 6.5 s from a
    textured poster into blank, low-contrast walls while the camera turns at 12-23 deg/s, then
    slowing to the stop before the sweep (loop+pure_rotation, seed 0, t = 7.0-13.5 s: the
    frames where the full-resolution sample used to be lost). Only these frames are rendered."""
    from mdr_slam.sim.render import Simulator, sim_camera
    from mdr_slam.sim.scene import make_scene
    from mdr_slam.sim.trajectory import build_trajectory
    scene = make_scene("office", seed=0)
    cam = sim_camera(scale=0.5)
    stamps = np.arange(7.0, 13.5, 0.05)
    poses = build_trajectory("loop+pure_rotation", 30.0, 0, scene=scene).poses(stamps)
    sim = Simulator(scene, cam, seed=0, noise=2.0)
    images = [sim.render(T, index=i, depth=False) for i, T in enumerate(poses)]
    return cam, stamps, poses, [(im["left"], im["right"]) for im in images]


def test_low_texture_turn_tracked_end_to_end(office_low_texture):
    from mdr_slam.io import Trajectory
    from mdr_slam.pipeline import load_params
    cam, stamps, poses, images = office_low_texture
    p = load_params("pose")
    p.update(n_features=1000)
    s = System(cam, params=p, threads=False)
    states, fallback = [], 0
    for t, (l, r) in zip(stamps, images):
        states.append(s.track(t, l, r).state)
        fallback += s.extractor.n_primary < p["n_features"]   # the FAST fallback was needed
    s.shutdown()
    # the sequence really is low-texture: most frames lack corners at the main FAST threshold
    assert fallback > 0.4 * len(images), fallback
    assert states.count("OK") == len(states), [(i, x) for i, x in enumerate(states) if x != "OK"]
    gt = Trajectory.from_matrices(stamps, poses)
    ate = ate_rmse(s.trajectory(), gt)
    assert len(s.trajectory()) == len(images)
    assert ate < 0.25, ate       # 2.2 m path; measured 0.14 m (blank walls: few, weak corners)
