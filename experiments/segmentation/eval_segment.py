"""Evaluate kinematic-prior segmentation (jaxcr.segmentation.refine) on jaxcr datasets.

For each dataset: forward kinematics of every frame, colour-mask background subtraction,
one batched refinement, then IoU (Watson et al. eq. 8) of the nominal and refined full
projections against the full masks, adjusted IoU against the visible masks (occluded pixels
excluded, for endoscopic views), and tip / mean centreline errors (mm) against the truth.

    python experiments/segmentation/eval_segment.py DATASET_DIR [DATASET_DIR ...] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.io.dataset import load_dataset
from jaxcr.io.images import read_image, read_mask
from jaxcr.segmentation.background import colour_mask
from jaxcr.segmentation.metrics import adjusted_iou, iou, mean_centreline_error, tip_error
from jaxcr.segmentation.refine import RefineConfig, refine_batch


def colour_masks(imgs, names):
    """(backgrounds, images) per camera, as tuples in ``names``' order: the colour-key
    background model of every frame of each camera's stack (batch, H, W, 3)."""
    bgs, ims = [], []
    for n in names:
        b, i = jax.jit(jax.vmap(colour_mask))(jnp.asarray(imgs[n], jnp.float32))
        bgs.append(b)
        ims.append(i)
    return tuple(bgs), tuple(ims)


def load_frames(path, max_frames=None):
    ds = load_dataset(path)
    names = list(ds.cameras)
    frames = [f for f in ds.frames if f.id not in ds.bad_frames][:max_frames]
    q = jnp.asarray(np.stack([f.q for f in frames]), jnp.float32)
    fk = jax.jit(jax.vmap(ds.robot.forward))(q)
    imgs = {n: np.stack([read_image(f.images[n]) for f in frames]) for n in names}
    full = {n: np.stack([read_mask(f.full_masks[n]) for f in frames]) for n in names}
    vis = {n: np.stack([read_mask(f.masks[n]) for f in frames]) for n in names}
    occ = {n: np.stack([read_mask(f.occluders[n]) for f in frames]) for n in names}
    truth = [np.load(ds.root / f.truth["centreline"], allow_pickle=False) for f in frames]
    return ds, names, frames, fk, imgs, full, vis, occ, truth


def evaluate(
    path, config: RefineConfig, mode: str = "map", verbose: bool = True, max_frames=None
) -> dict:
    ds, names, frames, fk, imgs, full, vis, occ, truth = load_frames(path, max_frames)
    cams = tuple(ds.cameras[n] for n in names)
    bgs, ims = colour_masks(imgs, names)
    t0 = time.perf_counter()
    out = refine_batch(fk.centreline, cams, tuple(ims), tuple(bgs), config, mode=mode)
    wall = time.perf_counter() - t0
    rows = []
    for k, f in enumerate(frames):
        r = {"id": f.id, "ok": bool(out.ok[k]), "steps": int(out.num_steps[k])}
        for ci, n in enumerate(names):
            pm, nm = np.asarray(out.masks[ci][k]), np.asarray(out.nominal_masks[ci][k])
            r[f"iou_nom_{n}"] = float(iou(nm, full[n][k]))
            r[f"iou_{n}"] = float(iou(pm, full[n][k]))
            r[f"aiou_nom_{n}"] = float(adjusted_iou(nm, vis[n][k], occ[n][k]))
            r[f"aiou_{n}"] = float(adjusted_iou(pm, vis[n][k], occ[n][k]))
        tp = jnp.asarray(truth[k], jnp.float32)
        r["tip_nom_mm"] = 1e3 * float(tip_error(fk.centreline.p[k], tp))
        r["tip_mm"] = 1e3 * float(tip_error(out.centreline.p[k], tp))
        r["mce_nom_mm"] = 1e3 * float(mean_centreline_error(fk.centreline.p[k], tp))
        r["mce_mm"] = 1e3 * float(mean_centreline_error(out.centreline.p[k], tp))
        rows.append(r)
    keys = [k for k in rows[0] if k not in ("id", "ok")]
    summary = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    summary["frames"] = len(rows)
    summary["wall_s"] = wall
    summary["ms_per_frame"] = 1e3 * wall / len(rows)
    if verbose:
        print(ds.name, json.dumps({k: round(v, 3) for k, v in summary.items()}))
    return {"name": ds.name, "summary": summary, "rows": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+")
    ap.add_argument("--json", default=None)
    ap.add_argument("--mode", default="map")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--set", nargs="*", default=[], help="RefineConfig overrides key=value")
    ap.add_argument("--cache", default=None, help="persistent JAX compilation cache folder")
    a = ap.parse_args(argv)
    if a.cache:
        jax.config.update("jax_compilation_cache_dir", a.cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    kw = {}
    for s in a.set:
        k, v = s.split("=", 1)
        kw[k] = eval(v)  # experiment script: tuples/floats from the command line
    cfg = RefineConfig(**kw)
    res = [evaluate(p, cfg, a.mode, max_frames=a.frames) for p in a.datasets]
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(res, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
