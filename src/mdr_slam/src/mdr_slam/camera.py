"""Stereo camera model: intrinsics, distortion, rectification (the CameraInfo D, K, R, P model).

A :class:`CameraModel` is exactly what a ``sensor_msgs/CameraInfo`` carries, as numpy arrays, so
the depth and pose nodes can work from the CameraInfo pair of a bag, and the calibration loaders
(EuRoC ``sensor.yaml``, Kalibr ``camchain.yaml``, ROS camera_info YAML) produce the same objects.

A :class:`StereoCamera` is the rectified pair the algorithms use: focal length ``fx, fy``,
principal point ``cx, cy``, baseline ``B`` (metres) and size, plus the remap tables that turn raw
images into rectified ones (identity when the input is already rectified).

Rectified images may come with the raw calibration (stereo_image_proc's ``image_rect`` topics
publish the raw camera_info): :func:`images_are_rectified` decides from a setting and the topic
name, and :meth:`StereoCamera.assume_rectified` makes the camera that does not rectify again.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Optional, Tuple, Union

import cv2
import numpy as np

__all__ = ["CameraModel", "StereoCamera", "CalibrationError", "images_are_rectified"]


class CalibrationError(ValueError):
    """Calibration that cannot be used (missing, zero, inconsistent)."""


@dataclass
class CameraModel:
    """One camera as in sensor_msgs/CameraInfo (ROS image_pipeline conventions)."""

    width: int
    height: int
    K: np.ndarray                       # 3x3 intrinsics of the raw image
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))  # distortion coefficients
    R: np.ndarray = field(default_factory=lambda: np.eye(3))    # rectification rotation
    P: Optional[np.ndarray] = None      # 3x4 projection of the rectified image
    distortion_model: str = "plumb_bob"
    frame_id: str = ""

    def __post_init__(self):
        self.K = np.asarray(self.K, dtype=float).reshape(3, 3)
        self.D = np.asarray(self.D, dtype=float).reshape(-1)
        self.R = np.asarray(self.R, dtype=float).reshape(3, 3)
        if self.P is None:
            self.P = np.hstack([self.K, np.zeros((3, 1))])
        self.P = np.asarray(self.P, dtype=float).reshape(3, 4)
        self.width = int(self.width)
        self.height = int(self.height)

    def validate(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError("camera size is %dx%d" % (self.width, self.height))
        for name, M in (("K", self.K), ("P", self.P), ("R", self.R), ("D", self.D)):
            if not np.all(np.isfinite(M)):
                raise CalibrationError("camera %s has non-finite values" % name)
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0 or self.P[0, 0] <= 0 or self.P[1, 1] <= 0:
            raise CalibrationError("camera focal length is zero or negative (K=%s, P=%s)"
                                   % (self.K.ravel().tolist(), self.P.ravel().tolist()))

    @property
    def is_rectified(self) -> bool:
        """True when the raw image already equals the rectified one (no distortion, R = I, P ~ K)."""
        # allclose's own tolerances (1e-8 + 1e-5 |b|) without its per-call overhead (per frame)
        return (not np.any(self.D)) and \
            bool(np.all(np.abs(self.R - np.eye(3)) <= 1e-8 + 1e-5)) and \
            bool(np.all(np.abs(self.P[:, :3] - self.K) <= 1e-8 + 1e-5 * np.abs(self.K)))


@dataclass
class StereoCamera:
    """A rectified stereo pair: everything the stereo matcher and the filters need."""

    left: CameraModel
    right: CameraModel

    def __post_init__(self):
        self.left.validate()
        self.right.validate()
        if (self.left.width, self.left.height) != (self.right.width, self.right.height):
            raise CalibrationError("left %dx%d and right %dx%d camera sizes differ" % (
                self.left.width, self.left.height, self.right.width, self.right.height))
        # ROS convention: P_right[0, 3] = -fx' * B (B > 0 for a right camera to the right).
        if not self.baseline > 0:
            raise CalibrationError("stereo baseline is %r; right P[0,3] must be -fx*B with B > 0"
                                   % self.baseline)
        self._maps = None

    # --- rectified intrinsics (from the left P, as image_geometry does)
    @property
    def fx(self) -> float:
        return float(self.left.P[0, 0])

    @property
    def fy(self) -> float:
        return float(self.left.P[1, 1])

    @property
    def cx(self) -> float:
        return float(self.left.P[0, 2])

    @property
    def cy(self) -> float:
        return float(self.left.P[1, 2])

    @property
    def baseline(self) -> float:
        """Baseline in metres: -(P_r[0,3] - P_l[0,3]) / fx."""
        return float(-(self.right.P[0, 3] - self.left.P[0, 3]) / self.right.P[0, 0])

    @property
    def doffs(self) -> float:
        """Principal point difference ``cx_left - cx_right`` of the rectified pair (px): a measured
        disparity ``d = u_left - u_right`` means depth ``Z = f*B / (d - doffs)`` (image_geometry's
        StereoCameraModel::getZ; Middlebury's ``doffs``). 0 when the rectification gave both
        cameras the same principal point (OpenCV's CALIB_ZERO_DISPARITY, KITTI's calib.txt); a
        calibration that is off by a fraction of a pixel is corrected by the right P's cx."""
        return float(self.left.P[0, 2] - self.right.P[0, 2])

    def with_doffs(self, doffs: float) -> "StereoCamera":
        """A copy whose right principal point gives ``doffs`` (P, and K for rectified images).
        Raw images keep this camera's rectification maps: the same rectified pixels, read with
        the corrected principal point (in a calibration file of raw images P also defines the
        rectification, so there the fix is a new stereo calibration)."""
        maps = None if self.is_rectified else self.rectify_maps()
        left, right = copy.deepcopy(self.left), copy.deepcopy(self.right)
        cx_r = float(left.P[0, 2]) - float(doffs)
        if self.right.is_rectified:
            right.K[0, 2] = cx_r
        right.P[0, 2] = cx_r
        cam = StereoCamera(left, right)
        cam._maps = maps
        return cam

    def assume_rectified(self) -> "StereoCamera":
        """A copy for images that are already rectified: each side's raw model is its rectified
        one (K = P[:3, :3], no distortion, R = I; P, size and frame unchanged), so
        :meth:`rectify` passes images through and fx, baseline and doffs are what P says."""
        def rect(m: CameraModel) -> CameraModel:
            return CameraModel(m.width, m.height, m.P[:, :3].copy(), np.zeros(5), np.eye(3),
                               m.P.copy(), distortion_model="plumb_bob", frame_id=m.frame_id)
        return StereoCamera(rect(self.left), rect(self.right))

    @property
    def size(self) -> Tuple[int, int]:
        """(width, height)."""
        return self.left.width, self.left.height

    @property
    def K_rect(self) -> np.ndarray:
        """3x3 intrinsics of the rectified left image."""
        return self.left.P[:, :3].copy()

    @property
    def is_rectified(self) -> bool:
        return self.left.is_rectified and self.right.is_rectified

    # --- rectification
    def rectify_maps(self):
        """cv2.remap tables (left, right), computed once from (K, D, R, P)."""
        if self._maps is None:
            maps = []
            for cam in (self.left, self.right):
                if cam.distortion_model in ("equidistant", "fisheye"):
                    m1, m2 = cv2.fisheye.initUndistortRectifyMap(
                        cam.K, cam.D[:4], cam.R, cam.P[:, :3], (cam.width, cam.height),
                        cv2.CV_16SC2)
                else:
                    m1, m2 = cv2.initUndistortRectifyMap(
                        cam.K, cam.D, cam.R, cam.P[:, :3], (cam.width, cam.height), cv2.CV_16SC2)
                maps.append((m1, m2))
            self._maps = maps
        return self._maps

    def rectify(self, left: np.ndarray, right: np.ndarray):
        """Rectify a raw pair (pass-through when the calibration says it is rectified)."""
        if self.is_rectified:
            return left, right
        (l1, l2), (r1, r2) = self.rectify_maps()
        return (cv2.remap(left, l1, l2, cv2.INTER_LINEAR),
                cv2.remap(right, r1, r2, cv2.INTER_LINEAR))

    # --- geometry in the rectified left camera
    def disparity_to_depth(self, disparity: np.ndarray) -> np.ndarray:
        """Z = f*B/(d - doffs); non-positive disparities (no match) give NaN."""
        d = np.asarray(disparity, dtype=np.float32)
        dc = d - np.float32(self.doffs)
        with np.errstate(divide="ignore", invalid="ignore"):
            Z = np.float32(self.fx * self.baseline) / dc
        Z[~((d > 0) & (dc > 0))] = np.nan
        return Z

    def backproject(self, u: np.ndarray, v: np.ndarray, Z: np.ndarray) -> np.ndarray:
        """(N, 3) points in the left optical frame from pixel coordinates and depths."""
        X = (np.asarray(u, dtype=np.float32) - self.cx) * Z / self.fx
        Y = (np.asarray(v, dtype=np.float32) - self.cy) * Z / self.fy
        return np.stack([X, Y, np.asarray(Z, dtype=np.float32)], axis=-1)

    def project(self, P: np.ndarray):
        """Pixel coordinates (u, v) and depth Z of (N, 3) points in the left optical frame."""
        Z = P[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * P[:, 0] / Z + self.cx
            v = self.fy * P[:, 1] / Z + self.cy
        return u, v, Z

    @classmethod
    def from_rectified(cls, width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                       baseline: float, frame_id: str = "", doffs: float = 0.0) -> "StereoCamera":
        """An ideal rectified pair (simulator, KITTI): same K for both (the right cx is
        ``cx - doffs``), R = I, no distortion."""
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        Pl = np.hstack([K, np.zeros((3, 1))])
        Kr = K.copy()
        Kr[0, 2] = cx - doffs
        Pr = np.hstack([Kr, np.zeros((3, 1))])
        Pr[0, 3] = -fx * baseline
        return cls(CameraModel(width, height, K, np.zeros(5), np.eye(3), Pl, frame_id=frame_id),
                   CameraModel(width, height, Kr, np.zeros(5), np.eye(3), Pr, frame_id=frame_id))


def images_are_rectified(setting: Union[str, bool], topic: Optional[str], camera) -> bool:
    """Whether the images on ``topic`` are rectified, for a ``rectified`` parameter.

    ``setting`` "true"/"false" (or a bool) forces the answer. "auto" says rectified when the
    topic's last name (ignoring an image_transport ``compressed`` suffix) starts with
    "image_rect" (stereo_image_proc's ``image_rect``, ZED's ``image_rect_color``, RealSense's
    ``image_rect_raw``), since those come with the raw camera_info; otherwise it is what the
    calibration says (``camera.is_rectified``, a CameraModel or StereoCamera).
    """
    if isinstance(setting, (bool, np.bool_)):
        return bool(setting)
    s = setting.strip().lower() if isinstance(setting, str) else None
    if s in ("true", "false"):
        return s == "true"
    if s != "auto":
        raise ValueError("rectified must be 'auto', 'true' or 'false', not %r" % (setting,))
    names = [n for n in (topic or "").split("/") if n]
    if len(names) > 1 and names[-1] in ("compressed", "theora"):
        names.pop()
    if names and names[-1].startswith("image_rect"):
        return True
    return bool(camera.is_rectified)
