"""`jaxcr fk`: outputs against model.forward, per-row failures, bad input, atomic outputs."""

import csv
import json
import os
import subprocess
import sys

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxcr.cli import main
from jaxcr.cli.fk import FORMAT, batch_forward, read_q_csv
from jaxcr.kinematics.robots import robot_from_dict

SS = {"kind": "single_segment", "length": 0.04, "radius": 0.002, "n_points": 9}
CC = {
    "kind": "constant_curvature",
    "sections": [{"length": 0.05, "radius": 0.003}, {"length": 0.04, "radius": 0.002}],
    "joints": ["kappa", "phi"],
    "n_points": 9,
}
Q_SS = [[0.3, -2.0], [np.pi / 2, 0.0], [1.0, 0.5]]

# The references: model.forward compiled (run eagerly, its ~15 operations were compiled one by
# one in each test)
_forward = eqx.filter_jit(lambda model, q: model.forward(q))


@pytest.fixture
def files(tmp_path):
    (tmp_path / "ss.json").write_text(json.dumps(SS))
    (tmp_path / "cc.json").write_text(json.dumps(CC))
    rows = "\n".join(",".join(repr(v) for v in r) for r in Q_SS)
    (tmp_path / "q.csv").write_text("theta_L,delta\n" + rows + "\n")
    return tmp_path


def _tips(path):
    with open(path) as fh:
        first = fh.readline().strip()
        rows = list(csv.DictReader(fh))
    return first, rows


def test_outputs_match_forward(files, capsys):
    out = files / "out"
    assert main(["fk", str(files / "ss.json"), str(files / "q.csv"), "-o", str(out)]) == 0
    assert "3/3 rows ok" in capsys.readouterr().out
    model = robot_from_dict(SS)
    z = np.load(out / "centrelines.npz")
    assert str(z["format"]) == FORMAT and str(z["kind"]) == "single_segment"
    assert z["p"].shape == (3, 9, 3) and z["R"].shape == (3, 9, 3, 3) and z["s"].shape == (3, 9)
    first, rows = _tips(out / "tips.csv")
    assert first == f"# format: {FORMAT}"
    assert list(rows[0]) == ["row", "ok", "x", "y", "z", "rx", "ry", "rz", "residual", "energy"]
    for i, q in enumerate(Q_SS):
        res = _forward(model, jnp.asarray(q, jnp.float32))
        np.testing.assert_allclose(z["p"][i], res.centreline.p, atol=1e-7)
        np.testing.assert_allclose(z["rho"][i], res.centreline.rho)
        tip = [float(rows[i][k]) for k in "xyz"]
        np.testing.assert_allclose(tip, res.centreline.p[-1], atol=1e-8)
        rv = [float(rows[i][k]) for k in ("rx", "ry", "rz")]
        np.testing.assert_allclose(
            Rotation.from_rotvec(rv).as_matrix(), res.centreline.R[-1], atol=1e-6
        )
        assert rows[i]["ok"] == "1" and int(rows[i]["row"]) == i
    assert z["ok"].all()
    assert not [f for f in os.listdir(out) if "tmp" in f]  # no temp files left behind


def test_headerless_comments_points_and_chunking(files):
    (files / "q2.csv").write_text(
        "# kappa1, phi1, kappa2, phi2\n\n" + "\n".join(f"{k},0.3,{-k},1.0" for k in range(5)) + "\n"
    )
    a, b = files / "a", files / "b"
    assert (
        main(["fk", str(files / "cc.json"), str(files / "q2.csv"), "-o", str(a), "--points", "11"])
        == 0
    )
    assert (
        main(
            [
                "fk",
                str(files / "cc.json"),
                str(files / "q2.csv"),
                "-o",
                str(b),
                "--points",
                "11",
                "--chunk",
                "2",
            ]
        )
        == 0
    )
    za, zb = np.load(a / "centrelines.npz"), np.load(b / "centrelines.npz")
    assert za["p"].shape == (5, 11, 3)
    np.testing.assert_allclose(za["p"], zb["p"], atol=1e-7)  # padded last chunk discarded
    np.testing.assert_allclose(za["q"][:, 0], np.arange(5))


def test_dataset_folder_as_robot(files):
    ds = files / "ds"
    ds.mkdir()
    (ds / "dataset.json").write_text(
        json.dumps({"format": "jaxcr.dataset/1", "robot": SS, "frames": []})
    )
    assert main(["fk", str(ds), str(files / "q.csv"), "-o", str(files / "o")]) == 0
    assert np.load(files / "o" / "centrelines.npz")["p"].shape == (3, 9, 3)


def test_nan_row_fails_that_row_only(files, capsys):
    (files / "qn.csv").write_text("0.3,-2.0\nnan,0.0\n1.0,0.5\n")
    out = files / "out"
    assert main(["fk", str(files / "ss.json"), str(files / "qn.csv"), "-o", str(out)]) == 1
    assert "2/3 rows ok, 1 failed (row 1: non-finite joint values;" in capsys.readouterr().out
    z = np.load(out / "centrelines.npz")
    np.testing.assert_array_equal(z["ok"], [True, False, True])
    _, rows = _tips(out / "tips.csv")
    assert [r["ok"] for r in rows] == ["1", "0", "1"]
    assert np.isfinite(float(rows[2]["x"]))


@pytest.mark.parametrize(
    "content, message",
    [
        (
            "theta_L,delta\n0.3,-2.0\n0.1,0.2,0.3\n",
            "row 1 (line 3): expected 2 joint values, got 3",
        ),
        ("0.3\n", "row 0 (line 1): expected 2 joint values, got 1"),
        ("0.3,1\nabc,1\n", "row 1 (line 2): non-numeric value"),
        ("0.3,abc\n0.3,1\n", "row 0 (line 1): non-numeric value"),
        ("theta_L,delta\n", "no joint rows found"),
        ("", "no joint rows found"),
    ],
)
def test_bad_q_csv_exits_2(files, capsys, content, message):
    (files / "bad.csv").write_text(content)
    code = main(["fk", str(files / "ss.json"), str(files / "bad.csv"), "-o", str(files / "o")])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err and err.count("\n") == 1 and "Traceback" not in err
    assert not (files / "o" / "tips.csv").exists()


def test_bad_files_exit_2(files, capsys):
    assert main(["fk", str(files / "nope.json"), str(files / "q.csv"), "-o", str(files / "o")]) == 2
    assert "nope.json: file not found" in capsys.readouterr().err
    assert (
        main(["fk", str(files / "ss.json"), str(files / "nope.csv"), "-o", str(files / "o")]) == 2
    )
    assert "nope.csv: file not found" in capsys.readouterr().err
    (files / "bin.csv").write_bytes(b"\xff\xfe\x00\x81binary")
    assert main(["fk", str(files / "ss.json"), str(files / "bin.csv"), "-o", str(files / "o")]) == 2
    assert "not a text CSV" in capsys.readouterr().err
    (files / "r.json").write_text(json.dumps({"kind": "single_segment", "length": -1, "radius": 1}))
    assert main(["fk", str(files / "r.json"), str(files / "q.csv"), "-o", str(files / "o")]) == 2
    assert "field 'length'" in capsys.readouterr().err
    assert (
        main(
            [
                "fk",
                str(files / "ss.json"),
                str(files / "q.csv"),
                "-o",
                str(files / "o"),
                "--points",
                "1",
            ]
        )
        == 2
    )
    assert (
        main(
            [
                "fk",
                str(files / "cc.json"),
                str(files / "q.csv"),
                "-o",
                str(files / "o"),
                "--points",
                "2",
            ]
        )
        == 2
    )
    assert "--points" in capsys.readouterr().err


def test_batch_forward_and_read_q_csv_direct(files):
    q = read_q_csv(str(files / "q.csv"), 2)
    np.testing.assert_allclose(q, Q_SS)
    out = batch_forward(robot_from_dict(SS), q, chunk=2, progress=False)
    assert out["p"].shape == (3, 9, 3) and out["tip_rotvec"].shape == (3, 3)


def test_console_script_smoke(files):
    exe = os.path.join(os.path.dirname(sys.executable), "jaxcr")
    r = subprocess.run(
        [exe, "fk", str(files / "ss.json"), str(files / "q.csv"), "-o", str(files / "sp")],
        capture_output=True,
        text=True,
        timeout=900,  # a hang guard only: a loaded machine can need minutes
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
    )
    assert r.returncode == 0, r.stderr
    assert (files / "sp" / "tips.csv").exists()


def _counting_segment(traces: list):
    """A SingleSegment whose forward appends to ``traces`` (at trace time only)."""
    from jaxcr.kinematics.single_segment import SingleSegment

    class CountingSegment(SingleSegment):
        def forward(self, q, guess=None):
            traces.append(q.shape)  # runs at trace time only
            return super().forward(q, guess)

    return CountingSegment


def test_batch_forward_traces_once_across_chunks():
    from jaxcr.kinematics.single_segment import SingleSegment

    traces = []
    CountingSegment = _counting_segment(traces)
    model = CountingSegment.make(length=0.03, radius=1e-3, n_points=7)
    q = np.random.default_rng(0).uniform(-1.0, 1.0, size=(5, 2))
    out = batch_forward(model, q, chunk=2, progress=False)  # chunks of 2, 2, 1 (padded to 2)
    assert len(traces) == 1
    batch_forward(model, q + 0.1, chunk=2, progress=False)  # new values, same shapes
    assert len(traces) == 1
    for i in range(5):
        ref = _forward(
            SingleSegment.make(length=0.03, radius=1e-3, n_points=7), jnp.asarray(q[i], jnp.float32)
        )
        np.testing.assert_allclose(out["p"][i], ref.centreline.p, atol=1e-7)


def test_batch_bucket_is_the_next_power_of_two():
    """batch_bucket against a slow loop: the smallest power of two >= n, capped at chunk."""
    from jaxcr.kinematics.batch import batch_bucket

    for chunk in (1, 2, 7, 64, 1024):
        for n in range(1, 300):
            p = 1
            while p < n:
                p *= 2
            assert batch_bucket(n, chunk) == min(p, chunk), (n, chunk)


def test_batch_sizes_in_one_bucket_share_one_program():
    """Batches of 5 and 7 rows (bucket 8) trace the forward pass once (issue 18: not one
    compile per batch size); each row equals the one-configuration forward within 1e-7 m."""
    from jaxcr.kinematics.single_segment import SingleSegment

    traces = []
    CountingSegment = _counting_segment(traces)
    model = CountingSegment.make(length=0.03, radius=1e-3, n_points=7)
    rng = np.random.default_rng(1)
    for n in (5, 7):
        q = rng.uniform(-1.0, 1.0, size=(n, 2))
        out = batch_forward(model, q, progress=False)
        assert out["p"].shape[0] == n
        ref_model = SingleSegment.make(length=0.03, radius=1e-3, n_points=7)
        for i in range(n):
            ref = _forward(ref_model, jnp.asarray(q[i], jnp.float32))
            np.testing.assert_allclose(out["p"][i], ref.centreline.p, atol=1e-7)
    assert len(traces) == 1


@pytest.fixture
def stored_programs(tmp_path, monkeypatch):
    """cached_call's folder in tmp_path with an empty memo (clearing the memo stands for a new
    process, as in tests/io/test_io_exported.py); returns the list of programs stored."""
    from jaxcr.io import exported

    folder = str(tmp_path / "exported")
    monkeypatch.setattr(exported, "_folder", lambda: folder)
    monkeypatch.setattr(exported, "_memo", {})
    stores = []
    store = exported._store

    def counting_store(*a):  # a program is stored exactly when it was traced and exported
        stores.append(a[0])
        store(*a)

    monkeypatch.setattr(exported, "_store", counting_store)
    return stores


def test_second_process_loads_the_stored_program_instead_of_tracing(stored_programs):
    """K4: batch_forward with ``jit_call=cached_call`` (what `jaxcr fk` passes) goes through
    jaxcr.io.exported.cached_call.
    The first process traces the forward pass once and stores it; a second one (empty memo)
    loads it and traces nothing. Both equal the direct jit of model.forward per row within
    1e-7 m (float32 rounding of the vectorised program, as above)."""
    from jaxcr.io import exported
    from jaxcr.kinematics.single_segment import SingleSegment

    traces = []
    model = _counting_segment(traces).make(length=0.03, radius=1e-3, n_points=7)
    q = np.random.default_rng(2).uniform(-1.0, 1.0, size=(3, 2))
    first = batch_forward(model, q, progress=False, jit_call=exported.cached_call)
    assert len(traces) == 1 and len(stored_programs) == 1
    exported._memo.clear()  # a new process
    second = batch_forward(model, q, progress=False, jit_call=exported.cached_call)
    assert len(traces) == 1, "the second process traced the forward pass again"
    assert len(stored_programs) == 1
    ref_model = SingleSegment.make(length=0.03, radius=1e-3, n_points=7)
    for i in range(3):
        ref = _forward(ref_model, jnp.asarray(q[i], jnp.float32))
        for out in (first, second):
            np.testing.assert_allclose(out["p"][i], ref.centreline.p, atol=1e-7)
            np.testing.assert_allclose(out["R"][i], ref.centreline.R, atol=1e-6)
    np.testing.assert_allclose(second["tip_rotvec"], first["tip_rotvec"], atol=1e-6)


def test_no_compile_cache_switch_stores_no_program(files, tmp_path, monkeypatch):
    """`jaxcr fk` stores its traced program in <cache folder>/exported/; `--no-compile-cache`
    still turns that off (nothing written to the cache folder), with the same outputs within
    1e-7 m (the same arithmetic traced in the process)."""
    from jaxcr.io import exported

    monkeypatch.setattr(exported, "_memo", {})
    argv = [str(files / "ss.json"), str(files / "q.csv"), "-o"]
    monkeypatch.setenv("JAXCR_CACHE_DIR", str(tmp_path / "on"))
    assert main(["fk", *argv, str(tmp_path / "a")]) == 0
    assert list((tmp_path / "on" / "exported").glob("forward_batch_rotvec-*.jaxexport"))
    monkeypatch.setenv("JAXCR_CACHE_DIR", str(tmp_path / "off"))
    assert main(["--no-compile-cache", "fk", *argv, str(tmp_path / "b")]) == 0
    assert not (tmp_path / "off").exists()
    a, b = np.load(tmp_path / "a" / "centrelines.npz"), np.load(tmp_path / "b" / "centrelines.npz")
    np.testing.assert_allclose(a["p"], b["p"], atol=1e-7)
