"""Bounds on what a node accepts from the ROS graph, checked before any conversion or allocation.

ROS 1 has no authentication: a stray node, a misconfigured driver or a fuzzer can publish any
message on the nodes' topics. Each check below looks at a message's header fields and lengths
only (no pixel or point is touched) and returns "" for an acceptable message, else the reason it
is refused; the nodes drop the message with a throttled warning and go on.
"""
from __future__ import annotations

import math

__all__ = ["MAX_IMAGE_DIM", "MAX_IMAGE_BYTES", "MAX_CLOUD_POINTS", "MAX_POINT_STEP",
           "MAX_CLOUD_FIELDS", "QUATERNION_NORM_TOL", "image_problem", "camera_info_problem",
           "cloud_problem", "pose_problem"]

MAX_IMAGE_DIM = 4096                       # px, width or height of a camera image
MAX_IMAGE_BYTES = MAX_IMAGE_DIM * MAX_IMAGE_DIM * 4   # raw data (4096^2 bgra8), compressed data
MAX_CLOUD_POINTS = MAX_IMAGE_DIM * MAX_IMAGE_DIM      # width * height of a PointCloud2
MAX_POINT_STEP = 1024                      # bytes per point
MAX_CLOUD_FIELDS = 64
MAX_FIELD_COUNT = 64                       # PointField.count
QUATERNION_NORM_TOL = 0.05                 # |q| may differ from 1 by this (rounding, not garbage)

# PointField datatype -> bytes (INT8 .. FLOAT64)
_FIELD_SIZE = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}
_JPEG_SOF = set(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _dims_problem(w: int, h: int, what: str) -> str:
    if w <= 0 or h <= 0:
        return "%s has size %dx%d" % (what, w, h)
    if w > MAX_IMAGE_DIM or h > MAX_IMAGE_DIM:
        return "%s of %dx%d exceeds %dx%d" % (what, w, h, MAX_IMAGE_DIM, MAX_IMAGE_DIM)
    return ""


def compressed_size(data) -> tuple:
    """(width, height) a png or jpeg stream declares in its header, or None (not found in the
    first 64 kB: the decoder will tell)."""
    b = bytes(data[:65536])
    if b[:8] == b"\x89PNG\r\n\x1a\n" and len(b) >= 24:
        return int.from_bytes(b[16:20], "big"), int.from_bytes(b[20:24], "big")
    if b[:2] == b"\xff\xd8":
        i = 2
        while i + 9 < len(b) and b[i] == 0xFF:
            m = b[i + 1]
            if m == 0xFF:      # fill byte
                i += 1
                continue
            if m in _JPEG_SOF:
                return int.from_bytes(b[i + 7:i + 9], "big"), int.from_bytes(b[i + 5:i + 7], "big")
            if m == 0xD8 or 0xD0 <= m <= 0xD7 or m == 0x01:   # markers without a length
                i += 2
                continue
            i += 2 + int.from_bytes(b[i + 2:i + 4], "big")
    return None


def image_problem(msg, info=None) -> str:
    """Why an Image or CompressedImage is refused ("" if not): a size of 0 or beyond
    MAX_IMAGE_DIM, more than MAX_IMAGE_BYTES of data, or a size other than ``info``'s (the
    camera_info it is used with, when given)."""
    n = len(msg.data)
    if n > MAX_IMAGE_BYTES:
        return "image data of %d bytes exceeds %d" % (n, MAX_IMAGE_BYTES)
    if getattr(msg, "_type", "") == "sensor_msgs/CompressedImage":
        wh = compressed_size(msg.data)
        if wh is None:
            return ""
        w, h = wh
        what = "compressed image"
    else:
        w, h = int(msg.width), int(msg.height)
        what = "image"
        if int(msg.step) > 8 * MAX_IMAGE_DIM:
            return "image step %d exceeds %d" % (msg.step, 8 * MAX_IMAGE_DIM)
    why = _dims_problem(w, h, what)
    if why:
        return why
    if info is not None and int(info.width) > 0 and (w, h) != (int(info.width), int(info.height)):
        return "%s of %dx%d: sizes differ from the calibration (camera_info %dx%d)" % (
            what, w, h, info.width, info.height)
    return ""


def camera_info_problem(msg) -> str:
    """Why a CameraInfo is refused: a size of 0 or beyond MAX_IMAGE_DIM, non-finite K or P."""
    why = _dims_problem(int(msg.width), int(msg.height), "camera_info")
    if why:
        return why
    for name in ("K", "P"):
        v = getattr(msg, name)
        if not all(math.isfinite(float(x)) for x in v):
            return "camera_info %s has non-finite values" % name
    return ""


def cloud_problem(msg) -> str:
    """Why a PointCloud2 is refused: more than MAX_CLOUD_POINTS points, a point_step of 0 or
    beyond MAX_POINT_STEP, a field layout that does not fit the point (unknown type, overlap of
    the point's end, a duplicated name, absurd counts), or data whose length disagrees with
    width, height and row_step."""
    w, h, step, row = int(msg.width), int(msg.height), int(msg.point_step), int(msg.row_step)
    n = w * h
    if n > MAX_CLOUD_POINTS:
        return "cloud of %dx%d points exceeds %d" % (w, h, MAX_CLOUD_POINTS)
    if len(msg.fields) > MAX_CLOUD_FIELDS:
        return "cloud has %d fields (at most %d)" % (len(msg.fields), MAX_CLOUD_FIELDS)
    if n == 0:
        return "" if len(msg.data) <= MAX_POINT_STEP else "empty cloud with %d bytes of data" % \
            len(msg.data)
    if step <= 0 or step > MAX_POINT_STEP:
        return "cloud point_step %d outside 1..%d" % (step, MAX_POINT_STEP)
    names = set()
    for f in msg.fields:
        size = _FIELD_SIZE.get(int(f.datatype))
        if size is None:
            return "cloud field %r has unknown datatype %d" % (f.name, f.datatype)
        count = max(1, int(f.count))
        if count > MAX_FIELD_COUNT or int(f.offset) < 0 or int(f.offset) + size * count > step:
            return "cloud field %r (offset %d, count %d) does not fit point_step %d" % (
                f.name, f.offset, f.count, step)
        if f.name in names:
            return "cloud field %r appears twice" % f.name
        names.add(f.name)
    if row < w * step:
        return "cloud row_step %d < width %d * point_step %d" % (row, w, step)
    need = row * (h - 1) + w * step
    if len(msg.data) < need or len(msg.data) > row * h:
        return "cloud data truncated or too long: %d bytes for %dx%d points (row_step %d: " \
            "%d..%d expected)" % (
            len(msg.data), w, h, row, need, row * h)
    return ""


def pose_problem(pose) -> str:
    """Why a geometry_msgs/Pose is refused: non-finite values or a quaternion whose norm is not
    1 within QUATERNION_NORM_TOL."""
    q = (pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w)
    t = (pose.position.x, pose.position.y, pose.position.z)
    if not all(math.isfinite(float(v)) for v in q + t):
        return "pose has non-finite values: t=%s q=%s" % (t, q)
    norm = math.sqrt(sum(float(v) ** 2 for v in q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOL:
        return "pose quaternion has norm %.4g (not a rotation)" % norm
    return ""
