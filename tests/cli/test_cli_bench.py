"""``jaxcr bench``: provider lookup, option passing and the report (with a fake provider)."""

from __future__ import annotations

import json

import pytest

from jaxcr.cli import bench, main

FAKE = """
CALLS = []

def run_fk_benchmark(batch=8, repeats=3, seed=0):
    CALLS.append((batch, repeats, seed))
    return {"name": "fake fk", "unit": "batch", "median_s": 0.002, "spread_s": 0.0001,
            "compile_s": 1.5, "reference": "scipy loop", "reference_median_s": 0.05,
            "batch": batch, "repeats": repeats,
            "rows": [{"batch": 1, "ms": 0.5}, {"batch": batch, "ms": 2.0}]}
"""


def test_bench_with_fake_provider(tmp_path, monkeypatch, capsys):
    prov = tmp_path / "fake_bench.py"
    prov.write_text(FAKE)
    monkeypatch.setitem(bench.PROVIDERS, "fk", [(str(prov), "run_fk_benchmark")])
    out = tmp_path / "b.md"
    assert main(["bench", "fk", "--batch", "16", "--repeats", "5", "-o", str(out)]) == 0
    text = out.read_text()
    assert "| median per batch | 2.000 ms |" in text
    assert "| compile (excluded above) | 1.500 s |" in text
    assert "| speed-up vs reference | 25x |" in text  # ratio computed: 0.05 / 0.002
    assert "| batch | 16 |" in text and "| repeats | 5 |" in text
    assert "| 16 | 2 |" in text  # the rows table
    assert "jax:" in text and "git_commit" in text  # metadata
    data = json.loads(out.with_suffix(".json").read_text())
    assert data["result"]["ratio"] == pytest.approx(25.0)
    assert "speed-up" in capsys.readouterr().out


def test_bench_missing_provider_is_input_error(monkeypatch, capsys):
    monkeypatch.setitem(bench.PROVIDERS, "segment", [("jaxcr.no_such_module", "f")])
    assert main(["bench", "segment"]) == 2
    assert "no 'segment' benchmark" in capsys.readouterr().err


def test_normalise_maps_aliases_and_flattens():
    r = bench.normalise(
        {"batch_ms_per_frame_median": 250.0, "compile_s_batch": 30.0,
         "reference_ms_per_frame_median": 5000.0, "warm_start": {"warm_steps_mean": 12.0},
         "image": [640, 480]}
    )  # fmt: skip
    assert r["median_s"] == pytest.approx(0.25) and r["compile_s"] == 30.0
    assert r["ratio"] == pytest.approx(20.0) and r["unit"] == "frame"
    md = bench.to_markdown(r, {}, "p")
    assert "| warm_start.warm_steps_mean | 12 |" in md and "| image | 640, 480 |" in md
    assert "batch_ms_per_frame_median" not in md


def test_markdown_without_reference():
    md = bench.to_markdown({"name": "x", "median_s": 2.5}, {"jax": "0"}, "p")
    assert "| median per call | 2.500 s |" in md and "reference" not in md


def test_bench_script_provider_main(tmp_path, monkeypatch, capsys):
    prov = tmp_path / "script_bench.py"
    prov.write_text(
        "import argparse\n"
        "def main(argv=None):\n"
        "    ap = argparse.ArgumentParser()\n"
        "    ap.add_argument('--batch', type=int, default=4)\n"
        "    ap.add_argument('--seed', type=int, default=0)\n"
        "    ap.add_argument('-o', '--out')\n"
        "    a = ap.parse_args(argv)\n"
        "    open(a.out, 'w').write(f'batch {a.batch} seed {a.seed}')\n"
        "    return 0\n"
    )
    monkeypatch.setitem(bench.PROVIDERS, "fk", [(str(prov), "run_fk_benchmark")])
    out = tmp_path / "fk.md"
    assert main(["bench", "fk", "--batch", "32", "--seed", "3", "-o", str(out)]) == 0
    assert out.read_text() == "batch 32 seed 3"
    assert "script_bench.py:main" in capsys.readouterr().out


def test_previous_flag_reaches_providers_that_accept_it(tmp_path, monkeypatch):
    prov = tmp_path / "prev_bench.py"
    prov.write_text(
        "def run_motion_benchmark(frames=2, previous=False):\n"
        "    return {'name': 'fake', 'unit': 'frame', 'median_s': 0.01, 'previous': previous}\n"
    )
    monkeypatch.setitem(bench.PROVIDERS, "motion", [(str(prov), "run_motion_benchmark")])
    for flag, expect in (([], "False"), (["--previous"], "True")):
        out = tmp_path / f"m{len(flag)}.md"
        assert main(["bench", "motion", *flag, "-o", str(out)]) == 0
        assert f"| previous | {expect} |" in out.read_text()
