"""Device sharding (jaxcr.scale.devices): refine_batch, batched fk and the eigen batch query on
2 forced host devices give the single-device results bit for bit.

The reference is the single-device run of the same function in the same process
(``devices=1``). The flag that makes 2 host devices must be set before JAX starts, hence the
subprocess (tests/scale/_devices_child.py). Tolerance: zero. Each device runs the very same
per-frame program on its block of frames (nothing crosses devices, no reduction is split), so
there is no rounding difference to allow for; integer/bool outputs are compared exactly too.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

CHILD = Path(__file__).with_name("_devices_child.py")


def test_two_host_devices_equal_one_bit_for_bit():
    # the suite's own XLA flags (tests/conftest.py, decisions T1) kept, two host devices added
    flags = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu",
           "JAXCR_COMPILE_CACHE": "0"}  # fmt: skip
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    r = subprocess.run([sys.executable, str(CHILD)], env=env, capture_output=True, text=True,
                       timeout=900)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["devices"] == 2
    assert out["fk"] == 0.0
    assert out["eigen_query"] == 0.0
    assert out["refine"] == 0.0
    # the refinement did take steps (not a trivially equal all-skipped batch)
    assert any(s > 0 for s in out["refine_steps"])
