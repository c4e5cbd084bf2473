"""BAWorker: the parent's side of the bundle-adjustment child process (``python -m
mdr_slam.pose.ba_worker``, which describes the pipe protocol): starts the child, sends it a
problem, reads the answer, and solves in the calling thread when the child cannot run. The same
child makes stereo frames' features for System (``stereo_features``: a pure function of the two
images, so only the images and the arrays cross the pipe).
"""
from __future__ import annotations

import logging
import os
import pickle
import select
import signal
import subprocess
import sys
import threading

from .frame import stereo_features_job
from .optimizer import bundle_adjust, bundle_adjust_sparse, essential_graph_job

__all__ = ["BAWorker", "BA_SOLVERS"]

# what a BAWorker child can solve (ba_worker.py looks the name up here too)
BA_SOLVERS = {"bundle_adjust": bundle_adjust, "bundle_adjust_sparse": bundle_adjust_sparse,
              "essential_graph": essential_graph_job, "stereo_features": stereo_features_job}


class BAWorker:
    """Solves bundle adjustments in one child process (``python -m mdr_slam.pose.ba_worker``):
    LocalMapping's local BA (``ba_process``) and LoopClosing's pose graph and global BA.

    Measured on this 2-core machine under heavy load (load average 8-10; KITTI clip, a captured
    local BA solved in a loop next to tracking): in a thread the GIL throttles the BA to ~1.2
    solves/s, in a process it runs ~4.4/s, with tracking ~100 ms/frame either way. In the live
    System (threads=True) at 10-20 Hz the process BA shortened the longest back-pressure waits on
    KITTI but, with no spare core, took CPU from tracking on the 20 Hz sample (median frame
    time up); hence System's ``ba_process`` is off by default: use it where a core is free.
    Only the arrays of the problem cross the pipe (~1 MB); the map stays in the tracking process.
    ``abort`` (a new keyframe is waiting) becomes SIGUSR1, checked by the solver between
    iterations as in-process. A dead child is restarted; if it cannot start, BA falls back to
    the calling thread for good (logged once).
    """

    def __init__(self, nice: int = 0):
        self.nice = int(nice)   # the child's nice increment (> 0: it yields the CPU to tracking)
        self._proc = None
        self._lock = threading.Lock()
        self.failed = False

    def _ensure(self):
        if self._proc is None or self._proc.poll() is not None:
            env = dict(os.environ)
            env["PYTHONPATH"] = os.pathsep.join([p for p in sys.path if p] +
                                                [env.get("PYTHONPATH", "")])
            env.setdefault("OPENBLAS_NUM_THREADS", "1")   # one core's worth, no BLAS spinning
            env["MDR_BA_NICE"] = str(max(0, self.nice))
            self._proc = subprocess.Popen([sys.executable, "-m", "mdr_slam.pose.ba_worker"],
                                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
            self._ready = False
        return self._proc

    def prewarm(self) -> None:
        """Start the child now (interpreter + numpy/scipy imports) instead of at the first BA."""
        with self._lock:
            try:
                self._ensure()
            except Exception as exc:   # noqa: BLE001 - any start failure means: BA in-thread
                self._fail(exc)

    def _fail(self, exc) -> None:
        if not self.failed:
            logging.getLogger(__name__).warning(
                "local BA process unavailable (%s): running BA in the LocalMapping thread", exc)
        self.failed = True
        self._kill()

    def _kill(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()

    def run(self, args: tuple, kwargs: dict, abort=None, solver: str = "bundle_adjust"):
        """``optimizer.<solver>(*args, abort=abort, **kwargs)`` solved in the child (``solver``:
        bundle_adjust or bundle_adjust_sparse); in this thread if the child cannot run."""
        with self._lock:
            if not self.failed:
                try:
                    proc = self._ensure()
                    if not self._ready:
                        if proc.stdout.read(1) != b"R":
                            raise RuntimeError("BA worker did not start")
                        self._ready = True
                    pickle.dump((solver, args, kwargs), proc.stdin,
                                protocol=pickle.HIGHEST_PROTOCOL)
                    proc.stdin.flush()
                    aborted = False
                    while not select.select([proc.stdout], [], [], 0.005)[0]:
                        if not aborted and abort is not None and abort():
                            proc.send_signal(signal.SIGUSR1)
                            aborted = True
                    res = pickle.load(proc.stdout)
                    if isinstance(res, Exception):
                        raise res
                    return res
                except Exception as exc:   # noqa: BLE001 - dead child, broken pipe, ...
                    self._fail(exc)
        return BA_SOLVERS[solver](*args, abort=abort, **kwargs)

    def close(self) -> None:
        with self._lock:
            proc, self._proc = self._proc, None
        if proc is not None:
            try:
                proc.stdin.close()
                proc.wait(timeout=5.0)
            except Exception:   # noqa: BLE001
                proc.kill()
                proc.wait()
