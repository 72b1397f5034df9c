"""The persistent compilation cache every command turns on (jaxcr.io.compile_cache, cli.main):
where it goes, the off switches, a bad switch value, an unwritable folder."""

import json
import os
import subprocess
import sys

import pytest

from jaxcr.errors import InputError
from jaxcr.io import compile_cache as cc

# a single-segment robot: `jaxcr fk` on it is the cheapest command that compiles something
SS = {"kind": "single_segment", "length": 0.04, "radius": 0.002, "n_points": 9}
_ENVS = ("JAXCR_COMPILE_CACHE", "JAXCR_CACHE_DIR", "JAXCR_JAX_CACHE", "XDG_CACHE_HOME")


@pytest.fixture
def clean_env(monkeypatch):
    for name in _ENVS:
        monkeypatch.delenv(name, raising=False)
    return monkeypatch


def test_folder_rules(clean_env, tmp_path):
    home = os.path.expanduser("~")
    assert cc.resolve_cache_dir() == os.path.join(home, ".cache", "jaxcr", "jax")
    clean_env.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cc.resolve_cache_dir() == str(tmp_path / "xdg" / "jaxcr" / "jax")
    clean_env.setenv("XDG_CACHE_HOME", "relative/ignored")  # XDG: relative paths are invalid
    assert cc.resolve_cache_dir() == os.path.join(home, ".cache", "jaxcr", "jax")
    clean_env.setenv("JAXCR_JAX_CACHE", str(tmp_path / "legacy"))
    assert cc.resolve_cache_dir() == str(tmp_path / "legacy")
    clean_env.setenv("JAXCR_CACHE_DIR", str(tmp_path / "mine"))  # wins over the older name
    assert cc.resolve_cache_dir() == str(tmp_path / "mine")
    assert cc.resolve_cache_dir(tmp_path / "arg") == str(tmp_path / "arg")
    clean_env.setenv("JAXCR_CACHE_DIR", "")
    assert cc.resolve_cache_dir() is None
    assert cc.resolve_cache_dir(False) is None


@pytest.mark.parametrize("value", ["0", "off", "False", " no "])
def test_switch_off(clean_env, value):
    clean_env.setenv("JAXCR_COMPILE_CACHE", value)
    assert cc.resolve_cache_dir() is None


@pytest.mark.parametrize("value", ["1", "on", "auto", ""])
def test_switch_on(clean_env, tmp_path, value):
    clean_env.setenv("JAXCR_COMPILE_CACHE", value)
    clean_env.setenv("JAXCR_CACHE_DIR", str(tmp_path))
    assert cc.resolve_cache_dir() == str(tmp_path)


def test_bad_switch_is_input_error(clean_env):
    clean_env.setenv("JAXCR_COMPILE_CACHE", "maybe")
    with pytest.raises(InputError, match="JAXCR_COMPILE_CACHE.*'maybe'"):
        cc.resolve_cache_dir()


def test_unwritable_folder_warns_once(clean_env, tmp_path, capsys, caplog):
    """The library logs the warning (logger jaxcr.io.compile_cache) and prints nothing; the
    CLI prints it on stderr (test_unwritable_cache_runs_on, below)."""
    blocker = tmp_path / "file"
    blocker.write_text("x")  # a folder below a regular file cannot be made, even by root
    bad = blocker / "cache"
    assert cc.enable_compile_cache(path=bad) is None
    assert cc.enable_compile_cache(path=bad) is None
    warned = [r for r in caplog.records if r.name == "jaxcr.io.compile_cache"]
    assert len(warned) == 1 and warned[0].levelname == "WARNING"
    assert str(bad) in warned[0].getMessage() and "warning" in warned[0].getMessage()
    assert capsys.readouterr().err == ""


# ------------------------------------------------------------------ the CLI, in new processes


def _fk(tmp_path, env_extra: dict, *flags: str) -> subprocess.CompletedProcess:
    (tmp_path / "ss.json").write_text(json.dumps(SS))
    (tmp_path / "q.csv").write_text("0.3,-2.0\n1.0,0.5\n")
    env = {k: v for k, v in os.environ.items() if k not in _ENVS}
    env.update(JAX_PLATFORMS="cpu", **env_extra)
    argv = [sys.executable, "-m", "jaxcr", *flags, "fk", str(tmp_path / "ss.json")]
    argv += [str(tmp_path / "q.csv"), "-o", str(tmp_path / "out")]
    return subprocess.run(argv, env=env, capture_output=True, text=True, timeout=900)


def _entries(folder) -> list[str]:
    return sorted(os.listdir(folder)) if os.path.isdir(folder) else []


def test_command_fills_cache(tmp_path):
    cache = tmp_path / "cache"
    p = _fk(tmp_path, {"JAXCR_CACHE_DIR": str(cache)})
    assert p.returncode == 0, p.stderr
    # JAX names entries <program>-<key>-cache; fk's compiled batch must be there: since K4 it
    # is the stored traced program (jit_forward_batch_rotvec_stored), kept in exported/ too
    names = _entries(cache)
    prog = "jit_forward_batch_rotvec_stored-"
    assert any(n.startswith(prog) and n.endswith("-cache") for n in names), names
    assert any(n.endswith(".jaxexport") for n in _entries(cache / "exported")), names


@pytest.mark.parametrize(
    "env_extra,flags", [({"JAXCR_COMPILE_CACHE": "0"}, ()), ({}, ("--no-compile-cache",))]
)
def test_off_writes_nothing(tmp_path, env_extra, flags):
    cache = tmp_path / "cache"
    p = _fk(tmp_path, {"JAXCR_CACHE_DIR": str(cache), **env_extra}, *flags)
    assert p.returncode == 0, p.stderr
    assert _entries(cache) == []


def test_bad_switch_exits_2_one_line(tmp_path, clean_env, capsys):
    """In this process (cli.main reads the switch on every call, before anything else; a new
    process would add a Python start and nothing to check)."""
    from jaxcr.cli import main

    (tmp_path / "ss.json").write_text(json.dumps(SS))
    (tmp_path / "q.csv").write_text("0.3,-2.0\n1.0,0.5\n")
    clean_env.setenv("JAXCR_COMPILE_CACHE", "maybe")
    clean_env.setenv("JAXCR_CACHE_DIR", str(tmp_path / "c"))
    argv = ["fk", str(tmp_path / "ss.json"), str(tmp_path / "q.csv"), "-o", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "JAXCR_COMPILE_CACHE" in lines[0], err
    assert not (tmp_path / "out").exists()


def test_unwritable_cache_runs_on(tmp_path):
    (tmp_path / "file").write_text("x")
    bad = tmp_path / "file" / "cache"
    p = _fk(tmp_path, {"JAXCR_CACHE_DIR": str(bad)})
    assert p.returncode == 0, p.stderr
    warnings = [ln for ln in p.stderr.splitlines() if "compilation cache" in ln]
    assert len(warnings) == 1 and str(bad) in warnings[0], p.stderr
    assert (tmp_path / "out" / "tips.csv").exists()
