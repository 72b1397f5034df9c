"""A curled tube end offered to the two-view tips, chosen by one view's residuals and the
other view's epipolar line (issue 16 item 2, docs/decisions.md S46), and the gently bent end
where the tracer stopped early (S47). The pipeline runs the second only by default
(:func:`jaxcr.stereo.pipeline.traced_stereo_tips`, ``refit_ends=True``, ``curl_ends=False``:
the first did not hold on fresh frames, S48).

Where a tube curls at its end, each view's tracer and end fit stop at the curl's apex
(:mod:`jaxcr.segmentation.curl_end`). After the two-view tip step
(:func:`jaxcr.stereo.pipeline.traced_stereo_tips`), each view's end is fitted with the
curled model and with the same model held to a gentle bend; a view's tip is replaced by
its curled fit's where

* the curl explains the view's cue clearly better than a gentle bend (the robust costs'
  ratio at most ``max_ratio``: one view's residual alone is a weak test, stop 37's
  prototype),
* the curled tip is at least ``min_move_px`` from the tip it replaces, and
* the other view agrees: the pair's epipolar distance drops by at least
  ``min_gap_drop_px`` (a curl that moves the tip along the epipolar line, or away from it,
  is not taken).

Of two views that qualify, the one with the lower cost ratio (action ``"curled"``).

Else (S47) a view's tip is replaced by its gentle fit's where that tip is at least
``refit_move_px`` from the two-view tip and the pair's epipolar distance drops by at least
``min_gap_drop_px`` to at most ``refit_gap_px`` (the tip step's own 5 px: the pair is then
consistent by its standard): the tube's cue fades before its end (the grey tube over the
white calibration board) and the tracer stopped where it faded; the end model fitted
over the whole window finds the end beyond (action ``"refitted"``; of two views, the lower
gap). Host side, numpy / scipy.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from jaxcr.segmentation.curl_end import CurlEnd, fit_curl_end
from jaxcr.stereo.tip_consistency import epipolar_gap_px

__all__ = ["CurlChoice", "choose_curled_end", "curled_trace"]


@dataclass(frozen=True)
class CurlChoice:
    """Result of :func:`choose_curled_end`: ``view`` (0 or 1) whose tip is replaced,
    ``fit`` its :class:`jaxcr.segmentation.curl_end.CurlEnd`, ``tips`` the new pair
    (distorted (u, v)), the pair's epipolar distance before and after (px), ``action``
    ``"curled"`` (the curled fit's tip) or ``"refitted"`` (the gentle fit's)."""

    view: int
    fit: CurlEnd
    tips: list
    epipolar_before_px: float
    epipolar_after_px: float
    action: str = "curled"


def choose_curled_end(
    cams,
    traces,
    tips,
    *,
    max_ratio: float = 0.9,
    min_move_px: float = 2.0,
    min_gap_drop_px: float = 2.0,
    curl: bool = True,
    refit: bool = True,
    refit_move_px: float = 10.0,
    refit_gap_px: float = 5.0,
) -> CurlChoice | None:
    """The view whose tip a curled end (with ``curl``) or a gentle end found well away
    (with ``refit``) replaces, by the rules of the module docstring, or None (the pipeline
    runs the second only: the first did not hold on fresh frames, docs/decisions.md S48;
    without ``curl`` only the gentle model is fitted). ``traces``: the two views'
    :class:`jaxcr.segmentation.foreground.TubeTrace` whose paths end where the tracer
    stopped (the branch choice's); ``tips``: the two-view tips."""
    tips = [np.asarray(t, np.float64) for t in tips]
    if not all(np.all(np.isfinite(t)) for t in tips):
        return None
    gap0 = epipolar_gap_px(cams, tips)
    if not gap0 >= min_gap_drop_px:  # no replacement can drop it that far: nothing to fit
        return None

    def with_tip(j, tip):
        new = list(tips)
        new[j] = np.asarray(tip, np.float64)
        return new, epipolar_gap_px(cams, new)

    best, refitted = None, None
    for j, t in enumerate(traces):
        score = getattr(t, "score", None)
        if score is None:
            continue
        fit = fit_curl_end(score, t.backbone, t.width_px, curled=curl)
        if fit is None or not fit.gentle_cost > 0:
            continue
        ratio = fit.cost / fit.gentle_cost
        if curl and ratio <= max_ratio and np.linalg.norm(fit.tip - tips[j]) >= min_move_px:
            new, gap = with_tip(j, fit.tip)
            if gap <= gap0 - min_gap_drop_px and (best is None or ratio < best[0]):
                best = (ratio, CurlChoice(j, fit, new, gap0, gap))
        if refit and np.linalg.norm(fit.gentle_tip - tips[j]) >= refit_move_px:
            new, gap = with_tip(j, fit.gentle_tip)
            if gap <= min(gap0 - min_gap_drop_px, refit_gap_px) and (
                refitted is None or gap < refitted.epipolar_after_px
            ):
                refitted = CurlChoice(j, fit, new, gap0, gap, "refitted")
    if best is not None:
        return best[1]
    return refitted


def curled_trace(trace, fit: CurlEnd, action: str = "curled"):
    """A copy of ``trace`` ending in the fit (the curled one, or the gentle one for
    ``action`` ``"refitted"``): its path behind the fit's anchor and the fitted axis
    (``backbone``), ``tip``, ``end_dir`` and ``end_half_width_px`` from the fit (the gentle
    fit's direction: its path's last step), ``cap_px`` 0 (the tip is the axis' end);
    attribute ``curl_of``: ``trace``."""
    if action == "refitted":
        bb = fit.gentle_backbone
        d = bb[-1] - bb[-2] if len(bb) > 1 else fit.direction
        d = d / max(float(np.linalg.norm(d)), 1e-12)
        out = replace(trace, tip=fit.gentle_tip.copy(), backbone=bb.copy(), end_dir=d,
                      cap_px=0.0)  # fmt: skip
    else:
        out = replace(trace, tip=fit.tip.copy(), backbone=fit.backbone.copy(),
                      end_dir=fit.direction.copy(), end_half_width_px=fit.half_width,
                      cap_px=0.0)  # fmt: skip
    out.curl_of = trace
    return out
