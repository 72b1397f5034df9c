"""Solver convergence of the kinematic-prior refinement (jaxcr.segmentation.refine) on synthetic presets.

For each preset (generated with ``jaxcr synth`` defaults for one seed, or reused with
``--keep``) all frames are refined in one compiled call per mode, and the script reports per
set and per frame:

* cold start (``refine_batch``, lax.map, the default): solver steps, final J, IoU and
  adjusted IoU against the visible mask, wall time per frame (median of ``--repeats``);
* vmap (``refine_batch(mode="vmap")``): agreement with the cold lax.map run (mask IoU
  between the two, |dJ|, max |d coeffs|), steps, time;
* warm start (``refine_sequence``, each frame from the previous frame's delta-u): steps,
  time, IoU;
* warm start from the answer (``refine_batch`` with ``inits`` = the cold run's coefficients):
  steps (a converged solver re-started at its own answer should stop almost at once).

The script only uses the public API, so the same file measures an older checkout with
``PYTHONPATH=/path/to/old/checkout``. Writes ``<results>/refine_convergence_seed<k>.md`` and
``.json``.

    python experiments/segmentation/refine_convergence.py --seed 1 --frames 8 --size 320x240 \
        --presets endoscopic endoscopic_occluded orthogonal_occluded
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

HERE = Path(__file__).resolve().parent


def load_preset(ds_dir: Path):
    from jaxcr.io.dataset import load_dataset
    from jaxcr.segmentation.background import colour_mask

    ds = load_dataset(ds_dir)
    cam = next(iter(ds.cameras))
    frames = list(ds.frames)
    qs = jnp.asarray(np.stack([np.asarray(f.q) for f in frames]), jnp.float32)
    fk = jax.jit(jax.vmap(ds.robot.forward))(qs)
    imgs = jnp.asarray(np.stack([f.load_image(cam) for f in frames]))
    bgs, subs = jax.jit(jax.vmap(colour_mask))(imgs)
    vis = [f.load_mask(cam) for f in frames]
    occ = [f.load_occluder(cam) for f in frames]
    return fk.centreline, ds.cameras[cam], subs, bgs, vis, occ, [f.id for f in frames]


def _ious(masks, vis, occ):
    from jaxcr.segmentation.metrics import adjusted_iou, iou

    raw, adj = [], []
    for k, v in enumerate(vis):
        m = np.asarray(masks[k])
        raw.append(float(iou(m, v)))
        o = occ[k] if occ[k] is not None else np.zeros_like(v)
        adj.append(float(adjusted_iou(m, v, o)))
    return raw, adj


def run_preset(ds_dir: Path, repeats: int, cfg) -> dict:
    from jaxcr.segmentation.metrics import iou
    from jaxcr.segmentation.refine import refine_batch, refine_sequence

    bases, cam, I, B, vis, occ, ids = load_preset(ds_dir)
    f = len(ids)
    out = {"frames": ids}

    def timed(fn):
        t0 = time.perf_counter()
        r = fn()
        compile_s = time.perf_counter() - t0
        ts = []
        for _ in range(repeats):
            r = fn()
            ts.append(float(r.time_s[0]))
        return r, compile_s, 1e3 * float(np.median(ts))

    def summary(r, name, ms, compile_s):
        raw, adj = _ious(r.masks[0], vis, occ)
        out[name] = {
            "steps": np.asarray(r.num_steps).tolist(),
            "steps_per_level": np.asarray(r.steps_per_level).tolist(),
            "status": np.asarray(r.status).tolist(),
            "J": np.asarray(r.energy.total).tolist(),
            "iou": raw,
            "adj_iou": adj,
            "ms_per_frame": ms,
            "compile_s": compile_s,
        }

    cold, c_s, c_ms = timed(lambda: refine_batch(bases, cam, I, B, cfg))
    summary(cold, "cold", c_ms, c_s)
    vm, v_s, v_ms = timed(lambda: refine_batch(bases, cam, I, B, cfg, mode="vmap"))
    summary(vm, "vmap", v_ms, v_s)
    out["vmap"]["mask_iou_vs_map"] = [
        float(iou(np.asarray(vm.masks[0][k]), np.asarray(cold.masks[0][k]))) for k in range(f)
    ]
    out["vmap"]["abs_dJ_vs_map"] = np.abs(
        np.asarray(vm.energy.total) - np.asarray(cold.energy.total)
    ).tolist()
    out["vmap"]["max_dcoeff_vs_map"] = (
        np.abs(np.asarray(vm.coeffs) - np.asarray(cold.coeffs)).reshape(f, -1).max(1).tolist()
    )
    warm, w_s, w_ms = timed(lambda: refine_sequence(bases, cam, I, B, cfg))
    summary(warm, "warm_sequence", w_ms, w_s)
    kw = {"inits": cold.coeffs}
    if "init_cams" in inspect.signature(refine_batch).parameters:
        kw["init_cams"] = cold.camera_correction  # camera correction warm-started too
    again, a_s, a_ms = timed(lambda: refine_batch(bases, cam, I, B, cfg, **kw))
    summary(again, "warm_from_answer", a_ms, a_s)
    return out


def _meta() -> dict:
    import jaxcr.segmentation.refine as R

    try:
        commit = subprocess.run(
            ["git", "-C", str(HERE), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=False,
        ).stdout.strip()
    except OSError:
        commit = "?"
    return {
        "refine_module": R.__file__,
        "commit": commit,
        "jax": jax.__version__,
        "loadavg_1_5_15": [round(x, 2) for x in os.getloadavg()],
        "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
    }


def _fmt(res: dict, argv: list[str]) -> str:
    lines = [
        f"# Refinement solver convergence (seed {res['seed']}, {res['size']}, "
        f"{res['n_frames']} frames per set)",
        "",
        f"Command: `python experiments/segmentation/refine_convergence.py {' '.join(argv)}`",
        "",
        f"Config: `{res['config']}`",
        "",
        "Machine: " + json.dumps(res["meta"]) + " (shared 2-core machine; times scale with load)",
        "",
        "| set | mode | median steps | mean steps | mean J | IoU | adj. IoU | ms/frame |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for p, r in res["presets"].items():
        for mode in ("cold", "vmap", "warm_sequence", "warm_from_answer"):
            m = r[mode]
            lines.append(
                f"| {p} | {mode} | {np.median(m['steps']):.0f} | {np.mean(m['steps']):.1f} | "
                f"{np.mean(m['J']):.4f} | {np.mean(m['iou']):.3f} | {np.mean(m['adj_iou']):.3f} "
                f"| {m['ms_per_frame']:.1f} |"
            )
    lines += [
        "",
        "vmap vs lax.map (same frames, cold start): min mask IoU between the two, max |dJ|, "
        "max |d coeff|",
        "",
        "| set | min mask IoU | max abs dJ | max abs dcoeff |",
        "|---|---|---|---|",
    ]
    for p, r in res["presets"].items():
        v = r["vmap"]
        lines.append(
            f"| {p} | {min(v['mask_iou_vs_map']):.4f} | {max(v['abs_dJ_vs_map']):.2e} | "
            f"{max(v['max_dcoeff_vs_map']):.2e} |"
        )
    lines += ["", "Per frame (cold): steps per level, J, adj. IoU; warm sequence steps", ""]
    lines += ["| set | frame | cold steps/level | cold J | cold adj IoU | warm steps | "
              "warm adj IoU | from-answer steps |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for p, r in res["presets"].items():
        for k, fid in enumerate(r["frames"]):
            c, w, a = r["cold"], r["warm_sequence"], r["warm_from_answer"]
            lines.append(
                f"| {p} | {fid} | {c['steps_per_level'][k]} | {c['J'][k]:.4f} | "
                f"{c['adj_iou'][k]:.3f} | {w['steps'][k]} | {w['adj_iou'][k]:.3f} | "
                f"{a['steps'][k]} |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--presets", nargs="*", default=["endoscopic", "orthogonal_occluded"])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--work", default="/tmp/jaxcr-convergence")
    ap.add_argument("--keep", action="store_true", help="reuse generated datasets if present")
    ap.add_argument("--results", default=str(HERE.parent / "results" / "segmentation"))
    ap.add_argument("--tag", default="", help="suffix of the output file names")
    a = ap.parse_args(argv)

    from jaxcr.segmentation.refine import RefineConfig
    from jaxcr.synth.generate import generate, parse_size

    size = parse_size(a.size)
    cfg = RefineConfig()
    res = {
        "seed": a.seed,
        "size": a.size,
        "n_frames": a.frames,
        "config": repr(cfg),
        "presets": {},
    }
    for preset in a.presets:
        ds_dir = Path(a.work) / f"seed{a.seed}_{a.size}" / preset
        if not (a.keep and (ds_dir / "dataset.json").exists()):
            generate(preset, ds_dir, seed=a.seed, frames=a.frames, size=size)
        res["presets"][preset] = run_preset(ds_dir, a.repeats, cfg)
        print(preset, "done", flush=True)
    res["meta"] = _meta()
    out = Path(a.results)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"refine_convergence_seed{a.seed}{a.tag}"
    (out / f"{stem}.json").write_text(json.dumps(res, indent=1))
    text = _fmt(res, argv)
    (out / f"{stem}.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
