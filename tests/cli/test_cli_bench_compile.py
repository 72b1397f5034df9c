"""``jaxcr bench compile`` with a fake child runner (no real process, no compilation): the
rows, their same-run references and ratios, the load fields, met/not met, a failing child as
a failed row (exit 1) and a bad ``--only`` (exit 2)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from jaxcr.benchmarks import compile as bc
from jaxcr.cli import main

#: compile seconds the fake "commands" report: cache off, empty cache, filled cache
OFF, FIRST, FILLED = 20.0, 12.0, 0.5


class FakeChildren:
    """Stands in for ``python -m jaxcr ...``: a cache folder holding ``filled`` makes a
    process cheap, as the persistent cache does; segment/demo write summary.json."""

    def __init__(self, fail: str | None = None):
        self.calls: list[tuple[list[str], dict]] = []
        self.fail = fail

    def __call__(self, argv, env, cwd):
        self.calls.append((list(argv), dict(env)))
        off = argv[0] == "--no-compile-cache"
        cmd = argv[1:] if off else argv
        if self.fail and cmd[0] == self.fail:
            return bc.ChildRun(
                1, 0.5, 0.4, "Traceback (most recent call last):\nValueError: boom\n"
            )
        cache = None if off else Path(env["JAXCR_CACHE_DIR"])
        filled = cache is not None and (cache / "filled").exists()
        c = OFF if off else FILLED if filled else FIRST
        if cmd[-2:] == ["--shape-buckets", "off"] and filled:
            c = FIRST  # a new size without buckets: new programs, as an empty cache
        if cache is not None:
            cache.mkdir(exist_ok=True)
            (cache / "filled").touch()
        if "-o" in cmd and cmd[0] in ("segment", "demo"):
            out = Path(cwd) / cmd[cmd.index("-o") + 1] / ("segment" if cmd[0] == "demo" else "")
            out.mkdir(parents=True, exist_ok=True)
            (out / "summary.json").write_text(json.dumps({"compile_s": c}))
        return bc.ChildRun(0, c + 3.0, c + 2.0, "")


@pytest.fixture
def fake(monkeypatch):
    f = FakeChildren()
    monkeypatch.setattr(bc, "run_child", f)
    return f


def _rows(out: Path) -> dict:
    data = json.loads(out.with_suffix(".json").read_text())
    return {r["row"]: r for r in data["result"]["rows"]}


def test_all_parts_rows_references_and_targets(tmp_path, fake, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")  # rich: one line per table row
    out = tmp_path / "c.md"
    assert main(["bench", "compile", "--size", "64x48", "--seed", "3", "-o", str(out)]) == 0
    rows = _rows(out)
    assert list(rows) == ["(a) first segment", "(b) second segment",
                          "(f) new size, same bucket", "(c) warmup, then segment",
                          "(d) first demo", "(e) first stereo"]  # fmt: skip
    a, b, f, c, d, e = rows.values()
    # (f): the cache (a) filled serves the new size; reference: buckets off on a copy of it
    assert (f["compile_s"], f["ref_compile_s"], f["result"]) == (FILLED, FIRST, "met")
    assert "60x45" in f["command"] and f["reference"].startswith("--shape-buckets off")
    # (a): empty cache 12 s compile > 10 s target; reference = --no-compile-cache, same run
    assert (a["compile_s"], a["ref_compile_s"], a["result"]) == (FIRST, OFF, "not met")
    assert a["ratio_wall"] == pytest.approx((OFF + 3) / (FIRST + 3))
    # (b), (c): the cache filled by (a) / by warmup -> 0.5 s <= 1 s; reference row (a)
    assert (b["compile_s"], b["ref_compile_s"], b["result"]) == (FILLED, FIRST, "met")
    assert (c["compile_s"], c["result"], c["warmup_cpu_s"]) == (FILLED, "met", FIRST + 2)
    assert (d["compile_s"], d["ref_compile_s"], d["judged_on"]) == (FIRST, OFF, "compile_s")
    # stereo writes no compile_s: judged on its wall seconds (15 s > 10 s)
    assert (e["judged_on"], e["wall_s"], e["result"]) == ("wall_s", FIRST + 3, "not met")
    for r in rows.values():
        assert all(isinstance(r[k], float) for k in ("load_before", "load_after"))
    # every cached child had its own cache folder; references had none and the flag first
    caches = {}
    for argv, env in fake.calls:
        if argv[0] == "--no-compile-cache":
            assert "JAXCR_CACHE_DIR" not in env and "JAXCR_COMPILE_CACHE" not in env
        else:
            caches.setdefault(env["JAXCR_CACHE_DIR"], []).append(argv[0])
    assert sorted(caches.values()) == [["demo"], ["segment"], ["segment", "segment", "segment"],
                                       ["stereo"], ["warmup", "segment"]]  # fmt: skip
    synth = next(a for a, _ in fake.calls if "synth" in a)
    assert [synth[synth.index(o) + 1] for o in ("--frames", "--size", "--seed")] == [
        "2",
        "64x48",
        "3",
    ]
    text = out.read_text()
    assert "| (b) second segment |" in text and "~0 (<= 1 s)" in text and "host" in text
    assert "(a) first segment" in capsys.readouterr().out


def test_failed_child_is_a_failed_row(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(bc, "run_child", FakeChildren(fail="stereo"))
    out = tmp_path / "c.md"
    assert main(["bench", "compile", "--only", "demo,stereo", "-o", str(out)]) == 1
    rows = _rows(out)
    assert rows["stereo synth dataset"]["result"] == "failed"
    assert rows["stereo synth dataset"]["error"] == "exit 1: ValueError: boom"
    assert rows["(d) first demo"]["result"] == "not met"
    err = capsys.readouterr().err
    assert "Traceback" not in err and "1 row(s) failed" in err
    assert "stereo synth dataset: exit 1: ValueError: boom" in err


def test_only_second_still_reports_the_filling_process(tmp_path, fake):
    out = tmp_path / "c.md"
    assert main(["bench", "compile", "--only", "second", "-o", str(out)]) == 0
    assert list(_rows(out)) == ["(a) first segment (fills the cache)", "(b) second segment"]


def test_unknown_part_exits_2_with_one_line(tmp_path, fake, capsys):
    assert main(["bench", "compile", "--only", "segment,nope", "-o", str(tmp_path / "c.md")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0] and "segment,second,warmup,demo,stereo" in err[0]
    assert not fake.calls


def test_repeats_alternate_the_order_with_new_caches(tmp_path, fake):
    out = tmp_path / "c.md"
    assert main(["bench", "compile", "--only", "demo", "--repeats", "2", "-o", str(out)]) == 0
    data = json.loads(out.with_suffix(".json").read_text())["result"]["rows"]
    assert [(r["repeat"], r["order"], r["compile_s"]) for r in data] == [
        (0, "ours first", FIRST), (1, "reference first", FIRST)]  # fmt: skip
    flags = [(a[0] == "--no-compile-cache", e.get("JAXCR_CACHE_DIR")) for a, e in fake.calls]
    assert [f for f, _ in flags] == [False, True, True, False]
    assert len({c for _, c in flags if c}) == 2  # a new cache folder per repeat


def test_bucket_size_stays_in_the_bucket():
    """Part (f)'s size: each side 1/16 smaller where that keeps the side's bucket (reference:
    the ladder's rule, jaxcr.segmentation.buckets.bucket_shape)."""
    from jaxcr.segmentation.buckets import bucket_shape

    assert bc.bucket_size(640, 480) == (600, 450)
    for w, h in ((640, 480), (64, 48), (1280, 720), (600, 450), (33, 33)):
        bw, bh = bc.bucket_size(w, h)
        assert bucket_shape(bh, bw) == bucket_shape(h, w) and bw <= w and bh <= h


def test_only_bucket_fills_the_cache_first(tmp_path, fake):
    out = tmp_path / "c.md"
    assert main(["bench", "compile", "--only", "bucket", "--size", "64x48", "-o", str(out)]) == 0
    rows = _rows(out)
    assert list(rows) == ["(a) first segment (fills the cache)", "(f) new size, same bucket"]
    synths = [a for a, _ in fake.calls if "synth" in a]
    assert [s[s.index("--size") + 1] for s in synths] == ["64x48", "60x45"]
