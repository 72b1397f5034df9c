"""Size and compile cost of ``jaxcr segment``'s nominal kinematics program
(``forward_batch``, the dataset's robot, a batch of 4 copies of the first frame's q): trace seconds, jaxpr equations
(nested jaxprs counted), and for XLA's default and the legacy loop emitter (docs/decisions.md
S22) the compile CPU seconds, optimised HLO instructions, while loops and fusions. The
persistent cache is off so that XLA really compiles.

Run: ``PYTHONPATH=$PWD python experiments/segmentation/fk_program_size.py DATASET``; prints.
"""

from __future__ import annotations

import argparse
import os
import re
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import ClosedJaxpr, Jaxpr

from jaxcr.io.dataset import load_dataset
from jaxcr.kinematics.batch import forward_batch

HLO_LINE = re.compile(r"\s+(ROOT )?%?[\w.\-]+ = ")


def count_equations(jaxpr) -> int:
    n = 0
    for eqn in jaxpr.eqns:
        n += 1
        for p in eqn.params.values():
            for sub in p if isinstance(p, (list, tuple)) else [p]:
                if isinstance(sub, ClosedJaxpr):
                    n += count_equations(sub.jaxpr)
                elif isinstance(sub, Jaxpr):
                    n += count_equations(sub)
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    a = ap.parse_args()
    jax.config.update("jax_enable_compilation_cache", False)
    ds = load_dataset(a.dataset)
    robot = ds.robot
    qs = jnp.asarray(np.stack([ds.frames[0].q] * 4), jnp.float32)
    print(f"{type(robot).__name__}, {robot.n_joints} joints, {robot.n_points} points, batch 4")
    t0, c0 = time.perf_counter(), time.process_time()
    jaxpr = jax.make_jaxpr(lambda q: forward_batch(robot, q))(qs)
    print(f"trace {time.perf_counter() - t0:.2f} s wall, {time.process_time() - c0:.2f} s CPU; "
          f"jaxpr equations {count_equations(jaxpr.jaxpr)}")  # fmt: skip
    for opts in ({}, {"xla_cpu_use_fusion_emitters": False}):
        lowered = jax.jit(lambda q: forward_batch(robot, q)).lower(qs)
        c0 = time.process_time()
        exe = lowered.compile(compiler_options=opts or None)
        cpu = time.process_time() - c0
        txt = exe.as_text()
        n_hlo = sum(1 for line in txt.splitlines() if HLO_LINE.match(line))
        n_fus = len(re.findall(r"\bfusion\(", txt))
        n_while = txt.count(" while(")
        print(f"{opts or 'default'}: compile {cpu:.2f} s CPU, optimised HLO instructions {n_hlo}, "
              f"while loops {n_while}, fusions {n_fus}")  # fmt: skip
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
