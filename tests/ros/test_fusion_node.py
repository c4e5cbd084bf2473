"""fusion_node against a private master: cloud + tf in, map points and grid out, map services,
autosave on SIGINT, reload at start, bad input skipped, keyframe corrections."""
from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from conftest import wait_for
from mdr_slam_msgs.srv import SaveMap
from mdr_slam import conversions as cv
from mdr_slam.geometry import make_T
from scipy.spatial.transform import Rotation

pytestmark = pytest.mark.ros


def _wall(n=8000, depth=2.0, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, (n, 2))
    return np.column_stack([u, np.full(n, depth)]).astype(np.float32)


def _node(start_process, tmp_path, name, extra=()):
    cmd = ["rosrun", "mdr_slam", "fusion_node", "__name:=" + name,
           "_map_path:=%s" % (tmp_path / "auto.ply"), "_map_dir:=%s" % tmp_path,
           "_publish_rate:=4.0", "_display_voxel:=0.0",
           "_display_min_confidence:=0", "_grid_min_confidence:=1", "_grid_z_min:=-1.0",
           "_grid_z_max:=1.0", "_voxel_size:=0.05", "_autosave_period:=0.0", "_tf_timeout:=0.3",
           "/mdr/depth/points:=/%s/cloud" % name, "/mdr/map/points:=/%s/map" % name,
           "/mdr/map/grid:=/%s/grid" % name, "/mdr/keyframes:=/%s/kf" % name] + list(extra)
    return start_process(cmd, name)


def test_fusion_node_end_to_end(rospy_client, start_process, tmp_path):
    rospy = rospy_client
    import tf2_ros
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import PointCloud2
    from mdr_slam_msgs.msg import KeyFrame, KeyFrameArray
    from mdr_slam_msgs.srv import ExportMesh, LoadMap, SaveMap
    from std_srvs.srv import Trigger
    name = "fusion_a"
    node = _node(start_process, tmp_path, name)
    maps, grids, diags = [], [], []
    from diagnostic_msgs.msg import DiagnosticArray
    rospy.Subscriber("/diagnostics", DiagnosticArray, diags.append)
    rospy.Subscriber("/%s/map" % name, PointCloud2, maps.append)
    rospy.Subscriber("/%s/grid" % name, OccupancyGrid, grids.append)
    pub = rospy.Publisher("/%s/cloud" % name, PointCloud2, queue_size=10)
    pub_kf = rospy.Publisher("/%s/kf" % name, KeyFrameArray, queue_size=10, latch=True)
    # map <- cam: camera 1 m up along map y... any rigid pose; the test checks the transform
    T = make_T(Rotation.from_euler("x", -90, degrees=True).as_matrix(), [1.0, 2.0, 0.5])
    static = tf2_ros.StaticTransformBroadcaster()
    static.sendTransform(cv.matrix_to_transform_stamped(T, rospy.Time(0), "map", "cam_test"))
    assert wait_for(lambda: pub.get_num_connections() > 0, 30), node.output()
    rospy.wait_for_service("/%s/save_map" % name, 30)
    base = rospy.Time.now()
    P = _wall()
    # keyframe 5 at the first cloud: the map anchors its points to it
    kfa = KeyFrameArray(reason=KeyFrameArray.NEW_KEYFRAME, correction_id=0,
                        keyframes=[KeyFrame(id=5, stamp=base, pose=cv.matrix_to_pose(T))])
    kfa.header.frame_id = "map"
    pub_kf.publish(kfa)
    rospy.sleep(0.5)
    for i in range(3):
        msg = cv.arrays_to_pointcloud2({"intensity": np.full(len(P), 100.0 + i, np.float32)},
                                       base + rospy.Duration(0.1 * i), "cam_test", xyz=P)
        pub.publish(msg)
        rospy.sleep(0.3)
    # bad input: empty cloud, NaN cloud, absurd depths, unknown frame, time going backwards
    # (spaced: the node's subscriber queue is short and drops what it cannot process)
    for xyz, dt, frame in ((np.zeros((0, 3), np.float32), 0.5, "cam_test"),
                           (np.full((100, 3), np.nan, np.float32), 0.6, "cam_test"),
                           (np.full((100, 3), 1e7, np.float32), 0.7, "cam_test"),
                           (P, 0.8, "nowhere"), (P, -5.0, "cam_test")):
        pub.publish(cv.arrays_to_pointcloud2({}, base + rospy.Duration(dt), frame, xyz=xyz))
        rospy.sleep(0.4)
    rospy.sleep(0.5)
    assert node.proc.poll() is None, node.output()

    def full_map():
        return maps and maps[-1].width > 0 and maps[-1]
    m = wait_for(full_map, 15)
    assert m, node.output()
    m = maps[-1]
    assert m.header.frame_id == "map"
    arr = cv.pointcloud2_to_arrays(m)
    assert {"x", "y", "z", "intensity", "confidence"} <= set(arr)
    xyz = np.stack([arr["x"], arr["y"], arr["z"]], 1)
    # camera z (2 m ahead) is map +y after the -90 deg roll: the wall is at y = 2 + 2
    np.testing.assert_allclose(np.median(xyz[:, 1]), 4.0, atol=0.01)
    assert np.median(arr["confidence"]) == 3 and 99 < np.median(arr["intensity"]) < 103
    n_map = len(xyz)
    g = wait_for(lambda: grids and grids[-1], 10)
    assert g and g.header.frame_id == "map" and g.info.resolution == pytest.approx(0.05)
    data = np.array(g.data, np.int8).reshape(g.info.height, g.info.width)
    assert (data == 100).sum() > 10
    # the known cells cover the wall's footprint (x in [0, 2], y about 4); unknown cells pad the
    # grid to whole grid_extent_step squares (5 m) around them and the camera
    ox, oy = g.info.origin.position.x, g.info.origin.position.y
    rows, cols = np.nonzero(data >= 0)
    assert ox + cols.min() * 0.05 == pytest.approx(0.0, abs=0.06)
    assert ox + (cols.max() + 1) * 0.05 == pytest.approx(2.0, abs=0.06)
    assert oy + rows.min() * 0.05 <= 4.0 <= oy + (rows.max() + 1) * 0.05
    assert np.allclose(np.array([ox, oy, g.info.width * 0.05, g.info.height * 0.05]) / 5.0,
                       np.round(np.array([ox, oy, g.info.width * 0.05, g.info.height * 0.05]) / 5.0))

    def fusion_diag():
        for d in diags[::-1]:
            for status in d.status:
                kv = {v.key: v.value for v in status.values}
                if name in status.name and int(kv.get("clouds integrated", 0)) == 3:
                    return kv
    kv = wait_for(fusion_diag, 10)
    assert kv and int(kv["map points"]) >= n_map and float(kv["process RSS (MB)"]) > 10, diags[-1:]
    assert float(kv["integration rate (Hz)"]) > 0

    save = rospy.ServiceProxy("/%s/save_map" % name, SaveMap)
    r = save(str(tmp_path / "saved.pcd"), "")
    assert r.success and r.n_points == n_map and os.path.exists(r.path), r.message
    r = save(str(tmp_path / "saved2"), "ply")
    assert r.success and r.path.endswith("saved2.ply") and os.path.exists(r.path)
    assert not save("", "xyz").success

    # a loop-closure correction of keyframe 5 moves the map by 0.5 m along map x
    T_new = make_T(T[:3, :3], T[:3, 3] + [0.5, 0, 0])
    kfa = KeyFrameArray(reason=KeyFrameArray.LOOP_CLOSURE, correction_id=1,
                        keyframes=[KeyFrame(id=5, stamp=base, pose=cv.matrix_to_pose(T_new))])
    kfa.header.frame_id = "map"
    pub_kf.publish(kfa)

    def moved():
        a = cv.pointcloud2_to_arrays(maps[-1])
        return abs(np.median(a["x"]) - (np.median(xyz[:, 0]) + 0.5)) < 0.01
    assert wait_for(moved, 10), node.output()

    mesh = rospy.ServiceProxy("/%s/export_mesh" % name, ExportMesh)
    # a caller's path resolves inside map_dir (tmp_path); escaping ones are refused, unwritten
    for bad in ("../mesh_out.ply", "/tmp/mdr_test_mesh_%d.ply" % os.getpid(), "a/../../x.ply"):
        r = mesh(bad, 0.05)
        assert not r.success and "outside the map directory" in r.message, (bad, r)
    assert not (tmp_path.parent / "mesh_out.ply").exists()
    assert not os.path.exists("/tmp/mdr_test_mesh_%d.ply" % os.getpid())
    r = mesh(str(tmp_path / "mesh.ply"), 0.05)
    assert r.success and r.n_triangles > 100 and os.path.exists(r.path), r.message

    # SIGINT: autosave to map_path, the same points
    node.stop()
    auto = tmp_path / "auto.ply"
    assert auto.exists(), node.output()
    from mdr_slam.io import read_cloud
    assert len(read_cloud(str(auto))["x"]) == n_map
    out = node.output()
    assert "Traceback" not in out and "Open3D WARNING" not in out, out
    for what in ("empty cloud", "no valid points", "no pose for the cloud", "older than"):
        assert what in out, (what, out)  # each bad input was reported (throttled) and skipped

    # restart from the saved map: the same point count, and load/reset services work
    node2 = _node(start_process, tmp_path, "fusion_b", ["_load_map:=%s" % auto,
                                                         "_map_path:=%s" % (tmp_path / "b.ply"),
                                                         "_autosave_period:=0.5"])
    rospy.wait_for_service("/fusion_b/save_map", 30)
    assert wait_for(lambda: (tmp_path / "b.ply").exists(), 10), node2.output()  # periodic autosave
    r = rospy.ServiceProxy("/fusion_b/save_map", SaveMap)("", "")
    assert r.success and r.n_points == n_map and r.path == str(tmp_path / "b.ply"), node2.output()
    assert rospy.ServiceProxy("/fusion_b/reset", Trigger)().success
    assert rospy.ServiceProxy("/fusion_b/save_map", SaveMap)("", "").n_points == 0
    r = rospy.ServiceProxy("/fusion_b/load_map", LoadMap)(str(tmp_path / "saved.pcd"), False)
    assert r.success and r.n_points == n_map
    assert not rospy.ServiceProxy("/fusion_b/load_map", LoadMap)("/nonexistent.ply", False).success
    assert node2.proc.poll() is None, node2.output()


def test_fusion_node_pose_topic_sync(rospy_client, start_process, tmp_path):
    """pose_source=topic pairs each cloud with /mdr/pose by ApproximateTime."""
    rospy = rospy_client
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import PointCloud2
    name = "fusion_c"
    node = _node(start_process, tmp_path, name, ["_pose_source:=topic", "_sync_tolerance:=0.02",
                                                   "/mdr/pose:=/%s/pose" % name])
    maps = []
    rospy.Subscriber("/%s/map" % name, PointCloud2, maps.append)
    pub = rospy.Publisher("/%s/cloud" % name, PointCloud2, queue_size=10)
    pub_pose = rospy.Publisher("/%s/pose" % name, PoseStamped, queue_size=10)
    assert wait_for(lambda: pub.get_num_connections() > 0 and pub_pose.get_num_connections() > 0,
                    30), node.output()
    base = rospy.Time.now()
    P = _wall(seed=1)
    for i in range(3):
        T = make_T(np.eye(3), [0.0, 0.0, 0.01 * i])  # pose at the cloud's stamp
        st = base + rospy.Duration(0.2 * i)
        wrong = make_T(np.eye(3), [0.0, 0.0, 1.0])  # a pose 0.1 s off: outside the slop
        pub_pose.publish(cv.matrix_to_pose_stamped(wrong, st - rospy.Duration(0.1), "map"))
        pub_pose.publish(cv.matrix_to_pose_stamped(T, st, "map"))
        pub.publish(cv.arrays_to_pointcloud2({}, st, "cam", xyz=P - [0, 0, 0.01 * i]))
        rospy.sleep(0.2)
    pub_pose.publish(cv.matrix_to_pose_stamped(np.eye(4), base + rospy.Duration(5.0), "map"))
    m = wait_for(lambda: maps and maps[-1].width > 0 and maps[-1], 15)
    assert m, node.output()
    a = cv.pointcloud2_to_arrays(maps[-1])
    np.testing.assert_allclose(np.median(a["z"]), 2.0, atol=0.005)
    assert node.proc.poll() is None


def test_reset_keeps_the_map_and_last_holds_one_session(rospy_client, start_process, tmp_path):
    """A stray ~reset, then a normal shutdown: the map of before the reset is kept (last.1, with
    the sparse map of its session), ``last`` holds the new session's map alone, and the kept map
    loads again after a restart. A folder whose parts are of two sessions is refused."""
    rospy = rospy_client
    import tf2_ros
    from sensor_msgs.msg import PointCloud2
    from mdr_slam_msgs.srv import LoadMap
    from std_srvs.srv import Trigger
    from mdr_slam.io.map_dir import check_folder_sessions, folder_sessions
    maps = tmp_path / "maps"
    last = maps / "last"
    os.makedirs(str(last))
    # the pose node's autosave of the same session (its sparse map: only the session id matters)
    np.savez(str(last / "pose_map.npz"), session_id=np.array("S"))
    name = "fusion_rs"
    args = ["_map_path:=last", "_map_dir:=%s" % maps, "_session_id:=S", "_pose_node:="]
    node = _node(start_process, tmp_path, name, args)
    pub = rospy.Publisher("/%s/cloud" % name, PointCloud2, queue_size=10)
    T = make_T(np.eye(3), [0.0, 0.0, 0.0])
    static = tf2_ros.StaticTransformBroadcaster()
    static.sendTransform(cv.matrix_to_transform_stamped(T, rospy.Time(0), "map", "cam_rs"))
    assert wait_for(lambda: pub.get_num_connections() > 0, 30), node.output()
    rospy.wait_for_service("/%s/reset" % name, 30)
    base = rospy.Time.now()
    big, small = _wall(8000, 2.0, 3), _wall(500, 3.0, 4)
    pub.publish(cv.arrays_to_pointcloud2({}, base, "cam_rs", xyz=big))
    save_map = rospy.ServiceProxy("/%s/save_map" % name, SaveMap)
    n_big = wait_for(lambda: save_map("probe", "").n_points, 15)
    assert n_big > 1000, node.output()
    r = rospy.ServiceProxy("/%s/reset" % name, Trigger)()
    assert r.success and "kept in %s" % last in r.message, r
    assert folder_sessions(str(last)) == {"dense": "S", "pose": "S"}
    pub.publish(cv.arrays_to_pointcloud2({}, base + rospy.Duration(0.5), "cam_rs", xyz=small))
    assert wait_for(lambda: 0 < save_map("probe2", "").n_points < n_big, 15), node.output()
    node.stop()   # SIGINT: the autosave of the new session rotates last -> last.1
    assert folder_sessions(str(last)) == {"dense": "S~1"}, node.output()
    assert folder_sessions(str(maps / "last.1")) == {"dense": "S", "pose": "S"}
    assert check_folder_sessions(str(last))[0] and check_folder_sessions(str(maps / "last.1"))[0]
    # restart: the map of before the reset loads again
    node2 = _node(start_process, tmp_path, name + "2", args)
    rospy.wait_for_service("/%s2/load_map" % name, 30)
    load = rospy.ServiceProxy("/%s2/load_map" % name, LoadMap)
    r = load("last.1", False)
    assert r.success and r.n_points == n_big, r
    # a folder whose dense and sparse maps are of two sessions is refused with the reason
    mixed = maps / "mixed"
    shutil.copytree(str(maps / "last.1"), str(mixed))
    np.savez(str(mixed / "pose_map.npz"), session_id=np.array("other"))
    r = load("mixed", False)
    assert not r.success and "different sessions" in r.message and r.n_points == n_big, r
    assert node2.proc.poll() is None, node2.output()


def test_the_planners_goal_is_kept_inside_the_grid(rospy_client, start_process, tmp_path):
    """A move_base goal in space not mapped yet (move_base/current_goal) widens the grid's extent
    to hold it with grid_margin: the static layer's costmap then contains it and the goal is
    planned through unknown space instead of refused as off the costmap."""
    rospy = rospy_client
    from nav_msgs.msg import OccupancyGrid
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import PointCloud2
    name = "fusion_goal"
    node = _node(start_process, tmp_path, name, ["_pose_source:=topic", "_sync_tolerance:=0.02",
                                                   "/mdr/pose:=/%s/pose" % name,
                                                   "move_base/current_goal:=/%s/goal" % name])
    grids = []
    rospy.Subscriber("/%s/grid" % name, OccupancyGrid, grids.append)
    pub = rospy.Publisher("/%s/cloud" % name, PointCloud2, queue_size=10)
    pub_pose = rospy.Publisher("/%s/pose" % name, PoseStamped, queue_size=10)
    pub_goal = rospy.Publisher("/%s/goal" % name, PoseStamped, queue_size=1, latch=True)
    assert wait_for(lambda: pub.get_num_connections() > 0 and pub_pose.get_num_connections() > 0,
                    30), node.output()
    st = rospy.Time.now()
    pub_pose.publish(cv.matrix_to_pose_stamped(np.eye(4), st, "map"))
    pub.publish(cv.arrays_to_pointcloud2({}, st, "cam", xyz=_wall(seed=2)))
    assert wait_for(lambda: grids and grids[-1].info.width > 0, 15), node.output()

    def x_range(g):
        return g.info.origin.position.x, g.info.origin.position.x + g.info.width * g.info.resolution
    before = x_range(grids[-1])
    assert before[1] < 12.0, before
    pub_goal.publish(cv.matrix_to_pose_stamped(make_T(np.eye(3), [20.0, 0.0, 0.0]), st, "map"))
    assert wait_for(lambda: x_range(grids[-1])[1] >= 22.0 - 1e-6, 15), (before, x_range(grids[-1]))
    assert x_range(grids[-1])[0] == before[0]
    assert node.proc.poll() is None


def test_the_grid_is_free_under_the_base_and_follows_it(rospy_client, start_process, tmp_path):
    """The grid's cells within grid_footprint_radius of the base (tf map <- base_frame) are free,
    and when the base moves with no new cloud (tracking LOST) the grid is republished with the
    freed disc at its new place and the old place occupied again."""
    rospy = rospy_client
    import tf2_ros
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import PointCloud2
    name = "fusion_base"
    node = _node(start_process, tmp_path, name, ["_base_frame:=fp_base",
                                                   "_grid_footprint_radius:=0.3"])
    grids = []
    rospy.Subscriber("/%s/grid" % name, OccupancyGrid, grids.append)
    pub = rospy.Publisher("/%s/cloud" % name, PointCloud2, queue_size=10)
    static = tf2_ros.StaticTransformBroadcaster()

    def put_base(x):
        static.sendTransform(cv.matrix_to_transform_stamped(make_T(np.eye(3), [x, Y, 0.0]),
                                                            rospy.Time(0), "map", "fp_base"))
    # a wall along map x in the middle of the cells of y 1.0-1.05 (the cloud is in map: the
    # camera at its origin)
    Y = 1.025
    xs, zs = np.meshgrid(np.arange(0.0, 3.0, 0.02), np.arange(0.2, 0.8, 0.05))
    wall = np.column_stack([xs.ravel(), np.full(xs.size, Y), zs.ravel()]).astype(np.float32)
    put_base(1.0)
    assert wait_for(lambda: pub.get_num_connections() > 0, 30), node.output()
    pub.publish(cv.arrays_to_pointcloud2({}, rospy.Time.now(), "map", xyz=wall))

    def cell(g, x, y):
        data = np.array(g.data, np.int8).reshape(g.info.height, g.info.width)
        c = int(np.floor((x - g.info.origin.position.x) / g.info.resolution))
        r = int(np.floor((y - g.info.origin.position.y) / g.info.resolution))
        return int(data[r, c])

    def at(x_free, x_occupied):
        return grids and cell(grids[-1], x_free, Y) == 0 and cell(grids[-1], x_occupied, Y) == 100
    assert wait_for(lambda: at(1.0, 2.0), 15), node.output()
    assert cell(grids[-1], 1.0 + 0.25, Y) == 0 and cell(grids[-1], 1.0 + 0.4, Y) == 100
    n = len(grids)
    put_base(2.0)                                    # no cloud since: only the base moved
    assert wait_for(lambda: len(grids) > n and at(2.0, 1.0), 15), node.output()
    assert node.proc.poll() is None
