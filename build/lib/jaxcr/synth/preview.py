"""README figures from a generated dataset: the first frame, its ground-truth mask and the
nominal projection overlaid (as Watson et al. Fig. 4c: nominal model in white, true robot in
blue).

The nominal projection is the nominal robot (dataset.json's robot at the frame's q) seen by
the nominal camera, drawn by jaxcr.synth's own ray caster (pixel centres). PNGs are written
with a 256-colour palette to stay small.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from jaxcr.synth.generate import robot_shapes, tube_body
from jaxcr.synth.render import robot_mask
from jaxcr.synth.scene import RenderCamera


def _save_small_png(path: Path, rgb: np.ndarray) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).quantize(256, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)


def nominal_mask(dataset_dir: str | Path, frame: int = 0, camera: str | None = None) -> np.ndarray:
    """(H, W) bool: the nominal robot's pixel-centre mask for ``frame`` of a dataset written
    inline by :func:`jaxcr.synth.generate.generate`."""
    root = Path(dataset_dir)
    doc = json.loads((root / "dataset.json").read_text())
    camera = camera or next(iter(doc["cameras"]))
    c = doc["cameras"][camera]
    cam = RenderCamera(
        np.asarray(c["K"], float),
        np.asarray(c["dist"], float),
        np.asarray(c["T_cam_robot"], float),
        int(c["size"][0]),
        int(c["size"][1]),
    )
    # All frames at once: the same batch shape as the generator, so its compilation is reused.
    q = np.asarray([f["q"] for f in doc["frames"]], float)
    shapes = robot_shapes(doc["robot"], q)
    return robot_mask(cam, tube_body(doc["robot"], shapes.p[frame], shapes.rho[frame]))


def write_preview(dataset_dir: str | Path, out_dir: str | Path, frame: int = 0) -> list[Path]:
    """Write ``example_frame.png``, ``example_mask.png`` and ``example_nominal_overlay.png``."""
    root = Path(dataset_dir)
    out = Path(out_dir)
    doc = json.loads((root / "dataset.json").read_text())
    fr = doc["frames"][frame]
    camera = next(iter(doc["cameras"]))
    img = cv2.cvtColor(cv2.imread(str(root / fr["images"][camera])), cv2.COLOR_BGR2RGB)
    full = cv2.imread(str(root / fr["full_masks"][camera]), cv2.IMREAD_GRAYSCALE) > 127
    vis = cv2.imread(str(root / fr["masks"][camera]), cv2.IMREAD_GRAYSCALE) > 127
    nom = nominal_mask(root, frame, camera)
    mask_rgb = np.zeros_like(img)
    mask_rgb[full] = (70, 70, 160)  # occluded robot pixels: dark blue
    mask_rgb[vis] = (255, 255, 255)
    overlay = img.astype(np.float32)
    overlay[full] = 0.35 * overlay[full] + 0.65 * np.array([40, 110, 255])
    overlay[nom] = 0.4 * overlay[nom] + 0.6 * 255.0
    overlay = np.clip(overlay, 0, 255).astype(np.uint8)
    paths = [
        out / "example_frame.png",
        out / "example_mask.png",
        out / "example_nominal_overlay.png",
    ]
    for p, a in zip(paths, (img, mask_rgb, overlay), strict=True):
        _save_small_png(p, a)
    return paths
