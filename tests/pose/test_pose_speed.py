"""Vectorized pose kernels against plain reference implementations (mdr_slam.pose speed work):
stereo row matching vs a per-keypoint loop (ORB-SLAM2 ComputeStereoMatches), SWAR Hamming vs a
popcount table, 3x3 cofactor inverses, the closed-form pose Jacobian vs finite differences, and the
dense-Schur bundle adjustment vs a plain dense Gauss-Newton step."""
from __future__ import annotations

import numpy as np
import pytest

from mdr_slam.camera import StereoCamera
from mdr_slam.pose import Frame, ORBextractor
from mdr_slam.pose.frame import compute_stereo_matches
from mdr_slam.pose.optimizer import _inv3, bundle_adjust
from mdr_slam.pose.orb import TH_HIGH, TH_LOW, hamming
from mdr_slam.pose.synthetic import BoxRoom, orbit_trajectory

_POP = np.array([bin(i).count("1") for i in range(256)], dtype=np.int32)


def test_hamming_swar_matches_table_including_full_distance():
    rng = np.random.RandomState(1)
    a = rng.randint(0, 256, (500, 32)).astype(np.uint8)
    b = rng.randint(0, 256, (500, 32)).astype(np.uint8)
    b[:10] = ~a[:10]          # distance 256: needs 9 bits, the SWAR sum must not wrap
    b[10:20] = a[10:20]       # distance 0
    ref = _POP[a ^ b].sum(axis=1)
    got = hamming(a, b)
    np.testing.assert_array_equal(got, ref)
    assert got.dtype == np.int32 and got[:10].tolist() == [256] * 10
    # gathered / non-contiguous rows and 1-D inputs
    idx = rng.randint(0, 500, 300)
    np.testing.assert_array_equal(hamming(a[idx], b[idx[::-1]]), _POP[a[idx] ^ b[idx[::-1]]].sum(1))
    assert hamming(a[0], b[0]) == ref[0]
    assert hamming(a[:0], b[:0]).shape == (0,)


def test_inv3_matches_numpy():
    rng = np.random.RandomState(2)
    A = rng.randn(200, 3, 3)
    A = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(3)
    np.testing.assert_allclose(_inv3(A), np.linalg.inv(A), rtol=1e-9, atol=1e-12)


def _reference_stereo(left, right, uv_l, oct_l, desc_l, uv_r, oct_r, desc_r, scale, fx, b):
    """ORB-SLAM2 ComputeStereoMatches written as a loop over left keypoints (slow, obvious)."""
    h, w = left.shape
    bf, max_d, W, L = fx * b, fx, 5, 5
    ur = -np.ones(len(uv_l), np.float32)
    depth = -np.ones(len(uv_l), np.float32)
    order = np.argsort(uv_r[:, 1], kind="stable")        # ties: first in row order wins
    res = []
    for i in range(len(uv_l)):
        best, best_j = TH_HIGH + 1, -1
        for j in order:
            if abs(uv_l[i, 1] - uv_r[j, 1]) > 2.0 * scale[oct_r[j]] or abs(oct_l[i] - oct_r[j]) > 1:
                continue
            du = uv_l[i, 0] - uv_r[j, 0]
            if du < 0 or du > max_d:
                continue
            d = int(_POP[desc_l[i] ^ desc_r[j]].sum())
            if d < best:
                best, best_j = d, j
        if best_j < 0 or best >= (TH_HIGH + TH_LOW) // 2:
            continue
        uL, vL, uR0 = int(round(uv_l[i, 0])), int(round(uv_l[i, 1])), int(round(uv_r[best_j, 0]))
        if not (vL - W >= 0 and vL + W < h and uL - W >= 0 and uL + W < w and uR0 - W - L >= 0
                and uR0 + W + L < w):
            continue
        patch = left[vL - W:vL + W + 1, uL - W:uL + W + 1].astype(float) - float(left[vL, uL])
        sad = []
        for s in range(-L, L + 1):
            c = uR0 + s
            win = right[vL - W:vL + W + 1, c - W:c + W + 1].astype(float) - float(right[vL, c])
            sad.append(np.abs(patch - win).sum())
        k = int(np.argmin(sad))
        if not 0 < k < 2 * L:      # minimum on the border of the search: no parabola, dropped
            continue
        den = 2.0 * (sad[k - 1] + sad[k + 1] - 2.0 * sad[k])
        if den == 0 or abs((sad[k - 1] - sad[k + 1]) / den) >= 1.0:
            continue
        delta = (sad[k - 1] - sad[k + 1]) / den
        disp = uL - (uR0 + (k - L) + delta)
        if disp < 0 or disp >= max_d:
            continue
        disp = disp if disp > 0 else 0.01
        res.append((i, uv_l[i, 0] - disp, disp, sad[k]))
    if res:
        thr = max(1.5 * 1.4 * float(np.median([r[3] for r in res])), float((2 * W + 1) ** 2))
        for i, u, disp, s in res:
            if s <= thr:
                ur[i] = u
                depth[i] = bf / disp
    return ur, depth


@pytest.mark.parametrize("noise", [0.0, 4.0])
def test_vectorized_stereo_matching_equals_per_keypoint_loop(noise):
    cam = StereoCamera.from_rectified(480, 320, 300.0, 300.0, 240.0, 160.0, 0.12)
    room = BoxRoom((3.0, 1.5, 3.0), tex_size=768, seed=3)
    left, right = room.render_stereo(orbit_trajectory(2, radius=1.0, arc=0.1)[1], cam)
    if noise:
        rng = np.random.RandomState(3)
        left = np.clip(left + rng.randn(*left.shape) * noise, 0, 255).astype(np.uint8)
        right = np.clip(right + rng.randn(*right.shape) * noise, 0, 255).astype(np.uint8)
    ex = ORBextractor(300)
    uv_l, oct_l, _, desc_l = ex(left)
    uv_r, oct_r, _, desc_r = ex(right)
    got = compute_stereo_matches(left, right, uv_l, oct_l, desc_l, uv_r, oct_r, desc_r, ex.scale,
                                 cam.fx, cam.baseline)
    ref = _reference_stereo(left, right, uv_l, oct_l, desc_l, uv_r, oct_r, desc_r, ex.scale,
                            cam.fx, cam.baseline)
    assert np.count_nonzero(ref[1] > 0) > 100
    np.testing.assert_array_equal(got[0] >= 0, ref[0] >= 0)
    np.testing.assert_allclose(got[0], ref[0], atol=1e-4)
    np.testing.assert_allclose(got[1], ref[1], rtol=1e-4)


def _stereo_ba_scene(rng, M, C, noise):
    """M points seen by C cameras stepping 0.3 m along x: (P, Ts, cam_idx, pt_idx, obs, K) with
    stereo observations (u, v, u_right) plus ``noise`` px of Gaussian noise."""
    fx = fy = 400.0
    cx, cy, bf = 320.0, 240.0, 40.0
    P = np.column_stack([rng.uniform(-2, 2, M), rng.uniform(-1, 1, M), rng.uniform(3, 8, M)])
    Ts = np.repeat(np.eye(4)[None], C, axis=0)
    Ts[:, 0, 3] = -0.3 * np.arange(C)
    cam_idx = np.repeat(np.arange(C), M)
    pt_idx = np.tile(np.arange(M), C)
    Pc = P[pt_idx] + Ts[cam_idx, :3, 3]
    u = fx * Pc[:, 0] / Pc[:, 2] + cx
    obs = np.column_stack([u, fy * Pc[:, 1] / Pc[:, 2] + cy, u - bf / Pc[:, 2]])
    obs += rng.randn(*obs.shape) * noise
    return P, Ts, cam_idx, pt_idx, obs, (fx, fy, cx, cy, bf)


def test_bundle_adjust_first_step_equals_dense_gauss_newton():
    """One LM step of the Schur-complement solver equals solving the full dense normal equations
    (cameras and points together) with the same damping."""
    from mdr_slam.pose.optimizer import _pose_point_jacobians
    rng = np.random.RandomState(4)
    M, C = 60, 4
    P, Ts, cam_idx, pt_idx, obs, (fx, fy, cx, cy, bf) = _stereo_ba_scene(rng, M, C, 0.3)
    u = obs[:, 0]
    stereo = rng.rand(len(u)) < 0.6
    obs[~stereo, 2] = 0.0
    info = np.ones(len(u))
    fixed = np.zeros(C, bool)
    fixed[0] = True
    P0 = P + rng.randn(M, 3) * 0.002   # residuals stay inside the Huber band (plain LS)
    lam = 1e-3
    Ts1, P1 = bundle_adjust(Ts, fixed, P0, cam_idx, pt_idx, obs, stereo, info,
                            (fx, fy, cx, cy, bf), iterations=1, lm_lambda=lam)
    # dense reference: residuals with all weights 1 (noise 0.3 px is far inside the Huber band)
    R = Ts[cam_idx, :3, :3]
    Pc = (R @ P0[pt_idx][:, :, None])[:, :, 0] + Ts[cam_idx, :3, 3]
    e = np.column_stack([obs[:, 0] - (fx * Pc[:, 0] / Pc[:, 2] + cx),
                         obs[:, 1] - (fy * Pc[:, 1] / Pc[:, 2] + cy),
                         np.where(stereo, obs[:, 2] - (fx * Pc[:, 0] - bf) / Pc[:, 2] - cx, 0.0)])
    Jc, Jl = _pose_point_jacobians(Pc, R, stereo, fx, fy, bf)
    nv = C - 1
    J = np.zeros((3 * len(u), 6 * nv + 3 * M))
    for k in range(len(u)):
        if cam_idx[k] > 0:
            J[3 * k:3 * k + 3, 6 * (cam_idx[k] - 1):6 * cam_idx[k]] = Jc[k]
        J[3 * k:3 * k + 3, 6 * nv + 3 * pt_idx[k]:6 * nv + 3 * pt_idx[k] + 3] = Jl[k]
    H = J.T @ J
    H += np.diag(lam * np.diag(H) + 1e-9)
    dx = -np.linalg.solve(H, J.T @ e.ravel())
    np.testing.assert_allclose(P1 - P0, dx[6 * nv:].reshape(M, 3), atol=1e-6)
    from mdr_slam.geometry import make_T
    from scipy.spatial.transform import Rotation
    for c, d in enumerate(dx[:6 * nv].reshape(nv, 6), start=1):
        T_ref = make_T(Rotation.from_rotvec(d[3:]).as_matrix(), d[:3]) @ Ts[c]
        np.testing.assert_allclose(Ts1[c], T_ref, atol=1e-6)
    np.testing.assert_array_equal(Ts1[0], Ts[0])   # the fixed camera


def test_ba_worker_process_matches_in_thread_and_recovers():
    """ba_process.BAWorker (local BA in a child process): same answer as in-process, abort stops
    it early, a killed child is replaced, close() leaves no process behind."""
    import os
    import signal
    from mdr_slam.pose.ba_process import BAWorker
    rng = np.random.RandomState(5)
    M, C = 1500, 5   # big enough that the abort signal lands long before 10 iterations end
    P, Ts, cam_idx, pt_idx, obs, (fx, fy, cx, cy, bf) = _stereo_ba_scene(rng, M, C, 0.5)
    u = obs[:, 0]
    stereo = np.ones(len(u), bool)
    fixed = np.zeros(C, bool)
    fixed[0] = True
    args = (Ts, fixed, P + rng.randn(M, 3) * 0.05, cam_idx, pt_idx, obs, stereo,
            np.ones(len(u)), (fx, fy, cx, cy, bf), 10)
    ref = bundle_adjust(*args)
    w = BAWorker()
    try:
        w.prewarm()
        got = w.run(args, {})
        assert not w.failed
        np.testing.assert_allclose(got[0], ref[0], atol=1e-9)
        np.testing.assert_allclose(got[1], ref[1], atol=1e-7)
        one = bundle_adjust(*args[:-1], 1)
        aborted = w.run(args, {}, abort=lambda: True)   # stops after the first iteration
        assert np.abs(aborted[1] - one[1]).max() < np.abs(ref[1] - one[1]).max()
        pid = w._proc.pid
        os.kill(pid, signal.SIGKILL)
        w._proc.wait()
        again = w.run(args, {})
        np.testing.assert_allclose(again[1], ref[1], atol=1e-7)
        assert w._proc.pid != pid and not w.failed
    finally:
        proc = w._proc
        w.close()
    assert proc.poll() is not None


def test_global_ba_in_a_worker_process_matches_in_thread():
    """LoopClosing's global BA solved in a BAWorker child (threads: the solver's long numpy/scipy
    steps then never hold the tracking thread's GIL) writes back the same map."""
    from mdr_slam.pose.ba_process import BAWorker
    from mdr_slam.pose.optimizer import global_bundle_adjustment
    from test_pose import _loop_map
    ref, _ = _loop_map()
    got, _ = _loop_map()
    r_ref = global_bundle_adjustment(ref, iterations=6)
    w = BAWorker(nice=5)   # LoopClosing's child yields the CPU to tracking
    try:
        r_got = global_bundle_adjustment(got, iterations=6, worker=w)
        assert not w.failed and w._proc is not None   # it really ran in the child
        import os
        assert os.getpriority(os.PRIO_PROCESS, w._proc.pid) == \
            min(19, os.getpriority(os.PRIO_PROCESS, 0) + 5)
    finally:
        proc = w._proc
        w.close()
    assert proc.poll() is not None
    assert r_got["moved"] == r_ref["moved"] and r_got["outliers"] == r_ref["outliers"]
    for k in ref.keyframes:
        np.testing.assert_allclose(got.keyframes[k].T_cw, ref.keyframes[k].T_cw, atol=1e-9)
    np.testing.assert_allclose(got.mp_pos[: got.n], ref.mp_pos[: ref.n], atol=1e-7)


def _orbit_system(n, params=None):
    """A System (synchronous mapping) that tracked the first ``n`` frames of a 28-frame quarter
    orbit in the textured box room (0.05 s apart), with the poses and images of all 28."""
    from mdr_slam.pose import System
    cam = StereoCamera.from_rectified(480, 320, 300.0, 300.0, 240.0, 160.0, 0.12)
    room = BoxRoom((3.0, 1.5, 3.0), tex_size=768, seed=3)
    poses = orbit_trajectory(28, radius=1.0, arc=np.pi / 2)
    images = [room.render_stereo(T, cam) for T in poses]
    s = System(cam, config=params, threads=False)
    for i in range(n):
        assert s.track(0.05 * i, *images[i]).state == "OK"
    return s, poses, images


def test_motion_model_uses_the_real_frame_gap():
    """Frames dropped while the node was busy: the constant-velocity prediction is scaled to the
    stamp gap (3 periods here), and the frame after the gap is tracked."""
    from types import SimpleNamespace
    from scipy.spatial.transform import Rotation
    from mdr_slam.geometry import inv_T
    s, poses, images = _orbit_system(12)
    tr = s.tracking
    V = tr.velocity
    assert V is not None and abs(tr.velocity_dt - 0.05) < 1e-9
    same = tr.predicted_velocity(SimpleNamespace(stamp=tr.last_frame.stamp + 0.05))
    assert same is V                                   # a regular stream is left untouched
    P = tr.predicted_velocity(SimpleNamespace(stamp=tr.last_frame.stamp + 0.15))
    truth = inv_T(poses[14]) @ poses[11]               # T_c14_c11: the camera motion over the gap
    ang = lambda T: np.linalg.norm(Rotation.from_matrix(T[:3, :3]).as_rotvec())
    assert ang(P @ inv_T(truth)) < 0.1 * ang(truth)
    assert np.linalg.norm(P[:3, 3] - truth[:3, 3]) < 0.1 * np.linalg.norm(truth[:3, 3])
    assert ang(V @ inv_T(truth)) > 0.5 * ang(truth)   # unscaled, it would be 2/3 off
    r = s.track(0.05 * 14, *images[14])               # frames 12 and 13 dropped
    assert r.state == "OK"
    T_true = inv_T(poses[0]) @ poses[14]
    assert np.linalg.norm(r.T_map_cam[:3, 3] - T_true[:3, 3]) < 0.03
    s.shutdown()


def test_relocalization_is_bounded_per_frame(monkeypatch):
    """LOST on an unknown view: with no time budget one candidate keyframe is tried per frame,
    and the next LOST frame tries another; with a large budget every candidate is tried."""
    from mdr_slam.pose import system as system_module, tracking
    monkeypatch.setattr(tracking, "RELOC_MAX_MS", 0.0)
    monkeypatch.setattr(tracking, "RESET_IF_LOST_BELOW_KFS", 0)
    s, poses, images = _orbit_system(12, params={"loop_closing": False})
    n_kfs = len(s.map.good_keyframes())
    assert n_kfs >= 3
    rng = np.random.RandomState(7)
    noise = [(rng.randint(0, 256, images[0][0].shape).astype(np.uint8),) * 2 for _ in range(3)]
    s.tracking.state, s.tracking.velocity = "LOST", None
    tried = []
    for k in range(2):
        r = s.track(1.0 + 0.05 * k, *noise[k])
        assert r.state == "LOST" and s.tracking.n_reloc_tried == 1
        tried.append(set(s.tracking.reloc_tried))
    assert len(tried[1]) == 2 and tried[0] < tried[1]   # a different keyframe the second time
    monkeypatch.setattr(tracking, "RELOC_MAX_MS", 1e6)
    s.tracking.reloc_tried.clear()
    r = s.track(1.2, *noise[2])
    assert r.state == "LOST" and s.tracking.n_reloc_tried == min(n_kfs, system_module.RELOC_CANDIDATES)
    r = s.track(1.25, *images[8])                       # a known view: relocalized
    assert r.state == "RELOCALIZED" and not s.tracking.reloc_tried
    s.shutdown()


def test_hamming_knn2_equals_full_matrix():
    """cv2.batchDistance's two nearest (relocalization, reference-keyframe and frame-to-frame
    matching) against the full Hamming matrix: same distances, same best index (ties to the
    lower index, as np.argmin), and a one-column input."""
    from mdr_slam.pose.orb import hamming_knn2, hamming_matrix
    rng = np.random.RandomState(8)
    a = rng.randint(0, 256, (300, 32)).astype(np.uint8)
    b = rng.randint(0, 256, (700, 32)).astype(np.uint8)
    b[100:110] = a[:10]
    b[200:210] = a[:10]                      # exact ties: the lower index wins
    d, i = hamming_knn2(a, b)
    D = hamming_matrix(a, b)
    np.testing.assert_array_equal(d, np.sort(D, axis=1)[:, :2])
    np.testing.assert_array_equal(i[:, 0], np.argmin(D, axis=1))
    assert i[:10, 0].tolist() == list(range(100, 110)) and (d[:10] == 0).all()
    d1, i1 = hamming_knn2(a[:5], b[:1])
    np.testing.assert_array_equal(d1[:, 0], D[:5, 0])
    assert (d1[:, 1] == 256).all() and (i1[:, 1] == -1).all()
    assert hamming_knn2(a[:0], b)[0].shape == (0, 2)


def test_feature_grid_pairs_equal_brute_force_radius_search():
    """FeatureGrid.pairs_within (the matcher's projection search) returns exactly the pairs a
    brute-force distance matrix puts within each point's radius: radii smaller and larger than a
    cell, projections off the image and at its corners, non-finite ones (none), keypoints on cell
    borders; the best-of-two resolution does not depend on the pair order."""
    from mdr_slam.pose.frame import FeatureGrid
    from mdr_slam.pose.matcher import _best_two
    rng = np.random.RandomState(3)
    kp = rng.uniform(0, [752, 480], (1500, 2)).astype(np.float32)
    kp[:20] = np.round(kp[:20] / 16.0) * 16.0                    # exactly on cell borders
    uv = rng.uniform([-40, -40], [792, 520], (700, 2))
    uv[:5] = [[0, 0], [751.9, 479.9], [-30, 10], [760, 470], [376, -25]]
    r = rng.uniform(0.5, 40.0, 700)
    uv[5:8] = np.nan
    g = FeatureGrid(kp)
    i, j, d = g.pairs_within(uv[:, 0], uv[:, 1], r)
    D = np.hypot(kp[None, :, 0].astype(float) - uv[:, None, 0], kp[None, :, 1] - uv[:, None, 1])
    with np.errstate(invalid="ignore"):
        ref = set(zip(*np.nonzero(D <= r[:, None])))
    got = list(zip(i.tolist(), j.tolist()))
    assert len(got) == len(set(got)) and set(got) == {(int(a), int(b)) for a, b in ref}
    np.testing.assert_allclose(d, D[i, j])
    assert len(ref) > 3000
    e = FeatureGrid(np.zeros((0, 2)))
    assert len(e.pairs_within(uv[:, 0], uv[:, 1], r)[0]) == 0
    # best pair per point with exact distance ties: the same whatever order the pairs come in
    dist = rng.randint(0, 4, len(i)).astype(np.int32)
    b1, s1, o1 = _best_two(i, dist, j)
    p = rng.permutation(len(i))
    b2, s2, o2 = _best_two(i[p], dist[p], j[p])
    np.testing.assert_array_equal(j[b1], j[p][b2])
    np.testing.assert_array_equal(s1, s2)
    np.testing.assert_array_equal(o1, o2)


def test_threaded_system_makes_frames_in_a_worker_process_identical_to_in_process():
    """System(threads=True) makes its frames' features in a child process (out of the lock that
    tracking and the mapping threads share): the same keypoints, descriptors and stereo depths
    as in-process, the parent spends little CPU on them, a killed child is replaced, and
    shutdown leaves no process behind."""
    import os
    import signal
    from mdr_slam.pose import System
    cam = StereoCamera.from_rectified(480, 320, 300.0, 300.0, 240.0, 160.0, 0.12)
    room = BoxRoom((3.0, 1.5, 3.0), tex_size=768, seed=3)
    pairs = [room.render_stereo(T, cam) for T in orbit_trajectory(3, radius=1.0, arc=0.2)]
    live = System(cam, threads=True)
    offline = System(cam, threads=False)
    try:
        assert live.frame_worker is not None and offline.frame_worker is None
        for i, (left, right) in enumerate(pairs):
            if i == 2:   # a dead child is restarted on the next frame
                pid = live.frame_worker._proc.pid
                os.kill(pid, signal.SIGKILL)
                live.frame_worker._proc.wait()
            a = live.make_frame(0.05 * i, left, right)
            b = offline.make_frame(0.05 * i, left, right)
            assert a.N == b.N > 200 and a.n_primary == b.n_primary
            for k in ("uv", "octave", "angle", "desc", "ur", "depth"):
                np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
            # the texture weights come made too: the tracking thread computes none
            assert a._grad is not None and a.texture_tau > 0
            every = np.arange(a.N)
            np.testing.assert_allclose(a.texture_weights(every), b.texture_weights(every))
            assert not live.frame_worker.failed
            assert a.build_cpu_ms < 0.5 * b.build_cpu_ms   # the work was done in the child
        assert live.frame_worker._proc.pid != pid
        res = live.track(0.0, frame=live.make_frame(0.0, *pairs[0]))
        assert res.state in ("OK", "NOT_INITIALIZED")
    finally:
        proc = live.frame_worker._proc
        live.shutdown()
        offline.shutdown()
    assert proc.poll() is not None and live.frame_worker is None
