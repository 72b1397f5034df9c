"""Benchmark: kinematic-prior refinement per 640x480 frame against a numpy/scipy reference.

The benchmark itself is :mod:`jaxcr.benchmarks.segment` (so that ``jaxcr bench segment`` runs
from an installed package); this script runs it and writes
``experiments/results/segmentation/bench_segment.md`` (+ .json).

    python experiments/segmentation/bench_segment.py [--frames 8] [--repeats 5] [--ref-frames 2]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from jaxcr.benchmarks.segment import (  # noqa: F401  (make_scene: refine_convergence_diag.py)
    make_scene,
    run_segment_benchmark,
    write_report,
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--ref-frames", type=int, default=2)
    ap.add_argument(
        "-o", "--out", default=str(Path(__file__).parent.parent / "results" / "segmentation")
    )
    a = ap.parse_args(argv)
    res = run_segment_benchmark(a.frames, a.repeats, a.ref_frames)
    path = write_report(res, Path(a.out))
    print(path.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
