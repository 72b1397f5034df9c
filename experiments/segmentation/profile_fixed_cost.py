"""The fixed (per-frame, not per-step) stages of a tracked frame, each jitted alone (issue 18,
refinement rows, engineer track29), and a candidate replacement of the costliest one.

``experiments/segmentation/profile_tracking.py`` measures a tracked frame's fixed cost as a
whole (the frame with a step budget of 0). This script times its pieces on the same scene
(``jaxcr.benchmarks.segment.make_scene(1, seed=1, smooth=True)``, package defaults), process
CPU and wall ms per call, medians of ``--repeats`` calls after a compile call:

* the level-0 pyramid and :func:`energy.region_data_from_level` (per-tile sums);
* one solve's band selection (merged tube, ``k_seg`` 4) and the output stage's (unmerged
  tube, 8 candidates), the band gather, margins, mask and hard terms, and one whole output
  (a frame computes two: the refined and the nominal tube);
* ``region data, stacked sums``: the same :class:`RegionData` with the five per-tile sums
  taken in one pass over a stacked (H, W, 6) array, rows of a tile first, then columns
  (a candidate, *not* in the library): its largest difference from the library's sums is
  printed (float32 rounding of another summation order).

Run: ``PYTHONPATH=$PWD python experiments/segmentation/profile_fixed_cost.py --size 1280x720
[--repeats 30] [--tag NAME]`` (writes ``experiments/results/segmentation/
profile_fixed_cost<tag>.md``).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxcr.benchmarks.segment as bs
from jaxcr.segmentation.background import colour_mask
from jaxcr.segmentation.energy import RegionData, padded_level, pyramid, region_data_from_level
from jaxcr.segmentation.refine import RefineConfig, _hard_terms, _mask
from jaxcr.segmentation.shape import perturbed_centreline
from jaxcr.segmentation.silhouette import (
    band_margin,
    level_tube,
    project_tube,
    select_band,
)

OUT = Path(__file__).resolve().parents[1] / "results" / "segmentation"


def region_data_stacked(img, w, b, level: int, tile: int) -> RegionData:
    """:func:`region_data_from_level` with the per-tile sums of one stacked array."""
    grid, img, w, b, total_w, centre = padded_level(img, w, b, tile)
    W = grid.cols * tile
    wc = w[..., None]
    st = jnp.concatenate(
        [wc, b[..., None], wc * img, (w * jnp.sum(img * img, axis=-1))[..., None]], -1
    )
    st = st.reshape(grid.rows, tile, W, 6).sum(axis=1)
    s = st.reshape(grid.rows, grid.cols, tile, 6).sum(axis=2).reshape(grid.n_tiles, 6)
    return RegionData(
        grid=grid, w=w, b=b, img=img, tile_w=s[:, 0], tile_b=s[:, 1], tile_s1=s[:, 2:5],
        tile_s2=s[:, 5], total_w=total_w, total_s1=jnp.sum(s[:, 2:5], axis=0),
        total_s2=jnp.sum(s[:, 5]), centre=centre, pix_area=float(4**level),
    )  # fmt: skip


def _time(fn, *args, repeats: int):
    jax.block_until_ready(fn(*args))
    cpu, wall = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        jax.block_until_ready(fn(*args))
        cpu.append(1e3 * (time.process_time() - c0))
        wall.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(cpu)), float(np.median(wall))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    wd, ht = (int(x) for x in args.size.lower().split("x"))
    bs.W, bs.H = wd, ht
    cfg = RefineConfig()
    base, cam, fr = bs.make_scene(1, seed=1, smooth=True)
    bg, im = colour_mask(jnp.asarray(fr[0]["img"]))
    load0 = os.getloadavg()[0]
    prep = jax.jit(lambda im, bg: region_data_from_level(*pyramid(im, bg, 1)[0], 0, cfg.tile))
    stacked = jax.jit(lambda im, bg: region_data_stacked(*pyramid(im, bg, 1)[0], 0, cfg.tile))
    d = prep(im, bg)
    d2 = stacked(im, bg)
    diff = max(
        float(jnp.max(jnp.abs(getattr(d, f) - getattr(d2, f))))
        for f in ("tile_w", "tile_b", "tile_s1", "tile_s2", "total_w", "total_s1", "total_s2")
    )
    tube = project_tube(cam, perturbed_centreline(base, jnp.zeros(cfg.coeff_shape)))
    k0 = cfg.tiles_at(0)
    kc = cfg.seg_merge * cfg.k_seg
    band = jax.jit(lambda t: select_band(t, d.grid, k0, kc))(tube)
    m = jax.jit(lambda t, b: band_margin(t, d.grid, b))(tube, band)

    def outputs(t):
        b = select_band(t, d.grid, k0, kc)
        mm = band_margin(t, d.grid, b)
        return _mask(t, b, d, mm), _hard_terms(t, b, d, cfg.local, cfg.robust, mm)

    stages = {
        "pyramid + region data, level 0": (prep, (im, bg)),
        "region data, stacked sums (candidate)": (stacked, (im, bg)),
        f"band selection of a solve (merged tube, k_seg {cfg.k_seg})": (
            jax.jit(lambda t: select_band(level_tube(t, 0, cfg.seg_merge), d.grid, k0, cfg.k_seg)),
            (tube,),
        ),
        f"band selection of an output ({kc} candidates)": (
            jax.jit(lambda t: select_band(t, d.grid, k0, kc)),
            (tube,),
        ),
        "band gather": (jax.jit(lambda tiles: d.gather(tiles)), (band.tiles,)),
        f"band margins ({kc} candidates)": (
            jax.jit(lambda t, b: band_margin(t, d.grid, b)),
            (tube, band),
        ),
        "mask": (jax.jit(lambda t, b, mm: _mask(t, b, d, mm)), (tube, band, m)),
        "hard terms": (
            jax.jit(lambda t, b, mm: _hard_terms(t, b, d, cfg.local, cfg.robust, mm)),
            (tube, band, m),
        ),
        "one output (x2 per frame)": (jax.jit(outputs), (tube,)),
    }
    res = {k: _time(fn, *a, repeats=args.repeats) for k, (fn, a) in stages.items()}
    load1 = os.getloadavg()[0]
    cmd = (
        "PYTHONPATH=$PWD python experiments/segmentation/profile_fixed_cost.py "
        f"--size {args.size} --repeats {args.repeats}" + (f" --tag {args.tag}" if args.tag else "")
    )
    lines = [
        f"# Fixed stages of a tracked frame, {wd}x{ht}, package defaults",
        "",
        f"Command: `{cmd}`",
        "",
        "| stage | CPU ms | wall ms |",
        "|---|---|---|",
        *(f"| {k} | {c:.2f} | {w:.2f} |" for k, (c, w) in res.items()),
        "",
        f"Largest difference of the stacked sums from the library's: {diff:.3g} (float32).",
        f"1-min load before/after: {load0:.1f} / {load1:.1f} on {os.cpu_count()} cores.",
        "",
        "Machine: " + json.dumps(bs._meta()),
    ]
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"profile_fixed_cost{args.tag}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
