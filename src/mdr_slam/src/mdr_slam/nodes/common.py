"""Helpers shared by the nodes: parameters, throttled warnings, time checks, static tf."""
from __future__ import annotations

import numpy as np

from ..geometry import parse_transform  # noqa: F401  (the nodes' transform arguments)


def get_params(defaults: dict, ns: str = "~") -> dict:
    """Read every key of ``defaults`` from the parameter server (private namespace by default)."""
    import rospy
    return {k: rospy.get_param(ns + k, v) for k, v in defaults.items()}


class Throttled:
    """rospy log calls limited to one per ``period`` seconds per key (logwarn_throttle keys on the
    call site only; here the key is the message kind, so distinct problems are all reported)."""

    def __init__(self, period: float = 5.0):
        self.period = period
        self._last = {}
        self.counts = {}

    def __call__(self, key: str, text: str, level: str = "warn") -> None:
        import re
        import time
        import rospy
        self.counts[key] = self.counts.get(key, 0) + 1
        now = time.monotonic()
        # throttled per kind and wording (numbers aside): a truncated image does not hide a wrong
        # encoding reported under the same kind a moment later
        slot = key + "|" + re.sub(r"[-+]?[0-9][0-9.eE+-]*", "#", text)[:80]
        if now - self._last.get(slot, -1e9) >= self.period:
            if len(self._last) > 500:   # wordings that never repeat must not grow without bound
                self._last.clear()
            self._last[slot] = now
            n = self.counts[key]
            suffix = " (%d times so far)" % n if n > 1 else ""
            getattr(rospy, "log" + level)("%s%s", text, suffix)


class StampGuard:
    """Detects time going backwards (a looping bag, a restarted clock) and duplicated stamps."""

    def __init__(self):
        self.last = None

    def check(self, t: float) -> str:
        """'ok', 'duplicate' or 'backwards' (after which the guard restarts from ``t``)."""
        if self.last is None or t > self.last:
            self.last = t
            return "ok"
        if t == self.last:
            return "duplicate"
        self.last = t
        return "backwards"


class StampRateLimiter:
    """Keeps at most ``rate`` Hz of a stream, chosen by message stamps (so it follows sim time and
    a bag played faster or slower): an item is due once its stamp reaches ``next_due``, which then
    advances by one period (20 Hz in, 12 Hz out: 3 of every 5 pairs, evenly spread). A stamp more
    than a second before the previous one (a looping bag) starts again. ``rate <= 0``: keep all."""

    def __init__(self, rate: float):
        self.period = 1.0 / float(rate) if float(rate) > 0 else 0.0
        self.next_due = None
        self.last = None

    def skip(self, t: float) -> bool:
        if self.last is not None and t < self.last - 1.0:
            self.next_due = None
        self.last = t
        if self.period <= 0:
            return False
        if self.next_due is not None and t < self.next_due - 0.2 * self.period:
            return True
        nxt = t if self.next_due is None else max(self.next_due, t - self.period)
        self.next_due = nxt + self.period
        return False


class ClockWatch:
    """Detects ROS time itself jumping back (a looping bag, a restarted sim clock): only then is
    an older stamp a new timeline (reset); without it an older stamp is one stale message (skip).
    The first message of a new lap can arrive just before the clock jumps: it is skipped as
    stale and the reset comes with the next one."""

    def __init__(self):
        self.last = -np.inf

    def jumped(self) -> bool:
        import rospy
        now = rospy.Time.now().to_sec()
        j = now < self.last - 1e-3
        self.last = now
        return j
