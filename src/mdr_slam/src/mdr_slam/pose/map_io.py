"""Save and load the pose tracker's sparse map (ORB-SLAM3 Atlas save/load, orb_slam_2_ros
``save_map``/``load_map``), so a later run relocalizes in a known place instead of starting a
new map.

    summary = save_pose_map(system, "room.posemap.npz")    # {"keyframes", "points", "bytes", ...}
    system = System(camera, config)                          # fresh: no frame tracked yet
    summary = load_pose_map(system, "room.posemap.npz")      # next frame relocalizes

One ``.npz`` (no pickled objects), written atomically (mdr_slam.io.atomic). Per-keyframe arrays
are concatenated over keyframes with an offsets array (``kf_*_offsets``, K + 1 entries) instead of
one entry per keyframe. Entries (K keyframes, N keypoints over all of them, n map points):

- header: ``magic`` (MAGIC), ``format_version`` (FORMAT_VERSION), ``camera`` (width, height, fx,
  fy, cx, cy, baseline, doffs of the rectified pair: a map is refused by another camera),
  ``pyramid`` (scale factor, levels), ``T_map_world`` (4x4: the map frame poses are published
  in), ``next_kf_id``, ``n_loop_closures``, ``n_points`` (n); optional ``session_id`` (the
  mapping session, mdr_slam.io.map_dir);
- keyframes (K,): ``kf_id``, ``kf_frame_id``, ``kf_stamp``, ``kf_bad``, ``kf_parent`` (-1: none),
  ``kf_T_cw`` (K,4,4), ``kf_has_T_cp``, ``kf_T_cp`` (K,4,4), ``kf_intrinsics`` (K,8: fx, fy, cx,
  cy, bf, baseline, th_depth, log_scale), ``kf_size`` (K,3: width, height, nlevels);
- keypoints (N,), by ``kf_kp_offsets``: ``kp_uv``, ``kp_octave``, ``kp_angle``, ``kp_desc``,
  ``kp_ur``, ``kp_depth``, ``kp_mp_ids``; texture weights ``tex_w`` by ``kf_tex_offsets`` (empty
  for keyframes without them, ``kf_has_tex``); ``scale``, ``inv_level_sigma2`` by
  ``kf_level_offsets``; ``loop_edges`` by ``kf_loop_offsets``; covisibility ``conn_ids``,
  ``conn_weights`` by ``kf_conn_offsets``;
- map points (n,): MP_FIELDS (``mp_pos``, ``mp_desc``, ... ``mp_bad``), as Map keeps them;
- optional (``images=True``): the loop closer's half and quarter resolution keyframe images of
  the proximity loops, ``img_kf_ids`` (M,), ``img_half`` (M,h/2,w/2), ``img_quarter``.

BoW vectors are not stored: they are recomputed at load with the tracker's vocabulary (one
vocabulary transform per keyframe, as LoopClosing does when a keyframe arrives), so a map stays
valid when the vocabulary file changes.
"""
from __future__ import annotations

import os
import time
from typing import Dict, List

import numpy as np

from ..io.atomic import atomic_path
from .frame import Frame
from .map import KeyFrame, Map
from .tracking import LOST, NOT_INITIALIZED
from .vocabulary import KeyFrameDatabase

__all__ = ["save_pose_map", "load_pose_map", "PoseMapError", "FORMAT_VERSION", "MAGIC"]

MAGIC = "mdr_slam pose map"
FORMAT_VERSION = 1

# map point arrays of Map, saved up to Map.n
MP_FIELDS = ("mp_pos", "mp_desc", "mp_normal", "mp_min_dist", "mp_max_dist", "mp_visible",
             "mp_found", "mp_nobs", "mp_first_kf", "mp_ref_kf", "mp_bad")
# (name, dtype, per-row shape) of the keypoint arrays sharing kf_kp_offsets
KP_FIELDS = (("uv", np.float32, (2,)), ("octave", np.int64, ()), ("angle", np.float32, ()),
             ("desc", np.uint8, (32,)), ("ur", np.float32, ()), ("depth", np.float32, ()),
             ("mp_ids", np.int64, ()))
CAMERA_RTOL = 1e-6      # intrinsics and baseline agree to this (a recalibration is another camera)
SAVE_DRAIN_S = 5.0      # threads: wait at most this for LocalMapping's queue before saving


class PoseMapError(ValueError):
    """A pose map that cannot be saved or loaded (missing, truncated, corrupt, another format
    version or another camera); the System it was to be loaded into is left unchanged."""


def _camera_vector(camera) -> np.ndarray:
    w, h = camera.size
    return np.array([w, h, camera.fx, camera.fy, camera.cx, camera.cy, camera.baseline,
                     float(getattr(camera, "doffs", 0.0))], np.float64)


def _camera_text(v: np.ndarray) -> str:
    return "%dx%d fx=%.6g fy=%.6g cx=%.6g cy=%.6g baseline=%.6g m doffs=%.6g" % tuple(v)


def _check_system(system) -> None:
    if not isinstance(getattr(system, "map", None), Map) or \
            getattr(system, "tracking", None) is None:
        raise PoseMapError("pose maps are saved and loaded by mdr_slam.pose.System only, not %s"
                           % type(system).__name__)


def _pack(arrays: List[np.ndarray], dtype, shape=()):
    """(offsets (len + 1,), concatenation) of per-keyframe arrays."""
    off = np.zeros(len(arrays) + 1, np.int64)
    off[1:] = np.cumsum([len(a) for a in arrays])
    arrays = [np.asarray(a, dtype).reshape((-1,) + shape) for a in arrays]
    data = np.concatenate(arrays) if arrays else np.zeros((0,) + shape, dtype)
    return off, data


# ---------------------------------------------------------------------- save
def save_pose_map(system, path: str, images: bool = True, compress: bool = True,
                  session_id: str = "") -> Dict:
    """Write the tracker's map to ``path`` (one .npz, atomically). ``images``: also the loop
    closer's keyframe images (proximity loops; ~112 kB per keyframe before compression).
    ``session_id``: the mapping session's id (entry ``session_id``, mdr_slam.io.map_dir).
    Returns {"keyframes", "points", "images", "bytes", "seconds"}."""
    _check_system(system)
    t0 = time.perf_counter()
    if getattr(system, "threads", False):
        # keyframes still queued have no covisibility yet and their tracked points are not
        # counted as observations: let LocalMapping take them first (best effort)
        system.local_mapping.wait_queue_below(1, timeout=SAVE_DRAIN_S)
    mp = system.map
    with mp.lock:
        kfs = [mp.keyframes[k] for k in sorted(mp.keyframes)]
        if not kfs:
            raise PoseMapError("the tracker has no map to save yet (no keyframe)")
        n = int(mp.n)
        d = {
            "magic": np.array(MAGIC),
            "format_version": np.int64(FORMAT_VERSION),
            "camera": _camera_vector(system.camera),
            "pyramid": np.array([system.extractor.scale_factor, system.extractor.nlevels],
                                np.float64),
            "T_map_world": np.asarray(system.T_map_world, np.float64).copy(),
            "next_kf_id": np.int64(mp.next_kf_id),
            "n_loop_closures": np.int64(mp.n_loop_closures),
            "n_points": np.int64(n),
            "kf_id": np.array([k.id for k in kfs], np.int64),
            "kf_frame_id": np.array([k.frame_id for k in kfs], np.int64),
            "kf_stamp": np.array([k.stamp for k in kfs], np.float64),
            "kf_bad": np.array([k.bad for k in kfs], bool),
            "kf_parent": np.array([-1 if k.parent is None else k.parent.id for k in kfs],
                                  np.int64),
            "kf_T_cw": np.array([k.T_cw for k in kfs], np.float64).reshape(-1, 4, 4),
            "kf_has_T_cp": np.array([k.T_cp is not None for k in kfs], bool),
            "kf_T_cp": np.array([np.eye(4) if k.T_cp is None else k.T_cp for k in kfs],
                                np.float64).reshape(-1, 4, 4),
            "kf_intrinsics": np.array([[k.fx, k.fy, k.cx, k.cy, k.bf, k.baseline, k.th_depth,
                                        k.log_scale] for k in kfs], np.float64),
            "kf_size": np.array([[k.width, k.height, k.nlevels] for k in kfs], np.int64),
            "kf_has_tex": np.array([k.tex_w is not None for k in kfs], bool),
        }
        for name, dtype, shape in KP_FIELDS:
            d["kf_kp_offsets"], d["kp_" + name] = _pack([getattr(k, name) for k in kfs],
                                                        dtype, shape)
        d["kf_tex_offsets"], d["tex_w"] = _pack(
            [k.tex_w if k.tex_w is not None else np.zeros((0, 2)) for k in kfs], np.float32, (2,))
        d["kf_level_offsets"], d["scale"] = _pack([k.scale for k in kfs], np.float64)
        _, d["inv_level_sigma2"] = _pack([k.inv_level_sigma2 for k in kfs], np.float64)
        d["kf_loop_offsets"], d["loop_edges"] = _pack([list(k.loop_edges) for k in kfs],
                                                      np.int64)
        conns = [sorted(k.connections.items()) for k in kfs]
        d["kf_conn_offsets"], d["conn_ids"] = _pack([[c for c, _ in cs] for cs in conns],
                                                    np.int64)
        _, d["conn_weights"] = _pack([[w for _, w in cs] for cs in conns], np.int64)
        for name in MP_FIELDS:
            d[name] = getattr(mp, name)[:n].copy()
        kept = {}
        lc = getattr(system, "loop_closing", None)
        if images and lc is not None:
            kept = {k: v for k, v in dict(lc.images).items()
                    if k in mp.keyframes and not mp.keyframes[k].bad}
        n_good_kfs = sum(1 for k in kfs if not k.bad)
        n_good_pts = int(np.count_nonzero(~mp.mp_bad[:n]))
    # the images are never modified once kept: stacked outside the lock
    ids = sorted(kept)
    if ids:   # one camera, one size; an odd one out (should not happen) is left out
        shape = kept[ids[0]][0].shape, kept[ids[0]][1].shape
        ids = [k for k in ids if (kept[k][0].shape, kept[k][1].shape) == shape]
    d["img_kf_ids"] = np.array(ids, np.int64)
    d["img_half"] = np.array([kept[k][0] for k in ids], np.uint8).reshape(
        (len(ids),) + (kept[ids[0]][0].shape if ids else (0, 0)))
    d["img_quarter"] = np.array([kept[k][1] for k in ids], np.uint8).reshape(
        (len(ids),) + (kept[ids[0]][1].shape if ids else (0, 0)))
    if session_id:
        d["session_id"] = np.array(str(session_id))
    writer = np.savez_compressed if compress else np.savez
    try:
        with atomic_path(path, ".npz") as tmp:
            with open(tmp, "wb") as f:
                writer(f, **d)
    except OSError as e:
        raise PoseMapError("cannot write the pose map %s: %s" % (path, e)) from e
    return {"keyframes": n_good_kfs, "points": n_good_pts, "images": len(ids),
            "bytes": int(os.path.getsize(path)), "seconds": time.perf_counter() - t0}


# ---------------------------------------------------------------------- load
def _read(path: str) -> Dict[str, np.ndarray]:
    """Every entry of the archive, read now (a truncated member fails here, not later)."""
    if not os.path.isfile(path):
        raise PoseMapError("no pose map at %s" % path)
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except TypeError:   # np.load of a single .npy has no context manager: not an archive
        raise PoseMapError("%s is not a pose map (not an .npz archive)" % path) from None
    except Exception as e:   # zipfile.BadZipFile, EOFError, ValueError (pickle), OSError, zlib
        raise PoseMapError("cannot read the pose map %s (truncated or not a pose map): %s: %s"
                           % (path, type(e).__name__, e)) from e


def _require(d, names) -> None:
    missing = [n for n in names if n not in d]
    if missing:
        raise PoseMapError("corrupt pose map: missing entries %s" % ", ".join(missing))


def _check_format(d, path: str) -> None:
    if "magic" not in d or d["magic"].shape != () or str(d["magic"]) != MAGIC:
        raise PoseMapError("%s is not a pose map (magic %r, expected %r)"
                           % (path, str(d["magic"]) if "magic" in d else None, MAGIC))
    _require(d, ["format_version"])
    try:
        version = int(d["format_version"])
    except (TypeError, ValueError):
        raise PoseMapError("corrupt pose map: format_version %r" % (d["format_version"],)) \
            from None
    if version != FORMAT_VERSION:
        raise PoseMapError("%s is pose map format version %d; this build reads version %d "
                           "(save the map again with this build)" % (path, version, FORMAT_VERSION))


def _check_header(d, path: str, system) -> None:
    _check_format(d, path)
    _require(d, ["camera", "pyramid"])
    saved = np.asarray(d["camera"], np.float64).ravel()
    mine = _camera_vector(system.camera)
    if saved.shape != mine.shape or not np.allclose(saved, mine, rtol=CAMERA_RTOL, atol=1e-9):
        raise PoseMapError("%s was made with another camera (%s); this tracker's camera is %s"
                           % (path, _camera_text(saved) if saved.shape == mine.shape else saved,
                              _camera_text(mine)))
    pyr = np.asarray(d["pyramid"], np.float64).ravel()
    ex = system.extractor
    if pyr.shape != (2,) or not np.isclose(pyr[0], ex.scale_factor) or int(pyr[1]) != ex.nlevels:
        raise PoseMapError("%s was made with ORB scale_factor/n_levels %s; this tracker uses "
                           "%g/%d (octaves would not compare)"
                           % (path, "/".join("%g" % v for v in pyr), ex.scale_factor, ex.nlevels))


def _slices(off: np.ndarray, K: int, total: int, name: str) -> np.ndarray:
    off = np.asarray(off, np.int64).ravel()
    if len(off) != K + 1 or off[0] != 0 or np.any(np.diff(off) < 0) or off[-1] != total:
        raise PoseMapError("corrupt pose map: %s does not index its %d rows" % (name, total))
    return off


def _build(d) -> Dict:
    """The map, keyframes and header values of a pose map, validated (nothing committed)."""
    _require(d, ["T_map_world", "next_kf_id", "n_loop_closures", "n_points", "kf_id",
                 "kf_frame_id", "kf_stamp", "kf_bad", "kf_parent", "kf_T_cw", "kf_has_T_cp",
                 "kf_T_cp", "kf_intrinsics", "kf_size", "kf_has_tex", "kf_kp_offsets",
                 "kf_tex_offsets", "tex_w", "kf_level_offsets", "scale", "inv_level_sigma2",
                 "kf_loop_offsets", "loop_edges", "kf_conn_offsets", "conn_ids", "conn_weights"]
             + ["kp_" + f[0] for f in KP_FIELDS] + list(MP_FIELDS))
    kf_id = np.asarray(d["kf_id"], np.int64).ravel()
    K = len(kf_id)
    n = int(d["n_points"])
    next_kf_id = int(d["next_kf_id"])
    T_map_world = np.asarray(d["T_map_world"], np.float64)
    if K == 0:
        raise PoseMapError("corrupt pose map: no keyframe")
    if T_map_world.shape != (4, 4) or not np.all(np.isfinite(T_map_world)):
        raise PoseMapError("corrupt pose map: T_map_world is not a finite 4x4 matrix")
    if len(np.unique(kf_id)) != K or kf_id.min() < 0 or kf_id.max() >= next_kf_id:
        raise PoseMapError("corrupt pose map: keyframe ids not unique or beyond next_kf_id")
    for name, shape in (("kf_frame_id", (K,)), ("kf_stamp", (K,)), ("kf_bad", (K,)),
                        ("kf_parent", (K,)), ("kf_T_cw", (K, 4, 4)), ("kf_has_T_cp", (K,)),
                        ("kf_T_cp", (K, 4, 4)), ("kf_intrinsics", (K, 8)), ("kf_size", (K, 3)),
                        ("kf_has_tex", (K,))):
        if d[name].shape != shape:
            raise PoseMapError("corrupt pose map: %s has shape %s, expected %s"
                               % (name, d[name].shape, shape))
    if not (np.all(np.isfinite(d["kf_T_cw"])) and np.all(np.isfinite(d["kf_T_cp"]))):
        raise PoseMapError("corrupt pose map: non-finite keyframe poses")
    # map points
    if n < 0:
        raise PoseMapError("corrupt pose map: n_points %d" % n)
    tmp = Map(capacity=max(4096, n + 1024))   # Map's own allocation: its dtypes and fill values
    for name in MP_FIELDS:
        a, dst = d[name], getattr(tmp, name)
        if a.shape != (n,) + dst.shape[1:]:
            raise PoseMapError("corrupt pose map: %s has shape %s, expected %s"
                               % (name, a.shape, (n,) + dst.shape[1:]))
        dst[:n] = a
    tmp.n = n
    tmp.next_kf_id = next_kf_id
    tmp.n_loop_closures = int(d["n_loop_closures"])
    # keyframes
    kp_off = _slices(d["kf_kp_offsets"], K, len(d["kp_uv"]), "kf_kp_offsets")
    kp = {}
    for name, dtype, shape in KP_FIELDS:
        a = d["kp_" + name]
        if a.shape != (kp_off[-1],) + shape:
            raise PoseMapError("corrupt pose map: kp_%s has shape %s" % (name, a.shape))
        kp[name] = a.astype(dtype, copy=False)
    mp_ids = kp["mp_ids"]
    if len(mp_ids) and (mp_ids.min() < -1 or mp_ids.max() >= n):
        raise PoseMapError("corrupt pose map: keypoints refer to map points beyond n_points")
    has_tex = d["kf_has_tex"].astype(bool)
    tex_off = _slices(d["kf_tex_offsets"], K, len(d["tex_w"]), "kf_tex_offsets")
    if np.any(np.diff(tex_off) != np.where(has_tex, np.diff(kp_off), 0)):
        raise PoseMapError("corrupt pose map: texture weights do not match the keypoints")
    lvl_off = _slices(d["kf_level_offsets"], K, len(d["scale"]), "kf_level_offsets")
    if d["inv_level_sigma2"].shape != d["scale"].shape or \
            np.any(np.diff(lvl_off) != d["kf_size"][:, 2]):
        raise PoseMapError("corrupt pose map: scale pyramids do not match their levels")
    loop_off = _slices(d["kf_loop_offsets"], K, len(d["loop_edges"]), "kf_loop_offsets")
    conn_off = _slices(d["kf_conn_offsets"], K, len(d["conn_ids"]), "kf_conn_offsets")
    if d["conn_weights"].shape != d["conn_ids"].shape:
        raise PoseMapError("corrupt pose map: conn_weights do not match conn_ids")
    known = set(kf_id.tolist())
    refs = np.concatenate([d["kf_parent"][d["kf_parent"] >= 0], d["loop_edges"], d["conn_ids"]])
    if not set(np.asarray(refs, np.int64).tolist()) <= known:
        raise PoseMapError("corrupt pose map: parents or graph edges name unknown keyframes")
    intr, size = d["kf_intrinsics"], d["kf_size"]
    kfs: Dict[int, KeyFrame] = {}
    for i in range(K):
        a, b = kp_off[i], kp_off[i + 1]
        la, lb = lvl_off[i], lvl_off[i + 1]
        fx, fy, cx, cy, bf, baseline, th_depth, log_scale = intr[i].tolist()
        kf = KeyFrame.from_fields(
            kf_id[i], d["kf_frame_id"][i], d["kf_stamp"][i],
            *(kp[name][a:b].copy() for name, _, _ in KP_FIELDS[:6]), mp_ids[a:b],
            d["kf_T_cw"][i], fx, fy, cx, cy, bf, baseline, th_depth,
            d["scale"][la:lb], d["inv_level_sigma2"][la:lb], log_scale,
            size[i, 2], size[i, 0], size[i, 1],
            tex_w=d["tex_w"][tex_off[i]:tex_off[i + 1]] if has_tex[i] else None)
        kf.bad = bool(d["kf_bad"][i])
        kf.T_cp = d["kf_T_cp"][i].copy() if d["kf_has_T_cp"][i] else None
        kf.loop_edges = d["loop_edges"][loop_off[i]:loop_off[i + 1]].astype(int).tolist()
        c = slice(conn_off[i], conn_off[i + 1])
        kf.connections = dict(zip(d["conn_ids"][c].astype(int).tolist(),
                                  d["conn_weights"][c].astype(int).tolist()))
        kfs[kf.id] = kf
    for i in range(K):
        p = int(d["kf_parent"][i])
        kfs[int(kf_id[i])].parent = kfs[p] if p >= 0 else None
    tmp.keyframes = kfs
    good = [k for k in kfs.values() if not k.bad]
    if not good:
        raise PoseMapError("corrupt pose map: every keyframe is culled")
    return {"map": tmp, "T_map_world": T_map_world, "good": good,
            "max_frame_id": int(np.max(d["kf_frame_id"]))}


def _images(d, mp: Map, camera) -> Dict[int, tuple]:
    """Kept keyframe images of the proximity loops, when stored and of this camera's size."""
    if "img_kf_ids" not in d or len(d["img_kf_ids"]) == 0:
        return {}
    _require(d, ["img_half", "img_quarter"])
    ids = np.asarray(d["img_kf_ids"], np.int64).ravel()
    half, quarter = d["img_half"], d["img_quarter"]
    w, h = camera.size
    h2, w2 = (h + 1) // 2, (w + 1) // 2   # cv2.pyrDown's size
    if half.dtype != np.uint8 or quarter.dtype != np.uint8 or \
            half.shape != (len(ids), h2, w2) or \
            quarter.shape != (len(ids), (h2 + 1) // 2, (w2 + 1) // 2):
        raise PoseMapError("corrupt pose map: keyframe images of shape %s / %s"
                           % (half.shape, quarter.shape))
    return {int(k): (half[i], quarter[i]) for i, k in enumerate(ids.tolist())
            if k in mp.keyframes and not mp.keyframes[k].bad}


def check_pose_map(path: str) -> Dict:
    """Read and validate a pose map file without a tracker (its camera is checked when it is
    loaded): PoseMapError when it is missing, truncated, corrupt or of another format version.
    Returns {"keyframes", "points"}."""
    d = _read(path)
    _check_format(d, path)
    try:
        got = _build(d)
    except PoseMapError:
        raise
    except (ValueError, TypeError, IndexError, KeyError) as e:
        raise PoseMapError("corrupt pose map %s: %s: %s" % (path, type(e).__name__, e)) from e
    m = got["map"]
    return {"keyframes": len(got["good"]), "points": int(np.count_nonzero(~m.mp_bad[: m.n]))}


def load_pose_map(system, path: str) -> Dict:
    """Restore a map saved by :func:`save_pose_map` into a freshly built System (no frame
    tracked yet): keyframes, map points, the loop closer's keyframe database (and kept images),
    T_map_world; tracking is left LOST so the next frame is relocalized against the loaded
    keyframes. Raises PoseMapError (the System left as it was) on a missing, truncated or
    corrupt file, another format version or another camera. Returns {"keyframes", "points",
    "images", "bytes", "seconds"}."""
    _check_system(system)
    t0 = time.perf_counter()
    mp, tr = system.map, system.tracking
    if mp.keyframes or mp.n or tr.state != NOT_INITIALIZED:
        raise PoseMapError("a pose map is loaded into a fresh System (this one has a map already)")
    d = _read(path)
    try:
        _check_header(d, path, system)
        got = _build(d)
        imgs = _images(d, got["map"], system.camera)
    except PoseMapError:
        raise
    except (ValueError, TypeError, IndexError, KeyError) as e:
        raise PoseMapError("corrupt pose map %s: %s: %s" % (path, type(e).__name__, e)) from e
    new_map, good = got["map"], got["good"]
    lc = getattr(system, "loop_closing", None)
    db = None
    if lc is not None:   # the keyframe database, as LoopClosing.process fills it
        db = KeyFrameDatabase(lc.voc)
        for kf in sorted(good, key=lambda k: k.id):
            db.add(kf.id, lc.bow(kf))
    ref = max(good, key=lambda k: k.id)
    # commit: plain assignments from here on (nothing left to fail half-way)
    with mp.lock:
        # the Map object is shared by Tracking, LocalMapping and LoopClosing: filled in place
        for name, value in vars(new_map).items():
            if name != "lock":
                setattr(mp, name, value)
        system.T_map_world = got["T_map_world"].copy()
        system.planar_recheck = True   # the floor plane in the loaded map's frame, at the next frame
        system.request_reset = False
        system.map_loaded = True
        mp.loaded_next_kf_id = mp.next_kf_id   # keyframes below it come from the saved run
        if lc is not None:
            lc.db = db
            lc.images.update(imgs)
        tr.state = LOST
        tr.ref_kf = ref
        tr.velocity = None
        tr.velocity_dt = 0.0
        tr.last_frame = None
        tr.local_kfs = [ref]
        tr.local_kf_ids = {ref.id}
        tr.reloc_tried = set()
        tr.last_reloc_frame_id = -10 ** 9
        tr.last_kf_frame_id = -10 ** 9
        # frame ids go on after the saved run's: keyframes made now have larger frame_id, as
        # in one run (ORB-SLAM3 restores Frame::nNextId likewise). Tracking's own frame-id
        # windows (last_reloc_frame_id, last_kf_frame_id) start over above.
        Frame._next_id = max(Frame._next_id, got["max_frame_id"] + 1)
    return {"keyframes": len(good), "points": int(np.count_nonzero(~mp.mp_bad[: mp.n])),
            "images": len(imgs), "bytes": int(os.path.getsize(path)),
            "seconds": time.perf_counter() - t0}
