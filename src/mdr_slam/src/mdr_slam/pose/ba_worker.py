"""Child process that solves bundle adjustments for LocalMapping and LoopClosing (the parent's
side: ba_process.BAWorker).

Protocol on its stdin/stdout: the parent writes pickled ``(name, args, kwargs)``, name a key of
``ba_process.BA_SOLVERS`` (``bundle_adjust``: local BA, ``bundle_adjust_sparse``: global BA,
``essential_graph``: a loop's pose graph, ``stereo_features``: a stereo frame's features); the child answers the pickled result or an
``Exception``. SIGUSR1 asks the solve in progress to stop
after the current iteration (ORB-SLAM2's abort when a new keyframe arrives). It is a plain
``python -m`` process, not multiprocessing, so the parent's main script is never re-imported in
the child. EOF on stdin (the parent is gone) ends it.
"""
from __future__ import annotations

import os
import pickle
import signal
import sys


def main() -> int:
    nice = int(os.environ.get("MDR_BA_NICE", "0") or 0)
    if nice > 0:
        os.nice(nice)                  # lower priority than the tracking process (BAWorker(nice))
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)                      # stray prints/warnings go to stderr, not into the protocol
    inp = os.fdopen(os.dup(0), "rb")
    # imported after the redirect: whatever its import prints stays out of the protocol
    import cv2
    from mdr_slam.pose.ba_process import BA_SOLVERS
    from mdr_slam.pose.factory import CV_THREADS
    cv2.setNumThreads(CV_THREADS)      # as the pose node: frame jobs run two ORB threads already
    flag = {"abort": False}

    def on_abort(signum, frame):
        flag["abort"] = True

    signal.signal(signal.SIGUSR1, on_abort)
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # Ctrl-C goes to the parent, which closes us
    out.write(b"R")                    # ready
    out.flush()
    while True:
        try:
            name, args, kwargs = pickle.load(inp)
        except (EOFError, OSError):
            return 0
        flag["abort"] = False
        try:
            res = BA_SOLVERS[name](*args, abort=lambda: flag["abort"], **kwargs)
        except Exception as exc:       # noqa: BLE001 - reported to the parent, which falls back
            res = RuntimeError("%s failed in the BA worker: %r" % (name, exc))
        pickle.dump(res, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()


if __name__ == "__main__":
    sys.exit(main())
