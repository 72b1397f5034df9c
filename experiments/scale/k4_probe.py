"""Run one ``jaxcr`` command in this process and write where its compile time went (K4).

``python experiments/scale/k4_probe.py OUT.json -- COMMAND ARGS...`` is ``jaxcr COMMAND
ARGS...`` (the same ``jaxcr.cli.main``, imported from ``PYTHONPATH``) with jax.monitoring
listeners that sum the seconds of tracing (jaxpr), lowering (StableHLO) and XLA compilation
or executable loading (``backend_compile``), and count persistent-cache hits and misses and
backend compilations. OUT.json also gets the seconds to import ``jaxcr.cli`` and the exit
code. Used by ``second_process_k4.py``; the process's wall and CPU are measured by its parent.
"""

import json
import sys
import time

T0 = time.perf_counter()
EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
    "/jax/core/compile/backend_compile_duration": "backend_s",
}
COUNTS = {
    "/jax/compilation_cache/cache_hits": "hits",
    "/jax/compilation_cache/cache_misses": "misses",
}


def main() -> int:
    out_json, sep, *argv = sys.argv[1:]
    assert sep == "--", "usage: k4_probe.py OUT.json -- COMMAND ARGS..."
    from jax import monitoring

    tally = dict.fromkeys([*EVENTS.values(), *COUNTS.values(), "backend_n"], 0.0)

    def on_duration(event, duration, **kw):
        if event in EVENTS:
            tally[EVENTS[event]] += duration
            if EVENTS[event] == "backend_s":
                tally["backend_n"] += 1

    def on_event(event, **kw):
        if event in COUNTS:
            tally[COUNTS[event]] += 1

    monitoring.register_event_duration_secs_listener(on_duration)
    monitoring.register_event_listener(on_event)
    from jaxcr.cli import main as jaxcr_main

    t_import = time.perf_counter() - T0
    rc = 1
    try:
        rc = jaxcr_main(argv)
    except SystemExit as e:
        rc = e.code if isinstance(e.code, int) else 1
    finally:
        tally.update(import_s=t_import, main_s=time.perf_counter() - T0 - t_import, rc=rc)
        with open(out_json, "w") as fh:
            json.dump(tally, fh)
    return rc


if __name__ == "__main__":
    sys.exit(main())
