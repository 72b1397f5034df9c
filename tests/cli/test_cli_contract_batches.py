"""Issue 17 items 4 and 5: ``evaluate`` and ``manifold train/query`` keep the batch contract.
A bad frame (a non-finite output centreline, a malformed record, a corrupt image) is a failed
frame with its reason, the rest are evaluated, exit 1; a run with missing frames exits 1 and
says how many."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest

from jaxcr.cli import main
from tests.helpers.datasets import H, W, make_dataset


def _stderr_lines(capsys) -> list[str]:
    err = capsys.readouterr().err.strip().splitlines()
    assert not any("Traceback" in ln for ln in err), err
    return err


def _fake_run(root, out, recs, done=True):
    """A segment output folder with the given records (``files`` filled in for ok frames
    unless the record already has one): a full-size refined mask and the dataset's own truth
    centreline as the refined centreline (so its errors are exactly 0)."""
    from jaxcr.io import results as R
    from jaxcr.io.dataset import load_dataset

    frames = {f.id: f for f in load_dataset(root).frames}
    out.mkdir()
    (out / "run.json").write_text(
        json.dumps({"format": R.RUN_FORMAT, "dataset": str(root), "cameras": ["main"]})
    )
    lines = []
    for rec in recs:
        fid = rec["frame"]
        rec = {"format": R.RESULTS_FORMAT, **rec}
        if rec["ok"] and "files" not in rec:
            rel = f"masks/main/{fid}.png"
            R.atomic_write_png(out / rel, np.ones((H, W), bool))
            (out / "centrelines").mkdir(exist_ok=True)
            np.save(out / "centrelines" / f"{fid}.npy", frames[fid].load_truth("centreline"))
            rec["files"] = {"masks": {"main": rel}, "centreline": f"centrelines/{fid}.npy"}
        lines.append(json.dumps(rec))
    (out / "results.jsonl").write_text("\n".join(lines) + "\n")
    if done:
        (out / "DONE").write_text("done\n")


def _per_frame(out):
    return {r["frame"]: r for r in csv.DictReader(open(out / "per_frame.csv"))}


def test_evaluate_nan_centreline_is_a_failed_frame(tmp_path, capsys):
    """An all-NaN output centreline counted as ok: its errors were NaN and the means silently
    covered the other frames only. It is now a failed frame naming the file, and table2.md
    says how many frames the averages cover."""
    root = make_dataset(tmp_path / "d", n_frames=3)
    out = tmp_path / "run"
    _fake_run(root, out, [{"frame": f"{k:06d}", "ok": True} for k in range(3)])
    assert main(["evaluate", str(out), "--no-plot"]) == 0
    rows = _per_frame(out)
    # the output centreline is the truth itself: every error is exactly 0 (reference)
    assert all(float(r["cl_refined_mm"]) == 0.0 for r in rows.values())
    assert "averages are over 3 of 3 frames" in (out / "table2.md").read_text()
    capsys.readouterr()

    for bad in (np.full((8, 3), np.nan), np.array([[0, 0, 0]] * 7 + [[np.inf, 0, 0]], float)):
        np.save(out / "centrelines" / "000001.npy", bad)
        assert main(["evaluate", str(out), "--no-plot"]) == 1
        err = _stderr_lines(capsys)
        assert "1 of 3 frame(s) failed (0 in the segment run, 1 in evaluation)" in err[-1]
        rows = _per_frame(out)
        assert rows["000001"]["ok"] == "False"
        assert "000001.npy" in rows["000001"]["reason"]
        assert "not finite" in rows["000001"]["reason"]
        assert rows["000000"]["ok"] == rows["000002"]["ok"] == "True"
        md = (out / "table2.md").read_text()
        assert "averages are over 2 of 3 frames (1 failed)" in md
    # an empty or one-point centreline has no tip and no mean error: failed, no traceback
    # (the audit, experiments/contract_audit.py item 4: an IndexError traceback)
    for bad in (np.zeros((0, 3)), np.zeros((1, 3))):
        np.save(out / "centrelines" / "000001.npy", bad)
        assert main(["evaluate", str(out), "--no-plot"]) == 1
        _stderr_lines(capsys)
        reason = _per_frame(out)["000001"]["reason"]
        assert "000001.npy" in reason and "N >= 2" in reason, reason


@pytest.mark.parametrize(
    "files",
    [
        "masks/main/000001.png",  # a string, not an object
        ["masks"],  # a list
        {"masks": "masks/main/000001.png"},  # a kind that is not {camera: path}
        {"masks": {"main": 7}},  # a path that is not a string
        {"centreline": ["c.npy"]},
        {"masks": {"main": "../../etc/passwd"}},  # outside OUT
        None,  # null: was evaluated as an ok frame with nothing compared (audit item 4)
        {},
    ],
)
def test_evaluate_malformed_files_field_fails_that_frame(tmp_path, capsys, files):
    """A record whose ``files`` field is malformed was an AttributeError/TypeError traceback.
    By the README's batch contract it is that frame failed, with a reason naming
    results.jsonl, the line and the field; the other frames are evaluated; exit 1."""
    root = make_dataset(tmp_path / "d", n_frames=3)
    out = tmp_path / "run"
    recs = [{"frame": f"{k:06d}", "ok": True} for k in range(3)]
    recs[1]["files"] = files
    _fake_run(root, out, recs)
    assert main(["evaluate", str(out), "--no-plot"]) == 1
    err = _stderr_lines(capsys)
    assert "1 of 3 frame(s) failed" in err[-1]
    rows = _per_frame(out)
    reason = rows["000001"]["reason"]
    assert rows["000001"]["ok"] == "False"
    assert "results.jsonl" in reason and "line 2" in reason and "files" in reason, reason
    assert rows["000000"]["ok"] == rows["000002"]["ok"] == "True"


def test_evaluate_record_of_an_unknown_frame_says_why_it_failed(tmp_path, capsys):
    """The audit (experiments/contract_audit.py, item 4): a record `{"frame": 3}` (no ok, an id
    the dataset does not have) was a failed frame with an empty reason."""
    root = make_dataset(tmp_path / "d", n_frames=2)
    out = tmp_path / "run"
    recs = [{"frame": f"{k:06d}", "ok": True} for k in range(2)]
    _fake_run(root, out, recs)
    with open(out / "results.jsonl", "a") as f:
        f.write('{"frame": 3}\n')
    assert main(["evaluate", str(out), "--no-plot"]) == 1
    err = _stderr_lines(capsys)
    reason = _per_frame(out)["3"]["reason"]
    assert "results.jsonl" in reason and "line 3" in reason and "does not have" in reason, reason
    # counted as a failed record of an unknown frame, not a dataset frame (audit r31: the
    # summary said "1 of 3" for this 2-frame dataset)
    assert "0 of 2 frame(s) failed" in err[-1], err
    assert "1 failed record(s) of frame(s) the dataset does not have (3)" in err[-1], err
    md = (out / "table2.md").read_text()
    assert "over 2 of 2 frames (1 record(s) of frames the dataset does not have" in md, md


def test_evaluate_incomplete_run_exits_1_with_the_missing_count(tmp_path, capsys):
    """5 of 12 records and no DONE marker exited 0 (a stderr warning only)."""
    root = make_dataset(tmp_path / "d", n_frames=12)
    out = tmp_path / "run"
    _fake_run(root, out, [{"frame": f"{k:06d}", "ok": True} for k in range(5)], done=False)
    assert main(["evaluate", str(out), "--no-plot"]) == 1
    err = _stderr_lines(capsys)
    assert any("7 of 12 frame(s) missing" in ln and "no DONE" in ln for ln in err), err
    md = (out / "table2.md").read_text()
    assert "**INCOMPLETE RUN**" in md and "7 of the dataset's 12 frames are missing" in md
    # the same 5 records with DONE (a finished run of a dataset shrunk since) still say so
    (out / "DONE").write_text("done\n")
    assert main(["evaluate", str(out), "--no-plot"]) == 1
    assert any("7 of 12 frame(s) missing" in ln for ln in _stderr_lines(capsys))


# ----------------------------------------------------------------------------- manifold


@pytest.fixture(scope="module")
def irep(tmp_path_factory):
    from jaxcr.synth.irep import generate_irep

    root = tmp_path_factory.mktemp("irep")
    generate_irep(root / "train", 14, "train", 0, (160, 120), progress=False)
    return root


def _corrupt(path):
    path.write_bytes(path.read_bytes()[:60])  # a truncated PNG


def test_manifold_corrupt_image_fails_that_frame_only(irep, tmp_path, capsys):
    """One corrupt image failed the whole batch with exit 2 (train and query). That frame is
    now failed (reason naming the file), the others go on, exit 1."""
    bad = tmp_path / "bad"
    shutil.copytree(irep / "train", bad)
    _corrupt(bad / "images" / "right" / "000003.png")
    _corrupt(bad / "images" / "left" / "000000.png")  # the default colour frame too
    model = tmp_path / "m.npz"
    args = ["manifold", "train", str(bad), "-o", str(model), "--bins", "24", "--step", "0.05"]
    assert main([*args, "--variance", "0.95"]) == 1
    err = _stderr_lines(capsys)
    assert any("2 frame(s) not used" in ln and "000000.png" in ln for ln in err), err
    with np.load(model, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
    assert set(meta["frames_unreadable"]) == {"000000", "000003"}
    assert "000003.png" in meta["frames_unreadable"]["000003"]
    assert meta["frames_used"] == 12

    out = tmp_path / "q"
    assert main(["manifold", "query", str(model), str(bad), "-o", str(out)]) == 1
    err = _stderr_lines(capsys)
    assert "2 frame(s) failed" in err[-1]
    rows = {r["id"]: r for r in map(json.loads, (out / "estimates.jsonl").read_text().splitlines())}
    assert len(rows) == 14
    assert rows["000003"]["ok"] is False and "000003.png" in rows["000003"]["error"]
    assert rows["000000"]["ok"] is False
    assert sum(r["ok"] for r in rows.values()) == 12
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 14 and summary["failed"] == 2
    # an explicitly chosen colour frame that cannot be read stays bad input (exit 2)
    assert main([*args, "--colour-frame", "0"]) == 2
    err = _stderr_lines(capsys)
    assert len(err) == 1 and "000000.png" in err[0] and "colour-frame" in err[0]


def test_manifold_neighbours_over_the_manifold_writes_no_model(irep, tmp_path, capsys):
    """--neighbours 1000000000 wrote a model (exit 0) that every query then refused."""
    model = tmp_path / "m.npz"
    args = ["manifold", "train", str(irep / "train"), "-o", str(model), "--bins", "24"]
    assert main([*args, "--step", "0.05", "--neighbours", "1000000000"]) == 2
    err = _stderr_lines(capsys)
    assert "field 'neighbours': must be at most the manifold's" in err[-1]
    assert not model.exists()
