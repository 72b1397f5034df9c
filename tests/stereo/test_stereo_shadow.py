"""Shadow removal (jaxcr.stereo.shadow.shadow_cut, report sec. 5.3) on constructed paths
with a known corner, and in the pipeline on a rendered pair whose background-plate
segmentation includes the tube's shadow."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from jaxcr.stereo.shadow import shadow_cut, slope_angle_segments


def _polyline(points: list[tuple[float, float]], step: float = 1.0) -> np.ndarray:
    """Points every ``step`` along the polyline through ``points`` (first vertex first)."""
    out = []
    for a, b in zip(points[:-1], points[1:], strict=True):
        a, b = np.asarray(a, float), np.asarray(b, float)
        n = int(round(np.linalg.norm(b - a) / step))
        out.append(a + (b - a) * np.arange(n)[:, None] / n)
    out.append(np.asarray(points[-1], float)[None])
    return np.concatenate(out)


@pytest.mark.parametrize("shadow_angle_deg", [60.0, 120.0, 150.0])
def test_cut_at_the_shadow_corner(shadow_angle_deg):
    # Shadow 40 px along the floor ending at the base (0, 0), then the tube rising 80 px
    # (image up = -v); the path turns by 180 deg - shadow_angle at the base (>= 30 deg
    # here, above the 20 deg tolerance). The base seed lies 9 px up the tube, as the
    # Hough seed does.
    a = np.radians(shadow_angle_deg)
    far = (40 * np.sin(a), -40 * np.cos(a))  # direction at angle a from the tube's
    path = _polyline([far, (0.0, 0.0), (0.0, -80.0)])
    corner = 40
    cut = shadow_cut(path, np.array([0.0, -9.0]), tolerance_deg=20.0, j=3)
    # The corner, up to the look-ahead (the slope over j points straddles it).
    assert corner - 3 <= cut <= corner + 3, cut
    # The report's slope-angle segments do start a segment there.
    starts = [int(s[0]) for s in slope_angle_segments(path, 20.0, 3)]
    assert cut in starts


def test_no_shadow_no_cut():
    # A tube curving away from the base: the base segment is the first one.
    t = np.linspace(0, np.radians(100), 120)
    path = np.stack([60 * (1 - np.cos(t)), -60 * np.sin(t)], 1)
    assert shadow_cut(path, path[9], 20.0) == 0
    # A tip curled back past the base, later in the path, does not move the base index.
    t2 = np.linspace(0, np.radians(330), 300)
    curl = np.stack([40 * (1 - np.cos(t2)), -40 * np.sin(t2)], 1)
    assert np.min(np.linalg.norm(curl[200:] - curl[9], axis=1)) < 30
    assert shadow_cut(curl, curl[9], 20.0) == 0
    # Too short to segment.
    assert shadow_cut(path[:5], path[0], 20.0) == 0


def test_tolerance_larger_than_the_turn_keeps_the_shadow():
    # A shadow only 15 deg off the tube's direction is not a defect at 20 deg tolerance.
    path = _polyline(
        [(40 * np.sin(np.radians(165)), 40 * np.cos(np.radians(15))), (0, 0), (0, -80)]
    )
    assert shadow_cut(path, np.array([0.0, -9.0]), tolerance_deg=20.0) == 0
    assert shadow_cut(path, np.array([0.0, -9.0]), tolerance_deg=10.0) > 30


@pytest.fixture(scope="module")
def plate_pair(tmp_path_factory):
    from jaxcr.cli.stereo import _read_rgb, load_stereo_dataset
    from jaxcr.synth.stereo_ctr import generate_stereo_set

    d = generate_stereo_set(
        tmp_path_factory.mktemp("shadow") / "set", n_frames=1, seed=3, size=(480, 360),
        kinds=("general",),
    )  # fmt: skip
    ds = load_stereo_dataset(d)
    fr = ds["frames"][0]
    ims = [_read_rgb(ds["root"] / fr["images"][n]) for n in ds["names"]]
    truth = dict(np.load(ds["root"] / fr["truth"]))
    return ds, ims, truth


def test_pipeline_removes_the_plate_shadow(plate_pair):
    """With the background-plate difference the shadow is segmented with the tube; the
    shadow cut makes the reconstructed backbone start at the robot's base again."""
    from jaxcr.stereo.evaluate import evaluate_frame
    from jaxcr.stereo.pipeline import reconstruct_pair

    ds, ims, truth = plate_pair
    out = {}
    for mode, tol in (("chroma", 20.0), ("plate", None), ("plate", 20.0)):
        cfg = dataclasses.replace(
            ds["config"], segmentation=mode, joint_fit=False, shadow_tolerance_deg=tol
        )
        r = reconstruct_pair(ims[0], ims[1], ds["cam1"], ds["cam2"], cfg, ds["plates"])
        out[mode, tol] = (r, evaluate_frame(r, truth))
    start = {k: 1e3 * np.linalg.norm(r["p"][0] - truth["p"][0]) for k, (r, _) in out.items()}
    # Without the cut the plate backbone starts on the floor along the shadow; with it, it
    # starts where the chroma key (no shadow in the mask) starts, within 1 mm.
    assert start["plate", None] > 5.0, start
    assert abs(start["plate", 20.0] - start["chroma", 20.0]) < 1.0, start
    rms = {k: e["backbone_rms_mm"] for k, (_, e) in out.items()}
    assert rms["plate", 20.0] < 0.5 < rms["plate", None], rms
