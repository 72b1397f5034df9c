"""Where the compile time of one ``jaxcr segment`` process goes (issue 18, compilation row).

Runs ``jaxcr segment DATASET -o OUT --overwrite --quiet --no-overlays [extra]`` in this process
and sums JAX's monitoring spans per kind: tracing to a jaxpr, lowering to MLIR, and the
backend compile (which, with the persistent cache filled, is the cache load), plus the
process's import time and wall time. Run it twice with the same ``JAXCR_CACHE_DIR`` to see what
a second process still pays.

Run: ``JAXCR_CACHE_DIR=/tmp/cc PYTHONPATH=$PWD python experiments/segmentation/compile_split.py
DATASET OUT [segment options]``; prints one JSON line.
"""

from __future__ import annotations

import time

T_START = time.perf_counter()

import json  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
from collections import defaultdict  # noqa: E402

import jax.monitoring as monitoring  # noqa: E402

EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "backend",
}


def main(argv: list[str]) -> int:
    spans: dict[str, float] = defaultdict(float)
    counts: dict[str, int] = defaultdict(int)

    def listener(event: str, start: float, end: float, **kwargs) -> None:
        if event in EVENTS:
            spans[EVENTS[event]] += end - start
            counts[EVENTS[event]] += 1

    monitoring.register_event_time_span_listener(listener)
    t_import = time.perf_counter()
    from jaxcr.cli import main as cli_main

    t_cli = time.perf_counter()
    dataset, out, *extra = argv
    rc = cli_main(
        ["segment", dataset, "-o", out, "--overwrite", "--quiet", "--no-overlays", *extra]
    )
    t_end = time.perf_counter()
    with open(os.path.join(out, "summary.json")) as fh:
        summary = json.load(fh)
    print(
        json.dumps(
            {
                "rc": rc,
                "import_jax_s": round(t_import - T_START, 2),
                "import_jaxcr_cli_s": round(t_cli - t_import, 2),
                "segment_call_s": round(t_end - t_cli, 2),
                "span_sums_s": {k: round(v, 2) for k, v in spans.items()},
                "span_counts": dict(counts),
                "summary_compile_s": summary.get("compile_s"),
                "summary_run_s": summary.get("run_s"),
                "median_time_s": summary.get("median_time_s"),
                "load_1min": round(os.getloadavg()[0], 2),
                "cache_dir": os.environ.get("JAXCR_CACHE_DIR"),
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
