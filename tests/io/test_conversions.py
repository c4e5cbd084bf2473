"""Round trips of mdr_slam.conversions: Image, CameraInfo, PointCloud2, poses and transforms."""
from __future__ import annotations

import time

import numpy as np
import pytest

from mdr_slam import conversions as cv
from mdr_slam.camera import CameraModel
from mdr_slam.geometry import make_T, quat_to_R

from conftest import serialize_roundtrip


@pytest.mark.parametrize("encoding,dtype,shape", [
    ("mono8", np.uint8, (48, 64)), ("mono16", np.uint16, (48, 64)), ("bgr8", np.uint8, (48, 64, 3)),
    ("rgb8", np.uint8, (48, 64, 3)), ("32FC1", np.float32, (48, 64)), ("bgra8", np.uint8, (4, 5, 4)),
])
def test_image_roundtrip(encoding, dtype, shape):
    rng = np.random.default_rng(0)
    if np.dtype(dtype).kind == "f":
        a = rng.normal(size=shape).astype(dtype)
    else:
        a = rng.integers(0, np.iinfo(dtype).max, size=shape, dtype=dtype)
    msg = cv.numpy_to_image(a, encoding, stamp=12.5, frame_id="cam")
    back = cv.image_to_numpy(serialize_roundtrip(msg))
    assert back.dtype == np.dtype(dtype) and back.shape == shape
    np.testing.assert_array_equal(back, a)
    assert msg.header.frame_id == "cam" and abs(cv.stamp_to_sec(msg.header.stamp) - 12.5) < 1e-9


def test_image_padding_bigendian_and_mono():
    a = np.arange(6 * 5, dtype=np.uint16).reshape(6, 5) * 1000
    msg = cv.numpy_to_image(a, "mono16")
    # big-endian rows padded to 16 bytes
    rows = [r.astype(">u2").tobytes() + b"\0" * 6 for r in a]
    msg.is_bigendian, msg.step, msg.data = 1, 16, b"".join(rows)
    np.testing.assert_array_equal(cv.image_to_numpy(msg), a)
    bgr = np.zeros((4, 4, 3), np.uint8)
    bgr[..., 2] = 255  # red
    grey = cv.image_to_numpy(cv.numpy_to_image(bgr, "bgr8"), to_mono=True)
    assert grey.shape == (4, 4) and grey.dtype == np.uint8 and 70 < grey[0, 0] < 80
    rgb = cv.numpy_to_image(bgr[..., ::-1].copy(), "rgb8")
    np.testing.assert_array_equal(cv.image_to_numpy(rgb, to_mono=True), grey)


def test_image_errors_are_clear():
    msg = cv.numpy_to_image(np.zeros((10, 10), np.uint8))
    msg.encoding = "nv12"
    with pytest.raises(cv.ConversionError, match="unsupported image encoding"):
        cv.image_to_numpy(msg)
    msg.encoding = "mono8"
    msg.data = msg.data[:50]
    with pytest.raises(cv.ConversionError, match="truncated"):
        cv.image_to_numpy(msg)
    msg = cv.numpy_to_image(np.zeros((10, 10), np.uint8))
    msg.step = 5
    with pytest.raises(cv.ConversionError, match="step"):
        cv.image_to_numpy(msg)
    with pytest.raises(cv.ConversionError):
        cv.numpy_to_image(np.zeros((3, 3), np.int64))


def test_camera_info_roundtrip():
    K = np.array([[458.6, 0, 367.2], [0, 457.3, 248.4], [0, 0, 1]])
    P = np.array([[435.2, 0, 367.5, -47.9], [0, 435.2, 252.2, 0], [0, 0, 1, 0]])
    R = quat_to_R([0.01, -0.02, 0.003, 1.0])
    m = CameraModel(752, 480, K, [-0.28, 0.07, 0.0002, 1.7e-05, 0.0], R, P, frame_id="cam0")
    back = cv.camera_info_to_model(serialize_roundtrip(cv.model_to_camera_info(m, stamp=3.0)))
    for name in ("K", "D", "R", "P"):
        np.testing.assert_allclose(getattr(back, name), getattr(m, name))
    assert (back.width, back.height, back.frame_id) == (752, 480, "cam0")


def test_camera_info_pair_keeps_the_principal_point_difference():
    from mdr_slam.camera import StereoCamera
    cam = StereoCamera.from_rectified(752, 480, 458.0, 458.0, 367.0, 248.0, 0.11).with_doffs(-0.2)
    back = StereoCamera(*[cv.camera_info_to_model(serialize_roundtrip(cv.model_to_camera_info(m)))
                          for m in (cam.left, cam.right)])
    assert back.doffs == pytest.approx(-0.2) and back.is_rectified
    assert back.baseline == pytest.approx(0.11)


def test_camera_info_of_zeros_is_rejected():
    from sensor_msgs.msg import CameraInfo
    with pytest.raises(cv.ConversionError, match="uncalibrated"):
        cv.camera_info_to_model(CameraInfo(width=752, height=480))


def test_pointcloud2_roundtrip_arbitrary_fields():
    rng = np.random.default_rng(1)
    n = 1000
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    fields = {"intensity": rng.random(n).astype(np.float32), "variance": rng.random(n),
              "n_obs": rng.integers(0, 100, n).astype(np.uint16)}
    msg = cv.arrays_to_pointcloud2(fields, xyz=xyz, stamp=1.0, frame_id="cam")
    assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity", "variance", "n_obs"]
    back = cv.pointcloud2_to_arrays(serialize_roundtrip(msg))
    np.testing.assert_array_equal(cv.pointcloud2_to_xyz(msg), xyz)
    np.testing.assert_allclose(back["variance"], fields["variance"].astype(np.float32))
    np.testing.assert_array_equal(back["n_obs"], fields["n_obs"])
    assert back["n_obs"].dtype == np.uint16
    # float64 storage on request
    m64 = cv.arrays_to_pointcloud2({}, xyz=xyz.astype(np.float64) / 3, dtype=np.float64)
    np.testing.assert_array_equal(cv.pointcloud2_to_xyz(m64, skip_nans=False),
                                  (xyz.astype(np.float64) / 3).astype(np.float32))


def test_pointcloud2_nans_padding_and_empty():
    xyz = np.array([[0, 0, 1], [np.nan, 0, 1], [1, 2, 3]], np.float32)
    msg = cv.arrays_to_pointcloud2({"intensity": np.array([1, 2, 3], np.float32)}, xyz=xyz)
    assert not msg.is_dense
    a = cv.pointcloud2_to_arrays(msg, skip_nans=True)
    np.testing.assert_array_equal(a["intensity"], [1, 3])
    # organized 2x2 cloud with 4 bytes of padding after each point and each row
    from sensor_msgs.msg import PointCloud2, PointField
    pts = np.arange(12, dtype=np.float32).reshape(4, 3)
    rows = []
    for r in range(2):
        row = b"".join(p.tobytes() + b"\xff" * 4 for p in pts[2 * r: 2 * r + 2])
        rows.append(row + b"\0" * 8)
    m = PointCloud2(height=2, width=2, point_step=16, row_step=40, is_bigendian=False,
                    fields=[PointField("x", 0, PointField.FLOAT32, 1),
                            PointField("y", 4, PointField.FLOAT32, 1),
                            PointField("z", 8, PointField.FLOAT32, 1)], data=b"".join(rows))
    np.testing.assert_array_equal(cv.pointcloud2_to_xyz(m), pts)
    empty = cv.arrays_to_pointcloud2({"intensity": np.zeros(0, np.float32)}, xyz=np.zeros((0, 3)))
    assert cv.pointcloud2_to_xyz(serialize_roundtrip(empty)).shape == (0, 3)
    bad = cv.arrays_to_pointcloud2({}, xyz=pts)
    bad.data = bad.data[:20]
    with pytest.raises(cv.ConversionError, match="truncated"):
        cv.pointcloud2_to_arrays(bad)


def test_pointcloud2_300k_points_speed():
    """The issue's figure: a 300k-point cloud both ways well under a second (printed, not asserted)."""
    rng = np.random.default_rng(2)
    n = 300_000
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    extra = {"intensity": rng.random(n).astype(np.float32), "confidence": rng.random(n).astype(np.float32)}
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        msg = cv.arrays_to_pointcloud2(extra, xyz=xyz, frame_id="map")
        t1 = time.perf_counter()
        back = cv.pointcloud2_to_arrays(msg)
        t2 = time.perf_counter()
        times.append((t1 - t0, t2 - t1))
    to_msg, from_msg = np.median(np.array(times), axis=0) * 1e3
    print("\nPointCloud2 300k points x 5 fields: to message %.1f ms, from message %.1f ms (median of 5)"
          % (to_msg, from_msg))
    np.testing.assert_array_equal(back["confidence"], extra["confidence"])
    np.testing.assert_array_equal(np.stack([back["x"], back["y"], back["z"]], 1), xyz)


def test_pose_and_transform_roundtrip():
    T = make_T(quat_to_R([0.1, -0.3, 0.2, 0.9]), [1.0, -2.0, 3.5])
    np.testing.assert_allclose(cv.pose_to_matrix(cv.matrix_to_pose(T)), T, atol=1e-12)
    ps = serialize_roundtrip(cv.matrix_to_pose_stamped(T, stamp=5.25, frame_id="map"))
    np.testing.assert_allclose(cv.pose_stamped_to_matrix(ps), T, atol=1e-12)
    assert ps.header.frame_id == "map"
    ts = serialize_roundtrip(cv.matrix_to_transform_stamped(T, 7, "odom", "base_link"))
    np.testing.assert_allclose(cv.transform_stamped_to_matrix(ts), T, atol=1e-12)
    assert (ts.header.frame_id, ts.child_frame_id) == ("odom", "base_link")
    p = cv.matrix_to_pose(T)
    p.position.x = float("nan")
    with pytest.raises(cv.ConversionError, match="non-finite"):
        cv.pose_to_matrix(p)
    p = cv.matrix_to_pose(T)
    p.orientation.x = p.orientation.y = p.orientation.z = p.orientation.w = 0.0
    with pytest.raises(cv.ConversionError, match="zero"):
        cv.pose_to_matrix(p)
