"""Forward-kinematics throughput of the concentric-tube model (TEST_CTR) against a scipy model.

The benchmark itself is :mod:`jaxcr.benchmarks.fk` (so that ``jaxcr bench fk`` runs from an
installed package); this script runs it, prints the Markdown table and writes
experiments/results/kinematics/bench_fk.md.

    python experiments/kinematics/bench_fk.py [--batch 1024] [--cold-batch 256] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import sys

from jaxcr.benchmarks.fk import markdown, run_fk_benchmark

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=1024, help="warm-start batch size")
    ap.add_argument("--cold-batch", type=int, default=256, help="cold-start batch size")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--n-reference", type=int, default=3, help="q timed with scipy")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--no-previous",
        action="store_true",
        help="skip the pre-issue-18 solvers (their cold path compiles for minutes)",
    )
    ap.add_argument(
        "-o", "--out", default=os.path.join(HERE, "..", "results", "kinematics", "bench_fk.md")
    )
    args = ap.parse_args(argv)
    res = run_fk_benchmark(
        args.batch, args.cold_batch, args.repeats, args.n_reference, args.seed,
        previous=not args.no_previous,
    )  # fmt: skip
    command = (
        f"python experiments/kinematics/bench_fk.py --batch {args.batch} "
        f"--cold-batch {args.cold_batch} --repeats {args.repeats}"
        + (" --no-previous" if args.no_previous else "")
    )
    text = markdown(res, command)
    print(text)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)  # "-o x.md": dirname is ""
    with open(args.out, "w") as fh:
        fh.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
