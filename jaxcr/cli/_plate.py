"""The ``--plate-...`` flags of the plate foreground (:mod:`jaxcr.segmentation.foreground`), shared by
``jaxcr segment --background plate`` and ``jaxcr stereo --segmentation trace``."""

from __future__ import annotations

import argparse
import dataclasses
import math

from jaxcr.errors import InputError
from jaxcr.segmentation.foreground import PlateForegroundConfig

_D = PlateForegroundConfig()

# (flag, config field, type, help); every default is the library's.
_FLAGS = (
    ("--plate-dark", "dark", float, "relative darkening 1 - Y/Y_plate that counts as robot"),
    ("--plate-desat", "desat", float, "saturation drop (max-min)/max from plate to frame"),
    ("--plate-hue", "hue_deg", float, "hue change in degrees (where both are coloured)"),
    ("--plate-diff", "diff", float, "RGB distance to the best-scaled plate (colours 0-1)"),
    ("--plate-min-gain", "min_gain", float, "darkest shadow gain the diff cue forgives"),
    ("--plate-min-chroma", "min_chroma", float, "chroma max-min below which hue is ignored"),
    ("--plate-min-luma", "min_luma", float,
     "darkening and saturation are relative to max(value, this): near-black pixels (tape) "
     "have no reliable relative change"),
    ("--plate-close", "close_px", float,
     "grey closing of the score (disc radius, px) filling a tube seen by its edges (0 = off)"),
    ("--plate-high", "high", float, "hysteresis: score (1 = a cue at its threshold) that seeds"),
    ("--plate-low", "low", float, "hysteresis: score that extends a seeded region"),
    ("--plate-blur", "blur_px", float, "Gaussian smoothing of frame and plate (px; 0 = off)"),
    ("--plate-max-shift", "max_shift_px", float, "largest plate drift searched (px)"),
    ("--plate-step", "step_px", float, "tracing step (px)"),
    ("--plate-look", "look_px", float, "length of the ray scoring a direction (px)"),
    ("--plate-max-turn", "max_turn_deg", float, "largest turn per tracing step (degrees)"),
    ("--plate-corner", "corner_deg", float,
     "where no turn up to --plate-max-turn is supported, turns up to this are tried (a "
     "projected kink or hook; degrees)"),
    ("--plate-support", "support", float, "fraction of that ray on the mask to go on"),
    ("--plate-max-gap", "max_gap_px", float,
     "longest stretch where the tube matches the background (tape, shadow, crease) that "
     "is bridged (px)"),
    ("--plate-gap-turn", "gap_turn_deg", float, "cone searched across a gap (degrees)"),
    ("--plate-max-width", "max_width_px", float, "widest tube searched across (px)"),
    ("--plate-min-seed", "min_seed_px", int, "smallest mask component accepted after a gap"),
    ("--plate-tip-cap", "tip_cap", float,
     "largest end-face correction of the tip, x the tube's half width (0 = the silhouette's "
     "end)"),
    ("--plate-gap-visible", "gap_visible", float,
     "a gap is not bridged where the tube's colour would score above --plate-high against "
     "the plate on more than this fraction of it (the tube would have been seen: it ended; "
     "1 = off)"),
    ("--plate-tube-width", "tube_width_px", float,
     "tube width (px) that every length above is set for: a view where the tube measures "
     "k = round(width / this) >= 2 times it (near the entry) is traced on the frame and plate "
     "reduced k times, and its tip refined at full resolution"),
    ("--plate-scale", "scale", int,
     "force that reduction factor k (1 = full resolution; 0 = from the measured width)"),
)  # fmt: skip


def add_plate_arguments(p: argparse.ArgumentParser, mode_flag: str) -> None:
    """Add the ``--plate-...`` flags (an argument group) to ``p``; ``mode_flag`` names the
    option that selects the plate foreground, for the help text."""
    g = p.add_argument_group(
        "plate foreground (" + mode_flag + "; jaxcr.segmentation.foreground)",
        "aligned background plate, cues beyond the key colour with hysteresis, tracing "
        "from the entry point with gap bridging. Each cue is 1 at its threshold. Lengths "
        "(px) are for a tube about --plate-tube-width px wide; wider tubes are traced at a "
        "reduced resolution (--plate-scale).",
    )
    for flag, name, typ, text in _FLAGS:
        g.add_argument(
            flag,
            type=typ,
            default=None,
            metavar="X",
            help=f"{text} (default {getattr(_D, name)})",
        )
    g.add_argument(
        "--plate-align",
        action=argparse.BooleanOptionalAction,
        default=None,
        help=f"register the plate to each frame (sub-pixel translation; default {_D.align})",
    )
    g.add_argument(
        "--plate-refine-tip",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="place the tip at the score's half level along the tube, minus the end face's "
        f"foreshortening (default {_D.refine}; off: the last mask pixel)",
    )


def plate_config(args) -> PlateForegroundConfig:
    """The :class:`PlateForegroundConfig` of the parsed flags (unset = default). Bad values
    raise :class:`InputError` naming the flag."""
    kw = {}
    for flag, name, typ, _ in _FLAGS:
        v = getattr(args, flag[2:].replace("-", "_"), None)
        if v is None:
            continue
        if (
            not math.isfinite(v)
            or v < 0
            or (
                v == 0
                and name
                not in (
                    "blur_px",
                    "min_chroma",
                    "min_luma",
                    "gap_visible",
                    "close_px",
                    "tip_cap",
                    "scale",
                )
            )
        ):
            raise InputError(f"{flag} must be a finite number > 0", field=flag[2:])
        kw[name] = typ(v)
    if getattr(args, "plate_align", None) is not None:
        kw["align"] = bool(args.plate_align)
    if getattr(args, "plate_refine_tip", None) is not None:
        kw["refine"] = bool(args.plate_refine_tip)
    cfg = dataclasses.replace(_D, **kw)
    if cfg.low > cfg.high:
        raise InputError("--plate-low must be <= --plate-high", field="plate-low")
    if cfg.support > 1:
        raise InputError("--plate-support must be <= 1", field="plate-support")
    if cfg.gap_visible > 1:
        raise InputError("--plate-gap-visible must be <= 1", field="plate-gap-visible")
    return cfg


def plate_flags_given(args) -> list[str]:
    """The ``--plate-...`` flags set on the command line (to refuse them without the mode)."""
    out = [f for f, *_ in _FLAGS if getattr(args, f[2:].replace("-", "_"), None) is not None]
    if getattr(args, "plate_align", None) is not None:
        out.append("--plate-align")
    if getattr(args, "plate_refine_tip", None) is not None:
        out.append("--plate-refine-tip")
    return out
