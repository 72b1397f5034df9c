"""read_image / read_mask / write_png: round trips, bit depths, corrupt files."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

from jaxcr.errors import InputError
from jaxcr.io.images import image_size, read_image, read_mask, write_png


def test_rgb8_round_trip_and_channel_order(tmp_path):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, size=(12, 17, 3), dtype=np.uint8)
    p = write_png(tmp_path / "a.png", img)
    out = read_image(p)
    assert out.dtype == np.float32 and out.shape == (12, 17, 3)
    np.testing.assert_array_equal(np.round(out * 255).astype(np.uint8), img)
    # independent reader: OpenCV gives BGR
    bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(bgr[:, :, ::-1], img)
    assert image_size(p) == (17, 12)


def test_float_write_rounds_and_clips(tmp_path):
    img = np.array([[[0.0, 0.5, 1.0], [-1.0, 2.0, 0.2]]], np.float32)
    out = read_image(write_png(tmp_path / "f.png", img))
    np.testing.assert_allclose(out, [[[0, 128 / 255, 1], [0, 1, 51 / 255]]], atol=1e-6)
    with pytest.raises(ValueError):
        write_png(tmp_path / "nan.png", np.full((2, 2), np.nan))


def test_16bit_and_grey_and_jpeg(tmp_path):
    img16 = (np.arange(20, dtype=np.uint16).reshape(4, 5) * 3000).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "g16.png"), img16)
    out = read_image(tmp_path / "g16.png")
    assert out.shape == (4, 5, 3)
    np.testing.assert_allclose(out[..., 1], img16 / 65535.0, atol=1e-7)
    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[..., 0] = 200  # red
    cv2.imwrite(str(tmp_path / "r.jpg"), rgb[:, :, ::-1])
    out = read_image(tmp_path / "r.jpg")
    assert abs(out[..., 0].mean() - 200 / 255) < 0.02 and out[..., 2].mean() < 0.02


def test_mask_threshold_and_bool_round_trip(tmp_path):
    m = np.zeros((6, 7), bool)
    m[2:4, 1:5] = True
    p = write_png(tmp_path / "m.png", m)
    assert cv2.imread(str(p), cv2.IMREAD_UNCHANGED).max() == 255
    np.testing.assert_array_equal(read_mask(p), m)
    cv2.imwrite(str(tmp_path / "v.png"), np.array([[0, 127, 128, 255]], np.uint8))
    np.testing.assert_array_equal(read_mask(tmp_path / "v.png"), [[False, False, True, True]])
    colour = np.zeros((3, 3, 3), np.uint8)
    colour[0, 0] = (255, 0, 0)
    cv2.imwrite(str(tmp_path / "c.png"), colour)
    with pytest.raises(InputError, match="single-channel"):
        read_mask(tmp_path / "c.png")


def test_atomic_write_leaves_no_temp_and_creates_dirs(tmp_path):
    p = write_png(tmp_path / "x" / "y" / "z.png", np.zeros((3, 3), np.uint8))
    assert p.exists()
    assert sorted(os.listdir(p.parent)) == ["z.png"]


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "empty"),
        (b"\x89PNG\r\n\x1a\n" + b"\x00" * 40, "corrupt"),
        (b"hello, not an image", "corrupt"),
    ],
)
def test_corrupt_files_raise_input_error_naming_file(tmp_path, content, message):
    p = tmp_path / "bad.png"
    p.write_bytes(content)
    for fn in (read_image, read_mask, image_size):
        with pytest.raises(InputError, match=message) as ei:
            fn(p)
        assert ei.value.file == str(p)
        assert "\n" not in str(ei.value)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(InputError, match="not found") as ei:
        read_image(tmp_path / "nope.png")
    assert str(tmp_path / "nope.png") in str(ei.value)
    with pytest.raises(InputError, match="directory"):
        read_image(tmp_path)


def test_truncated_png(tmp_path):
    p = write_png(
        tmp_path / "t.png", np.random.default_rng(1).integers(0, 255, (40, 40, 3), dtype=np.uint8)
    )
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError) as ei:
        read_image(p)
    assert ei.value.file == str(p)
