"""make_system: the pose tracker the ``backend`` parameter names (System or ORBSLAM3System)."""
from __future__ import annotations

from typing import Optional

import numpy as np

from .config import TrackerConfig
from .orbslam3 import ORBSLAM3System, available, import_error
from .system import System

__all__ = ["make_system"]


def make_system(camera, config=None, threads: bool = True,
                T_map_cam0: Optional[np.ndarray] = None):
    """The tracker ``config.backend`` names: :class:`System` (``mdr``, the default) or
    :class:`~mdr_slam.pose.orbslam3.ORBSLAM3System` (``orbslam3``; needs pyorbslam3, else
    ImportError). ``config``: a TrackerConfig or a mapping of its fields. Both backends take the
    same arguments and answer the same calls."""
    cfg = TrackerConfig.of(config)
    backend = (cfg.backend or "mdr").lower()
    if backend == "mdr":
        return System(camera, cfg, threads=threads, T_map_cam0=T_map_cam0)
    if backend == "orbslam3":
        if not available():
            raise ImportError("pose backend orbslam3 needs the pyorbslam3 package "
                              "(pip install pyorbslam3; x86-64 Linux, Python >= 3.9): %s"
                              % import_error())
        return ORBSLAM3System(camera, cfg, threads=threads, T_map_cam0=T_map_cam0)
    raise ValueError("pose backend must be mdr or orbslam3, not %r" % backend)
