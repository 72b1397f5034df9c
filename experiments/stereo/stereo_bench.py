"""Benchmark: time per stereo pair of the shape-sensing pipeline, by stage (no file I/O),
with compilation kept separate, and the JAX thinning against scikit-image's in the same run.

Usage (one command, about 1-2 minutes on an idle 2-core machine)::

    python experiments/stereo/stereo_bench.py [--data DIR] [--frames 8] [--repeats 5]

Images are loaded once. Pass 1 reconstructs every pair once (compilation: the first call
and any new shape bucket; reported separately with the number of XLA compilations). Then
``--repeats`` timed passes over all pairs; stage times are wall clock with JAX results
blocked (``reconstruct_pair``'s timings); the number of XLA compilations during the timed
passes is counted (should be 0: no recompilation per frame). Thinning: the pipeline's
thinning call (both views' bounding-box crops, one vmapped call) against
``skimage.morphology.skeletonize`` on the same crops, and the full-image masks; plus
Guo-Hall against ``skimage.morphology.thin`` (identical results expected). If ``--data``
does not exist the green stereo set of the accuracy experiment is generated there.
Writes ``experiments/results/stereo/stereo_bench.md``.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage as ndi
from skimage.morphology import skeletonize, thin

from jaxcr.cli.stereo import _read_rgb, load_stereo_dataset
from jaxcr.stereo.pipeline import _thin_batch, _thin_cropped_views, reconstruct_pair
from jaxcr.stereo.thinning import guo_hall_thin, zhang_suen_thin

_COMPILES: list[float] = []


def _on_event(name: str, secs: float, **_kw) -> None:
    if name == "/jax/core/compile/backend_compile_duration":
        _COMPILES.append(secs)


def _stats(x) -> tuple[float, float, float]:
    x = 1e3 * np.asarray(x)
    return float(np.median(x)), float(np.percentile(x, 10)), float(np.percentile(x, 90))


def _time(fn, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="/tmp/stereo_green")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default="experiments/results/stereo/stereo_bench.md")
    args = ap.parse_args()
    jax.monitoring.register_event_duration_secs_listener(_on_event)
    if not (Path(args.data) / "stereo.json").exists():
        from jaxcr.synth.stereo_ctr import generate_stereo_set

        print(f"generating the green stereo set in {args.data} ...", flush=True)
        generate_stereo_set(Path(args.data), n_frames=20, seed=1, background="green")
    load_before = os.getloadavg()
    ds = load_stereo_dataset(args.data)
    frames = ds["frames"][: args.frames]
    pairs = [[_read_rgb(ds["root"] / f["images"][n]) for n in ds["names"]] for f in frames]
    run = lambda im: reconstruct_pair(im[0], im[1], ds["cam1"], ds["cam2"], ds["config"])  # noqa: E731

    # Pass 1: compilation (first call, then every other shape bucket).
    t0 = time.perf_counter()
    first = run(pairs[0])
    t_first = time.perf_counter() - t0
    n_comp_first, s_comp_first = len(_COMPILES), sum(_COMPILES)
    t0 = time.perf_counter()
    results = [first] + [run(im) for im in pairs[1:]]
    t_rest = time.perf_counter() - t0
    n_comp_warm = len(_COMPILES)

    # Timed passes.
    totals, cpu, stages, stages_cpu = [], [], {}, {}
    for rep in range(args.repeats):
        print(f"timed pass {rep + 1}/{args.repeats}", flush=True)
        for im in pairs:
            t0, c0 = time.perf_counter(), time.process_time()
            r = run(im)
            totals.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            for k, v in r["timings"].items():
                if k != "cpu":
                    stages.setdefault(k, []).append(v)
            for k, v in r["timings"]["cpu"].items():
                stages_cpu.setdefault(k, []).append(v)
    n_comp_timed = len(_COMPILES) - n_comp_warm

    # Thinning, same run: the pipeline's call on the two views' crops vs skimage.
    masks = [list(r["robot_masks"]) for r in results]
    crops = []
    for m2 in masks:
        th = _thin_cropped_views(m2)
        crops.append(
            np.stack(
                [
                    m[r : r + sk.shape[0], c : c + sk.shape[1]]
                    for m, (sk, (r, c)) in zip(m2, th, strict=True)
                ]
            )
        )
    reps = max(args.repeats, 5)
    jx_pair, sk_pair, jx_full, sk_full, gh, skt = [], [], [], [], [], []
    agree, dist, gh_equal, zs_equal = [], [], 0, 0
    for c2, m2 in zip(crops, masks, strict=True):
        cj = jnp.asarray(c2)
        _thin_batch(cj).block_until_ready()
        jx_pair += _time(lambda cj=cj: np.asarray(_thin_batch(cj)), reps)
        sk_pair += _time(lambda c2=c2: [skeletonize(c) for c in c2], reps)
        for m in m2:
            mj = jnp.asarray(m)
            zhang_suen_thin(mj).block_until_ready()
            guo_hall_thin(mj).block_until_ready()
            jx_full += _time(lambda mj=mj: np.asarray(zhang_suen_thin(mj)), reps)
            sk_full += _time(lambda m=m: skeletonize(m), reps)
            gh += _time(lambda mj=mj: np.asarray(guo_hall_thin(mj)), reps)
            skt += _time(lambda m=m: thin(m), reps)
            a = np.asarray(zhang_suen_thin(mj))
            b = skeletonize(m)
            zs_equal += int(np.array_equal(a, b))
            gh_equal += int(np.array_equal(np.asarray(guo_hall_thin(mj)), thin(m)))
            agree.append(float(np.mean(a[b])))
            dist.append(float(ndi.distance_transform_edt(~b)[a].max()))
    n_masks = sum(len(m2) for m2 in masks)
    load_after = os.getloadavg()

    commit = subprocess.run(
        [
            "git",
            "log",
            "-1",
            "--format=%h",
            "--",
            "jaxcr/stereo",
            "experiments/stereo/stereo_bench.py",
        ],
        capture_output=True,
        text=True,
    ).stdout.strip()
    h, w = pairs[0][0].shape[:2]
    crop_shapes = sorted({tuple(c.shape[1:]) for c in crops})
    t_med = _stats(totals)[0]
    c_med = _stats(cpu)[0]
    lines = [
        "# Stereo pipeline benchmark (issue 4)",
        "",
        f"Command: `python experiments/stereo/stereo_bench.py --data {args.data} --frames {args.frames}"
        f" --repeats {args.repeats}`  ",
        f"commit {commit}; jax {jax.__version__}; Python {sys.version.split()[0]};"
        f" {platform.machine()}; {os.cpu_count()} logical CPUs (shared machine); load average"
        f" (1/5/15 min) before {load_before[0]:.1f}/{load_before[1]:.1f}/{load_before[2]:.1f},"
        f" after {load_after[0]:.1f}/{load_after[1]:.1f}/{load_after[2]:.1f}."
        f" {len(pairs)} pairs of {w}x{h}, {args.repeats} timed passes after a compiling pass.",
        "",
        "## Compilation (kept out of the per-pair times)",
        "",
        f"- first pair (compiles the pipeline's jitted functions): {t_first:.1f} s wall,"
        f" {n_comp_first} XLA compilations ({s_comp_first:.1f} s compiling);",
        f"- the other {len(pairs) - 1} pairs of the compiling pass: {t_rest:.1f} s,"
        f" {n_comp_warm - n_comp_first} more compilations (new shape buckets:"
        " thinning windows, backbone and chain-fit lengths; docs/decisions.md S23);",
        f"- timed passes: **{n_comp_timed} compilations** in {len(totals)} reconstructions"
        " (no recompilation per frame).",
        "",
        "## Time per stereo pair, without I/O",
        "",
        "Wall clock per stage (median, p10, p90) and the process CPU time of the stage (all"
        " threads; median). On a loaded machine wall clock includes waiting for a core; the"
        " CPU time does not.",
        "",
        "| stage | wall median (ms) | wall p10 (ms) | wall p90 (ms) | CPU median (ms) |",
        "|---|---|---|---|---|",
    ]
    for k, v in stages.items():
        lines.append(
            "| {} | {:.1f} | {:.1f} | {:.1f} | {:.1f} |".format(
                k, *_stats(v), _stats(stages_cpu[k])[0]
            )
        )
    lines.append(
        "| **total per stereo pair** | **{:.1f}** | {:.1f} | {:.1f} | **{:.1f}** |".format(
            *_stats(totals), c_med
        )
    )
    extra = [k for k in ("joint_fit",) if k in stages]
    if extra:
        wo = np.asarray(totals) - sum(np.asarray(stages[k]) for k in extra)
        wo_cpu = np.asarray(cpu) - sum(np.asarray(stages_cpu[k]) for k in extra)
        lines.append(
            "| total without {} | {:.1f} | {:.1f} | {:.1f} | {:.1f} |".format(
                " + ".join(extra), *_stats(wo), _stats(wo_cpu)[0]
            )
        )
    lines += [
        "",
        f"Target <= 100 ms per pair (median wall clock): {'met' if t_med <= 100 else 'NOT met'}"
        f" ({t_med:.1f} ms wall, {c_med:.1f} ms CPU). The two views' marker detections run in"
        " two threads (OpenCV releases the GIL), so wall clock can be below the CPU time; JAX"
        " and OpenCV may also use both cores inside one call. `joint_fit` (curvatures and"
        " bending planes from the joint chain fit, `StereoConfig.joint_fit`, default on) is"
        " the accuracy developer's stage (`jaxcr/stereo/chain_fit.py`); the row without it"
        " shows the rest of the pipeline.",
        "",
        "## Thinning, same run",
        "",
        f"{n_masks} robot masks (flood-filled, as the pipeline produces them);"
        f" pipeline crop shapes (both views padded to one bucket): {crop_shapes}.",
        "",
        "| implementation | median (ms) | p90 (ms) |",
        "|---|---|---|",
        "| jaxcr Zhang-Suen, pipeline call: both views' crops, one vmapped call | {:.2f} | {:.2f} |".format(
            *_stats(jx_pair)[::2]
        ),
        "| scikit-image skeletonize on the same two crops | {:.2f} | {:.2f} |".format(
            *_stats(sk_pair)[::2]
        ),
        f"| **ratio JAX / skimage (pipeline crops)** | **{_stats(jx_pair)[0] / _stats(sk_pair)[0]:.2f}** | |",
        "| jaxcr Zhang-Suen, one full {}x{} mask | {:.2f} | {:.2f} |".format(
            w, h, *_stats(jx_full)[::2]
        ),
        "| scikit-image skeletonize, one full mask | {:.2f} | {:.2f} |".format(
            *_stats(sk_full)[::2]
        ),
        f"| ratio JAX / skimage (full masks) | {_stats(jx_full)[0] / _stats(sk_full)[0]:.2f} | |",
        "| jaxcr Guo-Hall, one full mask | {:.2f} | {:.2f} |".format(*_stats(gh)[::2]),
        "| scikit-image thin (Guo-Hall), one full mask | {:.2f} | {:.2f} |".format(
            *_stats(skt)[::2]
        ),
        f"| ratio JAX Guo-Hall / skimage thin | {_stats(gh)[0] / _stats(skt)[0]:.2f} | |",
        "",
        f"Results: jaxcr Guo-Hall identical to `skimage.morphology.thin` on {gh_equal}/{n_masks}"
        f" masks. jaxcr Zhang-Suen (the paper's rule; identical to a per-pixel loop of the"
        f" paper in the tests) identical to `skimage.morphology.skeletonize` on"
        f" {zs_equal}/{n_masks} masks: skimage uses a different Zhang-Suen-based table"
        f" (see `jaxcr/stereo/thinning.py`); {np.mean(agree):.3f} of skimage's skeleton"
        f" pixels are also ours (mean), and every pixel of ours lies within"
        f" {max(dist):.2f} px of skimage's skeleton.",
    ]
    Path(args.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
