"""``mdr bench --compare``: its input checks, and the offline comparison end to end (no live run:
that needs roslaunch and takes minutes)."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from mdr_slam.pose import orbslam3

MDR = [sys.executable, "-c", "import sys; from mdr_slam.cli import main; sys.exit(main())"]


def _mdr(*args):
    return subprocess.run(MDR + list(args), capture_output=True, text=True)


def test_compare_without_an_input_says_what_to_give(tmp_path):
    r = _mdr("bench", "--compare", "--out", str(tmp_path / "c"))
    assert r.returncode != 0
    assert "give one input: a BAG, --kitti DIR or --euroc DIR" in r.stderr
    assert not (tmp_path / "c").exists()


def test_compare_refuses_two_inputs_and_kitti_without_compare(tmp_path):
    r = _mdr("bench", "x.bag", "--kitti", str(tmp_path), "--compare", "--out", str(tmp_path / "c"))
    assert r.returncode != 0 and "give one input" in r.stderr
    r = _mdr("bench", "--kitti", str(tmp_path), "--out", str(tmp_path / "c"))
    assert r.returncode != 0 and "--kitti and --euroc go with --compare" in r.stderr
    r = _mdr("bench", "--compare", "--euroc", str(tmp_path / "none"), "--out", str(tmp_path / "c"))
    assert r.returncode != 0 and "does not exist" in r.stderr


def test_compare_no_live_writes_the_report(small_sim, tmp_path):
    out = str(tmp_path / "c")
    r = _mdr("bench", os.path.join(small_sim, "sequence.bag"), "--out", out, "--compare",
             "--no-live", "--runs", "1", "--max-frames", "12")
    assert r.returncode == 0, r.stdout + r.stderr
    rep = json.load(open(os.path.join(out, "compare.json")))
    want = ["mdr", "orbslam3"] if orbslam3.available() else ["mdr"]
    # the built-in tracker offline twice: as mdr run runs it and with its mapping threads
    runs = want[:1] + ["mdr-threads"] + want[1:]
    assert rep["backends"] == want and list(rep["offline"]["backends"]) == runs
    assert rep["offline"]["frames"] == 12 and rep["live"] is None and rep["live_runs"] == []
    assert not [d for d in os.listdir(out) if d.startswith("live_")]
    md = open(os.path.join(out, "compare.md")).read()
    assert "## Offline" in md and "Not run (--no-live)." in md
    assert "- offline CPU per frame / ORB-SLAM3's (both with mapping threads): " in md


def test_a_live_run_whose_pose_node_fell_back_is_recognised(tmp_path):
    from mdr_slam.cli.main_bench import _fell_back
    log_dir = tmp_path / "run" / "roslog" / "1234-abcd"
    log_dir.mkdir(parents=True)
    (log_dir / "depth_node-3.log").write_text("using the built-in tracker\n")   # not the pose node
    assert not _fell_back(str(tmp_path / "run"))
    (log_dir / "pose_node-2.log").write_text(
        "[rosout][INFO] 2026-01-01 00:00:00,000: pose_node: tracking\n")
    assert not _fell_back(str(tmp_path / "run"))
    with open(str(log_dir / "pose_node-2.log"), "a") as f:
        f.write("[rosout][ERROR] 2026-01-01 00:00:01,000: pose_node: backend 'orbslam3' "
                "unavailable (ImportError: no pyorbslam3): using the built-in tracker\n")
    assert _fell_back(str(tmp_path / "run"))
    assert not _fell_back(str(tmp_path / "missing"))
