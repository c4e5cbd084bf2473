"""Memory debugging for long live runs (a debug option, off by default).

``MDR_MEMDEBUG=/path/file.jsonl`` in a node's environment (``mdr bench`` and ``roslaunch`` pass
their environment on) starts a daemon thread that appends one JSON line every
``MDR_MEMDEBUG_PERIOD`` seconds (default 60) with:

- ``rss_mb`` and the resident MB of ``/proc/self/smaps`` by kind of mapping: ``heap`` (the main
  glibc arena, brk), ``anon`` (anonymous mappings: the other threads' glibc arenas, large
  mmapped blocks, numpy buffers), ``file`` (code and data of the libraries), ``stack``, and the
  number of 64 MB-aligned glibc thread arenas (``arenas``);
- glibc ``mallinfo2`` (``malloc_in_use_mb``, ``malloc_free_mb`` = free memory malloc keeps, in
  all arenas, ``mmapped_mb``);
- ``gc_growth``: the Python object types whose count grew most since the previous line;
- with ``MDR_MEMDEBUG_TRACEMALLOC=1``, ``tracemalloc_growth``: the source lines whose Python
  allocations grew most since the previous line (tracemalloc slows the process; its own
  memory is reported as ``tracemalloc_mb``).

``python -m mdr_slam.nodes.memdebug FILE`` prints the lines as a table.
"""
from __future__ import annotations

import collections
import ctypes
import gc
import json
import os
import threading
import time
import tracemalloc

from .health import rss_bytes

__all__ = ["start_from_env", "smaps_summary", "mallinfo", "set_mmap_threshold"]


def smaps_summary(pid="self") -> dict:
    """Resident MB of a process's mappings by kind (heap, anon, file, stack) and glibc arenas."""
    out = {"heap": 0.0, "anon": 0.0, "file": 0.0, "stack": 0.0}
    arenas = 0
    kind = None
    with open("/proc/%s/smaps" % pid) as f:
        for line in f:
            first = line.split(None, 1)[0]
            if "-" in first and not first.endswith(":"):   # a mapping header
                parts = line.split()
                name = parts[5] if len(parts) > 5 else ""
                lo, hi = (int(x, 16) for x in first.split("-"))
                if name == "[heap]":
                    kind = "heap"
                elif name.startswith("[stack"):
                    kind = "stack"
                elif name == "":
                    kind = "anon"
                    # a glibc thread arena: 64 MB-aligned start (its reserve is HEAP_MAX_SIZE)
                    if lo % (64 << 20) == 0 and parts[1].startswith("rw"):
                        arenas += 1
                elif name.startswith("["):
                    kind = None
                else:
                    kind = "file"
            elif first == "Rss:" and kind is not None:
                out[kind] += int(line.split()[1]) / 1024.0
    out = {k: round(v, 2) for k, v in out.items()}
    out["arenas"] = arenas
    return out


class _Mallinfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
                 "uordblks", "fordblks", "keepcost")]


_LIBC = []


def _libc():
    """libc through ctypes, loaded once (None when not glibc)."""
    if not _LIBC:
        try:
            libc = ctypes.CDLL("libc.so.6")
            if hasattr(libc, "mallinfo2"):
                libc.mallinfo2.restype = _Mallinfo2
        except OSError:
            libc = None
        _LIBC.append(libc)
    return _LIBC[0]


def mallinfo() -> dict:
    """glibc mallinfo2 in MB ({} where glibc < 2.33 or not glibc)."""
    libc = _libc()
    if libc is None or not hasattr(libc, "mallinfo2"):
        return {}
    m = libc.mallinfo2()
    mb = 1.0 / (1 << 20)
    return {"malloc_arena_mb": round(m.arena * mb, 2), "malloc_in_use_mb": round(m.uordblks * mb, 2),
            "malloc_free_mb": round(m.fordblks * mb, 2), "mmapped_mb": round(m.hblkhd * mb, 2)}


def set_mmap_threshold(nbytes: int) -> bool:
    """glibc ``mallopt(M_MMAP_THRESHOLD, nbytes)``: blocks of at least ``nbytes`` are mmapped (and
    unmapped when freed). Setting it also turns off glibc's dynamic threshold, which otherwise
    rises to the size of the largest freed block (up to 32 MB) and takes the trim threshold of
    every arena with it (twice that): each thread's arena may then keep up to 64 MB of freed memory
    resident at its top. False where not glibc."""
    libc = _libc()
    if libc is None or not hasattr(libc, "mallopt"):
        return False
    return bool(libc.mallopt(-3, int(nbytes)))   # M_MMAP_THRESHOLD = -3


class MemDebug:
    def __init__(self, path: str, period: float = 60.0, trace: bool = False, top: int = 12):
        self.path, self.period, self.trace, self.top = path, float(period), trace, top
        self.prev_types = None
        self.prev_snap = None
        self.t0 = time.monotonic()
        if trace:
            tracemalloc.start(1)

    def sample(self) -> dict:
        rec = {"t": round(time.monotonic() - self.t0, 1), "pid": os.getpid(),
               "rss_mb": round(rss_bytes() / 1e6, 2), "threads": threading.active_count()}
        rec.update(smaps_summary())
        rec.update(mallinfo())
        counts = collections.Counter(type(o).__name__ for o in gc.get_objects())
        rec["gc_objects"] = sum(counts.values())
        if self.prev_types is not None:
            grow = {k: v - self.prev_types.get(k, 0) for k, v in counts.items()}
            rec["gc_growth"] = sorted(((k, d) for k, d in grow.items() if d), key=lambda x: -x[1])[:self.top]
        self.prev_types = counts
        if self.trace:
            snap = tracemalloc.take_snapshot()
            rec["tracemalloc_mb"] = round(tracemalloc.get_tracemalloc_memory() / 1e6, 2)
            rec["traced_mb"] = round(tracemalloc.get_traced_memory()[0] / 1e6, 2)
            if self.prev_snap is not None:
                stats = snap.compare_to(self.prev_snap, "lineno")[:self.top]
                rec["tracemalloc_growth"] = [(str(s.traceback[0]), s.size_diff, s.count_diff)
                                             for s in stats]
            self.prev_snap = snap
        return rec

    def run(self):
        while True:
            time.sleep(self.period)
            try:
                rec = self.sample()
                with open(self.path, "a") as f:
                    f.write(json.dumps(rec) + "\n")
            except Exception as e:  # a debug aid must never take the node down
                with open(self.path, "a") as f:
                    f.write(json.dumps({"error": repr(e)}) + "\n")


def start_from_env(name: str = "node"):
    """Start the memory debug thread when ``MDR_MEMDEBUG`` is set (``%p`` in it: the pid)."""
    path = os.environ.get("MDR_MEMDEBUG", "")
    if not path:
        return None
    path = path.replace("%p", str(os.getpid())).replace("%n", name)
    md = MemDebug(path, float(os.environ.get("MDR_MEMDEBUG_PERIOD", "60")),
                  os.environ.get("MDR_MEMDEBUG_TRACEMALLOC", "") not in ("", "0"))
    threading.Thread(target=md.run, name="memdebug", daemon=True).start()
    return md


def _print_table(path: str) -> None:
    recs = [json.loads(l) for l in open(path) if l.strip()]
    keys = ["t", "rss_mb", "heap", "anon", "arenas", "malloc_in_use_mb", "malloc_free_mb",
            "mmapped_mb", "gc_objects", "traced_mb", "threads"]
    print(" ".join("%10s" % k[:10] for k in keys))
    for r in recs:
        print(" ".join("%10s" % r.get(k, "") for k in keys))
    for r in recs[-3:]:
        print(r.get("t"), "gc:", r.get("gc_growth"))
        for g in r.get("tracemalloc_growth", [])[:6]:
            print("   ", g)


if __name__ == "__main__":
    import sys
    _print_table(sys.argv[1])
