"""The offline pipeline (mdr run), the ablation bench (mdr bench --ablation) and the map pictures,
end to end on a small simulated sequence with exact ground truth."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from mdr_slam.io import cloud_xyz, read_cloud, read_tum

# At half resolution one disparity step is twice as much depth: the relative convergence threshold
# tau (sigma_Z / Z) is loosened accordingly so points converge within the short run.
SMALL = ["--set", "depth.tau=0.02"]
MDR = [sys.executable, "-c", "import sys; from mdr_slam.cli import main; sys.exit(main())"]


def _mdr(*args, check=True):
    r = subprocess.run(MDR + list(args), capture_output=True, text=True)
    if check:
        assert r.returncode == 0, r.stdout + r.stderr
    return r


def test_mdr_run_writes_map_trajectory_and_summary(small_sim, tmp_path):
    from mdr_slam.eval import map_metrics
    out = str(tmp_path / "run")
    _mdr("run", os.path.join(small_sim, "sequence.bag"), "--out", out, "--quiet", "--max-frames",
         "60", "--pose-source", "groundtruth", *SMALL)
    s = json.load(open(os.path.join(out, "summary.json")))
    assert s["pose_source"] == "groundtruth"
    assert s["frames_in"] == s["frames_posed"] == 60
    assert s["frames_integrated"] > 40
    for stage in ("depth", "depth.elas", "depth.filter", "fusion", "frame"):
        assert s["timing"][stage]["median_ms"] > 0
        assert s["timing"][stage]["p90_ms"] >= s["timing"][stage]["median_ms"]
    traj = read_tum(os.path.join(out, "trajectory.tum"))
    gt = read_tum(os.path.join(small_sim, "groundtruth.tum"))
    assert len(traj) == 60
    np.testing.assert_allclose(traj.positions, gt.positions[:60], atol=1e-6)
    est = cloud_xyz(read_cloud(os.path.join(out, "map.ply")))
    assert s["map_points"] == len(est) > 500
    m = map_metrics(est, cloud_xyz(read_cloud(os.path.join(small_sim, "gt_map.ply"))))
    print("small office, full pipeline: map RMSE %.4f m, completeness %.1f %%, %d points"
          % (m["accuracy_rmse"], 100 * m["completeness"], len(est)))
    assert m["accuracy_rmse"] < 0.10          # half resolution: 2x coarser disparities
    assert m["accuracy"] > 0.8
    assert m["completeness"] > 0.02           # the ground-truth map covers all 30 s


@pytest.fixture(scope="module")
def tiny_sim(tmp_path_factory):
    """1 s of the office loop at quarter resolution (188x120, 20 Hz, 20 frames, ground truth)."""
    from mdr_slam.sim import generate
    d = str(tmp_path_factory.mktemp("tiny"))
    generate(d, scene="office", duration=1.0, seed=1, rate=20.0, scale=0.25, workers=1,
             map_cell=0.05)
    return d


def _driver_bag(src, dst, seed=0):
    """``src`` re-recorded as a camera driver and ``rosbag record`` make it: png-compressed
    images on /cam/{left,right}/image_raw/compressed, the right stamped 3 ms after the left, each
    camera_info after its image, messages in receive order (stamp + 5..65 ms: the bag's order is
    not the stamps'), no ground truth."""
    import genpy
    import rosbag
    from mdr_slam import conversions as cv
    rng = np.random.default_rng(seed)
    recs = []
    with rosbag.Bag(src) as bag:
        for topic, msg, _ in bag.read_messages(topics=[
                "/stereo/left/image_raw", "/stereo/right/image_raw",
                "/stereo/left/camera_info", "/stereo/right/camera_info"]):
            side = "left" if "/left/" in topic else "right"
            stamp = msg.header.stamp + genpy.Duration.from_sec(0.003 if side == "right" else 0)
            t_rx = stamp.to_sec() + 0.005 + rng.uniform(0, 0.06)
            if topic.endswith("image_raw"):
                recs.append((t_rx, "/cam/%s/image_raw/compressed" % side,
                             cv.numpy_to_compressed_image(cv.image_to_mono8(msg), "png", stamp)))
            else:
                msg.header.stamp = stamp
                recs.append((t_rx + 0.07, "/cam/%s/camera_info" % side, msg))   # after the image
    with rosbag.Bag(dst, "w") as bag:
        for t_rx, topic, msg in sorted(recs, key=lambda r: r[0]):
            bag.write(topic, msg, genpy.Time.from_sec(t_rx))
    return dst


def test_mdr_run_maps_a_driver_bag(tiny_sim, tmp_path):
    """Compressed images on the driver's topics, camera_info after the images, right lagging
    3 ms, no ground truth, no --calib: mapped with ORB poses (the default)."""
    bag = _driver_bag(os.path.join(tiny_sim, "sequence.bag"), str(tmp_path / "driver.bag"))
    topics = ["--left-image", "/cam/left/image_raw", "--right-image", "/cam/right/image_raw",
              "--left-info", "/cam/left/camera_info", "--right-info", "/cam/right/camera_info"]
    out = str(tmp_path / "run")
    _mdr("run", bag, "--out", out, "--quiet", "--max-frames", "8", *topics,
         "--image-transport", "compressed", *SMALL)
    s = json.load(open(os.path.join(out, "summary.json")))
    assert s["pose_source"] == "orb" and s["frames_in"] == 8 and s["skipped_inputs"] == 0, s
    assert s["camera"]["width"] == 188 and s["camera"]["baseline"] == pytest.approx(0.11)
    assert s["frames_posed"] > 0
    # the raw topics are not there: the error names the image topics the bag has
    r = _mdr("run", bag, "--out", str(tmp_path / "x"), *topics, check=False)
    assert r.returncode == 1 and "no stereo pair on /cam/left/image_raw and" in r.stderr and \
        "/cam/left/image_raw/compressed [sensor_msgs/CompressedImage]" in r.stderr, r.stderr


def test_mdr_run_tracks_unless_told_to_use_the_ground_truth(tiny_sim, tmp_path):
    bag = os.path.join(tiny_sim, "sequence.bag")
    _mdr("run", bag, "--out", str(tmp_path / "a"), "--quiet", "--max-frames", "8", *SMALL)
    assert json.load(open(str(tmp_path / "a" / "summary.json")))["pose_source"] == "orb"
    _mdr("run", bag, "--out", str(tmp_path / "b"), "--quiet", "--max-frames", "8",
         "--pose-source", "groundtruth", *SMALL)
    s = json.load(open(str(tmp_path / "b" / "summary.json")))
    assert s["pose_source"] == "groundtruth" and s["frames_in"] == s["frames_posed"] == 8, s
    traj = read_tum(str(tmp_path / "b" / "trajectory.tum"))
    gt = read_tum(os.path.join(tiny_sim, "groundtruth.tum"))
    np.testing.assert_allclose(traj.positions, gt.positions[:8], atol=1e-6)
    # another ground-truth topic: none there, so no frame is posed (and the run says so)
    r = _mdr("run", bag, "--out", str(tmp_path / "c"), "--max-frames", "4", "--pose-source",
             "groundtruth", "--ground-truth-pose", "/nothing", *SMALL)
    assert "no ground-truth pose at the first frame (topic /nothing)" in r.stderr
    assert json.load(open(str(tmp_path / "c" / "summary.json")))["frames_posed"] == 0


def test_orb_map_is_base_link_at_the_start_with_base_to_camera(small_sim):
    """As the pose node: with ``base_to_camera`` (T_base_cam) the offline runner's ORB trajectory
    and map are in base_link at the first tracked frame (REP-105 map), i.e. T_base_cam times what
    it gives without (a level camera looking along base_link's x: T_BASE_OPTICAL @ the tracker's
    first camera frame); the same run otherwise."""
    from mdr_slam.geometry import T_BASE_OPTICAL, inv_T, parse_transform, transform_points
    from mdr_slam.pipeline import Pipeline, PipelineConfig, frames_from_bag
    mount = "0.1 0 1.3 -0.5416 0.5416 -0.4545 0.4545"   # 1.3 m up, 10 deg down
    out = {}
    for m in ("", mount):
        cam, frames = frames_from_bag(os.path.join(small_sim, "sequence.bag"), max_frames=20)
        pl = Pipeline(cam, PipelineConfig(pose_source="orb", pose_params={"base_to_camera": m},
                                          depth_params={"tau": 0.02}))
        for f in frames:
            pl.process(f)
        pl.tracker.shutdown()
        out[m] = (pl.trajectory().matrices(), pl.map.points(1))
    A = parse_transform(mount)
    (Ta, Pa), (Tb, Pb) = out[""], out[mount]
    assert len(Ta) == len(Tb) >= 15 and min(len(Pa), len(Pb)) > 100
    np.testing.assert_allclose(Ta[0], T_BASE_OPTICAL, atol=1e-9)
    B = A @ inv_T(T_BASE_OPTICAL)   # from the default map to the mount's
    np.testing.assert_allclose(Tb, B[None] @ Ta, atol=1e-6)
    # the same surfaces, voxelized along other axes: each map point near one of the other map's
    from scipy.spatial import cKDTree
    d = cKDTree(transform_points(B, Pa)).query(Pb)[0]
    assert np.median(d) < 0.02 and np.percentile(d, 90) < 0.05, (np.median(d), np.percentile(d, 90))
    # ... and not the map of the first camera frame
    assert np.median(cKDTree(transform_points(inv_T(T_BASE_OPTICAL), Pa)).query(Pb)[0]) > 0.5


def test_ablation_switches_change_the_map(small_sim, tmp_path):
    """--temporal off publishes every ELAS pixel (many more, noisier points than the filter)."""
    outs = {}
    for name, t in (("base", "off"), ("temporal", "on")):
        outs[name] = str(tmp_path / name)
        _mdr("run", os.path.join(small_sim, "sequence.bag"), "--out", outs[name], "--quiet",
             "--pose-source", "groundtruth", "--temporal", t, "--confidence", "off",
             "--max-frames", "30", *SMALL)
    sb, st = (json.load(open(os.path.join(outs[k], "summary.json"))) for k in ("base", "temporal"))
    assert sb["temporal"] is False and sb["confidence"] is False
    assert sb["points_published"] > 2 * st["points_published"] > 0
    r = _mdr("run", os.path.join(small_sim, "sequence.bag"), "--out", str(tmp_path / "x"),
             "--temporal", "maybe", check=False)
    assert r.returncode != 0 and "on or off" in r.stderr


def test_run_refuses_bad_overrides_and_missing_input(tmp_path):
    r = _mdr("run", str(tmp_path / "missing.bag"), "--out", str(tmp_path / "o"), check=False)
    assert r.returncode != 0
    r = _mdr("run", str(tmp_path / "missing.bag"), "--out", str(tmp_path / "o"), "--set", "nodot=1",
             check=False)
    assert r.returncode != 0 and "NODE.KEY=VALUE" in r.stdout + r.stderr


def test_set_keeps_a_bare_off_for_a_word_parameter():
    # YAML reads a bare off as false: a word parameter (weak_texture, densify) keeps the word,
    # a switch gets the bool, a number refuses it
    from mdr_slam.cli.main_run import _overrides
    ov = _overrides(["depth.weak_texture=off", "depth.densify=off", "depth.temporal=off"])
    assert ov["depth"] == {"weak_texture": "off", "densify": "off", "temporal": False}
    with pytest.raises(SystemExit):
        _overrides(["depth.tau=off"])


def test_live_bench_set_reaches_the_launch_over_its_weak_texture_argument(tmp_path):
    """mdr.launch sets the depth node's weak_texture after its parameter file, so the live
    benchmark's --set passes it as the launch argument too."""
    import argparse
    import yaml
    from mdr_slam.cli.bench_live import _param_files
    args = argparse.Namespace(preset=None, out=str(tmp_path),
                              set=["depth.weak_texture=sgbm", "depth.tau=0.02"])
    launch = _param_files(args)
    assert "weak_texture:=sgbm" in launch
    with open(str(tmp_path / "depth.yaml")) as f:
        assert yaml.safe_load(f)["tau"] == 0.02
    args.set = ["depth.tau=0.02"]
    assert not any(a.startswith("weak_texture:=") for a in _param_files(args))


def test_bench_ablation_report(small_sim, tmp_path):
    out = tmp_path / "bench"
    out.mkdir()
    os.symlink(small_sim, str(out / "sim_office"))
    r = _mdr("bench", "--ablation", "--out", str(out), "--scenes", "office", "--max-frames", "20",
             "--configs", "elas_only,full", *SMALL)
    rep = json.load(open(str(out / "ablation.json")))
    res = rep["results"]["office"]
    assert set(res) == {"elas_only", "full"}
    for c in res.values():
        assert c["rmse_m"] > 0 and 0 < c["completeness"] <= 1 and c["n_points"] > 0
    assert "| office | full |" in r.stdout
    assert os.path.getsize(str(out / "ablation.png")) > 5000
    for c in res.values():
        assert 0 < c["accuracy_5cm"] <= 1 and 0 < c["fscore"] <= 1


def test_bench_ablation_with_estimated_poses(small_sim, tmp_path):
    """Estimated poses: the tracker's map is aligned to the truth by its trajectory before scoring."""
    out2 = tmp_path / "bench_orb"
    out2.mkdir()
    os.symlink(small_sim, str(out2 / "sim_office"))
    r = _mdr("bench", "--ablation", "--out", str(out2), "--scenes", "office", "--max-frames", "40",
             "--configs", "full", "--pose-source", "orb", *SMALL)
    full = json.load(open(str(out2 / "ablation.json")))["results"]["office"]["full"]
    # the tracker loses this half-resolution 10 Hz stream for a frame at ~10 where it turns to a
    # blank wall and relocalizes; the frames it posed must give a map that lands on
    # the true surfaces. Its ATE is chaotic: 0.049 m, then 0.172 m once a change of tie order broke
    # Hamming ties by keypoint index (the last 6 frames drift 1 deg each along a bright band's
    # edges, the weakness of office_loop_rotation seed 7), hence the loose bound
    assert full["frames_posed"] >= 35 and full["ate_m"] < 0.25, full
    assert full["rmse_m"] < 0.1 and full["accuracy_5cm"] > 0.5, full


def test_map_pictures_show_the_map(tmp_path):
    from mdr_slam.viz import drop_ceiling, save_map_pictures
    import cv2
    rng = np.random.default_rng(0)
    n = 40000
    floor = np.c_[rng.uniform(0, 8, n), rng.uniform(0, 6, n), np.zeros(n)]
    wall = np.c_[rng.uniform(0, 8, n), np.zeros(n), rng.uniform(0, 2.8, n)]
    ceiling = np.c_[rng.uniform(0, 8, n), rng.uniform(0, 6, n), np.full(n, 2.8)]
    P = np.concatenate([floor, wall, ceiling])
    keep = drop_ceiling(P)
    assert keep[: 2 * n].mean() > 0.9 and not keep[2 * n:].any()
    top, persp = save_map_pictures(P, str(tmp_path / "map"))
    for path in (top, persp):
        img = cv2.imread(path)
        assert img is not None and img.shape[0] > 200 and img.shape[1] > 200
        coloured = (np.abs(img.astype(int) - 255).sum(axis=2) > 60).mean()
        assert coloured > 0.15, (path, coloured)   # the map covers a good part of the picture


def test_demo_leaves_map_report_and_pictures(tmp_path):
    """The README's first command, small: render, map, score, draw (pictures show the map)."""
    import cv2
    out = str(tmp_path / "output")
    r = _mdr("demo", "--out", out, "--scale", "0.5", "--max-frames", "40", *SMALL)   # ORB poses
    demo = os.path.join(out, "demo")
    for name in ("map.ply", "report.md", "summary.json", "trajectory.tum", "map_top.png",
                 "map_perspective.png", "trajectory.png"):
        assert os.path.getsize(os.path.join(demo, name)) > 100, name
    report = open(os.path.join(demo, "report.md")).read()
    assert "map RMSE" in report and "frames in / posed / integrated" in report, report
    assert "Pose source: **orb**" in report and "ATE RMSE" in report, report
    for name in ("map_top.png", "map_perspective.png"):
        img = cv2.imread(os.path.join(demo, name))
        coloured = (np.abs(img.astype(int) - 255).sum(axis=2) > 60).mean()
        assert coloured > 0.02, (name, coloured)
    assert "[mdr demo] done" in r.stdout
    if shutil.which("rviz") and shutil.which("Xvfb"):
        # rviz under Xvfb drew the map the fusion node published: height-coloured pixels in its 3D
        # view (the grey background, grid and panels have no saturated colour)
        from mdr_slam.viz import colourful_share
        img = cv2.imread(os.path.join(demo, "map_rviz.png"))
        assert img is not None, r.stdout
        assert colourful_share(img[:, :, ::-1]) > 0.005, r.stdout
        assert "map_rviz.png" in report


def test_read_xwd_round_trip(tmp_path):
    """Xvfb's frame buffer format (XWD, 32 bits per pixel, LSB first) reads back as RGB."""
    import struct
    from mdr_slam.viz import read_xwd
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (7, 5, 3), dtype=np.uint8)
    name = b"screen\0"
    header = [100 + len(name), 7, 2, 24, 5, 7, 0, 0, 32, 0, 32, 32, 5 * 4, 4, 0xFF0000, 0xFF00, 0xFF,
              8, 0, 0, 5, 7, 0, 0, 0]
    bgra = np.concatenate([img[:, :, ::-1], np.zeros((7, 5, 1), np.uint8)], axis=2)
    path = str(tmp_path / "s.xwd")
    with open(path, "wb") as f:
        f.write(struct.pack(">25I", *header) + name + bgra.tobytes())
    assert np.array_equal(read_xwd(path), img)
    with open(path, "r+b") as f:
        f.truncate(150)
    with pytest.raises(ValueError):
        read_xwd(path)


@pytest.mark.ros
def test_bench_live_measures_the_running_nodes(small_sim, tmp_path):
    """mdr bench BAG: roslaunch of the three nodes on a private master, rates and per-node
    resources measured from outside (bench.json keys are what scripts compare)."""
    out = str(tmp_path / "live")
    r = subprocess.run(MDR + ["bench", os.path.join(small_sim, "sequence.bag"), "--out", out,
                              "--pose-source", "groundtruth", "--rate", "2",
                              "--live-duration", "25", "--set", "fusion.publish_rate=2.0"],
                       capture_output=True, text=True,
                       timeout=180)
    assert r.returncode == 0, r.stdout + r.stderr
    b = json.load(open(os.path.join(out, "bench.json")))
    import yaml   # --set reaches the live node through its parameter file
    assert yaml.safe_load(open(os.path.join(out, "fusion.yaml")))["publish_rate"] == 2.0
    for k in ("map_integration_hz", "depth_hz", "pose_hz", "frames_in", "frames_tracked",
              "latency_ms", "cpu_percent", "rss_mb"):
        assert k in b, k
    assert b["pose_hz"] > 5 and b["depth_hz"] > 0.5, b
    # where the clouds went: published, empty (nothing converged), reaching the fusion node, fused
    assert 0 <= b["depth_clouds_empty"] < b["depth_clouds"], b
    assert 0 < b["clouds_integrated"] <= b["clouds_received_by_fusion"], b
    assert b["frames_tracked"] > 100 and b["frames_in"] > 20, b
    # live ATE of /mdr/pose against the bag's ground truth: the relayed ground truth itself
    assert b["live_ate"]["n"] > 100 and b["live_ate"]["rmse_m"] < 0.005, b["live_ate"]
    assert len(open(os.path.join(out, "live_trajectory.tum")).read().splitlines()) >= b["live_ate"]["n"]
    for n in ("pose_node", "depth_node", "fusion_node", "total"):
        assert b["rss_mb"][n]["max"] > 30, (n, b["rss_mb"])
    assert b["rss_mb"]["total"]["max"] >= b["rss_mb"]["fusion_node"]["max"]
    assert os.path.getsize(os.path.join(out, "resources.png")) > 5000
    assert "| fusion_node |" in open(os.path.join(out, "report.md")).read()
    # long-run record: RSS slope per node and total, the map's size and rates per time window
    for n in ("pose_node", "depth_node", "fusion_node", "total"):
        assert isinstance(b["rss_slope_mb_per_min"][n], float), b["rss_slope_mb_per_min"]
        assert isinstance(b["anon_slope_mb_per_min"][n], float), b["anon_slope_mb_per_min"]
    assert b["map_points_max"] > 0 and b["timeline_window_s"] == 5.0, b
    tl = b["timeline"]
    assert len(tl) >= 4 and tl[0]["t0"] == 0 and all(a["t1"] == c["t0"] for a, c in zip(tl, tl[1:]))
    assert sum(w["integrations_per_min"] for w in tl) > 0 and max(w["poses_per_min"] for w in tl) > 300
    assert 0 < [w["map_points"] for w in tl if w["map_points"] is not None][-1] <= b["map_points_max"]
    assert all(w["rss_mb"]["total"] > 90 for w in tl if w["rss_mb"]["total"] is not None)
    assert all(0 < w["anon_mb"]["total"] < w["rss_mb"]["total"] for w in tl
               if w["rss_mb"]["total"] is not None)
    assert any("fusion" in k for k in b["diagnostics_age_s"]), b["diagnostics_age_s"]
    assert "Over time (5 s windows" in open(os.path.join(out, "report.md")).read()
