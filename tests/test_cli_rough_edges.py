"""User-facing rough edges of the command line: exit codes of batch commands, exact problem
counts, quiet video reading, implausible distortion, plain-text --help."""

from __future__ import annotations

import pytest
from _datasets import edit_json, make_dataset


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


# ------------------------------------------------------------------ loader's problem count


def test_loader_counts_problems_as_validate_does(tmp_path, capsys):
    """One broken camera used by 5 frames said '(and 5 more problems)': the per-frame
    consequences were counted as problems. The count now equals `jaxcr validate`'s list."""
    from jaxcr.cli import main
    from jaxcr.errors import InputErrors
    from jaxcr.io.dataset import check_dataset, load_dataset

    root = make_dataset(tmp_path / "d", n_frames=5)

    def break_camera(d):
        d["cameras"]["main"]["K"][0][0] = -1.0

    edit_json(root, break_camera)
    with pytest.raises(InputErrors) as ei:
        load_dataset(root)
    assert len(ei.value.errors) == len(check_dataset(root).report_errors) == 2
    msg = str(ei.value)
    assert "focal lengths must be positive" in msg
    assert f"(and 1 more problem; jaxcr validate {root} lists them all)" in msg
    assert main(["segment", str(root), "-o", str(tmp_path / "o"), "--quiet"]) == 2
    assert "(and 1 more problem;" in _one_line_error(capsys)

    # two independent frame problems besides the camera: 4 problems, 3 more
    def break_frames(d):
        d["frames"][1]["q"] = [1.0]
        d["frames"][3]["q"] = "x"

    edit_json(root, break_frames)
    with pytest.raises(InputErrors) as ei:
        load_dataset(root)
    assert len(ei.value.errors) == len(check_dataset(root).report_errors) == 4
    assert "(and 3 more problems;" in str(ei.value)
    # a single problem has no count
    root2 = make_dataset(tmp_path / "d2", n_frames=1)
    edit_json(root2, lambda d: d.update(format="jaxcr.dataset/9"))
    with pytest.raises(InputErrors) as ei:
        load_dataset(root2)
    assert len(ei.value.errors) == 1 and "more problem" not in str(ei.value)
