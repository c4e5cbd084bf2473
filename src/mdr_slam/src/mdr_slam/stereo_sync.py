"""Stereo pairing by approximate time: the left and right images of one exposure, as drivers stamp
them (equal stamps, or the right a few milliseconds after the left).

One policy for every consumer, so a bag pairs offline (``mdr run``) exactly as the nodes pair it
live: each left image is paired with the right image nearest in stamp when the two are at most
``tolerance`` apart (message_filters' ApproximateTime policy, reduced to two streams). The
tolerance follows the camera: by default a fraction of the frame period measured from the left
stamps (``AUTO_TOLERANCE_FRACTION``), below half a period so that no image can be nearest to two
partners. An image that can no longer find a partner (a newer image on the other side is already
further than the tolerance) is dropped and counted. When no pair forms while images arrive,
:meth:`StereoSync.stall_report` tells the offsets it sees, for the node's warning (rtabmap's "did
not receive data since 5 seconds" is the model).
"""
from __future__ import annotations

import bisect
from collections import deque
from typing import Any, Deque, Dict, List, Optional, Tuple

import numpy as np

__all__ = ["StereoSync", "AUTO_TOLERANCE_FRACTION", "STALL_WARNING_S"]

AUTO_TOLERANCE_FRACTION = 0.4   # of the frame period: a ZED's few-ms right lag pairs, a neighbour never does
DEFAULT_PERIOD = 0.05           # s, until two left stamps have been seen (20 Hz)
STALL_WARNING_S = 5.0           # s of images without a pair before a warning
_TIME_JUMP = 1.0                # s back on one side: a new timeline (a looping bag), queues cleared

Pair = Tuple[float, Any, float, Any]   # left stamp, left item, right stamp, right item


class StereoSync:
    """Pairs left and right items by stamp. ``add`` returns the pairs completed, oldest first.

    ``tolerance`` (s): the largest stamp difference of a pair; 0 = ``AUTO_TOLERANCE_FRACTION`` of
    the median left period. ``queue_size``: items kept per side while waiting for a partner.
    """

    def __init__(self, tolerance: float = 0.0, queue_size: int = 10):
        self.tolerance_setting = float(tolerance)
        self.queue_size = max(1, int(queue_size))
        self.q: Dict[str, List[Tuple[float, Any]]] = {"left": [], "right": []}
        self.periods: Deque[float] = deque(maxlen=50)
        self.offsets: Deque[float] = deque(maxlen=50)   # per right: its stamp - the nearest left's
        self.last_left: Optional[float] = None
        self.dropped = {"left": 0, "right": 0}
        self.received = {"left": 0, "right": 0}
        self.pairs = 0
        self._since_pair = {"left": 0, "right": 0}
        self._waiting_since: Optional[float] = None   # caller's clock: last pair, or first image

    # ------------------------------------------------------------------ the policy
    @property
    def tolerance(self) -> float:
        if self.tolerance_setting > 0:
            return self.tolerance_setting
        period = float(np.median(self.periods)) if self.periods else DEFAULT_PERIOD
        return AUTO_TOLERANCE_FRACTION * period

    def add(self, side: str, stamp: float, item: Any, now: Optional[float] = None) -> List[Pair]:
        """Queue ``item`` of ``side`` ('left' or 'right') stamped ``stamp`` (s); the pairs this
        completes. ``now``: the caller's monotonic clock, for :meth:`stall_report`."""
        if side not in self.q:
            raise ValueError("side must be 'left' or 'right', got %r" % side)
        stamp = float(stamp)
        q = self.q[side]
        if q and stamp < q[-1][0] - _TIME_JUMP:
            self.reset()
            q = self.q[side]
        if side == "left":
            if self.last_left is not None and stamp > self.last_left:
                self.periods.append(stamp - self.last_left)
            self.last_left = stamp if self.last_left is None else max(stamp, self.last_left)
        self.received[side] += 1
        self._since_pair[side] += 1
        if now is not None and self._waiting_since is None:
            self._waiting_since = now
        q.insert(bisect.bisect_right([s for s, _ in q], stamp), (stamp, item))   # arrival may be out of order
        if len(q) > self.queue_size:
            q.pop(0)
            self.dropped[side] += 1
        if side == "right" and self.q["left"]:
            ls = np.array([s for s, _ in self.q["left"]])
            self.offsets.append(float(stamp - ls[np.argmin(np.abs(ls - stamp))]))
        out = self._match()
        if out and now is not None:
            self._waiting_since = now
        return out

    def _match(self) -> List[Pair]:
        out: List[Pair] = []
        L, R = self.q["left"], self.q["right"]
        tol = self.tolerance
        while L and R:
            tl = L[0][0]
            j = min(range(len(R)), key=lambda k: abs(R[k][0] - tl))
            if abs(R[j][0] - tl) <= tol:
                # rights older than the partner had no left of their own (older lefts are gone)
                self.dropped["right"] += j
                tr, ir = R.pop(j)
                del R[:j]
                _, il = L.pop(0)
                out.append((tl, il, tr, ir))
                continue
            if R[-1][0] > tl + tol:          # every later right is further still: no partner
                L.pop(0)
                self.dropped["left"] += 1
                continue
            tr = R[0][0]
            if L[-1][0] > tr + tol and all(abs(s - tr) > tol for s, _ in L):
                R.pop(0)
                self.dropped["right"] += 1
                continue
            break                            # the partner may still come
        if out:
            self.pairs += len(out)
            self._since_pair = {"left": 0, "right": 0}
        return out

    def reset(self) -> None:
        """Forget the waiting items and the measured period (time went back: a new timeline)."""
        self.q = {"left": [], "right": []}
        self.periods.clear()
        self.offsets.clear()
        self.last_left = None

    # ------------------------------------------------------------------ diagnostics
    def stall_report(self, now: float) -> Optional[str]:
        """A sentence on why no pair formed, when images kept arriving for ``STALL_WARNING_S``
        seconds of the caller's clock ``now`` (as given to :meth:`add`) without one; else None."""
        n_l, n_r = self._since_pair["left"], self._since_pair["right"]
        if self._waiting_since is None or n_l + n_r < 2 or \
                now - self._waiting_since < STALL_WARNING_S:
            return None
        if not self.offsets:
            seen = "no stamp offsets (one side silent)"
        else:
            o = 1e3 * np.asarray(self.offsets)
            seen = "right - left stamp offsets %+.1f ms median (%+.1f .. %+.1f)" % (
                float(np.median(o)), float(o.min()), float(o.max()))
        return ("no stereo pair for %.0f s: %d left and %d right images received, %s, "
                "tolerance %.1f ms" % (now - self._waiting_since, n_l, n_r, seen,
                                       1e3 * self.tolerance))
