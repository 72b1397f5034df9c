"""How the candidates found along the other view's trace enter the branch choice (issue 16
item 2, round 15a, docs/decisions.md S36): their own turns at their view's junctions, and
the view's own re-traces first.

The branch choice (:func:`jaxcr.stereo.branch_choice.choose_branches`) ranks consistent
pairs by how many crossing objects their paths follow (``crossings_followed``) and by their
largest turn where they pass a junction (``crossing_turn_deg``): a tube goes on smoothly
behind a crossing cable, a path that turned onto the cable turns by the crossing angle. A
candidate found along the other view's trace
(:func:`jaxcr.stereo.guided_retrace.guided_candidate`) has no junctions of its own, so it
was given the values of the trace it may replace (round 14, S35). That made it "neither
smoother nor rougher" than that trace, but it is wrong exactly where it matters: where the
view's trace turned onto a cable, the guided path that goes on behind the cable carries the
trace's large turn; where the trace went on and the guided path turns (a path stopped at a
hook's apex, or led onto the cable by a wrong anchor), it carries the trace's small one.

Here the guided path is measured as the tracer measures its own paths, at the same
junctions: each junction the view's tracer saw (``TubeTrace.junctions`` of the trace at its
traced scale) that the guided path passes within a tube width of is a junction of the
guided path, and its turn (:func:`jaxcr.segmentation.foreground.crossing_turn`, two look
lengths on) and whether it leaves along a crossing object
(:func:`jaxcr.segmentation.foreground.crosses_through`, on the traced view's mask) are
computed on the guided path itself. Nothing is tuned: the lengths are the tracer's own.

A guided candidate agrees with its anchor (the other view's trace) *by construction*: it
was searched along the anchor's epipolar lines, so that the pair explains itself is no
evidence that it is the tube (a trace stopped at a hook's apex or a little short guides the
other view to a path that stops there too, dev 4087, 4010). A re-trace of the view's own
(:func:`jaxcr.segmentation.foreground.trace_alternatives`) that explains the other view's
trace is two independent traces agreeing in 3-D. :func:`offered_guided` therefore offers a
view's guided candidate only where none of the view's own re-traces explains the other
view's trace; where the *other* view's own candidates hold a pair that explains itself (a
re-trace onto a cable seen by both views: a real 3-D object, dev 4079, 4185), the guided
candidate still competes with it, ranked by its own turns.

Pixels are distorted (as the camera records them). Numpy, per frame, at the edge of the
stereo pipeline: nothing here is jitted.
"""

from __future__ import annotations

import numpy as np

__all__ = ["guided_turns", "offered_guided", "with_own_turns"]


def guided_turns(candidate, trace) -> tuple[float, int] | None:
    """``(crossing_turn_deg, crossings_followed)`` of the path ``candidate.backbone`` (full
    resolution, distorted (u, v)) at the junctions of ``trace`` (a
    :class:`jaxcr.segmentation.foreground.TubeTrace` of :func:`plate_foreground` with its
    ``retrace`` state) that it passes within one tube width of (module docstring); None
    when ``trace`` has no ``retrace`` state. A path that passes none of the junctions turns
    by 0 and follows no crossing object (the tracer's own convention for a path without
    junctions)."""
    from jaxcr.segmentation.foreground import _to_low, crosses_through, crossing_turn

    ctx = getattr(trace, "retrace", None)
    if ctx is None:
        return None
    k, cfg, low = ctx.k, ctx.cfg, ctx.low
    bb = _to_low(np.asarray(candidate.backbone, np.float64).reshape(-1, 2), k)
    if len(bb) < 3 or not low.junctions:
        return 0.0, 0
    # The tracer walks in steps of cfg.step_px at the traced scale; the guided path is
    # densified to that step, so the look lengths mean the same number of points.
    width = float(low.width_px)
    turn, followed = 0.0, 0
    for j in low.junctions:
        p = np.asarray(j[1], np.float64)
        d = np.linalg.norm(bb - p[None], axis=1)
        i = int(np.argmin(d))
        if not (d[i] <= width and 0 < i < len(bb) - 1):
            continue
        turn = max(turn, crossing_turn(bb, i, 2.0 * cfg.look_px))
        followed += int(crosses_through(ctx.seeds_l, bb, i, 2.0 * cfg.look_px, width))
    return float(turn), int(followed)


def with_own_turns(candidates, traces) -> list[list]:
    """``candidates`` (per view a list, as :func:`jaxcr.stereo.guided_retrace.
    guided_candidates` returns them) with each candidate's ``crossing_turn_deg`` and
    ``crossings_followed`` replaced by its own (:func:`guided_turns` against its view's
    trace in ``traces``); a candidate whose view has no ``retrace`` state keeps the
    copied values. The candidates are changed in place and returned."""
    for v, cands in enumerate(candidates):
        for c in cands:
            own = guided_turns(c, traces[v])
            if own is not None:
                c.crossing_turn_deg, c.crossings_followed = own
    return candidates


def offered_guided(guided, own, explains) -> list[list]:
    """``guided`` (per view a list, :func:`jaxcr.stereo.guided_retrace.guided_candidates`)
    without the candidates of a view ``v`` where one of ``v``'s own re-traces ``own[v][1:]``
    (``own[v][0]`` is ``v``'s trace) explains the other view's trace ``own[1 - v][0]``
    (module docstring). ``explains(a, b)``: whether the pair (view 0's ``a``, view 1's
    ``b``) explains itself (e.g. tips within the choice's epipolar ``match_px`` and whole
    backbones within its ``consistent_px``, as :func:`jaxcr.stereo.pipeline.
    traced_stereo_tips` passes)."""
    out = [[], []]
    for v in (0, 1):
        if not guided[v]:
            continue
        other = own[1 - v][0]
        pairs = ((alt, other) if v == 0 else (other, alt) for alt in own[v][1:])
        if not any(explains(a, b) for a, b in pairs):
            out[v] = list(guided[v])
    return out
