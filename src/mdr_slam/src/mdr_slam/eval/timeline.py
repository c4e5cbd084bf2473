"""Per-window figures of a long run: series of (time, value) cut into consecutive windows.

Shared by the live benchmark (``mdr bench BAG``: wall time since the start, series from the
nodes' topics and ``/diagnostics``) and the offline pipeline (``mdr run --window S``: bag time
since the first frame, :class:`RunTimeline`), so both cut and name their windows alike. A row
holds ``t0``/``t1`` (s) and whichever of these it measured:

- ``tracking_ms``: {median, p90, n} of the tracker's wall time per stereo pair in the window;
- ``frames``, ``frames_tracked``, ``tracked_share``: stereo pairs handled by the tracker in the
  window, those OK or RELOCALIZED, and their share (None without frames);
- ``keyframes``, ``sparse_map_points``, ``loop_closures_total``: the sparse map at the window's
  end (keyframes alive, not culled); ``loop_closures``: closed in the window;
- ``map_hz``: map integrations per second in the window; ``dense_map_points``;
- ``rss_mb``: a number (one process) or {node: MB, ..., "total": MB}.

Windows are ``[t0, t1)`` except the last, which holds its end: a run's last frame counts.
"""
from __future__ import annotations

import json
import os
from collections import OrderedDict
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

__all__ = ["TRACKED_STATES", "window_bounds", "Series", "Tracked", "increments", "process_rss_mb",
           "RunTimeline", "pipeline_gauges", "timeline_md", "plot_timeline", "write_timeline"]

TRACKED_STATES = ("OK", "RELOCALIZED", 1, 3)   # names (offline) and TrackingState codes (live)


def window_bounds(elapsed: float, window: float, min_len: float = 0.0) -> List[Tuple[float, float]]:
    """Consecutive ``(t0, t1)`` of ``window`` s from 0 to ``elapsed``; a last window shorter than
    ``min_len`` (or empty) is left out."""
    if window <= 0:
        raise ValueError("window must be > 0 s, got %r" % (window,))
    out = []
    k = 0
    while k * window < elapsed:
        a = k * window
        b = min(a + window, elapsed)
        if b - a < min_len or b <= a:
            break
        out.append((float(a), float(b)))
        k += 1
    return out


class Series:
    """A time series cut into windows: ``Series([(t, value), ...])``, or ``Series(times)`` for
    events (each worth 1). Built once (arrays), queried per window."""

    def __init__(self, series=()):
        series = list(series)
        if series and np.ndim(series[0]) == 0:
            self.t = np.asarray(series, dtype=float)
            self.v = np.ones(len(self.t))
        else:
            self.t = np.asarray([s[0] for s in series], dtype=float)
            self.v = np.asarray([s[1] for s in series], dtype=float)
        self._inc = None

    def __len__(self) -> int:
        return len(self.t)

    def mask(self, a: float, b: float, last: bool = False) -> np.ndarray:
        """``a <= t < b`` (``<= b`` for the last window)."""
        return (self.t >= a) & ((self.t <= b) if last else (self.t < b))

    def count(self, a: float, b: float, last: bool = False) -> int:
        return int(np.count_nonzero(self.mask(a, b, last)))

    def values(self, a: float, b: float, last: bool = False) -> np.ndarray:
        return self.v[self.mask(a, b, last)]

    def at(self, b: float, inclusive: bool = True) -> Optional[float]:
        """The last value reported at or before ``b`` (before it: not ``inclusive``), a gauge's
        value at a window's end (map size, RSS, keyframes)."""
        seen = self.v[(self.t <= b) if inclusive else (self.t < b)]
        return float(seen[-1]) if len(seen) else None

    def increase(self, a: float, b: float, last: bool = False) -> float:
        """How much a cumulative counter grew by reports in the window (restarts counted, see
        :func:`increments`)."""
        if self._inc is None:
            self._inc = increments(self.v)
        return float(self._inc[self.mask(a, b, last)].sum())


def increments(values) -> np.ndarray:
    """Per-report increments of a cumulative counter (values, or [(t, value)]); the first report
    adds nothing; a drop means the node (or the tracker) restarted and counts from zero again,
    so the new value is the increment."""
    v = np.asarray([c[1] for c in values] if len(values) and np.ndim(values[0]) else values,
                   dtype=float)
    if len(v) == 0:
        return v
    d = np.diff(v, prepend=v[0])
    return np.where(d < 0, v, d)


def _num(x, nd=1):
    return None if x is None or not np.isfinite(x) else round(float(x), nd)


class Tracked:
    """The tracker's per-pair record [(t, state, wall ms), ...] (states: names or TrackingState
    codes) cut into windows."""

    def __init__(self, tracked=()):
        tracked = list(tracked)
        self.t = np.asarray([x[0] for x in tracked], dtype=float)
        self.ok = np.asarray([x[1] in TRACKED_STATES for x in tracked], dtype=bool)
        self.ms = np.asarray([np.nan if x[2] is None else x[2] for x in tracked], dtype=float)

    def figures(self, a: float, b: float, last: bool = False) -> "OrderedDict":
        """tracking_ms {median, p90, n}, frames, frames_tracked and tracked_share (OK and
        RELOCALIZED over all states received) of the window."""
        m = (self.t >= a) & ((self.t <= b) if last else (self.t < b))
        ms = self.ms[m]
        ms = ms[np.isfinite(ms)]
        n, n_ok = int(np.count_nonzero(m)), int(np.count_nonzero(self.ok[m]))
        out = OrderedDict()
        out["tracking_ms"] = OrderedDict(
            median=_num(np.median(ms)) if len(ms) else None,
            p90=_num(np.percentile(ms, 90)) if len(ms) else None, n=int(len(ms)))
        out["frames"] = n
        out["frames_tracked"] = n_ok
        out["tracked_share"] = round(n_ok / float(n), 3) if n else None
        return out


def process_rss_mb(pid: Optional[int] = None) -> Optional[float]:
    """Resident memory (VmRSS) of a process, MB (1e6 bytes), from /proc; None where there is
    none (not Linux)."""
    try:
        with open("/proc/%s/status" % (pid or "self")) as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024 / 1e6
    except (IOError, OSError, ValueError, IndexError):
        pass
    return None


class RunTimeline:
    """Records an offline run frame by frame (bag time since the first frame) and cuts it into
    windows.

    Call ``before_frame(stamp)`` before a frame is processed and ``frame(stamp, state, ms)``
    after. ``sample()`` returns the gauges of that moment, e.g. {"rss_mb", "keyframes",
    "sparse_map_points", "loop_closures_total", "dense_map_points", "integrations"}
    (``integrations``: a cumulative count, reported per second as map_hz); it is called before
    the first frame, when a frame passes a window's end (so it describes the window that ended)
    and at the end by ``rows()``.
    """

    def __init__(self, window: float, sample: Callable[[], Dict[str, Optional[float]]]):
        if not window > 0:
            raise ValueError("window must be > 0 s, got %r" % (window,))
        self.window = float(window)
        self.sample = sample
        self.t_first: Optional[float] = None
        self.t_last = 0.0
        self.tracked: List[tuple] = []                 # (t, state, ms)
        self.gauges: Dict[str, List[tuple]] = {}       # key -> [(t, value)]
        self._next_end = self.window

    def _take(self, *times: float) -> None:
        vals = self.sample() or {}
        for t in times:
            for k, v in vals.items():
                if v is not None:
                    self.gauges.setdefault(k, []).append((t, float(v)))

    def before_frame(self, stamp: float) -> None:
        if self.t_first is None:
            self.t_first = float(stamp)
            self._take(0.0)
            return
        t = float(stamp) - self.t_first
        ends = []
        while t >= self._next_end:   # a gap in the bag: its windows get the same gauges
            ends.append(self._next_end)
            self._next_end += self.window
        if ends:
            self._take(*ends)

    def frame(self, stamp: float, state, tracking_ms: Optional[float]) -> None:
        if self.t_first is None:
            self.before_frame(stamp)
        t = float(stamp) - self.t_first
        self.t_last = max(self.t_last, t)
        self.tracked.append((t, state, tracking_ms))

    def rows(self) -> List["OrderedDict"]:
        """The windows from the first frame to the last (the gauges sampled once more)."""
        if self.t_first is None:
            return []
        self._take(self.t_last)
        bounds = window_bounds(self.t_last, self.window) or [(0.0, self.t_last)]
        tracked = Tracked(self.tracked)
        g = {k: Series(v) for k, v in self.gauges.items()}
        none = Series()
        out = []
        for i, (a, b) in enumerate(bounds):
            row = OrderedDict(t0=round(a, 3), t1=round(b, 3))
            row.update(tracked.figures(a, b, last=i == len(bounds) - 1))
            row["rss_mb"] = _num(g.get("rss_mb", none).at(b))
            for k in ("keyframes", "sparse_map_points", "loop_closures_total", "dense_map_points"):
                v = g.get(k, none).at(b)
                row[k] = None if v is None else int(v)
            # the gauges are sampled at the window ends: a window's growth is from the report
            # at its start to the one at its end
            row["loop_closures"] = int(g.get("loop_closures_total", none).increase(
                a + 1e-9, b, True))
            n_int = g.get("integrations", none).increase(a + 1e-9, b, True)
            row["map_hz"] = round(n_int / (b - a), 2) if b > a else None
            out.append(row)
        return out


# ---------------------------------------------------------------------- reports
def _fmt(x) -> str:
    return "-" if x is None else ("%g" % x if isinstance(x, float) else str(x))


def timeline_md(rows: Sequence[dict], nodes: Sequence[str] = (),
                extra: Sequence[Tuple[str, Callable[[dict], object]]] = (),
                labels: Optional[Sequence[str]] = None) -> List[str]:
    """Markdown table lines of timeline rows: time, ``extra`` columns ((header, row -> value)),
    RSS (per node, named ``labels`` in the header, and total when ``nodes``), tracking ms
    median / p90, frames tracked / frames (share), keyframes alive, sparse map points, loop
    closures in the window, map rate, dense map points. What a row lacks shows as -."""
    names = list(labels or nodes)
    rss_head = "RSS MB " + " / ".join(names + ["total"]) if nodes else "RSS MB"
    heads = ["t (s)"] + [h for h, _ in extra] + [
        rss_head, "tracking ms median / p90", "frames tracked / frames (share)", "keyframes",
        "sparse map points", "loop closures", "map Hz", "dense map points"]
    lines = ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for w in rows:
        rss = w.get("rss_mb")
        if isinstance(rss, dict):
            rss_s = " / ".join(_fmt(rss.get(n)) for n in list(nodes) + ["total"])
        else:
            rss_s = _fmt(rss)
        tm = w.get("tracking_ms") or {}
        share = w.get("tracked_share")
        cells = ["%g-%g" % (w["t0"], w["t1"])] + [_fmt(fn(w)) for _, fn in extra] + [
            rss_s, "%s / %s" % (_fmt(tm.get("median")), _fmt(tm.get("p90"))),
            "%s / %s (%s)" % (_fmt(w.get("frames_tracked")), _fmt(w.get("frames")),
                              "-" if share is None else "%.0f %%" % (100 * share)),
            _fmt(w.get("keyframes")), _fmt(w.get("sparse_map_points")),
            _fmt(w.get("loop_closures")), _fmt(w.get("map_hz")),
            _fmt(w.get("dense_map_points"))]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _col(rows, key, sub=None):
    out = []
    for w in rows:
        v = w.get(key)
        if sub is not None:
            v = v.get(sub) if isinstance(v, dict) else None
        out.append(np.nan if v is None else float(v))
    return np.asarray(out, dtype=float)


def plot_timeline(rows: Sequence[dict], path: str, title: str = "",
                  nodes: Sequence[str] = (), time_label: str = "time (s)") -> Optional[str]:
    """Five panels over the windows (steps): RSS (per node and total, or the process); tracking
    ms median and p90; share of frames tracked; keyframes alive and sparse map points; map rate
    (integrations per second). Returns ``path``, or None without rows."""
    if not rows:
        return None
    from .plot import _pyplot
    plt = _pyplot()
    edges = [w["t0"] for w in rows] + [rows[-1]["t1"]]
    scale, unit = (60.0, "min") if edges[-1] >= 600 else (1.0, "s")
    x = np.asarray(edges) / scale

    def step(ax, y, **kw):
        y = np.asarray(y, dtype=float)
        return ax.step(x, np.append(y, y[-1] if len(y) else np.nan), where="post", **kw)

    fig, axes = plt.subplots(5, 1, figsize=(9, 12), dpi=100, sharex=True)
    ax = axes[0]
    if nodes:
        for n in nodes:
            step(ax, _col(rows, "rss_mb", n), label=n)
        step(ax, _col(rows, "rss_mb", "total"), color="k", label="total")
        ax.legend(loc="best", fontsize=8, ncol=4)
    else:
        step(ax, _col(rows, "rss_mb"), color="k", label="process")
    ax.set_ylabel("RSS (MB)")
    ax.set_ylim(bottom=0)
    ax = axes[1]
    step(ax, _col(rows, "tracking_ms", "median"), label="median")
    step(ax, _col(rows, "tracking_ms", "p90"), label="p90")
    ax.set_ylabel("tracking (ms / pair)")
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper left", fontsize=8)
    ax = axes[2]
    step(ax, 100.0 * _col(rows, "tracked_share"), color="tab:green")
    ax.set_ylim(-5, 105)
    ax.set_ylabel("frames tracked (%)")
    ax = axes[3]
    step(ax, _col(rows, "keyframes"), color="tab:blue")
    ax.set_ylabel("keyframes alive", color="tab:blue")
    ax.set_ylim(bottom=0)
    ax2 = ax.twinx()
    step(ax2, _col(rows, "sparse_map_points"), color="tab:orange", ls="--")
    ax2.set_ylabel("sparse map points (dashed)", color="tab:orange")
    ax2.set_ylim(bottom=0)
    loops = _col(rows, "loop_closures")
    for x0, x1, n in zip(x[:-1], x[1:], loops):
        if np.isfinite(n) and n > 0:
            ax.axvspan(x0, x1, color="tab:red", alpha=0.12, lw=0)
    if np.nansum(loops) > 0:
        ax.fill_between([], [], color="tab:red", alpha=0.12, label="window with a loop closure")
        ax.legend(loc="upper left", fontsize=8)
    ax = axes[4]
    step(ax, _col(rows, "map_hz"), color="tab:purple")
    ax.set_ylabel("map integrations / s")
    ax.set_ylim(bottom=0)
    ax.set_xlabel(time_label.replace("(s)", "(%s)" % unit))
    if title:
        axes[0].set_title(title)
    for a in axes:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def write_timeline(out_dir: str, rows: Sequence[dict], window: float, extra: Optional[dict] = None,
                   title: str = "") -> dict:
    """``out_dir/timeline.json`` ({"window_s", "windows": rows, ...extra}) and
    ``out_dir/timeline.png`` (bag time)."""
    from ..io import atomic_write
    doc = OrderedDict(window_s=float(window))
    doc.update(extra or {})
    doc["windows"] = list(rows)
    atomic_write(os.path.join(out_dir, "timeline.json"), json.dumps(doc, indent=2) + "\n",
                 mode="w")
    if rows:
        plot_timeline(rows, os.path.join(out_dir, "timeline.png"), title=title,
                      time_label="bag time (s)")
    return doc


def pipeline_gauges(pipe) -> Dict[str, Optional[float]]:
    """The gauges of an offline :class:`mdr_slam.pipeline.Pipeline` for :class:`RunTimeline`:
    this process's RSS, the sparse map (keyframes alive, map points, loop closures; with the
    built-in tracker), the dense map's points and the frames integrated so far."""
    out = OrderedDict(rss_mb=process_rss_mb(), dense_map_points=len(pipe.map),
                      integrations=pipe.counts["frames_integrated"])
    tracker = pipe.tracker
    mp = getattr(tracker, "map", None)
    if mp is not None and hasattr(mp, "good_keyframes"):
        with mp.lock:
            out["keyframes"] = len(mp.good_keyframes())
            out["sparse_map_points"] = int(mp.n_points)
            out["loop_closures_total"] = int(mp.n_loop_closures)
    elif tracker is not None:   # a backend without the map's figures (orbslam3)
        out["loop_closures_total"] = pipe.counts["loop_closures"]
    return out
