"""Online calibration of a wheeled base's odometry against the tracker (not in ORB-SLAM2).

A differential drive's dead reckoning has systematic errors that grow with the distance driven
(Borenstein and Feng's UMBmark): a translation that reads long or short (the wheels' mean
diameter), a rotation that reads large or small (the wheelbase) and a yaw that creeps by a
fixed angle per metre (unequal wheel diameters). While the tracker follows the camera, each pair
of consecutive tracked frames measures them; while it is LOST (blank walls), the base coasts on
the odometry, and the corrected odometry keeps the pose close for many metres more than the raw
one, whose creeping yaw turns into a lateral error that grows with the square of the distance.

Per increment of the raw odometry in the base frame, translation ``t`` (its length ``m``, signed
``+`` forwards) and yaw ``b``, the model of the true increment (length ``d``, yaw ``a``) is::

    m = scale * d                     b = (1 + rot_scale) * a + drift * d

``scale`` comes from the lengths of chords of half a metre, ``(rot_scale, drift)`` from a
least-squares fit of ``b - a = rot_scale * a + drift * d`` over the tracked pairs, both with a
prior of no error worth ``PRIOR_M`` metres of driving (``PRIOR_RAD`` of turning), and data older
than ``HORIZON_M`` metres forgotten, so a change of load or floor is followed. Pairs that
disagree with the odometry by more than a wheel can (a relocalization, a map correction between
the two frames) are left out.
"""
from __future__ import annotations

import math
from typing import Optional, Tuple

import numpy as np

from ..geometry import inv_T

__all__ = ["OdometryCalibration"]

MIN_TRAVEL_M = 3.0        # m of tracked driving before the correction is applied
PRIOR_M = 2.0             # the prior of no error weighs as much as this many metres of data
PRIOR_RAD = math.pi       # ... and as this much turning, in steps of PRIOR_RAD_STEP per pair
PRIOR_RAD_STEP = 0.05
HORIZON_M = 200.0         # m: data this far back weighs 1/e
MAX_PAIR_GAP_S = 0.5      # s between two tracked frames that make a pair
SCALE_SEGMENT_M = 0.5     # m: the scale is fitted on chords of tracked driving this long
PAIR_GATE_M = 0.05        # m + PAIR_GATE_REL x travel: a pair whose lengths differ more is left out
PAIR_GATE_REL = 0.2
PAIR_GATE_DEG = 2.0       # deg + PAIR_GATE_DEG_PER_RAD x |yaw|: a pair whose yaws differ more ...
PAIR_GATE_DEG_PER_RAD = 10.0
MAX_SCALE_ERROR = 0.10    # the fitted errors are held to what a wheel can plausibly have
MAX_ROT_SCALE_ERROR = 0.10
MAX_DRIFT_DEG_PER_M = 5.0


def _planar(T: np.ndarray) -> Tuple[float, float, float]:
    return float(T[0, 3]), float(T[1, 3]), math.atan2(T[1, 0], T[0, 0])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class OdometryCalibration:
    """Systematic odometry errors fitted online, the raw odometry corrected with them (a chain of
    corrected increments) and the pose coasted on it while tracking is lost.

    Per frame: :meth:`correct` with the robot's raw ``T_odom_base`` (before tracking; returns
    the corrected ``T_odom_base``), then :meth:`observe` with the tracked
    ``T_map_base`` or None (LOST, relocalized). :meth:`coasted` is the ``T_map_base`` of the last
    tracked frame carried on by the corrected odometry since. Frames of base_link: the odometry's
    and the map's z axes are the floor's normal (REP-105)."""

    def __init__(self):
        self.sum_md = self.sum_dd = 0.0   # weighted sums of the fits (the prior: _solve)
        self.A = np.zeros((2, 2))
        self.y = np.zeros(2)
        self.travel = 0.0             # m of tracked driving used (not forgotten)
        self.n_pairs = self.n_refused = 0
        self.scale, self.rot_scale, self.drift = 1.0, 0.0, 0.0
        self._raw = None              # (stamp, raw T_odom_base) of the last correct() call
        self._chain = None            # the corrected T_odom_base there
        self._last_ok = None          # (stamp, raw, corrected, T_map_base) of the last tracked frame
        self._paired = False          # the last observed frame was tracked: the next one pairs
        self._segment = None          # (raw, T_map_base) where the current scale chord began

    # ------------------------------------------------------------------ the corrected chain
    def correct(self, stamp: float, T_odom_base: np.ndarray) -> np.ndarray:
        """The corrected ``T_odom_base`` at ``stamp`` (the raw one until calibrated, and after a
        clock that went back: the chain restarts there)."""
        T = np.asarray(T_odom_base, float)
        if self._raw is None or not float(stamp) >= self._raw[0]:
            self._chain = T.copy()
            self._last_ok, self._paired = None, False
        else:
            self._chain = self._chain @ self.corrected_increment(inv_T(self._raw[1]) @ T)
        self._raw = (float(stamp), T.copy())
        return self._chain.copy()

    def corrected_increment(self, D: np.ndarray) -> np.ndarray:
        """One raw increment ``D`` (4x4, in the base frame at its start) with the fitted errors
        taken out: its translation divided by ``scale``, its yaw ``(b - drift * d) / (1 +
        rot_scale)``. Identity errors until :attr:`calibrated`."""
        if not self.calibrated:
            return np.asarray(D, float).copy()
        D = np.asarray(D, float)
        t = D[:3, 3]
        m = float(np.hypot(t[0], t[1]))
        d = m / self.scale * (1.0 if t[0] >= 0.0 else -1.0)
        b = math.atan2(D[1, 0], D[0, 0])
        a = (b - self.drift * d) / (1.0 + self.rot_scale)
        out = np.eye(4)
        out[:3, :3] = _rot_z(a - b) @ D[:3, :3]
        out[:3, 3] = t / self.scale
        return out

    # ------------------------------------------------------------------ learning
    def observe(self, stamp: float, T_map_base: Optional[np.ndarray]) -> None:
        """The tracked base pose at ``stamp`` (the frame :meth:`correct` was last called for), or
        None when this frame was not tracked (the next tracked one starts a new pair)."""
        if T_map_base is None or self._raw is None or abs(self._raw[0] - float(stamp)) > 1e-9:
            self._paired = False     # no pair across an untracked frame (or one not corrected)
            self._segment = None
            return
        now = (float(stamp), self._raw[1], self._chain.copy(), np.asarray(T_map_base, float).copy())
        prev, self._last_ok = self._last_ok, now
        paired, self._paired = self._paired, True
        if prev is None or not paired or not 0.0 < now[0] - prev[0] <= MAX_PAIR_GAP_S:
            self._segment = None
            return
        raw = inv_T(prev[1]) @ now[1]
        trk = inv_T(prev[3]) @ now[3]
        mx, my, b = _planar(raw)
        tx, ty, a = _planar(trk)
        m = math.hypot(mx, my) * (1.0 if mx >= 0 else -1.0)
        d = math.hypot(tx, ty) * (1.0 if tx >= 0 else -1.0)
        if abs(abs(m) - abs(d)) > PAIR_GATE_M + PAIR_GATE_REL * abs(d) or \
                abs(math.degrees(_wrap(b - a))) > PAIR_GATE_DEG + PAIR_GATE_DEG_PER_RAD * abs(a):
            self.n_refused += 1
            self._segment = None
            return
        keep = math.exp(-abs(d) / HORIZON_M)
        self.sum_md *= keep
        self.sum_dd *= keep
        # the scale from chords of SCALE_SEGMENT_M: one pair's few centimetres would carry the
        # tracker's jitter into the squared lengths (a bias of percents)
        seg = self._segment
        if seg is None:
            self._segment = seg = (prev[1], prev[3])
        sm = float(np.linalg.norm((inv_T(seg[0]) @ now[1])[:2, 3]))
        sd = float(np.linalg.norm((inv_T(seg[1]) @ now[3])[:2, 3]))
        if sd >= SCALE_SEGMENT_M:
            self.sum_md += sm * sd
            self.sum_dd += sd * sd
            self._segment = (now[1], now[3])
        x = np.array([a, d])
        self.A = keep * self.A + np.outer(x, x)
        self.y = keep * self.y + x * _wrap(b - a)
        self.travel += abs(d)
        self.n_pairs += 1
        self._solve()

    def _solve(self) -> None:
        # the prior: PRIOR_M metres of driving, in steps of the pairs' mean length, with no error
        step = self.travel / max(self.n_pairs, 1)
        w = PRIOR_M * step                       # sum of d^2 of PRIOR_M metres in such steps
        ws = PRIOR_M * SCALE_SEGMENT_M           # the same in chords
        wr = PRIOR_RAD * PRIOR_RAD_STEP          # sum of a^2 of PRIOR_RAD of turning
        self.scale = float(np.clip((self.sum_md + ws) / (self.sum_dd + ws),
                                   1.0 - MAX_SCALE_ERROR, 1.0 + MAX_SCALE_ERROR))
        A = self.A + np.diag([wr, w])
        r, k = np.linalg.solve(A, self.y)
        self.rot_scale = float(np.clip(r, -MAX_ROT_SCALE_ERROR, MAX_ROT_SCALE_ERROR))
        lim = math.radians(MAX_DRIFT_DEG_PER_M)
        self.drift = float(np.clip(k, -lim, lim))

    @property
    def calibrated(self) -> bool:
        return self.travel >= MIN_TRAVEL_M

    # ------------------------------------------------------------------ coasting
    def coasted(self) -> Optional[np.ndarray]:
        """``T_map_base`` of the last tracked frame moved on by the corrected odometry since, at
        the stamp of the last :meth:`correct`; None before any tracked frame (or after the
        chain restarted)."""
        if self._last_ok is None or self._chain is None:
            return None
        return self._last_ok[3] @ inv_T(self._last_ok[2]) @ self._chain

    def errors(self) -> Tuple[float, float, float, float]:
        """(scale, rot_scale, drift in deg per metre, metres of tracked driving fitted on)."""
        return (self.scale, self.rot_scale, math.degrees(self.drift), self.travel)

    def summary(self) -> str:
        return ("odometry calibration: scale %.4f, rotation scale %+.4f, yaw drift %+.3f deg/m "
                "(%.1f m tracked, %d pairs, %d refused)%s"
                % (self.scale, self.rot_scale, math.degrees(self.drift), self.travel,
                   self.n_pairs, self.n_refused, "" if self.calibrated else ", not applied yet"))
