"""jaxcr.stereo.guided_ranking: a guided candidate's own turns at its view's junctions, against
closed-form crossing angles, and the branch choice of ``traced_stereo_tips`` with them on a
closed-form 3-D tube and a cable that leaves it, projected by OpenCV (``cv2.projectPoints``
with lens distortion)."""

from types import SimpleNamespace

import cv2
import numpy as np

from jaxcr.segmentation.foreground import (
    PlateForegroundConfig,
    TubeTrace,
    crosses_through,
    crossing_turn,
)
from jaxcr.stereo import pipeline
from jaxcr.stereo.guided_ranking import guided_turns, offered_guided, with_own_turns
from tests.helpers.stereo_views import cam as _cam
from tests.helpers.stereo_views import project as _project

H, W = 720, 1280
WIDTH = 9.0  # drawn tube width, px
CFG = PlateForegroundConfig()


def _draw(lines, shape, width):
    img = np.zeros(shape, np.uint8)
    for ln in lines:
        pts = np.round(np.asarray(ln) * 16).astype(np.int32)
        cv2.polylines(img, [pts], False, 255, int(width), cv2.LINE_AA, shift=4)
    return img.astype(np.float64) / 255.0


def _ctx(mask_low, k, junctions, width_low):
    """The ``retrace`` state guided_turns reads (as plate_foreground leaves it)."""
    low = SimpleNamespace(junctions=junctions, width_px=width_low)
    return SimpleNamespace(seeds_l=mask_low, k=k, cfg=CFG, low=low)


def _line(p, d, length, step=1.0):
    d = np.asarray(d, np.float64) / np.linalg.norm(d)
    return np.asarray(p, np.float64) + np.outer(np.arange(0.0, length + 1e-9, step), d)


def test_guided_turns_against_the_crossing_angle():
    """At the traced scale (k = 2) a straight tube (heading +u) is crossed at P by a cable
    at 50 deg. A path that goes on behind the cable turns by 0 and follows nothing; a path
    that turns onto the cable at P turns by the crossing angle (closed form: the chord two
    look lengths along a straight cable) and follows one crossing object (the cable goes
    on behind P); a path that passes no junction turns by 0."""
    k, theta = 2, np.radians(50.0)
    shape_low = (H // k, W // k)
    P = np.array([300.0, 180.0])
    tube = _line([100.0, 180.0], [1, 0], 400)
    cable_dir = np.array([np.cos(theta), -np.sin(theta)])
    cable = np.vstack([P - 150 * cable_dir, P + 150 * cable_dir])
    mask_low = _draw([tube, cable], shape_low, WIDTH / k) > 0.4
    trace = SimpleNamespace(retrace=_ctx(mask_low, k, [(100, P, None)], WIDTH / k))

    def full(low):  # traced-scale pixels to full resolution (foreground._to_full)
        return np.asarray(low) * k + (k - 1) / 2.0

    through = SimpleNamespace(backbone=full(tube[:350]))
    onto = SimpleNamespace(backbone=full(np.vstack([tube[:201], _line(P, cable_dir, 120)[1:]])))
    elsewhere = SimpleNamespace(backbone=full(_line([100.0, 300.0], [1, 0], 300)))

    t, f = guided_turns(through, trace)
    assert t < 1.0 and f == 0
    t, f = guided_turns(onto, trace)
    # Straight polylines: the turn is the crossing angle to rounding (the heading arriving
    # is the tube's, the chord lies on the cable).
    assert abs(t - 50.0) < 0.5 and f == 1
    assert guided_turns(elsewhere, trace) == (0.0, 0)
    assert guided_turns(through, SimpleNamespace(retrace=None)) is None


def test_with_own_turns_replaces_the_copied_values():
    k = 1
    P = np.array([300.0, 300.0])
    tube = _line([100.0, 300.0], [1, 0], 500)
    mask = _draw([tube], (H, W), WIDTH) > 0.4
    tr = SimpleNamespace(retrace=_ctx(mask, k, [(200, P, None)], WIDTH))
    cand = SimpleNamespace(backbone=tube, crossing_turn_deg=77.0, crossings_followed=2)
    kept = SimpleNamespace(backbone=tube, crossing_turn_deg=77.0, crossings_followed=2)
    out = with_own_turns([[cand], [kept]], [tr, SimpleNamespace(retrace=None)])
    assert out[0][0] is cand and cand.crossing_turn_deg < 1.0 and cand.crossings_followed == 0
    assert kept.crossing_turn_deg == 77.0 and kept.crossings_followed == 2


# A two-view scene: a 3-D tube and a straight cable leaving it in 3-D.
CAMS = [_cam([0.0, 0.0, 0.0], [0.0, -0.02, 0.35]), _cam([0.0, -0.35, 0.0], [-0.12, -0.02, 0.37])]


def _arc(n=400):
    """A circular arc of 60 mm radius turned by 120 deg in a tilted plane (metres)."""
    a = np.linspace(0.0, np.radians(120.0), n)
    r = 0.06
    return np.stack([0.3 * r * np.sin(a), -r * (1 - np.cos(a)), r * np.sin(a)], 1)


def test_traced_stereo_tips_one_choice_with_own_turns():
    """Both views see the tube and a cable that leaves it at 40 % of its length at 45 deg
    (in 3-D; both are drawn in both views). View 0 traced the tube, and a re-trace of
    view 0 from its junction followed the cable; view 1's trace followed the cable. The
    pair (view 0's cable re-trace, view 1's trace) is a wrong pair that explains itself
    (one 3-D cable), so round 14's second stage never ran. In one choice, view 1's tube
    found along view 0's trace goes on behind the junction (its own turn ~0) and wins:
    view 1's tip on the projected tube end, view 0's trace kept."""
    X = _arc()
    i = int(0.4 * len(X))
    tng = X[i + 1] - X[i - 1]
    tng /= np.linalg.norm(tng)
    side = np.cross(tng, [0.0, 0.0, 1.0])  # across the tube as both cameras see it
    side /= np.linalg.norm(side)
    dirc = np.cos(np.radians(45)) * tng + np.sin(np.radians(45)) * side
    C = X[i] + np.outer(np.linspace(0.0, 0.05, 200), dirc)  # 50 mm of cable
    bb = [_project(c, X) for c in CAMS]
    cb = [_project(c, C) for c in CAMS]
    assert all(np.all((b > 0) & (b < [W, H])) for b in (*bb, *cb))
    scores = [_draw([bb[v], cb[v]], (H, W), WIDTH) for v in range(2)]
    onto = [np.vstack([bb[v][: i + 1], cb[v][1:]]) for v in range(2)]

    def trace(v, path):
        mask = scores[v] > 0.4
        tr = TubeTrace(mask, path, path[-1].copy(), path[0].copy(), score=scores[v],
                       seed_mask=mask, width_px=WIDTH)  # fmt: skip
        tr.retrace = _ctx(mask, 1, [(i, bb[v][i], None)], WIDTH)
        # The turn and crossings the tracer gives its own paths at the junction.
        tr.crossing_turn_deg = crossing_turn(path, i, 2.0 * CFG.look_px)
        tr.crossings_followed = int(crosses_through(mask, path, i, 2.0 * CFG.look_px, WIDTH))
        return tr

    traces = [trace(0, bb[0]), trace(1, onto[1])]
    alt0 = trace(0, onto[0])
    alt0.departure = i
    alts = {id(traces[0]): [alt0], id(traces[1]): []}
    saved = pipeline.trace_alternatives
    pipeline.trace_alternatives = lambda t: alts[id(t)]
    try:
        tips, src, _, chosen = pipeline.traced_stereo_tips(CAMS, traces)
    finally:
        pipeline.trace_alternatives = saved
    assert "+branch" in src and chosen[0] is traces[0] and chosen[1].departure == -1
    # The bound of test_guided_retrace's refined guided tip (2.5 px).
    assert np.linalg.norm(tips[1] - bb[1][-1]) < 2.5, (tips[1], bb[1][-1])
    assert np.linalg.norm(tips[0] - bb[0][-1]) < 2.5, (tips[0], bb[0][-1])


def test_offered_guided_own_retraces_first():
    """A view's guided candidate is dropped exactly where one of the view's own re-traces
    explains the other view's trace (here: the pairs named in ``ok``); the other view's
    guided candidate is unaffected, and the trace itself does not count."""
    t0, a0, t1, a1 = (SimpleNamespace(name=n) for n in ("t0", "a0", "t1", "a1"))
    g0, g1 = SimpleNamespace(name="g0"), SimpleNamespace(name="g1")
    own = [[t0, a0], [t1, a1]]

    def explains_of(ok):
        return lambda a, b: (a.name, b.name) in ok

    # t0 with a1 explains: view 1's own re-trace agrees with view 0's trace -> g1 dropped.
    out = offered_guided([[g0], [g1]], own, explains_of({("t0", "a1")}))
    assert out == [[g0], []]
    # a0 with t1: view 0's guided dropped instead.
    out = offered_guided([[g0], [g1]], own, explains_of({("a0", "t1")}))
    assert out == [[], [g1]]
    # The traces' own pair, or a pair of two re-traces, does not gate anything.
    out = offered_guided([[g0], [g1]], own, explains_of({("t0", "t1"), ("a0", "a1")}))
    assert out == [[g0], [g1]]
