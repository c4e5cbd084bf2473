"""The long-run report: windows cut from synthetic series (no ROS), its markdown table and plot,
and ``mdr run --window`` on a short simulated bag."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from mdr_slam.eval.timeline import (RunTimeline, Series, Tracked, increments, plot_timeline,
                                    process_rss_mb, timeline_md, window_bounds)

MDR = [sys.executable, "-c", "import sys; from mdr_slam.cli import main; sys.exit(main())"]


def test_window_bounds_cover_the_run_and_drop_a_short_tail():
    assert window_bounds(10.0, 5.0) == [(0.0, 5.0), (5.0, 10.0)]
    assert window_bounds(11.0, 5.0) == [(0.0, 5.0), (5.0, 10.0), (10.0, 11.0)]
    assert window_bounds(10.5, 5.0, min_len=1.0) == [(0.0, 5.0), (5.0, 10.0)]
    assert window_bounds(0.0, 5.0) == []
    b = window_bounds(1800.0, 300.0)
    assert len(b) == 6 and b[-1] == (1500.0, 1800.0)
    with pytest.raises(ValueError):
        window_bounds(10.0, 0.0)


def test_series_counts_gauges_and_counters_with_a_restart():
    ev = Series([0.5, 1.5, 1.6, 4.0])             # events: receipt times
    assert [ev.count(a, b) for a, b in window_bounds(4.0, 1.0)] == [1, 2, 0, 0]
    assert ev.count(3.0, 4.0, last=True) == 1     # the last window holds its end
    gauge = Series([(0.5, 10), (2.5, 30)])
    assert gauge.at(0.4) is None and gauge.at(1.0) == 10 and gauge.at(3.0) == 30
    # a cumulative counter that restarts (the node respawned): 0 1 3 | 1 2
    c = Series([(0.1, 0), (0.9, 1), (1.5, 3), (2.2, 1), (3.5, 2)])
    np.testing.assert_array_equal(increments(c.v), [0, 1, 2, 1, 1])
    assert [c.increase(a, b) for a, b in window_bounds(4.0, 1.0)] == [1, 2, 1, 1]
    assert Series().increase(0, 1) == 0 and Series().at(5) is None


def test_tracked_share_and_tracking_time_per_window():
    # live TrackingState codes (1 OK, 2 LOST, 3 RELOCALIZED) and offline names
    tr = Tracked([(0.1, 1, 10.0), (0.2, 2, 30.0), (0.3, 3, 20.0), (0.4, 0, None),
                  (1.5, "OK", 5.0), (1.6, "LOST", float("nan"))])
    w0 = tr.figures(0.0, 1.0)
    assert w0["frames"] == 4 and w0["frames_tracked"] == 2 and w0["tracked_share"] == 0.5
    assert w0["tracking_ms"]["median"] == 20.0 and w0["tracking_ms"]["n"] == 3
    assert 20.0 < w0["tracking_ms"]["p90"] <= 30.0
    w1 = tr.figures(1.0, 2.0)
    assert w1["frames"] == 2 and w1["tracked_share"] == 0.5 and w1["tracking_ms"]["n"] == 1
    empty = tr.figures(2.0, 3.0)
    assert empty["frames"] == 0 and empty["tracked_share"] is None
    assert empty["tracking_ms"]["median"] is None and empty["tracking_ms"]["p90"] is None


def _offline_run(stamps, window=1.0, restart_at=None):
    """A RunTimeline fed like mdr run: each frame adds a point, every 3rd a keyframe, every
    10th a loop closure and an integration; ``restart_at``: the tracker restarts (counts from 0)."""
    st = {"n": 0, "base": 0}

    def sample():
        n = st["n"] - st["base"]
        return {"rss_mb": 100.0 + st["n"], "keyframes": n // 3, "sparse_map_points": 10 * n,
                "loop_closures_total": n // 10, "dense_map_points": 50 * st["n"],
                "integrations": st["n"]}
    tl = RunTimeline(window, sample)
    for i, s in enumerate(stamps):
        tl.before_frame(s)
        if restart_at is not None and i == restart_at:
            st["base"] = st["n"]
        st["n"] += 1
        tl.frame(s, "LOST" if i % 4 == 3 else "OK", 10.0 + i)
    return tl.rows()


def test_run_timeline_windows_in_bag_time_with_a_gap():
    # 10 Hz from t=100 s, then nothing from 1.2 s to 4 s: two empty windows in between
    stamps = [100.0 + 0.1 * i for i in range(12)] + [104.0 + 0.1 * i for i in range(10)]
    rows = _offline_run(stamps)
    assert [(r["t0"], r["t1"]) for r in rows] == [(0, 1), (1, 2), (2, 3), (3, 4), (4, 4.9)]
    assert [r["frames"] for r in rows] == [10, 2, 0, 0, 10]   # the last frame (4.9 s) counts
    assert sum(r["frames"] for r in rows) == len(stamps)
    assert rows[0]["frames_tracked"] == 8 and rows[0]["tracked_share"] == 0.8
    assert rows[2]["tracked_share"] is None and rows[2]["tracking_ms"]["median"] is None
    # the gauges at each window's end: 10 frames done by 1 s, 12 by 2 and 3 s (the gap)
    assert [r["rss_mb"] for r in rows] == [110.0, 112.0, 112.0, 112.0, 122.0]
    assert [r["keyframes"] for r in rows] == [3, 4, 4, 4, 7]
    assert [r["dense_map_points"] for r in rows] == [500, 600, 600, 600, 1100]
    assert [r["map_hz"] for r in rows] == [10.0, 2.0, 0.0, 0.0, 11.11]   # 10 in the last 0.9 s
    assert [r["loop_closures"] for r in rows] == [1, 0, 0, 0, 1]
    assert rows[-1]["loop_closures_total"] == 2
    assert rows[0]["tracking_ms"]["median"] == pytest.approx(14.5)


def test_run_timeline_survives_a_tracker_restart():
    rows = _offline_run([0.1 * i for i in range(40)], restart_at=25)
    # the loop-closure count drops to 0 at the restart: closures after it still count
    assert [r["loop_closures_total"] for r in rows] == [1, 2, 0, 1]
    assert [r["loop_closures"] for r in rows] == [1, 1, 0, 1]
    assert [r["keyframes"] for r in rows] == [3, 6, 1, 5]
    assert _offline_run([]) == []
    one = _offline_run([5.0])
    assert len(one) == 1 and one[0]["frames"] == 1 and one[0]["t1"] == 0


def test_timeline_table_and_plot(tmp_path):
    nodes = ("pose_node", "depth_node", "fusion_node")
    rows = [{"t0": 0.0, "t1": 300.0, "rss_mb": {"pose_node": 120.0, "depth_node": 90.5,
                                                "fusion_node": 200.0, "total": 410.5},
             "tracking_ms": {"median": 21.5, "p90": 40.0, "n": 3000}, "frames": 3000,
             "frames_tracked": 2970, "tracked_share": 0.99, "keyframes": 150,
             "sparse_map_points": 12000, "loop_closures": 1, "map_hz": 4.5,
             "dense_map_points": 2500000},
            {"t0": 300.0, "t1": 600.0, "rss_mb": {"pose_node": 130.0, "depth_node": None,
                                                  "fusion_node": 210.0, "total": None},
             "tracking_ms": {"median": None, "p90": None, "n": 0}, "frames": 0,
             "frames_tracked": 0, "tracked_share": None, "keyframes": None,
             "sparse_map_points": None, "loop_closures": 0, "map_hz": 0.0}]
    lines = timeline_md(rows, nodes)
    assert lines[0].startswith("| t (s) | RSS MB pose_node / depth_node / fusion_node / total |")
    assert len(lines) == 4 and all(ln.count("|") == lines[0].count("|") for ln in lines)
    assert lines[2] == ("| 0-300 | 120 / 90.5 / 200 / 410.5 | 21.5 / 40 | 2970 / 3000 (99 %) | "
                        "150 | 12000 | 1 | 4.5 | 2500000 |")
    assert lines[3] == "| 300-600 | 130 / - / 210 / - | - / - | 0 / 0 (-) | - | - | 0 | 0 | - |"
    # leading columns of the caller's, short node names in the header
    lines = timeline_md(rows, nodes, extra=(("poses", lambda w: w.get("poses_per_min")),),
                        labels=("pose", "depth", "fusion"))
    assert lines[0].startswith("| t (s) | poses | RSS MB pose / depth / fusion / total |")
    assert lines[2].startswith("| 0-300 | - | 120 / 90.5 / 200 / 410.5 |")
    # one process (mdr run): a single RSS column
    single = timeline_md([dict(rows[0], rss_mb=305.2)])
    assert "| RSS MB |" in single[0] and "| 0-300 | 305.2 |" in single[2]
    path = str(tmp_path / "timeline.png")
    assert plot_timeline(rows, path, title="test", nodes=nodes) == path
    assert os.path.getsize(path) > 5000
    assert plot_timeline([], str(tmp_path / "none.png")) is None


def test_process_rss_is_read_from_proc():
    rss = process_rss_mb()
    if os.path.exists("/proc/self/status"):
        assert 10 < rss < 1e5


@pytest.fixture(scope="module")
def sim3(tmp_path_factory):
    """3 s of the office loop at quarter resolution (188x120, 20 Hz, 60 frames)."""
    from mdr_slam.sim import generate
    d = str(tmp_path_factory.mktemp("sim3"))
    generate(d, scene="office", duration=3.0, seed=1, rate=20.0, scale=0.25, workers=1,
             map_cell=0.05)
    return d


def test_mdr_run_window_writes_the_timeline(sim3, tmp_path):
    out = str(tmp_path / "run")
    # ELAS on every pixel (--temporal off): the short run maps from its first frames
    r = subprocess.run(MDR + ["run", os.path.join(sim3, "sequence.bag"), "--out", out, "--quiet",
                              "--window", "1", "--temporal", "off"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.load(open(os.path.join(out, "summary.json")))
    d = json.load(open(os.path.join(out, "timeline.json")))
    assert d["window_s"] == 1.0 and d["pose_source"] == "orb"
    w = d["windows"]
    assert [(x["t0"], x["t1"]) for x in w] == [(0, 1), (1, 2), (2, 2.95)], w
    assert sum(x["frames"] for x in w) == s["frames_in"] == 60
    assert sum(x["frames_tracked"] for x in w) == s["frames_posed"] > 0
    for x in w:
        assert x["frames"] == 20 and 0 <= x["tracked_share"] <= 1
        assert 0 < x["tracking_ms"]["median"] <= x["tracking_ms"]["p90"] < 5000
        assert x["tracking_ms"]["n"] == 20
        assert 50 < x["rss_mb"] < 1e5
        assert x["keyframes"] > 0 and x["sparse_map_points"] > 0
        assert x["loop_closures"] >= 0 and x["loop_closures_total"] >= 0
        assert x["map_hz"] >= 0
    assert [x["dense_map_points"] for x in w] == sorted(x["dense_map_points"] for x in w)
    assert w[-1]["dense_map_points"] > 0
    assert sum(x["map_hz"] * (x["t1"] - x["t0"]) for x in w) == pytest.approx(
        s["frames_integrated"], abs=0.1)
    assert os.path.getsize(os.path.join(out, "timeline.png")) > 5000
    # a window of no length is refused
    r = subprocess.run(MDR + ["run", os.path.join(sim3, "sequence.bag"), "--out", out + "x",
                              "--window", "0"], capture_output=True, text=True)
    assert r.returncode == 2 and "expected seconds > 0" in r.stderr, r.stderr


def _fake_listener(elapsed=1800.0, t_start=1000.0):
    """A live benchmark's _Listener as 30 minutes of topics and diagnostics would leave it
    (no ROS): 10 Hz tracking states with every 10th LOST; the pose node down from 600 to 900 s
    (no states) and restarted then (keyframes and loop closures count from 0 again)."""
    import threading
    from mdr_slam.cli.bench_live import _Listener
    lst = _Listener.__new__(_Listener)   # without its subscribers
    lst.lock = threading.Lock()
    lst.t_start = t_start
    lst.n_pose = lst.n_depth = lst.n_depth_empty = 0
    lst.states, lst.diag, lst.diag_time = {}, {}, {}
    lst.tracking_ms, lst.latency_s, lst.depth_latency_s, lst.poses = [], [], [], []
    lst.t_pose, lst.t_depth, lst.integrated, lst.map_points = [], [], [], []
    lst.tracked, lst.keyframes, lst.loop_closures, lst.sparse_points = [], [], [], []
    for i in range(int(elapsed * 10)):
        t = 0.1 * i
        if i % 10 == 0:   # the fusion node's diagnostics once a second, all along
            lst.integrated.append((t_start + t, i // 5))
            lst.map_points.append((t_start + t, 100 * i))
        if 600 <= t < 900:
            continue
        restarted = t >= 900
        k = i - 9000 if restarted else i
        state = 2 if i % 10 == 0 else 1
        ms = 20.0 + (t / 60.0) + (i % 10)          # slower as the map grows
        w = t_start + t
        lst.states[state] = lst.states.get(state, 0) + 1
        lst.tracking_ms.append(ms)
        lst.tracked.append((w, state, ms))
        lst.keyframes.append((w, k // 50))
        lst.loop_closures.append((w, k // 3000))
        lst.t_pose.append(w)
        if i % 10 == 0:   # the pose node's
            lst.sparse_points.append((w, 20 * k))
    lst.diag = {"pose_node: pose": {"keyframes": str(lst.keyframes[-1][1])},
                "fusion_node: fusion": {"map points": str(lst.map_points[-1][1])}}
    samples = [{"t": float(t), "pose_node.rss_mb": 100.0 + t / 60, "pose_node.anon_mb": 80.0,
                "depth_node.rss_mb": 90.0, "depth_node.anon_mb": 70.0,
                "fusion_node.rss_mb": 200.0 + t / 10, "fusion_node.anon_mb": 150.0,
                "pose_node.cpu": 50.0, "depth_node.cpu": 80.0, "fusion_node.cpu": 30.0}
               for t in range(1, int(elapsed))]
    return lst, samples


def test_live_timeline_of_a_30_minute_run_in_5_minute_windows(sim3, tmp_path):
    import argparse
    from mdr_slam.cli.bench_live import NODES, _report_md, _summarize
    lst, samples = _fake_listener()
    args = argparse.Namespace(rate=1.0, loop=True, out=str(tmp_path), window=300.0,
                              left_image=None, right_image=None, image_transport="raw")
    r = _summarize(args, os.path.join(sim3, "sequence.bag"), lst, samples, 1800.0, "orb")
    assert r["timeline_window_s"] == 300.0
    tl = r["timeline"]
    assert [(w["t0"], w["t1"]) for w in tl] == [(300.0 * k, 300.0 * (k + 1)) for k in range(6)]
    w0, w1, w2, w3, w4, w5 = tl
    assert w0["frames"] == 3000 and w0["frames_tracked"] == 2700 and w0["tracked_share"] == 0.9
    assert w0["tracking_ms"]["n"] == 3000
    assert w0["tracking_ms"]["median"] < w5["tracking_ms"]["median"] <= w5["tracking_ms"]["p90"]
    assert w1["keyframes"] == 5999 // 50 and w1["sparse_map_points"] == 20 * 5990
    assert w1["loop_closures"] == 1 and w1["loop_closures_total"] == 1   # the first at 300 s
    # the pose node down for the whole window: no states, its last figures stand
    assert w2["frames"] == 0 and w2["tracked_share"] is None
    assert w2["tracking_ms"] == {"median": None, "p90": None, "n": 0}
    assert w2["keyframes"] == w1["keyframes"] and w2["loop_closures"] == 0
    # restarted at 900 s: counts from 0 again, later windows' closures still count
    assert w3["keyframes"] == 2999 // 50 and w3["loop_closures_total"] == 0
    assert w3["loop_closures"] == 0 and w3["frames"] == 3000
    assert (w4["loop_closures"], w4["loop_closures_total"]) == (1, 1)
    assert (w5["loop_closures"], w5["loop_closures_total"]) == (1, 2)
    assert sum(w["loop_closures"] for w in tl) == 3
    for w in tl:
        assert w["rss_mb"]["total"] == pytest.approx(sum(w["rss_mb"][n] for n in NODES), abs=0.2)
        assert w["map_hz"] == pytest.approx(2.0, abs=0.02)    # one integration per 0.5 s
        assert w["integrations_per_min"] == pytest.approx(60 * w["map_hz"], abs=1.0)
    assert tl[-1]["rss_mb"]["fusion_node"] > tl[0]["rss_mb"]["fusion_node"] + 100
    md = _report_md(r)
    assert "Over time (300 s windows" in md
    table = [ln for ln in md.splitlines() if ln.startswith("| 0-300 |")]
    assert len(table) == 1
    head = [ln for ln in md.splitlines() if ln.startswith("| t (s) | poses | depth clouds |")][0]
    assert "RSS MB pose / depth / fusion / total" in head and "sparse map points" in head
    assert table[0].count("|") == head.count("|")
    assert " 2700 / 3000 (90 %) " in table[0]
    assert [ln for ln in md.splitlines() if ln.startswith("| 600-900 |")][0].count(
        "| 0 / 0 (-) |") == 1
    # the default window of a 30-minute run: a minute
    del args.window
    assert _summarize(args, os.path.join(sim3, "sequence.bag"), lst, samples, 1800.0,
                      "orb")["timeline_window_s"] == 60.0
