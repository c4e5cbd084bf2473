"""Tracking LOST end to end: the real ORB tracker in the launch goes LOST, the
fusion node integrates nothing stamped while LOST (no smeared map) and resumes after relocalization.

The bag is the sample bag (the README demo's office sequence, 752x480, 20 Hz; conftest
``sample_bag``) with the camera "kidnapped": frames 0..A-1 as rendered (8 s of the first loop),
then UNMAPPED/2 pairs of another place (0.5 s of the sim's corridor, same camera: texture the
tracker cannot track or relocalize on, but the depth node matches it: LOST), BLANK uniform grey
pairs (1 s, no features at all), the other UNMAPPED/2 corridor pairs, then frames R0..R1-1 (5 s of
an earlier, already mapped part of the loop) with stamps that keep increasing, so the tracker must
relocalize. /tf and /ground_truth/pose of the sim are dropped (ORB poses; they would not fit the
restamped frames); the sample's ground truth of each played frame scores the run afterwards. The
launch plays it at PLAY = 0.5x (30 s) so that the ORB tracker keeps up with 20 Hz full-resolution
pairs on a loaded 2-core machine (it then saw 113-160 of the 160 tracked pairs, all OK). The file
takes 79-94 s there (the test at nice 19, the ~30 s sample render and a 20-pair corridor render
included).

The depth node's own LOST pause is off here, its temporal filter is off (every matched pair gives a
cloud) and it waits up to 5 s for tf: its filter stage waits on the first corridor pair (and keeps
the newest matched ones) until the relocalized pose comes, so these pairs get clouds posed by tf
interpolation between the last tracked pose and the relocalized one (a smeared pose, and another
place's geometry): only the fusion node's LOST gating keeps them out of the map. With that gating
off (fusion ``tracking_state_topic: ""``) the test fails: the skip counter stays 0 (measured: 2
clouds stamped while LOST reached the node, none skipped) and map points carry the LOST clouds'
stamps (another run, that assertion bypassed: 93880 map points from the clouds at 9.0, 10.85 and
10.95 s).

The smear is also measured on the sample's ground truth: the ORB map frame is aligned to it by the
tracked part's poses (Umeyama, SE(3)); the relocalized poses must lie on the true poses of the
replayed frames, and the map points added after relocalization on the true surfaces (gt_map.ply,
median distance) about as closely as the points mapped before the loss.
"""
from __future__ import annotations

import copy
import os
import time

import numpy as np
import pytest

from conftest import ROOT, wait_for

pytestmark = pytest.mark.ros

RATE = 20.0          # Hz of the sample bag
A = 160              # frames played normally (8 s)
BLANK = 20           # blank pairs (1 s)
UNMAPPED = 20        # pairs of an unmapped place (1 s)
R0, R1 = 40, 140     # the replayed, already mapped frames (5 s)
PLAY = 0.5           # play rate of the launch: 20 Hz full-resolution pairs at 10 Hz wall


@pytest.fixture(scope="module")
def lost_bag(sample_bag, tmp_path_factory):
    import rosbag
    import rospy
    d = str(tmp_path_factory.mktemp("lost_sample"))
    frames = {}   # stamp (ns) -> {topic: msg}, the first max(A, R1) stereo frames of the sample
    topics = ["/stereo/left/image_raw", "/stereo/right/image_raw", "/stereo/left/camera_info",
              "/stereo/right/camera_info"]
    stamps = []
    n_need = max(A, R1)
    with rosbag.Bag(os.path.join(sample_bag, "sequence.bag")) as b:
        for topic, msg, _t in b.read_messages(topics=topics):
            s = msg.header.stamp.to_nsec()
            if s not in frames:
                if len(stamps) == n_need:
                    break
                frames[s] = {}
                stamps.append(s)
            frames[s][topic] = msg
    stamps.sort()
    assert len(stamps) == n_need and all(len(frames[s]) == len(topics) for s in stamps)
    # a few frames of another place (the sim's corridor, same camera): textured, matchable
    # stereo that the tracker cannot relocalize on, so the depth node makes clouds while LOST
    from mdr_slam.sim import generate
    dc = os.path.join(d, "corridor")
    generate(dc, scene="corridor", duration=UNMAPPED / RATE, workers=1, map_cell=0.2)
    other = []
    with rosbag.Bag(os.path.join(dc, "sequence.bag")) as b:
        for topic, msg, _t in b.read_messages(topics=topics[:2]):
            if topic == topics[0]:
                other.append({})
            other[-1][topic] = msg
    assert len(other) >= UNMAPPED
    # LOST from the first unmapped pair: the depth node's filter stage waits on that pair (and
    # holds the newest matched ones) until the relocalized pose comes, so both halves give clouds
    h = UNMAPPED // 2
    seq = [("track", i) for i in range(A)] + [("unmapped", i) for i in range(h)] + \
        [("blank", A - 1)] * BLANK + [("unmapped", i) for i in range(h, UNMAPPED)] + \
        [("kidnap", i) for i in range(R0, R1)]
    t0 = stamps[0]
    dt = int(round(1e9 / RATE))
    info = {"t0": t0 * 1e-9, "dt": dt * 1e-9, "kinds": [k for k, _ in seq],
            "source": [i for _, i in seq],
            "source_stamps": [stamps[i] * 1e-9 if k != "unmapped" else None for k, i in seq],
            "sample": sample_bag}
    out = os.path.join(d, "lost.bag")
    with rosbag.Bag(out, "w") as w:
        for k, (kind, i) in enumerate(seq):
            st = rospy.Time(0, t0 + k * dt)
            for topic in topics:
                if kind == "unmapped":
                    m = frames[stamps[A - 1]][topic]
                    if topic.endswith("image_raw"):   # the corridor's pixels, the sample's header
                        m = copy.deepcopy(m)
                        m.data = other[i][topic].data
                else:
                    m = frames[stamps[i]][topic]
                if kind == "blank" and topic.endswith("image_raw"):
                    m = copy.deepcopy(m)
                    m.data = bytes([128]) * len(m.data)   # uniform grey: no features at all
                m.header.stamp = st
                w.write(topic, m, st)
    info.update(bag=out, dir=d)
    return info


def _stamp_kind(info, t):
    k = int(round((t - info["t0"]) / info["dt"]))
    return info["kinds"][k] if 0 <= k < len(info["kinds"]) else None


def test_lost_skips_integration_and_resumes_after_relocalization(lost_bag, roscore, rospy_client,
                                                                  start_process, tmp_path):
    rospy = rospy_client
    import yaml
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import PointCloud2
    from mdr_slam.conversions import pose_stamped_to_matrix
    from mdr_slam_msgs.msg import TrackingState
    from mdr_slam_msgs.srv import SaveMap
    from mdr_slam.io import cloud_xyz, read_cloud, read_tum
    from scipy.spatial import cKDTree

    d = str(tmp_path)
    fusion = yaml.safe_load(open(os.path.join(ROOT, "src", "mdr_slam", "config", "fusion.yaml")))
    fusion.update(map_path=os.path.join(d, "auto.ply"), map_dir=d, autosave_period=0.0,
                  resume=False,
                  clean_every=0, publish_rate=2.0, diagnostics_period=0.5,
                  # waits for tf as the depth node does: a cloud stamped while LOST then reaches
                  # the LOST gate instead of failing its pose lookup first (tf of the relocalized
                  # pose a moment late: CI once saw 3 LOST clouds and "skipped: lost" 0)
                  tf_timeout=5.0,
                  # every cloud reaches the gate: with the default queue a busy node drops the
                  # oldest waiting clouds, and the few stamped while LOST come first in the burst
                  # the depth node sends after relocalization (CI once received 71 of 152 clouds,
                  # none of the 4 LOST ones, and "skipped: lost" stayed 0)
                  cloud_queue=1000)
    depth = yaml.safe_load(open(os.path.join(ROOT, "src", "mdr_slam", "config", "depth.yaml")))
    depth.update(tracking_state_topic="",   # no LOST pause: the fusion node must gate (3.)
                 tf_timeout=5.0,   # waits for the relocalized pose: LOST frames get interpolated
                 temporal=False)   # every matched frame gives a cloud (no filter reset on the jump)
    for name, p in (("fusion", fusion), ("depth", depth)):
        with open(os.path.join(d, name + ".yaml"), "w") as f:
            yaml.safe_dump(p, f)

    cloud_msgs = []   # the first non-empty cloud, sent again stamped while LOST (3.)
    states, clouds, diag, poses = [], [], [], []   # (stamp, state, wall), non-empty cloud stamps,
    #                       (wall, fusion diagnostics {key: value}), (stamp, 4x4 T_map_cam) of ORB

    def on_diag(m):
        for s in m.status:
            if s.name.startswith("fusion_node"):
                diag.append((time.time(), {kv.key: kv.value for kv in s.values}))
    def on_state(m):
        states.append((m.header.stamp.to_sec(), m.state, time.time()))

    def on_cloud(m):
        if m.width * m.height:
            clouds.append(m.header.stamp.to_sec())
            if not cloud_msgs:
                cloud_msgs.append(m)

    def on_pose(m):
        poses.append((m.header.stamp.to_sec(), pose_stamped_to_matrix(m)))
    subs = [rospy.Subscriber("/mdr/tracking_state", TrackingState, on_state),
            rospy.Subscriber("/mdr/pose", PoseStamped, on_pose),
            rospy.Subscriber("/mdr/depth/points", PointCloud2, on_cloud),
            rospy.Subscriber("/diagnostics", DiagnosticArray, on_diag)]
    t_start = time.time()
    launch = start_process(["roslaunch", "mdr_slam", "mdr.launch", "bag:=" + lost_bag["bag"],
                            "pose_source:=orb", "rate:=%.2f" % PLAY, "delay:=4.0", "respawn:=false",
                            "keep_alive:=true",   # the clock (and diagnostics) go on after the bag
                            "fusion_params:=" + os.path.join(d, "fusion.yaml"),
                            "depth_params:=" + os.path.join(d, "depth.yaml")], "launch")
    n = len(lost_bag["kinds"])
    t_last = lost_bag["t0"] + (n - 1) * lost_bag["dt"]
    try:
        wait_for(lambda: states and states[-1][0] >= t_last - 1e-3, 30 + 2.0 * n / RATE / PLAY,
                 0.2)
        # the fusion node works through its queue of clouds (every cloud is queued here, and a
        # loaded machine integrates more slowly than the bag plays): its counters settle
        def counts(v):
            return {k: x for k, x in v.items() if k.startswith(("clouds ", "skipped: "))}

        def settled(quiet=8.0):
            if not diag or time.time() - diag[-1][0] > 2.0:
                return False
            last = counts(diag[-1][1])
            changed = [w for w, v in diag if counts(v) != last]
            return time.time() - max(changed, default=diag[0][0]) > quiet
        assert wait_for(settled, 240, 0.5), "the fusion node never settled: %s" % [
            (round(w - t_start, 1), counts(v)) for w, v in diag[-3:]]
        # 3. (below) needs a cloud stamped while LOST at the gate. The pipeline's come from the
        # few frames at the loss's onset that still get a pose, which a busy depth node may drop
        # (CI once: 145 clouds, none stamped while LOST); one of its clouds, stamped inside the
        # LOST stretch, always gets there
        lost_st = sorted(t for t, s, _w in states if s == TrackingState.LOST)
        assert lost_st and cloud_msgs, (len(lost_st), len(clouds))
        m = copy.deepcopy(cloud_msgs[0])
        m.header.stamp = rospy.Time.from_sec(lost_st[len(lost_st) // 2])
        pub = rospy.Publisher("/mdr/depth/points", PointCloud2, queue_size=1)
        subs.append(pub)
        assert wait_for(lambda: any("fusion_node" in c.endpoint_id for c in pub.impl.connections),
                        30, 0.1), "the fusion node never subscribed to the test's cloud"
        skipped_before = int(diag[-1][1].get("skipped: lost", 0))
        pub.publish(m)
        assert wait_for(lambda: int(diag[-1][1].get("skipped: lost", 0)) > skipped_before, 60,
                        0.2), "the fusion node did not skip a cloud stamped while LOST: %s" % (
                            counts(diag[-1][1]),)
        rospy.wait_for_service("/fusion_node/save_map", 10)
        r = rospy.ServiceProxy("/fusion_node/save_map", SaveMap)(os.path.join(d, "map.ply"), "")
        assert r.success, r.message
    finally:
        for s in subs:
            s.unregister()
    out = launch.output()
    print("run %.1f s; %d states, %d clouds" % (time.time() - t_start, len(states), len(clouds)))
    assert states, out[-3000:]
    kinds = [(_stamp_kind(lost_bag, t), s) for t, s, _w in states]
    blank = [s for k, s in kinds if k == "blank"]
    track = [s for k, s in kinds if k == "track"]
    print("states: track %s, blank %s, unmapped %s, kidnap %s" % (
        np.bincount(track, minlength=4), np.bincount(blank, minlength=4),
        np.bincount([s for k, s in kinds if k == "unmapped"], minlength=4),
        np.bincount([s for k, s in kinds if k == "kidnap"], minlength=4)))
    # 1. the real tracker tracks the first part and goes LOST on the corridor and blank frames
    # (a busy tracker drops the oldest waiting pair: on a loaded machine it sees 70-100 % of them)
    assert len(track) > 0.5 * A and np.mean(np.isin(track, (1, 3))) > 0.9, kinds
    assert blank.count(TrackingState.LOST) >= BLANK // 2, kinds
    unmapped = [s for k, s in kinds if k == "unmapped"]
    assert unmapped and all(s == TrackingState.LOST for s in unmapped), kinds   # no false reloc
    # 2. it relocalizes on the kidnapped (already mapped) frames
    lost_t = [t for t, s, _w in states if s == TrackingState.LOST]
    back = [(t, w) for t, s, w in states if s in (1, 3) and lost_t and t > min(lost_t)]
    assert back, "the tracker never relocalized after LOST\n" + out[-3000:]
    t_reloc, w_reloc = back[0]
    assert _stamp_kind(lost_bag, t_reloc) == "kidnap", (t_reloc, kinds)

    # 3. nothing stamped while LOST is integrated. The depth node's own LOST pause is off in this
    # test (depth tracking_state_topic ""), so it matches the LOST frames too and publishes a cloud
    # whenever tf gives it a pose: the fusion node alone must skip them.
    st = sorted((t, s) for t, s, _w in states)

    def state_at(t):
        prev = [s for ts, s in st if ts <= t + 1e-6]
        return prev[-1] if prev else None
    lost_clouds = [t for t in clouds if state_at(t) in (0, 2)]
    assert diag, "no fusion diagnostics\n" + out[-3000:]
    final = diag[-1][1]
    skipped_lost = int(final.get("skipped: lost", 0))
    print("clouds %d (stamped while LOST %d: %s), fusion: integrated %s, received %s, %s" % (
        len(clouds), len(lost_clouds), lost_clouds, final.get("clouds integrated"),
        final.get("clouds received"),
        ", ".join("%s %s" % kv for kv in sorted(final.items()) if kv[0].startswith("skipped"))))
    # every cloud reaches the gate (cloud_queue): each one stamped while LOST is skipped
    assert skipped_lost >= len(lost_clouds), "the fusion node skipped %d of the clouds stamped " \
        "while LOST %s" % (skipped_lost, lost_clouds)
    c = read_cloud(r.path)
    P = cloud_xyz(c)
    first = np.asarray(c["first_seen"], float)
    assert len(P) > 500 and np.all(np.isfinite(P))
    t_lost = min(lost_t)
    in_lost = (first > t_lost - 1e-6) & (first < t_reloc - 1e-6)
    assert not in_lost.any(), "%d map points from clouds stamped while LOST (%s)" % (
        in_lost.sum(), np.unique(first[in_lost]))
    # unsmeared: the relocalized frames revisit mapped places, so what they add lies on the map
    # built before the loss (a cloud posed between the lost and the relocalized pose would not)
    conf = np.asarray(c["confidence"]) >= 2
    old, new = P[first < t_lost], P[(first >= t_reloc - 1e-6) & conf]
    dist, _ = cKDTree(old).query(new)
    print("map %d points: %d before LOST, %d after relocalization, distance of these to the old "
          "map: median %.3f m, p95 %.3f m" % (len(P), len(old), len(new), np.median(dist),
                                                np.percentile(dist, 95)))
    assert len(new) > 50, len(new)
    # measured 0.035-0.123 m (the depth filter is off here); the LOST window itself is checked above
    assert np.percentile(dist, 95) < 0.25, "smeared map after relocalization"

    # 4. integration resumes after relocalization: clouds stamped after it come and the fusion
    # node's integrated count grows after the relocalization was seen
    after = [t for t in clouds if t >= t_reloc]
    assert len(after) >= 5, (len(after), t_reloc)
    at_reloc = [int(v.get("clouds integrated", 0)) for w, v in diag if w <= w_reloc]
    n_at = at_reloc[-1] if at_reloc else 0
    assert int(final.get("clouds integrated", 0)) >= n_at + 5, (n_at, final)
    assert "Traceback" not in out, out[-3000:]

    # 5. on the sample's ground truth. The ORB map frame is aligned to it by the tracked part
    # (Umeyama SE(3)); then the relocalized poses lie on the true poses of the replayed frames and
    # the map points added after relocalization on the true surfaces as well as the ones before
    from evo.core.geometry import umeyama_alignment
    gt = read_tum(os.path.join(lost_bag["sample"], "groundtruth.tum"))
    G = gt.matrices()

    def truth(t):   # the ground-truth pose of the sample frame played at stamp t
        k = int(round((t - lost_bag["t0"]) / lost_bag["dt"]))
        j = int(np.argmin(np.abs(gt.stamps - lost_bag["source_stamps"][k])))
        assert abs(gt.stamps[j] - lost_bag["source_stamps"][k]) < 1e-3
        return G[j]
    tracked = [(t, T) for t, T in poses if _stamp_kind(lost_bag, t) == "track"]
    relocd = [(t, T) for t, T in poses
              if _stamp_kind(lost_bag, t) == "kidnap" and t >= t_reloc - 1e-6]
    assert len(tracked) > 0.5 * A and len(relocd) >= 5, (len(tracked), len(relocd))
    E = np.array([T[:3, 3] for _t, T in tracked])
    Gt = np.array([truth(t)[:3, 3] for t, _T in tracked])
    R, tr, _c = umeyama_alignment(E.T, Gt.T, False)

    def to_gt(X):
        return X @ R.T + tr
    ate_track = np.linalg.norm(to_gt(E) - Gt, axis=1)
    err_reloc = np.linalg.norm(to_gt(np.array([T[:3, 3] for _t, T in relocd])) -
                               np.array([truth(t)[:3, 3] for t, _T in relocd]), axis=1)
    gt_map = cloud_xyz(read_cloud(os.path.join(lost_bag["sample"], "gt_map.ply")))
    tree = cKDTree(gt_map)
    d_old, _ = tree.query(to_gt(P[(first < t_lost) & conf]))
    d_new, _ = tree.query(to_gt(new))
    print("ground truth: tracked part ATE median %.3f m max %.3f m (%d poses); relocalized poses "
          "(%d) off by median %.3f m, max %.3f m; map points to gt_map: before LOST median %.3f "
          "p95 %.3f m (%d), after relocalization median %.3f p95 %.3f m (%d)" % (
              np.median(ate_track), ate_track.max(), len(E), len(relocd), np.median(err_reloc),
              err_reloc.max(), np.median(d_old), np.percentile(d_old, 95), len(d_old),
              np.median(d_new), np.percentile(d_new, 95), len(d_new)))
    # measured (8 runs while writing this test, loaded 2-core machine, the test at nice 19):
    # tracked ATE median 0.021-0.038 m; relocalized poses off by median 0.022-0.037 m, max
    # 0.042-0.064 m; map points to gt_map, median: before LOST 0.050-0.085 m, after
    # relocalization 0.077-0.128 m (1.2-1.8x).
    # Their p95 (0.24-0.82 m) is the ELAS-only depth noise of the surfaces in view (the depth
    # filter is off here), not the pose: it is not bounded here
    assert np.median(ate_track) < 0.10, "the tracked part does not fit the ground truth"
    assert np.median(err_reloc) < 0.10 and err_reloc.max() < 0.25, \
        "relocalized poses off the ground truth: %s" % err_reloc
    assert np.median(d_new) < max(0.20, 2.0 * np.median(d_old)), "smeared map after relocalization"
