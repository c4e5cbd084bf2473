"""Bad input to each node: a clear throttled log line naming the problem, no
crash, the next valid message is processed, and no NaN or absurd point reaches the map.

Not repeated here (tests/ros/test_depth_node.py, tests/ros/test_fusion_node.py cover them): unsupported
encoding, left/right size mismatch and a stamp without pose for the depth node; empty, all-NaN,
1e7 m, unknown-frame and one backward cloud for the fusion node. The bag loop (time jumping back
with the clock) is in tests/ros/test_faults.py.
"""
from __future__ import annotations

import numpy as np
import pytest

from conftest import wait_for
from mdr_slam import conversions as cv
from mdr_slam.geometry import make_T

W, H = 160, 120


def test_image_to_mono8_refuses_depth_encodings_and_truncation():
    rng = np.random.default_rng(0)
    grey = rng.integers(0, 255, (H, W), dtype=np.uint8)
    rgb = np.repeat(grey[:, :, None], 3, axis=2)
    assert np.array_equal(cv.image_to_mono8(cv.numpy_to_image(rgb, "rgb8")), grey)
    m16 = cv.numpy_to_image(grey.astype(np.uint16) << 8, "mono16")
    assert np.array_equal(cv.image_to_mono8(m16), grey)
    for arr, enc in ((grey.astype(np.uint16), "16UC1"), (rng.random((H, W)).astype(np.float32),
                                                          "32FC1")):
        with pytest.raises(cv.ConversionError, match="not a camera intensity image"):
            cv.image_to_mono8(cv.numpy_to_image(arr, enc))
    msg = cv.numpy_to_image(grey)
    msg.data = msg.data[: len(msg.data) // 2]
    with pytest.raises(cv.ConversionError, match="truncated"):
        cv.image_to_mono8(msg)


# ------------------------------------------------------------------------------ ROS nodes
def _truncated(msg):
    msg.data = msg.data[: len(msg.data) // 2]
    return msg


def _zero_info(stamp, frame):
    from sensor_msgs.msg import CameraInfo
    m = CameraInfo(width=W, height=H, distortion_model="plumb_bob")
    m.header.stamp, m.header.frame_id = stamp, frame
    return m


@pytest.mark.ros
def test_depth_node_bad_images_info_and_stamps(rospy_client, start_process):
    rospy = rospy_client
    from test_depth_node import FRAME, _pair, _pose_topic_rig
    prefix = "/bi_d/"
    node, got, sub, pose_pub, sp = _pose_topic_rig(rospy, start_process, "depth_bad", prefix,
                                                   "/mdr/depth/points:=/bi_d/points",
                                                   points="/bi_d/points")
    left, right = _pair()
    base = rospy.Time.now()

    def st(i):
        return base + rospy.Duration(0.1 * i)

    def send(i, l_msg=None, r_msg=None, info=None, expect=True):
        stamp = st(i)
        pose_pub.publish(cv.matrix_to_pose_stamped(np.eye(4), stamp, "map"))
        rospy.sleep(0.05)
        lm = l_msg or cv.numpy_to_image(left, stamp=stamp, frame_id=FRAME)
        rm = r_msg or cv.numpy_to_image(right, stamp=stamp, frame_id=FRAME)
        lm.header.stamp = rm.header.stamp = stamp
        li = info or cv.model_to_camera_info(sp.cam.left, stamp, FRAME)
        sp.pubs["left/info"].publish(li)
        sp.pubs["right/info"].publish(cv.model_to_camera_info(sp.cam.right, stamp, FRAME))
        n = len(got)
        sp.pubs["left/image"].publish(lm)
        sp.pubs["right/image"].publish(rm)
        if expect:   # a valid pair: published (rarely the worker drops one; checked below)
            wait_for(lambda: len(got) > n, 15)
        else:
            rospy.sleep(0.5)
            assert len(got) == n, "bad input %d was published" % i

    for i in range(4):
        send(i)
    rgb = cv.numpy_to_image(np.repeat(left[:, :, None], 3, axis=2), "rgb8", frame_id=FRAME)
    send(4, l_msg=rgb)                                                  # converted: fine
    send(5, l_msg=_truncated(cv.numpy_to_image(left, frame_id=FRAME)), expect=False)
    send(6, l_msg=cv.numpy_to_image(left.astype(np.uint16) * 200, "16UC1", frame_id=FRAME),
         expect=False)
    send(7, r_msg=cv.numpy_to_image(np.random.default_rng(1).normal(0, 1e6, (H, W))
                                    .astype(np.float32), "32FC1", frame_id=FRAME), expect=False)
    send(8, info=_zero_info(st(8), FRAME), expect=False)
    send(4, expect=False)                                               # older than 8: stale
    send(9)
    send(9, expect=False)                                               # duplicate
    send(10)                                                            # still processing
    assert node.proc.poll() is None, node.output()
    published = [m.header.stamp for m in got]
    assert st(4) in published and st(10) in published, node.output()   # rgb8 and the last pair
    a = cv.pointcloud2_to_arrays(got[-1])
    assert len(a["z"]) > 0 and np.all(np.isfinite(a["z"]))
    out = node.output()
    for what in ("image data truncated", "'16UC1' is not a camera intensity image",
                 "'32FC1' is not a camera intensity image", "uncalibrated",
                 "older than the last one", "duplicate stamp"):
        assert what in out, (what, out)
    assert "Traceback" not in out and "filter reset" not in out, out
    sub.unregister()


def _fusion(start_process, tmp_path, name, extra=()):
    return start_process(["rosrun", "mdr_slam", "fusion_node", "__name:=" + name,
                          "_map_path:=%s" % (tmp_path / (name + ".ply")), "_autosave_period:=0.0",
                          "_map_dir:=%s" % tmp_path,
                          "_voxel_size:=0.05", "_tf_timeout:=0.3", "_clean_every:=0",
                          "_sync_tolerance:=0.02", "/mdr/depth/points:=/%s/cloud" % name,
                          "/mdr/pose:=/%s/pose" % name, "/mdr/map/points:=/%s/map" % name,
                          "/mdr/map/grid:=/%s/grid" % name, "/mdr/keyframes:=/%s/kf" % name,
                          "/mdr/tracking_state:=/%s/state" % name] + list(extra), name)


def _wall(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-1, 1, (n, 2)), np.full(n, 2.0)]).astype(np.float32)


def _map_xyz(rospy, name, path):
    from mdr_slam_msgs.srv import SaveMap
    from mdr_slam.io import read_cloud
    r = rospy.ServiceProxy("/%s/save_map" % name, SaveMap)(str(path), "")
    assert r.success, r.message
    c = read_cloud(r.path)
    return np.stack([c["x"], c["y"], c["z"]], 1)


@pytest.mark.ros
def test_fusion_node_bad_poses_clouds_and_stamps(rospy_client, start_process, tmp_path):
    rospy = rospy_client
    import tf2_ros
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import PointCloud2
    a, b = "fusion_bad_topic", "fusion_bad_tf"
    node_a = _fusion(start_process, tmp_path, a, ["_pose_source:=topic"])
    node_b = _fusion(start_process, tmp_path, b)
    pub_a = rospy.Publisher("/%s/cloud" % a, PointCloud2, queue_size=10)
    pose_a = rospy.Publisher("/%s/pose" % a, PoseStamped, queue_size=10)
    pub_b = rospy.Publisher("/%s/cloud" % b, PointCloud2, queue_size=10)
    br = tf2_ros.TransformBroadcaster()
    assert wait_for(lambda: pub_a.get_num_connections() and pose_a.get_num_connections() and
                    pub_b.get_num_connections(), 40), node_a.output() + node_b.output()
    rospy.wait_for_service("/%s/save_map" % a, 30)
    rospy.wait_for_service("/%s/save_map" % b, 30)
    P = _wall()
    base = rospy.Time.now()
    good = cv.matrix_to_pose(np.eye(4))

    def pose_msg(i, finite=True, value=np.nan):
        m = cv.matrix_to_pose_stamped(np.eye(4), base + rospy.Duration(0.1 * i), "map")
        if not finite:
            m.pose.position.x = value
        return m

    def cloud(i, xyz=P, frame="cam"):
        return cv.arrays_to_pointcloud2({}, base + rospy.Duration(0.1 * i), frame, xyz=xyz)

    def send_a(i, xyz=P, finite=True, value=np.nan, msg=None):
        pose_a.publish(pose_msg(i, finite, value))
        pub_a.publish(msg or cloud(i, xyz))
        rospy.sleep(0.35)

    mixed = P.copy()
    mixed[::3] = np.nan                                     # a third NaN, the rest valid
    far = P.copy()
    far[:, 2] = 1e6                                         # absurd depth
    neg = P.copy()
    neg[:, 2] = -2.0                                        # behind the camera
    inf = P.copy()
    inf[:10] = np.inf
    trunc = cloud(9)
    trunc.data = trunc.data[: len(trunc.data) // 2]
    noxyz = cv.arrays_to_pointcloud2({"intensity": np.ones(10, np.float32)}, base + rospy.Duration(1.0), "cam")
    send_a(0)
    send_a(1, finite=False)                                 # NaN pose
    send_a(2, finite=False, value=np.inf)                   # infinite pose
    send_a(3, xyz=mixed)
    send_a(4, xyz=far)
    send_a(5, xyz=neg)
    send_a(6, xyz=inf)
    send_a(6)                                               # duplicate stamp
    send_a(5)                                               # backward stamp (clock goes on)
    send_a(9, msg=trunc)
    send_a(10, msg=noxyz)
    send_a(11)                                              # valid again
    pose_a.publish(pose_msg(30))                            # lets the synchroniser flush 11
    rospy.sleep(0.5)

    # tf mode: NaN and infinite transforms never become a pose (tf2 refuses them)
    for i, kind in ((0, "good"), (1, "nan"), (2, "inf"), (10, "good")):
        st = base + rospy.Duration(0.1 * i)
        ts = cv.matrix_to_transform_stamped(np.eye(4), st, "map", "cam_b")
        if kind == "nan":
            ts.transform.rotation.w = np.nan
        elif kind == "inf":
            ts.transform.translation.y = np.inf
        elif i == 10:   # tf2 interpolates: good samples on both sides of the last cloud
            br.sendTransform(cv.matrix_to_transform_stamped(np.eye(4), st - rospy.Duration(0.05),
                                                            "map", "cam_b"))
        br.sendTransform(ts)
        rospy.sleep(0.05)
        pub_b.publish(cv.arrays_to_pointcloud2({}, st, "cam_b", xyz=P + [0, 0, 0.5 * (i == 10)]))
        rospy.sleep(0.4)

    for node, name in ((node_a, a), (node_b, b)):
        assert node.proc.poll() is None, node.output()
        xyz = _map_xyz(rospy, name, tmp_path / (name + "_out.ply"))
        assert len(xyz) > 100, node.output()
        assert np.all(np.isfinite(xyz)), "NaN/inf in the map of " + name
        assert np.abs(xyz).max() < 5.0, "absurd point in the map of %s: %s" % (name, np.abs(xyz).max())
    # topic node: clouds 0, 3 (its finite two thirds) and 11 were integrated: depth 2 m only
    xyz = _map_xyz(rospy, a, tmp_path / "a2.ply")
    assert np.allclose(xyz[:, 2], 2.0, atol=0.05)
    # tf node: clouds 0 and 10 integrated (walls at 2 and 2.5 m), the NaN/inf ones skipped
    zb = _map_xyz(rospy, b, tmp_path / "b2.ply")[:, 2]
    assert np.sum(np.abs(zb - 2.5) < 0.05) > 100 and np.sum(np.abs(zb - 2.0) < 0.05) > 100
    out_a, out_b = node_a.output(), node_b.output()
    for what in ("bad pose paired with the cloud: pose has non-finite values", "no valid points",
                 "equal to the last one", "older than the last one", "truncated",
                 "no x, y, z fields"):
        assert what in out_a, (what, out_a)
    assert "nan" in out_b.lower() and "no pose for the cloud" in out_b, out_b
    for out in (out_a, out_b):
        assert "Traceback" not in out, out


@pytest.mark.ros
def test_pose_node_groundtruth_bad_poses(rospy_client, start_process):
    rospy = rospy_client
    from geometry_msgs.msg import PoseStamped
    node = start_process(["rosrun", "mdr_slam", "pose_node", "__name:=pose_bad_gt", "_source:=groundtruth",
                          "ground_truth_pose:=/bi_gt/in", "/mdr/pose:=/bi_gt/pose",
                          "/mdr/odom:=/bi_gt/odom", "/mdr/path:=/bi_gt/path"], "pose_bad_gt")
    got = []
    sub = rospy.Subscriber("/bi_gt/pose", PoseStamped, got.append)
    pub = rospy.Publisher("/bi_gt/in", PoseStamped, queue_size=20)
    assert wait_for(lambda: pub.get_num_connections() and sub.get_num_connections(), 30), node.output()
    base = rospy.Time.now()

    def send(i, x=0.0, qw=1.0):
        m = cv.matrix_to_pose_stamped(make_T(np.eye(3), [0.1 * i, 0, 0]), base + rospy.Duration(0.1 * i))
        m.pose.position.y = x
        m.pose.orientation.w = qw
        pub.publish(m)
        rospy.sleep(0.15)

    send(0)
    send(1)
    send(2, x=np.nan)
    send(3, x=np.inf)
    send(4, qw=0.0)       # zero quaternion
    send(0)               # older than the last one (the clock goes on): stale
    send(5)
    send(5)               # duplicate
    send(6)
    assert wait_for(lambda: len(got) >= 4, 5), node.output()
    rospy.sleep(0.3)
    stamps = [round((m.header.stamp - base).to_sec(), 2) for m in got]
    assert stamps == [0.0, 0.1, 0.5, 0.6], stamps
    assert all(np.isfinite(cv.pose_stamped_to_matrix(m)).all() for m in got)
    assert node.proc.poll() is None
    out = node.output()
    for what in ("non-finite", "quaternion is zero", "duplicate pose stamp", "older than the last"):
        assert what in out, (what, out)
    assert "Traceback" not in out and "clearing the path" not in out, out
    sub.unregister()


@pytest.mark.ros
def test_pose_node_orb_bad_images_and_info(rospy_client, start_process):
    rospy = rospy_client
    from mdr_slam_msgs.msg import TrackingState
    from test_depth_node import FRAME, StereoPublisher, _pair
    prefix = "/bi_o/"
    node = start_process(["rosrun", "mdr_slam", "pose_node", "__name:=pose_bad_orb", "_source:=orb",
                          "_threads:=false", "left/image:=%sleft/image" % prefix,
                          "right/image:=%sright/image" % prefix,
                          "left/camera_info:=%sleft/info" % prefix,
                          "right/camera_info:=%sright/info" % prefix,
                          "/mdr/tracking_state:=/bi_o/state", "/mdr/pose:=/bi_o/pose",
                          "/mdr/odom:=/bi_o/odom", "/mdr/path:=/bi_o/path",
                          "/mdr/keyframes:=/bi_o/kf"], "pose_bad_orb")
    states = []
    sub = rospy.Subscriber("/bi_o/state", TrackingState, states.append)
    sp = StereoPublisher(rospy, prefix)
    assert wait_for(lambda: sp.connected() and sub.get_num_connections(), 30), node.output()
    left, right = _pair()
    base = rospy.Time.now()

    def send(i, l_msg=None, r_msg=None, info=None, expect=True):
        stamp = base + rospy.Duration(0.1 * i)
        lm = l_msg or cv.numpy_to_image(left, frame_id=FRAME)
        rm = r_msg or cv.numpy_to_image(right, frame_id=FRAME)
        lm.header.stamp = rm.header.stamp = stamp
        sp.pubs["left/info"].publish(info or cv.model_to_camera_info(sp.cam.left, stamp, FRAME))
        sp.pubs["right/info"].publish(cv.model_to_camera_info(sp.cam.right, stamp, FRAME))
        n = len(states)
        sp.pubs["left/image"].publish(lm)
        sp.pubs["right/image"].publish(rm)
        if expect:
            assert wait_for(lambda: len(states) > n, 20), node.output()
        else:
            rospy.sleep(0.6)
            assert len(states) == n, "bad input %d was tracked" % i

    send(0)
    send(1, l_msg=_truncated(cv.numpy_to_image(left, frame_id=FRAME)), expect=False)
    send(2, r_msg=cv.numpy_to_image(np.full((H, W), np.nan, np.float32), "32FC1", frame_id=FRAME),
         expect=False)
    send(3, l_msg=cv.numpy_to_image(left[:100], frame_id=FRAME), expect=False)   # size mismatch
    send(4, info=_zero_info(base + rospy.Duration(0.4), FRAME), expect=False)
    send(5)
    assert node.proc.poll() is None, node.output()
    out = node.output()
    for what in ("image data truncated", "'32FC1' is not a camera intensity image",
                 "differ from the calibration", "uncalibrated"):
        assert what in out, (what, out)
    assert "Traceback" not in out, out
    sub.unregister()


@pytest.mark.ros
def test_depth_node_skips_pairs_whose_pose_is_nan_infinite_or_a_zero_quaternion(rospy_client,
                                                                                start_process):
    """The depth node's own pose input (pose topic mode): a NaN, infinite or zero-quaternion pose is
    refused with a log line, its image pair gets no pose and is skipped (nothing published, no
    NaN cloud), and the next valid pose + pair is processed. (tf mode: tf2 itself refuses NaN
    transforms, see test_fusion_node_bad_poses_clouds_and_stamps.)"""
    rospy = rospy_client
    from test_depth_node import _pair, _pose_topic_rig
    node, got, sub, pose_pub, sp = _pose_topic_rig(rospy, start_process, "depth_bad_pose", "/bi_dp/",
                                                   "/mdr/depth/points:=/bi_dp/points",
                                                   points="/bi_dp/points")
    left, right = _pair()
    base = rospy.Time.now()

    def send(t, x=0.0, qw=1.0, expect=True):
        stamp = base + rospy.Duration(t)
        m = cv.matrix_to_pose_stamped(np.eye(4), stamp, "map")
        m.pose.position.x, m.pose.orientation.w = x, qw
        pose_pub.publish(m)
        rospy.sleep(0.05)
        n = len(got)
        sp.publish(stamp, left, right)
        if expect:   # a valid pair (rarely the worker drops one; the last one is checked below)
            wait_for(lambda: len(got) > n, 15)
        else:        # poses 2 s apart: nothing to interpolate the bad one's stamp from
            rospy.sleep(0.6)
            assert len(got) == n, "the pair of a bad pose at %.1f s was published" % t

    for i in range(4):
        send(0.1 * i)
    send(2.0, x=np.nan, expect=False)
    send(4.0, x=np.inf, expect=False)
    send(6.0, qw=0.0, expect=False)
    for i in range(4):   # after the gap the filter confirms points again over a few pairs
        send(8.0 + 0.1 * i)
    assert node.proc.poll() is None, node.output()
    published = [m.header.stamp for m in got]
    assert base + rospy.Duration(8.3) in published, node.output()
    for m in got:
        a = cv.pointcloud2_to_arrays(m)
        assert all(np.all(np.isfinite(a[k])) for k in "xyz")
    assert len(cv.pointcloud2_to_arrays(got[-1])["z"]) > 0.3 * W * H, node.output()
    out = node.output()
    for what in ("pose skipped: pose has non-finite values", "pose quaternion is zero", "no pose at"):
        assert what in out, (what, out)
    assert "Traceback" not in out, out
    sub.unregister()


def test_bad_input_logs_are_throttled_per_kind_and_wording(monkeypatch):
    """A flood of bad input gives one log line per kind and wording per period (the
    numbers in it aside), with the running count, and a different problem is still reported."""
    import time as _time
    import rospy
    from mdr_slam.nodes.common import Throttled
    lines = []
    monkeypatch.setattr(rospy, "logwarn", lambda fmt, *a: lines.append(fmt % a))
    warn = Throttled(period=0.2)
    for i in range(200):   # 20 Hz of truncated images for 10 s, as fast as it comes
        warn("img", "image skipped: data has %d bytes, expected 360960" % (1000 + i))
    assert len(lines) == 1 and lines[0].startswith("image skipped: data has 1000 bytes"), lines
    warn("img", "image skipped: encoding 'rgb8' is not mono8")   # same kind, another problem
    assert len(lines) == 2 and "encoding" in lines[1], lines
    _time.sleep(0.25)
    warn("img", "image skipped: data has 7 bytes, expected 360960")
    assert len(lines) == 3 and lines[2].endswith("(202 times so far)"), lines
    assert warn.counts["img"] == 202
