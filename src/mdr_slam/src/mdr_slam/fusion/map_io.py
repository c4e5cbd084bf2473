"""Map file I/O (voxblox's ``io``): the map as a cloud dict, PLY/PCD save and load with every point's state.

:class:`MapIO` is a mixin of :class:`~mdr_slam.fusion.voxel_map.VoxelMap`; anchor poses go to a
``<path>.anchors.json`` sidecar. Reading and writing clouds is :mod:`mdr_slam.io`'s.
"""
from __future__ import annotations

import json
import os
from collections import OrderedDict

import numpy as np

from ..io.map_dir import SESSION_KEY, map_files
from .cloud import normal_bins

__all__ = ["MapIO", "DENSE_FORMAT_VERSION", "save_dense_map", "load_dense_map"]

DENSE_FORMAT = "mdr_slam dense map"
DENSE_FORMAT_VERSION = 1


class MapIO:
    """Save / load of a :class:`~mdr_slam.fusion.voxel_map.VoxelMap` (mixin)."""

    def to_cloud(self, min_confidence: int = 0, keys: bool = False) -> "OrderedDict[str, np.ndarray]":
        """The map as a cloud dict for :func:`mdr_slam.io.write_cloud` / PointCloud2.

        Fields: x, y, z, intensity, confidence, nx, ny, nz, weight, first_seen, last_seen,
        anchor_id, nbin, view_x, view_y, view_z (the camera centre the point was last seen from,
        NaN when unknown: the occupancy grid's rays), and with ``keys`` the hash voxel kx, ky, kz
        (the voxel of the position, except for a point that moved into a voxel held by a point
        whose normal disagrees, or with ``rekey=False``): everything :meth:`load` needs to
        restore the same map.
        """
        a = self._a
        s = self.live_slots()
        s = s[a["confidence"][s] >= min_confidence]
        p, n = a["pos"][s], a["normal"][s]
        out = OrderedDict([
            ("x", p[:, 0].copy()), ("y", p[:, 1].copy()), ("z", p[:, 2].copy()),
            ("intensity", a["intensity"][s].copy()), ("confidence", a["confidence"][s].copy()),
            ("nx", n[:, 0].copy()), ("ny", n[:, 1].copy()), ("nz", n[:, 2].copy()),
            ("weight", a["weight"][s].copy()), ("first_seen", a["first_seen"][s].copy()),
            ("last_seen", a["last_seen"][s].copy()),
            ("anchor_id", a["anchor"][s].astype(np.int32)),
            ("nbin", a["key"][s, 3].astype(np.uint8)),
        ])
        v = a["view"][s]
        for i, k in enumerate(("view_x", "view_y", "view_z")):
            out[k] = v[:, i].copy()
        if keys:
            for i, k in enumerate(("kx", "ky", "kz")):
                out[k] = a["key"][s, i].copy()
        return out

    def save(self, path: str) -> int:
        """Write every point with all its state (PLY or PCD by extension, atomic).

        Anchor poses go to a sidecar ``<path>.anchors.json`` (also atomic) when there are any.
        Returns the number of points written.
        """
        from ..io import atomic_write, write_cloud
        n = write_cloud(path, self.to_cloud(0, keys=True))
        side = path + ".anchors.json"
        if self.anchors:
            data = {str(k): np.asarray(v).reshape(-1).tolist() for k, v in self.anchors.items()}
            atomic_write(side, json.dumps({"voxel_size": self.voxel_size, "anchors": data}), "w")
        elif os.path.exists(side):
            os.unlink(side)
        return n

    @staticmethod
    def read_anchors(side: str) -> dict:
        """The anchor poses of a ``<map>.anchors.json`` sidecar ({} when there is none)."""
        if not side or not os.path.exists(side):
            return {}
        with open(side) as f:
            return {int(k): np.asarray(v, dtype=np.float64).reshape(4, 4)
                    for k, v in json.load(f)["anchors"].items()}

    def load(self, path, append: bool = False, anchors: dict = None) -> int:
        """Read a map written by :meth:`save` (or any PLY/PCD cloud with x, y, z); ``path`` may
        also be a cloud dict (as :meth:`to_cloud` returns) to add points directly.

        ``append=False`` replaces the map. Missing fields get defaults (confidence =
        ``min_confidence`` so a plain cloud survives cleaning, normals +z, views NaN: no ray in
        the occupancy grid). Points that fall on an occupied key are merged. Returns the number
        of points in the map afterwards.
        """
        from ..io import read_cloud
        c = read_cloud(path) if isinstance(path, str) else path
        if not all(k in c for k in "xyz"):
            raise ValueError("%s has no x, y, z fields" % (path if isinstance(path, str) else "cloud"))
        if anchors is None:
            anchors = self.read_anchors(path + ".anchors.json" if isinstance(path, str) else "")
        if not append:
            self.reset()
        self.anchors.update(anchors)
        P = np.stack([c["x"], c["y"], c["z"]], 1).astype(np.float64)
        n = len(P)

        def get(name, default, dt):
            return np.asarray(c[name], dtype=dt) if name in c else np.full(n, default, dt)

        ok = np.all(np.isfinite(P), axis=1)
        if all(k in c for k in ("nx", "ny", "nz")):
            N = np.stack([c["nx"], c["ny"], c["nz"]], 1).astype(np.float64)
        else:
            N = np.tile([0.0, 0.0, 1.0], (n, 1))
        if all(k in c for k in ("view_x", "view_y", "view_z")):
            V = np.stack([c["view_x"], c["view_y"], c["view_z"]], 1).astype(np.float64)
        else:   # a map saved before views were kept, or a plain cloud
            V = np.full((n, 3), np.nan)
        if self.confidence:
            b = get("nbin", -1, np.int32)
            b = np.where((b >= 0) & (b < 6), b, normal_bins(N)[0]) if n else b
        else:
            b = np.zeros(n, np.int32)
        keys = self._keys(P, b)
        if n and all(k in c for k in ("kx", "ky", "kz")):
            saved = np.stack([c["kx"], c["ky"], c["kz"]], 1).astype(np.int64)
            # saved voxels are only valid for the same voxel size: then every point lies in or
            # next to its saved voxel (the running mean drifts by less than a voxel)
            if np.all(np.abs(saved[ok] - keys[ok, :3]) <= 1):
                keys[:, :3] = saved
        sel = np.nonzero(ok)[0]
        slots = self._alloc(len(sel))
        a = self._a
        a["pos"][slots] = P[sel]
        a["normal"][slots] = N[sel]
        a["weight"][slots] = get("weight", 1.0, np.float32)[sel]
        a["intensity"][slots] = get("intensity", 0.0, np.float32)[sel]
        a["confidence"][slots] = get("confidence", max(self.min_confidence, 1), np.int32)[sel]
        a["first_seen"][slots] = get("first_seen", 0.0, np.float64)[sel]
        a["last_seen"][slots] = get("last_seen", 0.0, np.float64)[sel]
        a["anchor"][slots] = get("anchor_id", -1, np.int64)[sel]
        a["key"][slots] = keys[sel]
        a["alive"][slots] = True
        a["view"][slots] = V[sel]
        if len(slots):  # the map's clock continues after the loaded points (see _map_time)
            t_max = float(np.max(a["last_seen"][slots]))
            if np.isfinite(t_max) and (self._t_last is None or t_max > self._t_last):
                self._t_last = t_max
        self._n += len(slots)
        ins = self._insert(keys[sel], slots)
        if not ins.all():
            lost = slots[~ins]
            occ = self._find(keys[sel][~ins])  # occupant: an earlier point or a duplicate in the file
            okk = occ >= 0
            self._merge_slots(occ[okk], lost[okk])
            a["alive"][lost] = False
            self._free = np.concatenate([self._free, lost])
            self._n -= len(lost)
        return self._n


def _meta_path(folder: str) -> str:
    return os.path.splitext(map_files(folder)["dense"])[0] + ".json"


def save_dense_map(vmap, folder: str, session_id: str = "") -> int:
    """The dense map into a map folder (mdr_slam.io.map_dir): ``dense_map.ply`` with every
    point's state, then ``dense_map.json`` (format, version, voxel size, points, the mapping
    session's id); each written atomically. Returns the number of points."""
    from ..io import atomic_write
    os.makedirs(folder, exist_ok=True)
    n = vmap.save(map_files(folder)["dense"])
    meta = {"format": DENSE_FORMAT, "format_version": DENSE_FORMAT_VERSION,
            "voxel_size": float(vmap.voxel_size), "points": int(n)}
    if session_id:
        meta[SESSION_KEY] = str(session_id)
    atomic_write(_meta_path(folder), json.dumps(meta, indent=1), "w")
    return n


def load_dense_map(vmap, folder: str, append: bool = False) -> int:
    """Load a map folder's dense map into ``vmap``; a missing, truncated or corrupt file or
    another format version raises ValueError and leaves ``vmap`` as it was. Returns the number
    of points in the map afterwards."""
    from ..io import read_cloud
    path, meta_path = map_files(folder)["dense"], _meta_path(folder)
    try:
        with open(meta_path) as f:
            meta = json.load(f)
    except (IOError, OSError) as e:
        raise ValueError("no dense map in %s (%s)" % (folder, e))
    except ValueError as e:
        raise ValueError("corrupt %s: %s" % (meta_path, e))
    if not isinstance(meta, dict) or meta.get("format") != DENSE_FORMAT:
        raise ValueError("%s is not an MDR-SLAM dense map description" % meta_path)
    if meta.get("format_version") != DENSE_FORMAT_VERSION:
        raise ValueError("%s has format version %r; this MDR-SLAM reads version %d"
                         % (path, meta.get("format_version"), DENSE_FORMAT_VERSION))
    try:
        cloud = read_cloud(path)
    except (IOError, OSError) as e:
        raise ValueError("cannot read %s: %s" % (path, e))
    except (ValueError, KeyError, IndexError, TypeError, UnicodeDecodeError) as e:
        raise ValueError("corrupt dense map %s: %s: %s" % (path, type(e).__name__, e))
    n = len(cloud.get("x", ()))
    if n != meta.get("points"):
        raise ValueError("corrupt dense map %s: %d points, %s expected" % (path, n, meta.get("points")))
    try:
        anchors = vmap.read_anchors(path + ".anchors.json")
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError("corrupt %s.anchors.json: %s" % (path, e))
    return vmap.load(cloud, append=append, anchors=anchors)
