"""Ceilings and floors of every size, count and level the commands accept, in one place.

A value outside them is refused before any work with exit 2 and one line naming the flag (or
the file, frame and field) and the limit. Each ceiling is derived from something measured or
structural, stated beside it; README.md ("Limits") lists them.

Memory: the synthetic renderers and the refinement hold per-pixel buffers whose size grows
with the image. :data:`RENDER_BYTES_PER_PIXEL` is the peak traced (numpy) memory of rendering
one frame at 640x480 divided by its pixels (``experiments/segmentation/limits_memory_per_pixel.py``,
results in ``experiments/results/segmentation/limits_memory_per_pixel.md``); it includes the fixed part,
so it over-estimates at larger sizes. The ceiling is the number of pixels whose buffers fit
:data:`MEMORY_BUDGET`.
"""

from __future__ import annotations

import math

import numpy as np

from jaxcr.errors import InputError

#: working memory a run may plan for: the free memory of an 8 GB laptop with a desktop open
MEMORY_BUDGET = 4 << 30

#: longest image side of every command (OpenCV's and libpng's fast paths, and a 8192-px
#: texture is the largest a renderer samples without tiling)
MAX_SIDE = 8192
#: shortest image side (the smallest image on which the robot spans more than a few pixels)
MIN_SIDE = 16

#: peak traced memory per pixel of one rendered frame at 640x480 (bytes), see module docstring
RENDER_BYTES_PER_PIXEL = {
    "synth": 690,
    "stereo synth": 373,
    "motion synth": 511,
    "manifold synth": 742,
    "model-object": 276,
}

#: largest image (pixels) per renderer: the buffers of one frame fit MEMORY_BUDGET
MAX_PIXELS = {k: MEMORY_BUDGET // v for k, v in RENDER_BYTES_PER_PIXEL.items()}

#: frame ids are written zero-padded to six digits (``000000``): at most 10^6 frames
MAX_FRAMES = 1_000_000

#: segment keeps every view of a frame and its background as float32 RGB (24 bytes per pixel)
#: plus their pyramid (x 4/3): 32 bytes per pixel and view for each frame of a batch
SEGMENT_BYTES_PER_PIXEL = 32

#: the coarsest pyramid level must keep at least one band tile (RefineConfig.tile = 8 px)
#: along its shorter side: levels L of an image whose shorter side is s need s >> (L-1) >= 8
MIN_LEVEL_SIDE = 8

#: bench --repeats: the median's standard error is about 1.25 sigma / sqrt(n), 4 % of the
#: spread at 1000 repeats; more only take longer (a typo of 10^9 ran for days, silently)
MAX_REPEATS = 1000

#: manifold train --step: resampled grid points; 100x the default angle grid (0.5 deg over the
#: 70 x 180 deg of the synthetic set, ~50k points): 5M points of ~10 components in float64
#: are 0.4 GB, and the query's k-d index over them as much again
MAX_MANIFOLD_POINTS = 5_000_000

#: stereo --segments: the tube split (stereo.segments.piecewise_constant) is a dynamic program
#: of O(k n^2) in the backbone samples n, and a tube shorter than its 5-sample median filter
#: is not resolved; 16 tubes is twice the most any concentric-tube robot in the literature has
MAX_SEGMENTS = 16

#: --max-steps: 100x the core's finest-level default (30 steps); a frame then takes minutes
MAX_STEPS = 3000

#: model-object --capture-frames / scene capture_frames: depth frames averaged per capture; 64 is
#: ~2 s of a 30 fps RGB-D camera held still, and a per-pixel mean of more gains < 1 % over 64
MAX_CAPTURE_FRAMES = 64

#: seeds: JAX keys hold 32 bits (jax.random.PRNGKey(2**40) equals PRNGKey(0), and 2**64 is an
#: OverflowError), so two runs with different larger seeds could draw the same numbers
MAX_SEED = 2**32 - 1

#: float32's largest finite value: a joint value or coordinate beyond it is inf in the core
FLOAT32_MAX = float(np.finfo(np.float32).max)

#: joint angles (rad): float32 spacing at |q| = 2^13 is 2^-10 rad (1 mrad, 0.1 mm at the end
#: of a 10 cm link); beyond it a joint value no longer means one pose
MAX_ANGLE = 2.0**13


def check_count(value: int, flag: str, lo: int, hi: int | None = None, why: str = "") -> int:
    """``value`` if ``lo <= value <= hi``, else InputError naming ``flag`` and the limit."""
    if value < lo or (hi is not None and value > hi):
        rng = f">= {lo}" if hi is None else f"between {lo} and {hi}"
        raise InputError(f"must be {rng}, got {value}{f' ({why})' if why else ''}", field=flag)
    return int(value)


def check_number(
    value: float,
    flag: str,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
) -> float:
    """``value`` if finite and inside ``[lo, hi]`` (``(lo`` / ``hi)`` when open), else
    InputError naming ``flag`` (NaN and inf are always refused)."""
    ok = value is not None and math.isfinite(value)
    ok = ok and (lo is None or (value > lo if lo_open else value >= lo))
    ok = ok and (hi is None or (value < hi if hi_open else value <= hi))
    if not ok:
        if lo is not None and hi is not None:
            rng = f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
        elif lo is not None:
            rng = f"{'>' if lo_open else '>='} {lo:g}"
        elif hi is not None:
            rng = f"{'<' if hi_open else '<='} {hi:g}"
        else:
            rng = "finite"
        raise InputError(f"must be a finite number {rng}, got {value}", field=flag)
    return float(value)


def check_size(
    w: int, h: int, flag: str, kind: str, min_size: tuple[int, int] = (MIN_SIDE, MIN_SIDE)
) -> tuple[int, int]:
    """``(w, h)`` if at least ``min_size``, at most :data:`MAX_SIDE` per side and
    ``MAX_PIXELS[kind]`` in all; else InputError naming ``flag`` and the limit."""
    if min(w, h) < MIN_SIDE and tuple(min_size) == (MIN_SIDE, MIN_SIDE):
        raise InputError(
            f"image size must be between {MIN_SIDE} and {MAX_SIDE} pixels, got {w}x{h}",
            field=flag,
        )
    if w < min_size[0] or h < min_size[1]:
        raise InputError(
            f"image size {w}x{h} is too small, the minimum is {min_size[0]}x{min_size[1]}",
            field=flag,
        )
    if w > MAX_SIDE or h > MAX_SIDE or w * h > MAX_PIXELS[kind]:
        n = MAX_PIXELS[kind]
        raise InputError(
            f"image size {w}x{h} is over the limit of {MAX_SIDE} pixels per side and "
            f"{n} pixels in all ({n / 1e6:.1f} MP: {RENDER_BYTES_PER_PIXEL[kind]} bytes per "
            f"pixel within {MEMORY_BUDGET >> 30} GiB; README Limits)",
            field=flag,
        )
    return int(w), int(h)


def parse_size(
    text: str, flag: str, kind: str, min_size: tuple[int, int] = (MIN_SIDE, MIN_SIDE)
) -> tuple[int, int]:
    """``"640x480"`` -> (640, 480) checked by :func:`check_size`; InputError otherwise."""
    try:
        w, h = (int(x) for x in str(text).lower().split("x"))
    except ValueError:
        raise InputError(f"expected WIDTHxHEIGHT, e.g. 640x480, got {text!r}", field=flag) from None
    return check_size(w, h, flag, kind, min_size)


def check_frames(n: int, flag: str, lo: int = 1) -> int:
    """A frame count: at least ``lo``, at most :data:`MAX_FRAMES` (six-digit frame ids)."""
    return check_count(n, flag, lo, MAX_FRAMES - 1, "frame ids have six digits")


def max_levels(short_side: int) -> int:
    """Most pyramid levels an image whose shorter side is ``short_side`` pixels can have."""
    return max(1, int(math.floor(math.log2(max(short_side, 1) / MIN_LEVEL_SIDE))) + 1)


def check_finite_float32(
    a, file: str, field: str, frame=None, max_abs: float = FLOAT32_MAX
) -> np.ndarray:
    """``a`` as float64 if every value is finite and at most ``max_abs`` in magnitude (default:
    float32's range, so the core's float32 copy holds the same numbers); else InputError."""
    arr = np.asarray(a, np.float64)
    bad = ~np.isfinite(arr) | (np.abs(np.where(np.isfinite(arr), arr, 0)) > max_abs)
    if bad.any():
        v = float(arr[bad].ravel()[0])
        what = "not finite" if not np.isfinite(v) else f"over {max_abs:g} in magnitude"
        raise InputError(
            f"{int(bad.sum())} value(s) {what} (first {v!r})", file=file, frame=frame, field=field
        )
    return arr
