"""Spread of tests/segmentation/test_refine.py::test_batch_vmap_matches_per_frame_quality over
x86-64 code-generation targets and render seeds (docs/decisions.md T5).

For each target (an ``XLA_FLAGS`` setting, one fresh process each: the flags are read when
XLA starts) and each render seed ``s``, the test's two frames (its TRUE_COEFFS, rendered with
seeds ``s`` and ``s + 1``; the test itself is ``s = 0``) are refined with the test's programs:
``refine_frame_jit`` per frame and ``refine_batch(..., mode="vmap")`` on the test's batch of
five (the two good frames, a NaN centreline, an all-background frame, a frame out of view).
One row per frame: the mask IoU to the truth of the nominal shape, the per-frame and the vmap
refinement, and of two deliberately broken vmap batches run by the same compiled program:

- ``iou_rolled``: every frame refined against the next frame's image (a frame axis mixed up);
- ``iou_1step``: one solver step per pyramid level (a lock-step loop that stops early);
- ``iou_steps_A_B`` (with ``--budgets A,B ...``): the vmap batch with A and B solver steps per
  level instead of the test's 30 and 15, i.e. a solve cut short by that much: how far a
  vmap mode that stopped early could go before the test notices.

    JAX_PLATFORMS=cpu PYTHONPATH=. python experiments/segmentation/vmap_target_spread.py \\
        --seeds 0 10 20 30 40 50 --out ROWS.jsonl
    python experiments/segmentation/vmap_target_spread.py --summary ROWS.jsonl

``--targets`` picks some of TARGETS. The persistent compilation cache is not used (a fresh
process compiles for its own target). Results: experiments/results/suite_time.md "Twelfth
pass".
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

# the suite's flags (tests/conftest.py FAST_COMPILE_FLAGS) without their ISA cap
SUITE = "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0"
#: name -> XLA_FLAGS. "suite_*": the tests' flags with the cap replaced ("suite_AVX" is what
#: the suite runs on any CPU with AVX, "suite_SSE4_2" on one without); "xla_*": XLA's defaults
#: (JAXCR_TESTS_XLA_DEFAULT=1, what users run) for a CPU of that ISA; "xla_native": this host
TARGETS = {
    "suite_SSE4_2": f"{SUITE} --xla_cpu_max_isa=SSE4_2",
    "suite_AVX": f"{SUITE} --xla_cpu_max_isa=AVX",
    "suite_AVX2": f"{SUITE} --xla_cpu_max_isa=AVX2",
    "suite_native": SUITE,
    "xla_SSE4_2": "--xla_cpu_max_isa=SSE4_2",
    "xla_AVX": "--xla_cpu_max_isa=AVX",
    "xla_AVX2": "--xla_cpu_max_isa=AVX2",
    "xla_native": "",
}


def run_one(target: str, seeds: list[int], budgets: list[str] = ()) -> list[dict]:
    """Rows for one target, in this process (XLA_FLAGS already set by the caller)."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from jaxcr.camera import project_xy
    from jaxcr.kinematics.cosserat import Centreline
    from jaxcr.segmentation.metrics import iou
    from jaxcr.segmentation.refine import refine_batch, refine_frame_jit
    from jaxcr.segmentation.shape import perturbed_centreline
    from tests.helpers import refine_scene as rs
    from tests.helpers.jitted import colour_mask
    from tests.helpers.tube_render import render_tube

    jax.config.update("jax_enable_compilation_cache", False)
    # test_refine.py's TRUE_COEFFS
    true_coeffs = [
        jnp.array([[0.35, -0.15, 0.05], [0.0, 0.0, 0.0]], jnp.float32),
        jnp.array([[-0.3, 0.1, 0.0], [0.0, 0.0, 0.0]], jnp.float32),
    ]
    base, cam, cfg = rs.base(), rs.camera(), rs.CFG
    one_step = dataclasses.replace(cfg, steps=(1,) * len(cfg.levels))  # same program (traced)
    nan_base = jax.tree.map(lambda x: x * jnp.nan, base)
    far = Centreline(base.s, base.p + jnp.array([5.0, 5.0, 0.0]), base.R, base.u, base.rho)
    bases = jax.tree.map(lambda *x: jnp.stack(x), base, base, nan_base, base, far)
    R = jnp.asarray(cam.R)

    def shape_errors(p, truth_p):
        """test_refine.test_recovers_known_delta_u's two centreline measures: the mean
        projected distance to the truth (px) and the mean in-image-plane 3-D error (m)."""
        u1, v1, _ = project_xy(cam, p)
        u2, v2, _ = project_xy(cam, truth_p)
        px = float(jnp.mean(jnp.hypot(u1 - u2, v1 - v2)))
        lateral = float(jnp.mean(jnp.linalg.norm(((p - truth_p) @ R.T)[:, :2], axis=1)))
        return px, lateral

    rows = []
    for s in seeds:
        frames, truths = [], []
        for k, c in enumerate(true_coeffs):
            truth = perturbed_centreline(base, c)
            img, mask = render_tube(truth, cam, s + k, (rs.W, rs.H))
            bg, ip = colour_mask(jnp.asarray(img))
            frames.append((ip, bg, mask))
            truths.append(truth.p)
        t0 = time.process_time()
        per = [refine_frame_jit(base, cam, ip, bg, cfg) for ip, bg, _ in frames]
        f0, f1 = frames
        imgs = jnp.stack([f0[0], f1[0], f0[0], jnp.zeros_like(f0[0]), f0[0]])
        bgs = jnp.stack([f0[1], f1[1], f0[1], jnp.ones_like(f0[1]), f0[1]])
        vm = refine_batch(bases, cam, imgs, bgs, cfg, mode="vmap")
        # broken: frames 0 and 1 swapped (each refined against the other's image)
        order = jnp.array([1, 0, 2, 3, 4])
        rolled = refine_batch(bases, cam, imgs[order], bgs[order], cfg, mode="vmap")
        early = refine_batch(bases, cam, imgs, bgs, one_step, mode="vmap")
        cut = {}
        for b in budgets:
            steps = tuple(int(x) for x in b.split(","))
            short = dataclasses.replace(cfg, steps=steps)
            cut[b] = refine_batch(bases, cam, imgs, bgs, short, mode="vmap")
        cpu = time.process_time() - t0
        for k, (r, (_, _, mask)) in enumerate(zip(per, frames, strict=True)):
            px_pf, lat_pf = shape_errors(r.centreline.p, truths[k])
            px_vm, lat_vm = shape_errors(vm.centreline.p[k], truths[k])
            _, lat_nom = shape_errors(base.p, truths[k])
            rows.append(
                dict(
                    target=target,
                    seed=s + k,
                    frame=k,
                    iou_nominal=float(iou(r.nominal_masks[0], mask)),
                    iou_per_frame=float(iou(r.masks[0], mask)),
                    iou_vmap=float(iou(vm.masks[0][k], mask)),
                    iou_vmap_to_per_frame=float(iou(vm.masks[0][k], r.masks[0])),
                    iou_rolled=float(iou(rolled.masks[0][k], mask)),
                    iou_1step=float(iou(early.masks[0][k], mask)),
                    energy_per_frame=float(r.energy.total),
                    energy_vmap=float(vm.energy.total[k]),
                    steps_per_frame=int(r.num_steps),
                    steps_vmap=int(vm.num_steps[k]),
                    ok_vmap=bool(vm.ok[k]),
                    px_per_frame=px_pf,
                    px_vmap=px_vm,
                    lateral_ratio_per_frame=lat_pf / lat_nom,
                    lateral_ratio_vmap=lat_vm / lat_nom,
                    failure=[int(x) for x in vm.failure],
                    cpu_s=cpu,
                    **{
                        f"iou_steps_{b.replace(',', '_')}": float(iou(o.masks[0][k], mask))
                        for b, o in cut.items()
                    },
                )
            )
    return rows


def summary(rows: list[dict]) -> None:
    import collections

    by = collections.defaultdict(list)
    for r in rows:
        by[r["target"]].append(r)
    print(
        "| target | frames | per-frame IoU | vmap IoU | per-frame - vmap (max) | vmap - nominal"
        " (min) | rolled - nominal (max) | 1 step - nominal (max) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    allr = []
    for t in TARGETS:
        rs_ = by.get(t)
        if not rs_:
            continue
        allr += rs_
        pf = [r["iou_per_frame"] for r in rs_]
        vm = [r["iou_vmap"] for r in rs_]
        gap = max(r["iou_per_frame"] - r["iou_vmap"] for r in rs_)
        gain = min(r["iou_vmap"] - r["iou_nominal"] for r in rs_)
        rol = max(r["iou_rolled"] - r["iou_nominal"] for r in rs_)
        one = max(r["iou_1step"] - r["iou_nominal"] for r in rs_)
        print(
            f"| {t} | {len(rs_)} | {min(pf):.3f}-{max(pf):.3f} | {min(vm):.3f}-{max(vm):.3f} "
            f"| {gap:.3f} | {gain:.3f} | {rol:.3f} | {one:.3f} |"
        )
    worst = max(allr, key=lambda r: r["iou_per_frame"] - r["iou_vmap"])
    print(f"largest gap: {worst}")
    print(f"nominal IoU: {min(r['iou_nominal'] for r in allr):.3f}-"
          f"{max(r['iou_nominal'] for r in allr):.3f}")  # fmt: skip
    print(f"vmap IoU, all: min {min(r['iou_vmap'] for r in allr):.3f}")
    print(f"rolled IoU, all: max {max(r['iou_rolled'] for r in allr):.3f}")
    print(f"1-step IoU, all: max {max(r['iou_1step'] for r in allr):.3f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--targets", nargs="+", choices=sorted(TARGETS), default=list(TARGETS))
    ap.add_argument("--budgets", nargs="*", default=[], metavar="A,B", help="steps per level")
    ap.add_argument("--out", help="JSON lines file (appended)")
    ap.add_argument("--summary", metavar="ROWS", help="print the table of a rows file")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # worker: this process's target
    a = ap.parse_args(argv)
    if a.summary:
        with open(a.summary) as f:
            summary([json.loads(line) for line in f if line.strip()])
        return 0
    if a.one:
        for row in run_one(a.one, a.seeds, a.budgets):
            print(json.dumps(row), flush=True)
        return 0
    for t in a.targets:
        env = dict(os.environ, XLA_FLAGS=TARGETS[t], JAX_PLATFORMS="cpu")
        cmd = [sys.executable, __file__, "--one", t, "--seeds", *map(str, a.seeds)]
        cmd += ["--budgets", *a.budgets] if a.budgets else []
        out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout
        if a.out:
            with open(a.out, "a") as f:
                f.write(out)
        sys.stdout.write(out)
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
