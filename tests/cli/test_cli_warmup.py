"""`jaxcr warmup`: it takes segment's options and builds segment's config; with the cache off it
refuses (exit 2); after it, `jaxcr segment` in a new process compiles (almost) nothing."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest

from jaxcr.cli import build_parser, main, segment
from tests.cli.test_cli_segment import make_dataset  # the tiny 96x72 dataset drawn with OpenCV

SHAPE_OPTS = ["--camera", "main", "--levels", "2", "--max-steps", "4", "--basis", "3",
              "--batch-size", "2", "--background", "none", "--mu-out", "global",
              "--no-camera-correction", "--warm-start"]  # fmt: skip
#: the options of the warmup/segment pair below: the smallest refinement (one pyramid level, two
#: coefficients, no camera correction), since this test compiles everything in a cache of its
#: own (the run's cache cannot serve it: a fresh cache is what it tests). segment still runs
#: all its kinds of programs: refinement, covariance (uncertainty on), FK, background, overlays
WARMUP = ["--levels", "1", "--max-steps", "4", "--basis", "2", "--no-camera-correction",
          "--batch-size", "2", "--quiet"]  # fmt: skip


def test_same_options_same_config():
    parser = build_parser()
    w = parser.parse_args(["warmup", "DS", *SHAPE_OPTS])
    s = parser.parse_args(["segment", "DS", "-o", "OUT", *SHAPE_OPTS])
    assert segment.refine_config(w) == segment.refine_config(s)
    for name in ("camera", "batch_size", "background", "warm_start", "no_overlays"):
        assert getattr(w, name) == getattr(s, name)
    for name in ("out", "resume", "overwrite", "limit", "retry_failed"):  # output-only
        assert not hasattr(w, name)


def test_cache_off_exits_2(tmp_path, capsys):
    assert main(["--no-compile-cache", "warmup", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "compilation cache is off" in err[0]


def _cache_entries(folder) -> set[str]:
    """Every entry of the persistent compilation cache: JAX's compiled executables
    (``jit_<name>-<key>-cache``) and jaxcr's stored traced programs (``exported/``), by
    relative path; JAX's LRU access-time files (``-atime``) are bookkeeping, not programs."""
    return {
        p.relative_to(folder).as_posix()
        for p in folder.rglob("*")
        if p.is_file() and not p.name.endswith("-atime")
    }


@pytest.mark.slow
def test_segment_after_warmup_compiles_little(tmp_path):
    """After ``jaxcr warmup``, ``jaxcr segment`` with the same options in a new process adds
    no entry to the compilation cache: every program it runs (the refinement, nominal FK,
    background, overlays and the small eager ops) was compiled by warmup and is loaded.
    Counted, not timed: every XLA compilation is stored (min compile time 0 s and min
    entry size 0 bytes, jaxcr.io.compile_cache), so a program segment compiled itself
    would appear as a new file; the set of programs depends on shapes and options only,
    not on the machine's load (seconds did: the earlier check c_warm < 0.5 c_warmup
    failed under load)."""
    ds = make_dataset(tmp_path / "ds")
    cache = tmp_path / "cache"
    env = dict(os.environ, JAX_PLATFORMS="cpu", JAXCR_CACHE_DIR=str(cache))
    env.pop("JAXCR_COMPILE_CACHE", None)

    def jaxcr(*argv):
        p = subprocess.run([sys.executable, "-m", "jaxcr", *argv], env=env, text=True,
                           capture_output=True, timeout=1800)  # fmt: skip
        assert p.returncode in (0, 1), p.stderr  # 1: the dataset's bad frames
        return p

    w = jaxcr("warmup", str(ds), *WARMUP)
    n_compiled = int(re.search(r"jaxcr warmup: (\d+) programs compiled", w.stdout)[1])
    after_warmup = _cache_entries(cache)
    # not vacuous: warmup compiled and stored the stored traced programs segment calls
    # through jaxcr.io.exported.cached_call -- the refinement batch, the nominal forward
    # kinematics and the covariance batch -- and at least one entry per program it reported
    assert n_compiled >= 2 and len(after_warmup) >= n_compiled, (n_compiled, after_warmup)
    traced = {e.split("/")[1].rsplit("-", 1)[0] for e in after_warmup if e.startswith("exported/")}
    assert {"_refine_batch_jit", "forward_batch", "_batch_jit"} <= traced, after_warmup
    warm = tmp_path / "warm"
    jaxcr("segment", str(ds), "-o", str(warm), *WARMUP)
    summary = json.loads((warm / "summary.json").read_text())
    assert summary["ok"] >= 1  # it did refine frames (the programs ran, from the cache)
    new = sorted(_cache_entries(cache) - after_warmup)
    # measured here: none (12 programs compiled by warmup; 0 new entries after segment)
    assert new == [], f"segment compiled programs warmup did not: {new}"
