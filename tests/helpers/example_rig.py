"""docs/make_example_rig.py (the tutorial's rig generator, a script outside the package) as a
module, loaded once per process: its make_rig and its ROBOT."""

from __future__ import annotations

import functools
import importlib.util
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "docs" / "make_example_rig.py"


@functools.cache
def load_example_rig():
    spec = importlib.util.spec_from_file_location("make_example_rig", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
