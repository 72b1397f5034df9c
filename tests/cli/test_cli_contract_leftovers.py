"""Issue 17 leftovers: ``evaluate -o`` claims and locks its report folder; SIGTERM is handled
like Ctrl-C (exit 143, lock released, nothing that looks complete, the rerun starts at once);
``model-object`` writes report.md atomically. Each test failed before its fix.

(``--seed`` beyond 32 bits is one line and exit 2 on every command with ``--seed``:
``tests/cli/test_cli_contract_limits.py::test_seed_ceiling`` and the parametrised test below.)
"""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import textwrap
import time

import pytest

from jaxcr.cli import main
from jaxcr.io import outdir
from tests.cli.test_cli_contract_batches import _fake_run
from tests.helpers.datasets import make_dataset


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


@pytest.fixture
def finished_run(tmp_path):
    root = make_dataset(tmp_path / "d", n_frames=2)
    out = tmp_path / "run"
    _fake_run(root, out, [{"frame": "000000", "ok": True}, {"frame": "000001", "ok": True}])
    return out


def test_evaluate_report_folder_is_new_empty_or_an_earlier_report(finished_run, tmp_path, capsys):
    """`evaluate -o D` wrote table2.md/per_frame.csv into any folder (a user's, a dataset,
    another command's output) and took no lock."""
    user = tmp_path / "notes"
    user.mkdir()
    (user / "table.csv").write_text("the user's table")
    assert main(["evaluate", str(finished_run), "-o", str(user), "--no-plot"]) == 2
    assert "not written by jaxcr evaluate" in _one_line(capsys)
    assert sorted(p.name for p in user.iterdir()) == ["table.csv"]  # untouched, no lock left
    # another command's output folder (the segment run itself is allowed only as the default)
    other = tmp_path / "fk_out"
    outdir.release(outdir.claim(other, "fk"))
    assert main(["evaluate", str(finished_run), "-o", str(other), "--no-plot"]) == 2
    assert "holds the output of jaxcr fk" in _one_line(capsys)
    # a new folder, then the same folder again (an earlier evaluate report is replaced)
    rep = tmp_path / "report"
    for _ in range(2):
        assert main(["evaluate", str(finished_run), "-o", str(rep), "--no-plot"]) == 0
        assert outdir.owner(rep) == "evaluate" and (rep / "table2.md").exists()
        assert not (rep / outdir.LOCK_FILE).exists()
    capsys.readouterr()
    # the default report folder is the run's own (owned by segment): still written there
    assert main(["evaluate", str(finished_run), "--no-plot"]) == 0
    assert (finished_run / "table2.md").exists()


def test_evaluate_report_folder_is_locked_while_another_process_holds_it(
    finished_run, tmp_path, capsys
):
    rep = tmp_path / "report"
    assert main(["evaluate", str(finished_run), "-o", str(rep), "--no-plot"]) == 0
    before = (rep / "table2.md").read_bytes()
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        info = {**outdir.lock_info("evaluate"), "pid": holder.pid,
                "pid_start": outdir._pid_start(holder.pid)}  # fmt: skip
        (rep / outdir.LOCK_FILE).write_text(json.dumps(info))
        capsys.readouterr()
        assert main(["evaluate", str(finished_run), "-o", str(rep), "--no-plot"]) == 2
        line = _one_line(capsys)
        assert "in use by" in line and f"pid {holder.pid} on {socket.gethostname()}" in line
        assert (rep / "table2.md").read_bytes() == before
    finally:
        holder.kill()
        holder.wait()


# The command runs in a child process; its report step announces itself (a marker file) and
# then waits, so the parent sends SIGTERM while the report folder is claimed and locked and
# nothing of the report is written yet.
_CHILD = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    import jaxcr.cli.evaluate as ev

    def slow_report(rows, infos, report_dir, *a, **k):
        Path(sys.argv[1]).write_text("reporting")
        time.sleep(120)

    ev.write_report = slow_report
    from jaxcr.cli import main
    sys.exit(main(sys.argv[2:]))
    """
)


def test_sigterm_exits_143_releases_the_lock_and_the_rerun_starts_at_once(
    finished_run, tmp_path, capsys
):
    """SIGTERM (kill, a scheduler, a container stop) ended the process at once with the
    default action: exit -15, the output folder's lock left behind (the next run reported a
    stale lock, or refused while the pid was reused)."""
    rep, marker = tmp_path / "report", tmp_path / "marker"
    argv = ["evaluate", str(finished_run), "-o", str(rep), "--no-plot"]
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(marker), *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    deadline = time.monotonic() + 300
    while not marker.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert (rep / outdir.LOCK_FILE).exists()  # claimed and locked while it runs
    proc.send_signal(signal.SIGTERM)
    try:
        _, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        pytest.fail(f"SIGTERM did not end the run: {err[-500:]}")
    assert proc.returncode == 143, err
    assert err.strip().splitlines()[-1] == "jaxcr evaluate: terminated"
    assert "Traceback" not in err
    assert not (rep / outdir.LOCK_FILE).exists()  # released on the way out
    assert not (rep / "table2.md").exists()  # nothing that looks like a report
    capsys.readouterr()
    assert main(argv) == 0
    assert "stale lock" not in capsys.readouterr().err
    assert (rep / "table2.md").exists()


_MODEL_OBJECT_CHILD = textwrap.dedent(
    """
    import resource, signal, sys
    import jaxcr.registration.pipeline as pipeline
    from jaxcr.registration.pairwise import RegistrationFailed

    def fail(*a, **k):
        raise RegistrationFailed("the ring did not close " + "x" * 4000)

    pipeline.build_model = fail
    # a file-size ceiling stands for a full disk in the middle of the report: writes past
    # 2 KiB fail with EFBIG (SIGXFSZ ignored, so the write returns the error)
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (2048, 2048))
    from jaxcr.cli import main
    sys.exit(main(sys.argv[1:]))
    """
)


def test_model_object_report_is_written_atomically(tmp_path):
    """report.md was written in place (Path.write_text): a write cut short (a full disk, a
    kill) left a truncated report.md that reads as the run's report."""
    from jaxcr.synth.rgbd_tasks import generate_task

    scene = generate_task(tmp_path / "scene", "1", 0, (64, 48))
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-c", _MODEL_OBJECT_CHILD, "model-object", str(scene),
                           "-o", str(out)], capture_output=True, text=True, timeout=600)  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "report.md" in proc.stderr.strip().splitlines()[-1]  # the one line names the file
    assert not (out / "report.md").exists()
    assert not [p.name for p in out.iterdir() if p.name.endswith(".tmp")]


@pytest.mark.parametrize("argv", [
    ["synth", "-o", "X"], ["segment", "D", "-o", "X"], ["demo", "-o", "X"], ["bench", "fk"],
    ["manifold", "train", "D", "-o", "X"], ["manifold", "synth", "-o", "X"],
    ["model-object", "synth", "-o", "X"], ["motion", "synth", "-o", "X"],
    ["stereo", "synth", "-o", "X"],
])  # fmt: skip
@pytest.mark.parametrize("seed", [str(2**32), "2^32", "-1"])
def test_every_seed_option_refuses_out_of_range_seeds_with_one_line(argv, seed, capsys):
    """Every command with --seed: one line naming the option, exit 2, before any work."""
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--seed", seed])
    assert exc.value.code == 2
    line = _one_line(capsys)
    assert "--seed: expected a non-negative integer" in line and "see 'jaxcr" in line
