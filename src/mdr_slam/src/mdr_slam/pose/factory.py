"""make_system: the pose tracker the ``backend`` parameter names (System or ORBSLAM3System);
limit_library_threads: the BLAS and OpenCV thread counts the pose node tracks with."""
from __future__ import annotations

import contextlib
from typing import Optional

import cv2
import numpy as np

from .config import TrackerConfig
from .orbslam3 import ORBSLAM3System, available, import_error
from .system import System

__all__ = ["make_system", "limit_library_threads", "library_threads", "BLAS_THREADS",
           "CV_THREADS"]

BLAS_THREADS = 1            # OpenBLAS's second thread mostly spins on the small BA/PnP products
CV_THREADS = 1              # left and right ORB already run in two threads


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


def _limit(blas_threads: int, cv_threads: int):
    """(why the BLAS threads were not limited or None, threadpoolctl limiter or None)."""
    why, limiter = None, None
    if blas_threads > 0:
        # one BLAS thread: OpenBLAS's second thread mostly spins on the small BA/PnP products
        # and takes CPU from the depth and fusion nodes on a 2-core machine
        try:
            from threadpoolctl import threadpool_limits  # optional package
            limiter = threadpool_limits(int(blas_threads), user_api="blas")
        except Exception as e:   # noqa: BLE001  (threadpoolctl missing: library default)
            why = "%s: %s" % (type(e).__name__, e)
    if cv_threads > 0:
        # left and right ORB already run in two threads; OpenCV's own pool on top of them costs
        # CPU (the pyramid's parallel loops: 15.0 -> 11.9 ms CPU per 752x480 image with one)
        cv2.setNumThreads(int(cv_threads))
    return why, limiter


def limit_library_threads(blas_threads: int = BLAS_THREADS,
                          cv_threads: int = CV_THREADS) -> Optional[str]:
    """Limit this process's BLAS and OpenCV thread pools as the pose node runs (0: leave that
    library's default). Returns None, or why the BLAS threads were not limited (threadpoolctl is
    optional); OpenCV's are always set."""
    return _limit(blas_threads, cv_threads)[0]


@contextlib.contextmanager
def library_threads(blas_threads: int = BLAS_THREADS, cv_threads: int = CV_THREADS):
    """:func:`limit_library_threads` for a block (a benchmark inside a longer process): yields
    why the BLAS threads were not limited (or None); the previous limits are restored after."""
    n_cv = cv2.getNumThreads()
    why, limiter = _limit(blas_threads, cv_threads)
    try:
        yield why
    finally:
        cv2.setNumThreads(n_cv)
        if limiter is not None:
            limiter.restore_original_limits()
