"""pose_node with source:=orb: stereo images + camera_info in; pose, tracking state, keyframes,
tf and the save_trajectory service out; bad input is skipped, not fatal."""
from __future__ import annotations

import os

import numpy as np
import pytest

from conftest import wait_for

pytestmark = pytest.mark.ros


def _stereo_rig(rospy, prefix, cam, subs, node, queue_size=20, frame="cam"):
    """Publishers of a stereo pair and its camera_info under ``prefix`` (in ``frame``), once they
    and ``subs`` are connected; returns send(left, right, stamp)."""
    from mdr_slam import conversions as cv
    from sensor_msgs.msg import CameraInfo, Image
    pubs = {n: rospy.Publisher("%s/%s" % (prefix, n), t, queue_size=queue_size) for n, t in
            (("left/image", Image), ("right/image", Image), ("left/info", CameraInfo),
             ("right/info", CameraInfo))}
    assert wait_for(lambda: all(p.get_num_connections() > 0 for p in pubs.values()) and
                    all(s.get_num_connections() > 0 for s in subs), 30), node.output()
    li = cv.model_to_camera_info(cam.left, frame_id=frame)
    ri = cv.model_to_camera_info(cam.right, frame_id=frame)

    def send(left, right, stamp):
        for msg, name in ((li, "left/info"), (ri, "right/info")):
            msg.header.stamp = stamp
            pubs[name].publish(msg)
        pubs["left/image"].publish(cv.numpy_to_image(left, "mono8", stamp, frame))
        pubs["right/image"].publish(cv.numpy_to_image(right, "mono8", stamp, frame))
    return send


# a camera 1.2 m above base_link, looking ahead and pitched 10 deg down (x y z qx qy qz qw)
_MOUNT = "0.2 0 1.2 -0.5416 0.5416 -0.4545 0.4545"


def _orbit(n, arc):
    """The small rectified camera, ``n`` poses on an orbit of ``arc`` rad in a textured box
    room and their rendered stereo pairs."""
    from mdr_slam.camera import StereoCamera
    from mdr_slam.pose.synthetic import BoxRoom, orbit_trajectory
    cam = StereoCamera.from_rectified(480, 320, 300.0, 300.0, 240.0, 160.0, 0.12)
    room = BoxRoom((3.0, 1.5, 3.0), tex_size=768, seed=3)
    poses = orbit_trajectory(n, radius=1.0, arc=arc)
    return cam, poses, [room.render_stereo(T, cam) for T in poses]


def _orb_node(start_process, name, prefix, *args):
    """A serial ORB pose node ``name`` on the stereo topics under ``prefix``."""
    return start_process(["rosrun", "mdr_slam", "pose_node", "_source:=orb", "_threads:=false",
                          "_n_features:=1000", "__name:=" + name, *args,
                          "left/image:=%s/left/image" % prefix,
                          "right/image:=%s/right/image" % prefix,
                          "left/camera_info:=%s/left/info" % prefix,
                          "right/camera_info:=%s/right/info" % prefix], name)


@pytest.mark.parametrize("mount", ["", _MOUNT], ids=["camera_map", "base_map"])
def test_orb_node_tracks_synthetic_stream(rospy_client, start_process, tmp_path, mount):
    """With ``base_to_camera`` the ORB node's map is base_link where tracking starts (REP-105):
    every pose, keyframe pose, tf and the saved trajectory is T_base_cam @ (the tracker's pose in
    its first camera frame); without it (and no tf) base_link is a level camera looking along x,
    so map is still z-up: the camera's optical z is map's x, its y (down) map's -z."""
    rospy = rospy_client
    from mdr_slam.geometry import base_to_camera
    from mdr_slam import conversions as cv
    from mdr_slam.geometry import inv_T
    from mdr_slam_msgs.msg import KeyFrameArray, TrackingState
    from mdr_slam_msgs.srv import SaveTrajectory
    from geometry_msgs.msg import PoseStamped

    cam, poses, frames = _orbit(12, np.pi / 4)
    traj_path = str(tmp_path / "exit.txt")
    A = base_to_camera(mount)
    node = _orb_node(start_process, "orb_test", "/t", "_trajectory_path:=" + traj_path,
                     "_map_dir:=%s" % (tmp_path / "maps"),
                     *(["_base_to_camera:=" + mount] if mount else []))
    got, states, kfs = [], [], []
    subs = [rospy.Subscriber("/mdr/pose", PoseStamped, got.append),
            rospy.Subscriber("/mdr/tracking_state", TrackingState, states.append),
            rospy.Subscriber("/mdr/keyframes", KeyFrameArray, kfs.append)]
    rig = _stereo_rig(rospy, "/t", cam, subs, node)
    base = rospy.Time.now()

    def send(i, left, right, stamp):
        rig(left, right, stamp)

    for i, (l, r) in enumerate(frames):
        send(i, l, r, base + rospy.Duration(0.1 * (i + 1)))
        assert wait_for(lambda: len(states) >= i + 1, 20), node.output()
    # bad input: a wrongly sized pair is skipped with a warning, the node lives on
    send(99, np.zeros((100, 100), np.uint8), np.zeros((100, 100), np.uint8),
         base + rospy.Duration(5.0))
    rospy.sleep(0.5)
    assert node.proc.poll() is None, node.output()
    assert len(states) == len(frames)
    assert [s.state for s in states].count(TrackingState.OK) == len(frames)
    assert wait_for(lambda: len(got) == len(frames), 5)
    np.testing.assert_allclose(cv.pose_stamped_to_matrix(got[0]), A, atol=1e-6)   # map = base at start
    if not mount:   # z-up map, forward-looking base_link, and a warning saying what was assumed
        np.testing.assert_allclose(A[:3, :3] @ [0, 0, 1], [1, 0, 0], atol=1e-12)
        np.testing.assert_allclose(A[:3, :3] @ [0, 1, 0], [0, 0, -1], atol=1e-12)
        assert "assuming a level camera at base_link's origin looking along its x" in node.output()
    T_est = cv.pose_stamped_to_matrix(got[-1])
    T_true = A @ inv_T(poses[0]) @ poses[-1]
    assert np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) < 0.05
    assert np.degrees(np.arccos(np.clip((np.trace(T_est[:3, :3].T @ T_true[:3, :3]) - 1) / 2, -1, 1))) < 2.0
    # keyframe poses are in the same map: each equals /mdr/pose at its stamp
    got_t = np.array([m.header.stamp.to_sec() for m in got])
    kf_new = [k for a in kfs if a.reason == KeyFrameArray.NEW_KEYFRAME for k in a.keyframes]
    assert kf_new
    for k in kf_new:
        j = int(np.argmin(np.abs(got_t - k.stamp.to_sec())))
        assert abs(got_t[j] - k.stamp.to_sec()) < 1e-3
        np.testing.assert_allclose(cv.pose_to_matrix(k.pose), cv.pose_stamped_to_matrix(got[j]),
                                   atol=1e-5)
    assert kfs and kfs[0].reason == KeyFrameArray.NEW_KEYFRAME and kfs[0].keyframes[0].id == 0
    # trajectory service
    rospy.wait_for_service("/orb_test/save_trajectory", 10)
    save = rospy.ServiceProxy("/orb_test/save_trajectory", SaveTrajectory)
    # a caller's path resolves inside map_dir; escaping ones are refused and nothing is written
    (tmp_path / "victim.txt").write_text("keep")
    for bad in (str(tmp_path / "victim.txt"), "../victim.txt", "a/../../victim.txt",
                "/tmp/mdr_test_trajectory_%d.txt" % os.getpid()):
        resp = save(bad, "")
        assert not resp.success and "outside the map directory" in resp.message, (bad, resp)
    assert (tmp_path / "victim.txt").read_text() == "keep"
    assert not os.path.exists("/tmp/mdr_test_trajectory_%d.txt" % os.getpid())
    resp = save("traj.kitti", "")
    out = str(tmp_path / "maps" / "traj.kitti")
    assert resp.success and resp.n_poses == len(frames) and resp.path == out, resp.message
    assert np.loadtxt(out).shape == (len(frames), 12)
    np.testing.assert_allclose(np.loadtxt(out)[-1].reshape(3, 4), T_est[:3], atol=1e-3)   # in map too
    # trajectory on shutdown
    node.stop()
    assert os.path.exists(traj_path) and np.loadtxt(traj_path).shape == (len(frames), 8)


def test_frames_before_the_camera_mount_is_in_tf_are_tracked_and_published_in_base_map(
        rospy_client, start_process):
    """The robot's base -> camera transform reaches tf after the first images (robot_state_publisher
    starting): the node tracks meanwhile instead of waiting, and once the transform comes it
    publishes every held result, in the map that is base_link where tracking started."""
    rospy = rospy_client
    import tf2_ros
    from mdr_slam import conversions as cv
    from mdr_slam.geometry import inv_T, parse_transform
    from mdr_slam_msgs.msg import TrackingState
    from geometry_msgs.msg import PoseStamped

    cam, poses, frames = _orbit(10, np.pi / 6)
    A = parse_transform(_MOUNT)
    node = _orb_node(start_process, "orb_late_tf", "/l")
    got, states = [], []
    subs = [rospy.Subscriber("/mdr/pose", PoseStamped, got.append),
            rospy.Subscriber("/mdr/tracking_state", TrackingState, states.append)]
    # a frame of its own: the latched transform outlives this test in the shared client
    rig = _stereo_rig(rospy, "/l", cam, subs, node, queue_size=100, frame="cam_late")
    static = tf2_ros.StaticTransformBroadcaster()
    base = rospy.Time.now()
    for i, (l, r) in enumerate(frames):
        rig(l, r, base + rospy.Duration(0.1 * (i + 1)))
        if i == 3:   # 0.4 s after the first image: within the node's wait for it
            static.sendTransform(cv.matrix_to_transform_stamped(A, rospy.Time(0), "base_link",
                                                                "cam_late"))
        rospy.sleep(0.1)
    assert wait_for(lambda: len(states) >= len(frames), 20), (len(states), node.output()[-3000:])
    assert wait_for(lambda: len(got) >= len(frames), 5), len(got)
    assert [s.state for s in states].count(TrackingState.OK) == len(frames)
    assert "from tf" in node.output()
    np.testing.assert_allclose(cv.pose_stamped_to_matrix(got[0]), A, atol=1e-6)   # map = base
    T_true = A @ inv_T(poses[0]) @ poses[-1]
    assert np.linalg.norm(cv.pose_stamped_to_matrix(got[-1])[:3, 3] - T_true[:3, 3]) < 0.05
    assert [m.header.stamp for m in got] == sorted(m.header.stamp for m in got)
    static.pub_tf.unregister()


def test_latest_slot_keeps_the_newest_and_counts_drops():
    import threading
    import time
    from mdr_slam.nodes.pose_node import LatestSlot
    slot = LatestSlot()
    assert slot.get(timeout=0.01) is None
    assert [slot.put(i) for i in range(5)] == [False, True, True, True, True]
    assert slot.get(timeout=0.01) == 4 and slot.dropped == 4
    assert slot.get(timeout=0.01) is None          # taken: nothing stale is left behind
    got = []

    def consumer():                                 # a tracker slower than the stream
        while True:
            item = slot.get(timeout=1.0)
            if item is None:
                return
            got.append(item)
            time.sleep(0.03)

    th = threading.Thread(target=consumer)
    th.start()
    for i in range(30):
        slot.put(i)
        time.sleep(0.005)
    th.join(5.0)
    assert not th.is_alive()
    assert got[-1] == 29 and got == sorted(got)     # the newest is processed, in order
    assert len(got) + slot.dropped - 4 == 30 and slot.dropped > 4
    slot.close()
    t0 = time.monotonic()
    assert slot.get(timeout=5.0) is None and time.monotonic() - t0 < 1.0   # close wakes a reader
    two = LatestSlot(2)                             # max_pending 2: the two newest, oldest first
    assert [two.put(i) for i in range(4)] == [False, False, True, True] and two.dropped == 2
    assert [two.get(0.01), two.get(0.01), two.get(0.01)] == [2, 3, None]


def test_pose_node_stages_split_a_frame_into_making_tracking_and_the_tracking_cpu():
    """The diagnostics' stage medians: the Frame (ORB, stereo) apart from tracking, and the
    tracking thread's CPU beside its wall time (below it, the thread waited for the CPU or the
    GIL)."""
    from collections import deque
    from types import SimpleNamespace
    from mdr_slam.nodes.pose_node import STAGES, PoseRelay
    relay = SimpleNamespace(stages={k: deque() for k in STAGES},
                            tracking={"state": "", "time_ms": 0.0, "keyframes": 0,
                                      "loop_closures": 0, "lost": 0})
    relay.note_stage = lambda stage, ms: PoseRelay.note_stage(relay, stage, ms)
    res = SimpleNamespace(state="LOST", T_map_cam=None, time_ms=70.0, n_keyframes=3,
                          n_loop_closures=0, track_ms=70.0, frame_ms=40.0, track_cpu_ms=12.0,
                          lock_wait_ms=1.5, odom_refusal=None)
    PoseRelay.note_tracking(relay, res)
    got = {k: list(v) for k, v in relay.stages.items() if v}
    assert got == {"frame": [40.0], "tracking": [30.0], "tracking_cpu": [12.0],
                   "map_lock_wait": [1.5]}
    # a refused pose is logged with the check that refused it
    warned = []
    relay.warn = lambda key, text: warned.append(text)
    res.odom_refusal, res.stamp = (0.62, 4.0, 2.1, 66, "calibrated odometry"), 128.9
    PoseRelay.note_tracking(relay, res)
    assert len(warned) == 1 and "0.62 m / 4 deg" in warned[0] and "66 points" in warned[0] and \
        "refused at 128.900 (the calibrated odometry check)" in warned[0], warned


def test_lost_with_wheel_odometry_map_to_odom_follows_the_coasted_pose():
    """While tracking is LOST the robot's odometry carries base_link on; the pose node moves
    map -> odom so that map -> base_link is the pose the tracker coasted on its corrected
    odometry, not the last tracked pose plus the raw odometry's drift. Without wheel odometry
    (the node owns odom -> base_link) nothing is sent."""
    from types import SimpleNamespace
    import rospy
    from mdr_slam.geometry import make_T
    from mdr_slam.nodes.pose_node import PoseRelay
    from scipy.spatial.transform import Rotation
    sent = []
    T_base_cam = make_T(Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix(),
                        [0.1, 0.0, 0.5])
    T_odom_base = make_T(Rotation.from_euler("z", 20, degrees=True).as_matrix(), [3.0, 1.0, 0.0])
    relay = SimpleNamespace(wheel_odom=True, T_base_cam=T_base_cam, _last_map_odom=np.eye(4),
                            tf=SimpleNamespace(sendTransform=sent.extend),
                            p=SimpleNamespace(map_frame="map", odom_frame="odom"),
                            from_the_future=lambda t, what: False,
                            _odom_base_at=lambda stamp, warn=True: T_odom_base)
    T_map_base = make_T(Rotation.from_euler("z", 25, degrees=True).as_matrix(), [3.1, 1.3, 0.0])
    stamp = rospy.Time.from_sec(12.5)
    assert PoseRelay.coast(relay, stamp, T_map_base @ T_base_cam)
    assert len(sent) == 1 and sent[0].header.frame_id == "map" and \
        sent[0].child_frame_id == "odom" and sent[0].header.stamp == stamp
    np.testing.assert_allclose(relay._last_map_odom @ T_odom_base, T_map_base, atol=1e-9)
    relay.wheel_odom = False
    assert not PoseRelay.coast(relay, stamp, T_map_base @ T_base_cam) and len(sent) == 1


def test_orb_node_drops_stale_frames_when_busy(rospy_client, start_process):
    """A burst faster than tracking: the node tracks the newest pair, drops the ones that waited
    (counted in /diagnostics), and the frames after a gap are still tracked (motion model dt)."""
    rospy = rospy_client
    from diagnostic_msgs.msg import DiagnosticArray
    from mdr_slam_msgs.msg import TrackingState

    cam, poses, frames = _orbit(16, np.pi / 4)
    node = _orb_node(start_process, "orb_burst", "/b")
    states, diags = [], []
    subs = [rospy.Subscriber("/mdr/tracking_state", TrackingState, states.append),
            rospy.Subscriber("/diagnostics", DiagnosticArray, diags.append)]
    rig = _stereo_rig(rospy, "/b", cam, subs, node, queue_size=100)
    base = rospy.Time.now()
    stamps = [base + rospy.Duration(0.05 * (i + 1)) for i in range(len(frames))]

    def send(i):
        rig(frames[i][0], frames[i][1], stamps[i])

    send(0)                                         # initialise on the first frame
    assert wait_for(lambda: len(states) >= 1, 30), node.output()
    for i in range(1, len(frames)):                 # then 15 pairs within ~40 ms
        send(i)
        rospy.sleep(0.003)
    assert wait_for(lambda: states and states[-1].header.stamp == stamps[-1], 30), node.output()
    rospy.sleep(0.5)

    def dropped():
        for d in diags:
            for st in d.status:
                if st.name.endswith("pose"):
                    kv = {v.key: v.value for v in st.values}
                    if "frames_dropped_busy" in kv:
                        yield int(kv["frames_dropped_busy"])
    assert wait_for(lambda: max(dropped(), default=0) > 0, 5), [d.status for d in diags[-1:]]
    n_drop = max(dropped())
    kv = {v.key: v.value for d in diags for st in d.status if st.name.endswith("pose")
          for v in st.values}
    assert kv["frames_visual_odometry"] == "0"      # the map covered every view
    assert node.proc.poll() is None, node.output()
    assert 2 <= len(states) < len(frames)           # stale pairs were skipped, not queued
    assert len(states) + n_drop <= len(frames)
    assert [s.header.stamp for s in states] == sorted(s.header.stamp for s in states)
    assert all(s.state == TrackingState.OK for s in states), [s.state for s in states]


def _orbslam3_available():
    from mdr_slam.pose.orbslam3 import available
    return available()


@pytest.mark.parametrize("variant", ["orbslam3", "orbslam3_missing"])
def test_orb_node_with_the_orbslam3_backend_or_without_it(rospy_client, start_process, tmp_path,
                                                          variant):
    """``backend: orbslam3`` (launch arg pose_backend): ORB-SLAM3's C++ tracker behind the same
    topics. Where pyorbslam3 cannot be imported (stubbed here) the node says so and tracks with
    the built-in tracker: an optional backend never stops the robot."""
    if variant == "orbslam3" and not _orbslam3_available():
        pytest.skip("pyorbslam3 is not installed")
    rospy = rospy_client
    from mdr_slam import conversions as cv
    from mdr_slam.camera import StereoCamera
    from mdr_slam.geometry import T_BASE_OPTICAL, inv_T
    from mdr_slam.pose.synthetic import BoxRoom, orbit_trajectory
    from mdr_slam_msgs.msg import KeyFrameArray, TrackingState
    from geometry_msgs.msg import PoseStamped

    cam = StereoCamera.from_rectified(640, 480, 400.0, 400.0, 320.0, 240.0, 0.12)
    room = BoxRoom((3.0, 1.5, 3.0), tex_size=1024, seed=3)
    poses = orbit_trajectory(16, radius=1.0, arc=np.pi / 4)
    frames = [room.render_stereo(T, cam) for T in poses]
    env = []
    if variant == "orbslam3_missing":
        stub = tmp_path / "stub" / "pyorbslam3"
        stub.mkdir(parents=True)
        (stub / "__init__.py").write_text("raise ImportError('stubbed away by the test')\n")
        env = ["env", "PYTHONPATH=%s:%s" % (stub.parent, os.environ.get("PYTHONPATH", ""))]
    traj_path = str(tmp_path / "exit.txt")
    node = start_process(env + ["rosrun", "mdr_slam", "pose_node", "_source:=orb", "_threads:=false",
                                "_backend:=orbslam3", "_n_features:=1500", "__name:=o3_test",
                                "_trajectory_path:=" + traj_path,
                                "left/image:=/o3/left/image", "right/image:=/o3/right/image",
                                "left/camera_info:=/o3/left/info",
                                "right/camera_info:=/o3/right/info"], "o3")
    got, states, kfs = [], [], []
    subs = [rospy.Subscriber("/mdr/pose", PoseStamped, got.append),
            rospy.Subscriber("/mdr/tracking_state", TrackingState, states.append),
            rospy.Subscriber("/mdr/keyframes", KeyFrameArray, kfs.append)]
    send = _stereo_rig(rospy, "/o3", cam, subs, node)
    base = rospy.Time.now()
    for i, (l, r) in enumerate(frames):
        send(l, r, base + rospy.Duration(0.1 * (i + 1)))
        assert wait_for(lambda: len(states) >= i + 1, 30), node.output()
    assert node.proc.poll() is None, node.output()
    ok = [s.state for s in states].count(TrackingState.OK)
    assert ok >= len(frames) - 2 and wait_for(lambda: len(got) == ok, 5), node.output()
    T_est = cv.pose_stamped_to_matrix(got[-1])
    T_true = T_BASE_OPTICAL @ inv_T(poses[0]) @ poses[-1]   # no mount given: the default one
    assert np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) < 0.05, (T_est, T_true)
    log = node.output()
    if variant == "orbslam3_missing":
        assert "backend 'orbslam3' unavailable" in log and "stubbed away" in log
    else:
        assert "unavailable" not in log and "ORB-SLAM" in log
    # keyframe events from either tracker: ORB-SLAM3's are read back from it, each announced
    # once as NEW_KEYFRAME with the stamp of a frame that was sent
    sent = {round((base + rospy.Duration(0.1 * (i + 1))).to_sec(), 6) for i in range(len(frames))}
    new = [k for m in kfs if m.reason == KeyFrameArray.NEW_KEYFRAME for k in m.keyframes]
    assert len(new) >= 2 and len({k.id for k in new}) == len(new), kfs
    assert all(round(k.stamp.to_sec(), 6) in sent for k in new)
    node.stop()
    assert os.path.exists(traj_path) and len(np.loadtxt(traj_path)) == ok


def test_reset_keeps_the_sparse_map(rospy_client, start_process, tmp_path):
    """A stray ~reset: the map mapped before it is autosaved first (session S), the new map is
    the next session (S~1) and its shutdown autosave moves the old one to last.1, whole."""
    rospy = rospy_client
    from mdr_slam.io.map_dir import folder_sessions
    from mdr_slam_msgs.msg import TrackingState
    from std_srvs.srv import Trigger
    cam, poses, frames = _orbit(10, np.pi / 6)
    maps = tmp_path / "maps"
    node = _orb_node(start_process, "orb_reset", "/r", "_map_dir:=%s" % maps,
                     "_session_id:=S", "_autosave_period:=0")
    states = []
    subs = [rospy.Subscriber("/mdr/tracking_state", TrackingState, states.append)]
    rig = _stereo_rig(rospy, "/r", cam, subs, node, frame="cam_reset")
    base = rospy.Time.now()
    for i, (l, r) in enumerate(frames):
        rig(l, r, base + rospy.Duration(0.1 * (i + 1)))
        assert wait_for(lambda: len(states) >= i + 1, 20), node.output()
    rospy.wait_for_service("/orb_reset/reset", 10)
    res = rospy.ServiceProxy("/orb_reset/reset", Trigger)()
    assert res.success and "kept in %s" % (maps / "last") in res.message, res
    assert folder_sessions(str(maps / "last")) == {"pose": "S"}
    n = len(states)
    for i, (l, r) in enumerate(frames):   # a new map from the same frames, later stamps
        rig(l, r, base + rospy.Duration(5.0 + 0.1 * (i + 1)))
        assert wait_for(lambda: len(states) >= n + i + 1, 20), node.output()
    node.stop()
    assert folder_sessions(str(maps / "last")) == {"pose": "S~1"}, node.output()
    assert folder_sessions(str(maps / "last.1")) == {"pose": "S"}


def test_each_loop_closure_gets_one_log_line_with_its_checks(monkeypatch):
    """OrbNode._log_loops: one line per loop closed since the last call, with the map and
    odometry checks where they ran; a new map (shorter list) starts the count again."""
    import types
    from mdr_slam.nodes import pose_node
    lines = []
    monkeypatch.setattr(pose_node.rospy, "loginfo", lambda fmt, *a: lines.append(fmt % a))
    node = pose_node.OrbNode.__new__(pose_node.OrbNode)
    closed = [dict(kf=576, cand=366, stamp=313.8, moved_m=0.81, turned_deg=2.1, path_m=39.3,
                   map_check=(120, 131, 6.5), odometry_check=(0.42, 0.95, 38.0, 1.5, 3.25),
                   source="proximity", held_ms=2750.0, graph_ms=2400.0, graph_edges=19867),
              dict(kf=590, cand=223, stamp=321.4, moved_m=0.16, turned_deg=1.6, path_m=70.4,
                   map_check=None, odometry_check=None)]
    node.system = types.SimpleNamespace(loop_closing=types.SimpleNamespace(closed=closed[:1]))
    node.n_loops_logged = 0
    node._log_loops()
    node._log_loops()                                   # nothing new: nothing logged
    assert lines == ["pose_node: loop closed at 313.800 (proximity): keyframe 576 with keyframe "
                     "366, 39.3 m of keyframe path apart; the correction moved it 0.81 m and "
                     "turned it 2.1 deg; the loop keyframe's points matched 120 -> 131 times, "
                     "moved 6.5 px; 0.42 -> 0.95 m (1.5 -> 3.2 deg) off the wheel odometry over "
                     "38.0 m; tracking "
                     "waited 2.75 s for it (pose graph of 19867 edges: 2.40 s)"]
    node.system.loop_closing.closed = closed
    node._log_loops()
    assert len(lines) == 2 and "(bow): keyframe 590 with keyframe 223" in lines[1] and \
        lines[1].endswith("turned it 1.6 deg")
    node.system.loop_closing.closed = closed[1:]        # a new map's first loop
    node._log_loops()
    assert len(lines) == 3 and "keyframe 590" in lines[2]
    node.system = None                                  # between maps: nothing to tell
    node._log_loops()
    assert len(lines) == 3
