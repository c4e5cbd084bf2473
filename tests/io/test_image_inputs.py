"""Camera image inputs: Bayer, YUV and 16-bit colour images, CompressedImage, and the switch for
images that are already rectified while their camera_info carries the raw calibration."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from mdr_slam import conversions as cv
from mdr_slam.camera import CameraModel, StereoCamera, images_are_rectified
from mdr_slam.geometry import quat_to_R

from conftest import serialize_roundtrip


def _colour(h=64, w=80):
    """Smooth BGR image whose channels differ a lot, so a wrong Bayer pattern changes the grey."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    b = 30 + 20 * np.sin(x / 9.0)
    g = 110 + 40 * np.cos(y / 11.0)
    r = 200 + 30 * np.sin((x + y) / 13.0)
    return np.clip(np.stack([b, g, r], axis=2), 0, 255).round().astype(np.uint8)


def _mosaic(bgr, pattern):
    """Bayer mosaic of a BGR image in a ROS pattern ("rggb" = R G on even rows, G B on odd)."""
    out = np.empty(bgr.shape[:2], bgr.dtype)
    for i, c in enumerate(pattern):
        out[i // 2::2, i % 2::2] = bgr[i // 2::2, i % 2::2, "bgr".index(c)]
    return out


PATTERNS = ("rggb", "bggr", "gbrg", "grbg")


@pytest.mark.parametrize("bits", [8, 16])
def test_bayer_patterns_give_the_grey_of_the_colour_image(bits):
    colour = _colour()
    want = cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY).astype(int)[4:-4, 4:-4]
    src = colour if bits == 8 else colour.astype(np.uint16) * 257
    for pattern in PATTERNS:
        enc = "bayer_%s%d" % (pattern, bits)
        msg = serialize_roundtrip(cv.numpy_to_image(_mosaic(src, pattern), enc))
        grey = cv.image_to_mono8(msg)
        assert grey.dtype == np.uint8 and grey.shape == colour.shape[:2]
        assert np.abs(grey.astype(int)[4:-4, 4:-4] - want).max() <= 3, pattern
        # the test image tells the patterns apart: read as any other pattern it is far off
        for other in PATTERNS:
            if other != pattern:
                msg.encoding = "bayer_%s%d" % (other, bits)
                wrong = cv.image_to_mono8(msg).astype(int)[4:-4, 4:-4]
                assert np.abs(wrong - want).mean() > 10, (pattern, other)


def test_big_endian_padded_bayer16():
    colour16 = _colour().astype(np.uint16) * 257
    m = _mosaic(colour16, "gbrg")
    msg = cv.numpy_to_image(m, "bayer_gbrg16")
    msg.is_bigendian, msg.step = 1, m.shape[1] * 2 + 6
    msg.data = b"".join(r.astype(">u2").tobytes() + b"\0" * 6 for r in m)
    ref = cv.image_to_mono8(cv.numpy_to_image(m, "bayer_gbrg16"))
    np.testing.assert_array_equal(cv.image_to_mono8(msg), ref)


def test_yuv422_takes_the_luma():
    rng = np.random.default_rng(0)
    Y = rng.integers(0, 256, (6, 10), dtype=np.uint8)
    UV = rng.integers(0, 256, (6, 10), dtype=np.uint8)  # U0 V0 U1 V1 ... shared by pixel pairs
    uyvy = np.stack([UV, Y], axis=2)
    msg = serialize_roundtrip(cv.numpy_to_image(uyvy, "yuv422"))
    np.testing.assert_array_equal(cv.image_to_mono8(msg), Y)
    yuy2 = np.stack([Y, UV], axis=2)
    np.testing.assert_array_equal(cv.image_to_mono8(cv.numpy_to_image(yuy2, "yuv422_yuy2")), Y)


@pytest.mark.parametrize("encoding", ["bgr16", "rgb16", "bgra16", "rgba16", "8UC3"])
def test_16bit_and_generic_colour(encoding):
    bgr = _colour(8, 10)
    want = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(int)
    a = bgr[..., ::-1] if encoding.startswith("rgb") else bgr
    if encoding.endswith("a16"):
        a = np.concatenate([a, np.full(a.shape[:2] + (1,), 255, np.uint8)], axis=2)
    if encoding.endswith("16"):
        a = a.astype(np.uint16) * 257
    grey = cv.image_to_mono8(cv.numpy_to_image(np.ascontiguousarray(a), encoding))
    assert grey.dtype == np.uint8 and np.abs(grey.astype(int) - want).max() <= 1


def test_agrees_with_cv_bridge():
    cv_bridge = pytest.importorskip("cv_bridge")
    br = cv_bridge.CvBridge()
    colour = _colour(16, 20)
    cases = {"yuv422": np.stack([colour[..., 0], colour[..., 1]], axis=2),
             "bgr16": colour.astype(np.uint16) * 257, "rgb16": colour.astype(np.uint16) * 257,
             "mono16": colour[..., 2].astype(np.uint16) * 257 + 100}
    for p in PATTERNS:
        cases["bayer_%s8" % p] = _mosaic(colour, p)
        cases["bayer_%s16" % p] = _mosaic(colour, p).astype(np.uint16) * 257 + 128
    for enc, a in cases.items():
        msg = cv.numpy_to_image(a, enc)
        ours = cv.image_to_mono8(msg).astype(int)
        theirs = br.imgmsg_to_cv2(msg, "mono8").astype(int)
        # cv_bridge scales 16 bit by 255/65535 (rounded), we keep the high byte
        assert np.abs(ours - theirs).max() <= (1 if a.dtype == np.uint16 else 0), enc


def test_depth_and_malformed_images_are_refused():
    for a, enc in ((np.zeros((4, 4), np.uint16), "16UC1"), (np.zeros((4, 4), np.float32), "32FC1")):
        with pytest.raises(cv.ConversionError, match="depth"):
            cv.image_to_mono8(cv.numpy_to_image(a, enc))
    msg = cv.numpy_to_image(np.zeros((4, 6), np.uint8), "bayer_rggb8")
    msg.data = msg.data[:20]
    with pytest.raises(cv.ConversionError, match="truncated"):
        cv.image_to_mono8(msg)
    msg = cv.numpy_to_image(np.zeros((4, 6, 2), np.uint8), "yuv422")
    msg.step = 6
    with pytest.raises(cv.ConversionError, match="step"):
        cv.image_to_mono8(msg)


# ---------------------------------------------------------------------------- CompressedImage
@pytest.mark.parametrize("fmt", ["jpeg", "png"])
def test_compressed_roundtrip_and_format_strings(fmt):
    colour = _colour()
    mono = cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)
    for arr, fmt_str in ((mono, "mono8; %s compressed " % fmt),
                         (colour, "bgr8; %s compressed bgr8" % fmt)):
        msg = cv.numpy_to_compressed_image(arr, fmt, stamp=2.5, frame_id="cam0", quality=90)
        assert msg.format == fmt_str
        assert msg.header.frame_id == "cam0" and cv.stamp_to_sec(msg.header.stamp) == 2.5
        grey = cv.compressed_image_to_mono8(serialize_roundtrip(msg))
        assert grey.dtype == np.uint8 and grey.shape == mono.shape
        err = np.abs(grey.astype(int) - mono)
        if fmt == "png":
            assert err.max() <= 1
        else:
            assert err.mean() < 2 and err.max() <= 12
    # a hand-built message (data as a list) and older or third-party format strings
    msg = cv.numpy_to_compressed_image(colour, fmt)
    for f in (fmt, "rgb8; %s compressed bgr8" % fmt, ""):
        m = type(msg)(format=f, data=list(msg.data))
        assert np.abs(cv.compressed_image_to_mono8(m).astype(int) - mono).mean() < 2


def test_compressed_16bit_png():
    rng = np.random.default_rng(3)
    mono16 = rng.integers(0, 65536, (12, 16), dtype=np.uint16)
    msg = cv.numpy_to_compressed_image(mono16, "png")
    assert msg.format == "mono16; png compressed "
    np.testing.assert_array_equal(cv.compressed_image_to_mono8(msg), (mono16 >> 8).astype(np.uint8))
    colour = _colour(12, 16)
    ok, data = cv2.imencode(".png", colour.astype(np.uint16) * 257)
    msg.format, msg.data = "bgr16; png compressed bgr16", data.tobytes()
    want = cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY).astype(int)
    assert np.abs(cv.compressed_image_to_mono8(msg).astype(int) - want).max() <= 1
    with pytest.raises(cv.ConversionError, match="mono8 or bgr8"):
        cv.numpy_to_compressed_image(mono16, "jpeg")


def test_compressed_errors():
    colour = _colour()
    for fmt in ("jpeg", "png"):
        msg = cv.numpy_to_compressed_image(colour, fmt)
        msg.data = msg.data[: len(msg.data) // 2]
        with pytest.raises(cv.ConversionError, match="truncated"):
            cv.compressed_image_to_mono8(msg)
    good = cv.numpy_to_compressed_image(colour, "png")
    for f in ("16UC1; compressedDepth png", "32FC1; compressedDepth", "16UC1; compressedDepth rvl"):
        with pytest.raises(cv.ConversionError, match="depth"):
            cv.compressed_image_to_mono8(type(good)(format=f, data=good.data))
    for data in (b"", b"not an image at all"):
        with pytest.raises(cv.ConversionError):
            cv.compressed_image_to_mono8(type(good)(format="jpeg", data=data))
    with pytest.raises(cv.ConversionError, match="jpeg"):
        cv.numpy_to_compressed_image(colour, "bmp")
    with pytest.raises(cv.ConversionError):
        cv.numpy_to_compressed_image(np.zeros((4, 4), np.float32))


# ------------------------------------------------------------------------- rectified images
def _raw_pair():
    """A raw calibration as camera_info carries it: distortion, rectifying rotations, P != K."""
    K = np.array([[458.6, 0, 367.2], [0, 457.3, 248.4], [0, 0, 1]])
    Pl = np.array([[435.2, 0, 367.5, 0], [0, 435.2, 252.2, 0], [0, 0, 1, 0]])
    Pr = Pl.copy()
    Pr[0, 2], Pr[0, 3] = 368.0, -435.2 * 0.11
    D = [-0.28, 0.07, 0.0002, 1.7e-05, 0.0]
    left = CameraModel(752, 480, K, D, quat_to_R([0.01, -0.02, 0.003, 1.0]), Pl, frame_id="cam0")
    right = CameraModel(752, 480, K, D, quat_to_R([-0.01, 0.02, 0.001, 1.0]), Pr, frame_id="cam1")
    return StereoCamera(left, right)


def test_assume_rectified():
    raw = _raw_pair()
    assert not raw.is_rectified
    cam = raw.assume_rectified()
    assert cam.is_rectified and cam.left.is_rectified and cam.right.is_rectified
    for name in ("fx", "fy", "cx", "cy", "baseline", "doffs", "size"):
        assert getattr(cam, name) == getattr(raw, name), name
    assert raw.doffs == pytest.approx(-0.5) and cam.baseline == pytest.approx(0.11)
    for new, old in ((cam.left, raw.left), (cam.right, raw.right)):
        np.testing.assert_array_equal(new.K, old.P[:, :3])
        np.testing.assert_array_equal(new.P, old.P)
        np.testing.assert_array_equal(new.R, np.eye(3))
        assert not np.any(new.D)
        assert (new.frame_id, new.width, new.height) == (old.frame_id, old.width, old.height)
    assert np.any(raw.left.D) and not np.allclose(raw.left.R, np.eye(3))  # original untouched
    img = np.random.default_rng(0).integers(0, 256, (480, 752), dtype=np.uint8)
    left, right = cam.rectify(img, img)
    assert left is img and right is img
    assert not np.array_equal(raw.rectify(img, img)[0], img)


def test_images_are_rectified():
    raw, rect = _raw_pair(), StereoCamera.from_rectified(752, 480, 435.0, 435.0, 367.0, 252.0, 0.11)
    for topic in ("/stereo/left/image_rect", "stereo/left/image_rect_color",
                  "/zed/zed_node/left/image_rect_color", "/camera/infra1/image_rect_raw",
                  "/stereo/left/image_rect/compressed", "/stereo/left/image_rect/"):
        assert images_are_rectified("auto", topic, raw), topic
    for topic in ("/stereo/left/image_raw", "/cam0/image_raw/compressed",
                  "/image_rect/left/image_raw", "/cam0/compressed", "", None):
        assert images_are_rectified("auto", topic, raw) is False, topic
        assert images_are_rectified("auto", topic, rect) is True
    assert images_are_rectified("auto", "/cam0/image_raw", raw.left) is False
    for setting in ("true", "True", True):
        assert images_are_rectified(setting, "/cam0/image_raw", raw) is True
    for setting in ("false", " FALSE ", False):
        assert images_are_rectified(setting, "/stereo/left/image_rect", rect) is False
    for bad in ("yes", "", 1, None, "rect"):
        with pytest.raises(ValueError, match="auto"):
            images_are_rectified(bad, "/cam0/image_raw", raw)
