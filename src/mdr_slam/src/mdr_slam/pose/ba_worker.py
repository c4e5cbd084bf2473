"""Child process that solves local bundle adjustments for LocalMapping (see optimizer.BAWorker).

Protocol on its stdin/stdout: the parent writes pickled ``(args, kwargs)`` of
``optimizer.bundle_adjust``; the child answers the pickled ``(Ts, P)`` or an ``Exception``. SIGUSR1
asks the solve in progress to stop after the current iteration (ORB-SLAM2's abort when a new
keyframe arrives). It is a plain ``python -m`` process, not multiprocessing, so the parent's main
script is never re-imported in the child. EOF on stdin (the parent is gone) ends it.
"""
from __future__ import annotations

import os
import pickle
import signal
import sys


def main() -> int:
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)                      # stray prints/warnings go to stderr, not into the protocol
    inp = os.fdopen(os.dup(0), "rb")
    from mdr_slam.pose.optimizer import bundle_adjust
    flag = {"abort": False}

    def on_abort(signum, frame):
        flag["abort"] = True

    signal.signal(signal.SIGUSR1, on_abort)
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # Ctrl-C goes to the parent, which closes us
    out.write(b"R")                    # ready
    out.flush()
    while True:
        try:
            args, kwargs = pickle.load(inp)
        except (EOFError, OSError):
            return 0
        flag["abort"] = False
        try:
            res = bundle_adjust(*args, abort=lambda: flag["abort"], **kwargs)
        except Exception as exc:       # noqa: BLE001 - reported to the parent, which falls back
            res = RuntimeError("bundle_adjust failed in the BA worker: %r" % (exc,))
        pickle.dump(res, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()


if __name__ == "__main__":
    sys.exit(main())
