"""Shared helpers of the eigen-feature experiments: the colour model of the training set's
first frame, cached stereo contours of each dataset, error measures."""

from __future__ import annotations

import json
import platform
import subprocess
import time
from pathlib import Path

import jax
import numpy as np

from jaxcr.eigen.colour import ColourModel, fit_colour_model
from jaxcr.eigen.descriptor import Contours
from jaxcr.eigen.pipeline import StereoContours, dataset_contours
from jaxcr.io.dataset import load_dataset

RESULTS = Path(__file__).resolve().parent.parent / "results" / "eigen"


def colour_model(train_root: Path, seed: int = 0) -> ColourModel:
    """k = 5 clusters on the first training frame (left camera), marker = nearest to lime."""
    ds = load_dataset(train_root)
    return fit_colour_model(ds.frames[0].load_image("left"), k=5, seed=seed)


def _save(sc: StereoContours, path: Path) -> None:
    d = {"ids": np.array(sc.ids)}
    for v, c in zip(("l", "r"), sc.views, strict=True):
        lens = np.array([len(p) for p in c.points])
        d[f"{v}_pts"] = np.concatenate(c.points) if len(c.points) else np.zeros((0, 2), np.int64)
        d[f"{v}_len"] = lens
        d[f"{v}_centres"] = c.centres
        d[f"{v}_ok"] = c.ok
        d[f"{v}_npx"] = c.marker_pixels
    np.savez(path, **d)


def _load(path: Path) -> StereoContours:
    z = np.load(path, allow_pickle=False)
    views = []
    for v in ("l", "r"):
        off = np.concatenate([[0], np.cumsum(z[f"{v}_len"])])
        # Read the array once: every z[key] access decompresses a new copy, and each
        # slice would keep its own copy alive.
        allpts = z[f"{v}_pts"]
        pts = [allpts[off[i] : off[i + 1]] for i in range(len(off) - 1)]
        views.append(Contours(pts, z[f"{v}_centres"], z[f"{v}_ok"], z[f"{v}_npx"]))
    return StereoContours([str(i) for i in z["ids"]], tuple(views))  # type: ignore[arg-type]


def contours(
    root: Path, colour: ColourModel, cache_dir: Path
) -> tuple[StereoContours, np.ndarray, np.ndarray, float]:
    """Stereo contours, psi (n, 2), tips (n, 3) of a dataset; cached in ``cache_dir``.
    Returns also the extraction time per frame (s, 0 if cached)."""
    ds = load_dataset(root)
    psi = np.array([f.q for f in ds.frames])
    tips = np.array([f.truth["tip"] for f in ds.frames], np.float64)
    cache = cache_dir / f"contours_{root.name}.npz"
    if cache.exists():
        return _load(cache), psi, tips, 0.0
    t0 = time.perf_counter()
    sc = dataset_contours(ds, colour)
    dt = (time.perf_counter() - t0) / len(ds)
    cache_dir.mkdir(parents=True, exist_ok=True)
    _save(sc, cache)
    return sc, psi, tips, dt


def angle_errors(est: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Median absolute errors (deg) of delta, theta_L and combined.

    ``combined`` = median of all |errors| of both angles pooled (our reading of the paper's
    "both angles combined together"); ``combined_mean`` = median over frames of the mean of
    the two; ``combined_norm`` = median of sqrt(e_delta^2 + e_theta^2)."""
    e = np.rad2deg(np.abs(est - truth))
    return {
        "delta": float(np.median(e[:, 1])),
        "theta_L": float(np.median(e[:, 0])),
        "combined": float(np.median(e.ravel())),
        "combined_mean": float(np.median(e.mean(1))),
        "combined_norm": float(np.median(np.hypot(e[:, 0], e[:, 1]))),
        "p90_combined": float(np.percentile(e.ravel(), 90)),
        "n": int(len(e)),
    }


def metadata() -> dict:
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=RESULTS.parent
    ).stdout.strip()
    return {
        "commit": commit,
        "jax": jax.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "machine": f"{platform.machine()} {platform.processor()}".strip(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }


def write_json(name: str, obj) -> Path:
    RESULTS.mkdir(exist_ok=True)
    p = RESULTS / name
    p.write_text(json.dumps(obj, indent=1, default=float) + "\n")
    return p
