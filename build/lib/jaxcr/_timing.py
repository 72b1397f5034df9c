"""Wall-clock accounting that separates JAX compilation from execution.

:class:`CompileTimer` listens to JAX's monitoring time spans for tracing, lowering and backend
compilation (``/jax/core/compile/*``) while active, and reports the union of those spans (so
nested traces are not counted twice). ``wall - compile_s`` is then the execution time.
"""

from __future__ import annotations

import time

import jax.monitoring as monitoring

COMPILE_EVENTS = (
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/backend_compile_duration",
)


def _union_length(spans: list[tuple[float, float]]) -> float:
    total, end = 0.0, -float("inf")
    for a, b in sorted(spans):
        if b <= end:
            continue
        total += b - max(a, end)
        end = b
    return total


class CompileTimer:
    """Context manager: ``wall_s`` (elapsed) and ``compile_s`` (union of compile spans)."""

    def __init__(self):
        self.spans: list[tuple[float, float]] = []
        self.wall_s = 0.0

    def _listener(self, event: str, start: float, end: float, **kwargs) -> None:
        if event in COMPILE_EVENTS:
            self.spans.append((start, end))

    def __enter__(self) -> CompileTimer:
        monitoring.register_event_time_span_listener(self._listener)
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        self.wall_s = time.perf_counter() - self._t0
        monitoring.unregister_event_time_span_listener(self._listener)

    @property
    def compile_s(self) -> float:
        return (
            min(_union_length(self.spans), self.wall_s)
            if self.wall_s
            else _union_length(self.spans)
        )

    @property
    def run_s(self) -> float:
        return max(self.wall_s - self.compile_s, 0.0)
