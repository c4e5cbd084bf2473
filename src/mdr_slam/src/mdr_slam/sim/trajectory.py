"""Simulator trajectories: smooth, deterministic per seed, analytic in time.

Each trajectory is a function of time (so motion blur can render sub-poses between frames) giving
``T_map_cam`` of the left camera optical frame (z forward, x right, y down) in the z-up ``map``.
Kinds, chosen to exercise what the paper's indoor sequences stress:

- ``loop``: an ellipse around the room looking outwards, returning exactly to its start pose
  (loop closure);
- ``pure_rotation``: the camera stands still and sweeps its yaw (no parallax: monocular
  initialisation and depth triangulation fail, stereo must carry it);
- ``loop+pure_rotation``: the loop with a stop-and-sweep segment in the middle (office, garage);
- ``corner``: a corridor drive through a 90-degree corner with fast yaw rate (corridor).
"""
from __future__ import annotations

from typing import List, Tuple, Union

import numpy as np

from .scene import SCENES, Scene, _Builder, _LAYOUTS

__all__ = ["SimTrajectory", "build_trajectory", "make_trajectory", "camera_rotation", "KINDS"]

KINDS = ("loop", "pure_rotation", "loop+pure_rotation", "corner")
_DEFAULT_SCENE = {"loop": "office", "pure_rotation": "office", "loop+pure_rotation": "office",
                  "corner": "corridor"}


def camera_rotation(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """(N, 3, 3) R_map_cam of an optical frame looking along ``yaw`` (rad, from map +x towards
    +y), tilted down by ``pitch`` (rad), no roll. Columns: right (x), down (y), forward (z)."""
    yaw, pitch = np.broadcast_arrays(np.asarray(yaw, float), np.asarray(pitch, float))
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    f = np.stack([cp * cy, cp * sy, -sp], -1)
    r = np.stack([sy, -cy, np.zeros_like(yaw)], -1)
    d = np.cross(f, r)
    return np.stack([r, d, f], -1)


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


class SimTrajectory:
    """A trajectory as a function of time since its start (``poses(t)``), with named segments."""

    def __init__(self, kind: str, duration: float, pose_fn,
                 segments: List[Tuple[str, float, float]]):
        self.kind = kind
        self.duration = float(duration)
        self._pose_fn = pose_fn
        self.segments = segments

    def poses(self, t) -> np.ndarray:
        """(N, 4, 4) T_map_cam at times ``t`` (seconds since the start)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        p, yaw, pitch = self._pose_fn(t)
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, :3] = camera_rotation(yaw, pitch)
        T[:, :3, 3] = p
        return T

    def stamps(self, rate: float, t0: float = 0.0) -> np.ndarray:
        n = max(1, int(round(self.duration * rate)))
        return t0 + np.arange(n) / float(rate)


def _loop(params: dict, duration: float, rng, stop: bool) -> SimTrajectory:
    cx, cy = params["center"]
    rx, ry = params["radii"]
    h = params["height"]
    th0 = rng.uniform(0, 2 * np.pi)
    ph = rng.uniform(0, 2 * np.pi, 4)
    D = float(duration)
    segments = [("loop", 0.0, D)]
    # time law s(t) in [0, 1]: constant speed, or a smooth stop around [ta, tb] for the sweep
    tg = np.linspace(0.0, D, max(2001, int(200 * D)))
    w = np.ones_like(tg)
    ta = tb = None
    if stop:
        ta = 0.45 * D
        tb = ta + min(4.0, 0.15 * D)
        ramp = min(1.0, 0.06 * D)
        w = 1.0 - _smoothstep((tg - (ta - ramp)) / ramp) * (1.0 - _smoothstep((tg - tb) / ramp))
        segments = [("loop", 0.0, ta), ("pure_rotation", ta, tb), ("loop", tb, D)]
    S = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(tg))])
    S /= S[-1]

    def fn(t):
        s = np.interp(t, tg, S)
        th = th0 + 2 * np.pi * s
        p = np.stack([cx + rx * np.cos(th), cy + ry * np.sin(th),
                      h + 0.04 * np.sin(3 * th + ph[0])], -1)
        yaw = th + 0.3 * np.sin(2 * th + ph[1])          # outwards, swinging along the walls
        pitch = 0.05 + 0.04 * np.sin(th + ph[2])
        if stop:
            tau = np.clip((t - ta) / (tb - ta), 0.0, 1.0)
            yaw = yaw + 1.2 * np.sin(np.pi * tau) ** 2      # out by ~70 degrees and back
        return p, yaw, pitch

    return SimTrajectory("loop+pure_rotation" if stop else "loop", D, fn, segments)


def _pure_rotation(params: dict, duration: float, rng) -> SimTrajectory:
    cx, cy = params.get("center", (4.0, 3.0))
    h = params.get("height", 1.3)
    yaw0 = rng.uniform(0, 2 * np.pi)
    D = float(duration)

    def fn(t):
        tau = np.clip(t / D, 0.0, 1.0)
        yaw = yaw0 + 1.4 * np.sin(np.pi * tau) ** 2 - 0.6 * np.sin(2 * np.pi * tau)
        p = np.tile([cx, cy, h], (len(t), 1))
        return p, yaw, np.full(len(t), 0.05)

    return SimTrajectory("pure_rotation", D, fn, [("pure_rotation", 0.0, D)])


def _corner(params: dict, duration: float, rng) -> SimTrajectory:
    """Corridor drive: straight along leg A (y = 0), a quarter circle of radius r around the
    inner corner, straight along leg B (x = x_c). The yaw follows a look-ahead point 0.6 m ahead,
    so the turn takes ~1.5 s at 1 m/s: ~60 deg/s, the fast cornering that breaks trackers."""
    xc, yc = params["corner"]
    r = params["turn_radius"]
    h = params["height"]
    x_start, y_end = params["start_x"], params["end_y"]
    L1 = (xc - r) - x_start
    La = 0.5 * np.pi * r
    L2 = y_end - (yc + r)
    look = 0.6
    Ltot = L1 + La + L2 - look
    D = float(duration)
    v = min(1.0, 0.98 * Ltot / D)
    l0 = float(np.clip(L1 + 0.5 * La - 0.5 * v * D, 0.0, Ltot - v * D))
    ph = rng.uniform(0, 2 * np.pi, 3)

    def path(l):
        l = np.asarray(l, float)
        x = np.where(l < L1, x_start + l, xc)
        y = np.where(l < L1, yc, yc + r + (l - L1 - La))
        arc = (l >= L1) & (l < L1 + La)
        al = -0.5 * np.pi + (l - L1) / r
        x = np.where(arc, xc - r + r * np.cos(al), x)
        y = np.where(arc, yc + r + r * np.sin(al), y)
        return np.stack([x, y], -1)

    def fn(t):
        l = l0 + v * np.asarray(t, float)
        p2 = path(l)
        ahead = path(l + look) - p2
        yaw = np.arctan2(ahead[:, 1], ahead[:, 0])
        left = np.stack([-np.sin(yaw), np.cos(yaw)], -1)
        p2 = p2 + left * (0.08 * np.sin(2 * np.pi * t / 5.0 + ph[0]))[:, None]
        z = h + 0.03 * np.sin(2 * np.pi * t / 1.1 + ph[1])
        yaw = yaw + 0.05 * np.sin(2 * np.pi * t / 3.0 + ph[2])
        return np.column_stack([p2, z]), yaw, np.full(len(t), 0.03)

    t_in = float(np.clip((L1 - look - l0) / v, 0.0, D))
    t_out = float(np.clip((L1 + La - l0) / v, 0.0, D))
    segments = [s for s in (("drive", 0.0, t_in), ("corner", t_in, t_out), ("drive", t_out, D))
                if s[2] > s[1]]
    return SimTrajectory("corner", D, fn, segments)


def build_trajectory(kind_or_scene, duration: float = 30.0, seed: int = 0,
                     scene=None) -> SimTrajectory:
    """The :class:`SimTrajectory` of a kind (``KINDS``) or of a scene's default.

    ``kind_or_scene`` is a kind, a scene name, or a :class:`~mdr_slam.sim.scene.Scene`; a kind
    runs in ``scene`` when given, else in its natural scene (loop: office, corner: corridor).
    """
    if isinstance(kind_or_scene, Scene):
        kind, params = kind_or_scene.default_trajectory, kind_or_scene.params
    elif kind_or_scene in SCENES:
        kind, params = _LAYOUTS[kind_or_scene][1], _layout_params(kind_or_scene)
    elif kind_or_scene in KINDS:
        kind = kind_or_scene
        params = scene.params if scene is not None else _layout_params(_DEFAULT_SCENE[kind])
    else:
        raise ValueError("unknown trajectory %r (kinds: %s; scenes: %s)"
                         % (kind_or_scene, ", ".join(KINDS), ", ".join(SCENES)))
    return _build(kind, params, duration, seed)


def _layout_params(scene_name: str) -> dict:
    """The layout parameters (room centre, corridor corner...) of a named scene, without
    building its textures (they do not depend on the seed)."""
    return _LAYOUTS[scene_name][0](_Builder(np.random.default_rng(0), 4.0), False)[2]


def _build(kind: str, params: dict, duration: float, seed: int) -> SimTrajectory:
    if duration <= 0:
        raise ValueError("trajectory duration must be positive, got %r" % duration)
    rng = np.random.default_rng([int(seed), KINDS.index(kind), 7])
    if kind in ("loop", "loop+pure_rotation"):
        if "center" not in params:
            raise ValueError("a %s trajectory needs a room scene (office, garage)" % kind)
        return _loop(params, duration, rng, stop=(kind == "loop+pure_rotation"))
    if kind == "pure_rotation":
        return _pure_rotation(params, duration, rng)
    if "corner" not in params:
        raise ValueError("a corner trajectory needs the corridor scene")
    return _corner(params, duration, rng)


def make_trajectory(kind_or_scene: Union[str, object] = "office", duration: float = 30.0,
                    rate: float = 20.0, seed: int = 0, t0: float = 1.0, scene=None):
    """``(stamps (N,), Ts (N, 4, 4) T_map_cam)`` sampled at ``rate`` Hz from stamp ``t0``.

    ``t0`` defaults to 1 s rather than 0 because a ROS stamp of 0 means "no stamp" (tf "latest").
    """
    traj = build_trajectory(kind_or_scene, duration, seed, scene)
    stamps = traj.stamps(rate, t0)
    return stamps, traj.poses(stamps - t0)
