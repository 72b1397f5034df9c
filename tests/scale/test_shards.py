"""--shard I/N bookkeeping (jaxcr.scale.shards): the frame split, the locks between shards and
unsharded runs, and the merge that jaxcr evaluate reads. No compilation: the segment runs
themselves are covered by tests/scale/test_ray_fault.py."""

from __future__ import annotations

import json
import os
import socket

import pytest

from jaxcr.errors import InputError
from jaxcr.io import outdir
from jaxcr.scale import shards as S


def test_parse_shard_accepts_i_of_n_and_refuses_the_rest():
    assert S.parse_shard("0/4") == S.Shard(0, 4)
    assert S.parse_shard(" 3 / 4 ") == S.Shard(3, 4)
    assert S.parse_shard(None) is None
    for bad in ("4/4", "-1/4", "1/0", "a/b", "1", "1/2/3", ""):
        with pytest.raises(InputError, match="shard"):
            S.parse_shard(bad)


@pytest.mark.parametrize("n_items", [0, 1, 7, 12, 100])
@pytest.mark.parametrize("n_shards", [1, 2, 3, 5, 16])
def test_shards_cover_every_frame_once_in_contiguous_balanced_blocks(n_items, n_shards):
    items = [f"f{k:03d}" for k in range(n_items)]
    blocks = [S.Shard(i, n_shards).select(items) for i in range(n_shards)]
    # reference: concatenating the blocks in shard order gives the list back (each frame once,
    # contiguous, in order); sizes differ by at most one (floor/ceil of n/N)
    assert sum(blocks, []) == items
    sizes = [len(b) for b in blocks]
    assert max(sizes) - min(sizes) <= 1
    assert all(n_items // n_shards <= s <= -(-n_items // n_shards) for s in sizes)
    # deterministic: the same call gives the same block
    assert S.Shard(n_shards - 1, n_shards).select(items) == blocks[-1]


def _foreign_live_lock(path):
    """A lock held by a live process other than this one: the test runner's parent."""
    pid = os.getppid()
    info = {"format": outdir.LOCK_FORMAT, "command": "segment", "pid": pid,
            "host": socket.gethostname(), "pid_start": outdir._pid_start(pid),
            "started": "2026-12-01T00:00:00+00:00", "argv": ["jaxcr"]}  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(info))
    return pid


def test_shard_refused_while_an_unsharded_run_holds_out(tmp_path):
    pid = _foreign_live_lock(tmp_path / outdir.LOCK_FILE)
    with pytest.raises(InputError, match=rf"in use by jaxcr segment \(pid {pid} .*unsharded"):
        S.claim_shard(tmp_path, "segment", S.Shard(0, 2))
    assert not (tmp_path / "shards" / "0-of-2" / outdir.LOCK_FILE).exists()


def test_unsharded_run_refused_while_a_shard_runs(tmp_path):
    pid = _foreign_live_lock(tmp_path / "shards" / "1-of-2" / outdir.LOCK_FILE)
    with pytest.raises(InputError, match=rf"in use by shard 1/2 of jaxcr segment \(pid {pid} "):
        outdir.claim(tmp_path, "segment", recognise=lambda o: True)
    assert not (tmp_path / outdir.LOCK_FILE).exists()  # our lock released on refusal


def test_same_shard_twice_and_another_split_refused(tmp_path):
    pid = _foreign_live_lock(tmp_path / "shards" / "0-of-2" / outdir.LOCK_FILE)
    with pytest.raises(InputError, match=rf"pid {pid}"):
        S.claim_shard(tmp_path, "segment", S.Shard(0, 2))
    with pytest.raises(InputError, match="another split.*share N"):
        S.claim_shard(tmp_path, "segment", S.Shard(0, 3))


def test_two_shards_share_out_and_stale_shard_lock_is_taken_over(tmp_path):
    a = S.claim_shard(tmp_path, "segment", S.Shard(0, 2))
    b = S.claim_shard(tmp_path, "segment", S.Shard(1, 2))  # the other shard: no conflict
    assert outdir.owner(tmp_path) == "segment"
    outdir.release(a)
    outdir.release(b)
    # a dead holder (pid that does not run) is stale: the next shard takes over
    lock = tmp_path / "shards" / "0-of-2" / outdir.LOCK_FILE
    lock.write_text(json.dumps({"format": outdir.LOCK_FORMAT, "command": "segment",
                                "pid": 2**22 + 12345, "host": socket.gethostname()}))  # fmt: skip
    c = S.claim_shard(tmp_path, "segment", S.Shard(0, 2))
    outdir.release(c)
    # a folder of another command is refused
    with pytest.raises(InputError, match="not written by jaxcr stereo"):
        S.claim_shard(tmp_path, "stereo", S.Shard(0, 2))


def _write_log(path, frames, ok=True):
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        for fid in frames:
            f.write(json.dumps({"frame": fid, "ok": ok}) + "\n")


def test_merge_reads_every_shard_and_names_unfinished_ones(tmp_path):
    _write_log(tmp_path / "shards" / "0-of-3" / "results.jsonl", ["a", "b"])
    _write_log(tmp_path / "shards" / "2-of-3" / "results.jsonl", ["e", "f"])
    (tmp_path / "shards" / "0-of-3" / "DONE").write_text("x\n")
    # an unsharded --resume record of b supersedes? no: OUT's own file is read first, the
    # shards' later, so a shard's record wins over an older unsharded one
    _write_log(tmp_path / "results.jsonl", ["b", "z"], ok=False)
    recs = {r["frame"]: r for r in S.read_all_records(tmp_path)}
    assert sorted(recs) == ["a", "b", "e", "f", "z"]
    assert recs["b"]["ok"] is True and recs["z"]["ok"] is False
    assert S.missing_shards(tmp_path) == [S.Shard(1, 3), S.Shard(2, 3)]
    assert not S.sharded_complete(tmp_path)
    for i in (1, 2):
        (tmp_path / "shards" / f"{i}-of-3").mkdir(exist_ok=True)
        (tmp_path / "shards" / f"{i}-of-3" / "DONE").write_text("x\n")
    assert S.sharded_complete(tmp_path) and S.missing_shards(tmp_path) == []
