"""Point clouds as dicts of per-point arrays (``x, y, z`` plus any fields: intensity, confidence,
normals...), written and read as binary PLY or PCD with numpy structured arrays (no per-point
Python). Writes are atomic. Mesh files are Open3D's business (see mdr_slam.fusion).
"""
from __future__ import annotations

import os
from collections import OrderedDict
from typing import Mapping

import numpy as np

from .atomic import atomic_path

Cloud = "OrderedDict[str, np.ndarray]"

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_NP_TO_PLY = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int",
              "u4": "uint", "f4": "float", "f8": "double"}


def _columns(cloud: Mapping[str, np.ndarray]):
    cols = OrderedDict()
    n = None
    for k, v in cloud.items():
        v = np.asarray(v).reshape(-1)
        if v.dtype.kind == "b":
            v = v.astype(np.uint8)
        if v.dtype.kind == "f" and v.dtype.itemsize not in (4, 8):
            v = v.astype(np.float32)
        if v.dtype.kind in "iu" and v.dtype.itemsize == 8:
            v = v.astype(np.int32 if v.dtype.kind == "i" else np.uint32)
        if n is None:
            n = len(v)
        elif len(v) != n:
            raise ValueError("field %r has %d values, expected %d" % (k, len(v), n))
        cols[k] = v
    return cols, (n or 0)


def points_cloud(xyz: np.ndarray, **fields) -> "OrderedDict[str, np.ndarray]":
    """Cloud dict from (N, 3) points and named per-point arrays."""
    xyz = np.asarray(xyz)
    c = OrderedDict([("x", xyz[:, 0]), ("y", xyz[:, 1]), ("z", xyz[:, 2])])
    c.update(fields)
    return c


def cloud_xyz(cloud: Mapping[str, np.ndarray]) -> np.ndarray:
    return np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1)


def write_ply(path: str, cloud: Mapping[str, np.ndarray]) -> int:
    """Binary little-endian PLY with one vertex element; returns the number of points."""
    cols, n = _columns(cloud)
    dt = np.dtype([(k, v.dtype.newbyteorder("<")) for k, v in cols.items()])
    rec = np.empty(n, dtype=dt)
    for k, v in cols.items():
        rec[k] = v
    header = ["ply", "format binary_little_endian 1.0", "comment written by mdr_slam",
              "element vertex %d" % n]
    header += ["property %s %s" % (_NP_TO_PLY[v.dtype.str.lstrip("<>|=")], k) for k, v in cols.items()]
    header.append("end_header")
    with atomic_path(path, ".ply") as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(rec.tobytes())
    return n


def read_ply(path: str) -> "OrderedDict[str, np.ndarray]":
    """Vertex properties of a PLY file (binary LE/BE or ASCII) as a dict of arrays."""
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError("%s is not a PLY file" % path)
        fmt, elements, cur = None, [], None
        while True:
            line = f.readline()
            if not line:
                raise ValueError("%s: PLY header has no end_header" % path)
            tok = line.decode("ascii", "replace").split()
            if not tok or tok[0] in ("comment", "obj_info"):
                continue
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                cur = {"name": tok[1], "count": int(tok[2]), "props": []}
                elements.append(cur)
            elif tok[0] == "property":
                if tok[1] == "list":
                    cur["props"].append(("list", tok[4], tok[2], tok[3]))
                else:
                    cur["props"].append((tok[1], tok[2]))
            elif tok[0] == "end_header":
                break
        if not elements or elements[0]["name"] != "vertex":
            raise ValueError("%s: the first PLY element must be 'vertex'" % path)
        v = elements[0]
        if any(p[0] == "list" for p in v["props"]):
            raise ValueError("%s: list properties in vertices are not supported" % path)
        names = [p[1] for p in v["props"]]
        if fmt == "ascii":
            data = np.loadtxt(f, max_rows=v["count"], ndmin=2) if v["count"] else \
                np.zeros((0, len(names)))
            out = OrderedDict()
            for i, (t, name) in enumerate(v["props"]):
                out[name] = data[:, i].astype(_PLY_TYPES[t])
            return out
        order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
        if order is None:
            raise ValueError("%s: unknown PLY format %r" % (path, fmt))
        dt = np.dtype([(name, order + _PLY_TYPES[t]) for t, name in v["props"]])
        buf = f.read(dt.itemsize * v["count"])
        if len(buf) < dt.itemsize * v["count"]:
            raise ValueError("%s: PLY file is truncated" % path)
        rec = np.frombuffer(buf, dtype=dt)
    return OrderedDict((k, rec[k].astype(rec[k].dtype.newbyteorder("="))) for k in names)


_PCD_TYPE = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
             ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("I", 8): "i8", ("U", 8): "u8"}


def write_pcd(path: str, cloud: Mapping[str, np.ndarray]) -> int:
    """Binary PCD v0.7 (what PCL's pcl_viewer and Open3D read)."""
    cols, n = _columns(cloud)
    dt = np.dtype([(k, v.dtype.newbyteorder("<")) for k, v in cols.items()])
    rec = np.empty(n, dtype=dt)
    for k, v in cols.items():
        rec[k] = v
    kinds = {"f": "F", "i": "I", "u": "U"}
    header = ["# .PCD v0.7 - Point Cloud Data file format (written by mdr_slam)", "VERSION 0.7",
              "FIELDS " + " ".join(cols), "SIZE " + " ".join(str(v.dtype.itemsize) for v in cols.values()),
              "TYPE " + " ".join(kinds[v.dtype.kind] for v in cols.values()),
              "COUNT " + " ".join("1" for _ in cols), "WIDTH %d" % n, "HEIGHT 1",
              "VIEWPOINT 0 0 0 1 0 0 0", "POINTS %d" % n, "DATA binary"]
    with atomic_path(path, ".pcd") as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(rec.tobytes())
    return n


def read_pcd(path: str) -> "OrderedDict[str, np.ndarray]":
    """Fields of an ASCII or binary PCD file (binary_compressed: use Open3D)."""
    hdr = {}
    with open(path, "rb") as f:
        while True:
            line = f.readline()
            if not line:
                raise ValueError("%s: PCD header has no DATA line" % path)
            s = line.decode("ascii", "replace").strip()
            if not s or s.startswith("#"):
                continue
            key, _, rest = s.partition(" ")
            hdr[key.upper()] = rest.split()
            if key.upper() == "DATA":
                break
        names = hdr["FIELDS"]
        sizes = [int(x) for x in hdr["SIZE"]]
        types = hdr["TYPE"]
        counts = [int(x) for x in hdr.get("COUNT", ["1"] * len(names))]
        n = int(hdr["POINTS"][0])
        mode = hdr["DATA"][0]
        if any(c != 1 for c in counts):
            raise ValueError("%s: PCD fields with COUNT > 1 are not supported" % path)
        dt = np.dtype([(nm, "<" + _PCD_TYPE[(t, s)]) for nm, t, s in zip(names, types, sizes)])
        if mode == "ascii":
            data = np.loadtxt(f, max_rows=n, ndmin=2) if n else np.zeros((0, len(names)))
            return OrderedDict((nm, data[:, i].astype(dt[nm].newbyteorder("=")))
                               for i, nm in enumerate(names))
        if mode != "binary":
            raise ValueError("%s: PCD DATA %s is not supported (convert with Open3D)" % (path, mode))
        buf = f.read(dt.itemsize * n)
        if len(buf) < dt.itemsize * n:
            raise ValueError("%s: PCD file is truncated" % path)
        rec = np.frombuffer(buf, dtype=dt)
    return OrderedDict((k, rec[k].astype(rec[k].dtype.newbyteorder("="))) for k in names)


def write_cloud(path: str, cloud: Mapping[str, np.ndarray]) -> int:
    """PLY or PCD by extension."""
    ext = os.path.splitext(path)[1].lower()
    if ext == ".pcd":
        return write_pcd(path, cloud)
    if ext == ".ply":
        return write_ply(path, cloud)
    raise ValueError("unknown point cloud extension %r (use .ply or .pcd)" % ext)


def read_cloud(path: str) -> "OrderedDict[str, np.ndarray]":
    ext = os.path.splitext(path)[1].lower()
    if ext == ".pcd":
        return read_pcd(path)
    if ext == ".ply":
        return read_ply(path)
    raise ValueError("unknown point cloud extension %r (use .ply or .pcd)" % ext)
