"""Overlay panels on large frames: the tiles are cropped to the robot (the same box for all),
tile (a) carries a full-frame thumbnail with the box, output size is bounded, and a robot that
fills a small frame leaves the panel as the uncropped one."""

from __future__ import annotations

import numpy as np
import pytest

from jaxcr.io.overlay import (
    MIN_CROP,
    NO_CROP_FRACTION,
    YELLOW,
    fig4_panel,
    robot_crop,
)

W, H = 320, 240


def _blob(rng, w=W, h=H, size=12):
    """A thin random polyline-like robot mask of about ``size`` px extent."""
    m = np.zeros((h, w), bool)
    x, y = rng.integers(0, w), rng.integers(0, h)
    for _ in range(size):
        x = int(np.clip(x + rng.integers(-1, 2), 0, w - 1))
        y = int(np.clip(y + rng.integers(0, 2), 0, h - 1))
        m[max(0, y - 1) : y + 2, max(0, x - 1) : x + 2] = True
    return m


@pytest.mark.parametrize("seed", range(20))
def test_crop_contains_every_robot_pixel(seed):
    rng = np.random.default_rng(seed)
    nominal = _blob(rng)
    refined = np.roll(nominal, tuple(rng.integers(-4, 5, size=2)), axis=(0, 1))  # refined nearby
    box = robot_crop([nominal, refined, None])
    # a blob of <= 15 px moved <= 4 px: the box is MIN_CROP = 96 px (+ margins), under 60 % of 240
    assert box is not None
    x0, y0, x1, y1 = box
    assert 0 <= x0 < x1 <= W and 0 <= y0 < y1 <= H
    for m in (nominal, refined):
        ys, xs = np.nonzero(m)
        assert xs.min() >= x0 and xs.max() < x1 and ys.min() >= y0 and ys.max() < y1
    assert x1 - x0 >= MIN_CROP and y1 - y0 >= MIN_CROP


def test_crop_tiles_equal_the_uncropped_panel_cut_to_the_box():
    rng = np.random.default_rng(100)
    img = rng.random((H, W, 3))
    fg = rng.random((H, W)) > 0.3
    nominal = np.zeros((H, W), bool)
    nominal[200:230, 300:305] = True  # near the bottom-right corner
    refined = np.zeros((H, W), bool)
    refined[203:236, 301:306] = True
    truth = refined.copy()
    box = robot_crop([nominal, refined, truth])
    x0, y0, x1, y1 = box
    full = fig4_panel(img, fg, nominal, refined, truth, labels=False, crop=False)
    cut = fig4_panel(img, fg, nominal, refined, truth, labels=False)
    h, w = y1 - y0, x1 - x0
    assert cut.shape == (2 * h, 2 * w, 3)
    # tiles (b), (c), (d): exactly the uncropped tiles cut to the box
    for r, c in ((0, 1), (1, 0), (1, 1)):
        ref = full[r * H : (r + 1) * H, c * W : (c + 1) * W][y0:y1, x0:x1]
        np.testing.assert_array_equal(cut[r * h : (r + 1) * h, c * w : (c + 1) * w], ref)
    # tile (a): the raw crop except the thumbnail, which shows the crop box in yellow
    a = cut[:h, :w]
    differs = np.any(a != full[:H, :W][y0:y1, x0:x1], axis=-1)
    ys, xs = np.nonzero(differs)
    assert differs.sum() > 0
    # thumbnail in the corner away from the robot (robot right of centre and low: top-left)
    assert xs.max() < w / 2 and ys.min() == 0
    assert np.any(np.all(a[differs] == np.array(YELLOW, np.uint8), axis=-1))


def test_robot_filling_a_small_frame_is_not_cropped():
    rng = np.random.default_rng(7)
    img = rng.random((H, W, 3))
    fg = np.ones((H, W), bool)
    nominal = np.zeros((H, W), bool)
    # a diagonal robot spanning more than NO_CROP_FRACTION of both sides
    n = int(0.8 * min(W, H))
    idx = np.arange(n)
    nominal[idx + 10, (idx * W / H).astype(int) + 10] = True
    assert (idx * W / H).max() > NO_CROP_FRACTION * W
    assert robot_crop([nominal, nominal, None]) is None
    a = fig4_panel(img, fg, nominal, nominal)
    b = fig4_panel(img, fg, nominal, nominal, crop=False)
    np.testing.assert_array_equal(a, b)
    assert a.shape == (2 * H, 2 * W, 3)


def test_empty_projection_shows_the_full_frame():
    img = np.zeros((H, W, 3))
    empty = np.zeros((H, W), bool)
    assert robot_crop([empty, empty, None]) is None
    assert fig4_panel(img, empty, empty, empty).shape == (2 * H, 2 * W, 3)


def test_output_size_is_bounded():
    rng = np.random.default_rng(3)
    img = rng.random((H, W, 3))
    m = np.ones((H, W), bool)  # fills the frame: no crop, so only the size bound acts
    out = fig4_panel(img, m, m, m, max_tile=100)
    assert max(out.shape[:2]) <= 200
    # aspect ratio kept to within the rounding of one pixel
    assert abs(out.shape[1] / out.shape[0] - W / H) < 2 / 75
