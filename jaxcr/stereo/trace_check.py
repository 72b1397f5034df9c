"""Whether one camera's traced backbone is plausible without a second view (issue 16, S33:
one camera, ``--segmentation trace``, real_like development seeds: the default trace put a
tip 386 px off (seed 4005, the trace stopped at the entry) or 591 px off (seed 4000 f0001,
the trace bridged onto a crossing cable) and nothing said so).

Two views check each other (``tip_epipolar_px``); one view has no such check, and a
one-camera dataset declares no robot length or diameter. What the traced view itself gives,
host numpy, per frame:

- ``length_px``: the length of the view's ``backbone_px`` (entry to ``tip_px``, px);
- ``width_px``: the tube's width the tracer measured near the entry (px,
  :class:`jaxcr.segmentation.foreground.TubeTrace` ``measured_width_px``);
- ``edge_px``: the tip's distance to the image border (px).

``suspect`` when ``length_px < STUB_WIDTHS * width_px`` (the trace stopped within a few
tube widths of the entry: a gap, a shadow or the tape there) or ``edge_px < width_px`` (the
trace ran out of the image, along something that leaves the view: a tube whose tip is in
view does not end within a tube width of the border). Measured (docs/decisions.md S33,
experiments/results/stereo/warnings_s33.md, development seeds, 1280x720): the true
backbones of seeds 4000-4199 (400 views) project to 226 px or longer (about 15 tube widths
of ~15 px) and their tips lie 34 px or more from the border; the 26 right traces of seeds
4000-4015 are 18 widths or longer, their tips 126 px or more from the border; of the six
wrong ones, the stopped trace of seed 4005 is 0.5 widths long and seed 4010's view-2 trace
ends 1.6 px from the border.

Only those kinds of wrong trace are caught. A trace that runs on along an object crossing
the tube and ends inside the image (seed 4000 f0001: 591 px off, 35 widths long, 32 px from
the border) or stops part way is like a right one; its tip stays unchecked
(docs/stereo-format.md, "One camera").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["STUB_WIDTHS", "TraceCheck", "trace_check"]

#: A traced backbone shorter than this many tube widths is suspect (module docstring).
STUB_WIDTHS = 4.0


@dataclass
class TraceCheck:
    """Result of :func:`trace_check`: ``length_px``, ``width_px`` and ``edge_px`` (module
    docstring) and ``suspect`` (``length_px`` under :data:`STUB_WIDTHS` tube widths or
    ``edge_px`` under one)."""

    length_px: float
    width_px: float
    edge_px: float
    suspect: bool


def trace_check(backbone_px, width_px: float, image_size: tuple[int, int]) -> TraceCheck:
    """Check one view's traced backbone. ``backbone_px``: (n, 2) (u, v) OpenCV pixels from
    the entry to the tip (n >= 1; the centre of pixel (row 0, column 0) is (0, 0));
    ``width_px``: the tube's measured width (px); ``image_size``: (width, height) px."""
    bb = np.asarray(backbone_px, np.float64).reshape(-1, 2)
    length = float(np.sum(np.linalg.norm(np.diff(bb, axis=0), axis=1)))
    width = float(width_px)
    u, v = bb[-1]
    edge = float(min(u, v, image_size[0] - 1 - u, image_size[1] - 1 - v))
    suspect = length < STUB_WIDTHS * width or edge < width
    return TraceCheck(round(length, 1), round(width, 1), round(edge, 1), bool(suspect))
