"""Process health for the nodes' /diagnostics: CPU %, RSS and an event-rate window (psutil).

One :class:`ProcessHealth` per node; its :meth:`ProcessHealth.add_to` writes the keys every
MDR-SLAM node reports (``cpu_percent``, ``rss_mb``, ``threads``) into a diagnostic_updater
status, so monitors (rqt_robot_monitor, ``mdr bench``) read the same names from all three nodes.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import threading
import time
from collections import deque

import rospy

try:
    import psutil
except ImportError:   # CPU % is then NaN and RSS comes from /proc
    psutil = None

__all__ = ["ProcessHealth", "RateWindow", "rss_bytes", "trim_heap"]

_LIBC = None


def trim_heap() -> bool:
    """Give the heap's free pages back to the system (glibc ``malloc_trim(0)``; False where that
    is not available). A node that allocates and frees large buffers per message from several
    threads (clouds of ~8k points, depth images) leaves free memory spread over malloc's arenas,
    which RSS keeps counting: a long run's RSS then creeps although the memory in use is flat
    (fusion node, 9-minute looped run: malloc in use ~70 MB flat, RSS +0.1 MB/min)."""
    global _LIBC
    if _LIBC is False:  # looked for before and not there (not glibc)
        return False
    try:
        if _LIBC is None:
            _LIBC = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return bool(_LIBC.malloc_trim(0))
    except (OSError, AttributeError):
        _LIBC = False
        return False


def rss_bytes() -> int:
    """Resident set size of this process in bytes (psutil, or /proc when psutil is missing)."""
    if psutil is not None:
        return int(psutil.Process().memory_info().rss)
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


class ProcessHealth:
    """CPU % (of one core, over the interval since the previous call, like ``top``) and RSS of
    this process. :meth:`add_to` also calls :func:`trim_heap` every ``trim_period`` seconds, so
    every node's RSS follows its memory in use."""

    def __init__(self, trim_period: float = 60.0):
        self._proc = None
        self.trim_period = float(trim_period)  # s between two trim_heap calls (0 = never)
        self._last_trim = time.monotonic()
        if psutil is not None:
            self._proc = psutil.Process()
            self._proc.cpu_percent(None)     # starts the interval

    def cpu_percent(self) -> float:
        """CPU use since the last call (100 = one full core); NaN without psutil."""
        return float(self._proc.cpu_percent(None)) if self._proc is not None else float("nan")

    def rss_mb(self) -> float:
        return rss_bytes() / 1e6

    def add_to(self, stat) -> None:
        """Add ``cpu_percent``, ``rss_mb`` and ``threads`` to a DiagnosticStatusWrapper."""
        stat.add("cpu_percent", "%.1f" % self.cpu_percent())
        stat.add("rss_mb", "%.1f" % self.rss_mb())
        stat.add("threads", str(threading.active_count()))
        now = time.monotonic()
        if self.trim_period > 0 and now - self._last_trim >= self.trim_period:
            self._last_trim = now
            trim_heap()


class RateWindow:
    """Events per second over the last ``window`` seconds (monotonic clock), thread-safe."""

    def __init__(self, window: float = 10.0):
        self.window = float(window)
        self._t = deque()
        self._lock = threading.Lock()
        self.t_start = time.monotonic()

    def tick(self) -> None:
        now = time.monotonic()
        with self._lock:
            self._t.append(now)
            self._trim(now)

    def _trim(self, now: float) -> None:
        while self._t and now - self._t[0] > self.window:
            self._t.popleft()

    def rate(self) -> float:
        now = time.monotonic()
        with self._lock:
            self._trim(now)
            span = min(self.window, max(1e-6, now - self.t_start))
            return len(self._t) / span


def update_diagnostics(updater) -> None:
    """``diagnostic_updater.Updater.update()`` that survives ROS time jumping back (a looping bag):
    the updater waits until ``last_time + period``, which lies in the future after a jump, so
    /diagnostics would go quiet for the bag's length. Reset it when now is before its last update.
    A tick that comes while the node shuts down (its publisher already closed) is dropped."""
    last = getattr(updater, "last_time", None)
    if last is not None and rospy.Time.now() < last:
        updater.last_time = rospy.Time(0)
    try:
        updater.update()
    except rospy.ROSException:
        if not rospy.is_shutdown():
            raise
