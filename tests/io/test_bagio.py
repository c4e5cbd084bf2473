"""mdr_slam.bagio: stereo bags written and read back; pairing, camera_info, ground truth, and
bags as drivers record them (receive order, infos after the images, right lag, compressed)."""
from __future__ import annotations

import re

import numpy as np
import pytest

from mdr_slam import bagio
from mdr_slam.camera import StereoCamera
from mdr_slam.geometry import make_T, quat_to_R


def test_stereo_bag_roundtrip(tmp_path):
    cam = StereoCamera.from_rectified(64, 48, 50.0, 50.0, 32.0, 24.0, 0.1)
    path = str(tmp_path / "s.bag")
    rng = np.random.default_rng(0)
    imgs = [(rng.integers(0, 255, (48, 64), dtype=np.uint8),
             rng.integers(0, 255, (48, 64), dtype=np.uint8)) for _ in range(4)]
    Ts = [make_T(quat_to_R([0, 0, np.sin(0.05 * i), np.cos(0.05 * i)]), [0.1 * i, 0, 0]) for i in range(4)]
    with bagio.StereoBagWriter(path) as w:
        for i, ((l, r), T) in enumerate(zip(imgs, Ts)):
            w.write_ground_truth(10.0 + 0.05 * i, T)
            w.write_stereo(10.0 + 0.05 * i, l, r, cam)
        # an unpaired left image and a right image of another size: both skipped, with a reason
        w.write_stereo(10.5, imgs[0][0], np.zeros((10, 10), np.uint8))
    skipped = []
    frames = list(bagio.read_stereo_frames(path, on_skip=skipped.append, with_ground_truth=True))
    assert [f.index for f in frames] == [0, 1, 2, 3]
    for f, (l, r), T in zip(frames, imgs, Ts):
        np.testing.assert_array_equal(f.left, l)
        np.testing.assert_array_equal(f.right, r)
        np.testing.assert_allclose(f.T_map_cam_gt, T, atol=1e-9)
        assert abs(f.left_info.P[0, 0] - 50.0) < 1e-12
        assert abs(StereoCamera(f.left_info, f.right_info).baseline - 0.1) < 1e-12
    assert any("sizes differ" in s for s in skipped)
    gt = bagio.read_ground_truth(path)
    mid = gt.at(10.025)
    np.testing.assert_allclose(mid[:3, 3], [0.05, 0, 0], atol=1e-9)
    assert gt.at(11.0) is None
    assert len(list(bagio.read_stereo_frames(path, max_frames=2))) == 2
    # ground truth only when asked
    assert all(f.T_map_cam_gt is None for f in bagio.read_stereo_frames(path))


# ------------------------------------------------------------ bags as drivers record them
CAM = StereoCamera.from_rectified(32, 24, 30.0, 30.0, 16.0, 12.0, 0.1)


def _frame_images(i):
    """Left image of frame i is all 2*i+10, the right all 2*i+11: a pair tells its frames."""
    return np.full((24, 32), 2 * i + 10, np.uint8), np.full((24, 32), 2 * i + 11, np.uint8)


def _image_msg(img, stamp, transport, encoding):
    from mdr_slam import conversions as cv
    if transport in ("jpeg", "png"):
        return cv.numpy_to_compressed_image(img, transport, stamp=stamp)
    if encoding == "mono16":
        return cv.numpy_to_image(img.astype(np.uint16) * 256 + 77, "mono16", stamp=stamp)
    if encoding == "bgr8":
        return cv.numpy_to_image(np.repeat(img[:, :, None], 3, axis=2), "bgr8", stamp=stamp)
    return cv.numpy_to_image(img, "mono8", stamp=stamp)


def write_driver_bag(path, n=30, rate=20.0, right_lag=0.0, info="before", receive_jitter=0.0,
                     transport="raw", encoding="mono8", fx_per_frame=False, gt=False, seed=0):
    """A stereo bag as a driver and ``rosbag record`` make it: each message is written at the
    time it is received (its stamp plus a random delay up to ``receive_jitter`` s: the bag's
    order is then not the stamps'), the right image stamped ``right_lag`` s after the left,
    camera_info "before" or "after" each image (same stamp), only "once" at the end of the bag,
    or "none"; images raw (mono8, mono16, bgr8) or compressed ("jpeg", "png") on
    <topic>/compressed. ``fx_per_frame``: frame i's camera_info has fx = 30 + i."""
    import genpy
    import rosbag
    from mdr_slam import conversions as cv
    rng = np.random.default_rng(seed)
    T = bagio.DEFAULT_TOPICS
    suffix = "/compressed" if transport in ("jpeg", "png") else ""
    recs = []   # (receive time, order, topic, msg)
    for i in range(n):
        imgs = _frame_images(i)
        for side, img, lag in (("left", imgs[0], 0.0), ("right", imgs[1], right_lag)):
            stamp = 1000.0 + i / rate + lag
            t_rx = stamp + rng.uniform(0.0, receive_jitter) + 0.004
            model = CAM.left if side == "left" else CAM.right
            if fx_per_frame:
                model = bagio.CameraModel(model.width, model.height, model.K, model.D, model.R,
                                          model.P.copy())
                model.P[0, 0] = 30.0 + i
                if side == "right":
                    model.P[0, 3] = -model.P[0, 0] * 0.1
            recs.append((t_rx, 1, T[side + "_image"] + suffix,
                         _image_msg(img, stamp, transport, encoding)))
            if info in ("before", "after"):
                recs.append((t_rx, 0 if info == "before" else 2, T[side + "_info"],
                             cv.model_to_camera_info(model, stamp=stamp)))
        if gt:
            stamp = 1000.0 + i / rate
            recs.append((stamp + 0.004, 1, T["ground_truth"], cv.matrix_to_pose_stamped(
                make_T(np.eye(3), [0.1 * i, 0, 0]), stamp)))
    end = max(r[0] for r in recs) + 0.01
    if info == "once":
        for side in ("left", "right"):
            recs.append((end, 0, T[side + "_info"], cv.model_to_camera_info(
                CAM.left if side == "left" else CAM.right, stamp=end)))
    recs.sort(key=lambda r: (r[0], r[1]))
    with rosbag.Bag(path, "w") as bag:
        for t_rx, _, topic, msg in recs:
            bag.write(topic, msg, genpy.Time.from_sec(t_rx))
    return path


def _check_frames(frames, n, tol=0):
    assert [f.index for f in frames] == list(range(n))
    for i, f in enumerate(frames):
        assert f.left.dtype == np.uint8 and f.left.shape == (24, 32)
        assert abs(int(np.median(f.left)) - (2 * i + 10)) <= tol, (i, np.median(f.left))
        assert abs(int(np.median(f.right)) - (2 * i + 11)) <= tol, (i, np.median(f.right))
        assert f.stamp == pytest.approx(1000.0 + i / 20.0, abs=1e-6)   # the left's
    assert all(b.stamp > a.stamp for a, b in zip(frames, frames[1:]))


@pytest.mark.parametrize("info", ["before", "after", "once"])
def test_camera_info_before_after_or_once(tmp_path, info):
    path = write_driver_bag(str(tmp_path / "b.bag"), info=info)
    skipped = []
    frames = list(bagio.read_stereo_frames(path, on_skip=skipped.append))
    _check_frames(frames, 30)
    assert skipped == []
    for f in frames:
        assert StereoCamera(f.left_info, f.right_info).baseline == pytest.approx(0.1)
        assert f.left_info.P[0, 0] == 30.0


def test_camera_info_after_its_image_is_the_image_s(tmp_path):
    """With info recorded after its image (same stamp) each frame takes its own, not the last
    frame's: the info stamped at or before the image."""
    path = write_driver_bag(str(tmp_path / "b.bag"), info="after", fx_per_frame=True)
    frames = list(bagio.read_stereo_frames(path))
    _check_frames(frames, 30)
    assert [f.left_info.P[0, 0] for f in frames] == [30.0 + i for i in range(30)]
    assert [f.right_info.P[0, 0] for f in frames] == [30.0 + i for i in range(30)]


def test_no_camera_info_gives_none(tmp_path):
    path = write_driver_bag(str(tmp_path / "b.bag"), n=5, info="none")
    frames = list(bagio.read_stereo_frames(path))
    assert len(frames) == 5 and all(f.left_info is None and f.right_info is None for f in frames)


def test_right_lag_pairs_within_the_tolerance(tmp_path):
    """A ZED-like 3 ms right lag pairs (auto tolerance: 0.4 of the 50 ms period = 20 ms); 25 ms
    (half a period: 25 ms from both neighbouring lefts) does not, every image reported as
    skipped, unless the tolerance is set above it. (A 30 ms lag is the boundary: the right is
    then 20 ms before the next left, within the tolerance.)"""
    path = write_driver_bag(str(tmp_path / "a.bag"), right_lag=0.003)
    frames = list(bagio.read_stereo_frames(path))
    _check_frames(frames, 30)
    assert [f.right_stamp - f.stamp for f in frames] == pytest.approx([0.003] * 30, abs=1e-6)
    path = write_driver_bag(str(tmp_path / "b.bag"), right_lag=0.025)
    skipped = []
    assert list(bagio.read_stereo_frames(path, on_skip=skipped.append)) == []
    assert len(skipped) == 60 and all("partner within 20.0 ms (nearest" in s
                                      for s in skipped), skipped[:3]
    lefts = [s for s in skipped if re.search(r"^left image .*nearest right [+-]25\.0 ms", s)]
    assert len(lefts) == 30
    frames = list(bagio.read_stereo_frames(path, sync_tolerance=0.03))
    _check_frames(frames, 30)
    assert [f.right_stamp - f.stamp for f in frames] == pytest.approx([0.025] * 30, abs=1e-6)


def test_messages_out_of_stamp_order_pair(tmp_path):
    """Receive delays up to 120 ms at 20 Hz: images recorded up to two frames late, left and
    right in any order, infos after their images; the pairs come out whole and in stamp order."""
    import rosbag
    path = write_driver_bag(str(tmp_path / "b.bag"), info="after", receive_jitter=0.12,
                            right_lag=0.002, gt=True)
    with rosbag.Bag(path) as bag:
        st = [m.header.stamp.to_sec() for _, m, _ in bag.read_messages(
            topics=[bagio.DEFAULT_TOPICS["left_image"]])]
    assert any(b < a for a, b in zip(st, st[1:]))      # the bag really is out of stamp order
    skipped = []
    frames = list(bagio.read_stereo_frames(path, on_skip=skipped.append, with_ground_truth=True))
    _check_frames(frames, 30)
    assert skipped == []
    assert [f.T_map_cam_gt[0, 3] for f in frames] == pytest.approx([0.1 * i for i in range(30)])
    assert [f.index for f in bagio.read_stereo_frames(path, max_frames=7)] == list(range(7))


@pytest.mark.parametrize("transport", ["jpeg", "png"])
def test_compressed_images(tmp_path, transport):
    path = write_driver_bag(str(tmp_path / "b.bag"), transport=transport, n=10)
    skipped = []
    frames = list(bagio.read_stereo_frames(path, image_transport="compressed",
                                           on_skip=skipped.append))
    _check_frames(frames, 10, tol=1 if transport == "jpeg" else 0)
    assert skipped == []
    assert list(bagio.read_stereo_frames(path)) == []          # not on the raw topics
    assert bagio.bag_image_topics(path) == {
        "/stereo/left/image_raw/compressed": "sensor_msgs/CompressedImage",
        "/stereo/right/image_raw/compressed": "sensor_msgs/CompressedImage"}
    with pytest.raises(ValueError):
        bagio.image_topics(None, "theora")


@pytest.mark.parametrize("encoding", ["mono16", "bgr8"])
def test_raw_intensity_encodings(tmp_path, encoding):
    path = write_driver_bag(str(tmp_path / "b.bag"), encoding=encoding, n=10)
    _check_frames(list(bagio.read_stereo_frames(path)), 10)


def test_frames_from_bag_camera_and_rectified(tmp_path):
    """The offline pipeline's camera from a bag whose infos follow the images; image_rect topics
    with the raw (distorted) camera_info are not rectified again (rectified auto/true/false)."""
    import genpy
    import rosbag
    from mdr_slam import conversions as cv
    from mdr_slam.pipeline import frames_from_bag
    path = write_driver_bag(str(tmp_path / "b.bag"), info="after", n=8)
    cam, frames = frames_from_bag(path)
    assert cam.baseline == pytest.approx(0.1) and len(list(frames)) == 8
    # a distorted calibration, images on image_rect topics (as stereo_image_proc publishes)
    dist = StereoCamera(*[bagio.CameraModel(m.width, m.height, m.K, [-0.2, 0.05, 0, 0, 0], m.R,
                                            m.P) for m in (CAM.left, CAM.right)])
    topics = {"left_image": "/cam/left/image_rect", "right_image": "/cam/right/image_rect"}
    rect = str(tmp_path / "rect.bag")
    with rosbag.Bag(rect, "w") as bag:
        for i in range(4):
            t = genpy.Time.from_sec(5.0 + 0.05 * i)
            for side, img, m in zip(("left", "right"), _frame_images(i), (dist.left, dist.right)):
                bag.write(topics[side + "_image"], cv.numpy_to_image(img, stamp=t), t)
                bag.write(bagio.DEFAULT_TOPICS[side + "_info"], cv.model_to_camera_info(m, t), t)
    cam, _ = frames_from_bag(rect, topics=topics)
    assert cam.is_rectified and cam.left.P[0, 0] == 30.0
    cam, _ = frames_from_bag(rect, topics=topics, rectified="false")
    assert not cam.is_rectified
    cam, _ = frames_from_bag(rect, topics=topics, rectified="true")
    assert cam.is_rectified
    with pytest.raises(ValueError, match="no stereo pair on /stereo/left/image_raw.*"
                                         "/cam/left/image_rect"):
        frames_from_bag(rect)
    with pytest.raises(ValueError, match="rectified"):
        frames_from_bag(rect, topics=topics, rectified="maybe")


def test_unreadable_images_are_skipped_with_a_reason(tmp_path):
    """A truncated jpeg drops its pair (both images reported); the other pairs come through."""
    import rosbag
    src = write_driver_bag(str(tmp_path / "a.bag"), transport="jpeg", n=6)
    path = str(tmp_path / "b.bag")
    left = bagio.DEFAULT_TOPICS["left_image"] + "/compressed"
    with rosbag.Bag(src) as a, rosbag.Bag(path, "w") as b:
        for topic, msg, t in a.read_messages():
            if topic == left and abs(msg.header.stamp.to_sec() - 1000.1) < 1e-6:
                msg.data = msg.data[: len(msg.data) // 2]
            b.write(topic, msg, t)
    skipped = []
    frames = list(bagio.read_stereo_frames(path, image_transport="compressed",
                                           on_skip=skipped.append))
    assert [round(f.stamp - 1000.0, 3) for f in frames] == [0.0, 0.05, 0.15, 0.2, 0.25]
    assert len(skipped) == 2, skipped
    assert "left image at 1000.100000000" in skipped[0] and "truncated" in skipped[0]
    assert "right image at 1000.100000000 dropped: its partner could not be read" == skipped[1]


def test_a_bag_recorded_from_a_looping_source_reads_lap_after_lap(tmp_path):
    """Stamps that jump back (a recorded ``rosbag play --loop`` of a 1.5 s bag) start a new
    timeline, as the live pairing resets: the laps are not interleaved by stamp."""
    import genpy
    import rosbag
    from mdr_slam import conversions as cv
    path = str(tmp_path / "loop.bag")
    with rosbag.Bag(path, "w") as bag:
        for lap in range(2):
            for i in range(30):
                stamp = genpy.Time.from_sec(1000.0 + 0.05 * i)
                t_rx = genpy.Time.from_sec(2000.0 + 5.0 * lap + 0.05 * i)
                for side, img in zip(("left", "right"), _frame_images(i + 30 * lap)):
                    bag.write(bagio.DEFAULT_TOPICS[side + "_image"],
                              cv.numpy_to_image(img, stamp=stamp), t_rx)
    frames = list(bagio.read_stereo_frames(path))
    assert [int(f.left[0, 0]) for f in frames] == [2 * i + 10 for i in range(60)]
    assert [int(f.right[0, 0]) for f in frames] == [2 * i + 11 for i in range(60)]
    want = [1000.0 + 0.05 * (i % 30) for i in range(60)]
    assert [f.stamp for f in frames] == pytest.approx(want)
