"""``jaxcr motion`` over a batch of videos: local, shards and Ray give the same outputs.

The reference for a batch is the single-video run (``jaxcr motion DATASET -o OUT``, the path
the other motion tests check): each video's folder of a batch must hold the same files, and
the shards' / Ray's folders the same files and records as the local batch's, apart from the
timings (``time_s`` per record; ``wall_s``/``median_ms`` and the report's timing line per
video; the summary's ``executor``). Videos are tiny (128x96, 6 frames; with the flags of FAST
every run uses the programs test_motion_pipeline and the other motion tests compile, so
the module compiles ~nothing of its own in a full run) and one Ray instance serves the
module (started by the first Ray run, shut down at the end).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from jaxcr.cli import main

TIMING = {"time_s", "wall_s", "median_ms"}
# one motion model and no baseline: the batch machinery is under test, not the models
FAST = ("--no-baseline", "--model", "translation", "--superpixel-step", "8", "--flow-step", "4")


@pytest.fixture(scope="module")
def videos(tmp_path_factory):
    """Three videos: v0 and v2 good, v1 with one unreadable frame (a failed video, exit 1)."""
    root = tmp_path_factory.mktemp("mbatch") / "videos"
    for seed in (0, 1, 2):
        assert main(["motion", "synth", "--preset", "pushed_static", "--seed", str(seed),
                     "--size", "128x96", "--frames", "6", "-o", str(root / f"v{seed}")]) == 0  # fmt: skip
    (root / "v1" / "frames" / "000003.png").write_bytes(b"not a png")
    return root


def _records(out: Path) -> list[dict]:
    from jaxcr.motion.batch import read_video_records
    from jaxcr.scale.shards import read_all_records

    recs = read_all_records(out, read_video_records, key="video")
    return sorted(({k: v for k, v in r.items() if k not in TIMING} for r in recs),
                  key=lambda r: r["video"])  # fmt: skip


def _video_files(d: Path) -> dict[str, bytes | dict | list]:
    """A video folder's files, with the timings taken out of the three that hold them."""
    files = {}
    for f in sorted(d.iterdir()):
        if f.name.startswith("."):  # the folder's lock / owner bookkeeping
            continue
        data = f.read_bytes()
        if f.name == "summary.json":
            s = json.loads(data)
            files[f.name] = {k: v for k, v in s.items() if k not in TIMING | {"dataset"}}
        elif f.name == "frames.jsonl":
            files[f.name] = [{k: v for k, v in json.loads(x).items() if not k.endswith("_ms")}
                             for x in data.splitlines()]  # fmt: skip
        elif f.name == "report.md":
            files[f.name] = [x for x in data.decode().splitlines()[1:]
                             if not x.startswith("Median per-frame time")]  # fmt: skip
        else:
            files[f.name] = data
    return files


@pytest.fixture(scope="module")
def local(videos, tmp_path_factory):
    out = tmp_path_factory.mktemp("mb_local") / "out"
    rc = main(["motion", str(videos), "-o", str(out), *FAST])
    return rc, out


@pytest.fixture(scope="module")
def ray_session():
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install -e '.[ray]')")
    yield ray
    ray.shutdown()


def test_local_batch_records_and_single_video_equality(videos, local, tmp_path, capsys):
    rc, out = local
    assert rc == 1  # v1 lost a frame: recorded failed, the others ok, as a single run exits 1
    recs = _records(out)
    assert [r["video"] for r in recs] == ["v0", "v1", "v2"]
    assert [r["ok"] for r in recs] == [True, False, True]
    assert recs[1]["reason"].startswith("1 frame(s) failed: frame 3:")
    assert json.loads((out / "summary.json").read_text())["failures"] == {"v1": recs[1]["reason"]}
    assert (out / "DONE").exists()
    # each video's folder equals the single-video run of that dataset
    single = tmp_path / "single"
    assert main(["motion", str(videos / "v2"), "-o", str(single), *FAST]) == 0
    assert _video_files(out / "v2") == _video_files(single)


def test_shards_then_resume_equal_the_local_batch(videos, local, tmp_path):
    out = tmp_path / "sharded"
    base = ["motion", str(videos), "-o", str(out), *FAST]
    assert main([*base, "--shard", "1/2"]) == 1  # v1, v2 (v1 failed)
    assert main([*base, "--shard", "0/2"]) == 0  # v0
    assert not (out / "results.jsonl").exists()  # shards write only their own logs
    assert _records(out) == _records(local[1])
    for v in ("v0", "v1", "v2"):
        assert _video_files(out / v) == _video_files(local[1] / v), v
    # the unsharded resume combines: nothing left to run, OUT's summary over all videos
    assert main([*base, "--resume"]) == 1
    s = json.loads((out / "summary.json").read_text())
    assert (s["videos"], s["ok"], s["missing"]) == (3, 2, [])


def test_rerun_needs_resume_and_retry_failed_reruns_only_failed(videos, local, tmp_path, capsys):
    out = tmp_path / "re"
    base = ["motion", str(videos / "v0"), str(videos / "v1"), "-o", str(out), *FAST]
    assert main(base) == 1
    capsys.readouterr()
    assert main(base) == 2  # records exist: refused, one line
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--resume" in err[0]
    before = (out / "results.jsonl").read_text().splitlines()
    assert main([*base, "--resume"]) == 1  # nothing re-run
    assert (out / "results.jsonl").read_text().splitlines() == before
    assert main([*base, "--retry-failed"]) == 1  # v1 again (still failing), v0 kept
    after = (out / "results.jsonl").read_text().splitlines()
    assert after[:2] == before and json.loads(after[2])["video"] == "v1"


@pytest.mark.parametrize(
    "extra, field",
    [(["--shard", "1/1"], "shard"), (["--executor", "ray", "--chunk", "0"], "chunk"),
     (["--workers", "2"], "workers")],
)  # fmt: skip
def test_bad_input_is_one_line_exit_2_before_any_work(videos, tmp_path, capsys, extra, field):
    out = tmp_path / "bad"
    assert main(["motion", str(videos), "-o", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and field in err[0], err
    assert not (out / "results.jsonl").exists()


def test_damaged_motion_json_and_single_video_flags(videos, tmp_path, capsys):
    bad = tmp_path / "vids"
    shutil.copytree(videos, bad)
    (bad / "v2" / "motion.json").write_text('{"format": "jaxcr.motion/1"}')
    assert main(["motion", str(bad), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "v2" in err[0] and "motion.json" in err[0], err
    assert not (tmp_path / "o" / "results.jsonl").exists()
    # a single video is one sequence: scale flags are refused with one line
    assert main(["motion", str(videos / "v0"), "-o", str(tmp_path / "s"), "--shard", "0/2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "batch of videos" in err[0], err


def test_ray_batch_equals_local(videos, local, ray_session, tmp_path):
    out = tmp_path / "ray"
    rc = main(["motion", str(videos), "-o", str(out), *FAST, "--executor", "ray",
               "--workers", "2"])  # fmt: skip
    assert rc == local[0] == 1
    # the driver appends in video order, as locally
    lines = [json.loads(x)["video"] for x in (out / "results.jsonl").read_text().splitlines()]
    assert lines == ["v0", "v1", "v2"]
    assert _records(out) == _records(local[1])
    for v in ("v0", "v1", "v2"):
        assert _video_files(out / v) == _video_files(local[1] / v), v
    s_ray = json.loads((out / "summary.json").read_text())
    s_loc = json.loads((local[1] / "summary.json").read_text())
    drop = {"executor", "run_s", "wall_s"}
    assert {k: v for k, v in s_ray.items() if k not in drop} == {
        k: v for k, v in s_loc.items() if k not in drop
    }
    assert s_ray["executor"]["kind"] == "ray" and s_ray["executor"]["chunks_lost"] == 0


def test_concurrent_runs_are_refused_naming_the_holder(videos, tmp_path, capsys):
    """A shard that runs (its lock held by a live process) refuses an unsharded run into the
    same OUT, and the same shard twice: one line naming the holder's pid, exit 2, no work."""
    import json as _json
    import subprocess
    import sys

    from jaxcr.io import outdir

    out = tmp_path / "busy"
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        d = out / "shards" / "0-of-2"
        d.mkdir(parents=True)
        info = outdir.lock_info("motion")
        info.update(pid=holder.pid, pid_start=outdir._pid_start(holder.pid))
        (d / outdir.LOCK_FILE).write_text(_json.dumps(info) + "\n")
        for extra in ([], ["--shard", "0/2"]):
            assert main(["motion", str(videos), "-o", str(out), *FAST, *extra]) == 2
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and f"pid {holder.pid}" in err[0], err
        assert not (out / "results.jsonl").exists() and not (d / "results.jsonl").exists()
    finally:
        holder.kill()
        holder.wait()
