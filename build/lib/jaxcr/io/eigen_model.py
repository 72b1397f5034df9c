"""Model files of the eigen-feature estimator: a ``.npz`` with a ``format`` field
(``"jaxcr.manifold/2"``), the training configuration as JSON (``config``) and the arrays
(colour centres and marker index, PCA mean/components/variance, resampled manifold, and
``view_centres`` (2, 2), the fixed histogram reference points, NaN when the model uses
per-frame region centroids). Version 1 files (no ``view_centres``; always per-frame
centroids) are still read, as ``centre = "region"`` models.

Self-describing: ``format``, ``config`` (JSON, includes the parameter names and units) and
``meta`` (JSON: jaxcr version, training set, timings) travel with the arrays. Loading checks
the format, every field's presence, shape and finiteness; a corrupt or incompatible file
raises :class:`~jaxcr.errors.InputError` naming the file and field.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import asdict
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxcr.eigen.colour import ColourModel
from jaxcr.eigen.manifold import Manifold
from jaxcr.eigen.model import PARAM_KINDS, EigenModel, TrainConfig
from jaxcr.eigen.pca import PCA
from jaxcr.errors import InputError

FORMAT = "jaxcr.manifold/2"
#: Older formats this version reads.
FORMAT_V1 = "jaxcr.manifold/1"
_ARRAYS = (
    "colour_centres",
    "colour_marker",
    "pca_mean",
    "pca_components",
    "pca_variance",
    "manifold_psi",
    "manifold_features",
)


def save_model(
    model: EigenModel, path: str | os.PathLike, meta: dict[str, Any] | None = None
) -> Path:
    """Write ``model`` to ``path`` (.npz, atomically: temp file then rename)."""
    from jaxcr import __version__

    path = Path(path)
    cfg = asdict(model.config)
    cfg["cameras"] = list(cfg["cameras"])
    cfg["param_names"] = list(PARAM_KINDS[model.config.params])
    cfg["param_units"] = "rad" if model.config.params == "angles" else "m"
    m = {"jaxcr_version": __version__, "n_train": model.n_train, "timings": model.timings}
    m.update(meta or {})
    arrays = {
        "format": np.array(FORMAT),
        "config": np.array(json.dumps(cfg)),
        "meta": np.array(json.dumps(m, default=str)),
        "colour_centres": np.asarray(model.colour.centres, np.float32),
        "colour_marker": np.asarray(model.colour.marker, np.int32),
        "pca_mean": np.asarray(model.pca.mean, np.float32),
        "pca_components": np.asarray(model.pca.components, np.float32),
        "pca_variance": np.asarray(model.pca.variance, np.float32),
        "manifold_psi": np.asarray(model.manifold.psi, np.float32),
        "manifold_features": np.asarray(model.manifold.features, np.float32),
        "view_centres": (
            np.full((2, 2), np.nan)
            if model.view_centres is None
            else np.asarray(model.view_centres, np.float64)
        ),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)
    return path


def load_model(path: str | os.PathLike) -> EigenModel:
    """Read a model written by :func:`save_model`; InputError if corrupt or incompatible."""
    f = str(path)
    if Path(path).is_dir():
        raise InputError("is a folder, expected a model file (jaxcr manifold train -o M.npz)",
                         file=f)  # fmt: skip
    if not Path(path).is_file():
        raise InputError("model file not found", file=f)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise InputError(f"not a readable .npz model file ({type(err).__name__})", file=f) from None
    if "format" not in data:
        raise InputError("not a jaxcr manifold model (no 'format' field)", file=f, field="format")
    fmt = str(data["format"])
    if fmt not in (FORMAT, FORMAT_V1):
        raise InputError(
            f"unsupported model format {fmt!r} (this jaxcr reads {FORMAT!r})",
            file=f,
            field="format",
        )
    for k in ("config", *_ARRAYS):
        if k not in data:
            raise InputError("missing field", file=f, field=k)
    try:
        cfg = json.loads(str(data["config"]))
        meta = json.loads(str(data.get("meta", "{}")))
    except json.JSONDecodeError:
        raise InputError("config is not valid JSON", file=f, field="config") from None
    known = set(TrainConfig.__dataclass_fields__)
    if fmt == FORMAT_V1:
        cfg["centre"] = "region"  # version 1 had only per-frame centroids
    try:
        config = TrainConfig(**{k: v for k, v in cfg.items() if k in known})
        config.cameras = tuple(config.cameras)  # type: ignore[assignment]
        config.check()
    except (TypeError, ValueError, InputError) as err:
        raise InputError(f"bad config: {err}", file=f, field="config") from None
    a = {k: data[k] for k in _ARRAYS}
    for k, v in a.items():
        if v.dtype.kind not in "fi" or not np.all(np.isfinite(v)):
            raise InputError("array is not finite numeric data", file=f, field=k)
    m = 2 * config.n_bins
    d = len(PARAM_KINDS[config.params])
    kk = a["pca_components"].shape[1] if a["pca_components"].ndim == 2 else -1
    checks = [
        ("colour_centres", a["colour_centres"].ndim == 2 and a["colour_centres"].shape[1] == 2),
        (
            "colour_marker",
            a["colour_marker"].ndim == 0
            and 0 <= int(a["colour_marker"]) < len(a["colour_centres"]),
        ),
        ("pca_mean", a["pca_mean"].shape == (m,)),
        ("pca_components", a["pca_components"].ndim == 2 and a["pca_components"].shape[0] == m),
        ("pca_variance", a["pca_variance"].shape == (kk,)),
        ("manifold_psi", a["manifold_psi"].ndim == 2 and a["manifold_psi"].shape[1] == d),
        ("manifold_features", a["manifold_features"].shape == (len(a["manifold_psi"]), kk)),
    ]
    for k, ok in checks:
        if not ok:
            raise InputError(
                f"shape {a[k].shape} does not fit the config (n_bins={config.n_bins}, params={config.params})",
                file=f,
                field=k,
            )
    centres = None
    if config.centre == "fixed":
        if "view_centres" not in data:
            raise InputError("missing field", file=f, field="view_centres")
        centres = np.asarray(data["view_centres"], np.float64)
        if centres.shape != (2, 2) or not np.all(np.isfinite(centres)):
            raise InputError(
                "view centres must be finite (2, 2) for centre 'fixed'",
                file=f,
                field="view_centres",
            )
    if len(a["manifold_psi"]) < config.b:
        raise InputError(
            f"manifold has fewer points than b={config.b}", file=f, field="manifold_psi"
        )
    return EigenModel(
        config=config,
        colour=ColourModel(
            jnp.asarray(a["colour_centres"]), jnp.asarray(a["colour_marker"], jnp.int32)
        ),
        pca=PCA(
            jnp.asarray(a["pca_mean"]),
            jnp.asarray(a["pca_components"]),
            jnp.asarray(a["pca_variance"]),
        ),
        manifold=Manifold(jnp.asarray(a["manifold_psi"]), jnp.asarray(a["manifold_features"])),
        n_train=int(meta.get("n_train", 0)),
        timings=dict(meta.get("timings", {})),
        view_centres=centres,
    )
