"""Stereo calibration files -> :class:`~mdr_slam.camera.StereoCamera` (CameraInfo D, K, R, P pairs).

Supported, as the nodes' ``calib`` parameter and the importers need them:

* EuRoC / ASL ``sensor.yaml`` pair (``cam0``, ``cam1``): ``T_BS`` (sensor in body), intrinsics
  ``fu fv cu cv``, radial-tangential distortion, resolution;
* Kalibr ``camchain.yaml``: ``cam0``/``cam1`` with ``intrinsics``, ``distortion_coeffs``,
  ``distortion_model`` (``radtan`` or ``equidistant``), ``resolution`` and ``cam1.T_cn_cnm1``;
* ROS camera_info YAML (camera_calibration's format): a (left, right) pair of files, or one file
  with ``left:`` and ``right:`` sections;
* KITTI odometry ``calib.txt`` (already rectified: ``P0``, ``P1`` rows).

Raw (unrectified) pairs are rectified with ``cv2.stereoRectify`` (``alpha=0`` so the rectified
image has no black border, ``CALIB_ZERO_DISPARITY`` so both principal points coincide): this yields
exactly what ROS's camera_info carries for a stereo pair, R1/R2 as ``R`` and P1/P2 as ``P`` with
``P_right[0, 3] = -fx * B`` (OpenCV and ROS share that convention).
"""
from __future__ import annotations

import glob
import os
import re
from typing import Dict, List, Optional, Sequence, Tuple, Union

import cv2
import numpy as np
import yaml

from .camera import CalibrationError, CameraModel, StereoCamera
from .geometry import inv_T

__all__ = [
    "CalibrationError", "load_stereo_calibration", "load_euroc_calibration",
    "load_kalibr_calibration", "load_camera_info_yaml", "load_camera_info_pair",
    "load_kitti_calibration", "rectify_stereo", "euroc_T_BS",
]

PathLike = Union[str, Sequence[str]]


# --------------------------------------------------------------------------------------- helpers
def _read_yaml(path: str) -> dict:
    """YAML text of ``path``; OpenCV's ``%YAML:1.0`` header (EuRoC) is not valid for PyYAML."""
    if not os.path.isfile(path):
        raise CalibrationError("calibration file %s does not exist" % path)
    with open(path) as f:
        text = "".join(line for line in f if not line.startswith("%"))
    # OpenCV FileStorage writes "!!opencv-matrix" tags; treat them as plain mappings.
    text = re.sub(r"!!opencv-matrix", "", text)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise CalibrationError("%s is not valid YAML: %s" % (path, e))
    if not isinstance(data, dict):
        raise CalibrationError("%s does not hold a YAML mapping" % path)
    return data


def _need(d: dict, key: str, where: str):
    if key not in d or d[key] is None:
        raise CalibrationError("%s: missing '%s'" % (where, key))
    return d[key]


def _matrix(value, rows: int, cols: int, where: str) -> np.ndarray:
    """A matrix given as ``{rows, cols, data}`` (ROS/OpenCV YAML) or as a (nested) list."""
    if isinstance(value, dict):
        value = _need(value, "data", where)
    try:
        M = np.asarray(value, dtype=float).reshape(rows, cols)
    except (ValueError, TypeError):
        raise CalibrationError("%s: expected %dx%d numbers, got %r" % (where, rows, cols, value))
    if not np.all(np.isfinite(M)):
        raise CalibrationError("%s: non-finite values" % where)
    return M


def _size(value, where: str) -> Tuple[int, int]:
    try:
        w, h = [int(v) for v in value]
    except (ValueError, TypeError):
        raise CalibrationError("%s: resolution must be [width, height], got %r" % (where, value))
    if w <= 0 or h <= 0:
        raise CalibrationError("%s: resolution is %dx%d" % (where, w, h))
    return w, h


def _intrinsics(values, where: str) -> np.ndarray:
    try:
        fu, fv, cu, cv_ = [float(v) for v in values]
    except (ValueError, TypeError):
        raise CalibrationError("%s: intrinsics must be [fu, fv, cu, cv], got %r" % (where, values))
    if fu <= 0 or fv <= 0:
        raise CalibrationError("%s: focal length is zero or negative (fu=%g, fv=%g)" % (where, fu, fv))
    return np.array([[fu, 0.0, cu], [0.0, fv, cv_], [0.0, 0.0, 1.0]])


def _distortion(model: str, coeffs, where: str) -> Tuple[str, np.ndarray]:
    """(ROS distortion_model, D) from an ASL/Kalibr model name and coefficients."""
    D = np.asarray(coeffs if coeffs is not None else [], dtype=float).reshape(-1)
    m = (model or "radtan").lower()
    if m in ("radtan", "radial-tangential", "plumb_bob", "rational_polynomial"):
        if len(D) not in (0, 4, 5, 8):
            raise CalibrationError("%s: radial-tangential needs 4, 5 or 8 coefficients, got %d"
                                   % (where, len(D)))
        D5 = np.zeros(5) if len(D) < 5 else D
        if len(D) == 4:
            D5[:4] = D
        return ("rational_polynomial" if len(D5) == 8 else "plumb_bob"), D5
    if m in ("equidistant", "fisheye", "equi"):
        if len(D) != 4:
            raise CalibrationError("%s: equidistant needs 4 coefficients, got %d" % (where, len(D)))
        return "equidistant", D
    raise CalibrationError("%s: unsupported distortion model %r (radtan or equidistant)" % (where, model))


def _check_T(T: np.ndarray, where: str) -> np.ndarray:
    R = T[:3, :3]
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-4) and abs(np.linalg.det(R) - 1) < 1e-4):
        raise CalibrationError("%s: the rotation part is not a rotation matrix" % where)
    if not np.linalg.norm(T[:3, 3]) > 0:
        raise CalibrationError("%s: zero baseline between the two cameras" % where)
    return T


# ---------------------------------------------------------------------------- rectification
def rectify_stereo(K0: np.ndarray, D0: np.ndarray, K1: np.ndarray, D1: np.ndarray,
                   size: Tuple[int, int], T_cam1_cam0: np.ndarray,
                   distortion_model: str = "plumb_bob", frame_ids: Tuple[str, str] = ("", "")
                   ) -> StereoCamera:
    """Rectify a raw stereo pair: R1, R2, P1, P2 from ``cv2.stereoRectify`` as CameraInfo R, P.

    ``T_cam1_cam0`` maps left-camera points into the right camera (OpenCV's R, T). ``alpha=0``
    crops to valid pixels only (no black border reaching the stereo matcher);
    ``CALIB_ZERO_DISPARITY`` makes the principal points equal so depth is ``fx*B/d``.
    """
    R = np.ascontiguousarray(T_cam1_cam0[:3, :3])
    t = np.ascontiguousarray(T_cam1_cam0[:3, 3].reshape(3, 1))
    w, h = int(size[0]), int(size[1])
    if distortion_model == "equidistant":
        R1, R2, P1, P2, _Q = cv2.fisheye.stereoRectify(
            K0, D0[:4].reshape(4, 1), K1, D1[:4].reshape(4, 1), (w, h), R, t,
            flags=cv2.CALIB_ZERO_DISPARITY, newImageSize=(w, h), balance=0.0, fov_scale=1.0)
    else:
        R1, R2, P1, P2, _Q, _r1, _r2 = cv2.stereoRectify(
            K0, D0, K1, D1, (w, h), R, t, flags=cv2.CALIB_ZERO_DISPARITY, alpha=0,
            newImageSize=(w, h))
    if abs(P2[0, 3]) < abs(P2[1, 3]):
        raise CalibrationError("the stereo pair is vertical (baseline along y); only horizontal "
                               "left/right pairs are supported")
    left = CameraModel(w, h, K0, D0, R1, P1, distortion_model, frame_ids[0])
    right = CameraModel(w, h, K1, D1, R2, P2, distortion_model, frame_ids[1])
    return StereoCamera(left, right)


# ---------------------------------------------------------------------------------- EuRoC
def euroc_T_BS(path: str) -> np.ndarray:
    """``T_BS`` (sensor -> body) of an ASL ``sensor.yaml``."""
    d = _read_yaml(path)
    T = _matrix(_need(d, "T_BS", path), 4, 4, path + ": T_BS")
    return T


def _euroc_camera(path: str):
    d = _read_yaml(path)
    where = path
    T_BS = _matrix(_need(d, "T_BS", where), 4, 4, where + ": T_BS")
    K = _intrinsics(_need(d, "intrinsics", where), where)
    model, D = _distortion(d.get("distortion_model", "radial-tangential"),
                           d.get("distortion_coefficients"), where)
    size = _size(_need(d, "resolution", where), where)
    return T_BS, K, D, model, size


def _euroc_yaml_pair(path: str) -> Tuple[str, str]:
    """(cam0, cam1) sensor.yaml paths from a sequence folder, ``mav0``, or either yaml."""
    if os.path.isfile(path):
        cam_dir = os.path.dirname(os.path.abspath(path))
        base = os.path.dirname(cam_dir)
        return os.path.join(base, "cam0", "sensor.yaml"), os.path.join(base, "cam1", "sensor.yaml")
    for base in (os.path.join(path, "mav0"), path):
        c0 = os.path.join(base, "cam0", "sensor.yaml")
        if os.path.isfile(c0):
            return c0, os.path.join(base, "cam1", "sensor.yaml")
    raise CalibrationError("%s: no EuRoC cam0/sensor.yaml found (looked in mav0/ and the folder)"
                           % path)


def load_euroc_calibration(cam0_yaml: str, cam1_yaml: Optional[str] = None) -> StereoCamera:
    """EuRoC ``sensor.yaml`` pair -> rectified StereoCamera.

    ``cam0_yaml`` may also be the sequence folder or ``mav0``; ``cam1_yaml`` defaults to the
    sibling ``cam1/sensor.yaml``. T_cam1_cam0 = T_BS1^-1 T_BS0 (both cameras in the body frame).
    """
    if cam1_yaml is None:
        cam0_yaml, cam1_yaml = _euroc_yaml_pair(cam0_yaml)
    T0, K0, D0, m0, s0 = _euroc_camera(cam0_yaml)
    T1, K1, D1, m1, s1 = _euroc_camera(cam1_yaml)
    if s0 != s1:
        raise CalibrationError("cam0 %dx%d and cam1 %dx%d resolutions differ" % (s0 + s1))
    if m0 != m1:
        raise CalibrationError("cam0 and cam1 distortion models differ (%s, %s)" % (m0, m1))
    T_c1_c0 = _check_T(inv_T(T1) @ T0, "%s/%s T_BS" % (cam0_yaml, cam1_yaml))
    return rectify_stereo(K0, D0, K1, D1, s0, T_c1_c0, m0)


# ---------------------------------------------------------------------------------- Kalibr
def load_kalibr_calibration(path: str) -> StereoCamera:
    """Kalibr ``camchain.yaml`` (cam0 left, cam1 right with ``T_cn_cnm1`` = T_cam1_cam0)."""
    d = _read_yaml(path)
    cams = []
    for name in ("cam0", "cam1"):
        c = _need(d, name, path)
        where = "%s: %s" % (path, name)
        model = c.get("camera_model", "pinhole")
        if model != "pinhole":
            raise CalibrationError("%s: camera_model %r is not supported (pinhole only)" % (where, model))
        K = _intrinsics(_need(c, "intrinsics", where), where)
        dm, D = _distortion(c.get("distortion_model", "radtan"), c.get("distortion_coeffs"), where)
        cams.append((K, D, dm, _size(_need(c, "resolution", where), where)))
    (K0, D0, m0, s0), (K1, D1, m1, s1) = cams
    if s0 != s1 or m0 != m1:
        raise CalibrationError("%s: cam0 and cam1 differ in resolution or distortion model" % path)
    T = _check_T(_matrix(_need(d["cam1"], "T_cn_cnm1", path + ": cam1"), 4, 4,
                         path + ": cam1.T_cn_cnm1"), path + ": cam1.T_cn_cnm1")
    return rectify_stereo(K0, D0, K1, D1, s0, T, m0)


# ------------------------------------------------------------------------- ROS camera_info
def _camera_info_model(d: dict, where: str) -> CameraModel:
    w = int(_need(d, "image_width", where))
    h = int(_need(d, "image_height", where))
    K = _matrix(_need(d, "camera_matrix", where), 3, 3, where + ": camera_matrix")
    Dv = _need(d, "distortion_coefficients", where)
    Dv = Dv.get("data", []) if isinstance(Dv, dict) else Dv
    D = np.asarray(Dv if Dv is not None else [], dtype=float).reshape(-1)
    R = _matrix(d.get("rectification_matrix", np.eye(3).ravel().tolist()), 3, 3,
                where + ": rectification_matrix")
    P = _matrix(_need(d, "projection_matrix", where), 3, 4, where + ": projection_matrix")
    model = d.get("distortion_model", "plumb_bob")
    if K[0, 0] <= 0 or P[0, 0] <= 0:
        raise CalibrationError("%s: zero focal length in camera_matrix or projection_matrix" % where)
    cam = CameraModel(w, h, K, D, R, P, model, d.get("camera_name", "") or "")
    cam.frame_id = ""
    try:
        cam.validate()
    except CalibrationError as e:
        raise CalibrationError("%s: %s" % (where, e))
    return cam


def load_camera_info_yaml(path: str) -> CameraModel:
    """One camera_calibration YAML (``image_width``, ``camera_matrix``, ...) -> CameraModel."""
    return _camera_info_model(_read_yaml(path), path)


def load_camera_info_pair(left: str, right: Optional[str] = None) -> StereoCamera:
    """camera_info YAML pair, or one file with ``left:`` / ``right:`` sections."""
    if right is None:
        d = _read_yaml(left)
        if "left" not in d or "right" not in d:
            raise CalibrationError("%s: a single camera_info file needs 'left:' and 'right:' "
                                   "sections (or give two files)" % left)
        return StereoCamera(_camera_info_model(d["left"], left + ": left"),
                            _camera_info_model(d["right"], left + ": right"))
    return StereoCamera(load_camera_info_yaml(left), load_camera_info_yaml(right))


# ----------------------------------------------------------------------------------- KITTI
def _kitti_rows(path: str) -> Dict[str, np.ndarray]:
    rows: Dict[str, np.ndarray] = {}
    plain: List[np.ndarray] = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            if ":" in line:
                key, _, vals = line.partition(":")
                rows[key.strip()] = np.array(vals.split(), dtype=float)
            else:
                plain.append(np.array(line.split(), dtype=float))
    for i, v in enumerate(plain):  # rows without "P0:" prefixes are P0, P1, ... in order
        rows.setdefault("P%d" % i, v)
    return rows


def load_kitti_calibration(path: str, size: Tuple[int, int],
                           left: str = "P0", right: str = "P1",
                           doffs: Optional[float] = None) -> StereoCamera:
    """KITTI odometry ``calib.txt`` (rectified: P0 left grey, P1 right grey) -> StereoCamera.

    ``size`` is (width, height) of the images (calib.txt does not say it). The baseline is
    ``-(P1[0,3] - P0[0,3]) / fx`` (0.5372 m for the grey pair). ``doffs`` overrides the principal
    point difference (the right cx becomes ``P0 cx - doffs``; calib.txt gives both the same cx,
    but on sequence 06 the disparities measure -0.16 to -0.21 px against the ground truth:
    scripts/check_stereo_offset.py, docs/benchmarks.md "Stereo calibration check").
    """
    if not os.path.isfile(path):
        raise CalibrationError("KITTI calibration %s does not exist" % path)
    rows = _kitti_rows(path)
    Ps = []
    for key in (left, right):
        if key not in rows or rows[key].size != 12:
            raise CalibrationError("%s: missing or malformed %s row (12 values)" % (path, key))
        Ps.append(rows[key].reshape(3, 4))
    Pl, Pr = Ps
    if Pl[0, 0] <= 0:
        raise CalibrationError("%s: zero focal length in %s" % (path, left))
    w, h = int(size[0]), int(size[1])
    K = Pl[:, :3].copy()
    # Make the left P carry no translation (ROS: the left camera is the stereo origin).
    Pr = Pr.copy()
    Pr[:, 3] = Pr[:, 3] - Pl[:, 3]
    Pl = np.hstack([K, np.zeros((3, 1))])
    if doffs is not None:
        Pr[0, 2] = K[0, 2] - float(doffs)
    return StereoCamera(CameraModel(w, h, K, np.zeros(5), np.eye(3), Pl),
                        CameraModel(w, h, Pr[:, :3].copy(), np.zeros(5), np.eye(3), Pr))


# ----------------------------------------------------------------------------------- guess
def load_stereo_calibration(path_or_paths: PathLike,
                            size: Optional[Tuple[int, int]] = None) -> StereoCamera:
    """Load a stereo calibration, guessing the format.

    Accepts: a (left, right) pair of paths (EuRoC sensor.yaml or camera_info YAML), a string
    ``"left.yaml,right.yaml"`` (the nodes' ``calib`` parameter), an EuRoC sequence / ``mav0``
    folder or one of its ``sensor.yaml``, a Kalibr camchain, a camera_info YAML with
    ``left``/``right`` sections, or a KITTI ``calib.txt`` (needs ``size``, or finds an image
    beside it).
    """
    if isinstance(path_or_paths, str) and "," in path_or_paths:
        path_or_paths = [p.strip() for p in path_or_paths.split(",") if p.strip()]
    if not isinstance(path_or_paths, str):
        paths = list(path_or_paths)
        if len(paths) == 1:
            return load_stereo_calibration(paths[0], size)
        if len(paths) != 2:
            raise CalibrationError("give one calibration file or a (left, right) pair, got %d paths"
                                   % len(paths))
        d = _read_yaml(paths[0])
        if "T_BS" in d:
            return load_euroc_calibration(paths[0], paths[1])
        return load_camera_info_pair(paths[0], paths[1])
    path = path_or_paths
    if not path:
        raise CalibrationError("no calibration file given")
    if os.path.isdir(path):
        if os.path.isfile(os.path.join(path, "calib.txt")):
            return load_stereo_calibration(os.path.join(path, "calib.txt"), size)
        return load_euroc_calibration(path)
    if not os.path.isfile(path):
        raise CalibrationError("calibration file %s does not exist" % path)
    if path.endswith(".txt"):
        if size is None:
            size = _kitti_image_size(os.path.dirname(os.path.abspath(path)))
        return load_kitti_calibration(path, size)
    d = _read_yaml(path)
    if "cam0" in d and "cam1" in d:
        return load_kalibr_calibration(path)
    if "T_BS" in d:
        return load_euroc_calibration(path)
    if "left" in d and "right" in d:
        return load_camera_info_pair(path)
    if "camera_matrix" in d:
        raise CalibrationError("%s holds one camera_info; give the (left, right) pair "
                               "(\"left.yaml,right.yaml\")" % path)
    raise CalibrationError("%s: unknown calibration format (expected EuRoC sensor.yaml, Kalibr "
                           "camchain, ROS camera_info YAML or KITTI calib.txt)" % path)


def _kitti_image_size(folder: str) -> Tuple[int, int]:
    for sub in ("image_0", "image_l"):
        files = sorted(glob.glob(os.path.join(folder, sub, "*.png")))
        if files:
            img = cv2.imread(files[0], cv2.IMREAD_UNCHANGED)
            if img is not None:
                return img.shape[1], img.shape[0]
    raise CalibrationError("%s: KITTI calib.txt has no image size; give size=(w, h)" % folder)
