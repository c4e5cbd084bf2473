#!/usr/bin/env python3
"""The pose tracker's CPU per stereo pair of a bag, by stage, and the cores it needs at a rate.

The bag's pairs tracked offline (``System(threads=False)``, no frame worker, the pose node's
library thread limits, ``config/pose.yaml``), each pair's process CPU split into: making the
Frame (ORB on both images, stereo matching: ``System.make_frame``), tracking it
(``System.track(frame=...)``), and LocalMapping + LoopClosing (their ``spin_sync``, timed apart).
Means per group of ``--group`` pairs (a lap of a patrol: a new place costs mapping, a revisit
does not), and the cores each needs at ``--rate`` Hz. Run it on an idle machine.

    python scripts/pose_cpu_budget.py BAG [--pairs 1800] [--group 600] [--rate 20]
        [--left-image T --right-image T --left-info T --right-info T] [--set n_features=1000]
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag")
    ap.add_argument("--pairs", type=int, default=1800, help="pairs read (default 1800)")
    ap.add_argument("--group", type=int, default=600, help="pairs per printed row (default 600)")
    ap.add_argument("--rate", type=float, default=20.0, help="camera rate for the cores, Hz")
    for k in ("left_image", "right_image", "left_info", "right_info"):
        ap.add_argument("--" + k.replace("_", "-"), dest=k, default=None)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="pose parameter override (YAML value), e.g. n_features=1000")
    a = ap.parse_args(argv)
    import yaml
    from mdr_slam.pipeline import frames_from_bag, load_params
    from mdr_slam.pose import System, TrackerConfig
    from mdr_slam.pose.factory import limit_library_threads
    limit_library_threads()
    topics = {k: getattr(a, k) for k in ("left_image", "right_image", "left_info", "right_info")
              if getattr(a, k)}
    cam, frames = frames_from_bag(a.bag, topics=topics or None, max_frames=a.pairs)
    p = load_params("pose")
    for kv in a.set:
        k, v = kv.split("=", 1)
        p[k] = yaml.safe_load(v)
    s = System(cam, config=TrackerConfig.pick(p), threads=False)
    mapping = [0.0]

    def timed(fn):
        def run():
            c = time.process_time()
            fn()
            mapping[0] += time.process_time() - c
        return run
    s.local_mapping.spin_sync = timed(s.local_mapping.spin_sync)
    if s.loop_closing is not None:
        s.loop_closing.spin_sync = timed(s.loop_closing.spin_sync)
    rows = []   # (frame, tracking, mapping) ms per pair
    tracked = 0
    for f in frames:
        c0 = time.process_time()
        frame = s.make_frame(f.stamp, f.left, f.right)
        c1 = time.process_time()
        mapping[0] = 0.0
        res = s.track(f.stamp, frame=frame)
        c2 = time.process_time()
        tracked += res.state in ("OK", "RELOCALIZED")
        m = 1000.0 * mapping[0]
        rows.append((1000.0 * (c1 - c0), 1000.0 * (c2 - c1) - m, m))
    s.shutdown()
    if not rows:
        print("%s: no stereo pairs" % a.bag, file=sys.stderr)
        return 1
    R = np.array(rows)
    print("| pairs | Frame ms | tracking ms | mapping ms | total ms | cores at %g Hz |" % a.rate)
    print("|---|---|---|---|---|---|")
    out = []
    for i in range(0, len(R), a.group):
        m = R[i:i + a.group].mean(axis=0)
        out.append(dict(pairs=[i, min(i + a.group, len(R))], frame_ms=m[0], tracking_ms=m[1],
                        mapping_ms=m[2], total_ms=m.sum(), cores=m.sum() * a.rate / 1000.0))
        print("| %d-%d | %.1f | %.1f | %.1f | %.1f | %.2f |" % (
            i, out[-1]["pairs"][1], m[0], m[1], m[2], m.sum(), out[-1]["cores"]))
    print("%d of %d pairs tracked, %d keyframes alive" % (tracked, len(R),
                                                         len(s.map.good_keyframes())))
    print(json.dumps(dict(groups=out, tracked=tracked, pairs=len(R))), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
