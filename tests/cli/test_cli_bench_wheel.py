"""``jaxcr bench`` from a wheel installed outside the checkout (issue 15: bench.py used to load
experiments/*.py by repository path, which an installed package does not have)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _run(cmd, **kw):
    return subprocess.run(cmd, capture_output=True, text=True, timeout=900, **kw)


@pytest.mark.slow  # a wheel build (~20 s) plus one compile of the CTR forward model (~20-60 s)
def test_bench_runs_from_an_installed_wheel(tmp_path):
    # build from a copy, so setuptools' build/ and *.egg-info never land in the checkout
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    shutil.copytree(ROOT / "jaxcr", src / "jaxcr", ignore=shutil.ignore_patterns("__pycache__"))
    wheels = tmp_path / "wheels"
    build = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-w", str(wheels), str(src)])
    if build.returncode != 0:  # no index reachable for the isolated build env: use this venv's
        build = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                      "-w", str(wheels), str(src)])  # fmt: skip
    assert build.returncode == 0, build.stderr[-2000:]
    (wheel,) = wheels.glob("jaxcr-*.whl")
    site = tmp_path / "site"
    inst = _run([sys.executable, "-m", "pip", "install", "--no-deps", "--target", str(site),
                 str(wheel)])  # fmt: skip
    assert inst.returncode == 0, inst.stderr[-2000:]
    assert (site / "jaxcr" / "benchmarks" / "fk.py").exists()

    cwd = tmp_path / "elsewhere"  # outside the checkout: neither it nor its parents hold jaxcr
    cwd.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}
    out = cwd / "fk.md"
    # One process (a Python + JAX start is seconds of CPU; this used to take three): which
    # jaxcr it imports, then `python -m jaxcr bench --help` and `python -m jaxcr bench fk ...`
    # run as jaxcr/__main__.py (runpy), the module `python -m jaxcr` runs.
    # --batch 4: the benchmark's cold program (TEST_CTR, 4 rows, the model an argument) is
    # examples/kinematics_projection.py's, which tests/core/test_examples.py compiles earlier
    # in the run (tests/conftest.py LONGEST_FIRST), so this process loads it from the run's
    # compilation cache (measured: its compile 14.1 -> 2.7 s of CPU, a load from the cache)
    code = textwrap.dedent("""
        import contextlib, io, runpy, sys
        import jaxcr
        print("JAXCR", jaxcr.__file__)
        def as_main(*argv):
            sys.argv = ["jaxcr", *argv]
            try:
                runpy.run_module("jaxcr", run_name="__main__")
            except SystemExit as e:
                return e.code
        text = io.StringIO()
        with contextlib.redirect_stdout(text):
            code = as_main("bench", "--help")
        print("HELP", code, repr(text.getvalue()))
        sys.exit(as_main("bench", "fk", "--batch", "4", "--repeats", "1", "-o", "fk.md"))
    """)
    r = _run([sys.executable, "-c", code], cwd=cwd, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    imported = next(ln for ln in r.stdout.splitlines() if ln.startswith("JAXCR "))[6:]
    assert Path(imported).resolve().is_relative_to(site.resolve())
    h = next(ln for ln in r.stdout.splitlines() if ln.startswith("HELP "))[5:]
    code, _, text = h.partition(" ")
    assert code == "0" and "segment" in text and "fk" in text, h
    text = out.read_text()
    assert "jaxcr.benchmarks.fk:run_fk_benchmark" in text and "median per q" in text


@pytest.mark.parametrize(
    "text, expected",
    [("0-9", list(range(10))), ("3,5", [3, 5]), ("0-2,7,10-11", [0, 1, 2, 7, 10, 11]), ("4", [4])],
)
def test_parse_seeds_matches_written_out_lists(text, expected):
    from jaxcr.benchmarks import parse_seeds

    assert parse_seeds(text) == expected
