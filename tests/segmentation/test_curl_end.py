"""The curled-end fit (jaxcr.segmentation.curl_end) against tube ends drawn in the test: the
union of discs of radius r round a densely sampled axis (straight, then an arc), counted by
supersampling and blurred by scipy.ndimage (tests.helpers.drawn_tube), with noise; the path given to the fit stops
where a tracer stops on a curl (before the arc). The axis distance in closed form against
the distance to the densely sampled axis (scipy cKDTree).

Tolerances: over the cases below and 12 more (turns -150..150 deg, arcs 12-24 px, half widths
5-8 px, noise 5 % of the contrast; 5 December 2026) the largest tip error was 1.34 px (a nearly straight
end, 4 deg: the drawn round end against the model's end face; the three cases below 0.2-0.3
px) and of the half width 0.04 px; the bounds are about twice and five times those (the
solve is iterative, lsmr: a BLAS of another CPU may end it elsewhere).
Float64 numpy/scipy (no jit), so it holds on any x86-64 CPU.
"""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from jaxcr.segmentation.curl_end import _axis_distance, curl_axis, fit_curl_end
from tests.helpers.drawn_tube import drawn_tube

TIP_PX = 2.5


@pytest.mark.parametrize("k", [0.0, 0.02, -0.09, 0.3])
def test_axis_distance_is_the_sampled_axis_distance(k):
    P, th, L0, L1 = np.array([3.0, -2.0]), 0.7, 20.0, 25.0
    X = np.random.default_rng(1).uniform(-40, 60, (500, 2))
    d_ax, d_end, end, th_end = _axis_distance(X, P, th, L0, k, L1)
    dense, th_e = curl_axis(P, th, L0, k, L1, step=0.005)
    ref = cKDTree(dense).query(X)[0]
    np.testing.assert_allclose(np.minimum(d_ax, d_end), ref, atol=0.01)
    np.testing.assert_allclose(end, dense[-1], atol=0.01)
    assert th_end == pytest.approx(th_e)


@pytest.mark.parametrize(
    "r, turn_deg, arc_px", [(6.0, 0.0, 20.0), (6.0, 110.0, 16.0), (7.0, -150.0, 18.0)]
)
def test_fit_puts_the_tip_of_a_drawn_curl(r, turn_deg, arc_px):
    rng = np.random.default_rng(int(r * 10 + abs(turn_deg)))
    k = np.radians(turn_deg) / arc_px
    start = np.array([10.0, 70.3])
    axis, _ = curl_axis(start, -0.2, 60.0, k, arc_px, step=0.1)
    score = 0.1 + 0.9 * drawn_tube((128, 128), axis, r)
    score += rng.normal(0.0, 0.05, score.shape)
    # The path a tracer leaves on a curl: the straight part, ending 2 px into the arc.
    path, _ = curl_axis(start, -0.2, 62.0, 0.0, 0.0, step=4.0)
    fit = fit_curl_end(score, path, 2.0 * r)
    assert fit is not None
    assert np.linalg.norm(fit.tip - axis[-1]) <= TIP_PX
    assert abs(fit.half_width - r) <= 0.2


def test_fit_refuses_a_path_too_short():
    score = np.zeros((64, 64))
    assert fit_curl_end(score, np.array([[10.0, 10.0], [12.0, 10.0]]), 12.0) is None
