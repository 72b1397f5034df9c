"""The plate foreground at any resolution (issue 16 item 2): the tracer's lengths are set for
a tube about ``tube_width_px`` wide, and a view where the tube is ``k`` times wider is traced
reduced ``k`` times with its tip refined at full resolution. References: a tube drawn with
OpenCV (``cv2.fillPoly``, 8x8 supersampled) at 1x and 2x the size, its end point known;
``cv2.resize(INTER_AREA)`` for the reduction; drawn bands for the width."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from jaxcr.segmentation.foreground import (
    PlateForegroundConfig,
    downsample,
    measure_tube_width,
    plate_foreground,
)

GREEN = np.array([0.16, 0.50, 0.20])
TUBE = np.array([0.10, 0.15, 0.11])  # the real_like preset's dark green-tinted outer tube


def _tube_scene(k: int, width: float = 6.0, seed: int = 0):
    """An 80x60 scene drawn at ``k`` times the size: a dark tube ``width`` px wide (at 1x)
    entering at the left border and curving up to a flat end, over smoothly shaded green
    cloth, with noise (sigma 0.01). Geometry is defined in 1x pixels and mapped to the
    k-times image by ``u_k = k u + (k - 1)/2`` (pixel centres; the same area). Returns
    frame, plate, entry (u, v), the end point (u, v) in the k-times image."""
    h, w, ss = 60 * k, 80 * k, 8
    t = np.linspace(0.0, 1.0, 400)[:, None]
    c = np.hstack([-4 + 62 * t, 44 - 28 * t**2])
    d = np.gradient(c, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    n = np.stack([-d[:, 1], d[:, 0]], 1)
    c = k * c + (k - 1) / 2
    half = k * width / 2
    poly = np.vstack([c + half * n, (c - half * n)[::-1]])
    canvas = np.zeros((h * ss, w * ss), np.uint8)
    q = np.round(((poly + 0.5) * ss - 0.5) * 16).astype(np.int32)  # 4 fractional bits
    cv2.fillPoly(canvas, [q], 255, lineType=cv2.LINE_8, shift=4)
    cover = canvas.reshape(h, ss, w, ss).mean((1, 3))[..., None] / 255.0
    yy, xx = (np.mgrid[0:h, 0:w] - (k - 1) / 2) / k
    plate = GREEN * (0.9 + 0.1 * np.sin(xx / 9.0) * np.cos(yy / 7.0))[..., None]
    frame = plate * (1 - cover) + TUBE * cover
    rng = np.random.default_rng(seed)
    frame = np.clip(frame + rng.normal(0, 0.01, frame.shape), 0, 1)
    plate = np.clip(plate + rng.normal(0, 0.01, plate.shape), 0, 1)
    entry = np.array([0.0, k * 44 + (k - 1) / 2])
    return frame, plate, entry, c[-1]


@pytest.fixture(scope="module")
def traces():
    cfg = PlateForegroundConfig(align=False)
    out = {}
    for k in (1, 2):
        frame, plate, entry, end = _tube_scene(k)
        out[k] = (plate_foreground(frame, plate, entry, (1.0, 0.0), cfg=cfg), end)
    return out


def test_reduction_factor_follows_the_tube_width(traces):
    # Drawn widths 6 and 12 px, measured within 1 px (test_measure_tube_width_on_drawn_bands);
    # factor round(w / 7): 1 (5-7 px) and 2 (11-13 px).
    assert traces[1][0].scale == 1 and traces[2][0].scale == 2
    for k, (tr, _) in traces.items():
        assert abs(tr.measured_width_px - 6.0 * k) <= 1.0


@pytest.mark.parametrize("k", [1, 2])
def test_same_tip_at_every_size(traces, k):
    """The tip is the drawn end at every size, within a tolerance that grows with the
    reduction factor s the view was traced at: the path is found at 1/s resolution,
    where nearest-pixel sampling and re-centring leave the end's lateral position within
    0.5 + 0.71 (pixel half-diagonal) reduced pixels, i.e. 1.25 s full pixels; the refined
    position along the tube adds 0.3 px (test_refine_tip_on_drawn_ends) and the noise and
    blur of the score 0.2 px."""
    tr, end = traces[k]
    tol = 1.25 * tr.scale + 0.5
    assert np.linalg.norm(tr.tip - end) < tol, (tr.tip, end)
    # The same tip in 1x pixels at every size (both tolerances added).
    tip1 = (tr.tip - (k - 1) / 2) / k
    ref1 = traces[1][0].tip
    assert np.linalg.norm(tip1 - ref1) < (tol / k + 1.75)
    # The backbone is in full-resolution pixels and starts at the entry.
    assert tr.backbone[0][0] < 2.0 * k and tr.mask.shape == (60 * k, 80 * k)


def test_fixed_scale_flag_is_honoured():
    frame, plate, entry, end = _tube_scene(2)
    tr = plate_foreground(frame, plate, entry, (1.0, 0.0),
                          cfg=PlateForegroundConfig(align=False, scale=1))  # fmt: skip
    assert tr.scale == 1


@pytest.mark.parametrize("k", [2, 3])
def test_downsample_matches_cv2_inter_area(k):
    rng = np.random.default_rng(k)
    img = rng.uniform(0, 1, (37, 50, 3))
    ref = cv2.resize(img[: 37 // k * k, : 50 // k * k], (50 // k, 37 // k),
                     interpolation=cv2.INTER_AREA)  # fmt: skip
    # Both are block means of float64 values: rounding only.
    np.testing.assert_allclose(downsample(img, k), ref, atol=1e-12)
    assert np.array_equal(downsample(img, 1), img)


@pytest.mark.parametrize("width, angle", [(7, 0.0), (8, 0.0), (14, 30.0), (5, 63.0)])
def test_measure_tube_width_on_drawn_bands(width, angle):
    """A band of pixels whose centres lie within ``width / 2`` of a line: across it (axis
    aligned) exactly ``width`` pixels; the estimate ``2 d - 1/2`` on the distance ridge is
    within 1/2 px of it (docstring), plus the staircase of a tilted band's edge on the
    Euclidean distance (< 1/2 px)."""
    h, w = 80, 120
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    th = np.radians(angle)
    n = np.array([-np.sin(th), np.cos(th)])
    dist = (xx - 10) * n[0] + (yy - 40) * n[1]
    along = (xx - 10) * np.cos(th) + (yy - 40) * np.sin(th)
    half = width / 2 - 1e-9 if width % 2 == 0 else width / 2
    band = (np.abs(dist + (0.5 if width % 2 == 0 and angle == 0 else 0.0)) < half) & (along > 0)
    band[:, :5] = False
    band[5:9, 90:110] = True  # a separate speck: not the component at the entry
    got = measure_tube_width(band, (10.0, 40.0))
    assert abs(got - width) <= 1.0, got
