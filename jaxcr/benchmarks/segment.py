"""Benchmark: kinematic-prior refinement (jaxcr.segmentation.refine) per 640x480 frame, against the
straightforward reference a user would write first: the same energy (Watson eq. 5/6, same
weights, normalisation, soft silhouette and pyramid levels) on dense numpy masks, minimised by
``scipy.optimize.minimize(method="L-BFGS-B")`` with finite-difference gradients.

Scene: a 3-D tube (tissue-like noisy background, grey tube) rendered independently of jaxcr's
silhouette code (eq. 7 surface points, convex hull per segment filled at pixel centres), with a
known curvature perturbation per frame; the nominal centreline is the unperturbed one.

Reports: compile time (first call), median and spread of ms per frame for the batch
(``refine_batch``, lax.map) and single-frame calls, the numpy/scipy reference's ms per frame,
the ratio, the IoU of both, and the warm-start speed-up of ``refine_sequence`` on a smooth
sequence. ``write_report`` writes ``bench_segment.md`` (+ .json) with metadata.

Run it with ``jaxcr bench segment`` (installed package) or
``python experiments/segmentation/bench_segment.py [--frames 8] [--repeats 5] [--ref-frames 2]``
(writes ``experiments/results/segmentation/``).
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import scipy
import scipy.optimize

from jaxcr.camera import Camera, project_points, surface_points
from jaxcr.errors import InputError
from jaxcr.kinematics.cosserat import integrate_centreline
from jaxcr.segmentation.background import colour_mask
from jaxcr.segmentation.energy import pyramid
from jaxcr.segmentation.metrics import iou
from jaxcr.segmentation.refine import RefineConfig, refine_batch, refine_frame_jit, refine_sequence
from jaxcr.segmentation.shape import perturbed_centreline, regularisation
from jaxcr.segmentation.silhouette import project_tube, rasterise_dense, scale_tube

W, H = 640, 480


def make_scene(n_frames: int, seed: int = 0, smooth: bool = False):
    """Nominal centreline, camera, and per frame: true coefficients, image, truth mask."""
    try:  # the scene is filled by scikit-image, a test dependency (not a runtime one)
        from skimage.draw import polygon
    except ModuleNotFoundError:
        raise InputError(
            "the segment benchmark needs scikit-image (pip install 'jaxcr[test]')", field="what"
        ) from None
    n = 97
    s = jnp.linspace(0.0, 0.12, n)
    u = jnp.tile(jnp.array([7.0, 2.0, 0.0]), (n - 1, 1))
    R0 = jnp.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    base = integrate_centreline(s, u, jnp.full(n, 1.1e-3), jnp.array([-0.06, 0.01, 0.0]), R0)
    cam = Camera.look_at([0, 0, -0.25], [0, 0, 0], [0, -1, 0], fx=700.0, size=(W, H))
    rng = np.random.default_rng(seed)
    bg_img = tissue_background(rng)
    frames = []
    c_prev = rng.normal(0, 0.12, (2, 4))
    for k in range(n_frames):
        if smooth:
            c = c_prev + rng.normal(0, 0.02, (2, 4))
        else:
            c = rng.normal(0, 0.12, (2, 4))
        c[:, 0] += np.array([0.25, 0.0]) * (1 if k % 2 == 0 else -1)
        c_prev = c
        frames.append(render_frame(base, cam, bg_img, c, rng, polygon))
    return base, cam, frames


def tissue_background(rng) -> np.ndarray:
    """make_scene's smooth tissue-like background: blurred noise over a red/pink palette."""
    tex = cv2.GaussianBlur(rng.random((H, W)).astype(np.float32), (0, 0), 12)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    pink, red = np.array([0.80, 0.45, 0.45]), np.array([0.55, 0.15, 0.15])
    return (tex[..., None] * pink + (1 - tex[..., None]) * red).astype(np.float32)


def render_frame(base, cam, bg_img, c, rng, polygon) -> dict:
    """One frame of make_scene: the tube of shape coefficients ``c`` drawn over ``bg_img``
    with pixel noise from ``rng`` (``polygon``: skimage.draw.polygon). Returns coeffs, img,
    mask."""
    truth = perturbed_centreline(base, jnp.asarray(c, jnp.float32))
    pts = surface_points(truth, 24)
    uv, _ = project_points(cam, pts.reshape(-1, 3))
    uv = np.asarray(uv).reshape(pts.shape[0], 24, 2)
    mask = np.zeros((H, W), bool)
    for i in range(pts.shape[0] - 1):
        hull = cv2.convexHull(np.concatenate([uv[i], uv[i + 1]]).astype(np.float32))[:, 0]
        rr, cc = polygon(hull[:, 1], hull[:, 0], mask.shape)
        mask[rr, cc] = True
    img = bg_img + rng.normal(0, 0.04, bg_img.shape).astype(np.float32)
    img[mask] = np.array([0.55, 0.55, 0.57]) + rng.normal(0, 0.03, (mask.sum(), 3))
    return dict(coeffs=c, img=np.clip(img, 0, 1).astype(np.float32), mask=mask)


# ----------------------------------------------------------------------------- reference


def _margin_numpy(px, py, t):
    """Dense capsule margins (pixels x segments) in numpy, max over segments."""
    ax, ay, bx, by, ra, rb, valid = (np.asarray(x, np.float64) for x in jax.tree.leaves(t))
    dx, dy = bx - ax, by - ay
    l2 = np.maximum(dx * dx + dy * dy, 1e-12)
    wx = px[:, None] - ax[None]
    wy = py[:, None] - ay[None]
    tt = np.clip((wx * dx + wy * dy) / l2, 0.0, 1.0)
    ex, ey = wx - tt * dx, wy - tt * dy
    m = ra + tt * (rb - ra) - np.sqrt(ex * ex + ey * ey)
    m = np.where(valid > 0, m, -1e4)
    return m.max(axis=1)


def reference_refine(base, cam, img_p, bg, cfg: RefineConfig):
    """The same energy on dense numpy masks, scipy L-BFGS-B with finite differences."""
    levels = pyramid(jnp.asarray(img_p), jnp.asarray(bg), max(cfg.levels) + 1)
    levels = [tuple(np.asarray(x, np.float64) for x in lv) for lv in levels]
    fk = jax.jit(lambda c: project_tube(cam, perturbed_centreline(base, c)))
    regf = jax.jit(lambda c: regularisation(c, base.s))
    shape = cfg.coeff_shape
    t0 = fk(jnp.zeros(shape))
    length = np.hypot(np.asarray(t0.bx - t0.ax), np.asarray(t0.by - t0.ay))
    area_ref = max(float(np.sum((np.asarray(t0.ra) + np.asarray(t0.rb)) * length)), 1.0)
    nfev = 0

    def energy(x, level, tau):
        nonlocal nfev
        nfev += 1
        c = jnp.asarray(x.reshape(shape), jnp.float32)
        t = scale_tube(fk(c), level)
        img, w, b = levels[level]
        h, wd = w.shape
        py, px = np.mgrid[0:h, 0:wd]
        m = _margin_numpy(px.ravel().astype(np.float64), py.ravel().astype(np.float64), t)
        soft = 1.0 / (1.0 + np.exp(-m / tau))
        a = 4.0**level
        ww = w.ravel()
        I = img.reshape(-1, 3)
        tot0, tot1 = ww.sum(), (ww[:, None] * I).sum(0)
        centre = tot1 / tot0
        Ic = (I - centre) * (ww[:, None] > 0)
        q = (Ic * Ic).sum(1)
        s0, s1, s2 = (ww * soft).sum(), ((ww * soft)[:, None] * Ic).sum(0), (ww * soft * q).sum()
        t0_, t1_, t2_ = ww.sum(), (ww[:, None] * Ic).sum(0), (ww * q).sum()
        e_in = s2 - (s1 @ s1) / max(s0, 1e-6)
        e_out = (t2_ - s2) - ((t1_ - s1) @ (t1_ - s1)) / max(t0_ - s0, 1e-6)
        e_empty = t2_ - (t1_ @ t1_) / t0_
        var = t2_ / t0_
        pen = (b.ravel() * soft).sum()
        J = (cfg.g_in * a * e_in + cfg.g_out * a * (e_out - e_empty)) / (area_ref * var)
        J += cfg.g_pen * a * pen / area_ref + cfg.g_reg * float(regf(c))
        return float(J)

    x = np.zeros(int(np.prod(shape)))
    for li, level in enumerate(cfg.levels):
        for _ in range(cfg.outer[li]):
            res = scipy.optimize.minimize(
                energy,
                x,
                args=(level, cfg.tau[li]),
                method="L-BFGS-B",
                # finite-difference step: the FK runs in float32 (as ours), so scipy's
                # default 1e-8 is below its resolution and the gradient is noise (the
                # reference then never moved); 1e-4 of a dimensionless coefficient moves
                # the tip by ~0.01 mm, far above the float32 noise
                options={"maxiter": cfg.steps[li], "eps": 1e-4},
            )
            x = res.x
    c = jnp.asarray(x.reshape(shape), jnp.float32)
    mask = np.asarray(rasterise_dense(fk(c), H, W))
    return mask, nfev


# ----------------------------------------------------------------------------- benchmark


def _meta() -> dict:
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
        ).stdout.strip()
    except OSError:
        commit = "?"
    load = os.getloadavg()
    return {
        "commit": commit,
        "python": sys.version.split()[0],
        "jax": jax.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "opencv": cv2.__version__,
        "machine": platform.machine(),
        "processor": platform.processor() or platform.uname().machine,
        "cpus": os.cpu_count(),
        "loadavg_1_5_15": [round(x, 2) for x in load],
        "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
    }


def run_segment_benchmark(
    frames: int = 8, repeats: int = 5, ref_frames: int = 2, config: RefineConfig | None = None
) -> dict:
    """Run the benchmark (see module docstring); returns a dict of the numbers.

    The timed configuration is the paper's energy (eq. 5 with eq. 6: global mu_out, no camera
    correction), which is what the scipy reference implements; the package defaults (local
    mu_out and camera correction) are timed as well, in the same run."""
    cfg = RefineConfig(local=False, camera_correction=False) if config is None else config
    base, cam, fr = make_scene(frames)
    imgs, bgs = [], []
    for f in fr:
        b, i = colour_mask(jnp.asarray(f["img"]))
        imgs.append(i)
        bgs.append(b)
    I, B = jnp.stack(imgs), jnp.stack(bgs)
    bases = jax.tree.map(lambda x: jnp.broadcast_to(x, (frames,) + x.shape), base)

    t0 = time.perf_counter()
    out = refine_batch(bases, cam, I, B, cfg)
    compile_batch = time.perf_counter() - t0
    batch_ms = []
    for _ in range(repeats):
        out = refine_batch(bases, cam, I, B, cfg)
        batch_ms.append(1e3 * float(out.time_s[0]))
    ious = [float(iou(out.masks[0][k], f["mask"])) for k, f in enumerate(fr)]
    ious_nom = [float(iou(out.nominal_masks[0][k], f["mask"])) for k, f in enumerate(fr)]

    t0 = time.perf_counter()
    refine_frame_jit(base, cam, I[0], B[0], cfg)
    compile_single = time.perf_counter() - t0
    single_ms = []
    for _ in range(repeats):
        for k in range(frames):
            single_ms.append(1e3 * float(refine_frame_jit(base, cam, I[k], B[k], cfg).time_s))

    dflt = RefineConfig()
    t0 = time.perf_counter()
    refine_batch(bases, cam, I, B, dflt)
    compile_default = time.perf_counter() - t0
    dflt_ms = []
    for _ in range(repeats):
        o = refine_batch(bases, cam, I, B, dflt)
        dflt_ms.append(1e3 * float(o.time_s[0]))
    dflt_iou = float(np.mean([float(iou(o.masks[0][k], f["mask"])) for k, f in enumerate(fr)]))

    ref_ms, ref_iou, ref_nfev = [], [], []
    for k in range(min(ref_frames, frames)):
        t0 = time.perf_counter()
        mask, nfev = reference_refine(base, cam, np.asarray(I[k]), np.asarray(B[k]), cfg)
        ref_ms.append(1e3 * (time.perf_counter() - t0))
        ref_iou.append(float(iou(mask, fr[k]["mask"])))
        ref_nfev.append(nfev)
    jax_iou_same = float(np.mean(ious[: len(ref_iou)]))

    # warm start on a smooth sequence
    sbase, scam, sfr = make_scene(frames, seed=1, smooth=True)
    sI, sB = [], []
    for f in sfr:
        b, i = colour_mask(jnp.asarray(f["img"]))
        sI.append(i)
        sB.append(b)
    sI, sB = jnp.stack(sI), jnp.stack(sB)
    sbases = jax.tree.map(lambda x: jnp.broadcast_to(x, (frames,) + x.shape), sbase)
    refine_sequence(sbases, scam, sI, sB, cfg)  # compile
    cold = refine_batch(sbases, scam, sI, sB, cfg)
    warm = refine_sequence(sbases, scam, sI, sB, cfg)
    cold_ms = 1e3 * float(
        np.median([refine_batch(sbases, scam, sI, sB, cfg).time_s[0] for _ in range(3)])
    )
    warm_ms = 1e3 * float(
        np.median([refine_sequence(sbases, scam, sI, sB, cfg).time_s[0] for _ in range(3)])
    )

    med = float(np.median(batch_ms))
    res = {
        "config": {
            f: getattr(cfg, f) for f in ("levels", "steps", "outer", "n_coeffs", "band_tiles")
        },
        "frames": frames,
        "image": [W, H],
        "compile_s_batch": compile_batch,
        "compile_s_single": compile_single,
        "batch_ms_per_frame_median": med,
        "batch_ms_per_frame_minmax": [float(np.min(batch_ms)), float(np.max(batch_ms))],
        "single_ms_median": float(np.median(single_ms)),
        "single_ms_p10_p90": [
            float(np.percentile(single_ms, 10)),
            float(np.percentile(single_ms, 90)),
        ],
        "solver_steps_mean": float(np.mean(np.asarray(out.num_steps))),
        "default_config": {
            "compile_s_batch": compile_default,
            "batch_ms_per_frame_median": float(np.median(dflt_ms)),
            "iou_refined_mean": dflt_iou,
        },
        "iou_nominal_mean": float(np.mean(ious_nom)),
        "iou_refined_mean": float(np.mean(ious)),
        "reference_frames": len(ref_ms),
        "reference_ms_per_frame_median": float(np.median(ref_ms)) if ref_ms else None,
        "reference_energy_evaluations_mean": float(np.mean(ref_nfev)) if ref_nfev else None,
        "reference_iou_mean": float(np.mean(ref_iou)) if ref_iou else None,
        "jax_iou_mean_same_frames": jax_iou_same,
        "speedup_vs_reference": float(np.median(ref_ms)) / med if ref_ms else None,
        "warm_start": {
            "cold_steps_mean": float(np.mean(np.asarray(cold.num_steps))),
            "warm_steps_mean": float(np.mean(np.asarray(warm.num_steps))),
            "cold_ms_per_frame": cold_ms,
            "warm_ms_per_frame": warm_ms,
            "cold_iou_mean": float(
                np.mean([float(iou(cold.masks[0][k], f["mask"])) for k, f in enumerate(sfr)])
            ),
            "warm_iou_mean": float(
                np.mean([float(iou(warm.masks[0][k], f["mask"])) for k, f in enumerate(sfr)])
            ),
        },
        "meta": _meta(),
    }
    return res


def write_markdown(path: Path, lines: list[str], meta: dict) -> str:
    """Write an experiment's markdown report ``lines`` to ``path``, ending with the
    "Machine:" line of ``meta`` (:func:`_meta`); returns the text (the experiment scripts'
    shared tail: they print it)."""
    text = "\n".join([*lines, "", "Machine: " + json.dumps(meta)])
    Path(path).write_text(text + "\n")
    return text


def write_report(res: dict, out_dir: Path) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "bench_segment.json").write_text(json.dumps(res, indent=1))
    ws = res["warm_start"]
    lines = [
        "# Segmentation refinement benchmark (640x480)",
        "",
        "Command: `python experiments/segmentation/bench_segment.py` "
        f"(frames={res['frames']}, config={res['config']})",
        "",
        "| quantity | value |",
        "|---|---|",
        f"| compile, batch entry point (s) | {res['compile_s_batch']:.1f} |",
        f"| compile, single-frame entry point (s) | {res['compile_s_single']:.1f} |",
        f"| jaxcr refine_batch, median ms/frame (min-max of repeats) | {res['batch_ms_per_frame_median']:.1f} ({res['batch_ms_per_frame_minmax'][0]:.1f}-{res['batch_ms_per_frame_minmax'][1]:.1f}) |",
        f"| jaxcr refine_frame_jit, median ms/frame (p10-p90) | {res['single_ms_median']:.1f} ({res['single_ms_p10_p90'][0]:.1f}-{res['single_ms_p10_p90'][1]:.1f}) |",
        f"| mean BFGS steps per frame | {res['solver_steps_mean']:.1f} |",
        f"| package defaults (local mu_out, camera correction): compile s / median ms/frame / IoU | {res['default_config']['compile_s_batch']:.1f} / {res['default_config']['batch_ms_per_frame_median']:.1f} / {res['default_config']['iou_refined_mean']:.3f} |",
        f"| IoU nominal -> refined (mean over frames) | {res['iou_nominal_mean']:.3f} -> {res['iou_refined_mean']:.3f} |",
    ]
    if res["reference_frames"]:
        lines += [
            f"| reference (numpy dense + scipy L-BFGS-B, FD), ms/frame | {res['reference_ms_per_frame_median']:.0f} ({res['reference_frames']} frames, {res['reference_energy_evaluations_mean']:.0f} energy evaluations) |",
            f"| reference IoU / jaxcr IoU on the same frames | {res['reference_iou_mean']:.3f} / {res['jax_iou_mean_same_frames']:.3f} |",
            f"| speed-up vs reference | {res['speedup_vs_reference']:.0f}x |",
        ]
    else:
        lines += ["| reference | not run (--ref-frames 0) |"]
    lines += [
        f"| warm start (refine_sequence) vs cold: steps/frame | {ws['warm_steps_mean']:.1f} vs {ws['cold_steps_mean']:.1f} |",
        f"| warm start vs cold: ms/frame | {ws['warm_ms_per_frame']:.1f} vs {ws['cold_ms_per_frame']:.1f} |",
        f"| warm start vs cold: IoU | {ws['warm_iou_mean']:.3f} vs {ws['cold_iou_mean']:.3f} |",
        "",
        "Machine: " + json.dumps(res["meta"]),
        "",
        "The machine is shared (see the load average above); times scale with the load.",
    ]
    path = out_dir / "bench_segment.md"
    path.write_text("\n".join(lines) + "\n")
    return path
