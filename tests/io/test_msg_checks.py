"""mdr_slam.msg_checks: oversized and malformed images, camera_infos, clouds and poses are told
apart from good ones by their header fields alone."""
from __future__ import annotations

import numpy as np

from mdr_slam import conversions as cv
from mdr_slam.msg_checks import (MAX_IMAGE_DIM, camera_info_problem, cloud_problem,
                                 compressed_size, image_problem, pose_problem)
from sensor_msgs.msg import CameraInfo, Image, PointField


def test_images():
    good = cv.numpy_to_image(np.zeros((48, 64), np.uint8))
    info = CameraInfo(width=64, height=48)
    assert image_problem(good) == "" and image_problem(good, info) == ""
    assert "differ from the calibration" in image_problem(good, CameraInfo(width=32, height=48))
    huge = Image(width=MAX_IMAGE_DIM + 1, height=10, encoding="mono8", step=MAX_IMAGE_DIM + 1,
                 data=b"")
    assert "exceeds" in image_problem(huge)
    assert "size" in image_problem(Image(width=0, height=10, encoding="mono8"))
    assert "step" in image_problem(Image(width=10, height=10, step=1 << 30, encoding="mono8"))


def test_compressed_image_declared_size():
    for fmt in ("png", "jpeg"):
        m = cv.numpy_to_compressed_image(np.zeros((48, 64), np.uint8), fmt)
        assert compressed_size(m.data) == (64, 48), fmt
        assert image_problem(m, CameraInfo(width=64, height=48)) == ""
    # a png header declaring 100000 x 100000 px (a decompression bomb): refused before decoding
    m = cv.numpy_to_compressed_image(np.zeros((48, 64), np.uint8), "png")
    data = bytearray(m.data)
    data[16:24] = (100000).to_bytes(4, "big") * 2
    m.data = bytes(data)
    assert "exceeds" in image_problem(m)


def test_camera_info():
    assert camera_info_problem(CameraInfo(width=64, height=48)) == ""
    assert camera_info_problem(CameraInfo(width=0, height=48))
    assert camera_info_problem(CameraInfo(width=10 ** 6, height=48))
    bad = CameraInfo(width=64, height=48)
    bad.K = [float("nan")] * 9
    assert "non-finite" in camera_info_problem(bad)


def test_clouds():
    good = cv.arrays_to_pointcloud2({}, xyz=np.zeros((10, 3), np.float32))
    assert cloud_problem(good) == ""
    empty = cv.arrays_to_pointcloud2({}, xyz=np.zeros((0, 3), np.float32))
    assert cloud_problem(empty) == ""

    def variant(**kw):
        m = cv.arrays_to_pointcloud2({}, xyz=np.zeros((10, 3), np.float32))
        for k, v in kw.items():
            setattr(m, k, v)
        return m
    assert "exceeds" in cloud_problem(variant(width=1 << 20, height=1 << 20))
    assert "point_step" in cloud_problem(variant(point_step=0))
    assert "does not fit" in cloud_problem(variant(point_step=4))
    assert "truncated" in cloud_problem(variant(data=b"\0" * 7))
    assert "truncated" in cloud_problem(variant(data=b"\0" * 10 ** 6))
    f = [PointField(name="x", offset=0, datatype=7, count=1)] * 2
    assert "twice" in cloud_problem(variant(fields=f))
    f = [PointField(name="x", offset=0, datatype=42, count=1)]
    assert "datatype" in cloud_problem(variant(fields=f))
    f = [PointField(name="x", offset=0, datatype=7, count=1 << 30)]
    assert "does not fit" in cloud_problem(variant(fields=f))
    f = [PointField(name="f%d" % i, offset=0, datatype=1, count=1) for i in range(1000)]
    assert "fields" in cloud_problem(variant(fields=f))


def test_poses():
    p = cv.matrix_to_pose(np.eye(4))
    assert pose_problem(p) == ""
    p.orientation.w = 3.0
    assert "norm" in pose_problem(p)
    p.orientation.w = float("nan")
    assert "non-finite" in pose_problem(p)
