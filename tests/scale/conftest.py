"""One local Ray instance per test process, shared by every test that runs commands with
``--executor ray`` in-process (a Ray start costs seconds: it is paid once, not per test)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def ray_instance():
    """A private local Ray instance with 2 CPUs (two worker actors), started in this process;
    :func:`jaxcr.scale.executor.ray_init` then reuses it. The actors inherit this process's
    environment, so they read and write the run's compilation cache (tests/conftest.py)."""
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install -e '.[ray]')")
    started = not ray.is_initialized()
    if started:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
                 configure_logging=False)  # fmt: skip
    yield ray
    if started:
        ray.shutdown()
