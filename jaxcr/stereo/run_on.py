"""A view's trace that ran on past the other view's tube end onto something else: its path
cut back there is offered to the branch choice (issue 16 item 2, round 17b,
docs/decisions.md S41).

The branch choice of :func:`jaxcr.stereo.pipeline.traced_stereo_tips` offers each view's
tube searched again along the other view's trace
(:func:`jaxcr.stereo.guided_retrace.guided_candidates`). Where one view's trace ``t_a``
ends where its tube ends and the other view's trace ``t_b`` explains all of it with its
own beginning (view ``b``'s path searched along ``t_a`` lies along ``t_b`` and explains
``t_a`` to its tip: ``guided_candidates``' ``cut_back``), the two traces are independent
tracings that agree in 3-D from the base to ``t_a``'s end, and ``t_b`` goes on. Either
``t_b`` ran on past the tube's end, or ``t_a`` stopped short (at a hook's apex: dev 3908,
3934, where view ``a``'s path along ``t_b`` is the right candidate). ``guided_candidates``
leaves this to the trim after the choice (:func:`jaxcr.stereo.tip_consistency.
trim_unexplained_tail`), which cuts ``t_b`` back where ``t_a``'s tip's epipolar line meets
it; where the tube's end touches a crossing cable or tool, that line meets ``t_b`` on the
object too, and the choice may first replace ``t_a`` by a path along ``t_b`` (agreeing with
``t_b`` by construction) or pair ``t_b`` with a re-trace onto the same object.

Physical test of which trace ran on: a tube's silhouette is continuous to its end, and a
tube goes on behind a crossing object without turning (its curvature is piecewise
constant), while a trace that took a crossing cable or tool turns by the crossing angle
(the branch choice's own reading, ``crossing_turn_deg``). A cable or tool is not attached
to the tube, so a trace that goes on past the tube's end onto one either crosses
background (a gap its tracer bridged) or leaves at a junction its tracer saw, turning
there. So where ``t_b``, at its point that explains ``t_a``'s end, begins a bridged gap
within ``near_widths`` widths, or passes a junction of its own tracer within
``junction_widths`` widths at which it turns by more than ``turn_deg``
(:func:`jaxcr.segmentation.foreground.crossing_turn`, two look lengths on, as the tracer
measures it), ``t_b`` ran on (:func:`ran_on`): view ``b``'s path cut back there (its tip
refined on the score by the guided search) is offered, and view ``a``'s path along
``t_b`` is not (:func:`with_run_on`). Where ``t_a`` stopped short (a hook's apex) ``t_b``
goes on along the tube: no gap and no turning junction there (development even seeds:
turns of 24-76 deg where ``t_b`` ran on, 5-9 deg where ``t_a`` stopped short). The
choice's gate and ranking are unchanged.

Numpy, per frame, at the edge of the stereo pipeline; nothing here is jitted.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ran_on", "with_run_on"]


def ran_on(
    trace, cut_px, *, near_widths: float = 1.0, junction_widths: float = 1.5,
    turn_deg: float = 20.0,
) -> bool:  # fmt: skip
    """Whether ``trace`` (a :class:`jaxcr.segmentation.foreground.TubeTrace` of
    :func:`plate_foreground`: ``backbone`` (n, 2) distorted (u, v), ``gaps`` index pairs of
    bridged segments, ``width_px``, ``retrace`` its traced-scale state) leaves its tube at
    its point nearest ``cut_px`` (2,) (where the other view's tube ends): a bridged gap
    begins within ``near_widths`` widths along the path of it, or one of its tracer's
    junctions within ``junction_widths`` widths of it turns the path by more than
    ``turn_deg`` (module docstring). False when the path goes on under a width beyond
    that point."""
    from jaxcr.segmentation.foreground import _to_low, crossing_turn

    bb = np.asarray(trace.backbone, np.float64).reshape(-1, 2)
    if len(bb) < 3:
        return False
    w = float(trace.width_px)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(bb, axis=0), axis=1))]
    cut = np.asarray(cut_px, np.float64)
    i = int(np.argmin(np.linalg.norm(bb - cut[None], axis=1)))
    if arc[-1] - arc[i] < w:
        return False
    gaps = list(getattr(trace, "gaps", None) or [])
    if any(abs(arc[int(g[0])] - arc[i]) <= near_widths * w for g in gaps):
        return True
    ctx = getattr(trace, "retrace", None)
    if ctx is None:
        return False
    low_bb = _to_low(bb, ctx.k)
    for j in ctx.low.junctions:
        p = np.asarray(j[1], np.float64)  # traced scale
        if np.linalg.norm(p * ctx.k + (ctx.k - 1) / 2.0 - cut) > junction_widths * w:
            continue
        m = int(np.argmin(np.linalg.norm(low_bb - p[None], axis=1)))
        if 0 < m < len(low_bb) - 1 and crossing_turn(low_bb, m, 2.0 * ctx.cfg.look_px) > turn_deg:
            return True
    return False


def with_run_on(guided, traces, cut_back, **kw) -> list[list]:
    """``guided`` (per view a list, :func:`jaxcr.stereo.guided_retrace.guided_candidates`)
    with, for each ``(b, path)`` in ``cut_back`` (filled by ``guided_candidates``) whose
    trace ``traces[b]`` ran on at the path's end (:func:`ran_on`, keywords ``kw``), that
    cut-back path added to view ``b``'s candidates and view ``1 - b``'s candidates
    removed (module docstring)."""
    out = [list(g) for g in guided]
    for b, path in cut_back:
        if ran_on(traces[b], path.tip, **kw):
            out[b].append(path)
            out[1 - b] = []
    return out
