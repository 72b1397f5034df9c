"""A Ray run's output folder equals a local run's (issue 19), for ``jaxcr fk``, ``jaxcr
manifold query`` and ``jaxcr stereo``, and ``--shard`` runs merge to the same outputs.

The reference of every comparison is the same command with ``--executor local`` (one process,
no Ray): the Ray run must give the same files and records, apart from timings. Each dataset has
a frame (row) that fails, so "a frame failing on a worker is recorded as failed exactly as
locally" is checked too. The tolerance is zero (bit-identical): both executors run the same
compiled programs on the same chunks (same shapes, same rows in the same positions), and the
rest is the same numpy/OpenCV code on the same inputs.

One Ray instance for the whole module (tests/scale/conftest.py: ``ray_instance``); the sizes
are tiny (a 9-point single-segment robot, 160x120 IREP frames, 320x240 stereo pairs).
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ray", reason="Ray is not installed (pip install -e '.[ray]')")

from jaxcr.cli import main  # noqa: E402

RAY = ["--executor", "ray", "--workers", "2"]
#: one worker actor: every Ray run starts its actors anew (a Python process importing JAX and
#: jaxcr, then loading the command's programs, ~3-5 s of a worker's wall here), and the
#: merging of chunks finished out of order by several actors is the executor's, common to all
#: commands (jaxcr/scale/executor.py ``_run_ray``): pinned with two workers by the fk run
#: below and by tests/scale/test_ray_fault.py's segment run. The manifold, stereo and
#: evaluate runs check their command's worker in a Ray process against the local run
#: (docs/decisions.md T3)
RAY1 = ["--executor", "ray", "--workers", "1"]


def _npz(path: Path) -> dict:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _assert_npz_equal(a: Path, b: Path) -> None:
    za, zb = _npz(a), _npz(b)
    assert sorted(za) == sorted(zb)
    for k in za:
        np.testing.assert_array_equal(za[k], zb[k], err_msg=f"{a.name}: {k}")


def _jsonl(path: Path, drop=()) -> list[dict]:
    return [{k: v for k, v in json.loads(x).items() if k not in drop}
            for x in path.read_text().splitlines()]  # fmt: skip


# --------------------------------------------------------------------------- fk

SS = {"kind": "single_segment", "length": 0.04, "radius": 0.002, "n_points": 9}
Q = [[0.3, -2.0], [1.5, 0.0], [1.0, 0.5], [float("nan"), 0.1], [0.2, 0.2], [2.0, -1.0],
     [0.7, 3.0]]  # fmt: skip


@pytest.fixture(scope="module")
def fk(ray_instance, tmp_path_factory):
    root = tmp_path_factory.mktemp("fk")
    (root / "ss.json").write_text(json.dumps(SS))
    (root / "q.csv").write_text("theta_L,delta\n" + "\n".join(f"{a!r},{b!r}" for a, b in Q))
    base = ["fk", str(root / "ss.json"), str(root / "q.csv"), "--chunk", "2"]
    codes = {name: main([*base, "-o", str(root / name), *extra]) for name, extra in [
        ("local", []), ("ray", RAY), ("shards", ["--shard", "1/2"]),
    ]}  # fmt: skip
    codes["shard1_alone"] = (root / "shards" / "tips.csv").exists()  # before shard 0 finishes
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        codes["evaluate_partial"] = (main(["evaluate", str(root / "shards")]), err.getvalue())
    codes["shards"] = (codes["shards"], main([*base, "-o", str(root / "shards"), "--shard", "0/2"]))
    return root, codes


def test_fk_ray_equals_local(fk):
    root, codes = fk
    # row 3 has a NaN joint: failed, exit 1, under both executors
    assert codes["local"] == 1 and codes["ray"] == 1
    a, b = root / "local", root / "ray"
    assert (a / "results.jsonl").read_bytes() == (b / "results.jsonl").read_bytes()
    recs = _jsonl(a / "results.jsonl")
    assert [r["row"] for r in recs] == list(range(len(Q)))
    assert [r["ok"] for r in recs] == [True, True, True, False, True, True, True]
    assert recs[3]["reason"] == "non-finite joint values"
    assert (a / "tips.csv").read_bytes() == (b / "tips.csv").read_bytes()
    _assert_npz_equal(a / "centrelines.npz", b / "centrelines.npz")
    assert sorted(p.name for p in (a / "parts").iterdir()) == sorted(
        p.name for p in (b / "parts").iterdir()
    )
    # the local run is itself checked against the model (the independent reference): tips
    from jaxcr.kinematics.robots import robot_from_dict

    model = robot_from_dict(SS)
    p = _npz(a / "centrelines.npz")["p"]
    for i in (0, 6):  # one row of the first and of the last (padded) chunk
        ref = np.asarray(model.forward(np.asarray(Q[i], np.float32)).centreline.p)
        np.testing.assert_allclose(p[i], ref, atol=1e-7)  # float32 of ~0.04 m: eps x 0.04


def test_fk_shards_merge_into_the_local_output(fk):
    root, codes = fk
    assert codes["shard1_alone"] is False  # rows 0..2 missing: no whole-job output yet
    # shard 1/2 (rows 3..6, with the NaN row): exit 1; shard 0/2 (rows 0..2): exit 0
    assert codes["shards"] == (1, 0)
    s, a = root / "shards", root / "local"
    assert all((s / "shards" / f"{i}-of-2" / "DONE").exists() for i in (0, 1))
    # the last shard wrote the job's outputs: equal to the unsharded run's (rows run in other
    # chunks, so other positions in the batch: per-row results of a vmap do not depend on it)
    assert (s / "tips.csv").read_bytes() == (a / "tips.csv").read_bytes()
    _assert_npz_equal(s / "centrelines.npz", a / "centrelines.npz")


def test_evaluate_names_missing_fk_rows_then_writes_the_job_files(fk, tmp_path):
    root, codes = fk
    code, err = codes["evaluate_partial"]  # after shard 1/2 alone
    assert code == 1
    assert "3 of 7 row(s) missing" in err and ": 0, 1, 2;" in err and "shard(s) 0/2" in err
    out = tmp_path / "o"
    shutil.copytree(root / "shards", out)
    (out / "tips.csv").unlink()
    (out / "centrelines.npz").unlink()
    assert main(["evaluate", str(out)]) == 1  # complete: written again; row 3 failed: exit 1
    assert (out / "tips.csv").read_bytes() == (root / "local" / "tips.csv").read_bytes()


def test_fk_resume_skips_recorded_rows_and_new_input_starts_over(fk, tmp_path):
    root, _ = fk
    out = tmp_path / "o"
    shutil.copytree(root / "local", out)
    (out / ".jaxcr.lock").unlink(missing_ok=True)
    before = (out / "results.jsonl").read_bytes()
    base = ["fk", str(root / "ss.json"), str(root / "q.csv"), "--chunk", "2", "-o", str(out)]
    assert main(base) == 1
    assert (out / "results.jsonl").read_bytes() == before  # nothing recomputed
    assert (out / "tips.csv").read_bytes() == (root / "local" / "tips.csv").read_bytes()
    # other rows in the same folder: another job, started over (fk replaces its outputs)
    (tmp_path / "q2.csv").write_text("0.3,-2.0\n")
    assert main(["fk", str(root / "ss.json"), str(tmp_path / "q2.csv"), "-o", str(out)]) == 0
    assert len(_jsonl(out / "results.jsonl")) == 1 and not (out / "shards").exists()
    assert len((out / "tips.csv").read_text().splitlines()) == 3  # format line, header, 1 row


# --------------------------------------------------------------------------- manifold query


@pytest.fixture(scope="module")
def manifold(ray_instance, tmp_path_factory):
    from jaxcr.io.images import write_png
    from jaxcr.synth.irep import generate_irep

    root = tmp_path_factory.mktemp("manifold")
    generate_irep(root / "train", 14, "train", 0, (160, 120), progress=False)
    generate_irep(root / "test", 4, "test", 0, (160, 120), occluded=True, progress=False)
    # frame 000002 without markers (a grey image): failed, not estimated
    write_png(root / "test" / "images" / "left" / "000002.png",
              np.full((120, 160, 3), 0.5, np.float32))  # fmt: skip
    model = root / "m.npz"
    assert main(["manifold", "train", str(root / "train"), "-o", str(model), "--bins", "24",
                 "--step", "0.05", "--variance", "0.95"]) == 0  # fmt: skip
    base = ["manifold", "query", str(model), str(root / "test"), "--chunk", "2"]
    codes = {name: main([*base, "-o", str(root / name), *extra]) for name, extra in [
        ("local", []), ("ray", RAY1), ("shards", ["--shard", "0/2"]),
    ]}  # fmt: skip
    codes["shards"] = (codes["shards"], main([*base, "-o", str(root / "shards"), "--shard", "1/2"]))
    return root, codes


TIMES = ("descriptor_s", "query_s")


def test_manifold_query_ray_equals_local(manifold):
    root, codes = manifold
    assert codes["local"] == 1 and codes["ray"] == 1  # frame 000002 failed under both
    a, b = root / "local", root / "ray"
    for name in ("estimates.csv", "estimates.jsonl"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert _jsonl(a / "results.jsonl", TIMES) == _jsonl(b / "results.jsonl", TIMES)
    rows = {r["id"]: r for r in _jsonl(a / "estimates.jsonl")}
    assert rows["000002"]["ok"] is False and "marker pixels" in rows["000002"]["error"]
    assert sum(r["ok"] for r in rows.values()) == 3
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in (a, b))
    drop = ("descriptor_s_per_frame", "query_s_per_frame")
    assert {k: v for k, v in sa.items() if k not in drop} == {
        k: v for k, v in sb.items() if k not in drop
    }
    assert sa["frames"] == 4 and sa["failed"] == 1


def test_manifold_query_shards_merge_into_the_local_output(manifold):
    root, codes = manifold
    assert codes["shards"] == (0, 1)  # frames 0-1 ok; frames 2-3 hold the failed one
    for name in ("estimates.csv", "estimates.jsonl"):
        assert (root / "shards" / name).read_bytes() == (root / "local" / name).read_bytes()


# --------------------------------------------------------------------------- stereo


@pytest.fixture(scope="module")
def stereo(ray_instance, tmp_path_factory):
    from jaxcr.synth.stereo_ctr import generate_stereo_set

    root = tmp_path_factory.mktemp("stereo")
    ds = generate_stereo_set(root / "ds", 2, seed=0, size=(320, 240))
    # frame 1's second view unreadable (a truncated PNG): failed with reason "image"
    doc = json.loads((ds / "stereo.json").read_text())
    bad = ds / doc["frames"][1]["images"][doc["cameras"][1]]
    bad.write_bytes(bad.read_bytes()[:100])
    codes = {name: main(["stereo", str(ds), "-o", str(root / name), *extra])
             for name, extra in [("local", []), ("ray", [*RAY1, "--chunk", "1"])]}  # fmt: skip
    return root, ds, codes


def test_stereo_ray_equals_local(stereo):
    root, _, codes = stereo
    a, b = root / "local", root / "ray"
    assert codes["local"] == 1 and codes["ray"] == 1
    recs_a = _jsonl(a / "results.jsonl", ("timings",))
    assert recs_a == _jsonl(b / "results.jsonl", ("timings",))
    assert [r["ok"] for r in recs_a].count(False) >= 1
    assert recs_a[1]["ok"] is False and recs_a[1]["reason"] == "image"
    assert any(r["ok"] for r in recs_a)  # at least one frame reconstructed

    def files(d: Path) -> list[str]:
        return sorted(p.relative_to(d).as_posix() for p in d.rglob("*") if p.is_file())

    skip = {".jaxcr-out.json", "run.json", "results.jsonl"}
    fa, fb = files(a), files(b)
    assert fa == fb
    for rel in fa:
        if Path(rel).name in skip:
            continue
        if rel.endswith(".npz"):  # zip entries carry their write time: compare the arrays
            _assert_npz_equal(a / rel, b / rel)
        else:
            assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel


def test_evaluate_merges_stereo_shards_and_names_missing_frames(stereo, capsys):
    root, ds, _ = stereo
    out = root / "shards"
    assert main(["stereo", str(ds), "-o", str(out), "--shard", "0/2"]) == 0  # frame 000 ok
    capsys.readouterr()
    assert main(["evaluate", str(out)]) == 1
    err = capsys.readouterr().err
    # the frame of shard 1/2 has no record yet: named, with the unfinished shard
    assert "1 of 2 frame(s) missing" in err and ": 001;" in err and "shard(s) 1/2" in err
    merge = json.loads((out / "merge.json").read_text())
    assert merge["missing"] == ["001"] and merge["unfinished_shards"] == ["1/2"]
    assert main(["stereo", str(ds), "-o", str(out), "--shard", "1/2"]) == 1  # frame 001 bad
    capsys.readouterr()
    assert main(["evaluate", str(out)]) == 1  # complete, but a frame failed (as locally)
    out_text = capsys.readouterr()
    assert "1/2 frames reconstructed, 1 failed, 0 missing" in out_text.out
    assert "frame 001" in out_text.err
    merge = json.loads((out / "merge.json").read_text())
    assert merge["missing"] == [] and merge["unfinished_shards"] == [] and merge["ok"] == 1
    # the merged table equals the unsharded local run's (the reference)
    for name in ("segments.csv", "segments.md"):
        assert (out / name).read_bytes() == (root / "local" / name).read_bytes()


# --------------------------------------------------------------------------- evaluate


@pytest.fixture(scope="module")
def segment_out(ray_instance, tmp_path_factory):
    """A segment output folder written here from the dataset's ground truth (evaluate only
    reads files; no refinement is run): frames 0-2 ok with the true mask shifted by k pixels
    and the true centreline offset by k mm, frame 3 failed in the run, frame 4 ok with a
    mis-sized mask (failed in evaluation)."""
    from jaxcr.io import results as R
    from jaxcr.io.dataset import load_dataset
    from tests.helpers.scale_data import make_segment_dataset

    root = tmp_path_factory.mktemp("evaluate")
    ds_path = make_segment_dataset(root / "ds", 5)
    ds = load_dataset(ds_path)
    out = root / "out"
    out.mkdir()
    lay = R.OutputLayout(out)
    R.atomic_write_json(lay.run, {"format": R.RUN_FORMAT, "dataset": str(ds_path),
                                  "cameras": ["main"]})  # fmt: skip
    log = R.ResultsLog(lay.results)
    for k, frame in enumerate(ds.frames):
        fid = frame.id
        if k == 3:
            log.append({"frame": fid, "ok": False, "reason": "diverged"})
            continue
        mask = np.roll(frame.load_mask("main"), k, axis=1)
        if k == 4:
            mask = mask[:-1]
        R.atomic_write_png(lay.abs(lay.mask("main", fid)), mask.astype(np.uint8) * 255)
        cl = np.asarray(frame.load_truth("centreline"), np.float64) + [1e-3 * k, 0.0, 0.0]
        R.atomic_write_npy(lay.abs(lay.centreline(fid)), cl)
        log.append({"frame": fid, "ok": True, "num_steps": 3, "time_s": 0.1,
                    "files": {"masks": {"main": lay.mask("main", fid)},
                              "centreline": lay.centreline(fid)}})  # fmt: skip
    (out / R.DONE_FILE).write_text("done\n")
    return root, ds, out


def test_evaluate_ray_equals_local(segment_out, capsys):
    import csv

    root, ds, out = segment_out
    codes = {name: main(["evaluate", str(out), "-o", str(root / name), "--no-plot", *extra])
             for name, extra in [("local", []), ("ray", [*RAY1, "--chunk", "2"])]}  # fmt: skip
    # both: exit 1 (frame 3 failed in the run, frame 4 in evaluation), the same report
    assert codes == {"local": 1, "ray": 1}
    for name in ("per_frame.csv", "table2.csv", "table2.md"):
        assert (root / "ray" / name).read_bytes() == (root / "local" / name).read_bytes(), name
    rows = list(csv.DictReader((root / "local" / "per_frame.csv").open()))
    assert [r["frame"] for r in rows] == [f.id for f in ds.frames]
    assert "mask masks/main is (119, 160)" in rows[4]["reason"]
    # the metrics themselves against numpy: IoU of the shifted mask, the tip 1 mm per shift
    for k in range(3):
        truth = ds.frames[k].load_mask("main")
        shifted = np.roll(truth, k, axis=1)
        iou = (truth & shifted).sum() / (truth | shifted).sum()
        assert float(rows[k]["iou_refined"]) == pytest.approx(iou, abs=1e-6)
        # float32 centrelines at ~0.1 m: 1e-7 relative -> ~1e-5 mm; 1e-3 mm tolerance
        assert float(rows[k]["tip_refined_mm"]) == pytest.approx(k, abs=1e-3)


def test_evaluate_ray_refuses_outputs_without_images(stereo, capsys):
    root, _, _ = stereo
    assert main(["evaluate", str(root / "local"), *RAY]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--executor ray evaluates segment outputs" in err[0]
