"""IREP scene preset (exact disc ray casting, dataset contract) and the ``jaxcr manifold``
CLI: train -> query round trip, failed frames reported, bad inputs exit 2."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from jaxcr.cli import main
from jaxcr.io.dataset import load_dataset, validate_dataset
from jaxcr.io.images import write_png
from jaxcr.synth.irep import DISC_DIAMETER, DISC_HEIGHT, generate_irep, ray_disc


def test_ray_disc_against_dense_marching():
    rng = np.random.default_rng(0)
    centre = np.array([0.01, -0.005, 0.2])
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    d = np.concatenate([rng.normal(size=(400, 2)) * 0.03, np.ones((400, 1))], 1)
    d[:, :2] += centre[:2] / centre[2]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, n = ray_disc(d, centre, axis, DISC_HEIGHT / 2, DISC_DIAMETER / 2)
    # Reference: march along each ray in 2 um steps, first sample inside the solid.
    ts = np.arange(0.15, 0.25, 2e-6)
    for i in range(0, 400, 7):
        p = ts[:, None] * d[i] - centre
        ax = p @ axis
        rad = np.linalg.norm(p - ax[:, None] * axis, axis=1)
        inside = (np.abs(ax) <= DISC_HEIGHT / 2) & (rad <= DISC_DIAMETER / 2)
        if inside.any():
            assert abs(ts[np.argmax(inside)] - t[i]) < 5e-6
            # Outward unit normal: the point just before the hit is on its positive side.
            assert np.isclose(np.linalg.norm(n[i]), 1.0) and n[i] @ d[i] < 0
        else:
            assert not np.isfinite(t[i])
    assert np.isfinite(t).sum() > 50


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("irep")
    generate_irep(root / "train", 14, "train", 0, (160, 120), progress=False)
    generate_irep(root / "test", 4, "test", 0, (160, 120), occluded=True, progress=False)
    return root


def test_irep_dataset_contract(data):
    assert validate_dataset(data / "train") == []
    ds = load_dataset(data / "test")
    assert ds.camera_names == ["left", "right"] and len(ds) == 4
    f = ds.frames[0]
    q = np.asarray(f.q)
    assert np.pi / 2 - np.deg2rad(85) - 1e-6 <= q[0] <= np.pi / 2 - np.deg2rad(15) + 1e-6
    assert 0 <= q[1] <= np.pi
    tip = np.asarray(f.truth["tip"])
    cl = f.load_truth("centreline")
    np.testing.assert_allclose(cl[-1], tip, atol=1e-7)
    # Arc length of the centreline is the segment length.
    assert abs(np.linalg.norm(np.diff(cl, axis=0), axis=1).sum() - 0.061) < 1e-4
    assert f.meta["marker_pixels"]["left"] > 100 and "occluded" in f.tags
    # Deterministic for given arguments (the stratified sampling depends on the frame count).
    d2 = data / "again"
    generate_irep(d2, 4, "test", 0, (160, 120), occluded=True, progress=False)
    a = load_dataset(d2).frames[1]
    np.testing.assert_array_equal(a.load_image("left"), ds.frames[1].load_image("left"))


def test_cli_train_query_round_trip(data, tmp_path, capsys):
    model = tmp_path / "m.npz"
    assert (
        main(
            [
                "manifold",
                "train",
                str(data / "train"),
                "-o",
                str(model),
                "--bins",
                "24",
                "--step",
                "0.05",
                "--variance",
                "0.95",
            ]
        )
        == 0
    )
    out = tmp_path / "q"
    code = main(["manifold", "query", str(model), str(data / "train"), "-o", str(out)])
    assert code == 0
    rows = [json.loads(x) for x in (out / "estimates.jsonl").read_text().splitlines()]
    assert len(rows) == 14 and all(r["ok"] for r in rows)
    summary = json.loads((out / "summary.json").read_text())
    # Training frames are on the (smoothed) manifold: small errors.
    assert summary["median_error_deg"]["combined"] < 3.0
    header = (out / "estimates.csv").read_text().splitlines()[0]
    assert header == "id,ok,theta_L,delta,err_theta_L_deg,err_delta_deg"

    # A frame without markers (grey image) is reported failed, not estimated; exit code 1.
    bad = tmp_path / "bad"
    shutil.copytree(data / "test", bad)
    write_png(bad / "images" / "left" / "000002.png", np.full((120, 160, 3), 0.5, np.float32))
    out2 = tmp_path / "q2"
    assert main(["manifold", "query", str(model), str(bad), "-o", str(out2)]) == 1
    rows = {
        r["id"]: r for r in map(json.loads, (out2 / "estimates.jsonl").read_text().splitlines())
    }
    assert rows["000002"]["ok"] is False and "marker pixels" in rows["000002"]["error"]
    assert "theta_L" not in rows["000002"]
    assert sum(r["ok"] for r in rows.values()) == 3

    # The default model stores its fixed histogram centres: the mean region centroid of
    # the training frames per view (reference: the centroids of the generator's marker
    # masks are not the same pixels, so only the image box and stereo disparity are checked).
    from jaxcr.io.eigen_model import load_model

    m = load_model(model)
    assert m.config.centre == "fixed" and m.view_centres.shape == (2, 2)
    assert np.all((m.view_centres > 0) & (m.view_centres < [160, 120]))
    assert m.view_centres[0, 0] > m.view_centres[1, 0]  # left camera sees it further right
    # The paper's per-frame centroid as an option.
    model_r = tmp_path / "mr.npz"
    args = ["manifold", "train", str(data / "train"), "-o", str(model_r), "--bins", "24"]
    assert main([*args, "--step", "0.05", "--variance", "0.95", "--centre", "region"]) == 0
    assert load_model(model_r).config.centre == "region"
    out3 = tmp_path / "q3"
    assert main(["manifold", "query", str(model_r), str(data / "train"), "-o", str(out3)]) == 0
    s3 = json.loads((out3 / "summary.json").read_text())
    assert s3["median_error_deg"]["combined"] < 3.0


def test_cli_bad_inputs(data, tmp_path, capsys):
    assert (
        main(
            [
                "manifold",
                "query",
                str(tmp_path / "missing.npz"),
                str(data / "test"),
                "-o",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    assert "model file not found" in capsys.readouterr().err
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"\x00" * 64)
    assert (
        main(["manifold", "query", str(junk), str(data / "test"), "-o", str(tmp_path / "o")]) == 2
    )
    assert "npz" in capsys.readouterr().err
    assert (
        main(
            [
                "manifold",
                "train",
                str(data / "train"),
                "-o",
                str(tmp_path / "x.npz"),
                "--cameras",
                "left",
            ]
        )
        == 2
    )
    assert (
        main(
            [
                "manifold",
                "train",
                str(data / "train"),
                "-o",
                str(tmp_path / "x.npz"),
                "--variance",
                "1.5",
            ]
        )
        == 2
    )
    assert (
        main(
            [
                "manifold",
                "train",
                str(data / "train"),
                "-o",
                str(tmp_path / "x.npz"),
                "--cameras",
                "left,top",
            ]
        )
        == 2
    )
    assert "no camera 'top'" in capsys.readouterr().err
    assert main(["manifold", "synth", "-o", str(data / "train"), "--frames", "2"]) == 2
