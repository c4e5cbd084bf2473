"""mdr_slam.sim.driver: simulated bags recorded the way ZED, RealSense and stereo_image_proc
drivers on a wheeled base record them (topics, encodings, frames, ordering, lag, tf_static,
wheel odometry, compressed images), with no ground truth in the bag."""
from __future__ import annotations

import os
import subprocess

import numpy as np
import pytest
import yaml

from mdr_slam import conversions as cv
from mdr_slam.geometry import inv_T, make_T
from mdr_slam.sim import build_trajectory, generate, generate_driver, make_scene, sim_camera
from mdr_slam.sim import driver as drv

ARGS = dict(scene="office", duration=1.0, seed=3, scale=0.25, workers=1, map_cell=0.05)
RATE = 20.0

EXPECT = {
    "zed": dict(images=("/zed/zed_node/left/image_rect_color",
                        "/zed/zed_node/right/image_rect_color"),
                infos=("/zed/zed_node/left/camera_info", "/zed/zed_node/right/camera_info"),
                frames=("zed_left_camera_optical_frame", "zed_right_camera_optical_frame"),
                encoding="bgr8", lag_ms=3.0,
                chain=["base_link", "zed_camera_center", "zed_left_camera_frame",
                       "zed_left_camera_optical_frame"]),
    "realsense": dict(images=("/camera/infra1/image_rect_raw", "/camera/infra2/image_rect_raw"),
                      infos=("/camera/infra1/camera_info", "/camera/infra2/camera_info"),
                      frames=("camera_infra1_optical_frame", "camera_infra2_optical_frame"),
                      encoding="mono8", lag_ms=0.0,
                      chain=["base_link", "camera_link", "camera_infra1_frame",
                             "camera_infra1_optical_frame"]),
    "stereo_image_proc": dict(images=("/stereo/left/image_rect", "/stereo/right/image_rect"),
                              infos=("/stereo/left/camera_info", "/stereo/right/camera_info"),
                              frames=("stereo_left_optical", "stereo_right_optical"),
                              encoding="mono8", lag_ms=0.0,
                              chain=["base_link", "stereo_left_optical"]),
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Driver bags of the same 1 s office sequence (188x120, 20 frames) and the default
    ground-truth bag as the rendered reference."""
    root = tmp_path_factory.mktemp("driver")
    out = {"reference": generate(str(root / "reference"), **ARGS)}
    for name in drv.DRIVERS:
        out[name] = generate_driver(str(root / name), name, **ARGS)
    out["zed_jpeg"] = generate_driver(str(root / "zed_jpeg"), "zed", compressed="jpeg", **ARGS)
    out["realsense_png"] = generate_driver(str(root / "realsense_png"), "realsense",
                                           compressed="png", **ARGS)
    return out


def _read(bag_path):
    """[(topic, msg, receive time s, connection header)] in bag (receive time) order."""
    import rosbag
    with rosbag.Bag(bag_path) as bag:
        return [(t, m, rt.to_sec()) for t, m, rt in bag.read_messages()]


def _types(bag_path):
    import rosbag
    with rosbag.Bag(bag_path) as bag:
        info = bag.get_type_and_topic_info()
        return {t: v.msg_type for t, v in info.topics.items()}


def _reference_frames(runs):
    """(left, right) rendered grey images per frame index."""
    from mdr_slam.bagio import read_stereo_frames
    return [(f.left, f.right) for f in read_stereo_frames(runs["reference"]["bag"])]


def _stamp(msg):
    return cv.stamp_to_sec(msg.header.stamp)


# ------------------------------------------------------------------------------ contents
@pytest.mark.parametrize("name", drv.DRIVERS)
def test_topics_types_frames_and_no_ground_truth(runs, name):
    e = EXPECT[name]
    types = _types(runs[name]["bag"])
    want = {e["images"][0]: "sensor_msgs/Image", e["images"][1]: "sensor_msgs/Image",
            e["infos"][0]: "sensor_msgs/CameraInfo", e["infos"][1]: "sensor_msgs/CameraInfo",
            "/tf_static": "tf2_msgs/TFMessage", "/tf": "tf2_msgs/TFMessage",
            "/odom": "nav_msgs/Odometry"}
    assert types == want
    msgs = _read(runs[name]["bag"])
    n_img = 0
    for topic, msg, _ in msgs:
        if topic in e["images"] + e["infos"]:
            side = 0 if topic in (e["images"][0], e["infos"][0]) else 1
            assert msg.header.frame_id == e["frames"][side]
        if topic in e["images"]:
            n_img += 1
            assert msg.encoding == e["encoding"]
            assert (msg.width, msg.height) == sim_camera(scale=0.25).size
        if topic == "/tf":   # only odometry: no map -> ground_truth_camera
            assert [(t.header.frame_id, t.child_frame_id) for t in msg.transforms] == \
                [("odom", "base_link")]
    assert n_img == 2 * runs[name]["n_frames"] == 40
    # the ground truth stays outside the bag
    d = runs[name]["out_dir"]
    for f in ("groundtruth.tum", "gt_map.ply", "scene.yaml", "driver.yaml"):
        assert os.path.exists(os.path.join(d, f)), f
    scene = yaml.safe_load(open(os.path.join(d, "scene.yaml")))
    assert scene["ground_truth"]["topic"] is None and scene["driver"]["name"] == name


@pytest.mark.parametrize("name", drv.DRIVERS)
def test_each_camera_info_follows_its_image_and_the_right_lags(runs, name):
    e = EXPECT[name]
    seq = [(t, m, rt) for t, m, rt in _read(runs[name]["bag"]) if t in e["images"] + e["infos"]]
    want = [e["images"][0], e["infos"][0], e["images"][1], e["infos"][1]]
    assert [t for t, _, _ in seq] == want * runs[name]["n_frames"]
    for k in range(0, len(seq), 4):
        (_, li, lrt), (_, lc, lcrt), (_, ri, rrt), (_, rc, rcrt) = seq[k:k + 4]
        assert li.header.stamp == lc.header.stamp and ri.header.stamp == rc.header.stamp
        # right = left + lag, to the nanosecond
        lag_ns = (ri.header.stamp - li.header.stamp).to_nsec()
        assert abs(lag_ns - e["lag_ms"] * 1e6) <= 1
        assert _stamp(li) == pytest.approx(1.0 + (k // 4) / RATE, abs=1e-9)
        # receive time = stamp + a few ms of transport latency
        for msg, rt in ((li, lrt), (lc, lcrt), (ri, rrt), (rc, rcrt)):
            assert 0.003 < rt - _stamp(msg) < 0.008
        assert lrt < lcrt < rrt < rcrt
        assert li.header.seq == lc.header.seq == k // 4
    y = yaml.safe_load(open(runs[name]["driver_yaml"]))
    assert y["right_lag_ms"] == e["lag_ms"]


@pytest.mark.parametrize("name", drv.DRIVERS)
def test_camera_info_calibration(runs, name):
    from mdr_slam.camera import StereoCamera
    e = EXPECT[name]
    ref = sim_camera(scale=0.25)
    infos = {}
    for topic, msg, _ in _read(runs[name]["bag"]):
        if topic in e["infos"]:
            infos.setdefault(topic, cv.camera_info_to_model(msg))
    cam = StereoCamera(infos[e["infos"][0]], infos[e["infos"][1]])
    # P is the rectified projection the images were rendered with, for every driver
    np.testing.assert_allclose(cam.left.P, ref.left.P, atol=1e-9)
    np.testing.assert_allclose(cam.right.P, ref.right.P, atol=1e-9)
    assert cam.right.P[0, 3] == pytest.approx(-ref.fx * 0.11)
    if name == "stereo_image_proc":
        # a raw calibration: rectifying these already rectified images again warps them
        assert not cam.is_rectified
        for m in (cam.left, cam.right):
            assert abs(m.D[0]) > 0.1 and 1e-3 < np.abs(m.R - np.eye(3)).max() < 0.05
        import cv2
        mx, my = cv2.initUndistortRectifyMap(cam.left.K, cam.left.D, cam.left.R, cam.left.P,
                                             (cam.left.width, cam.left.height), cv2.CV_32FC1)
        u = np.arange(cam.left.width)[None, :]
        assert np.abs(mx - u).max() > 5.0
    else:
        assert cam.is_rectified
        for m in (cam.left, cam.right):
            assert not np.any(m.D) and np.array_equal(m.R, np.eye(3))


def test_images_equal_the_rendered_grey(runs):
    import cv2
    ref = _reference_frames(runs)
    assert len(ref) == 20
    for name in ("zed", "realsense", "stereo_image_proc", "realsense_png", "zed_jpeg"):
        base = name.split("_")[0] if name != "stereo_image_proc" else name
        e = EXPECT[base]
        compressed = name.endswith(("png", "jpeg"))
        topics = [t + "/compressed" if compressed else t for t in e["images"]]
        got = {0: [], 1: []}
        for topic, msg, _ in _read(runs[name]["bag"]):
            if topic in topics:
                side = topics.index(topic)
                if compressed:
                    img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
                else:
                    img = cv.image_to_numpy(msg)
                if img.ndim == 3:
                    img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
                got[side].append(img)
        for side in (0, 1):
            assert len(got[side]) == len(ref)
            for i, img in enumerate(got[side]):
                diff = np.abs(img.astype(int) - ref[i][side].astype(int))
                if name == "zed_jpeg":
                    assert diff.mean() < 3.0, (name, side, i, diff.mean())
                elif name == "zed":
                    assert diff.max() <= 1, (name, side, i)
                else:   # mono8 raw and png are the rendered bytes
                    assert diff.max() == 0, (name, side, i)


def test_compressed_topics_and_formats(runs):
    for name, fmt in (("zed_jpeg", "bgr8; jpeg compressed bgr8"),
                      ("realsense_png", "mono8; png compressed ")):
        e = EXPECT[name.split("_")[0]]
        types = _types(runs[name]["bag"])
        for t in e["images"]:
            assert t not in types                       # no raw image topics
            assert types[t + "/compressed"] == "sensor_msgs/CompressedImage"
        for t in e["infos"]:
            assert types[t] == "sensor_msgs/CameraInfo"
        seq = [(t, m) for t, m, _ in _read(runs[name]["bag"])
               if t.endswith("/compressed") or t in e["infos"]]
        assert [t for t, _ in seq[:4]] == [e["images"][0] + "/compressed", e["infos"][0],
                                          e["images"][1] + "/compressed", e["infos"][1]]
        for t, m in seq:
            if t.endswith("/compressed"):
                assert m.format == fmt
                assert m.header.frame_id in e["frames"]
        y = yaml.safe_load(open(runs[name]["driver_yaml"]))
        assert y["image_transport"] == "compressed"
        assert y["compressed_format"] == fmt.split(";")[1].split()[0]
        assert y["topics"]["left_image"] == e["images"][0]   # the transport's base topic
        assert y["bag_topics"]["left_image"] == e["images"][0] + "/compressed"


# ------------------------------------------------------------------------------------- tf
@pytest.mark.parametrize("name", drv.DRIVERS)
def test_tf_static_chain_composes_to_T_base_cam(runs, name):
    import rosbag
    import rospy
    import tf2_py
    e = EXPECT[name]
    y = yaml.safe_load(open(runs[name]["driver_yaml"]))
    T_base_cam = np.array(y["T_base_cam"])
    with rosbag.Bag(runs[name]["bag"]) as bag:
        read = list(bag.read_messages(topics=["/tf_static"], return_connection_header=True))
    static = [r[1] for r in read]
    assert len(static) == 1      # written once, before everything else, latched (rosbag play)
    assert read[0][3]["latching"] in (b"1", "1")
    assert _read(runs[name]["bag"])[0][0] == "/tf_static"
    buf = tf2_py.BufferCore()
    edges = {}
    for ts in static[0].transforms:
        # rosbag yields its own generated message classes; tf2 wants geometry_msgs' own
        buf.set_transform_static(cv.matrix_to_transform_stamped(
            cv.transform_stamped_to_matrix(ts), ts.header.stamp, ts.header.frame_id,
            ts.child_frame_id), "bag")
        edges[ts.child_frame_id] = ts.header.frame_id
    chain = [e["chain"][-1]]
    while chain[-1] in edges:
        chain.append(edges[chain[-1]])
    assert chain[::-1] == e["chain"]
    T = cv.transform_stamped_to_matrix(
        buf.lookup_transform_core("base_link", e["frames"][0], rospy.Time(0)))
    np.testing.assert_allclose(T, T_base_cam, atol=1e-7)
    # the right optical frame is the baseline along the left's x
    Tr = cv.transform_stamped_to_matrix(
        buf.lookup_transform_core(e["frames"][0], e["frames"][1], rospy.Time(0)))
    np.testing.assert_allclose(Tr, make_T(np.eye(3), [0.11, 0, 0]), atol=1e-7)
    # REP-103 optical frame: z forward ~ base x (tilted down by the mount pitch), x = -base y
    assert T_base_cam[:3, 2] @ [1, 0, 0] > 0.99 and T_base_cam[2, 2] < 0
    np.testing.assert_allclose(T_base_cam[:3, 0], [0, -1, 0], atol=1e-9)
    assert T_base_cam[0, 3] == pytest.approx(0.1)
    # a realistic mounting: base_link stays near the floor and near level along the sequence
    from mdr_slam.io import read_tum
    gt = read_tum(os.path.join(runs[name]["out_dir"], "groundtruth.tum"))
    Tb = gt.matrices() @ inv_T(T_base_cam)
    assert np.abs(Tb[:, 2, 3]).max() < 0.1
    assert np.degrees(np.arccos(np.clip(Tb[:, 2, 2], -1, 1))).max() < 5.0


# ------------------------------------------------------------------------------- odometry
def test_wheel_odometry_drifts_by_the_configured_amount(runs):
    name = "zed"
    y = yaml.safe_load(open(runs[name]["driver_yaml"]))
    T_base_cam = np.array(y["T_base_cam"])
    od = y["odometry"]
    assert od["scale_error"] == drv.ODOM_SCALE_ERROR and od["rate_hz"] == 50.0
    msgs = _read(runs[name]["bag"])
    odom = [(m, rt) for t, m, rt in msgs if t == "/odom"]
    tfs = [m.transforms[0] for t, m, _ in msgs if t == "/tf"]
    stamps = np.array([_stamp(m) for m, _ in odom])
    # its own 50 Hz clock from the first frame, over the image stamps
    np.testing.assert_allclose(np.diff(stamps), 0.02, atol=1e-8)
    assert stamps[0] == pytest.approx(1.0) and stamps[-1] > 1.0 + 0.95 - 0.02
    assert all(0 < rt - _stamp(m) < 0.002 for m, rt in odom)
    assert all(m.header.frame_id == "odom" and m.child_frame_id == "base_link" for m, _ in odom)
    T_odom = np.array([cv.pose_to_matrix(m.pose.pose) for m, _ in odom])
    np.testing.assert_allclose(T_odom[0], np.eye(4), atol=1e-9)
    assert len(tfs) == len(odom)
    for ts, (m, _) in zip(tfs, odom):
        assert ts.header.stamp == m.header.stamp
        np.testing.assert_allclose(cv.transform_stamped_to_matrix(ts),
                                   cv.pose_to_matrix(m.pose.pose), atol=1e-9)
    cov = np.array(odom[0][0].pose.covariance).reshape(6, 6)
    assert np.all(np.diag(cov) > 0) and np.count_nonzero(cov) == 6
    # the true base motion at the odometry stamps (the simulator's analytic trajectory)
    sc = make_scene("office", seed=3)
    traj = build_trajectory(sc, 1.0, 3, scene=sc)
    Tb = traj.poses(stamps - 1.0) @ inv_T(T_base_cam)
    true_inc = np.einsum("nij,njk->nik", np.linalg.inv(Tb[:-1]), Tb[1:])
    odo_inc = np.einsum("nij,njk->nik", np.linalg.inv(T_odom[:-1]), T_odom[1:])
    L = np.linalg.norm(true_inc[:, :3, 3], axis=1)
    Lo = np.linalg.norm(odo_inc[:, :3, 3], axis=1)
    assert L.sum() > 1.0
    assert Lo.sum() / L.sum() == pytest.approx(1.0 + drv.ODOM_SCALE_ERROR, abs=1e-6)
    # yaw error at the end ~ drift per metre x path length (the base stays near level)
    T_true = inv_T(Tb[0]) @ Tb[-1]
    E = inv_T(T_true) @ T_odom[-1]
    yaw_err = np.degrees(np.arctan2(E[1, 0], E[0, 0]))
    assert yaw_err == pytest.approx(drv.ODOM_YAW_DRIFT * L.sum(), rel=0.15)
    # twist: the last increment over its step, in the base frame
    for k in (5, 20):
        tw = odom[k][0].twist.twist
        v = np.array([tw.linear.x, tw.linear.y, tw.linear.z])
        np.testing.assert_allclose(v * 0.02, odo_inc[k - 1][:3, 3], atol=1e-6)


def test_wheel_odometry_function():
    """Straight 1 m drive in 100 steps: 2 % long, 1 deg of yaw, from identity."""
    Tb = np.tile(np.eye(4), (101, 1, 1))
    Tb[:, 0, 3] = np.linspace(0, 1, 101)
    T, inc = drv.wheel_odometry(Tb, 0.02, 1.0)
    np.testing.assert_allclose(T[0], np.eye(4))
    assert np.linalg.norm(inc[1:, :3, 3], axis=1).sum() == pytest.approx(1.02)
    assert np.degrees(np.arctan2(T[-1][1, 0], T[-1][0, 0])) == pytest.approx(1.0)
    T0, _ = drv.wheel_odometry(Tb, 0.0, 0.0)
    np.testing.assert_allclose(T0, Tb, atol=1e-12)


# ------------------------------------------------------------------------------ options, CLI
def test_bad_options_raise():
    with pytest.raises(ValueError, match="unknown driver"):
        drv.DriverConfig(driver="kinect")
    with pytest.raises(ValueError, match="compressed"):
        drv.DriverConfig(driver="zed", compressed="webp")
    with pytest.raises(ValueError, match="right_lag_ms"):
        drv.DriverConfig(driver="zed", right_lag_ms=-1.0)
    with pytest.raises(ValueError, match="rectified"):
        generate_driver("/nonexistent/never", "zed", distort=True, **ARGS)
    with pytest.raises(ValueError, match="half the frame period"):
        generate_driver("/nonexistent/never", "zed", right_lag_ms=30.0, **ARGS)


def test_cli_defaults_match_the_module():
    import argparse
    from mdr_slam.cli import main_sim
    p = argparse.ArgumentParser()
    a = main_sim.add_parser(p.add_subparsers()).parse_args(["--out", "x", "--driver", "zed"])
    assert a.odom_drift == [drv.ODOM_SCALE_ERROR, drv.ODOM_YAW_DRIFT]
    assert a.odom_rate == drv.ODOM_RATE and a.jpeg_quality == drv.JPEG_QUALITY
    assert a.odom and a.compressed is None and a.right_lag is None


def test_mdr_sim_driver_cli(tmp_path):
    out = tmp_path / "sip"
    r = subprocess.run(["mdr", "sim", "--scene", "corridor", "--duration", "0.3", "--scale",
                        "0.25", "--map-cell", "0.1", "--out", str(out), "--quiet",
                        "--driver", "stereo_image_proc", "--right-lag", "2", "--no-odom",
                        "--compressed", "jpeg"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "stereo_image_proc" in r.stdout and "driver.yaml" in r.stdout
    y = yaml.safe_load(open(out / "driver.yaml"))
    assert set(y) >= {"driver", "topics", "image_transport", "compressed_format", "frames",
                      "T_base_cam", "base_to_camera", "right_lag_ms", "odometry", "bag_topics"}
    assert y["driver"] == "stereo_image_proc" and y["right_lag_ms"] == 2.0
    assert set(y["topics"]) == {"left_image", "right_image", "left_info", "right_info"}
    assert y["odometry"]["enabled"] is False
    T = np.array(y["T_base_cam"])
    q = [float(v) for v in y["base_to_camera"].split()]
    from mdr_slam.geometry import T_from_pos_quat
    np.testing.assert_allclose(T_from_pos_quat(q[:3], q[3:]), T, atol=1e-7)
    types = _types(str(out / "sequence.bag"))
    assert set(types) == {"/stereo/left/image_rect/compressed",
                          "/stereo/right/image_rect/compressed", "/stereo/left/camera_info",
                          "/stereo/right/camera_info", "/tf_static"}
    msgs = _read(str(out / "sequence.bag"))
    li = [m for t, m, _ in msgs if t == "/stereo/left/image_rect/compressed"]
    ri = [m for t, m, _ in msgs if t == "/stereo/right/image_rect/compressed"]
    assert all(abs((b.header.stamp - a.header.stamp).to_nsec() - 2e6) <= 1
               for a, b in zip(li, ri))
    # options that only make sense with a driver
    bad = subprocess.run(["mdr", "sim", "--duration", "0.1", "--scale", "0.25", "--out",
                          str(tmp_path / "x"), "--compressed", "png"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "--driver" in bad.stderr
    bad = subprocess.run(["mdr", "sim", "--duration", "0.1", "--scale", "0.25", "--out",
                          str(tmp_path / "y"), "--driver", "zed", "--distort"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "rectified" in bad.stderr


def test_bench_counts_the_pairs_on_the_topics_it_is_given(runs):
    """``mdr bench`` reports the bag's stereo pairs on the driver's topics, compressed too."""
    from types import SimpleNamespace
    from mdr_slam.cli.bench_live import _stereo_pairs
    info = runs["zed_jpeg"]["driver"]
    args = SimpleNamespace(left_image=info["topics"]["left_image"],
                           right_image=info["topics"]["right_image"], image_transport="compressed")
    assert _stereo_pairs(runs["zed_jpeg"]["bag"], args) == 20
    assert _stereo_pairs(runs["zed_jpeg"]["bag"]) == 0     # nothing on the default topics
