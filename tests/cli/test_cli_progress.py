"""Progress reporting policy (``jaxcr.progress``) and its use by the commands.

Unit tests of the policy (terminal test, ``JAXCR_PROGRESS`` override, plain-line schedule on a
fake clock), then commands run with stderr not a terminal (``fk`` as a subprocess writing to a
pipe, ``validate`` in this process with stderr captured): no carriage-return bar redraws, a few
plain lines instead; ``JAXCR_PROGRESS=1`` forces the bar.
``model-object``'s no-total progress is checked in-process with a stand-in for the pipeline
(the real one takes minutes).
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from jaxcr import progress as P
from jaxcr.errors import InputError

EXE = os.path.join(os.path.dirname(sys.executable), "jaxcr")


class _Stream(io.StringIO):
    def __init__(self, tty: bool):
        super().__init__()
        self._tty = tty

    def isatty(self) -> bool:
        return self._tty


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


# ---------------------------------------------------------------------------- the policy


@pytest.mark.parametrize(
    "env, tty, want",
    [
        ("", True, "bar"),
        ("", False, "lines"),
        ("auto", True, "bar"),
        (" AUTO ", False, "lines"),
        ("1", False, "bar"),
        ("on", False, "bar"),
        ("true", False, "bar"),
        ("0", True, "lines"),
        ("off", True, "lines"),
        ("no", True, "lines"),
    ],
)
def test_mode_policy(env, tty, want):
    assert P.mode(_Stream(tty), env=env) == want


def test_mode_reads_environment_and_real_tty(monkeypatch):
    master, slave = os.openpty()  # a real terminal device, independent of isatty stubs
    try:
        with open(slave, "w", closefd=False) as tty, open(os.devnull, "w") as null:
            monkeypatch.delenv(P.ENV, raising=False)
            assert P.mode(tty) == "bar" and P.mode(null) == "lines"
            monkeypatch.setenv(P.ENV, "0")
            assert P.mode(tty) == "lines"
            monkeypatch.setenv(P.ENV, "1")
            assert P.mode(null) == "bar"
    finally:
        os.close(master)
        os.close(slave)
    closed = io.StringIO()
    closed.close()
    assert P.mode(closed, env="") == "lines"  # isatty on a closed stream raises


def test_mode_rejects_other_values():
    with pytest.raises(InputError, match="JAXCR_PROGRESS.*'maybe'"):
        P.mode(_Stream(True), env="maybe")


def test_plain_lines_every_tenth_of_a_known_total():
    out, clock = io.StringIO(), _Clock()
    bar = P.PlainProgress(total=100, desc="seg", unit="frame", file=out, clock=clock)
    for _ in range(100):
        clock.t += 0.5
        bar.update(1)
    bar.close()
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    assert len(lines) == 10  # close adds nothing: 100/100 was the last line
    assert lines[0] == "seg: 10/100 frames (10 %), 5.0 s"
    assert lines[-1] == "seg: 100/100 frames (100 %), 50.0 s"
    # jumps of several tenths print one line; the total may be set late (validate does)
    out2 = io.StringIO()
    bar = P.PlainProgress(total=0, desc="v", unit="batch", file=out2, clock=_Clock())
    bar.total = 7
    bar.update(3)
    bar.update(4)
    assert out2.getvalue().splitlines() == ["v: 3/7 batches (42 %), 0.0 s", "v: 7/7 batches (100 %), 0.0 s"]  # fmt: skip


def test_plain_lines_unknown_total_every_n_and_after_silence():
    out, clock = io.StringIO(), _Clock()
    bar = P.PlainProgress(desc="model-object", unit="view", every=3, file=out, clock=clock)
    bar.set_postfix_str("route 1 (1/1): view 2 registered")
    for _ in range(7):
        bar.update(1)
    bar.close()
    bar.close()  # idempotent
    assert out.getvalue().splitlines() == [
        "model-object: 3 views, 0.0 s; route 1 (1/1): view 2 registered",
        "model-object: 6 views, 0.0 s; route 1 (1/1): view 2 registered",
        "model-object: 7 views, 0.0 s; route 1 (1/1): view 2 registered",
    ]
    # a slow loop still shows it is alive once MAX_SILENCE_S has passed
    out, clock = io.StringIO(), _Clock()
    bar = P.PlainProgress(total=1000, desc="x", unit="frame", file=out, clock=clock)
    clock.t = P.MAX_SILENCE_S - 1
    bar.update(1)
    assert out.getvalue() == ""
    clock.t = P.MAX_SILENCE_S + 65
    bar.update(1)
    assert out.getvalue() == "x: 2/1000 frames (0 %), 2 min 05 s\n"


def test_plain_refresh_prints_a_new_stage_once():
    out = io.StringIO()
    bar = P.PlainProgress(desc="m", unit="view", every=100, file=out, clock=_Clock())
    bar.update(1)
    bar.set_postfix_str("route a: view 1 registered")
    bar.refresh()
    bar.refresh()  # nothing new
    bar.set_postfix_str("registration done; evaluating")
    bar.refresh()
    bar.close()  # the count was printed already
    assert out.getvalue().splitlines() == [
        "m: 1 view, 0.0 s; route a: view 1 registered",
        "m: 1 view, 0.0 s; registration done; evaluating",
    ]


def test_plain_iteration_silent_and_progress_factory(monkeypatch):
    out = io.StringIO()
    items = list(P.PlainProgress(range(20), desc="it", unit="frame", file=out))
    assert items == list(range(20))
    assert len(out.getvalue().splitlines()) == 10  # total taken from len(range)
    quiet = io.StringIO()
    bar = P.PlainProgress(total=5, file=quiet, silent=True)
    bar.update(5)
    bar.close()
    assert quiet.getvalue() == ""
    monkeypatch.setattr(sys, "stderr", _Stream(False))
    monkeypatch.delenv(P.ENV, raising=False)
    assert isinstance(P.progress(total=3), P.PlainProgress)
    assert P.progress(total=3, enabled=False).silent
    monkeypatch.setenv(P.ENV, "1")
    from tqdm import tqdm

    bar = P.progress(total=3, desc="forced", mininterval=0)
    assert isinstance(bar, tqdm) and not bar.disable
    bar.update(3)
    bar.close()
    assert "\r" in sys.stderr.getvalue() and "forced" in sys.stderr.getvalue()
    assert isinstance(P.progress(total=3, enabled=False), P.PlainProgress)


# ---------------------------------------------------------------------------- commands


def _run(args, env_value=None, timeout=900):  # a hang guard, not a speed check
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env.pop(P.ENV, None)
    if env_value is not None:
        env[P.ENV] = env_value
    # bytes, decoded here: text=True would translate the very "\r" looked for into "\n"
    r = subprocess.run([EXE, *args], capture_output=True, timeout=timeout, env=env)
    return SimpleNamespace(
        returncode=r.returncode, stdout=r.stdout.decode(), stderr=r.stderr.decode()
    )


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from jaxcr.camera import Camera
    from jaxcr.io.dataset import DatasetWriter

    root = tmp_path_factory.mktemp("progress") / "ds"
    robot = {"kind": "single_segment", "length": 0.04, "radius": 0.002, "n_points": 9}
    cam = Camera.look_at((-0.15, 0.0, 0.02), (0.0, 0.0, 0.02), (0.0, -1.0, 0.0), 80.0, (32, 24))
    rng = np.random.default_rng(0)
    with DatasetWriter(root, "tiny", robot, {"main": cam}) as w:
        for k in range(20):
            w.add_frame(k, (0.1 * k, 0.0), {"main": rng.random((24, 32, 3), dtype=np.float32)})
    return root


def _main(args, monkeypatch, capsys, env_value=None):
    """``jaxcr ARGS`` in this process, stderr captured (not a terminal, as a pipe): the same
    policy as in a new process, without one's Python/JAX start-up (~2 s of CPU each);
    test_fk_redirected_plain_lines_forced_bar runs a real subprocess with a real pipe."""
    from jaxcr.cli import main

    monkeypatch.delenv(P.ENV, raising=False)
    if env_value is not None:
        monkeypatch.setenv(P.ENV, env_value)
    capsys.readouterr()
    code = main(args)
    out = capsys.readouterr()
    return SimpleNamespace(returncode=code, stdout=out.out, stderr=out.err)


def test_validate_redirected_plain_lines_forced_bar_and_bad_override(dataset, monkeypatch,
                                                                     capsys):  # fmt: skip
    def _run(args, env_value=None):
        return _main(args, monkeypatch, capsys, env_value)

    assert not sys.stderr.isatty()  # captured, as a pipe
    r = _run(["validate", str(dataset)])
    assert r.returncode == 0, r.stderr
    assert "\r" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("validate: ")]
    assert 2 <= len(lines) <= 11 and lines[-1].startswith("validate: 20/20 frames (100 %)")
    q = _run(["validate", "-q", str(dataset)])
    assert q.returncode == 0 and q.stderr == ""  # --quiet: no progress lines either
    f = _run(["validate", str(dataset)], env_value="1")
    assert f.returncode == 0 and "\r" in f.stderr and "validate:" in f.stderr
    b = _run(["validate", str(dataset)], env_value="sometimes")
    assert b.returncode == 2
    assert b.stderr.strip().splitlines() == [
        "jaxcr validate: error: environment variable JAXCR_PROGRESS: expected 0, 1 or auto, "
        "got 'sometimes'"
    ]


def test_fk_redirected_plain_lines_forced_bar(tmp_path, monkeypatch, capsys):
    (tmp_path / "ss.json").write_text(
        json.dumps({"kind": "single_segment", "length": 0.04, "radius": 0.002, "n_points": 9})
    )
    q = np.stack([np.linspace(0.1, 3.0, 12), np.linspace(-1.0, 1.0, 12)], axis=1)
    (tmp_path / "q.csv").write_text("\n".join(f"{float(a)!r},{float(b)!r}" for a, b in q))
    r = _run(["fk", str(tmp_path / "ss.json"), str(tmp_path / "q.csv"), "-o",
              str(tmp_path / "a"), "--chunk", "4"])  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "\r" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("fk: ")]
    assert [ln.split(",")[0] for ln in lines] == [
        "fk: 4/12 rows (33 %)",
        "fk: 8/12 rows (66 %)",
        "fk: 12/12 rows (100 %)",
    ]
    # the forced bar in this process (the redirected case above is the one that needs a real
    # pipe; a second child cost another Python/JAX start, ~3.5 s of CPU)
    f = _main(["fk", str(tmp_path / "ss.json"), str(tmp_path / "q.csv"), "-o",
               str(tmp_path / "b"), "--chunk", "4"], monkeypatch, capsys, env_value="1")  # fmt: skip
    assert f.returncode == 0 and "\r" in f.stderr and "12/12" in f.stderr


def _fake_build_model(n_views):
    from jaxcr.registration.pairwise import RegistrationFailed

    def build_model(sim, cfg, progress=None, seed=0):
        for r in sim.cfg["runs"]:
            log = SimpleNamespace(name=str(r["name"]), captures=[], status="")
            for _ in range(n_views):
                log.captures.append(object())
                progress(log, log.captures[-1])
        raise RegistrationFailed("stand-in pipeline stops here")

    return build_model


def test_model_object_views_done_and_stage_without_fake_total(tmp_path, monkeypatch, capsys):
    import jaxcr.registration.pipeline as pipeline
    from jaxcr.cli import main
    from jaxcr.synth.rgbd_tasks import generate_task, load_scene

    scene = generate_task(tmp_path / "scene", "2", seed=1, size=(32, 24))  # two routes
    monkeypatch.setattr(pipeline, "build_model", _fake_build_model(3))
    monkeypatch.delenv(P.ENV, raising=False)
    assert main(["model-object", str(scene), "-o", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("model-object: ")]
    max_steps = pipeline.PipelineConfig().max_steps
    last = load_scene(scene)["runs"][1]["name"]
    # a line every 5 views, then the count at close; no "/total": none is known
    assert [ln.split(",")[0] for ln in lines] == ["model-object: 5 views", "model-object: 6 views"]
    assert lines[-1].endswith(
        f"route {last} (2/2): view 3 registered (at most {max_steps} per route)"
    )
    monkeypatch.setenv(P.ENV, "1")
    assert main(["model-object", str(scene), "-o", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "\r" in err and "model-object: 6 views [" in err and "6view" not in err
