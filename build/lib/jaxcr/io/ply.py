"""PLY writer/reader for coloured point clouds (binary little-endian; x y z float32,
optional nx ny nz float32, red green blue uchar). Written to a temporary file, then renamed."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from jaxcr.errors import InputError


def write_ply(
    path, points: np.ndarray, colours: np.ndarray, normals: np.ndarray | None = None
) -> Path:
    """Write ``points`` (n, 3) m, ``colours`` (n, 3) in [0, 1] and optional ``normals``."""
    path = Path(path)
    n = len(points)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.zeros(n, dtype=fields)
    for k, a in zip("xyz", np.asarray(points).T, strict=True):
        rec[k] = a
    if normals is not None:
        for k, a in zip(("nx", "ny", "nz"), np.asarray(normals).T, strict=True):
            rec[k] = a
    c8 = np.clip(np.rint(np.asarray(colours) * 255), 0, 255).astype(np.uint8)
    for k, a in zip(("red", "green", "blue"), c8.T, strict=True):
        rec[k] = a
    types = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property {types[t]} {name}" for name, t in fields]
    header += ["end_header"]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(rec.tobytes())
    os.replace(tmp, path)
    return path


def read_ply(path) -> dict[str, np.ndarray]:
    """Read a binary little-endian PLY vertex element written by :func:`write_ply`."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file", file=str(path))
    lines = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise InputError("only binary little-endian PLY is supported", file=str(path))
    n = next(int(s.split()[2]) for s in lines if s.startswith("element vertex"))
    tmap = {"float": "<f4", "uchar": "u1"}
    fields = [(s.split()[2], tmap[s.split()[1]]) for s in lines if s.startswith("property")]
    rec = np.frombuffer(data[end + 11 :], dtype=fields, count=n)
    return {name: np.asarray(rec[name]) for name, _ in fields}
