"""Simulator trajectories: smooth, deterministic per seed, analytic in time.

Each trajectory is a function of time (so motion blur can render sub-poses between frames) giving
``T_map_cam`` of the left camera optical frame (z forward, x right, y down) in the z-up ``map``.
Kinds, chosen to exercise what the paper's indoor sequences stress:

- ``loop``: an ellipse around the room looking outwards, returning exactly to its start pose
  (loop closure);
- ``pure_rotation``: the camera stands still and sweeps its yaw (no parallax: monocular
  initialisation and depth triangulation fail, stereo must carry it);
- ``loop+pure_rotation``: the loop with a stop-and-sweep segment in the middle (office, garage);
- ``corner``: a corridor drive through a 90-degree corner with fast yaw rate (corridor);
- ``route``: a long walk (~100+ m at ~0.9 m/s) round a building floor's corridor ring and through
  two rooms, back to its start (floor): loop closure after a long drift.

Patrols: ``laps=N`` drives a loop kind (loop, loop+pure_rotation, route) N times end to end
(:func:`_patrol`); ``duration`` stays the duration of ONE lap. Lap 0 is the single-lap trajectory
exactly; every later lap varies its path slightly (radii / lateral offset, height, yaw swing, drawn
from ``(seed, lap)``) with perturbations that vanish smoothly at the lap ends, so the pose stays
continuous across lap boundaries and every lap still starts and ends at the same pose.
"""
from __future__ import annotations

from typing import List, Optional, Sequence, Tuple, Union

import numpy as np

from .scene import SCENES, Scene, _Builder, _LAYOUTS

__all__ = ["SimTrajectory", "build_trajectory", "make_trajectory", "camera_rotation", "KINDS",
           "LOOP_KINDS", "DEFAULT_DURATION"]

KINDS = ("loop", "pure_rotation", "loop+pure_rotation", "corner", "route")
LOOP_KINDS = ("loop", "loop+pure_rotation", "route")     # return to their start pose: lappable
_DEFAULT_SCENE = {"loop": "office", "pure_rotation": "office", "loop+pure_rotation": "office",
                  "corner": "corridor", "route": "floor"}
DEFAULT_DURATION = 30.0   # s, when none is given (the route: its own length at its speed)


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
    """A trajectory as a function of time since its start (``poses(t)``), with named segments
    and its laps ``[(lap, t0, t1)]`` (one lap unless built by :func:`_patrol`)."""

    def __init__(self, kind: str, duration: float, pose_fn,
                 segments: List[Tuple[str, float, float]],
                 laps: Optional[List[Tuple[int, float, float]]] = None):
        self.kind = kind
        self.duration = float(duration)
        self._pose_fn = pose_fn
        self.segments = segments
        self.laps = laps if laps is not None else [(0, 0.0, self.duration)]

    @property
    def lap_duration(self) -> float:
        return self.laps[0][2] - self.laps[0][1]

    def lap_of(self, t) -> np.ndarray:
        """Lap index of times ``t`` (a lap boundary belongs to the lap it starts)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return np.clip(np.floor(t / self.lap_duration + 1e-9), 0, len(self.laps) - 1).astype(int)

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


def _envelope(s):
    """0 at both lap ends with zero slope, 1 mid-lap: a lap's perturbations ride on it."""
    return np.sin(np.pi * np.clip(s, 0.0, 1.0)) ** 2


def _loop(params: dict, duration: float, rng, stop: bool,
          perturb: Optional[dict] = None) -> SimTrajectory:
    """The ellipse loop; ``perturb`` (a later lap's draws, see :func:`_lap_perturbation`) shifts
    radii, centre, height and the yaw swing by amounts that vanish at the lap's ends."""
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
        if perturb is None:     # lap 0: exactly the single-lap trajectory
            p = np.stack([cx + rx * np.cos(th), cy + ry * np.sin(th),
                          h + 0.04 * np.sin(3 * th + ph[0])], -1)
            yaw = th + 0.3 * np.sin(2 * th + ph[1])          # outwards, swinging along the walls
        else:
            e = _envelope(s)
            q = perturb
            p = np.stack([cx + q["dcx"] * e + (rx + q["drx"] * e) * np.cos(th),
                          cy + q["dcy"] * e + (ry + q["dry"] * e) * np.sin(th),
                          h + q["dh"] * e + 0.04 * np.sin(3 * th + ph[0])], -1)
            yaw = th + (0.3 + q["dswing"] * e) * np.sin(2 * th + ph[1] + q["dphase"] * e)
        pitch = 0.05 + 0.04 * np.sin(th + ph[2])
        if stop:
            tau = np.clip((t - ta) / (tb - ta), 0.0, 1.0)
            yaw = yaw + 1.2 * np.sin(np.pi * tau) ** 2      # out by ~70 degrees and back
        return p, yaw, pitch

    return SimTrajectory("loop+pure_rotation" if stop else "loop", D, fn, segments)


def _pure_rotation(params: dict, duration: float, rng) -> SimTrajectory:
    cx, cy = params.get("rotation_center", params.get("center", (4.0, 3.0)))
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


def _smooth_closed(x: np.ndarray, sigma: float) -> np.ndarray:
    """Circular Gaussian smoothing (``sigma`` in samples) of a closed curve's samples (axis 0)."""
    n = len(x)
    f = np.fft.fftfreq(n)
    g = np.exp(-2.0 * (np.pi * sigma * f) ** 2)
    X = np.fft.fft(x, axis=0)
    return np.real(np.fft.ifft(X * (g if x.ndim == 1 else g[:, None]), axis=0))


def _fillet_polyline(pts: Sequence, radii: Sequence[float], step: float) -> np.ndarray:
    """Dense samples (``step`` m apart at most) of a closed polyline whose corners are replaced
    by circular arcs of the given radii (tangent to both legs), starting at ``pts[0]``."""
    P = np.asarray(pts, float)
    n = len(P)
    ends = []     # per corner: (tangent point in, tangent point out, arc samples)
    for i in range(n):
        a, c, nx = P[i - 1], P[i], P[(i + 1) % n]
        din = (c - a) / np.linalg.norm(c - a)
        dout = (nx - c) / np.linalg.norm(nx - c)
        turn = np.arctan2(din[0] * dout[1] - din[1] * dout[0], float(np.dot(din, dout)))
        r = float(radii[i])
        if r <= 0 or abs(turn) < 1e-9:
            ends.append((c, c, np.zeros((0, 2))))
            continue
        k = r * np.tan(0.5 * abs(turn))
        t_in, t_out = c - din * k, c + dout * k
        left = np.array([-din[1], din[0]]) * np.sign(turn)
        centre = t_in + left * r
        a0 = np.arctan2(*(t_in - centre)[::-1])
        m = max(2, int(np.ceil(abs(turn) * r / step)) + 1)
        ang = a0 + np.sign(turn) * np.linspace(0.0, abs(turn), m)
        ends.append((t_in, t_out, centre + r * np.stack([np.cos(ang), np.sin(ang)], -1)))
    out = []
    for i in range(n):
        out.append(ends[i][2])
        p0, p1 = ends[i][1], ends[(i + 1) % n][0]
        m = max(2, int(np.ceil(np.linalg.norm(p1 - p0) / step)) + 1)
        out.append(p0 + np.linspace(0.0, 1.0, m)[:-1, None] * (p1 - p0))
    return np.concatenate([o for o in out if len(o)])


def _resample_closed(xy: np.ndarray, step: float):
    """(M, 2) samples of the closed curve through ``xy`` every ~``step`` m of arc, and the
    curve's length."""
    seg = np.linalg.norm(np.diff(np.vstack([xy, xy[:1]]), axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    L = float(s[-1])
    m = int(np.round(L / step))
    su = np.arange(m) * (L / m)
    closed = np.vstack([xy, xy[:1]])
    return np.stack([np.interp(su, s, closed[:, 0]), np.interp(su, s, closed[:, 1])], -1), L


class _Route:
    """The geometry and nominal timing of a closed route (a scene's ``route`` waypoints with
    fillet radii): a smooth path sampled every ``STEP`` m, its heading, the camera's forward-
    looking yaw with a gentle swing, and a time law at ``speed`` that slows down in turns so
    the yaw rate stays near ``MAX_YAW_RATE`` at most."""

    STEP = 0.02            # m between path samples
    SMOOTH = 0.35          # m: Gaussian rounding of the fillets' curvature jumps
    LOOK = 0.3             # m: the camera looks at the path this far ahead
    MAX_YAW_RATE = 0.55    # rad/s (31.5 deg/s) in turns: well under the 45 deg/s that hurts
    SWING = 0.1            # rad: yaw swing amplitude (~6 deg), one period per ~9 m

    def __init__(self, params: dict, rng):
        dense = _fillet_polyline(params["route"], params["fillet"], 0.5 * self.STEP)
        xy, _ = _resample_closed(dense, self.STEP)
        xy = _smooth_closed(xy, self.SMOOTH / self.STEP)
        self.xy, self.length = _resample_closed(xy, self.STEP)
        n = len(self.xy)
        self.ds = self.length / n
        self.s = np.arange(n) * self.ds
        d = np.roll(self.xy, -1, 0) - np.roll(self.xy, 1, 0)
        head = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        self.winding = int(np.round((head[-1] - head[0]) / (2 * np.pi)))
        trend = 2 * np.pi * self.winding * self.s / self.length
        # headings minus the loop's winding are periodic in s: interpolate those
        self.head_per = head - trend
        self.look_per = np.roll(self.head_per, -int(round(self.LOOK / self.ds)))
        self.height = float(params["height"])
        self.speed = float(params["speed"])
        self.rooms = params.get("rooms", {})
        ph = rng.uniform(0, 2 * np.pi, 4)
        self.n_swing = max(1, int(round(self.length / 9.0)))
        self.n_bob = max(1, int(round(self.length / 2.5)))
        self.ph = ph
        # time law: v = speed, softly capped by MAX_YAW_RATE / |dyaw/ds|, smoothed over ~1 m
        dyaw = np.gradient(self.yaw(self.s, None), self.ds)
        v = self.speed / np.sqrt(1.0 + (self.speed * dyaw / self.MAX_YAW_RATE) ** 2)
        v = _smooth_closed(v, 0.5 / self.ds)
        self.t_of_s = np.concatenate([[0.0], np.cumsum(self.ds / v)])   # at s, s + ds, ..., L
        self.lap_time = float(self.t_of_s[-1])

    def yaw(self, s, q: Optional[dict]):
        s = np.asarray(s, float)
        w = 2 * np.pi * s / self.length
        base = np.interp(s, self.s, self.look_per, period=self.length) + self.winding * w
        if q is None:
            return base + self.SWING * np.sin(self.n_swing * w + self.ph[0])
        e = _envelope(s / self.length)
        return base + (self.SWING + q["dswing"] * e) * np.sin(self.n_swing * w + self.ph[0]
                                                               + q["dphase"] * e)

    def pose(self, s, q: Optional[dict]):
        s = np.asarray(s, float)
        x = np.interp(s, self.s, self.xy[:, 0], period=self.length)
        y = np.interp(s, self.s, self.xy[:, 1], period=self.length)
        w = 2 * np.pi * s / self.length
        z = self.height + 0.02 * np.sin(self.n_bob * w + self.ph[1])
        pitch = 0.04 + 0.02 * np.sin(3 * w + self.ph[2])
        if q is not None:      # a later lap: sideways offset along the path normal, height
            e = _envelope(s / self.length)
            head = np.interp(s, self.s, self.head_per, period=self.length) + self.winding * w
            off = e * (q["dlat"] + q["dlat2"] * np.sin(3 * w + q["dphase2"]))
            x = x - np.sin(head) * off
            y = y + np.cos(head) * off
            z = z + q["dh"] * e
        return np.stack([x, y, z], -1), self.yaw(s, q), pitch

    def region(self, s) -> List[str]:
        """"corridor" or the name of the room each arc length ``s`` is in."""
        x = np.interp(s, self.s, self.xy[:, 0], period=self.length)
        y = np.interp(s, self.s, self.xy[:, 1], period=self.length)
        out = np.full(len(x), "corridor", dtype=object)
        for name, (x0, y0, x1, y1) in self.rooms.items():
            out[(x > x0) & (x < x1) & (y > y0) & (y < y1)] = name
        return list(out)


def _route(params: dict, duration: Optional[float], rng, perturb: Optional[dict] = None,
           geometry: Optional[_Route] = None) -> SimTrajectory:
    """The floor's route. A ``duration`` at least the route's lap time walks all of it (slower
    when longer) and ends at the start pose; a shorter one walks only the route's first
    ``duration`` seconds at the nominal speed (not a loop). Segments: "corridor" and the rooms'
    names."""
    g = geometry if geometry is not None else _Route(params, rng)
    D = g.lap_time if duration is None else float(duration)
    full = D >= g.lap_time * (1 - 1e-9)
    scale = g.lap_time / D if full else 1.0
    s_knots = np.arange(len(g.t_of_s)) * g.ds

    def s_of(t):
        return np.interp(np.asarray(t, float) * scale, g.t_of_s, s_knots)

    def fn(t):
        return g.pose(s_of(t), perturb)

    tt = np.linspace(0.0, D, max(2, int(D * 20) + 1))
    names = g.region(s_of(tt))
    segments = []
    k0 = 0
    for k in range(1, len(tt) + 1):
        if k == len(tt) or names[k] != names[k0]:
            segments.append((str(names[k0]), float(tt[k0]), float(tt[k - 1] if k == len(tt)
                                                                   else tt[k])))
            k0 = k
    tr = SimTrajectory("route", D, fn, segments)
    tr.closed = full
    tr.route = g
    return tr


def _lap_perturbation(seed: int, lap: int, kind: str) -> dict:
    """A later lap's small path changes, drawn from ``(seed, lap)``: each a random sign times
    a magnitude in a range (a few cm to ~0.15 m, a few cm in height, a few degrees of swing)."""
    rng = np.random.default_rng([int(seed), int(lap), KINDS.index(kind), 8])

    def draw(lo, hi):
        return float(rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi))

    return {"drx": draw(0.03, 0.12), "dry": draw(0.03, 0.10), "dcx": draw(0.02, 0.06),
            "dcy": draw(0.02, 0.06), "dh": draw(0.02, 0.05), "dswing": draw(0.02, 0.06),
            "dphase": draw(0.05, 0.2), "dlat": draw(0.03, 0.08), "dlat2": draw(0.02, 0.06),
            "dphase2": float(rng.uniform(0, 2 * np.pi))}


def _patrol(laps: List[SimTrajectory]) -> SimTrajectory:
    """Laps of one loop trajectory driven end to end: lap k runs over [k D, (k + 1) D]. The
    laps must each start and end at the same pose (loops), so the patrol is continuous.
    Segments keep their names, shifted to their lap; ``laps`` lists each lap's time span."""
    if len(laps) == 1:
        return laps[0]
    D = laps[0].duration
    n = len(laps)

    def fn(t):
        t = np.asarray(t, float)
        k = np.clip(np.floor(t / D + 1e-9), 0, n - 1).astype(int)
        p = np.empty((len(t), 3))
        yaw = np.empty(len(t))
        pitch = np.empty(len(t))
        for lap in np.unique(k):
            m = k == lap
            p[m], yaw[m], pitch[m] = laps[lap]._pose_fn(t[m] - lap * D)
        return p, yaw, pitch

    segments = [(name, a + k * D, b + k * D) for k, tr in enumerate(laps)
                for name, a, b in tr.segments]
    out = SimTrajectory(laps[0].kind, n * D, fn, segments,
                        [(k, k * D, (k + 1) * D) for k in range(n)])
    for attr in ("closed", "route"):
        if hasattr(laps[0], attr):
            setattr(out, attr, getattr(laps[0], attr))
    return out


def build_trajectory(kind_or_scene, duration: Optional[float] = DEFAULT_DURATION, seed: int = 0,
                     scene=None, laps: int = 1) -> SimTrajectory:
    """The :class:`SimTrajectory` of a kind (``KINDS``) or of a scene's default.

    ``kind_or_scene`` is a kind, a scene name, or a :class:`~mdr_slam.sim.scene.Scene`; a kind
    runs in ``scene`` when given, else in its natural scene (loop: office, corner: corridor,
    route: floor). ``duration`` is one lap's (``None``: the route's own lap time, else
    :data:`DEFAULT_DURATION`); ``laps`` > 1 patrols a loop kind (:func:`_patrol`).
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
    return _build(kind, params, duration, seed, laps)


def _layout_params(scene_name: str) -> dict:
    """The layout parameters (room centre, corridor corner...) of a named scene, without
    building its textures (they do not depend on the seed)."""
    return _LAYOUTS[scene_name][0](_Builder(np.random.default_rng(0), 4.0), False)[2]


def _build(kind: str, params: dict, duration: Optional[float], seed: int,
           laps: int = 1) -> SimTrajectory:
    if duration is not None and duration <= 0:
        raise ValueError("trajectory duration must be positive, got %r" % duration)
    if int(laps) != laps or laps < 1:
        raise ValueError("laps must be a positive integer, got %r" % (laps,))
    laps = int(laps)
    if laps > 1 and kind not in LOOP_KINDS:
        raise ValueError("--laps needs a loop trajectory (%s: office, garage, floor); a %s "
                         "drive does not return to its start" % (", ".join(LOOP_KINDS), kind))

    def rng():    # every lap draws the same shape (start pose, phases) as lap 0
        return np.random.default_rng([int(seed), KINDS.index(kind), 7])

    def pert(k):
        return None if k == 0 else _lap_perturbation(seed, k, kind)

    if kind == "route":
        if "route" not in params:
            raise ValueError("a route trajectory needs the floor scene")
        g = _Route(params, rng())
        out = [_route(params, duration, rng(), pert(k), geometry=g) for k in range(laps)]
        if laps > 1 and not out[0].closed:
            raise ValueError("a lap of the route takes %.1f s at %.2g m/s: with laps, the "
                             "duration (of one lap) must be at least that, or left out"
                             % (g.lap_time, g.speed))
        return _patrol(out)
    if duration is None:
        duration = DEFAULT_DURATION
    if kind in ("loop", "loop+pure_rotation"):
        if "center" not in params:
            raise ValueError("a %s trajectory needs a room scene (office, garage)" % kind)
        return _patrol([_loop(params, duration, rng(), stop=(kind == "loop+pure_rotation"),
                              perturb=pert(k)) for k in range(laps)])
    if kind == "pure_rotation":
        return _pure_rotation(params, duration, rng())
    if "corner" not in params:
        raise ValueError("a corner trajectory needs the corridor scene")
    return _corner(params, duration, rng())


def make_trajectory(kind_or_scene: Union[str, object] = "office",
                    duration: Optional[float] = DEFAULT_DURATION, rate: float = 20.0,
                    seed: int = 0, t0: float = 1.0, scene=None, laps: int = 1):
    """``(stamps (N,), Ts (N, 4, 4) T_map_cam)`` sampled at ``rate`` Hz from stamp ``t0``
    (``laps`` x ``duration`` seconds).

    ``t0`` defaults to 1 s rather than 0 because a ROS stamp of 0 means "no stamp" (tf "latest").
    """
    traj = build_trajectory(kind_or_scene, duration, seed, scene, laps)
    stamps = traj.stamps(rate, t0)
    return stamps, traj.poses(stamps - t0)
