"""``jaxcr demo`` argument checking (the full demo is exercised by the README Quickstart; it
compiles the CTR model and the refinement, too slow for the unit-test budget)."""

from __future__ import annotations

from jaxcr.cli import main


def test_demo_rejects_bad_options(tmp_path, capsys):
    assert main(["demo", "-o", str(tmp_path / "d"), "--frames", "0"]) == 2
    assert "--frames" in capsys.readouterr().err
    assert main(["demo", "-o", str(tmp_path / "d"), "--size", "320"]) == 2
    assert "size" in capsys.readouterr().err
    assert main(["demo", "-o", str(tmp_path / "d"), "--preset", "nope", "--frames", "1",
                 "--size", "32x24"]) == 2  # fmt: skip
    assert "nope" in capsys.readouterr().err
    assert not (tmp_path / "d" / "segment").exists()
