"""A flood of oversized and malformed messages from a stray node: every node stays alive and its
memory stays flat (RSS within 50 MB of where it was after a warm-up of the same flood).

The pose node (ORB, camera_info input) and the depth node get images beyond 4096 px, images of
another size than their camera_info, and absurd camera_infos; the pose node relaying ground truth
and the fusion node (clouds paired with /mdr/pose) get PoseStamped with NaN and non-unit
quaternions and PointCloud2 with absurd sizes, field layouts and data lengths."""
from __future__ import annotations

import os

import numpy as np
import pytest

from conftest import wait_for

pytestmark = pytest.mark.ros

RSS_SLACK_MB = 50.0
WARMUP = 20      # messages of each kind before the baseline
FLOOD = 150      # messages of each kind measured


def _rss_mb(pid: int) -> float:
    """VmRSS of ``pid`` or, when it is a launcher (rosrun's shell), of its python child."""
    def rss(p):
        with open("/proc/%d/status" % p) as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return float(line.split()[1]) / 1024.0
        return 0.0
    try:
        with open("/proc/%d/task/%d/children" % (pid, pid)) as f:
            kids = [int(k) for k in f.read().split()]
    except OSError:
        kids = []
    return max([rss(pid)] + [rss(k) for k in kids])


def _messages(rospy, W=64, H=48):
    """One of each bad message kind: (topic key, message)."""
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
    from mdr_slam import conversions as cv
    now = rospy.Time.now()
    out = []
    huge = Image(width=5000, height=5000, encoding="mono8", step=5000, data=b"\0" * 5000)
    wide = cv.numpy_to_image(np.zeros((8, 4200), np.uint8))      # 4200 px wide, real data
    small = cv.numpy_to_image(np.zeros((H // 2, W // 2), np.uint8))   # not the camera_info's size
    for side in ("left", "right"):
        for m in (huge, wide, small):
            m.header.stamp = now
            out.append((side + "/image", m))
        out.append((side + "/info", CameraInfo(width=10 ** 6, height=H)))
        nan = CameraInfo(width=W, height=H)
        nan.K = [float("nan")] * 9
        out.append((side + "/info", nan))
    good = cv.arrays_to_pointcloud2({}, now, "cam", xyz=np.zeros((10, 3), np.float32))
    for change in ({"width": 1 << 30, "height": 1 << 10}, {"point_step": 0},
                   {"fields": [PointField(name="x", offset=0, datatype=7, count=1 << 28)]},
                   {"fields": [PointField(name="x", offset=9000, datatype=99, count=1)]},
                   {"data": b"\0" * 3}, {"row_step": 1}):
        m = cv.arrays_to_pointcloud2({}, now, "cam", xyz=np.zeros((10, 3), np.float32))
        for k, v in change.items():
            setattr(m, k, v)
        out.append(("cloud", m))
    for q in ((0, 0, 0, float("nan")), (0, 0, 0, 7.0), (0, 0, 0, 0)):
        p = PoseStamped()
        p.header.stamp, p.header.frame_id = now, "map"
        p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z, p.pose.orientation.w = q
        out.append(("pose", p))
    p = PoseStamped()
    p.header.stamp, p.header.frame_id = now, "map"
    p.pose.position.x, p.pose.orientation.w = float("inf"), 1.0
    out.append(("pose", p))
    out.append(("cloud", good))   # a good cloud with no pose at its stamp
    return out


def test_flood_of_malformed_messages_leaves_nodes_alive_and_flat(rospy_client, start_process,
                                                                 tmp_path):
    rospy = rospy_client
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2
    from mdr_slam import conversions as cv
    from mdr_slam.camera import CameraModel
    pre = "/fz"
    stereo = ["left/image:=%s/left/image" % pre, "right/image:=%s/right/image" % pre,
              "left/camera_info:=%s/left/info" % pre, "right/camera_info:=%s/right/info" % pre]
    common = ["_map_dir:=%s" % (tmp_path / "maps"), "_autosave:=false", "_resume:=false"]
    nodes = {
        "pose_orb": start_process(["rosrun", "mdr_slam", "pose_node", "__name:=fz_pose_orb",
                                   "_source:=orb", "_threads:=false", "/mdr/pose:=%s/orb_out" % pre]
                                  + common + stereo, "fz_pose_orb"),
        "pose_gt": start_process(["rosrun", "mdr_slam", "pose_node", "__name:=fz_pose_gt",
                                  "_source:=groundtruth", "ground_truth_pose:=%s/pose" % pre,
                                  "/mdr/pose:=%s/gt_out" % pre, "/mdr/odom:=%s/odom" % pre,
                                  "/mdr/path:=%s/path" % pre], "fz_pose_gt"),
        "depth": start_process(["rosrun", "mdr_slam", "depth_node", "__name:=fz_depth",
                                "/mdr/depth/points:=%s/depth_out" % pre] + stereo, "fz_depth"),
        "fusion": start_process(["rosrun", "mdr_slam", "fusion_node", "__name:=fz_fusion",
                                 "_pose_source:=topic", "/mdr/depth/points:=%s/cloud" % pre,
                                 "/mdr/pose:=%s/pose" % pre, "/mdr/map/points:=%s/map" % pre,
                                 "/mdr/map/grid:=%s/grid" % pre] + common, "fz_fusion"),
    }
    pubs = {k: rospy.Publisher(pre + "/" + k, t, queue_size=200) for k, t in (
        ("left/image", Image), ("right/image", Image), ("left/info", CameraInfo),
        ("right/info", CameraInfo), ("cloud", PointCloud2), ("pose", PoseStamped))}
    for k, n in (("left/image", 2), ("right/image", 2), ("left/info", 2), ("right/info", 2),
                 ("cloud", 1), ("pose", 2)):
        assert wait_for(lambda: pubs[k].get_num_connections() >= n, 60), \
            (k, {name: p.output()[-2000:] for name, p in nodes.items()})
    # a valid camera_info pair first, so images are also checked against it
    model = CameraModel(64, 48, np.array([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]]))
    for side in ("left", "right"):
        pubs[side + "/info"].publish(cv.model_to_camera_info(model, rospy.Time.now(), "cam"))

    def flood(count):
        for i in range(count):
            for key, msg in _messages(rospy):
                msg.header.stamp = rospy.Time.now()
                pubs[key].publish(msg)
            rospy.sleep(0.01)

    flood(WARMUP)
    rospy.sleep(3.0)
    pids = {name: p.proc.pid for name, p in nodes.items()}
    start = {name: _rss_mb(pid) for name, pid in pids.items()}
    flood(FLOOD)
    rospy.sleep(5.0)   # let the queues drain
    end = {name: _rss_mb(pid) for name, pid in pids.items()}
    print("RSS MB before -> after the flood: %s" % {n: (round(start[n], 1), round(end[n], 1))
                                                    for n in start})
    for name, p in nodes.items():
        assert p.proc.poll() is None, (name, p.output()[-3000:])
        assert end[name] - start[name] < RSS_SLACK_MB, (name, start[name], end[name])
        out = p.output()
        assert "Traceback" not in out, (name, out[-3000:])
    # each kind was refused by name (the warnings are throttled, not silent)
    assert "image refused" in nodes["pose_orb"].output(), nodes["pose_orb"].output()[-3000:]
    assert "camera_info refused" in nodes["depth"].output(), nodes["depth"].output()[-3000:]
    assert "cloud refused" in nodes["fusion"].output(), nodes["fusion"].output()[-3000:]
    assert "ground-truth pose skipped" in nodes["pose_gt"].output(), nodes["pose_gt"].output()
