"""Bad scale-out input is one line on stderr and exit 2 under every executor, before any
work (no compile, no Ray started): the reference is the CLI contract of every command (one
line naming the field, exit 2)."""

from __future__ import annotations

import pytest

from jaxcr.cli import main
from tests.helpers.datasets import make_dataset


@pytest.fixture(scope="module")
def ds(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("scale_cli") / "ds", n_frames=2)


@pytest.mark.parametrize(
    "extra, field",
    [
        (["--shard", "2/2"], "shard"),
        (["--shard", "x"], "shard"),
        (["--executor", "ray", "--chunk", "0"], "chunk"),
        (["--executor", "ray", "--workers", "0"], "workers"),
        (["--address", "auto"], "address"),  # needs --executor ray
        (["--workers", "2"], "workers"),
        (["--executor", "ray", "--warm-start"], "warm-start"),
    ],
)
def test_bad_scale_flags_are_one_line_exit_2(ds, tmp_path, capsys, extra, field):
    out = tmp_path / "out"
    assert main(["segment", str(ds), "-o", str(out), "--quiet", *extra]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("jaxcr segment: error:"), err
    assert field in err[0]
    assert not (out / "results.jsonl").exists()  # refused before any work


@pytest.mark.parametrize("executor", ["local", "ray"])
def test_missing_dataset_is_one_line_under_every_executor(tmp_path, capsys, executor):
    code = main(["segment", str(tmp_path / "nope"), "-o", str(tmp_path / "o"),
                 "--executor", executor])  # fmt: skip
    assert code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert err == [f"jaxcr segment: error: {tmp_path / 'nope'}: dataset not found"]


def test_stereo_bad_shard_is_one_line(tmp_path, capsys):
    assert main(["stereo", str(tmp_path), "-o", str(tmp_path / "o"), "--shard", "1/1"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("jaxcr stereo: error:") and "shard" in err[0]


@pytest.mark.parametrize("executor", ["local", "ray"])
@pytest.mark.parametrize(
    "kind, extra, field",
    [
        ("fk_bad_q", [], "line 2"),  # a non-numeric joint value: the file, row and line
        ("fk", ["--shard", "3/2"], "shard"),
        ("fk", ["--chunk", "0"], "chunk"),
        ("query_missing_model", [], "not found"),
        ("query_missing_model", ["--shard", "x"], "shard"),
    ],
)
def test_fk_and_manifold_query_bad_input_is_one_line_exit_2(tmp_path, capsys, executor, kind,
                                                            extra, field):  # fmt: skip
    import json

    robot, q = tmp_path / "r.json", tmp_path / "q.csv"
    robot.write_text(json.dumps({"kind": "single_segment", "length": 0.04, "radius": 0.002}))
    q.write_text("0.3,1\nabc,1\n" if kind == "fk_bad_q" else "0.3,1\n")
    out = tmp_path / "o"
    if kind.startswith("fk"):
        argv, cmd = ["fk", str(robot), str(q), "-o", str(out)], "fk"
    else:
        argv, cmd = ["manifold", "query", str(tmp_path / "m.npz"), str(tmp_path), "-o",
                     str(out)], "manifold"  # fmt: skip
    code = main([*argv, "--executor", executor, *extra])
    assert code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith(f"jaxcr {cmd}: error:") and field in err[0], err
    assert not (out / "results.jsonl").exists()  # refused before any work
