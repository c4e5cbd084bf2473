"""Simulator scenes: textured rectangles and axis-aligned boxes, with exact geometry.

A scene is a list of :class:`Rect` (boxes are expanded into their faces), each with a deterministic
surface texture (a tileable mip-mapped tile sampled at the 2-D surface coordinate, so every camera
and every frame sees the same pattern), a baked diffuse light map (view independent, so the left
and right images agree) and a surface label. The scenes are built to be hard the way the paper's
indoor sequences are: large LOW-TEXTURE walls/floors/ceilings whose contrast is a parameter, a few
WELL-TEXTURED surfaces (posters, book shelves, floor mats) and an optional SPECULAR band whose
highlight moves with the camera (a reflected line light), which a stereo matcher cannot match.

Scenes: ``office`` (8 x 6 m room), ``corridor`` (L-shaped, 20 + 19 m), ``garage`` (24 x 16 m
hall) and ``floor`` (a 32 x 20 m building floor: a corridor ring round a block of rooms, two of
them open, whose default trajectory is a ~105 m route through both and back to its start) and
``atrium`` (a 14.6 x 12.4 m hall whose faint walls stay 4.2-5 m from its loop, beyond the stereo
rig's convergence range; the texture is on free-standing furniture and rugs in the hall).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np

__all__ = ["Rect", "Texture", "Scene", "make_scene", "SCENES", "LABELS",
           "LABEL_NONE", "LABEL_LOW_TEXTURE", "LABEL_TEXTURED", "LABEL_SPECULAR"]

LABEL_NONE = 0
LABEL_LOW_TEXTURE = 1
LABEL_TEXTURED = 2
LABEL_SPECULAR = 3
LABELS = {LABEL_NONE: "nothing", LABEL_LOW_TEXTURE: "low_texture", LABEL_TEXTURED: "textured",
          LABEL_SPECULAR: "specular"}

SCENES = ("office", "corridor", "garage", "floor", "atrium")
TILE = 512             # texels per texture tile side (all tiles, so the atlas is arithmetic)
LIGHTMAP_STEP = 0.1   # m; diffuse shading varies slowly, a coarse baked grid is exact enough


# ----------------------------------------------------------------------------------- textures
class Texture:
    """A square power-of-two tile, zero mean / unit spread, with its box-filter mip pyramid.

    Box filtering 2x2 blocks keeps the tile exactly periodic at every level, so sampling with
    wrap-around never shows seams; the renderer picks the level from the pixel footprint (the
    trilinear mip-mapping of GPUs) so far surfaces do not alias and left/right images agree.
    """

    def __init__(self, tile: np.ndarray, name: str = ""):
        tile = np.asarray(tile, dtype=np.float32)
        assert tile.shape[0] == tile.shape[1] and (tile.shape[0] & (tile.shape[0] - 1)) == 0
        self.name = name
        self.levels = [tile]
        while self.levels[-1].shape[0] > 8:
            t = self.levels[-1]
            n = t.shape[0] // 2
            self.levels.append(np.ascontiguousarray(
                t.reshape(n, 2, n, 2).mean(axis=(1, 3), dtype=np.float32)))

    @property
    def size(self) -> int:
        return self.levels[0].shape[0]


def _fft_noise(rng, n: int, sigma: float) -> np.ndarray:
    """Periodic smooth noise: white noise low-passed by a Gaussian of ``sigma`` texels (via FFT,
    so the tile wraps without seams), normalised to unit standard deviation."""
    w = rng.standard_normal((n, n))
    f = np.fft.fftfreq(n)
    g = np.exp(-2.0 * (np.pi * sigma) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))
    out = np.real(np.fft.ifft2(np.fft.fft2(w) * g))
    out -= out.mean()
    return out / max(out.std(), 1e-9)


def _normalise(t: np.ndarray) -> np.ndarray:
    t = t - t.mean()
    return (t / max(t.std(), 1e-9)).astype(np.float32)


def texture_low(rng, n: int = 512) -> Texture:
    """Painted wall / concrete: smooth blotches plus a faint grain (texel ~8 mm)."""
    return Texture(_normalise(_fft_noise(rng, n, 10.0) + 0.35 * _fft_noise(rng, n, 1.0)), "low")


def texture_noise(rng, n: int = 512) -> Texture:
    """High-contrast multi-scale noise (carpet, floor mat, wood): octaves 1..32 texels,
    sharpened by a tanh so it has edges at every scale (good for ORB and ELAS)."""
    t = sum(_fft_noise(rng, n, s) / (1.0 + 0.15 * i) for i, s in enumerate((1, 2, 4, 8, 16, 32)))
    return Texture(_normalise(np.tanh(1.2 * _normalise(t))), "noise")


def texture_books(rng, n: int = 512) -> Texture:
    """Book shelf front: vertical spines of random width and grey, shelf boards every 128
    texels (divides the tile, so it stays periodic), fine print noise."""
    t = np.zeros((n, n))
    x = 0
    while x < n:
        w = int(rng.integers(4, 12))
        t[:, x:x + w] = rng.uniform(-1.5, 1.5)
        t[:, x:x + 1] -= 1.0
        x += w
    for y0 in range(0, n, 128):
        band = rng.integers(0, 28)
        t[y0:y0 + 6, :] = 1.8
        t[y0 + 6:y0 + 6 + band, :] *= 0.3      # shadow / empty space above the books
    t += 0.4 * _fft_noise(rng, n, 0.8)
    return Texture(_normalise(t), "books")


def texture_poster(rng, n: int = 512) -> Texture:
    """Poster / sign: random rectangles and disks of strong contrast on noise."""
    t = np.zeros((n, n), np.float32)
    for _ in range(int(rng.integers(25, 45))):
        c = float(rng.uniform(-2, 2))
        x, y = (int(v) for v in rng.integers(0, n, 2))
        if rng.random() < 0.5:
            w, h = (int(v) for v in rng.integers(8, n // 4, 2))
            cv2.rectangle(t, (x, y), (x + w, y + h), c, -1)
        else:
            cv2.circle(t, (x, y), int(rng.integers(5, n // 8)), c, -1)
    t += 0.5 * _fft_noise(rng, n, 1.5).astype(np.float32)
    return Texture(_normalise(t), "poster")


TEXTURE_MAKERS = {"low": texture_low, "noise": texture_noise, "books": texture_books,
                  "poster": texture_poster}


# --------------------------------------------------------------------------------- primitives
@dataclass
class Rect:
    """A textured rectangle ``origin + s*u + r*v`` for ``0 <= s <= a``, ``0 <= r <= b``.

    ``u``, ``v`` are orthonormal; the front side is ``normal = u x v`` (rectangles are one-sided:
    walls face into the room, box faces face outwards). Albedo = ``base + amp * tile(s, r)``.
    """

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    a: float
    b: float
    label: int
    texture: str            # key into Scene.textures
    texel: float            # metres per level-0 texel
    base: float             # mean albedo (grey levels at unit light)
    amp: float              # texture amplitude (grey levels per tile unit)
    name: str = ""
    offset: Tuple[float, float] = (0.0, 0.0)   # texel offset, decorrelates surfaces sharing a tile
    spec_light: Optional[Tuple[np.ndarray, np.ndarray]] = None   # (point, direction) line light
    lightmap: Optional[np.ndarray] = None

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)

    def corners(self) -> np.ndarray:
        o, u, v = self.origin, self.u * self.a, self.v * self.b
        return np.array([o, o + u, o + u + v, o + v])

    def to_world(self, s: np.ndarray, r: np.ndarray) -> np.ndarray:
        return self.origin + np.multiply.outer(s, self.u) + np.multiply.outer(r, self.v)


def rect(p0, p1, p2, facing, **kw) -> Rect:
    """Rectangle with corners p0, p1 = p0 + a*u, p2 = p0 + b*v, front side towards ``facing``."""
    p0, p1, p2 = (np.asarray(p, dtype=float) for p in (p0, p1, p2))
    eu, ev = p1 - p0, p2 - p0
    a, b = float(np.linalg.norm(eu)), float(np.linalg.norm(ev))
    u, v = eu / a, ev / b
    if np.dot(np.cross(u, v), np.asarray(facing, dtype=float) - (p0 + 0.5 * (eu + ev))) < 0:
        u, v, a, b = v, u, b, a
    return Rect(p0, u, v, a, b, **kw)


def box(lo, hi, floor: bool = True, faces: Optional[Dict[str, dict]] = None, **kw) -> List[Rect]:
    """Axis-aligned box [lo, hi] as up to 6 outward-facing rectangles (bottom skipped when it
    stands on the floor). ``faces`` overrides per face ('-x', '+x', '-y', '+y', '+z', '-z')."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    c = 0.5 * (lo + hi)
    out = []
    for axis in range(3):
        for sign in (-1, 1):
            key = ("-" if sign < 0 else "+") + "xyz"[axis]
            if key == "-z" and floor and lo[2] <= 1e-6:
                continue
            k = dict(kw)
            k.update((faces or {}).get(key, {}))
            p0 = lo.copy()
            if sign > 0:
                p0[axis] = hi[axis]
            o1, o2 = [i for i in range(3) if i != axis]
            p1, p2 = p0.copy(), p0.copy()
            p1[o1] = hi[o1]
            p2[o2] = hi[o2]
            facing = c.copy()
            facing[axis] += sign * 10.0
            k.setdefault("name", "box")
            k["name"] = k["name"] + key
            out.append(rect(p0, p1, p2, facing, **k))
    return out


# --------------------------------------------------------------------------------------- scene
@dataclass
class Scene:
    name: str
    rects: List[Rect]
    textures: Dict[str, Texture]
    lights: List[Tuple[np.ndarray, float, float]]    # (position, power, falloff radius)
    ambient: float
    bounds: Tuple[np.ndarray, np.ndarray]           # room/hall axis-aligned extent
    seed: int = 0
    contrast: float = 4.0
    specular: bool = True
    default_trajectory: str = "loop"
    params: dict = field(default_factory=dict)     # layout parameters the trajectories use

    def __post_init__(self):
        self._pack()

    def _pack(self):
        """Per-primitive parameters as arrays (vectorized culling and per-pixel lookups).
        Every lookup table has one trailing entry for "no primitive" (pid = -1)."""
        R = self.rects
        self.O = np.array([r.origin for r in R], dtype=np.float64)
        self.U = np.array([r.u for r in R], dtype=np.float64)
        self.V = np.array([r.v for r in R], dtype=np.float64)
        self.N = np.cross(self.U, self.V)
        self.A = np.array([r.a for r in R])
        self.B = np.array([r.b for r in R])
        self.label_lut = np.array([r.label for r in R] + [LABEL_NONE], dtype=np.uint8)
        self._atlas = None

    def atlas(self) -> dict:
        """Texture atlas + per-primitive constants for deferred full-frame shading.

        All tiles are TILE x TILE; texture i occupies column block i, its mip level l sits at
        rows ``y_l = sum_{j<l} (TILE/2^j + 2)`` with a one-texel wrap-around border on every
        side, so the atlas position of any level is arithmetic (no per-pixel lookups) and a
        bilinear sample never leaves its tile: two cv2.remap calls (levels floor(L), floor(L)+1)
        texture a whole frame. Light maps are stacked likewise with a replicated border.
        """
        if self._atlas is not None:
            return self._atlas
        names = sorted(self.textures)
        for n in names:
            if self.textures[n].size != TILE:
                raise ValueError("texture %r is %d texels, the atlas needs %d"
                                 % (n, self.textures[n].size, TILE))
        nl = len(self.textures[names[0]].levels)
        col_w = TILE + 2
        height = sum(TILE // (1 << l) + 2 for l in range(nl))
        tex = np.zeros((height, col_w * len(names)), np.float32)
        for ti, n in enumerate(names):
            y = 0
            for t in self.textures[n].levels:
                sz = t.shape[0]
                tex[y:y + sz + 2, ti * col_w:ti * col_w + sz + 2] = np.pad(t, 1, mode="wrap")
                y += sz + 2
        lms = [np.pad(r.lightmap, 1, mode="edge") for r in self.rects]
        lw = max(m.shape[1] for m in lms)
        light = np.zeros((sum(m.shape[0] for m in lms), lw), np.float32)
        loff = np.zeros((len(self.rects), 2), np.float32)
        y = 0
        for k, m in enumerate(lms):
            light[y:y + m.shape[0], :m.shape[1]] = m
            loff[k] = (1, y + 1)
            y += m.shape[0]
        f32 = np.float32
        self._atlas = {
            "tex": tex, "max_level": f32(nl - 1),
            "col_x": np.array([names.index(r.texture) * col_w for r in self.rects], f32),
            "log2_inv_texel": np.array([-np.log2(r.texel) for r in self.rects], f32),
            "inv_texel": np.array([1.0 / r.texel for r in self.rects], f32),
            "off": np.array([r.offset for r in self.rects], f32),
            "base": np.array([r.base for r in self.rects], f32),
            "amp": np.array([r.amp for r in self.rects], f32),
            "light": light, "light_off": loff,
        }
        return self._atlas

    def bake_lighting(self):
        """Diffuse light maps: ambient + sum of point lights (Lambert, 1/(1+(d/R)^2) falloff),
        sampled every LIGHTMAP_STEP metres over each rectangle. No shadows (trade-off: the
        images stay smooth and cheap, the geometry stays exact)."""
        for rc in self.rects:
            ns = int(np.ceil(rc.a / LIGHTMAP_STEP)) + 1
            nr = int(np.ceil(rc.b / LIGHTMAP_STEP)) + 1
            s = np.linspace(0, rc.a, ns)
            r = np.linspace(0, rc.b, nr)
            P = rc.to_world(*np.meshgrid(s, r, indexing="xy"))      # (nr, ns, 3)
            shade = np.full(P.shape[:2], self.ambient)
            n = rc.normal
            for pos, power, radius in self.lights:
                d = np.asarray(pos) - P
                dist = np.linalg.norm(d, axis=-1)
                cos = np.clip((d @ n) / np.maximum(dist, 1e-6), 0.0, 1.0)
                shade += power * cos / (1.0 + (dist / radius) ** 2)
            rc.lightmap = shade.astype(np.float32)

    def distance_to_surfaces(self, P: np.ndarray) -> np.ndarray:
        """Euclidean distance (N,) of points (N, 3) to the nearest rectangle (exact)."""
        P = np.asarray(P, dtype=float).reshape(-1, 3)
        best = np.full(len(P), np.inf)
        for rc in self.rects:
            d = P - rc.origin
            s = np.clip(d @ rc.u, 0, rc.a)
            r = np.clip(d @ rc.v, 0, rc.b)
            q = rc.to_world(s, r)
            best = np.minimum(best, np.linalg.norm(P - q, axis=1))
        return best

    def summary(self) -> dict:
        counts = {LABELS[k]: int(sum(r.label == k for r in self.rects)) for k in (1, 2, 3)}
        area = {LABELS[k]: round(float(sum(r.a * r.b for r in self.rects if r.label == k)), 2)
                for k in (1, 2, 3)}
        lo, hi = self.bounds
        return {"name": self.name, "n_rects": len(self.rects), "rects_per_label": counts,
                "area_m2_per_label": area, "bounds": [lo.tolist(), hi.tolist()],
                "contrast": self.contrast, "specular": self.specular}


class _Builder:
    """Collects rectangles with seeded texture offsets and grey levels."""

    def __init__(self, rng, contrast: float):
        self.rng = rng
        self.contrast = float(contrast)
        self.rects: List[Rect] = []

    def _kw(self, kind: str, base: Optional[float], amp: Optional[float], texel: Optional[float],
            name: str) -> dict:
        rng = self.rng
        if kind == "low":
            return dict(label=LABEL_LOW_TEXTURE, texture="low", texel=texel or 0.008,
                        base=base if base is not None else float(rng.uniform(150, 190)),
                        amp=self.contrast if amp is None else amp, name=name,
                        offset=tuple(rng.uniform(0, 256, 2)))
        if kind == "spec":
            return dict(label=LABEL_SPECULAR, texture="low", texel=texel or 0.008,
                        base=base if base is not None else 205.0, amp=1.0 if amp is None else amp,
                        name=name, offset=tuple(rng.uniform(0, 256, 2)))
        return dict(label=LABEL_TEXTURED, texture=kind, texel=texel or 0.004,
                    base=base if base is not None else float(rng.uniform(110, 140)),
                    amp=amp if amp is not None else float(rng.uniform(45, 60)), name=name,
                    offset=tuple(rng.uniform(0, 512, 2)))

    def add_rect(self, p0, p1, p2, facing, kind="low", base=None, amp=None, texel=None, name="",
                 spec_light=None):
        kw = self._kw(kind, base, amp, texel, name)
        rc = rect(p0, p1, p2, facing, spec_light=spec_light, **kw)
        _orient_texture(rc, np.asarray(p1, float) - np.asarray(p0, float))
        self.rects.append(rc)

    def add_box(self, lo, hi, kind="low", base=None, amp=None, texel=None, name="box",
                faces: Optional[Dict[str, Tuple[str, Optional[float]]]] = None):
        kw = self._kw(kind, base, amp, texel, name)
        fk = {}
        for key, (fkind, fbase) in (faces or {}).items():
            fk[key] = self._kw(fkind, fbase, None, None, name)
        for rc in box(lo, hi, faces=fk, **kw):
            # keep directional textures (book spines) vertical on the box's side faces
            _orient_texture(rc, np.array([0.0, 0.0, 1.0]) if abs(rc.normal[2]) < 0.5 else rc.u)
            self.rects.append(rc)

    def add_room(self, lo, hi, wall_base=(170, 182, 165, 176), floor_base=105.0,
                 ceil_base=205.0, name="room"):
        """Floor, ceiling and four walls of the box [lo, hi], all facing inwards, low texture."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        c = 0.5 * (lo + hi)
        x0, y0, z0 = lo
        x1, y1, z1 = hi
        self.add_rect((x0, y0, z0), (x1, y0, z0), (x0, y1, z0), c, base=floor_base,
                      name=name + "_floor")
        self.add_rect((x0, y0, z1), (x1, y0, z1), (x0, y1, z1), c, base=ceil_base,
                      name=name + "_ceiling")
        self.add_rect((x0, y0, z0), (x1, y0, z0), (x0, y0, z1), c, base=wall_base[0],
                      name=name + "_wall_y0")
        self.add_rect((x0, y1, z0), (x1, y1, z0), (x0, y1, z1), c, base=wall_base[1],
                      name=name + "_wall_y1")
        self.add_rect((x0, y0, z0), (x0, y1, z0), (x0, y0, z1), c, base=wall_base[2],
                      name=name + "_wall_x0")
        self.add_rect((x1, y0, z0), (x1, y1, z0), (x1, y0, z1), c, base=wall_base[3],
                      name=name + "_wall_x1")

    def on_wall(self, axis: int, coord: float, facing_sign: int, s0, s1, z0, z1, kind,
                base=None, amp=None, name="", gap=0.006, spec_light=None):
        """A flat panel (poster, whiteboard, door, band) ``gap`` metres in front of a wall
        ``x = coord`` (axis 0) or ``y = coord`` (axis 1) whose inside is towards ``facing_sign``."""
        w = coord + facing_sign * gap
        if axis == 0:
            p0, p1, p2 = (w, s0, z0), (w, s1, z0), (w, s0, z1)
            facing = (w + facing_sign, 0.5 * (s0 + s1), 0.5 * (z0 + z1))
        else:
            p0, p1, p2 = (s0, w, z0), (s1, w, z0), (s0, w, z1)
            facing = (0.5 * (s0 + s1), w + facing_sign, 0.5 * (z0 + z1))
        self.add_rect(p0, p1, p2, facing, kind=kind, base=base, amp=amp, name=name,
                      spec_light=spec_light)


def _orient_texture(rc: Rect, along) -> None:
    """Book spines run along the texture's rows: when the face's u axis is not ``along``
    (rect() swapped u and v to face the right way, or u is vertical on a box face), use the
    transposed tile so the pattern keeps its intended orientation."""
    if rc.texture == "books" and abs(np.dot(rc.u, along) / max(np.linalg.norm(along), 1e-9)) < 0.5:
        rc.texture = "books_t"


def _textures(rng) -> Dict[str, Texture]:
    tex = {k: TEXTURE_MAKERS[k](np.random.default_rng(rng.integers(1 << 31))) for k in
           ("low", "noise", "books", "poster")}
    # books with the spines along the other surface axis (faces whose u runs vertically)
    tex["books_t"] = Texture(np.ascontiguousarray(tex["books"].levels[0].T), "books_t")
    return tex


def _office(b: _Builder, specular: bool):
    L, W, H = 8.0, 6.0, 2.8
    b.add_room((0, 0, 0), (L, W, H), name="office")
    b.add_rect((2.6, 1.6, 0.004), (5.2, 1.6, 0.004), (2.6, 3.4, 0.004), (4, 3, 1), kind="noise",
               name="floor_mat")
    # whiteboard (white, almost uniform), posters, a door
    b.on_wall(0, 0.0, +1, 1.6, 3.8, 0.9, 2.1, "low", base=228, amp=1.0, name="whiteboard")
    b.on_wall(0, 0.0, +1, 4.3, 5.1, 1.1, 2.1, "poster", name="poster_w")
    b.on_wall(0, L, -1, 1.0, 1.9, 1.0, 2.2, "poster", name="poster_e")
    b.on_wall(0, L, -1, 4.2, 5.1, 0.0, 2.1, "low", base=120, name="door")
    b.on_wall(1, 0.0, +1, 4.8, 5.6, 1.0, 2.0, "poster", name="poster_s")
    b.on_wall(1, W, -1, 0.4, 1.0, 1.8, 2.5, "poster", name="poster_n")
    if specular:
        # glossy band reflecting a horizontal line light 2 m in front of the north wall: the
        # highlight is a horizontal stripe whose height moves with the camera, the same in both
        # rectified images (horizontal baseline) so disparity along it is ambiguous
        b.on_wall(1, W, -1, 1.2, 7.0, 1.05, 1.75, "spec", name="specular_band",
                  spec_light=(np.array([4.0, W - 2.0, 1.45]), np.array([1.0, 0, 0])))
    # furniture: desks with monitors, a cabinet, a book shelf
    for lo, hi in (((5.8, 0.35, 0.0), (7.5, 1.15, 0.74)), ((0.5, 4.6, 0.0), (2.1, 5.4, 0.74))):
        b.add_box(lo, hi, kind="noise", base=120, amp=30, name="desk")
    b.add_box((6.4, 0.5, 0.74), (6.95, 0.58, 1.1), kind="poster", base=60, amp=30, name="monitor")
    b.add_box((1.0, 5.1, 0.74), (1.55, 5.18, 1.1), kind="poster", base=60, amp=30, name="monitor")
    b.add_box((7.35, 3.3, 0.0), (7.95, 4.0, 1.9), kind="low", base=150, name="cabinet")
    b.add_box((2.4, 0.02, 0.0), (3.8, 0.40, 2.0), kind="low", base=140, name="bookshelf",
              faces={"+y": ("books", 110)})
    b.add_box((4.6, 5.3, 0.0), (5.4, 5.9, 1.1), kind="low", base=130, name="drawers")
    lights = [(np.array([2.7, 3.0, 2.7]), 0.45, 3.0), (np.array([5.3, 3.0, 2.7]), 0.45, 3.0)]
    return lights, (np.zeros(3), np.array([L, W, H])), {"center": (4.0, 3.0), "radii": (1.8, 0.95),
                                                        "height": 1.3}


def _corridor(b: _Builder, specular: bool):
    # L-shaped corridor, 2 m wide: leg A along +x (y in [-1, 1]), 90-degree left corner at
    # x in [18, 20], leg B along +y
    H = 2.6
    b.add_rect((0, -1, 0), (20, -1, 0), (0, 1, 0), (5, 0, 1), base=100, name="floor_a")
    b.add_rect((18, 1, 0), (20, 1, 0), (18, 20, 0), (19, 5, 1), base=100, name="floor_b")
    b.add_rect((0, -1, H), (20, -1, H), (0, 1, H), (5, 0, 0), base=200, name="ceiling_a")
    b.add_rect((18, 1, H), (20, 1, H), (18, 20, H), (19, 5, 0), base=200, name="ceiling_b")
    b.add_rect((0, -1, 0), (20, -1, 0), (0, -1, H), (5, 0, 1), base=175, name="wall_a_south")
    b.add_rect((0, 1, 0), (18, 1, 0), (0, 1, H), (5, 0, 1), base=168, name="wall_a_north")
    b.add_rect((20, -1, 0), (20, 20, 0), (20, -1, H), (19, 5, 1), base=172, name="wall_east")
    b.add_rect((18, 1, 0), (18, 20, 0), (18, 1, H), (19, 5, 1), base=178, name="wall_b_west")
    b.add_rect((0, -1, 0), (0, 1, 0), (0, -1, H), (5, 0, 1), base=160, name="end_a")
    b.add_rect((18, 20, 0), (20, 20, 0), (18, 20, H), (19, 5, 1), base=160, name="end_b")
    # doors (low texture, darker), posters/notice boards, mats, benches, radiators
    for x in (3.0, 9.5, 15.0):
        b.on_wall(1, -1.0, +1, x, x + 0.9, 0.0, 2.05, "low", base=115, name="door_s")
    for y in (5.0, 12.0):
        b.on_wall(0, 20.0, -1, y, y + 0.9, 0.0, 2.05, "low", base=115, name="door_e")
    for x in (1.5, 6.5, 12.5, 16.5):
        b.on_wall(1, -1.0, +1, x, x + 0.7, 1.0, 1.9, "poster", name="poster_s")
    for y in (3.0, 8.5, 15.5):
        b.on_wall(0, 18.0, +1, y, y + 0.8, 1.0, 1.9, "poster", name="poster_bw")
    b.on_wall(0, 20.0, -1, 0.9, 1.7, 0.9, 1.9, "poster", name="poster_corner")
    b.on_wall(1, 1.0, -1, 17.0, 18.0, 0.3, 1.0, "books", base=120, name="notice_board")
    b.on_wall(0, 18.0, +1, 10.0, 11.0, 0.15, 0.75, "books", base=120, name="radiator")
    for x in (3.0, 9.5):
        b.add_rect((x, -0.95, 0.004), (x + 0.9, -0.95, 0.004), (x, -0.35, 0.004), (x, 0, 1),
                   kind="noise", name="mat")
    b.add_box((7.0, 0.6, 0.0), (8.4, 0.98, 0.45), kind="noise", base=110, amp=35, name="bench")
    b.add_box((19.55, 9.0, 0.0), (19.98, 9.4, 0.9), kind="poster", base=120, name="bin")
    if specular:
        b.on_wall(1, 1.0, -1, 4.0, 15.0, 1.05, 1.7, "spec", name="specular_band",
                  spec_light=(np.array([9.0, -0.3, 1.4]), np.array([1.0, 0, 0])))
    lights = [(np.array([x, 0.0, H - 0.1]), 0.5, 2.5) for x in (2.0, 7.0, 12.0, 17.0)]
    lights += [(np.array([19.0, y, H - 0.1]), 0.5, 2.5) for y in (5.0, 10.0, 15.0)]
    return lights, (np.array([0, -1, 0.0]), np.array([20, 20, H])), {
        "corner": (19.0, 0.0), "turn_radius": 0.8, "height": 1.3, "start_x": 0.6, "end_y": 19.4}


def _garage(b: _Builder, specular: bool):
    L, W, H = 24.0, 16.0, 3.6
    b.add_room((0, 0, 0), (L, W, H), wall_base=(150, 158, 145, 155), floor_base=95, ceil_base=170,
               name="hall")
    for x in (6.0, 12.0, 18.0):
        for y in (4.0, 12.0):
            b.add_box((x - 0.3, y - 0.3, 0), (x + 0.3, y + 0.3, H), kind="low", base=165,
                      name="column", faces={"+y" if y < 8 else "-y": ("poster", None)})
    # parked cars along the long walls (textured), parking lines (textured stripes)
    for x in np.arange(3.0, 20.0, 4.5):
        b.add_box((x, 0.4, 0), (x + 1.8, 2.6 + 0.5 * b.rng.random(), 1.4), kind="noise",
                  base=float(b.rng.uniform(70, 160)), amp=40, name="car")
    for x in np.arange(3.5, 20.0, 6.0):
        b.add_box((x, W - 2.8, 0), (x + 1.8, W - 0.4, 1.5), kind="noise",
                  base=float(b.rng.uniform(70, 160)), amp=40, name="car")
    for x in np.arange(2.4, 22.0, 4.5):
        b.add_rect((x, 0.3, 0.003), (x + 0.12, 0.3, 0.003), (x, 3.6, 0.003), (x, 3, 1),
                   kind="noise", base=200, amp=25, name="parking_line")
    b.on_wall(0, 0.0, +1, 6.0, 7.5, 1.0, 2.5, "poster", name="sign_w")
    b.on_wall(0, L, -1, 9.4, 10.6, 1.0, 2.3, "poster", name="sign_e")
    b.on_wall(0, L, -1, 4.2, 5.2, 0.0, 2.2, "low", base=100, name="door_e")
    if specular:
        b.on_wall(0, L, -1, 5.8, 9.0, 1.1, 1.8, "spec", name="specular_band",
                  spec_light=(np.array([L - 4.0, 7.5, 1.5]), np.array([0, 1.0, 0])))
    lights = [(np.array([x, y, H - 0.1]), 0.45, 5.0) for x in (6.0, 12.0, 18.0)
              for y in (5.5, 10.5)]
    return lights, (np.zeros(3), np.array([L, W, H])), {"center": (12.0, 8.0),
                                                        "radii": (6.0, 2.8), "height": 1.35}


def _atrium(b: _Builder, specular: bool):
    """An entrance hall (14.6 x 12.4 m, 4 m high) whose four walls are faint (low texture, a few
    grey levels apart) and FAR: the default loop (radii 3 x 2 m round the centre, looking
    outwards as the office's) keeps them 4.2 to 5 m away, beyond the stereo rig's ~3.5 m
    convergence range. Only a door, two signs and a glossy band are on them. The texture a
    tracker needs stands free in the hall, 2-2.6 m out from the loop, where the outward-looking
    camera sees it whole (its lowest ray meets the floor ~2 m ahead) and mostly below the walls'
    view (two clad pillars, two planters with plants, a bench, an information kiosk, a display
    cabinet), and lies on rugs between them. ``seed`` shuffles, moves and resizes the furniture
    and the rugs, moves the door and the signs along their walls and changes the wall greys.

    ``params["furniture"]``: the floor-standing boxes' footprints ``(x0, y0, x1, y1, top)``; the
    loop stays well clear of every one (tests/sim check it for several seeds)."""
    L, W, H = 14.6, 12.4, 4.0
    cx, cy = 0.5 * L, 0.5 * W
    rx, ry = 3.0, 2.0
    rng = b.rng
    grey = float(rng.uniform(146.0, 162.0))
    walls = tuple(grey + float(d) for d in rng.uniform(-6.0, 6.0, 4))
    b.add_room((0, 0, 0), (L, W, H), wall_base=walls, floor_base=float(rng.uniform(96, 108)),
               ceil_base=190.0, name="atrium")
    # the walls: a double door (low texture, darker), two signs, the glossy band
    yd = float(rng.uniform(3.0, W - 4.8))
    b.on_wall(0, 0.0, +1, yd, yd + 1.8, 0.0, 2.4, "low", base=112, name="door")
    xs = float(rng.uniform(2.0, L - 3.0))
    b.on_wall(1, W, -1, xs, xs + 1.0, 1.6, 2.3, "poster", name="sign_n")
    ys = float(rng.uniform(2.0, W - 3.0))
    b.on_wall(0, L, -1, ys, ys + 0.8, 1.5, 2.1, "poster", name="sign_e")
    if specular:
        xb = float(rng.uniform(3.0, L - 6.0))
        b.on_wall(1, 0.0, +1, xb, xb + 3.0, 1.05, 1.7, "spec", name="specular_band",
                  spec_light=(np.array([xb + 1.5, 2.0, 1.45]), np.array([1.0, 0, 0])))
    # free-standing furniture round the loop, d m out along the ellipse's outward normal;
    # each (along the path, across it, height), its long side along the path
    furniture = []
    kinds = ["pillar", "planter", "bench", "kiosk", "pillar", "planter", "cabinet"]
    order = [kinds[i] for i in rng.permutation(len(kinds))]
    n = len(order)
    th0 = float(rng.uniform(0, 2 * np.pi))

    def out_point(th, d):
        nx, ny = ry * np.cos(th), rx * np.sin(th)
        k = d / np.hypot(nx, ny)
        return cx + rx * np.cos(th) + k * nx, cy + ry * np.sin(th) + k * ny, nx, ny

    for i, kind in enumerate(order):
        th = th0 + 2 * np.pi * i / n + float(rng.uniform(-0.12, 0.12))
        along, across, top = {
            "pillar": (0.45, 0.45, H),
            "planter": (float(rng.uniform(0.7, 0.9)),) * 2 + (float(rng.uniform(0.6, 0.8)),),
            "bench": (float(rng.uniform(1.4, 1.8)), 0.45, 0.45),
            "kiosk": (0.9, 0.45, float(rng.uniform(1.5, 1.7))),
            "cabinet": (float(rng.uniform(1.1, 1.4)), 0.5, 0.9)}[kind]
        d = float(rng.uniform(2.0, 2.6))
        x, y, nx, ny = out_point(th, d + 0.5 * across)
        if abs(nx) >= abs(ny):    # the path runs along y here: the long side too
            hx, hy = 0.5 * across, 0.5 * along
            inner = "-x" if nx > 0 else "+x"
        else:
            hx, hy = 0.5 * along, 0.5 * across
            inner = "-y" if ny > 0 else "+y"
        lo, hi = (x - hx, y - hy, 0.0), (x + hx, y + hy, top)
        if kind == "pillar":      # stone cladding, a poster on the side facing the path
            b.add_box(lo, hi, kind="noise", base=float(rng.uniform(115, 145)), amp=35,
                      name="pillar", faces={inner: ("poster", None)})
        elif kind == "planter":   # stone planter, foliage above it
            b.add_box(lo, hi, kind="noise", base=140, amp=30, name="planter")
            plant = float(rng.uniform(1.1, 1.3))
            b.add_box((x - hx + 0.1, y - hy + 0.1, top), (x + hx - 0.1, y + hy - 0.1, plant),
                      kind="noise", base=85, amp=50, name="plant")
            top = plant
        elif kind == "bench":
            b.add_box(lo, hi, kind="noise", base=110, amp=35, name="bench")
        elif kind == "kiosk":     # information kiosk: posters all round
            b.add_box(lo, hi, kind="poster", base=120, name="kiosk")
        else:                     # display cabinet: books behind glass on the path's side
            b.add_box(lo, hi, kind="low", base=140, name="cabinet", faces={inner: ("books", 110)})
        furniture.append((float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]), float(top)))
        # a rug between this piece and the next, on the floor the camera sees
        x, y, nx, ny = out_point(th + np.pi / n, float(rng.uniform(1.9, 2.3)) + 0.5)
        a, c = float(rng.uniform(1.3, 1.8)), float(rng.uniform(0.9, 1.2))   # along, across
        hx, hy = (0.5 * c, 0.5 * a) if abs(nx) >= abs(ny) else (0.5 * a, 0.5 * c)
        b.add_rect((x - hx, y - hy, 0.004), (x + hx, y - hy, 0.004), (x - hx, y + hy, 0.004),
                   (x, y, 1), kind="noise", base=float(rng.uniform(90, 150)), amp=40,
                   name="rug")
    lights = [(np.array([x, y, H - 0.1]), 0.45, 5.0) for x in (0.25 * L, 0.5 * L, 0.75 * L)
              for y in (0.25 * W, 0.75 * W)]
    return lights, (np.zeros(3), np.array([L, W, H])), {
        "center": (cx, cy), "radii": (rx, ry), "height": 1.3, "furniture": furniture}


def _wall(b: _Builder, axis: int, coord: float, facing_sign: int, s0: float, s1: float, H: float,
          doors=(), door_h: float = 2.1, base=None, name: str = "wall"):
    """A one-sided wall ``x = coord`` (axis 0) or ``y = coord`` (axis 1) from s0 to s1, facing
    ``facing_sign``, with doorway openings ``doors`` [(d0, d1), ...]: the solid parts and a
    lintel above each opening (walls have no thickness, so an opening needs no jambs)."""
    base = base if base is not None else float(b.rng.uniform(165, 182))
    cuts = [s0] + [v for d in sorted(doors) for v in d] + [s1]
    parts = [(cuts[i], cuts[i + 1], 0.0, H) for i in range(0, len(cuts), 2)]
    parts += [(d0, d1, door_h, H) for d0, d1 in doors]
    for a0, a1, z0, z1 in parts:
        if a1 - a0 < 1e-6:
            continue
        if axis == 0:
            p0, p1, p2 = (coord, a0, z0), (coord, a1, z0), (coord, a0, z1)
            facing = (coord + facing_sign, 0.5 * (a0 + a1), 0.5 * (z0 + z1))
        else:
            p0, p1, p2 = (a0, coord, z0), (a1, coord, z0), (a0, coord, z1)
            facing = (0.5 * (a0 + a1), coord + facing_sign, 0.5 * (z0 + z1))
        b.add_rect(p0, p1, p2, facing, base=base, name=name)


def _floor(b: _Builder, specular: bool):
    """A building floor (32 x 20 m): a 2.4 m wide corridor ring around a block of rooms. Two
    rooms open onto the corridor through two doorways each (a lab on the south side, a meeting
    room on the north side); the other offices are closed doors. Only surfaces a camera in the
    corridor or the two rooms can see exist (walls have no thickness, one rect per visible side),
    which keeps the rect count near the garage's."""
    L, W, H, c = 32.0, 20.0, 2.7, 2.4
    lab = (8.0, c, 16.0, 8.8)                 # x0, y0, x1, y1
    meet = (17.0, 11.2, 25.0, W - c)
    lab_doors = ((8.7, 10.3), (13.7, 15.3))
    meet_doors = ((17.7, 19.3), (22.7, 24.3))
    b.add_rect((0, 0, 0), (L, 0, 0), (0, W, 0), (1, 1, 1), base=102, name="floor")
    b.add_rect((0, 0, H), (L, 0, H), (0, W, H), (1, 1, 0), base=205, name="ceiling")
    # building shell, facing in
    _wall(b, 1, 0.0, +1, 0, L, H, name="outer_s")
    _wall(b, 1, W, -1, 0, L, H, name="outer_n")
    _wall(b, 0, 0.0, +1, 0, W, H, name="outer_w")
    _wall(b, 0, L, -1, 0, W, H, name="outer_e")
    # the room block's corridor faces, with the two rooms' doorways
    _wall(b, 1, c, -1, c, L - c, H, doors=lab_doors, name="block_s")
    _wall(b, 1, W - c, +1, c, L - c, H, doors=meet_doors, name="block_n")
    _wall(b, 0, c, -1, c, W - c, H, name="block_w")
    _wall(b, 0, L - c, +1, c, W - c, H, name="block_e")
    # the two rooms' insides
    for (x0, y0, x1, y1), doors, door_side, nm in ((lab, lab_doors, 0, "lab"),
                                                   (meet, meet_doors, 1, "meeting")):
        _wall(b, 1, y0, +1, x0, x1, H, doors=doors if door_side == 0 else (), name=nm + "_s")
        _wall(b, 1, y1, -1, x0, x1, H, doors=doors if door_side == 1 else (), name=nm + "_n")
        _wall(b, 0, x0, +1, y0, y1, H, name=nm + "_w")
        _wall(b, 0, x1, -1, y0, y1, H, name=nm + "_e")
    # closed office doors along the corridor (low texture, darker)
    for x in (4.0, 18.5, 23.0, 26.5):
        b.on_wall(1, c, -1, x, x + 0.9, 0.0, 2.05, "low", base=112, name="door")
    for x in (4.5, 10.0, 13.5):
        b.on_wall(1, W - c, +1, x, x + 0.9, 0.0, 2.05, "low", base=112, name="door")
    for y in (6.0, 12.5):
        b.on_wall(0, c, -1, y, y + 0.9, 0.0, 2.05, "low", base=112, name="door")
        b.on_wall(0, L - c, +1, y, y + 0.9, 0.0, 2.05, "low", base=112, name="door")
    # posters / notice boards every few metres, and one at every corridor end the camera
    # walks towards (so no straight stretch stares at a blank wall)
    # (one facing each doorway the route leaves a room by; none over the specular band)
    for x in (2.5, 7.0, 11.5, 14.1, 27.5):
        b.on_wall(1, 0.0, +1, x, x + 0.8, 1.0, 1.9, "poster", name="poster_s")
    for x in (6.5, 11.5, 14.5, 18.1, 21.5, 26.0):
        b.on_wall(1, W, -1, x, x + 0.8, 1.0, 1.9, "poster", name="poster_n")
    for y in (3.5, 9.0, 15.0):
        b.on_wall(0, L, -1, y, y + 0.8, 1.0, 1.9, "poster", name="poster_e")
        b.on_wall(0, 0.0, +1, y + 1.5, y + 2.3, 1.0, 1.9, "poster", name="poster_w")
    b.on_wall(0, L, -1, 0.4, 2.0, 0.8, 2.0, "poster", name="end_se")
    b.on_wall(1, W, -1, L - 2.0, L - 0.4, 0.8, 2.0, "poster", name="end_ne")
    b.on_wall(0, 0.0, +1, W - 2.0, W - 0.4, 0.8, 2.0, "poster", name="end_nw")
    b.on_wall(1, 0.0, +1, 0.4, 2.0, 0.8, 2.0, "books", base=120, name="end_sw")
    b.on_wall(0, L - c, +1, 8.5, 10.5, 0.9, 1.9, "books", base=120, name="notice_board")
    b.on_wall(0, c, -1, 9.0, 11.0, 0.9, 1.9, "books", base=120, name="notice_board")
    # a textured feature wall (wood panelling) along the north corridor
    b.on_wall(1, W, -1, 2.5, 6.0, 0.0, H - 0.1, "noise", base=125, amp=35, name="panelling")
    for x, y in ((29.4, 0.5), (29.6, 18.1), (0.8, 18.3), (0.6, 0.8)):
        b.add_rect((x - 0.5, y - 0.3, 0.004), (x + 0.5, y - 0.3, 0.004), (x - 0.5, y + 0.3, 0.004),
                   (x, y, 1), kind="noise", name="mat")
    b.add_box((19.0, 0.02, 0.0), (20.6, 0.4, 0.45), kind="noise", base=110, amp=35, name="bench")
    # lab: book shelf and desks along the north wall, whiteboard west, poster east
    x0, y0, x1, y1 = lab
    b.add_box((9.0, y1 - 0.4, 0.0), (11.0, y1 - 0.02, 2.0), kind="low", base=140,
              name="bookshelf", faces={"-y": ("books", 110)})
    b.add_box((12.0, y1 - 0.9, 0.0), (15.0, y1 - 0.1, 0.74), kind="noise", base=120, amp=30,
              name="desk")
    b.add_box((12.6, y1 - 0.4, 0.74), (13.2, y1 - 0.32, 1.1), kind="poster", base=60, amp=30,
              name="monitor")
    b.on_wall(0, x0, +1, 4.0, 6.5, 0.9, 2.0, "low", base=228, amp=1.0, name="whiteboard")
    b.on_wall(0, x1, -1, 4.5, 5.5, 1.0, 2.1, "poster", name="poster_lab")
    b.add_rect((10.5, 4.6, 0.004), (13.5, 4.6, 0.004), (10.5, 7.0, 0.004), (12, 6, 1),
               kind="noise", name="carpet")
    # meeting room: table, shelf on the south wall, poster west, whiteboard east
    x0, y0, x1, y1 = meet
    b.add_box((19.0, y0 + 0.4, 0.0), (23.0, y0 + 1.4, 0.75), kind="noise", base=115, amp=35,
              name="table")
    b.add_box((17.2, y0 + 0.02, 0.0), (18.6, y0 + 0.4, 1.9), kind="low", base=140,
              name="bookshelf", faces={"+y": ("books", 110)})
    b.on_wall(0, x0, +1, 13.0, 14.6, 1.0, 2.0, "poster", name="poster_meeting")
    b.on_wall(1, y0, +1, 23.1, 24.1, 1.0, 1.9, "poster", name="poster_meeting")
    b.on_wall(0, x1, -1, 12.5, 15.0, 0.9, 2.0, "low", base=228, amp=1.0, name="whiteboard")
    if specular:
        # a glossy band along the south corridor's outer wall, lit by a line light along it
        b.on_wall(1, 0.0, +1, 16.5, 26.5, 1.05, 1.7, "spec", name="specular_band",
                  spec_light=(np.array([21.5, 2.0, 1.45]), np.array([1.0, 0, 0])))
    lights = [(np.array([x, 1.2, H - 0.1]), 0.5, 2.5) for x in np.arange(2.0, L, 4.0)]
    lights += [(np.array([x, W - 1.2, H - 0.1]), 0.5, 2.5) for x in np.arange(2.0, L, 4.0)]
    lights += [(np.array([x, y, H - 0.1]), 0.5, 2.5) for x in (1.2, L - 1.2)
               for y in (6.0, 10.0, 14.0)]
    lights += [(np.array([x, y, H - 0.1]), 0.45, 3.0) for x, y in ((10.0, 5.6), (14.0, 5.6),
                                                                     (19.0, 14.4), (23.0, 14.4))]
    # the route (counter-clockwise round the ring, through the lab and the meeting room) as
    # waypoints with the fillet radius of each corner; trajectory.py smooths and times it
    route = [(4.0, 1.2), (9.5, 1.2), (9.5, 6.2), (14.5, 6.2), (14.5, 1.2), (L - 1.2, 1.2),
             (L - 1.2, W - 1.2), (23.5, W - 1.2), (23.5, 13.8), (18.5, 13.8), (18.5, W - 1.2),
             (1.2, W - 1.2), (1.2, 1.2)]
    fillet = [0.0, 1.5, 1.5, 1.5, 1.5, 2.0, 2.0, 1.5, 1.5, 1.5, 1.5, 2.0, 2.0]
    return lights, (np.zeros(3), np.array([L, W, H])), {
        "route": route, "fillet": fillet, "height": 1.3, "speed": 0.9,
        "rooms": {"lab": lab, "meeting": meet}, "rotation_center": (12.0, 5.6),
        "map_cell": 0.02}


_LAYOUTS = {"office": (_office, "loop+pure_rotation"), "corridor": (_corridor, "corner"),
            "garage": (_garage, "loop+pure_rotation"), "floor": (_floor, "route"),
            "atrium": (_atrium, "loop")}


def make_scene(name: str = "office", contrast: float = 4.0, specular: bool = True,
               seed: int = 0) -> Scene:
    """Build a named scene (``SCENES``: 'office', 'corridor', 'garage', 'floor', 'atrium'),
    deterministic for ``seed``.

    ``contrast`` is the texture amplitude (grey levels, ~std) of the large low-texture surfaces:
    ~2-4 is a painted wall (almost nothing for a stereo matcher), 15+ makes them easy.
    """
    if name not in _LAYOUTS:
        raise ValueError("unknown scene %r (choose from %s)" % (name, ", ".join(SCENES)))
    rng = np.random.default_rng([int(seed), SCENES.index(name)])
    textures = _textures(rng)
    b = _Builder(rng, contrast)
    layout, default_traj = _LAYOUTS[name]
    lights, bounds, params = layout(b, bool(specular))
    scene = Scene(name, b.rects, textures, lights, 0.55, bounds, seed=int(seed),
                  contrast=float(contrast), specular=bool(specular),
                  default_trajectory=default_traj, params=params)
    scene.bake_lighting()
    return scene
