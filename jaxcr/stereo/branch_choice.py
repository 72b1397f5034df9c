"""Which branch each view's tube took at a crossing, chosen by the two views together
(issue 16 item 2: the tracer turned onto a cable or tool crossing in front of the tube).

One view's tracer (:func:`jaxcr.segmentation.foreground.plate_foreground`) decides at a
crossing from that view alone; where it follows the crossing object, its tip lands on the
object, and the two views' tips are far from each other's epipolar lines (the flag of
:func:`jaxcr.stereo.pipeline.traced_stereo_tips`). Each view then offers candidates: its
trace and the re-traces from the junctions it passed
(:func:`jaxcr.segmentation.foreground.trace_alternatives`). A pair of candidates is
*consistent* when its two tips (as ``tips_of`` places them) lie within ``match_px`` of each
other's epipolar lines: the two tips may then be the images of one 3-D point, which the
tube's end is and a random pair of ends is not.

A tip's epipolar line crosses the whole other image, so a view's alternatives, ending here
and there, meet it now and then by chance; the choice is therefore narrow. Only pairs in
which one view keeps its own trace are considered (a view's tip that agrees with the other
view's traced tip), and a view's trace is replaced only by an alternative that is
*smoother* than it: one that follows fewer crossing objects (``crossings_followed``: the
line it leaves a junction along lies on the mask behind the junction too, an X rather than
a Y, :func:`jaxcr.segmentation.foreground.crosses_through`), or as many with a smaller
largest turn at its junctions (``crossing_turn_deg``; a tube goes on behind a crossing
object, a trace that followed the object turns by the crossing angle). Among those pairs
(the two traces themselves included) the one with the fewest crossings followed, then the
smallest sum of turns, then the smallest epipolar distance wins. No consistent pair:
nothing is chosen (the caller keeps its traces; the frame stays flagged).

With ``inconsistency_of`` (what :func:`jaxcr.stereo.pipeline.traced_stereo_tips` passes:
the length of the two whole backbones that does not triangulate consistently,
:mod:`jaxcr.stereo.backbone_consistency`) the smoothness gate is replaced by that length:
an alternative must lower it clearly and follow no more crossing objects (a tube that
hooks back turns more at the hook than the trace that stopped there, so the turn cannot
gate it; a chance meeting of a wrong end with the other tip's epipolar line leaves the
rest of the backbone unexplained).

Pixels are distorted (as the camera records them) at the interface and undistorted inside.
Numpy float64 and cv2 (undistortion), per frame, at the edge of the stereo pipeline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jaxcr.stereo.tip_consistency import undistort_pixels
from jaxcr.stereo.tip_geometry import epipolar_distances, fundamental_from_poses

__all__ = ["BranchChoice", "choose_branches"]


@dataclass
class BranchChoice:
    """Result of :func:`choose_branches`: ``indices`` (i0, i1) the chosen candidate of each
    view; ``tips`` [(2,), (2,)] their tips (distorted (u, v), from ``tips_of``);
    ``epipolar_px`` their epipolar distance; ``turn_deg`` the sum of their
    ``crossing_turn_deg``; ``consistent_pairs`` how many pairs were within ``match_px``;
    ``inconsistent_px`` the chosen pair's ``inconsistency_of`` (None without it)."""

    indices: tuple[int, int]
    tips: list
    epipolar_px: float
    turn_deg: float
    consistent_pairs: int
    inconsistent_px: float | None = None


#: :func:`choose_branches`' level (px) of a pair whose whole backbones explain each other
CONSISTENT_PX = 40.0


def _smoother(alt, orig) -> bool:
    """Whether ``alt`` follows fewer crossing objects than ``orig``, or as many with a
    smaller largest turn at its junctions."""
    fa, fo = int(getattr(alt, "crossings_followed", 0)), int(getattr(orig, "crossings_followed", 0))
    return (fa, float(alt.crossing_turn_deg)) < (fo, float(orig.crossing_turn_deg))


def _follows_no_more(alt, orig) -> bool:
    """Whether ``alt`` follows no more crossing objects than ``orig``."""
    return int(getattr(alt, "crossings_followed", 0)) <= int(getattr(orig, "crossings_followed", 0))


def _follows_fewer(alt, orig) -> bool:
    """Whether ``alt`` follows fewer crossing objects than ``orig``."""
    return int(getattr(alt, "crossings_followed", 0)) < int(getattr(orig, "crossings_followed", 0))


def choose_branches(
    cams, candidates, *, tips_of=None, match_px: float = 15.0, inconsistency_of=None,
    consistent_px: float = CONSISTENT_PX, margin_px: float = 20.0, any_pair: bool = False,
    more_crossings_if_consistent: bool = False, both_if_traces_cross: bool = False,
    tip_flag_px: float | None = None, tip_rank: bool = True,
) -> BranchChoice | None:  # fmt: skip
    """The consistent pair of candidates with the smoothest paths (module docstring).

    ``cams``: two calibrated cameras (``K``, ``dist``, ``T_cam_robot`` in one frame).
    ``candidates``: per view a list of objects with ``tip`` (2,) (distorted (u, v)) and
    ``crossing_turn_deg`` (as :class:`jaxcr.segmentation.foreground.TubeTrace`).
    ``tips_of(a, b)``: the two tips of a pair (e.g. corrected for the end face by
    :func:`jaxcr.stereo.pipeline.trace_stereo_tips`), or None to use ``a.tip``, ``b.tip``;
    a pair whose tips are not finite is skipped. ``match_px``: the largest epipolar
    distance (px, undistorted) of a consistent pair (15: three times the flag of
    :func:`jaxcr.stereo.pipeline.traced_stereo_tips`, because a tip that is on the right
    branch but off along it, a trace stopped short or run on, is mended after the choice by
    :func:`jaxcr.stereo.tip_consistency.reconcile_tips`). None when no pair is
    consistent.

    ``inconsistency_of(a, b, tips)``: the length (px) of the pair's backbones that the
    other view does not explain (e.g. :func:`jaxcr.stereo.backbone_consistency.
    backbone_consistency`'s ``inconsistent_px`` of the backbones ending at ``tips``), or
    None for the tips-only rule above. Given, it replaces the smoothness gate: a view's
    trace is replaced by an alternative when the pair's inconsistent length is more than
    ``margin_px`` below the traces' own pair's, smooth or not (a tube that hooks back
    turns more at the hook than the trace that stopped there); and the pairs are ranked
    first by whether that length is within ``consistent_px``, then as above (crossings
    followed, turns), then by the length. ``margin_px`` scales with the image: the
    caller gives it in tube widths (:func:`jaxcr.stereo.pipeline.traced_stereo_tips`:
    1.25 widths). ``any_pair`` (with ``inconsistency_of``): pairs in which both views
    leave their traces are offered too, each alternative under the same gate (not used
    by the pipeline: docs/decisions.md S31). ``more_crossings_if_consistent``: an
    alternative that follows more crossing objects than its view's trace is allowed when
    the pair's length is within ``consistent_px`` (what :func:`jaxcr.stereo.pipeline.
    traced_stereo_tips` passes since S36: a tube that crosses its own silhouette is an X
    as a cable is, :func:`jaxcr.segmentation.foreground.crosses_through`).
    ``both_if_traces_cross`` (with ``inconsistency_of``): where *both* views' traces
    follow a crossing object (each view's own tracer left a junction along an X, so
    neither trace is evidence for the other view), pairs in which both views leave their
    traces are offered too, each alternative following fewer crossing objects than its
    view's trace and the pair under the same gate (what :func:`jaxcr.stereo.pipeline.
    traced_stereo_tips` passes since S39; ``any_pair`` offers them everywhere, which S31
    found breaks right frames whose one view's trace is right).

    ``tip_flag_px`` (with ``inconsistency_of``; docs/decisions.md S49): where the traces'
    own tips are over ``tip_flag_px`` from each other's epipolar lines, a pair whose tips
    are within it also passes the gate when it leaves no more unexplained than the traces'
    pair, follows no more crossing objects, and each changed view's tip is over
    ``margin_px`` from its trace's tip (another branch, not the same path's end, which the
    tip step mends); and with ``tip_rank`` pairs within ``tip_flag_px`` rank before the
    others (after the consistency level). A trace that follows a cable along the epipolar
    lines explains itself with the other view, so no alternative can be ``margin_px``
    better there."""
    F = fundamental_from_poses(np.asarray(cams[0].K, np.float64), cams[0].T_cam_robot,
                               np.asarray(cams[1].K, np.float64), cams[1].T_cam_robot)  # fmt: skip
    best, key, n_ok = None, None, 0
    base_bad, base_e = np.inf, np.inf
    if inconsistency_of is not None:
        a, b = candidates[0][0], candidates[1][0]
        tips = tips_of(a, b) if tips_of is not None else (a.tip, b.tip)
        tips = [np.asarray(t, np.float64) for t in tips]
        if all(np.all(np.isfinite(t)) for t in tips):
            base_bad = float(inconsistency_of(a, b, tips))
            base_tips = tips
            x0, x1 = (undistort_pixels(c, t)[0] for c, t in zip(cams, tips, strict=True))
            base_e = float(max(epipolar_distances(F, x0, x1)))
    # The traces' tips disagree: a pair whose tips agree may replace them with backbones no
    # less consistent than the traces' (S49).
    tips_flagged = tip_flag_px is not None and inconsistency_of is not None and base_e > tip_flag_px
    both_cross = (
        both_if_traces_cross
        and inconsistency_of is not None
        and all(int(getattr(c[0], "crossings_followed", 0)) > 0 for c in candidates)
    )
    for i0, a in enumerate(candidates[0]):
        for i1, b in enumerate(candidates[1]):
            if i0 and i1 and not (any_pair and inconsistency_of is not None):
                # One view keeps its trace (the first candidate), unless both traces
                # followed a crossing object and both alternatives follow fewer (S39).
                if not (
                    both_cross
                    and _follows_fewer(a, candidates[0][0])
                    and _follows_fewer(b, candidates[1][0])
                ):
                    continue
            if (
                inconsistency_of is None
                and (i0 or i1)
                and not _smoother(
                    candidates[0 if i0 else 1][i0 or i1], candidates[0 if i0 else 1][0]
                )  # fmt: skip
            ):
                continue
            tips = tips_of(a, b) if tips_of is not None else (a.tip, b.tip)
            tips = [np.asarray(t, np.float64) for t in tips]
            if not all(np.all(np.isfinite(t)) for t in tips):
                continue
            x0, x1 = (undistort_pixels(c, t)[0] for c, t in zip(cams, tips, strict=True))
            e = float(max(epipolar_distances(F, x0, x1)))
            if not e <= match_px:
                continue
            n_ok += 1
            turn = float(a.crossing_turn_deg) + float(b.crossing_turn_deg)
            followed = int(getattr(a, "crossings_followed", 0)) + int(
                getattr(b, "crossings_followed", 0)
            )
            k, bad = (followed, turn, e), None
            if inconsistency_of is not None:
                bad = base_bad if not (i0 or i1) else float(inconsistency_of(a, b, tips))
                alts_ok = all(
                    _follows_no_more(x, candidates[v][0])
                    for v, (i, x) in enumerate(((i0, a), (i1, b)))
                    if i
                )
                # A pair that explains itself may follow more crossing objects than the
                # traces (a tube that crosses its own silhouette is an X too); it still
                # ranks after every such pair that follows fewer (the key below).
                alts_ok = alts_ok or (more_crossings_if_consistent and bad <= consistent_px)
                better = bad < base_bad - margin_px
                if tips_flagged and e <= tip_flag_px and bad <= base_bad:
                    # Another branch (its tip over the margin from the trace's), not the
                    # same path's end placed again, which the tip step mends.
                    better = better or all(
                        np.linalg.norm(tips[v] - base_tips[v]) > margin_px
                        for v, i in enumerate((i0, i1))
                        if i
                    )
                if (i0 or i1) and not (better and alts_ok):
                    continue
                off = bool(tips_flagged and tip_rank and e > tip_flag_px)
                k = (bad > consistent_px, off, followed, turn, bad, e)
            if key is None or k < key:
                best, key = ((i0, i1), tips, e, turn, bad), k
    if best is None:
        return None
    return BranchChoice(best[0], best[1], best[2], best[3], n_ok, best[4])
