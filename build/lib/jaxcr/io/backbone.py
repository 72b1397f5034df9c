"""Measured backbones and tip pixels for ``jaxcr fit`` (file formats in docs/dataset-format.md).

A backbone file holds k >= 2 points (x, y, z), base first and the tip last, in a declared
unit (``m``, ``cm`` or ``mm``); they are returned in metres:

* ``.csv`` / ``.txt``: one point per line, comma- or whitespace-separated; blank lines and
  ``#`` comments skipped; a comment ``# unit: mm`` declares the unit; an optional first line
  of column names (e.g. ``x,y,z``) is a header.
* ``.json``: ``{"unit": "mm", "points": [[x, y, z], ...]}``.
* ``.npy``: a (k, 3) float array; the unit comes from ``--unit``.

A unit given both in the file and by ``--unit`` must agree; no unit at all is an error (a
backbone in millimetres read as metres would be 1000 times too large).

A tip-pixel file is ``{"tips": {"<camera>": [u, v], ...}}`` (pixels, OpenCV convention).
"""

from __future__ import annotations

import math
import os
import re

import numpy as np

from jaxcr.errors import InputError
from jaxcr.io.jsonfile import read_json, read_text

UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
_UNIT_LINE = re.compile(r"^#\s*unit\s*[:=]\s*(\S+)\s*$", re.I)


def _unit(declared: str | None, given: str | None, path: str) -> float:
    for u, where in ((declared, "unit"), (given, "--unit")):
        if u is not None and u not in UNITS:
            raise InputError(
                f"unknown unit {u!r}; expected one of {list(UNITS)}", path, None, where
            )
    if declared is not None and given is not None and declared != given:
        raise InputError(
            f"the file declares unit {declared!r} but --unit is {given!r}", path, None, "unit"
        )
    unit = declared if declared is not None else given
    if unit is None:
        raise InputError(
            "no unit declared: add a '# unit: mm' line (or \"unit\" in JSON) or pass --unit "
            f"{'/'.join(UNITS)}",
            path,
            None,
            "unit",
        )
    return UNITS[unit]


def _check_points(a: np.ndarray, path: str) -> np.ndarray:
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(
            f"expected k x 3 points (x, y, z), got shape {a.shape}", path, None, "points"
        )
    if a.shape[0] < 2:
        raise InputError(f"need at least 2 points, got {a.shape[0]}", path, None, "points")
    bad = np.argwhere(~np.isfinite(a))
    if bad.size:
        raise InputError(f"point {bad[0][0]} is not finite", path, None, "points")
    return a


def _read_text_points(path: str) -> tuple[np.ndarray, str | None]:
    text = read_text(path, "a CSV file", "not a text CSV file")
    unit, rows, header_allowed = None, [], True
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            m = _UNIT_LINE.match(line)
            if m:
                unit = m.group(1)
            continue
        fields = [f for f in re.split(r"[,\s;]+", line) if f]
        try:
            values = [float(f) for f in fields]
        except ValueError:
            if header_allowed and not rows:
                header_allowed = False
                continue
            raise InputError(
                f"line {lineno}: non-numeric value in {fields}", path, None, "points"
            ) from None
        header_allowed = False
        if len(values) != 3:
            raise InputError(
                f"line {lineno}: expected 3 values (x, y, z), got {len(values)}",
                path,
                None,
                "points",
            )
        rows.append(values)
    if not rows:
        raise InputError("no points found", path, None, "points")
    return np.asarray(rows, np.float64), unit


def read_backbone(path: str | os.PathLike, unit: str | None = None) -> np.ndarray:
    """(k, 3) backbone points in metres from ``path`` (module docstring); ``unit`` is
    ``--unit``. Raises :class:`InputError` (one line naming the file and field)."""
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext == ".npy":
        if not os.path.isfile(path):
            raise InputError("file not found", path)
        try:
            a = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as err:
            raise InputError(f"not a readable .npy array ({err})", path) from None
        if not np.issubdtype(a.dtype, np.number):
            raise InputError(f"expected a numeric array, got dtype {a.dtype}", path, None, "points")
        declared = None
        a = np.asarray(a, np.float64)
    elif ext == ".json":
        d = read_json(path)
        if not isinstance(d, dict):
            raise InputError('expected an object {"unit": ..., "points": [...]}', path)
        unknown = sorted(set(d) - {"unit", "points"})
        if unknown:
            raise InputError(
                f"unknown key(s) {unknown}; allowed: ['points', 'unit']", path, None, unknown[0]
            )
        if "points" not in d:
            raise InputError("missing required key", path, None, "points")
        declared = d.get("unit")
        try:
            a = np.asarray(d["points"], np.float64)
        except (TypeError, ValueError):
            raise InputError("expected a list of [x, y, z] numbers", path, None, "points") from None
    else:
        a, declared = _read_text_points(path)
    scale = _unit(declared, unit, path)
    return _check_points(a, path) * scale


def read_tips(path: str | os.PathLike, cameras: list[str]) -> dict[str, tuple[float, float]]:
    """``{camera: (u, v)}`` from a tip-pixel JSON file; every camera must be in ``cameras``."""
    path = os.fspath(path)
    d = read_json(path)
    if not isinstance(d, dict) or set(d) != {"tips"} or not isinstance(d["tips"], dict):
        raise InputError('expected {"tips": {"<camera>": [u, v], ...}}', path, None, "tips")
    if not d["tips"]:
        raise InputError("no tips given", path, None, "tips")
    out = {}
    for cam, uv in d["tips"].items():
        field = f"tips.{cam}"
        if cam not in cameras:
            raise InputError(
                f"unknown camera {cam!r}; the dataset has {cameras}", path, None, field
            )
        ok = (
            isinstance(uv, list)
            and len(uv) == 2
            and all(isinstance(x, int | float) and not isinstance(x, bool) for x in uv)
        )
        if not ok or not all(math.isfinite(x) for x in uv):
            raise InputError(f"expected [u, v] finite pixel numbers, got {uv!r}", path, None, field)
        out[cam] = (float(uv[0]), float(uv[1]))
    return out
