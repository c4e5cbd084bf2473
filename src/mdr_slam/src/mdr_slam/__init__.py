"""MDR-SLAM: modular decoupled stereo dense mapping (ROS 1).

The algorithms live here, free of ROS: ``mdr_slam.pose`` (ORB-SLAM2-style tracking, local BA,
loop closure), ``mdr_slam.depth`` (ELAS + keyframe-guided Kalman temporal filter),
``mdr_slam.fusion`` (confidence-based global map), ``mdr_slam.camera`` and ``mdr_slam.geometry``,
``mdr_slam.io`` (maps, trajectories, bags), ``mdr_slam.sim`` (stereo simulator with exact ground
truth) and ``mdr_slam.eval`` (the paper's metrics). ``mdr_slam.conversions`` is the only bridge
between ROS messages and numpy, and ``mdr_slam.nodes`` holds the thin rospy shells.
"""
__version__ = "0.1.0"

import os as _os
import sys as _sys


def _openblas_coretype(cpuinfo: str = "/proc/cpuinfo"):
    """The OpenBLAS kernel family (OPENBLAS_CORETYPE) that this CPU's flags allow, or None.

    numpy 1.26's OpenBLAS (0.3.23) does not know recent Xeons (e.g. Sapphire Rapids) and falls
    back to its "Prescott" kernels without AVX: small matrix products were 4.6x slower and the
    pose node's CPU per frame 6 % higher on our 2-core test machine. The kernel family follows
    from the CPU flags; an existing OPENBLAS_CORETYPE (or MDR_OPENBLAS_CORETYPE=keep) is kept.
    Only effective when set before numpy is first imported (every node and ``mdr`` import
    mdr_slam first)."""
    if _os.environ.get("OPENBLAS_CORETYPE") or _os.environ.get("MDR_OPENBLAS_CORETYPE") == "keep":
        return None
    try:
        with open(cpuinfo) as f:
            flags = next((line.split(":", 1)[1].split() for line in f
                          if line.startswith("flags")), [])
    except (OSError, StopIteration):
        return None
    flags = set(flags)
    if {"avx512f", "avx512bw", "avx512vl", "avx512dq"} <= flags:
        return "SkylakeX"
    if {"avx2", "fma"} <= flags:
        return "Haswell"
    return None


if "numpy" not in _sys.modules and _sys.platform.startswith("linux"):
    _core = _openblas_coretype()
    if _core:
        _os.environ["OPENBLAS_CORETYPE"] = _core
