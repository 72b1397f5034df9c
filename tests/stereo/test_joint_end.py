"""The stereo-joint end (:mod:`jaxcr.stereo.joint_end`, docs/decisions.md S27) against an
independent reference: a capped cylinder (the tube's last stretch, a flat end disc) ray-cast
through two pinhole cameras at 4x4 sub-pixels, area-averaged and Gaussian-blurred (scipy),
one view with a narrower bar continuing the silhouette past the end (a shadow or other
foreground touching the tip). Truth: the end disc's centre projected."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage as ndi
from scipy.special import erfinv

from jaxcr.stereo.joint_end import axis_line, end_profile, joint_end
from jaxcr.synth.scene import look_at_pose

K1 = np.array([[900.0, 0, 640], [0, 900, 360], [0, 0, 1]])
K2 = np.array([[850.0, 0, 620], [0, 860, 350], [0, 0, 1]])
T1 = look_at_pose(np.array([0.30, -0.05, 0.10]), [0.0, 0.0, 0.06], up=(0.0, 0.0, 1.0))
T2 = look_at_pose(np.array([0.05, -0.30, 0.12]), [0.0, 0.0, 0.06], up=(0.0, 0.0, 1.0))
RADIUS, BLUR, SUB, HALF = 0.0015, 1.0, 4, 48  # m, px, sub-pixels per pixel, window half side


def _proj(K, T, X):
    Xc = (T[:3, :3] @ np.atleast_2d(X).T).T + T[:3, 3]
    x = (K @ Xc.T).T
    return x[:, :2] / x[:, 2:]


def _render(K, T, E, u, centre_px, bar=None):
    """Score window (2 HALF, 2 HALF) around ``centre_px`` (its top-left pixel returned too):
    the capped cylinder of axis ``u`` ending at ``E`` (length 0.05 m) ray-cast at SUB x SUB
    sub-pixels, averaged, then ``bar`` ((p0, p1, half width) px: a segment rasterised on the
    same sub-pixels) added, blurred by BLUR px."""
    c0 = np.floor(centre_px).astype(int) - HALF
    g = (np.arange(2 * HALF * SUB) + 0.5) / SUB - 0.5
    uu, vv = np.meshgrid(c0[0] + g, c0[1] + g)
    R, t = T[:3, :3], T[:3, 3]
    C = -R.T @ t
    v = (R.T @ np.linalg.solve(K, np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)]))).T
    w = C - E
    a = np.einsum("ij,ij->i", v, v) - (v @ u) ** 2
    b = 2 * (v @ w - (w @ u) * (v @ u))
    c = w @ w - (w @ u) ** 2 - RADIUS**2
    disc = b * b - 4 * a * c
    sq = np.sqrt(np.maximum(disc, 0))
    t1, t2 = (-b - sq) / (2 * a), (-b + sq) / (2 * a)
    # Axial coordinate (w + t v) . u in [-0.05, 0]: the slab between the caps.
    vu = v @ u
    ta, tb = (-0.05 - w @ u) / vu, (0.0 - w @ u) / vu
    lo, hi = np.minimum(ta, tb), np.maximum(ta, tb)
    occ = (disc > 0) & (np.maximum(t1, lo) <= np.minimum(t2, hi))
    img = occ.reshape(uu.shape).astype(float)
    if bar is not None:
        p0, p1, hw = bar
        d = (p1 - p0) / np.linalg.norm(p1 - p0)
        q = np.stack([uu - p0[0], vv - p0[1]], -1)
        along = q @ d
        across = np.abs(q @ np.array([-d[1], d[0]]))
        img = np.maximum(img, ((along >= 0) & (along <= np.linalg.norm(p1 - p0)) & (across <= hw)))
    img = img.reshape(2 * HALF, SUB, 2 * HALF, SUB).mean((1, 3))
    return ndi.gaussian_filter(img, BLUR), c0


def _sampler(img, c0, contrast, bg):
    def f(p):
        q = np.asarray(p) - c0
        return bg + contrast * ndi.map_coordinates(img, [q[:, 1], q[:, 0]], order=1, mode="nearest")

    return f


def _scene(seed):
    """End point, unit axis (out of the tip), per view tip pixel, unit image direction, half
    width (px) and pixels per metre along the axis."""
    rng = np.random.default_rng(seed)
    E = np.array([0.0, 0.0, 0.06]) + rng.uniform(-0.005, 0.005, 3)
    while True:
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        # Non-degenerate draws only (the planes' angle is the gate tested below).
        if axis_line([K1, K2], [T1, T2], *_tips_dirs(E, u)[:2])[2] > 0.5:
            break
    return (E, u) + _tips_dirs(E, u)


def _tips_dirs(E, u):
    tips, dirs, R, J = [], [], [], []
    for K, T in ((K1, T1), (K2, T2)):
        p = _proj(K, T, np.stack([E, E + 1e-4 * u]))
        d = p[1] - p[0]
        J.append(np.linalg.norm(d) / 1e-4)
        dirs.append(d / np.linalg.norm(d))
        tips.append(p[0])
        z = (T[:3, :3] @ E + T[:3, 3])[2]
        R.append(K[0, 0] * RADIUS / z)
    return tips, dirs, R, J


@pytest.mark.parametrize("seed", range(3))
def test_the_clean_view_outvotes_a_silhouette_going_on_past_the_end(seed):
    E, u, tips, dirs, R, J = _scene(seed)
    # View 2's silhouette goes on 12 px past its end as a bar as wide as the central band
    # the profiles average (half width R / 2).
    bar = (tips[1], tips[1] + 12.0 * dirs[1], 0.5 * R[1])
    imgs = [_render(K1, T1, E, u, tips[0]), _render(K2, T2, E, u, tips[1], bar)]
    samplers = [_sampler(img, c0, 2.4, 0.2) for img, c0 in imgs]
    # The views' own ends as a one-view method finds them: view 2 at the bar's end.
    start = [tips[0] + 1.0 * dirs[0], tips[1] + 11.0 * dirs[1]]
    # One view alone: view 2's profile stays above the half level to the bar's end, so its
    # own end is over 8 px off. ``level``: the bar's profile (0 background, 1 tube).
    tau, prof, bg = end_profile(samplers[1], tips[1], dirs[1], R[1])
    q = (prof - bg) / 2.4
    assert tau[np.flatnonzero(q >= 0.5)[-1]] > 8.0
    level = float(np.median(q[(tau >= 3.0) & (tau <= 9.0)]))
    # Moving view 2's edge over the bar gains (2 level - 1) c per px (1 - level behind it,
    # level ahead); view 1's clean step must cost more per unit of s for it to decide.
    gain = (2.0 * level - 1.0) * J[1] / J[0]
    assert 0.0 < gain < 0.8

    res = joint_end([K1, K2], [T1, T2], start, dirs, R, samplers)
    assert res is not None
    # Bound: (1) the joint L1 minimum sits in view 1's blurred step, pulled by view 2's bar:
    # view 1's blurred-step L1 cost rises by c (2 Phi(x / sigma) - 1) per px of offset x, so
    # the pull is at most sigma sqrt(2) erfinv(gain) px of view 1 (J: px per metre), times
    # J2 / J1 in view 2 where that is larger;
    # (2) the grid of s (0.25 px in the faster view: 0.125) and the 4x4 sub-pixel raster
    # (an edge within 1/8 px); (3) the end face's band model (0.957 a for a mean of 0.968 a
    # over the band: 0.011 a < 0.05 px) and orthographic foreshortening (0.5 % of R);
    # (4) bilinear sampling of a blurred step (< 0.05 px). Margin 0.25 px.
    pull = BLUR * np.sqrt(2) * erfinv(gain) * max(1.0, J[1] / J[0])
    bound = pull + 0.125 + 0.125 + 0.05 + 0.005 * max(R) + 0.05 + 0.25
    for k in range(2):
        assert np.linalg.norm(res.tips[k] - tips[k]) < bound, (k, res.tips, tips, bound)
    assert np.linalg.norm(res.point - E) * min(J) < bound
    assert abs(abs(res.direction @ u) - 1) < 1e-9  # the exact end lines give the exact axis


def test_axis_line_recovers_the_3d_axis():
    """Exact tips and end directions: the two planes meet in the true axis (direction to
    rounding, 1e-9 for float64 at pixel coordinates ~1e3), the point on it."""
    for seed in range(4):
        E, u, tips, dirs, R, J = _scene(seed)
        X0, axis, sin = axis_line([K1, K2], [T1, T2], tips, dirs)
        assert axis @ u == pytest.approx(1.0, abs=1e-9)  # oriented out of the tip
        assert np.linalg.norm(X0 - E) < 1e-9


def test_degenerate_axis_keeps_the_per_view_ends():
    """An axis inside an epipolar plane (the plane through both camera centres and the end):
    the two views' planes coincide and do not fix it; nothing is returned."""
    E = np.array([0.0, 0.0, 0.06])
    C1, C2 = (-T[:3, :3].T @ T[:3, 3] for T in (T1, T2))
    u = np.cross(np.cross(C2 - C1, E - C1), C2 - C1)  # in the epipolar plane of E
    u = u / np.linalg.norm(u)
    tips, dirs, R, J = _tips_dirs(E, u)
    assert axis_line([K1, K2], [T1, T2], tips, dirs)[2] < 1e-6
    flat = [lambda p: np.ones(len(p))] * 2
    assert joint_end([K1, K2], [T1, T2], tips, dirs, R, flat) is None
