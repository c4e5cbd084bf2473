"""The one module that converts between ROS messages and numpy (vectorized, no per-point loops).

Nodes and the bag tools call these; the core library (pose, depth, fusion, sim, eval) never sees a
ROS message. Everything here raises :class:`ConversionError` (a ``ValueError``) with a message a
user can act on when a message is malformed, so a node can log it (throttled) and skip the input.

- Image <-> ndarray: mono8, mono16, bgr8, rgb8, bgra8, rgba8, 8UC1, 8UC3, 16UC1, 32FC1, bgr16,
  rgb16, bgra16, rgba16, the Bayer encodings (bayer_rggb8 ... bayer_grbg16) and yuv422 (UYVY) /
  yuv422_yuy2 (row padding and big-endian data handled). Colour, Bayer and YUV images are turned
  into grey with ``to_mono=True`` (OpenCV's conversions, with cv_bridge's Bayer mapping);
  :func:`image_to_mono8` gives the 8-bit grey image the depth and pose code work on.
- CompressedImage (image_transport's ``compressed`` plugin: png, jpeg) -> grey with
  :func:`compressed_image_to_mono8`; :func:`numpy_to_compressed_image` writes one with the
  ``format`` string compressed_image_transport writes (for driver-like bags).
- CameraInfo <-> :class:`mdr_slam.camera.CameraModel`.
- PointCloud2 <-> dict of per-field arrays (any FLOAT32/FLOAT64/integer fields) via one structured
  numpy view of the buffer: sensor_msgs.point_cloud2's per-point Python path takes seconds for
  100k points, this takes milliseconds.
- Pose, PoseStamped, TransformStamped, Odometry <-> 4x4 matrices.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Mapping, Optional, Sequence

import cv2
import numpy as np

import genpy
from geometry_msgs.msg import Pose, PoseStamped, Transform, TransformStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2, PointField
from std_msgs.msg import Header

from .camera import CameraModel
from .geometry import make_T, quat_to_R, R_to_quat
from .msg_checks import pose_problem

__all__ = [
    "ConversionError", "image_to_numpy", "image_to_mono8", "image_msg_to_mono8", "numpy_to_image",
    "compressed_image_to_mono8", "numpy_to_compressed_image", "camera_info_to_model",
    "model_to_camera_info", "pointcloud2_to_arrays", "pointcloud2_to_xyz", "arrays_to_pointcloud2",
    "pose_to_matrix", "matrix_to_pose", "pose_stamped_to_matrix", "matrix_to_pose_stamped",
    "transform_to_matrix", "matrix_to_transform", "transform_stamped_to_matrix",
    "matrix_to_transform_stamped", "make_header", "stamp_to_sec",
]


class ConversionError(ValueError):
    """A ROS message that cannot be converted (bad encoding, size mismatch, truncated data)."""


# ----------------------------------------------------------------------------------- headers
def make_header(stamp=None, frame_id: str = "", seq: int = 0) -> Header:
    h = Header()
    h.seq = seq
    h.frame_id = frame_id
    if stamp is not None:
        h.stamp = _to_time(stamp)
    return h


def _to_time(stamp):
    if isinstance(stamp, genpy.Time):
        return stamp
    if isinstance(stamp, (int, np.integer)):  # nanoseconds
        return genpy.Time(int(stamp) // 1000000000, int(stamp) % 1000000000)
    return genpy.Time.from_sec(float(stamp))


def stamp_to_sec(stamp) -> float:
    return stamp.secs + 1e-9 * stamp.nsecs


# ------------------------------------------------------------------------------------ images
def _as_bytes(data):
    """Message data as a buffer (bytes when deserialized; a list when built by hand)."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        return data
    return bytes(bytearray(data))


# encoding -> (numpy dtype, channels)
_ENCODINGS = {
    "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1),
    "mono16": (np.uint16, 1), "16UC1": (np.uint16, 1),
    "bgr8": (np.uint8, 3), "rgb8": (np.uint8, 3), "8UC3": (np.uint8, 3),
    "bgra8": (np.uint8, 4), "rgba8": (np.uint8, 4),
    "bgr16": (np.uint16, 3), "rgb16": (np.uint16, 3), "bgra16": (np.uint16, 4),
    "rgba16": (np.uint16, 4),
    "yuv422": (np.uint8, 2), "yuv422_yuy2": (np.uint8, 2),
    "32FC1": (np.float32, 1),
}
# encoding -> name of the cv2 code that makes it grey. Bayer as cv_bridge maps it: OpenCV names a
# pattern by the 2nd and 3rd pixels of its second row, so ROS "rggb" (RGGB...) is OpenCV's "BG".
_GREY_CODES = {"bgr8": "BGR2GRAY", "8UC3": "BGR2GRAY", "rgb8": "RGB2GRAY", "bgra8": "BGRA2GRAY",
               "rgba8": "RGBA2GRAY", "bgr16": "BGR2GRAY", "rgb16": "RGB2GRAY",
               "bgra16": "BGRA2GRAY", "rgba16": "RGBA2GRAY",
               "yuv422": "YUV2GRAY_UYVY", "yuv422_yuy2": "YUV2GRAY_YUY2"}
_BAYER = {"rggb": "BG", "bggr": "RG", "gbrg": "GR", "grbg": "GB"}
_ENCODINGS.update({"bayer_%s%d" % (p, b): (np.uint8 if b == 8 else np.uint16, 1)
                   for p in _BAYER for b in (8, 16)})
_GREY_CODES.update({"bayer_%s%d" % (p, b): "Bayer%s2GRAY" % c
                    for p, c in _BAYER.items() for b in (8, 16)})


def image_to_numpy(msg: Image, to_mono: bool = False) -> np.ndarray:
    """(H, W) or (H, W, C) array viewing ``msg.data`` (copied only when padding/endianness need it).

    ``to_mono=True`` returns a single-channel image (grey from colour, Bayer and YUV images with
    OpenCV's conversions, in the source bit depth; mono16 and float stay as they are).
    """
    enc = msg.encoding
    if enc not in _ENCODINGS:
        raise ConversionError("unsupported image encoding %r (supported: %s)"
                              % (enc, ", ".join(sorted(_ENCODINGS))))
    dtype, ch = _ENCODINGS[enc]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    h, w = int(msg.height), int(msg.width)
    row_bytes = w * ch * dt.itemsize
    if h <= 0 or w <= 0:
        raise ConversionError("image has size %dx%d" % (w, h))
    if msg.step < row_bytes:
        raise ConversionError("image step %d is smaller than width*channels*bytes = %d"
                              % (msg.step, row_bytes))
    need = msg.step * (h - 1) + row_bytes
    if len(msg.data) < need:
        raise ConversionError("image data truncated: %d bytes for %dx%d %s with step %d (need %d)"
                              % (len(msg.data), w, h, enc, msg.step, need))
    buf = np.frombuffer(_as_bytes(msg.data), dtype=np.uint8)
    if msg.step == row_bytes:
        arr = buf[: h * row_bytes].view(dt).reshape(h, w, ch)
    else:  # padded rows: strided view, then a compact copy
        arr = np.lib.stride_tricks.as_strided(
            buf, shape=(h, row_bytes), strides=(msg.step, 1)).copy().view(dt).reshape(h, w, ch)
    if msg.is_bigendian and dt.itemsize > 1:
        arr = arr.astype(dt.newbyteorder("="))
    if ch == 1:
        arr = arr[:, :, 0]
    if to_mono and enc in _GREY_CODES:
        arr = cv2.cvtColor(np.ascontiguousarray(arr), getattr(cv2, "COLOR_" + _GREY_CODES[enc]))
    return arr


# encodings that carry intensity (16UC1 and 32FC1 are depth/disparity images, not camera images)
_INTENSITY = tuple(e for e in _ENCODINGS if e not in ("16UC1", "32FC1"))


def image_to_mono8(msg: Image) -> np.ndarray:
    """(H, W) uint8 grey image of a camera image message (what ELAS and ORB need).

    Colour, Bayer (demosaiced as cv_bridge does) and YUV 4:2:2 are converted to grey; 16-bit
    images keep their high byte (value >> 8; cv_bridge's 255/65535 scaling differs by at most 1).
    Raises ConversionError for encodings that are not intensity images (16UC1, 32FC1: depth maps)
    and for the malformed messages :func:`image_to_numpy` refuses.
    """
    if msg.encoding in _ENCODINGS and msg.encoding not in _INTENSITY:
        raise ConversionError("image encoding %r is not a camera intensity image (a depth or "
                              "disparity map; expected mono8/16, bgr8, rgb8, bayer_*, yuv422, ...)"
                              % msg.encoding)
    img = image_to_numpy(msg, to_mono=True)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    return np.ascontiguousarray(img)


def numpy_to_image(arr: np.ndarray, encoding: Optional[str] = None, stamp=None,
                   frame_id: str = "") -> Image:
    """Image message from an array. ``encoding`` defaults from dtype/shape (mono8, mono16,
    bgr8, bgra8, 32FC1)."""
    arr = np.asarray(arr)
    ch = 1 if arr.ndim == 2 else arr.shape[2]
    if encoding is None:
        encoding = {(np.dtype(np.uint8), 1): "mono8", (np.dtype(np.uint16), 1): "mono16",
                    (np.dtype(np.uint8), 3): "bgr8", (np.dtype(np.uint8), 4): "bgra8",
                    (np.dtype(np.float32), 1): "32FC1"}.get((arr.dtype, ch))
        if encoding is None:
            raise ConversionError("no image encoding for dtype %s with %d channels" % (arr.dtype, ch))
    if encoding not in _ENCODINGS:
        raise ConversionError("unsupported image encoding %r" % encoding)
    dtype, want_ch = _ENCODINGS[encoding]
    if ch != want_ch or arr.dtype != np.dtype(dtype):
        raise ConversionError("array %s x%d channels does not fit encoding %s"
                              % (arr.dtype, ch, encoding))
    msg = Image()
    msg.header = make_header(stamp, frame_id)
    msg.height, msg.width = int(arr.shape[0]), int(arr.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = 0
    a = np.ascontiguousarray(arr, dtype=np.dtype(dtype).newbyteorder("<"))
    msg.step = int(msg.width * ch * a.itemsize)
    msg.data = a.tobytes()
    return msg


# -------------------------------------------------------------------------- CompressedImage
def compressed_image_to_mono8(msg: CompressedImage) -> np.ndarray:
    """(H, W) uint8 grey image of a png or jpeg CompressedImage (image_transport's ``compressed``).

    Any ``format`` compressed_image_transport writes ("bgr8; jpeg compressed bgr8",
    "mono8; png compressed ", or just "jpeg"/"png" from old publishers) is decoded by what the data
    is: 8-bit images straight to grey, 16-bit png unchanged and then its high byte, as
    :func:`image_to_mono8` does. Raises ConversionError for compressedDepth images (depth maps)
    and for empty, undecodable or truncated data.
    """
    fmt = msg.format or ""
    if "compresseddepth" in fmt.lower():
        raise ConversionError("CompressedImage format %r is a compressed depth image, not a camera "
                              "image" % fmt)
    data = _as_bytes(msg.data)
    if len(data) == 0:
        raise ConversionError("CompressedImage (format %r) has no data" % fmt)
    if bytes(data[:2]) == b"\xff\xd8" and not bytes(data[-16:]).rstrip(b"\0").endswith(b"\xff\xd9"):
        # libjpeg decodes a truncated stream with only a warning, grey-filling the missing rows
        raise ConversionError("CompressedImage jpeg data is truncated (no end-of-image marker, "
                              "%d bytes)" % len(data))
    # PNG bit depth is byte 24 (signature, IHDR length and type, width, height)
    png16 = bytes(data[:8]) == b"\x89PNG\r\n\x1a\n" and len(data) > 24 and data[24] == 16
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8),
                       cv2.IMREAD_UNCHANGED if png16 else cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ConversionError("cannot decode CompressedImage (format %r, %d bytes): not png/jpeg "
                              "or truncated" % (fmt, len(data)))
    if img.ndim == 3:
        code = {3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}.get(img.shape[2])
        if code is None:
            raise ConversionError("CompressedImage png has %d channels" % img.shape[2])
        img = cv2.cvtColor(img, code)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    return img


def image_msg_to_mono8(msg) -> np.ndarray:
    """Grey uint8 image of a sensor_msgs/Image or a sensor_msgs/CompressedImage."""
    if getattr(msg, "_type", "") == "sensor_msgs/CompressedImage":
        return compressed_image_to_mono8(msg)
    return image_to_mono8(msg)


def numpy_to_compressed_image(arr: np.ndarray, fmt: str = "jpeg", stamp=None, frame_id: str = "",
                              quality: int = 95) -> CompressedImage:
    """CompressedImage of a mono8 (H, W) or bgr8 (H, W, 3) uint8 array (png also takes mono16),
    with the ``format`` compressed_image_transport writes: "mono8; jpeg compressed ",
    "bgr8; jpeg compressed bgr8", "mono8; png compressed ", "bgr8; png compressed bgr8".
    ``quality`` is the jpeg quality (0-100)."""
    arr = np.asarray(arr)
    if fmt not in ("jpeg", "png"):
        raise ConversionError("compressed format must be 'jpeg' or 'png', not %r" % (fmt,))
    ch = 1 if arr.ndim == 2 else (arr.shape[2] if arr.ndim == 3 else 0)
    enc = {(np.dtype(np.uint8), 1): "mono8", (np.dtype(np.uint8), 3): "bgr8",
           (np.dtype(np.uint16), 1): "mono16" if fmt == "png" else None}.get((arr.dtype, ch))
    if enc is None:
        raise ConversionError("cannot %s-compress a %s array of shape %s (mono8 or bgr8 arrays; "
                              "mono16 for png)" % (fmt, arr.dtype, arr.shape))
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if fmt == "jpeg" else []
    ok, data = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", np.ascontiguousarray(arr), params)
    if not ok:
        raise ConversionError("cv2.imencode (%s) failed for a %s array" % (fmt, arr.shape))
    msg = CompressedImage()
    msg.header = make_header(stamp, frame_id)
    # the transport appends the target encoding for colour images only (mono ends in a space)
    msg.format = "%s; %s compressed %s" % (enc, fmt, "bgr8" if enc == "bgr8" else "")
    msg.data = data.tobytes()
    return msg


# ------------------------------------------------------------------------------- CameraInfo
def camera_info_to_model(msg: CameraInfo) -> CameraModel:
    """CameraModel from a CameraInfo; raises ConversionError when it is empty or zero."""
    K = np.asarray(msg.K, dtype=float)
    P = np.asarray(msg.P, dtype=float)
    R = np.asarray(msg.R, dtype=float)
    if K.size != 9 or P.size != 12 or R.size != 9:
        raise ConversionError("camera_info has K/R/P of sizes %d/%d/%d" % (K.size, R.size, P.size))
    if not np.any(K) or not np.any(P):
        raise ConversionError("camera_info is uncalibrated (K or P all zeros); give a calib file")
    if not np.any(R):
        R = np.eye(9)  # an unset R means no rectification rotation
    model = CameraModel(width=msg.width, height=msg.height, K=K, D=np.asarray(msg.D, dtype=float),
                        R=R, P=P, distortion_model=msg.distortion_model or "plumb_bob",
                        frame_id=msg.header.frame_id)
    try:
        model.validate()
    except ValueError as e:
        raise ConversionError(str(e)) from e
    return model


def model_to_camera_info(model: CameraModel, stamp=None, frame_id: Optional[str] = None) -> CameraInfo:
    msg = CameraInfo()
    msg.header = make_header(stamp, model.frame_id if frame_id is None else frame_id)
    msg.width, msg.height = int(model.width), int(model.height)
    msg.distortion_model = model.distortion_model
    msg.D = [float(x) for x in model.D]
    msg.K = [float(x) for x in model.K.ravel()]
    msg.R = [float(x) for x in model.R.ravel()]
    msg.P = [float(x) for x in model.P.ravel()]
    return msg


# ------------------------------------------------------------------------------ PointCloud2
_PF_TO_NP = {
    PointField.INT8: np.int8, PointField.UINT8: np.uint8, PointField.INT16: np.int16,
    PointField.UINT16: np.uint16, PointField.INT32: np.int32, PointField.UINT32: np.uint32,
    PointField.FLOAT32: np.float32, PointField.FLOAT64: np.float64,
}
_NP_TO_PF = {np.dtype(v): k for k, v in _PF_TO_NP.items()}


def _cloud_dtype(msg: PointCloud2) -> np.dtype:
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in _PF_TO_NP:
            raise ConversionError("PointCloud2 field %r has unknown datatype %d" % (f.name, f.datatype))
        dt = np.dtype(_PF_TO_NP[f.datatype]).newbyteorder(">" if msg.is_bigendian else "<")
        names.append(f.name)
        formats.append(dt if f.count <= 1 else (dt, (f.count,)))
        offsets.append(f.offset)
    try:
        return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                         "itemsize": msg.point_step})
    except ValueError as e:
        raise ConversionError("PointCloud2 fields do not fit point_step %d: %s" % (msg.point_step, e))


def pointcloud2_to_arrays(msg: PointCloud2, fields: Optional[Sequence[str]] = None,
                          skip_nans: bool = False) -> "OrderedDict[str, np.ndarray]":
    """Per-field 1-D arrays (N = width*height) of a PointCloud2, in native byte order.

    ``skip_nans`` drops points whose x, y or z is not finite.
    """
    n = int(msg.width) * int(msg.height)
    out = OrderedDict()
    if n == 0:
        for f in msg.fields:
            if fields is None or f.name in fields:
                out[f.name] = np.zeros(0, dtype=_PF_TO_NP.get(f.datatype, np.float32))
        return out
    dt = _cloud_dtype(msg)
    row_used = int(msg.width) * int(msg.point_step)
    if msg.row_step < row_used or len(msg.data) < msg.row_step * (msg.height - 1) + row_used:
        raise ConversionError("PointCloud2 data truncated or row_step too small: %d bytes for "
                              "%dx%d points of %d bytes (row_step %d)" % (
                                  len(msg.data), msg.width, msg.height, msg.point_step, msg.row_step))
    buf = np.frombuffer(_as_bytes(msg.data), dtype=np.uint8)
    if msg.row_step == row_used:
        rec = buf[: n * msg.point_step].view(dt)
    else:
        rows = np.lib.stride_tricks.as_strided(buf, shape=(msg.height, row_used),
                                               strides=(msg.row_step, 1))
        rec = np.ascontiguousarray(rows).reshape(-1).view(dt)
    names = dt.names if fields is None else [f for f in fields]
    for name in names:
        if name not in dt.names:
            raise ConversionError("PointCloud2 has no field %r (has %s)" % (name, ", ".join(dt.names)))
        a = rec[name]
        out[name] = a.astype(a.dtype.newbyteorder("="), copy=True)
    if skip_nans and all(k in dt.names for k in "xyz"):
        x, y, z = (rec[k] for k in "xyz")
        keep = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
        if not keep.all():
            for k in out:
                out[k] = out[k][keep]
    return out


def pointcloud2_to_xyz(msg: PointCloud2, skip_nans: bool = True) -> np.ndarray:
    """(N, 3) float32 x, y, z of a PointCloud2."""
    a = pointcloud2_to_arrays(msg, ("x", "y", "z"), skip_nans=skip_nans)
    return np.stack([a["x"], a["y"], a["z"]], axis=1).astype(np.float32, copy=False)


def arrays_to_pointcloud2(arrays: Mapping[str, np.ndarray], stamp=None, frame_id: str = "",
                          xyz: Optional[np.ndarray] = None, dtype=np.float32) -> PointCloud2:
    """Unorganized PointCloud2 (height 1) from named 1-D arrays of equal length.

    ``xyz`` (N, 3) is a shortcut for the fields x, y, z. Float fields are stored as ``dtype``
    (float32 by default, what rviz and PCL expect); integer arrays keep their type.
    """
    cols: "OrderedDict[str, np.ndarray]" = OrderedDict()
    if xyz is not None:
        xyz = np.asarray(xyz)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ConversionError("xyz must be (N, 3), got %s" % (xyz.shape,))
        cols["x"], cols["y"], cols["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for k, v in arrays.items():
        cols[k] = np.asarray(v).reshape(-1)
    n = len(next(iter(cols.values()))) if cols else 0
    for k, v in cols.items():
        if len(v) != n:
            raise ConversionError("field %r has %d values, expected %d" % (k, len(v), n))
    np_fields, pfields, offset = [], [], 0
    for k, v in cols.items():
        dt = np.dtype(dtype) if v.dtype.kind in "fb" else v.dtype
        if v.dtype.kind == "b":
            dt = np.dtype(np.uint8)
        if dt.newbyteorder("=") not in _NP_TO_PF:
            raise ConversionError("field %r has unsupported dtype %s" % (k, v.dtype))
        dt = dt.newbyteorder("<")
        np_fields.append((k, dt))
        pfields.append(PointField(name=k, offset=offset, datatype=_NP_TO_PF[dt.newbyteorder("=")],
                                  count=1))
        offset += dt.itemsize
    rec = np.empty(n, dtype=np_fields)
    for k, v in cols.items():
        rec[k] = v
    msg = PointCloud2()
    msg.header = make_header(stamp, frame_id)
    msg.height, msg.width = 1, n
    msg.fields = pfields
    msg.is_bigendian = False
    msg.point_step = offset
    msg.row_step = offset * n
    msg.is_dense = bool(n == 0 or all(np.all(np.isfinite(cols[c])) for c in "xyz" if c in cols))
    msg.data = rec.tobytes()
    return msg


# ------------------------------------------------------------------------------------ poses
def pose_to_matrix(p: Pose) -> np.ndarray:
    q = (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w)
    t = (p.position.x, p.position.y, p.position.z)
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
        raise ConversionError("pose has non-finite values: t=%s q=%s" % (t, q))
    if np.linalg.norm(q) < 1e-6:
        raise ConversionError("pose quaternion is zero")
    why = pose_problem(p)   # a quaternion far from unit norm is garbage, not a rotation
    if why:
        raise ConversionError(why)
    return make_T(quat_to_R(q), t)


def matrix_to_pose(T: np.ndarray) -> Pose:
    p = Pose()
    q = R_to_quat(T[:3, :3])
    p.position.x, p.position.y, p.position.z = (float(v) for v in T[:3, 3])
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = (float(v) for v in q)
    return p


def pose_stamped_to_matrix(msg: PoseStamped) -> np.ndarray:
    return pose_to_matrix(msg.pose)


def matrix_to_pose_stamped(T: np.ndarray, stamp=None, frame_id: str = "map") -> PoseStamped:
    msg = PoseStamped()
    msg.header = make_header(stamp, frame_id)
    msg.pose = matrix_to_pose(T)
    return msg


def transform_to_matrix(t: Transform) -> np.ndarray:
    q = (t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w)
    p = (t.translation.x, t.translation.y, t.translation.z)
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(p))):
        raise ConversionError("transform has non-finite values: t=%s q=%s" % (p, q))
    if np.linalg.norm(q) < 1e-6:
        raise ConversionError("transform quaternion is zero")
    return make_T(quat_to_R(q), p)


def matrix_to_transform(T: np.ndarray) -> Transform:
    t = Transform()
    q = R_to_quat(T[:3, :3])
    t.translation.x, t.translation.y, t.translation.z = (float(v) for v in T[:3, 3])
    t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w = (float(v) for v in q)
    return t


def transform_stamped_to_matrix(msg: TransformStamped) -> np.ndarray:
    return transform_to_matrix(msg.transform)


def matrix_to_transform_stamped(T: np.ndarray, stamp=None, parent: str = "map",
                                child: str = "") -> TransformStamped:
    msg = TransformStamped()
    msg.header = make_header(stamp, parent)
    msg.child_frame_id = child
    msg.transform = matrix_to_transform(T)
    return msg
