"""Optional pose backend: ORB-SLAM3's C++ stereo tracker (PyPI ``pyorbslam3``) behind System's API.

    from mdr_slam.pose import make_system
    system = make_system(camera, {"backend": "orbslam3"}, threads=True)   # or TrackerConfig(backend=...)

``ORBSLAM3System`` answers what the pose node and ``mdr run`` ask of :class:`System`
(``make_frame``, ``track`` -> :class:`TrackResult`, ``trajectory``, ``keyframe_poses``,
``shutdown``), so the node publishes the same topics and tf with either tracker. It is used only
when ``backend: orbslam3`` is set and ``pyorbslam3`` imports; nothing else in MDR-SLAM needs it.

Vocabulary: ``orbslam3_vocabulary`` names a DBoW2 text vocabulary (the official ``ORBvoc.txt``
when you have it). Empty: the project's own vocabulary (``mdr vocab``, src/mdr_slam/data/
orb_vocab.npz) is written once in DBoW2's text format (:func:`export_dbow2_text`, ~2 MB,
cached next to it or under ~/.cache/mdr_slam) and loaded in milliseconds; nothing is downloaded.
ORB-SLAM3 reads its settings from a YAML written from the camera model (rectified pinhole, no
distortion: the node rectifies first) and the tracker's ORB parameters of pose.yaml; a right
camera whose principal point differs from the left's (``StereoCamera.doffs``) has its image
shifted by the difference, since those settings hold one principal point.

Keyframes: pyorbslam3 0.1 has no keyframe API, but it saves ORB-SLAM3's keyframe trajectory
(``save_keyframe_trajectory_tum``: every live keyframe of the active map with its current pose).
After each ``track`` (every ``orbslam3_keyframe_poll`` frames) that file is read back
(:meth:`ORBSLAM3System.poll_keyframes`): keyframes not seen before come out as
``TrackResult.new_keyframes`` with their own stamps (ORB-SLAM3's LocalMapping adds a keyframe to
the map asynchronously, so it usually shows a frame after the one it was made from), and
keyframes whose pose moved as ``corrections`` (``loop_closure`` when ORB-SLAM3 reports a big map
change, else ``local_ba``), so /mdr/keyframes carries them and the depth and fusion nodes follow
as with the built-in tracker (``mdr run`` anchors each frame's points to the newest keyframe).
About 1 ms per frame (0.2-4 ms on the KITTI clip). What it does not give: loop-corrected past
poses of frames that are not keyframes (``trajectory()`` holds the poses as tracked). After ORB-SLAM3 loses track for good it starts a new map in its Atlas, with a
new origin: poses jump, and the keyframes of the old map are no longer listed.
"""
from __future__ import annotations

import bisect
import contextlib
import hashlib
import os
import sys
import tempfile
import time
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np

from ..geometry import relative_motion
from ..io import Trajectory, atomic_path, read_tum
from .config import TrackerConfig
from .result import TrackResult
from .tracking import LOST, NOT_INITIALIZED, OK
from .vocabulary import default_vocabulary_path, load_vocabulary

__all__ = ["ORBSLAM3System", "available", "import_error", "export_dbow2_text", "settings_yaml"]

KEYFRAME_POLL = 1              # read ORB-SLAM3's keyframes back every N frames for /mdr/keyframes (0: never; ~1 ms)


_IMPORT_ERROR = ""


def available() -> bool:
    """True when pyorbslam3 imports (the backend can run); else :func:`import_error` says why."""
    global _IMPORT_ERROR
    try:
        import pyorbslam3  # noqa: F401
    except Exception as e:   # ImportError, or a shared library the wheel needs is missing
        _IMPORT_ERROR = "%s: %s" % (type(e).__name__, e)
        return False
    return True


def import_error() -> str:
    """Why the last :func:`available` call failed ("" when it did not)."""
    return _IMPORT_ERROR


def export_dbow2_text(voc, path: str) -> int:
    """Write an :class:`ORBVocabulary` (complete k-ary tree) in DBoW2's text format, as
    ORB-SLAM2/3 load ``ORBvoc.txt``: a ``k L scoring weighting`` line (L1 norm, tf-idf), then one
    line per node in breadth-first order, ``parent_id is_leaf d0 .. d31 weight`` (node ids count
    from 1 in file order, 0 is the root). Leaves carry the idf weight. Returns the node count."""
    k, L = int(voc.k), int(voc.L)
    first = [0, 1]                     # first[l]: id of the first node of depth l (1-based)
    for lvl in range(1, L + 1):
        first.append(first[-1] + k ** lvl)
    rows = ["%d %d 0 0" % (k, L)]
    for lvl in range(1, L + 1):
        cents = np.asarray(voc.levels[lvl - 1], np.uint8)
        idx = np.arange(len(cents))
        parent = np.zeros(len(cents), np.int64) if lvl == 1 else first[lvl - 1] + idx // k
        leaf = 1 if lvl == L else 0
        weight = np.asarray(voc.idf, float) if lvl == L else np.zeros(len(cents))
        desc = [" ".join(map(str, row)) for row in cents.tolist()]
        rows.extend("%d %d %s %.6f" % (p, leaf, d, w)
                    for p, d, w in zip(parent.tolist(), desc, weight.tolist()))
    with atomic_path(path, ".txt") as tmp:
        with open(tmp, "w") as f:
            f.write("\n".join(rows))   # no trailing newline: DBoW2 would read an empty node
    return len(rows) - 1


def _vocabulary_file(cfg: TrackerConfig) -> str:
    given = str(cfg.orbslam3_vocabulary or "")
    if given:
        if not os.path.isfile(given):
            raise FileNotFoundError("orbslam3_vocabulary %s does not exist" % given)
        return given
    src = str(cfg.vocabulary or "") or default_vocabulary_path()
    voc = load_vocabulary(src if os.path.isfile(src) else None)
    key = hashlib.sha1(b"".join(np.ascontiguousarray(c).tobytes() for c in voc.levels) +
                       np.asarray(voc.idf, np.float32).tobytes()).hexdigest()[:12]
    name = "orb_vocab_dbow2_%s.txt" % key
    for d in (os.path.dirname(os.path.abspath(src)),
              os.path.join(os.path.expanduser("~"), ".cache", "mdr_slam")):
        path = os.path.join(d, name)
        if os.path.isfile(path):
            return path
        try:
            os.makedirs(d, exist_ok=True)
            export_dbow2_text(voc, path)
            return path
        except OSError:
            continue
    raise OSError("no writable place for the DBoW2 vocabulary file")


def _real(x) -> str:
    """A float as OpenCV's YAML reads a real (``35`` would be an int: ORB-SLAM3 refuses it)."""
    r = repr(float(x))
    return r if ("." in r or "e" in r or "n" in r) else r + ".0"


def settings_yaml(camera, cfg: TrackerConfig) -> str:
    """ORB-SLAM3 settings (OpenCV YAML, the pre-1.0 layout: a rectified pinhole pair by fx, fy,
    cx, cy and bf) from a StereoCamera and the tracker's parameters."""
    w, h = camera.size
    return "\n".join([
        "%YAML:1.0",
        'Camera.type: "PinHole"',
        "Camera.fx: %s" % _real(camera.fx), "Camera.fy: %s" % _real(camera.fy),
        "Camera.cx: %s" % _real(camera.cx), "Camera.cy: %s" % _real(camera.cy),
        "Camera.k1: 0.0", "Camera.k2: 0.0", "Camera.p1: 0.0", "Camera.p2: 0.0",
        "Camera.width: %d" % w, "Camera.height: %d" % h,
        # ORB-SLAM uses fps as the largest gap between keyframes (frames): max_frames here
        "Camera.fps: %d" % max(1, int(cfg.max_frames)),
        "Camera.bf: %s" % _real(camera.fx * camera.baseline),
        "Camera.RGB: 1",
        "ThDepth: %s" % _real(cfg.th_depth),
        "ORBextractor.nFeatures: %d" % int(cfg.n_features),
        "ORBextractor.scaleFactor: %s" % _real(cfg.scale_factor),
        "ORBextractor.nLevels: %d" % int(cfg.n_levels),
        "ORBextractor.iniThFAST: %d" % int(cfg.fast_threshold),
        "ORBextractor.minThFAST: %d" % max(1, int(cfg.min_fast_threshold or 7)),
        # the viewer is never started, but ORB-SLAM3 reads these keys
        "Viewer.KeyFrameSize: 0.05", "Viewer.KeyFrameLineWidth: 1.0",
        "Viewer.GraphLineWidth: 0.9", "Viewer.PointSize: 2.0", "Viewer.CameraSize: 0.08",
        "Viewer.CameraLineWidth: 3.0", "Viewer.ViewpointX: 0.0", "Viewer.ViewpointY: -0.7",
        "Viewer.ViewpointZ: -1.8", "Viewer.ViewpointF: 500.0", ""])


@contextlib.contextmanager
def _stdout_silenced():
    """ORB-SLAM3 announces every save on std::cout: file descriptor 1 goes to /dev/null for the
    call (its lines end with std::endl, so nothing is left buffered for later)."""
    try:
        sys.stdout.flush()
        saved = os.dup(1)
    except (OSError, ValueError):   # no fd 1 (embedded): nothing to silence
        yield
        return
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(null)


def _read_keyframe_file(path: str):
    """(stamps (N,), T_wc (N, 4, 4)) of a TUM keyframe trajectory; empty when the file is."""
    if not os.path.isfile(path) or os.path.getsize(path) == 0:
        return np.zeros(0), np.zeros((0, 4, 4))
    traj = read_tum(path)
    return np.asarray(traj.stamps, float), np.asarray(traj.matrices(), float)


class _Pair:
    """What ``make_frame`` hands to ``track``: ORB-SLAM3 does its own feature work."""

    __slots__ = ("stamp", "left", "right", "build_ms")

    def __init__(self, stamp: float, left: np.ndarray, right: np.ndarray):
        self.stamp, self.left, self.right, self.build_ms = float(stamp), left, right, 0.0


class ORBSLAM3System:
    """:class:`System`'s interface over ``pyorbslam3.Slam`` (Sensor.STEREO)."""

    def __init__(self, camera, config=None, threads: bool = True,
                 T_map_cam0: Optional[np.ndarray] = None):
        import pyorbslam3
        self.cfg = TrackerConfig.of(config)
        self.camera = camera
        self.threads = bool(threads)   # ORB-SLAM3 always runs its mapping threads
        self.T_map_world = np.eye(4) if T_map_cam0 is None else np.asarray(T_map_cam0, float)
        self.correction_id = 0
        self._records: List[Tuple[float, Optional[np.ndarray], str]] = []
        self._loops = 0
        self._state = "NOT_INITIALIZED"
        vocab = _vocabulary_file(self.cfg)
        fd, self._settings = tempfile.mkstemp(prefix="mdr_orbslam3_", suffix=".yaml")
        with os.fdopen(fd, "w") as f:
            f.write(settings_yaml(camera, self.cfg))
        self._states = {s: s.name for s in pyorbslam3.TrackingState.__members__.values()}
        fd, self._kf_file = tempfile.mkstemp(prefix="mdr_orbslam3_kfs_", suffix=".txt")
        os.close(fd)
        self._kf_ids: Dict[float, int] = {}     # keyframe stamp -> our keyframe id
        self._kf_poses: Dict[int, Tuple[float, np.ndarray]] = {}   # id -> (stamp, T_map_kf)
        self._fed: List[float] = []             # stamps of the frames fed, in order
        self._next_kf = 0
        self._frames = 0
        self.slam = pyorbslam3.Slam(vocab, self._settings, pyorbslam3.Sensor.STEREO)

    def make_frame(self, stamp: float, left_rect: np.ndarray, right_rect: np.ndarray) -> _Pair:
        if left_rect.ndim == 3:
            left_rect = cv2.cvtColor(left_rect, cv2.COLOR_BGR2GRAY)
            right_rect = cv2.cvtColor(right_rect, cv2.COLOR_BGR2GRAY)
        doffs = float(getattr(self.camera, "doffs", 0.0))
        if abs(doffs) > 1e-3:
            # ORB-SLAM3's settings have one principal point for both cameras: the right image is
            # moved by the difference (StereoCamera.doffs) so its disparities mean f*B/Z
            h, w = right_rect.shape[:2]
            right_rect = cv2.warpAffine(right_rect, np.float32([[1, 0, doffs], [0, 1, 0]]), (w, h),
                                        flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        return _Pair(stamp, np.ascontiguousarray(left_rect), np.ascontiguousarray(right_rect))

    def track(self, stamp: float, left_rect: Optional[np.ndarray] = None,
              right_rect: Optional[np.ndarray] = None, frame: Optional[_Pair] = None):
        if frame is None:
            frame = self.make_frame(stamp, left_rect, right_rect)
        t0 = time.perf_counter()
        c0 = time.thread_time()
        res = self.slam.track_stereo(frame.left, frame.right, frame.stamp)
        ms = 1000.0 * (time.perf_counter() - t0)
        cpu = 1000.0 * (time.thread_time() - c0)
        name = self._states.get(res.state, str(res.state))
        # OK and OK_KLT track; RECENTLY_LOST coasts on the motion model: reported LOST, no pose
        state = OK if name.startswith("OK") else (
            NOT_INITIALIZED if name in ("NOT_INITIALIZED", "NO_IMAGES_YET", "SYSTEM_NOT_READY")
            else LOST)
        T = None
        if state == OK and res.pose_valid:
            T_wc = np.asarray(res.pose_wc, float)
            if np.all(np.isfinite(T_wc)):
                T = self.T_map_world @ T_wc
            else:
                state = LOST
        self._state = state
        self._records.append((frame.stamp, T, state))
        if self._fed and frame.stamp <= self._fed[-1]:   # time went back: a new timeline
            self._fed = []
        self._fed.append(frame.stamp)
        self._frames += 1
        new_kfs, corrections = None, None
        poll = int(KEYFRAME_POLL)
        if poll > 0 and self._frames % poll == 0:
            new_kfs, corrections = self.poll_keyframes()
        n = int(res.num_tracked_points)
        return TrackResult(stamp=frame.stamp, state=state, T_map_cam=T, n_tracked=n,
                           is_keyframe=False, keyframe_id=-1, corrections=corrections,
                           time_ms=ms, ref_keyframe_id=-1, n_map_points=n,
                           n_keyframes=len(self._kf_poses), n_loop_closures=self._loops,
                           track_ms=ms, track_cpu_ms=cpu, lock_wait_ms=0.0, frame_ms=0.0,
                           new_keyframes=new_kfs)

    def poll_keyframes(self):
        """Read ORB-SLAM3's live keyframes back (``save_keyframe_trajectory_tum``) and diff them
        against the last read: (new {id: (stamp, T_map_kf)} or None, corrections
        (reason, correction_id, {id: (stamp, T_map_kf)}) or None), as :class:`System` reports
        them. Keyframes are known by their stamps (the file has microseconds: the stamp of the
        frame fed within 2 us is used); ids count from 0 in order of appearance."""
        with _stdout_silenced():
            self.slam.save_keyframe_trajectory_tum(self._kf_file)
        big_change = bool(self.slam.map_changed())   # loop closure / global BA / map merge
        if big_change:
            self._loops += 1
        stamps, Ts = _read_keyframe_file(self._kf_file)
        new, moved, live = {}, {}, {}
        for st, T_wc in zip(stamps.tolist(), Ts):
            if not np.all(np.isfinite(T_wc)):
                continue
            stamp = st
            i = bisect.bisect_left(self._fed, st)
            near = [self._fed[j] for j in (i - 1, i) if 0 <= j < len(self._fed)]
            if near:
                best = min(near, key=lambda f: abs(f - st))
                if abs(best - st) <= 2e-6:
                    stamp = best
            T = self.T_map_world @ T_wc
            kid = self._kf_ids.get(stamp)
            if kid is None:
                kid = self._next_kf
                self._next_kf += 1
                self._kf_ids[stamp] = kid
                new[kid] = (stamp, T)
            elif kid not in self._kf_poses or \
                    max(relative_motion(self._kf_poses[kid][1], T)) > 1e-4:   # 0.1 mm / rad
                moved[kid] = (stamp, T)
            live[kid] = (stamp, T if kid in new or kid in moved else self._kf_poses[kid][1])
        self._kf_poses = live          # culled keyframes (and an abandoned map's) drop out
        corrections = None
        if moved:
            self.correction_id += 1
            corrections = ("loop_closure" if big_change else "local_ba", self.correction_id, moved)
        return (new or None), corrections

    @property
    def state(self) -> str:
        return self._state

    def keyframe_poses(self) -> Dict[int, Tuple[float, np.ndarray]]:
        """{id: (stamp, T_map_kf)} of ORB-SLAM3's live keyframes as last read."""
        return dict(self._kf_poses)

    def trajectory(self, include_lost: bool = False):
        rows = [(s, T) for s, T, _ in self._records if T is not None]
        if not rows:
            return Trajectory(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)))
        return Trajectory.from_matrices([s for s, _ in rows], [T for _, T in rows])

    def reset(self) -> None:
        self.slam.reset()
        self._records = []
        self._kf_poses = {}

    def shutdown(self) -> None:
        if self.slam is not None:
            try:
                self.slam.shutdown()
            finally:
                self.slam = None
                for path in (self._settings, self._kf_file):
                    try:
                        os.remove(path)
                    except OSError:
                        pass
