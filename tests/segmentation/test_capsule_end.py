"""The capsule end fit (jaxcr.segmentation.capsule_end) against tube ends rendered in closed
form in the test (a band and a half-ellipse, counted by supersampling and blurred by
scipy.ndimage), at several angles, widths and end-face lengths, with noise.

Tolerances: over 24 random ends (half widths 3-8 px, caps 0-r, blur 0.8-1.5 px, noise 5 % of
the contrast, start 2 px and 5 deg off) the largest errors were 0.9 px (tip), 1.4 deg
(direction), 0.1 px (half width) and 1.0 px (cap); the bounds below are 1.5-2 times those.
The fit is float64 numpy/scipy (no jit), so they hold on any x86-64 CPU.
"""

from dataclasses import dataclass, field

import numpy as np
import pytest

from jaxcr.segmentation.capsule_end import capsule_end_image, fit_capsule_end, with_capsule_end

TIP_PX, DIR_DEG, HALF_PX, CAP_PX = 1.5, 3.0, 0.3, 1.5


def _dir(a):
    return np.array([np.cos(a), np.sin(a)])


def test_rendered_end_area_is_the_half_ellipse():
    """The reference's covered area beyond the band is pi r a / 2 (closed form)."""
    d, r, a = _dir(0.4), 5.0, 3.0
    im = capsule_end_image((80, 80), np.array([40.2, 39.7]), d, r, a, blur=0.0, supersample=16)
    band = capsule_end_image((80, 80), np.array([40.2, 39.7]), d, r, 0.0, blur=0.0,
                             supersample=16)  # fmt: skip
    assert float((im - band).sum()) == pytest.approx(np.pi * r * a / 2, abs=0.3)


@pytest.mark.parametrize(
    "angle, r, cap_frac",
    [(0.3, 5.0, 0.6), (2.0, 6.0, 1.0), (-1.2, 4.0, 0.1), (3.0, 3.0, 1.0), (0.9, 7.0, 0.3),
     (-2.5, 8.0, 0.0)],
)  # fmt: skip
def test_fit_recovers_the_rendered_end(angle, r, cap_frac):
    rng = np.random.default_rng(int(100 * r))
    d, tip, a = _dir(angle), np.array([48.3, 47.6]), cap_frac * r
    im = capsule_end_image((96, 96), tip, d, r, a, blur=1.2, inside=1.0, background=0.1)
    im = im + rng.normal(0.0, 0.05, im.shape)
    # Started off the end: 2.5 px away, 5 deg turned, the half width 20 % wide, no cap.
    fit = fit_capsule_end(im, tip + np.array([2.0, -1.5]), _dir(angle + np.radians(5.0)),
                          1.2 * r, cap=0.0)  # fmt: skip
    assert fit is not None
    assert np.linalg.norm(fit.tip - tip) <= TIP_PX
    turn = np.degrees(np.arccos(np.clip(fit.direction @ d, -1.0, 1.0)))
    assert turn <= DIR_DEG
    assert abs(fit.half_width - r) <= HALF_PX
    assert abs(fit.cap - a) <= CAP_PX
    # The silhouette's end (tip + cap d) is better fixed than the split between the two.
    assert abs((fit.tip + fit.cap * fit.direction - tip - a * d) @ d) <= 1.0


def test_fit_finds_no_end_in_a_blank_window():
    im = np.full((64, 64), 0.2) + np.random.default_rng(0).normal(0, 0.01, (64, 64))
    assert fit_capsule_end(im, np.array([32.0, 32.0]), _dir(0.0), 4.0) is None


@dataclass
class _Trace:
    backbone: np.ndarray
    tip: np.ndarray
    score: np.ndarray | None
    end_dir: np.ndarray = field(default_factory=lambda: np.zeros(2))
    cap_px: float = 0.0
    end_half_width_px: float = 0.0
    width_px: float = 10.0


def test_with_capsule_end_replaces_the_tip_only():
    d, tip, r = _dir(0.5), np.array([48.0, 48.0]), 5.0
    im = capsule_end_image((96, 96), tip, d, r, 0.6 * r, blur=1.2, inside=1.0, background=0.1)
    start = tip + 3.0 * d  # the end walk's tip on the silhouette's end
    bb = np.array([start - 30 * d, start - 20 * d, start - 10 * d, start])
    tr = _Trace(backbone=bb, tip=start.copy(), score=im, end_dir=d.copy(), end_half_width_px=r)
    out = with_capsule_end(tr)
    assert out is not tr
    assert np.linalg.norm(out.tip - tip) <= TIP_PX
    np.testing.assert_array_equal(out.backbone[:-1], bb[:-1])
    np.testing.assert_array_equal(out.backbone[-1], out.tip)
    np.testing.assert_array_equal(tr.tip, start)  # the input is not changed
    assert abs(out.cap_px - 0.6 * r) <= CAP_PX
    # No score or no end direction: the trace itself.
    assert with_capsule_end(_Trace(backbone=bb, tip=start, score=None, end_dir=d)) is not None
    bare = _Trace(backbone=bb, tip=start, score=im)
    assert with_capsule_end(bare) is bare
