"""Stereo pairing by approximate time (mdr_slam.stereo_sync): the policy every node and the offline
runners share."""
from __future__ import annotations

import random

import pytest

from mdr_slam.stereo_sync import AUTO_TOLERANCE_FRACTION, STALL_WARNING_S, StereoSync

RATE = 20.0


def _stream(n, lag, drop_right=()):
    ev = []
    for k in range(n):
        t = 1.0 + k / RATE
        ev.append(("left", t, k))
        if k not in drop_right:
            ev.append(("right", t + lag, k))
    return ev


def _run(sync, events):
    pairs = []
    for i, (side, t, k) in enumerate(events):
        pairs += sync.add(side, t, k, now=i / (2 * RATE))
    return pairs


@pytest.mark.parametrize("lag", [0.0, 0.003, -0.004, 0.015])
def test_pairs_within_the_auto_tolerance(lag):
    s = StereoSync()
    pairs = _run(s, _stream(60, lag))
    assert len(pairs) == 60 and all(a == b for _, a, _, b in pairs)
    assert [p[1] for p in pairs] == list(range(60))   # oldest first
    assert s.tolerance == pytest.approx(AUTO_TOLERANCE_FRACTION / RATE)
    assert s.dropped == {"left": 0, "right": 0}


def test_half_a_period_apart_never_pairs_and_is_reported():
    s = StereoSync()
    events = _stream(200, 0.5 / RATE)
    pairs = _run(s, events)
    assert pairs == []
    assert s.dropped["left"] >= 190
    report = s.stall_report(len(events) / (2 * RATE))
    assert report is not None and "+25.0 ms median" in report and "tolerance 20.0 ms" in report
    assert s.stall_report(0.5 * STALL_WARNING_S) is None   # not yet 5 s without a pair


def test_fixed_tolerance_and_missing_partners():
    s = StereoSync(tolerance=0.03)
    pairs = _run(s, _stream(70, 0.025, drop_right={3, 10, 11, 40}))
    assert s.tolerance == 0.03
    assert len(pairs) == 66 and all(a == b for _, a, _, b in pairs)


def test_interleaving_across_sides_does_not_matter():
    for seed in range(4):
        rnd = random.Random(seed)
        L = [e for e in _stream(80, 0.003) if e[0] == "left"]
        R = [e for e in _stream(80, 0.003) if e[0] == "right"]
        ev = []
        while L or R:   # each side in its own order (one connection each), sides interleaved
            src = L if (L and (not R or rnd.random() < 0.5)) else R
            ev.append(src.pop(0))
        pairs = _run(StereoSync(queue_size=100), ev)
        assert len(pairs) == 80 and all(a == b for _, a, _, b in pairs)


def test_a_stale_left_does_not_block_the_stream():
    """An image whose partner never comes is dropped once a newer partner exists."""
    s = StereoSync()
    ev = _stream(30, 0.002, drop_right={5})
    pairs = _run(s, ev)
    assert len(pairs) == 29 and s.dropped["left"] == 1 and not s.q["left"]


def test_time_jumping_back_starts_over():
    s = StereoSync()
    _run(s, _stream(20, 0.0))
    s.add("left", 100.0, "x")
    assert s.add("left", 1.0, "a") == []   # a looping bag: queues cleared, no pairing across
    assert s.q["left"] == [(1.0, "a")]
    assert s.add("right", 1.001, "b") == [(1.0, "a", 1.001, "b")]


def test_rejects_unknown_side():
    with pytest.raises(ValueError):
        StereoSync().add("middle", 1.0, None)
