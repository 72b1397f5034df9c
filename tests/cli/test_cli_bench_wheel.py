"""``jaxcr bench`` from a wheel installed outside the checkout (issue 15: bench.py used to load
experiments/*.py by repository path, which an installed package does not have)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
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
    where = _run([sys.executable, "-c", "import jaxcr; print(jaxcr.__file__)"], cwd=cwd, env=env)
    assert where.returncode == 0, where.stderr
    assert Path(where.stdout.strip()).resolve().is_relative_to(site.resolve())

    h = _run([sys.executable, "-m", "jaxcr", "bench", "--help"], cwd=cwd, env=env)
    assert h.returncode == 0 and "segment" in h.stdout and "fk" in h.stdout, h.stderr

    out = cwd / "fk.md"
    # --batch 4: the benchmark's cold program (TEST_CTR, 4 rows, the model an argument) is
    # examples/kinematics_projection.py's, which tests/core/test_examples.py compiles earlier
    # in the run (tests/conftest.py LONGEST_FIRST), so this process loads it from the run's
    # compilation cache (measured: its compile 14.1 -> 2.7 s of CPU, a load from the cache)
    code = ("import sys, runpy, jaxcr; print('JAXCR', jaxcr.__file__); "
            "sys.argv = ['jaxcr', 'bench', 'fk', '--batch', '4', '--repeats', '1', '-o', 'fk.md']; "
            "runpy.run_module('jaxcr', run_name='__main__')")  # fmt: skip
    r = _run([sys.executable, "-c", code], cwd=cwd, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    imported = next(ln for ln in r.stdout.splitlines() if ln.startswith("JAXCR "))[6:]
    assert Path(imported).resolve().is_relative_to(site.resolve())
    text = out.read_text()
    assert "jaxcr.benchmarks.fk:run_fk_benchmark" in text and "median per q" in text


@pytest.mark.parametrize(
    "text, expected",
    [("0-9", list(range(10))), ("3,5", [3, 5]), ("0-2,7,10-11", [0, 1, 2, 7, 10, 11]), ("4", [4])],
)
def test_parse_seeds_matches_written_out_lists(text, expected):
    from jaxcr.benchmarks import parse_seeds

    assert parse_seeds(text) == expected
