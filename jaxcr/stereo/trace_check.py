"""Whether one camera's traced backbone is plausible without a second view (issue 16, S33:
one camera, ``--segmentation trace``, real_like development seeds: the default trace put a
tip 386 px off (seed 4005, the trace stopped at the entry) or 591 px off (seed 4000 f0001,
the trace bridged onto a crossing cable) and nothing said so).

Two views check each other (``tip_epipolar_px``); one view has no such check, and a
one-camera dataset declares no robot length or diameter. What the traced view itself gives,
host numpy, per frame:

- ``length_px``: the length of the view's ``backbone_px`` (entry to ``tip_px``, px);
- ``width_px``: the tube's width the tracer measured near the entry (px,
  :class:`jaxcr.segmentation.foreground.TubeTrace` ``measured_width_px``).

``suspect`` when ``length_px < STUB_WIDTHS * width_px``: the trace stopped within a few
tube widths of the entry (a gap, a shadow or the tape at the entry), so ``tip_px`` is not
the tube's end unless the robot is seen end-on. Measured (docs/decisions.md S33,
experiments/results/stereo/warnings_s33.md): the true backbones of development seeds
4000-4199 (400 views, 1280x720) project to 226 px or longer (about 15 tube widths of
~15 px); the stopped trace of seed 4005 is under 10 px.

Only that kind of wrong trace is caught. A trace that runs on along an object crossing the
tube (seed 4000 f0001) or stops part way is as long as a right one; its tip stays unchecked
(docs/stereo-format.md, "One camera"). Rejected: the tip's distance to the image border
(the cable trace ended 32 px from it, true tips come as close as 34 px).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["STUB_WIDTHS", "TraceCheck", "trace_check"]

#: A traced backbone shorter than this many tube widths is suspect (module docstring).
STUB_WIDTHS = 4.0


@dataclass
class TraceCheck:
    """Result of :func:`trace_check`: ``length_px`` and ``width_px`` (module docstring) and
    ``suspect`` (``length_px`` under :data:`STUB_WIDTHS` tube widths)."""

    length_px: float
    width_px: float
    suspect: bool


def trace_check(backbone_px, width_px: float) -> TraceCheck:
    """Check one view's traced backbone. ``backbone_px``: (n, 2) (u, v) pixels from the
    entry to the tip (n >= 1); ``width_px``: the tube's measured width (px)."""
    bb = np.asarray(backbone_px, np.float64).reshape(-1, 2)
    length = float(np.sum(np.linalg.norm(np.diff(bb, axis=0), axis=1)))
    width = float(width_px)
    return TraceCheck(round(length, 1), round(width, 1), bool(length < STUB_WIDTHS * width))
