"""Compile CPU against run CPU per program of ``jaxcr segment``, for XLA:CPU compile options
(issue 18, compilation row; docs/decisions.md S22).

Runs ``jaxcr segment DATASET`` in this process with the persistent cache off, capturing the
arguments of every program the driver calls through ``jaxcr.io.exported.cached_call`` (the
nominal kinematics ``forward_batch``, the refinement ``_refine_batch_jit``, the covariance
``_batch_jit`` with ``--uncertainty``). Then, for each program and each variant of compiler
options, interleaved ROUNDS times: the process CPU seconds of XLA's compile
(``jax.jit(f, compiler_options=...).lower(...).compile()``, a new trace each time so nothing is
reused), and the CPU and wall seconds of one call (median of CALLS calls); and the largest
difference of every output leaf to the default options' outputs.

Run (from the repository root)::

    PYTHONPATH=$PWD python experiments/segmentation/compile_options_programs.py DATASET \
        [--rounds 2] [--calls 3] [--name compile_options_programs] \
        [--variant 'LABEL=OPTION:VALUE,...' ...] [--only NAME ...] [-- segment options]

``--variant`` replaces the default variants (``default``, always measured, plus those given;
values are parsed as JSON, else kept as strings); ``--only`` keeps the programs whose name
contains one of the given strings.

Writes experiments/results/segmentation/NAME.md and .json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "experiments" / "results" / "segmentation"
VARIANTS = {
    "default": {},
    "legacy emitter": {"xla_cpu_use_fusion_emitters": False},
}


def _value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def capture(dataset: str, extra: list[str]) -> dict:
    """{program name: (fn, args)} of the first call of each program in a segment run."""
    import jaxcr.segmentation.batch as batch
    from jaxcr.cli import main as cli_main

    seen: dict = {}

    def recorder(fn, *args, **kw):
        seen.setdefault(fn.__qualname__ if hasattr(fn, "__qualname__") else repr(fn), (fn, args))
        return fn(*args)

    batch.cached_call = recorder
    with tempfile.TemporaryDirectory() as tmp:
        cli_main(["--no-compile-cache", "segment", dataset, "-o", tmp, "--overwrite", "--quiet",
                  "--no-overlays", *extra])  # fmt: skip
    return seen


def flat_program(fn, args):
    import equinox as eqx
    import jax

    dyn, static = eqx.partition(args, eqx.is_array)
    leaves, in_tree = jax.tree_util.tree_flatten(dyn)

    def make():
        def flat(*lv):
            a = eqx.combine(jax.tree_util.tree_unflatten(in_tree, lv), static)
            return jax.tree_util.tree_leaves(fn(*a))

        return flat

    return make, leaves


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--calls", type=int, default=3)
    ap.add_argument("--name", default="compile_options_programs")
    ap.add_argument("--variant", action="append", default=[])
    ap.add_argument("--only", action="append", default=[])
    ap.add_argument("extra", nargs="*")
    a = ap.parse_args()
    if a.variant:
        VARIANTS.clear()
        VARIANTS["default"] = {}
        for v in a.variant:
            label, _, opts = v.partition("=")
            VARIANTS[label] = {k: _value(x) for k, _, x in (o.partition(":")
                                                            for o in opts.split(","))}  # fmt: skip
    import jax
    import numpy as np

    jax.config.update("jax_enable_compilation_cache", False)
    programs = capture(a.dataset, a.extra)
    res: dict = {"command": " ".join(["python", *sys.argv]), "programs": {}}
    for name, (fn, args) in programs.items():
        if a.only and not any(o in name for o in a.only):
            continue
        make, leaves = flat_program(fn, args)
        rows: dict = {v: {"compile_cpu": [], "compile_wall": [], "call_cpu": [], "call_wall": [], "load": []}
                      for v in VARIANTS}  # fmt: skip
        ref = None
        for _ in range(a.rounds):
            for v, opts in VARIANTS.items():
                rows[v]["load"].append(os.getloadavg()[0])
                lowered = jax.jit(make(), compiler_options=opts or None).lower(*leaves)
                c0, t0 = time.process_time(), time.perf_counter()
                exe = lowered.compile()
                rows[v]["compile_cpu"].append(time.process_time() - c0)
                rows[v]["compile_wall"].append(time.perf_counter() - t0)
                out = jax.block_until_ready(exe(*leaves))
                for _ in range(a.calls):
                    c0, t0 = time.process_time(), time.perf_counter()
                    out = jax.block_until_ready(exe(*leaves))
                    rows[v]["call_cpu"].append(time.process_time() - c0)
                    rows[v]["call_wall"].append(time.perf_counter() - t0)
                out = [np.asarray(x) for x in out]
                if ref is None:
                    ref = out
                diff = 0.0
                for x, y in zip(out, ref, strict=True):
                    if x.dtype == bool:
                        diff = max(diff, float(np.sum(x != y)))
                    elif np.issubdtype(x.dtype, np.number):
                        d = np.abs(x.astype(float) - y.astype(float))
                        diff = max(diff, float(np.nanmax(d)) if d.size else 0.0)
                rows[v]["max_diff_to_default"] = diff
                print(name, v, {k: vv[-1] if isinstance(vv, list) else vv
                                for k, vv in rows[v].items()}, flush=True)  # fmt: skip
        res["programs"][name] = rows
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{a.name}.json").write_text(json.dumps(res, indent=1) + "\n")
    lines = [
        "# XLA:CPU compile options per program of `jaxcr segment`",
        "",
        f"Reproduce: `PYTHONPATH=$PWD {res['command']}` (2-core CPU shared with other jobs; "
        f"variants interleaved, {a.rounds} round(s); medians; one call = the whole batch).",
        "",
        "| program | options | compile CPU s | compile wall s | call CPU ms | call wall ms | max diff to default "
        "(bool: pixels) | loads |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, rows in res["programs"].items():
        for v, r in rows.items():
            lines.append(
                f"| `{name}` | {v} `{VARIANTS[v]}` | {statistics.median(r['compile_cpu']):.2f} | "
                f"{statistics.median(r['compile_wall']):.2f} | "
                f"{1000 * statistics.median(r['call_cpu']):.1f} | "
                f"{1000 * statistics.median(r['call_wall']):.1f} | {r['max_diff_to_default']:.3g} "
                f"| {', '.join(f'{x:.1f}' for x in r['load'])} |"
            )
    (RESULTS / f"{a.name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
