"""mdr_slam.io (PLY/PCD/trajectories, atomic writes), mdr_slam.geometry and mdr_slam.camera."""
from __future__ import annotations

import os

import numpy as np
import pytest

from mdr_slam import geometry as g
from mdr_slam import io as mio
from mdr_slam.camera import CalibrationError, StereoCamera


def _cloud(n=500, seed=0):
    rng = np.random.default_rng(seed)
    return mio.points_cloud(rng.normal(size=(n, 3)).astype(np.float32),
                            intensity=rng.random(n).astype(np.float32),
                            confidence=rng.integers(0, 50, n).astype(np.uint16),
                            last_seen=rng.random(n) * 1e9)


@pytest.mark.parametrize("ext", [".ply", ".pcd"])
def test_cloud_roundtrip(tmp_path, ext):
    c = _cloud()
    path = str(tmp_path / ("map" + ext))
    assert mio.write_cloud(path, c) == 500
    back = mio.read_cloud(path)
    assert list(back) == list(c)
    for k in c:
        np.testing.assert_array_equal(back[k], c[k])
        assert back[k].dtype == c[k].dtype
    assert [f for f in os.listdir(tmp_path)] == ["map" + ext]  # no temporary left behind


def test_ply_readable_by_open3d_and_ascii(tmp_path):
    import open3d as o3d
    c = _cloud(100)
    mio.write_ply(str(tmp_path / "a.ply"), c)
    pc = o3d.io.read_point_cloud(str(tmp_path / "a.ply"))
    np.testing.assert_allclose(np.asarray(pc.points), mio.cloud_xyz(c), atol=1e-6)
    o3d.io.write_point_cloud(str(tmp_path / "b.ply"), pc, write_ascii=True)
    np.testing.assert_allclose(mio.cloud_xyz(mio.read_ply(str(tmp_path / "b.ply"))),
                               mio.cloud_xyz(c), atol=1e-5)
    mio.write_ply(str(tmp_path / "empty.ply"), mio.points_cloud(np.zeros((0, 3), np.float32)))
    assert len(mio.read_ply(str(tmp_path / "empty.ply"))["x"]) == 0


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    p = str(tmp_path / "m.ply")
    mio.write_ply(p, _cloud(10))
    with pytest.raises(ValueError):
        mio.write_ply(p, {"x": np.zeros(3), "y": np.zeros(2), "z": np.zeros(3)})
    assert len(mio.read_ply(p)["x"]) == 10
    assert os.listdir(tmp_path) == ["m.ply"]


def test_truncated_ply_is_reported(tmp_path):
    p = str(tmp_path / "m.ply")
    mio.write_ply(p, _cloud(100))
    data = open(p, "rb").read()
    open(p, "wb").write(data[:-10])
    with pytest.raises(ValueError, match="truncated"):
        mio.read_ply(p)


def test_trajectory_formats(tmp_path):
    rng = np.random.default_rng(3)
    Ts = [g.make_T(g.quat_to_R(rng.normal(size=4)), rng.normal(size=3)) for _ in range(20)]
    t = mio.Trajectory.from_matrices(np.arange(20) * 0.05 + 100, Ts)
    mio.write_tum(str(tmp_path / "t.tum"), t)
    back = mio.read_trajectory(str(tmp_path / "t.tum"))
    np.testing.assert_allclose(back.matrices(), np.array(Ts), atol=1e-7)
    np.testing.assert_allclose(back.stamps, t.stamps)
    mio.write_kitti_poses(str(tmp_path / "t.txt"), t)
    np.testing.assert_allclose(mio.read_trajectory(str(tmp_path / "t.txt")).matrices(), np.array(Ts),
                               atol=1e-7)
    with open(tmp_path / "gt.csv", "w") as f:
        f.write("#timestamp [ns],x,y,z,qw,qx,qy,qz\n")
        for s, T in zip(t.stamps, Ts):
            q = g.R_to_quat(T[:3, :3])
            f.write("%d,%r,%r,%r,%r,%r,%r,%r\n" % (int(round(s * 1e9)), *T[:3, 3], q[3], *q[:3]))
    e = mio.read_trajectory(str(tmp_path / "gt.csv"))
    np.testing.assert_allclose(e.matrices(), np.array(Ts), atol=1e-9)
    assert abs(t.path_length() - np.linalg.norm(np.diff([T[:3, 3] for T in Ts], axis=0), axis=1).sum()) < 1e-9


def test_geometry():
    rng = np.random.default_rng(4)
    T = g.make_T(g.quat_to_R(rng.normal(size=4)), rng.normal(size=3))
    np.testing.assert_allclose(g.inv_T(T) @ T, np.eye(4), atol=1e-12)
    P = rng.normal(size=(10, 3))
    np.testing.assert_allclose(g.transform_points(g.inv_T(T), g.transform_points(T, P)), P, atol=1e-12)
    assert g.is_valid_T(T) and not g.is_valid_T(T * np.nan) and not g.is_valid_T(2 * T)
    t, r = g.relative_motion(np.eye(4), g.make_T(g.quat_to_R([0, 0, np.sin(0.25), np.cos(0.25)]), [3, 4, 0]))
    assert abs(t - 5) < 1e-12 and abs(r - 0.5) < 1e-12


def test_body_twist():
    """nav_msgs/Odometry's twist: velocities in the moving frame (a car driving forward while
    turning left has +x linear and +z angular velocity, whatever its heading)."""
    from scipy.spatial.transform import Rotation
    from mdr_slam.geometry import body_twist, make_T
    yaw0 = 2.0
    T0 = make_T(Rotation.from_euler("z", yaw0).as_matrix(), [1.0, 2.0, 0.0])
    step = make_T(Rotation.from_euler("z", 0.05).as_matrix(), [0.1, 0.0, 0.0])
    v, w = body_twist(T0, T0 @ step, 0.1)
    assert np.allclose(v, [1.0, 0.0, 0.0]) and np.allclose(w, [0.0, 0.0, 0.5])


def test_stereo_camera_geometry_and_rectification():
    cam = StereoCamera.from_rectified(752, 480, 458.0, 457.0, 370.0, 245.0, 0.11)
    assert abs(cam.baseline - 0.11) < 1e-12 and cam.is_rectified
    d = np.array([[50.38, 0.0, -1.0]], np.float32)
    Z = cam.disparity_to_depth(d)
    assert abs(Z[0, 0] - 458 * 0.11 / 50.38) < 1e-4 and np.isnan(Z[0, 1]) and np.isnan(Z[0, 2])
    P = np.array([[0.3, -0.2, 2.0], [-1.0, 0.5, 7.0]])
    u, v, z = cam.project(P)
    np.testing.assert_allclose(cam.backproject(u, v, z), P, atol=1e-5)
    img = np.arange(480 * 752, dtype=np.uint32).reshape(480, 752).astype(np.uint8)
    l, r = cam.rectify(img, img)
    assert l is img  # rectified input passes through
    # a distorted camera gets remapped; identity distortion with R = I maps a pixel onto itself
    raw = StereoCamera.from_rectified(64, 48, 50.0, 50.0, 32.0, 24.0, 0.1)
    raw.left.D = np.array([0.01, 0, 0, 0, 0])
    raw.right.D = raw.left.D.copy()
    assert not raw.is_rectified
    img = np.zeros((48, 64), np.uint8)
    img[24, 32] = 255
    l, _ = raw.rectify(img, img)
    assert l[24, 32] > 200
    with pytest.raises(CalibrationError):
        StereoCamera.from_rectified(64, 48, 50.0, 50.0, 32.0, 24.0, -0.1)
