"""Frames averaged per capture (RgbdSimulator capture_frames, scene field capture_frames,
model-object --capture-frames; decision R3) against independent references: the single-frame
capture drawn by the same generator, the noise-free render and the sensor's declared noise
model (the mean of N independent draws has 1/N of one draw's variance), and the one-line
contract for bad values."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from jaxcr.cli import main
from jaxcr.errors import InputError
from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return generate_task(tmp_path_factory.mktemp("rgbd") / "task1", "1", 0, (160, 120))


def _pose():
    """A camera 0.45 m from the object's axis looking at its middle (OpenCV axes)."""
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.43, 0.1]
    z = np.array([0.0, 0.0, 0.05]) - T[:3, 3]
    z /= np.linalg.norm(z)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    return T


def test_one_frame_is_the_scene_default_and_the_first_draw(scene):
    T = _pose()
    a = RgbdSimulator(scene, seed=4).capture(T)
    b = RgbdSimulator(scene, seed=4, capture_frames=1).capture(T)
    assert RgbdSimulator(scene).capture_frames == 1
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


def test_depth_noise_of_n_frames_is_one_frame_over_sqrt_n(scene):
    # Reference: the noise-free render (sigma = 0, no holes; still quantised to 0.5 mm) and
    # the declared noise model. Per frame the error is sigma_z (~1.2-1.3 mm here) plus the
    # frame's quantisation (uniform, variance q^2 / 12), both averaged over the n frames,
    # plus the reference's own quantisation (not averaged). Bounds: ~1800 object pixels
    # estimate a standard deviation to ~2 %; 10 % margin.
    T = _pose()
    clean = RgbdSimulator(scene, seed=1)
    clean.cfg["depth_noise"] = dict(clean.cfg["depth_noise"], sigma0=0.0, sigma2=0.0, hole_rate=0.0)
    _, d0 = clean.capture(T)
    sd = {}
    for n in (1, 4):
        _, d = RgbdSimulator(scene, seed=2, capture_frames=n).capture(T)
        ok = np.isfinite(d) & np.isfinite(d0)
        assert ok.sum() > 1000
        sd[n] = float(np.std((d - d0)[ok]))
        z = d0[ok]
        sigma = RgbdSimulator(scene).cfg["depth_noise"]
        var_z = np.mean((sigma["sigma0"] + sigma["sigma2"] * (z - sigma["z0"]) ** 2) ** 2)
        model = np.sqrt((var_z + 0.0005**2 / 12) / n + 0.0005**2 / 12)
        assert 0.9 * model < sd[n] < 1.1 * model, (n, sd[n], model)


def test_bad_capture_frames_are_one_line(scene, tmp_path, capsys):
    d = tmp_path / "s"
    shutil.copytree(scene, d)
    meta = json.loads((d / "scene.json").read_text())
    for bad in (0, 65, 2.5, "4"):
        meta["capture_frames"] = bad
        (d / "scene.json").write_text(json.dumps(meta))
        with pytest.raises(InputError) as exc:
            RgbdSimulator(d)
        assert "capture_frames" in str(exc.value) and "scene.json" in str(exc.value)
    with pytest.raises(InputError, match="capture_frames"):
        RgbdSimulator(scene, capture_frames=0)
    for arg in ("0", "65", "x"):
        with pytest.raises(SystemExit) as ex:
            main(["model-object", str(scene), "-o", str(tmp_path / "o"), "--capture-frames", arg])
        assert ex.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) <= 2 and "--capture-frames" in err[-1], err
    assert not (tmp_path / "o").exists()
