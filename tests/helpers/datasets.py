"""Tiny datasets for the dataset/validate tests (built in tmp_path, 96x72 images)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jaxcr.camera import Camera
from jaxcr.io.dataset import DatasetWriter

W, H = 96, 72
ROBOT = {
    "kind": "constant_curvature",
    "sections": [{"length": 0.05, "radius": 0.001}],
    "joints": ["kappa", "phi"],
}


def camera() -> Camera:
    return Camera.look_at([0.0, -0.2, 0.03], [0.0, 0.0, 0.03], [0.0, 0.0, 1.0], 150.0, (W, H))


def make_dataset(root: Path, n_frames: int = 3, seed: int = 0) -> Path:
    """A clean 1-camera dataset with masks and truth; returns its root."""
    rng = np.random.default_rng(seed)
    with DatasetWriter(root, "tiny", ROBOT, {"main": camera()}, meta={"seed": seed}) as w:
        for i in range(n_frames):
            img = rng.random((H, W, 3))
            w.add_frame(
                i,
                [5.0 + i, 0.1 * i],
                {"main": img},
                masks={"main": img[..., 0] > 0.5},
                tags=["test"],
                truth={"centreline": rng.normal(size=(8, 3))},
            )
        w.add_background("main", rng.random((H, W, 3)))
    return Path(root)


def edit_json(root: Path, fn) -> None:
    """Apply ``fn(d)`` to dataset.json in place."""
    p = Path(root) / "dataset.json"
    d = json.loads(p.read_text())
    fn(d)
    p.write_text(json.dumps(d))


def spoil_joint_values(root: Path, bad) -> None:
    """Give frames ``bad`` (ids) a joint value of 1e39 in dataset.json: the writer refuses such
    values, the loader accepts them, and ``jaxcr segment`` fails those frames."""

    def spoil(d):
        for f in d["frames"]:
            if int(f["id"]) in bad:
                f["q"][0] = 1e39

    edit_json(root, spoil)
