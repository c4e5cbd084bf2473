"""depth_node against a private master: synthetic stereo pairs + camera_info + pose in,
/mdr/depth/points out (frame, stamp, fields); bad input skipped without killing the node."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import wait_for
from mdr_slam import conversions as cv
from mdr_slam.camera import StereoCamera

pytestmark = pytest.mark.ros

W, H, D = 160, 120, 16      # f*B = 100*0.2 = 20 -> a wall at 1.25 m
FRAME = "camera_left_optical_frame"


def _pair(seed=0):
    import cv2
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur((rng.random((H, W + 2 * D + 8)) * 255).astype(np.uint8), (3, 3), 0)
    return np.ascontiguousarray(tex[:, 4:4 + W]), np.ascontiguousarray(tex[:, 4 + D:4 + D + W])


def _camera():
    return StereoCamera.from_rectified(W, H, 100.0, 100.0, 79.5, 59.5, 0.2, frame_id=FRAME)


class StereoPublisher:
    def __init__(self, rospy, prefix):
        from sensor_msgs.msg import CameraInfo, Image
        self.rospy = rospy
        self.pubs = {k: rospy.Publisher(prefix + k, t, queue_size=10) for k, t in (
            ("left/image", Image), ("right/image", Image), ("left/info", CameraInfo),
            ("right/info", CameraInfo))}
        self.cam = _camera()

    def connected(self):
        return all(p.get_num_connections() > 0 for p in self.pubs.values())

    def publish(self, stamp, left, right, left_enc=None):
        cam = self.cam
        self.pubs["left/info"].publish(cv.model_to_camera_info(cam.left, stamp, FRAME))
        self.pubs["right/info"].publish(cv.model_to_camera_info(cam.right, stamp, FRAME))
        lm = cv.numpy_to_image(left, stamp=stamp, frame_id=FRAME)
        if left_enc:
            lm.encoding = left_enc
        self.pubs["left/image"].publish(lm)
        self.pubs["right/image"].publish(cv.numpy_to_image(right, stamp=stamp, frame_id=FRAME))


def _node_cmd(name, prefix, *extra):
    return ["rosrun", "mdr_slam", "depth_node", "__name:=" + name,
            "left/image:=%sleft/image" % prefix, "right/image:=%sright/image" % prefix,
            "left/camera_info:=%sleft/info" % prefix, "right/camera_info:=%sright/info" % prefix,
            "_tau:=0.05", "_stride:=1", "_elas/disp_max:=64",
            "_max_rate:=0"] + list(extra)   # every pair (a test asks for max_rate itself)


def _fields(msg):
    return [f.name for f in msg.fields]


def _pose_topic_rig(rospy, start_process, name, prefix, *extra, points="/mdr/depth/points",
                    others=()):
    """A depth_node taking its poses from PREFIXpose, a subscriber collecting its clouds, the pose
    and stereo publishers, all connected (and the publishers/subscribers in ``others``).
    Returns (node, clouds, cloud subscriber, pose publisher, StereoPublisher)."""
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import PointCloud2
    node = start_process(_node_cmd(name, prefix, "_use_tf:=false",
                                   "_pose_source_topic:=%spose" % prefix, *extra), name)
    got = []
    sub = rospy.Subscriber(points, PointCloud2, got.append)
    pose_pub = rospy.Publisher(prefix + "pose", PoseStamped, queue_size=50)
    sp = StereoPublisher(rospy, prefix)
    assert wait_for(lambda: sp.connected() and pose_pub.get_num_connections() > 0 and
                    sub.get_num_connections() > 0 and
                    all(o.get_num_connections() > 0 for o in others), 30), node.output()
    return node, got, sub, pose_pub, sp


def test_depth_node_publishes_points_from_pose_topic_and_survives_bad_input(rospy_client,
                                                                           start_process):
    rospy = rospy_client
    from sensor_msgs.msg import Image
    imgs = []
    sub_img = rospy.Subscriber("/mdr/depth/image", Image, imgs.append)
    node, got, sub, pose_pub, sp = _pose_topic_rig(rospy, start_process, "depth_test1", "/dn1/",
                                                   "_publish_depth_image:=true", others=[sub_img])
    left, right = _pair()
    base = rospy.Time.now()
    stamps = []
    for i in range(8):
        st = base + rospy.Duration(0.1 * i)
        stamps.append(st)
        pose_pub.publish(cv.matrix_to_pose_stamped(np.eye(4), st, "map"))
        rospy.sleep(0.05)
        sp.publish(st, left, right)
        n = len(got)
        wait_for(lambda: len(got) > n, 10)
    assert len(got) >= 6, node.output()
    msg = got[-1]
    assert msg.header.frame_id == FRAME
    assert msg.header.stamp in stamps
    assert _fields(msg) == ["x", "y", "z", "intensity", "variance", "n_obs"]
    a = cv.pointcloud2_to_arrays(msg)
    assert len(a["z"]) > 0.3 * W * H, node.output()
    np.testing.assert_allclose(np.median(a["z"]), 1.25, rtol=0.02)
    assert np.all(a["n_obs"] >= 3) and np.all(a["variance"] > 0)
    assert imgs and imgs[-1].encoding == "32FC1" and imgs[-1].header.stamp == msg.header.stamp

    # bad input: unsupported encoding, left/right size mismatch, a stamp with no pose
    n = len(got)
    st = base + rospy.Duration(2.0)
    pose_pub.publish(cv.matrix_to_pose_stamped(np.eye(4), st, "map"))
    rospy.sleep(0.05)
    sp.publish(st, left, right, left_enc="nv12")
    rospy.sleep(0.3)
    st = base + rospy.Duration(2.1)
    pose_pub.publish(cv.matrix_to_pose_stamped(np.eye(4), st, "map"))
    rospy.sleep(0.05)
    sp.publish(st, left, right[:100])
    rospy.sleep(0.3)
    sp.publish(base + rospy.Duration(5.0), left, right)    # no pose anywhere near
    rospy.sleep(0.6)
    assert len(got) == n, "bad input must be skipped"
    assert node.proc.poll() is None, "depth_node died:\n" + node.output()
    # and a good pair afterwards is processed again
    st = base + rospy.Duration(5.1)
    pose_pub.publish(cv.matrix_to_pose_stamped(np.eye(4), st, "map"))
    rospy.sleep(0.05)
    sp.publish(st, left, right)
    assert wait_for(lambda: len(got) > n, 10), node.output()
    assert got[-1].header.stamp == st
    out = node.output()
    # a right image of another size than its camera_info is refused on arrival
    assert "unsupported image encoding" in out and "sizes differ from the calibration" in out \
        and "no pose" in out, out
    sub.unregister()
    sub_img.unregister()


def test_depth_node_pose_from_tf_and_elas_only(rospy_client, start_process):
    rospy = rospy_client
    import tf2_ros
    from sensor_msgs.msg import PointCloud2
    prefix = "/dn2/"
    node = start_process(_node_cmd("depth_test2", prefix, "_temporal:=false"), "depth2")
    got = []
    sub = rospy.Subscriber("/mdr/depth/points", PointCloud2, got.append)
    sp = StereoPublisher(rospy, prefix)
    br = tf2_ros.TransformBroadcaster()
    # the node's tf listener must be connected too, or the first frame finds no pose (a race)
    assert wait_for(lambda: sp.connected() and sub.get_num_connections() > 0
                    and br.pub_tf.get_num_connections() > 0, 30), node.output()
    left, right = _pair(1)
    base = rospy.Time.now()
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 0.5]
    for i in range(3):
        st = base + rospy.Duration(0.1 * i)
        br.sendTransform(cv.matrix_to_transform_stamped(T, st, "map", FRAME))
        rospy.sleep(0.1)
        sp.publish(st, left, right)
        n = len(got)
        wait_for(lambda: len(got) > n, 10)
    assert len(got) == 3, node.output()
    a = cv.pointcloud2_to_arrays(got[-1])
    assert got[-1].header.frame_id == FRAME
    assert len(a["z"]) > 0.5 * W * H and np.all(a["n_obs"] == 1)
    np.testing.assert_allclose(np.median(a["z"]), 1.25, rtol=0.02)
    assert node.proc.poll() is None, node.output()
    sub.unregister()


def test_stamp_rate_limiter_keeps_max_rate_by_stamp_and_restarts_on_loop():
    from mdr_slam.nodes.common import StampRateLimiter
    ts = 1000.0 + 0.05 * np.arange(200)            # 10 s of a 20 Hz stream
    for rate, want in ((12.0, 120), (10.0, 100), (0.0, 200), (30.0, 200)):
        lim = StampRateLimiter(rate)
        kept = np.array([t for t in ts if not lim.skip(t)])
        assert len(kept) == want, (rate, len(kept))
        if 0 < rate < 20:                           # evenly spread: no gap over one period + 1 frame
            assert np.diff(kept).max() <= 1.0 / rate + 0.05 + 1e-9
    lim = StampRateLimiter(10.0)
    assert [lim.skip(t) for t in (5.0, 5.05, 5.1)] == [False, True, False]
    assert lim.skip(0.0) is False                   # the bag looped: time 0 is due at once
    assert lim.skip(0.05) is True


def test_depth_node_max_rate_and_a_pose_that_arrives_after_the_images(rospy_client, start_process):
    """The filter stage waits for each matched pair's pose (the pose node is still tracking it)
    while ELAS goes on; ``max_rate`` 10 on a 20 Hz stream keeps every second pair."""
    rospy = rospy_client
    node, got, sub, pose_pub, sp = _pose_topic_rig(rospy, start_process, "depth_test3", "/dn3/",
                                                   "_max_rate:=10", "_tf_timeout:=0.5")
    left, right = _pair()
    base = rospy.Time.now()
    stamps = [base + rospy.Duration(0.05 * i) for i in range(12)]
    for st in stamps:
        sp.publish(st, left, right)
        rospy.sleep(0.08)                            # ELAS of this pair runs meanwhile
        pose_pub.publish(cv.matrix_to_pose_stamped(np.eye(4), st, "map"))   # the pose comes late
        rospy.sleep(0.15)
    assert wait_for(lambda: len(got) >= 6, 10), node.output()
    rospy.sleep(0.5)
    assert [m.header.stamp for m in got] == stamps[::2], node.output()
    sub.unregister()


@pytest.mark.parametrize("lost_rate", [2.0, 0.0])
def test_depth_node_pauses_while_the_tracker_is_lost(rospy_client, start_process, lost_rate):
    """Pairs stamped while the pose node reports LOST get no pose: the filter pauses (nothing on
    /mdr/depth/points, the rest counted as paused_lost) and the first OK report resumes it.
    Meanwhile ``lost_cloud_rate`` pairs a second are matched and their single-frame points go to
    /mdr/depth/raw_points (obstacle sensing while the base drives on odometry), and an empty
    cloud there ends the LOST stretch, so that a costmap does not keep re-marking the last one.
    ``lost_cloud_rate: 0``: nothing is matched while LOST."""
    rospy = rospy_client
    from mdr_slam_msgs.msg import TrackingState
    from sensor_msgs.msg import PointCloud2
    ns = "/dn4%d/" % int(lost_rate)
    state_pub = rospy.Publisher(ns + "state", TrackingState, queue_size=10)
    raw = []
    raw_sub = rospy.Subscriber(ns + "raw", PointCloud2, raw.append)
    node, got, sub, pose_pub, sp = _pose_topic_rig(
        rospy, start_process, "depth_test4%d" % int(lost_rate), ns,
        "_tracking_state_topic:=%sstate" % ns, "_lost_cloud_rate:=%g" % lost_rate,
        "/mdr/depth/raw_points:=%sraw" % ns, others=[state_pub] + ([raw_sub] if lost_rate else []))
    left, right = _pair()
    base = rospy.Time.now()

    def frame(i, state):
        st = base + rospy.Duration(0.1 * i)
        msg = TrackingState(state=state)
        msg.header.stamp = st
        state_pub.publish(msg)
        pose_pub.publish(cv.matrix_to_pose_stamped(np.eye(4), st, "map"))  # tf could interpolate
        rospy.sleep(0.1)
        sp.publish(st, left, right)
        rospy.sleep(0.3)
        return st

    ok1 = frame(0, TrackingState.OK)
    assert wait_for(lambda: len(got) >= 1, 10), node.output()
    lost = [frame(i, TrackingState.LOST) for i in (1, 2, 3)]
    if lost_rate:   # 2 Hz of pairs 0.1 s apart: the first of the three
        assert wait_for(lambda: len(raw) >= 1, 10), node.output()
    ok2 = frame(4, TrackingState.OK)
    assert wait_for(lambda: len(got) >= 2, 10), node.output()
    if lost_rate:
        assert wait_for(lambda: len(raw) >= 2, 10), node.output()
    rospy.sleep(0.5)
    assert [m.header.stamp for m in got] == [ok1, ok2], node.output()
    if not lost_rate:
        assert raw == []
        return
    assert [m.header.stamp for m in raw] == [lost[0], ok2], node.output()
    assert raw[0].header.frame_id == FRAME and raw[1].header.frame_id == FRAME
    P = cv.pointcloud2_to_xyz(raw[0])
    assert len(P) > 1000 and np.median(P[:, 2]) == pytest.approx(1.25, abs=0.05)   # the wall
    assert raw[1].width * raw[1].height == 0
    sub.unregister()
    raw_sub.unregister()


_ARENA = r"""
import json, sys, threading
from mdr_slam.nodes.memdebug import set_mmap_threshold
from mdr_slam.nodes.health import rss_bytes
if int(sys.argv[1]) > 0:
    assert set_mmap_threshold(int(sys.argv[1]))
import numpy as np
def work():   # like the depth node's worker threads, each with its own glibc arena
    big = np.ones(20 << 17)     # a 20 MB buffer, mmapped; freeing it raises glibc's dynamic threshold
    del big
    for _ in range(3):          # a frame's working set: 30 arrays of 1.4 MB, freed after the frame
        arrs = [np.ones(180000) for _ in range(30)]
        del arrs
t = threading.Thread(target=work)
t.start()
t.join()
print(json.dumps({"rss_mb": rss_bytes() / 1e6}))
"""


def test_fixed_mmap_threshold_keeps_freed_frame_buffers_out_of_thread_arenas():
    """The depth node's RSS creep in long runs is freed memory kept resident in its threads' glibc
    arenas. With glibc's dynamic mmap threshold (raised by any large freed block) the 1.4 MB
    frame arrays a thread frees stay in its arena; ``set_mmap_threshold`` (the node's
    ``~malloc_mmap_threshold``) maps them, and returns them on free. Measured in fresh processes."""
    import json
    import subprocess
    import sys
    from mdr_slam.nodes.memdebug import mallinfo
    if not mallinfo():
        pytest.skip("not glibc >= 2.33")
    rss = {}
    for th in (0, 1 << 20):
        out = subprocess.run([sys.executable, "-c", _ARENA, str(th)], capture_output=True,
                             text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        rss[th] = json.loads(out.stdout.strip().splitlines()[-1])["rss_mb"]
    assert rss[1 << 20] < rss[0] - 25, rss     # measured: 37 against 82 MB


def test_depth_node_writes_memory_samples_with_memdebug(rospy_client, start_process, tmp_path,
                                                       monkeypatch):
    """``MDR_MEMDEBUG`` (the long-run debug aid) makes the node write memory samples: smaps by
    mapping kind, mallinfo2, Python object growth, tracemalloc growth; the node keeps publishing
    its diagnostics meanwhile (with ``~malloc_mmap_threshold`` set)."""
    import json
    rospy = rospy_client
    from diagnostic_msgs.msg import DiagnosticArray
    stats = []
    sub = rospy.Subscriber("/diagnostics", DiagnosticArray,
                           lambda m: stats.extend(s for s in m.status if "depth" in s.name))
    path = tmp_path / "mem.jsonl"
    for k, v in (("MDR_MEMDEBUG", str(path)), ("MDR_MEMDEBUG_PERIOD", "0.5"),
                 ("MDR_MEMDEBUG_TRACEMALLOC", "1")):
        monkeypatch.setenv(k, v)      # the node process inherits the environment
    node = start_process(_node_cmd("depth_test5", "/dn5/", "_malloc_mmap_threshold:=1048576"),
                         "depth_test5")
    assert wait_for(lambda: len(stats) >= 2, 30), node.output()
    assert wait_for(lambda: path.exists() and len(path.read_text().splitlines()) >= 2, 30), \
        node.output()
    recs = [json.loads(line) for line in path.read_text().splitlines()]
    assert "error" not in recs[-1], recs[-1]
    for k in ("rss_mb", "heap", "anon", "arenas", "malloc_free_mb", "gc_growth",
              "tracemalloc_growth"):
        assert k in recs[-1], (k, recs[-1])
    assert 0 < recs[-1]["heap"] + recs[-1]["anon"] < recs[-1]["rss_mb"] * 1.05
    assert "cannot set malloc_mmap_threshold" not in node.output()
    sub.unregister()
