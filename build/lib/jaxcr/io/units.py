"""Length units and key checks shared by the calibration, dataset and stereo file readers.

A file (or an entry of one) may declare ``unit``: ``"m"`` (default), ``"cm"`` or ``"mm"``.
Lengths in it are converted to metres on load. Unknown keys are errors that name the key and
suggest the nearest known one, because a misspelt key is otherwise ignored silently: a stereo
file in millimetres with ``units: mm`` (not ``unit``) was once read as a 426 m baseline.

Plausible ranges (bench-top continuum-robot rigs; anything outside is almost always a unit
error, so it is refused with a suggested unit):

* camera-to-robot translation (``T_cam_robot``) and any position in a file: at most
  :data:`MAX_LENGTH_M` = 5 m from its origin;
* stereo baseline ``|T|``: :data:`MIN_BASELINE_M` = 1 mm to :data:`MAX_LENGTH_M` = 5 m
  (coinciding cameras cannot triangulate).
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from jaxcr.errors import InputError

UNITS: dict[str, float] = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
MAX_LENGTH_M = 5.0
MIN_BASELINE_M = 1e-3
_UNIT_WORDS = {"m": "metres", "cm": "centimetres", "mm": "millimetres"}


def unit_scale(d: Mapping[str, Any], file=None, prefix: str = "") -> float:
    """Metres per unit of the mapping's ``unit`` key (1.0 when absent)."""
    unit = d.get("unit", "m")
    if not isinstance(unit, str) or unit not in UNITS:
        raise InputError(
            f"expected one of {list(UNITS)}, got {unit!r}", file=file, field=prefix + "unit"
        )
    return UNITS[unit]


def unit_name(scale: float) -> str:
    """The ``unit`` string of a scale from :func:`unit_scale`."""
    return next(u for u, s in UNITS.items() if s == scale)


def nearest_key(key: str, known: Iterable[str]) -> str | None:
    """The known key closest to ``key`` (difflib ratio, case-insensitive), or None when
    nothing is reasonably close (ratio below 0.5)."""
    known = list(known)
    lower = {k.lower(): k for k in known}
    m = difflib.get_close_matches(str(key).lower(), list(lower), n=1, cutoff=0.5)
    return lower[m[0]] if m else None


def check_known_keys(
    d: Mapping[str, Any],
    known: Iterable[str],
    file=None,
    prefix: str = "",
    frame=None,
    informational: Iterable[str] = (),
) -> None:
    """Raise on the first key of ``d`` (in file order) that is neither in ``known`` nor in
    ``informational`` (accepted and ignored), naming it and the nearest known key."""
    known = list(known)
    allowed = set(known) | set(informational)
    for k in d:
        if k in allowed:
            continue
        near = nearest_key(k, known)
        hint = f" (did you mean {near!r}?)" if near else f" (known keys: {', '.join(known)})"
        raise InputError(f"unknown key {k!r}{hint}", file=file, frame=frame, field=prefix + k)


def _unit_hint(length_m: float, scale: float, lo: float, hi: float, typical: float) -> str:
    """``; if it is in millimetres (...), set "unit": "mm"`` for the unit that brings the
    number written in the file into ``[lo, hi]`` metres, closest (in log scale) to a
    ``typical`` length; ``""`` when no unit does."""
    written = length_m / scale
    fits = [u for u in UNITS if UNITS[u] != scale and lo <= written * UNITS[u] <= hi]
    if not fits:
        return ""
    u = min(fits, key=lambda u: abs(np.log(written * UNITS[u] / typical)))
    what = f"{written:.4g} {u} = {written * UNITS[u]:.4g} m"
    return f'; if it is in {_UNIT_WORDS[u]} ({what}), set "unit": "{u}"'


def check_length(
    length_m: float,
    what: str,
    scale: float,
    file=None,
    field: str | None = None,
    lo: float = 0.0,
    hi: float = MAX_LENGTH_M,
    frame=None,
    typical: float = 0.3,
) -> None:
    """Refuse a length (metres, after unit conversion with ``scale``) outside ``[lo, hi]``,
    suggesting the unit that makes the written number plausible and nearest ``typical``
    (metres; default 0.3 m, a bench-top rig's camera distance or baseline)."""
    if lo <= length_m <= hi:
        return
    unit = unit_name(scale)
    side = f"over {hi:g} m" if length_m > hi else f"under {lo * 1e3:g} mm"
    raise InputError(
        f"{what} of {length_m:.4g} m is implausible ({side}, read with unit {unit!r})"
        + _unit_hint(length_m, scale, max(lo, 1e-6), hi, typical),
        file=file,
        frame=frame,
        field=field,
    )
