"""Where the time of one refinement goes (issue 18: "profile first, and commit the profile").

Scene: the 640x480 scene of ``jaxcr/benchmarks/segment.py`` (``make_scene``), package
defaults (:class:`jaxcr.segmentation.refine.RefineConfig`). Timers per stage, each a separately
jitted function, medians over repeats after a warm-up call (compile excluded):

* ``pyramid + region data``: :func:`energy.pyramid` and :func:`energy.region_data_from_level`
  for the levels the schedule visits and level 0 (the outputs);
* ``band selection``: one :func:`silhouette.select_band` at the finest solve level;
* ``energy value+grad``: one value-and-gradient of the objective at each level (what a solver
  step pays, plus the BFGS bookkeeping which is negligible at ~14 parameters);
* ``outputs``: the full-resolution band, mask and hard terms of the refined and of the nominal
  tube (twice :func:`refine._mask` and its band);
* ``whole frame``: :func:`refine.refine_frame_jit` cold, and warm (the ``warm()`` schedule started
  from the cold answer), with its solver steps.

``steps x value+grad + fixed stages`` is compared with the whole frame. The machine is shared
with other engineers: the 1-minute load average is recorded before and after.

Run: ``PYTHONPATH=$PWD python experiments/segmentation/profile_refine.py --tag before``
(writes ``experiments/results/segmentation/profile_refine_<tag>.md`` and ``.json``).
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

from jaxcr.benchmarks.segment import _meta, make_scene
from jaxcr.segmentation.background import colour_mask
from jaxcr.segmentation.energy import chan_vese_energy, pyramid, region_data_from_level
from jaxcr.segmentation.metrics import iou
from jaxcr.segmentation.refine import RefineConfig, _mask, refine_frame_jit
from jaxcr.segmentation.shape import perturbed_centreline, regularisation
from jaxcr.segmentation.silhouette import level_tube, project_tube, select_band

OUT = Path(__file__).resolve().parents[1] / "results" / "segmentation"


def _median_ms(fn, *args, repeats: int = 20) -> float:
    jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(ts))


def profile(cfg: RefineConfig, frames: int, repeats: int) -> dict:
    base, cam, fr = make_scene(frames)
    imgs, bgs = [], []
    for f in fr:
        b, i = colour_mask(jnp.asarray(f["img"]))
        imgs.append(i)
        bgs.append(b)
    weights = cfg.weights
    n_levels = max(cfg.levels) + 1
    res: dict = {"stages_ms": {}}
    st = res["stages_ms"]

    @jax.jit
    def prep(im, bg):
        p = pyramid(im, bg, n_levels)
        return [region_data_from_level(*p[lv], lv, cfg.tile) for lv in sorted({*cfg.levels, 0})]

    st["pyramid + region data"] = _median_ms(prep, imgs[0], bgs[0], repeats=repeats)
    datas = prep(imgs[0], bgs[0])
    by_level = dict(zip(sorted({*cfg.levels, 0}), datas, strict=True))
    c0 = jnp.zeros(cfg.coeff_shape)
    tube0 = project_tube(cam, perturbed_centreline(base, c0))
    area_ref = jnp.asarray(1000.0)
    for li, lv in enumerate(cfg.levels):
        d = by_level[lv]
        k_tiles = cfg.tiles_at(lv)

        @jax.jit
        def band_of(c, d=d, lv=lv, k_tiles=k_tiles):
            t = project_tube(cam, perturbed_centreline(base, c))
            return select_band(level_tube(t, lv, cfg.seg_merge), d.grid, k_tiles, cfg.k_seg)

        st[f"band selection, level {lv} ({k_tiles} tiles)"] = _median_ms(
            band_of, c0, repeats=repeats
        )
        band = band_of(c0)

        @jax.jit
        def vg(c, band=band, d=d, lv=lv, tau=cfg.tau[li]):
            def J(c):
                t = project_tube(cam, perturbed_centreline(base, c))
                reg = regularisation(c, base.s)
                e, _ = chan_vese_energy(
                    level_tube(t, lv, cfg.seg_merge), band, d, reg, weights, tau, area_ref,
                    cfg.local, cfg.robust,
                )  # fmt: skip
                return e

            return jax.value_and_grad(J)(c)

        st[f"energy value+grad, level {lv}"] = _median_ms(vg, c0, repeats=repeats)

    d0 = by_level[0]
    k0 = cfg.tiles_at(0)

    @jax.jit
    def outputs(c):
        t = project_tube(cam, perturbed_centreline(base, c))
        band = select_band(t, d0.grid, k0, cfg.seg_merge * cfg.k_seg)
        return _mask(t, band, d0)

    st["outputs: one full-resolution mask (x2: refined + nominal)"] = _median_ms(
        outputs, c0, repeats=repeats
    )
    del tube0

    # whole frames
    refine_frame_jit(base, cam, imgs[0], bgs[0], cfg)  # compile
    cold_ms, cold_steps, cold_iou, answers = [], [], [], []
    for k in range(frames):
        r = refine_frame_jit(base, cam, imgs[k], bgs[k], cfg)
        cold_ms.append(1e3 * float(r.time_s))
        cold_steps.append(np.asarray(r.steps_per_level).tolist())
        cold_iou.append(float(iou(r.masks[0], fr[k]["mask"])))
        # with the solver's Hessian where the library returns one (hessian_memory)
        answers.append((r.coeffs, r.camera_correction, getattr(r, "hessian_inv", None)))
    warm = cfg.warm()

    def warm_call(k, a):
        kw = {} if a[2] is None else {"init_hessian": a[2]}
        return refine_frame_jit(base, cam, imgs[k], bgs[k], warm, a[0], True, a[1], **kw)

    warm_call(0, answers[0])  # compile
    warm_ms, warm_steps, warm_iou = [], [], []
    for k in range(frames):
        # warm start from this frame's own cold answer: the steps a converged tracker pays
        r = warm_call(k, answers[k])
        warm_ms.append(1e3 * float(r.time_s))
        warm_steps.append(np.asarray(r.steps_per_level).tolist())
        warm_iou.append(float(iou(r.masks[0], fr[k]["mask"])))
    res["cold"] = {
        "ms_median": float(np.median(cold_ms)),
        "steps_per_level": cold_steps,
        "iou_mean": float(np.mean(cold_iou)),
    }
    res["warm_from_answer"] = {
        "ms_median": float(np.median(warm_ms)),
        "steps_per_level": warm_steps,
        "iou_mean": float(np.mean(warm_iou)),
    }
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tag", default="before")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args(argv)
    load0 = os.getloadavg()[0]
    res = profile(RefineConfig(), args.frames, args.repeats)
    res["load_1min_before_after"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
    res["meta"] = _meta()
    res["command"] = (
        f"PYTHONPATH=$PWD python experiments/segmentation/profile_refine.py --tag {args.tag} "
        f"--frames {args.frames} --repeats {args.repeats}"
    )
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"profile_refine_{args.tag}.json").write_text(json.dumps(res, indent=1))
    lines = [
        f"# Refinement profile, 640x480, package defaults ({args.tag})",
        "",
        f"Command: `{res['command']}`",
        "",
        "| stage | median ms |",
        "|---|---|",
    ]
    lines += [f"| {k} | {v:.2f} |" for k, v in res["stages_ms"].items()]
    for key in ("cold", "warm_from_answer"):
        r = res[key]
        steps = np.asarray(r["steps_per_level"])
        lines.append(
            f"| whole frame, {key} (refine_frame_jit) | {r['ms_median']:.1f} "
            f"(steps per level, mean: {steps.mean(0).round(1).tolist()}; IoU {r['iou_mean']:.3f}) |"
        )
    lines += [
        "",
        f"1-min load before/after: {res['load_1min_before_after']} on {os.cpu_count()} cores "
        "(shared machine: times scale with the load).",
        "",
        "Machine: " + json.dumps(res["meta"]),
    ]
    (OUT / f"profile_refine_{args.tag}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
