"""`mdr bench --navigate` runs each scene in a child process: Ctrl-C must let that child stop
what it started (launches, roscore, the recorder) instead of killing it."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

CHILD = textwrap.dedent("""
    import sys, time
    open(sys.argv[1] + ".started", "w").close()
    try:
        time.sleep(60)
    finally:                       # what run_scene's finally does: stop its processes
        time.sleep(1.0)
        open(sys.argv[1] + ".cleaned", "w").close()
""")

PARENT = textwrap.dedent("""
    import signal, sys
    # as from a terminal: a shell's background job (as CI may run the suite) has SIGINT ignored,
    # which Python and the scene process would keep; the handler here is reset to the default
    # action in the child at exec
    signal.signal(signal.SIGINT, signal.default_int_handler)
    from mdr_slam.cli.bench_navigate import _run_scene_process
    try:
        _run_scene_process([sys.executable, "-c", sys.argv[1], sys.argv[2]])
    except KeyboardInterrupt:
        open(sys.argv[2] + ".parent", "w").close()
""")


def test_ctrl_c_lets_the_scene_process_clean_up(tmp_path):
    mark = str(tmp_path / "scene")
    p = subprocess.Popen([sys.executable, "-c", PARENT, CHILD, mark], start_new_session=True)
    try:
        t_end = time.time() + 60
        while not os.path.exists(mark + ".started") and time.time() < t_end:
            time.sleep(0.05)
        assert os.path.exists(mark + ".started")
        os.killpg(p.pid, signal.SIGINT)          # a terminal's Ctrl-C: the whole group
        p.wait(60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert os.path.exists(mark + ".cleaned")
    assert os.path.exists(mark + ".parent")
