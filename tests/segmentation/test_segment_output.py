"""The segment output folder: atomic writes, the results.jsonl log (resume, truncation),
the Fig. 4 overlay panel and the Table II report (against direct numpy computations)."""

from __future__ import annotations

import csv
import io
import json
import math
import os

import cv2
import numpy as np
import pytest

from jaxcr.io import overlay, report, results


def test_atomic_write_png_roundtrip_and_no_temp_left(tmp_path):
    rng = np.random.default_rng(0)
    mask = rng.random((12, 17)) > 0.5
    p = results.atomic_write_png(tmp_path / "a" / "m.png", mask)
    back = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint8 and back.shape == (12, 17)
    np.testing.assert_array_equal(back, mask.astype(np.uint8) * 255)
    np.testing.assert_array_equal(results.read_mask_png(p), mask)
    rgb = rng.random((5, 6, 3)).astype(np.float32)
    p2 = results.atomic_write_png(tmp_path / "rgb.png", rgb)
    back = cv2.cvtColor(cv2.imread(str(p2)), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(back, np.rint(rgb * 255).astype(np.uint8))
    assert sorted(os.listdir(tmp_path)) == ["a", "rgb.png"]
    assert os.listdir(tmp_path / "a") == ["m.png"]


def test_atomic_write_gives_ordinary_file_mode(tmp_path):
    p = results.atomic_write_text(tmp_path / "a.txt", "x")
    q = tmp_path / "b.txt"
    q.write_text("x")
    assert (p.stat().st_mode & 0o777) == (q.stat().st_mode & 0o777)


def test_atomic_write_failure_keeps_old_file(tmp_path, monkeypatch):
    p = tmp_path / "x.npy"
    results.atomic_write_npy(p, np.arange(3))

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(results.os, "replace", boom)
    with pytest.raises(OSError):
        results.atomic_write_npy(p, np.arange(5))
    np.testing.assert_array_equal(np.load(p), np.arange(3))
    assert os.listdir(tmp_path) == ["x.npy"]  # temp file removed


def test_results_log_append_read_and_truncated_tail(tmp_path):
    path = tmp_path / "results.jsonl"
    with results.ResultsLog(path) as log:
        log.append({"frame": "000", "ok": True, "x": np.float32(1.5), "v": np.arange(2)})
        log.append({"frame": "001", "ok": False, "reason": "nan q", "e": float("nan")})
    recs = results.read_results(path)
    assert [r["frame"] for r in recs] == ["000", "001"]
    assert recs[0]["x"] == 1.5 and recs[0]["v"] == [0, 1]
    assert recs[1]["e"] is None  # NaN is stored as null (strict JSON)
    # A run killed while appending leaves a partial last line: ignored, then cut off.
    with open(path, "ab") as f:
        f.write(b'{"frame": "002", "ok": tr')
    assert [r["frame"] for r in results.read_results(path)] == ["000", "001"]
    with results.ResultsLog(path) as log:
        log.append({"frame": "002", "ok": True})
    lines = path.read_text().splitlines()
    assert len(lines) == 3 and all(json.loads(line) for line in lines)
    assert results.done_frame_ids(results.read_results(path)) == {"000", "001", "002"}


def test_read_results_rejects_corrupt_middle_line(tmp_path):
    path = tmp_path / "results.jsonl"
    path.write_text('{"frame": "0"}\nnot json\n{"frame": "1"}\n')
    with pytest.raises(ValueError, match=":2:"):
        results.read_results(path)


def test_read_results_last_record_of_a_frame_wins(tmp_path):
    path = tmp_path / "results.jsonl"
    path.write_text('{"frame": "0", "v": 1}\n{"frame": "1", "v": 2}\n{"frame": "0", "v": 3}\n')
    recs = results.read_results(path)
    assert [(r["frame"], r["v"]) for r in recs] == [("0", 3), ("1", 2)]


def test_fig4_panel_layout_and_colours():
    h, w = 20, 30
    img = np.full((h, w, 3), 0.5, np.float32)
    fg = np.zeros((h, w), bool)
    fg[:, : w // 2] = True
    nominal = np.zeros((h, w), bool)
    nominal[5:8, 2:10] = True
    refined = np.zeros((h, w), bool)
    refined[10:14, 3:12] = True
    truth = np.zeros((h, w), bool)
    truth[9:15, 2:13] = True
    panel = overlay.fig4_panel(img, fg, nominal, refined, truth, labels=False)
    assert panel.shape == (2 * h, 2 * w, 3) and panel.dtype == np.uint8
    raw, sub = panel[:h, :w], panel[:h, w:]
    c, d = panel[h:, :w], panel[h:, w:]
    assert np.all(raw == 128)
    np.testing.assert_array_equal(sub[:, : w // 2], 128)
    np.testing.assert_array_equal(sub[:, w // 2 :], 0)
    # white blend at alpha 0.5 of 128 -> 192 inside the projection (away from the contour)
    np.testing.assert_array_equal(c[6, 5], [192, 192, 192])
    np.testing.assert_array_equal(d[12, 7], [192, 192, 192])
    # the blue truth contour is drawn on the truth boundary only
    contour = np.all(d == np.array(overlay.BLUE, np.uint8), axis=-1)
    assert contour[9, 5] and contour[14, 5] and not contour[12, 7]
    assert not np.any(contour & ~truth)
    # no truth: no blue
    panel2 = overlay.fig4_panel(img, fg, nominal, refined, None, labels=True)
    assert not np.any(np.all(panel2 == np.array(overlay.BLUE, np.uint8), axis=-1))


def _rows():
    return [
        dict(
            group="a",
            dataset="d",
            frame="0",
            camera="c",
            ok=True,
            iou_background=0.1,
            iou_nominal=0.2,
            iou_refined=0.6,
            adj_iou_nominal=math.nan,
            adj_iou_refined=math.nan,
            tip_nominal_mm=3.0,
            tip_refined_mm=1.0,
            cl_nominal_mm=2.0,
            cl_refined_mm=0.5,
            num_steps=10,
            time_s=0.1,
        ),
        dict(
            group="a",
            dataset="d",
            frame="1",
            camera="c",
            ok=True,
            iou_background=0.3,
            iou_nominal=0.4,
            iou_refined=0.8,
            adj_iou_nominal=math.nan,
            adj_iou_refined=math.nan,
            tip_nominal_mm=5.0,
            tip_refined_mm=2.0,
            cl_nominal_mm=4.0,
            cl_refined_mm=1.5,
            num_steps=20,
            time_s=0.3,
        ),
        dict(
            group="b",
            dataset="d",
            frame="2",
            camera="c",
            ok=True,
            iou_background=0.0,
            iou_nominal=0.5,
            iou_refined=0.7,
            adj_iou_nominal=0.6,
            adj_iou_refined=0.9,
            tip_nominal_mm=math.nan,
            tip_refined_mm=math.nan,
            cl_nominal_mm=math.nan,
            cl_refined_mm=math.nan,
            num_steps=5,
            time_s=0.2,
        ),
        dict(group="b", dataset="d", frame="3", camera="c", ok=False),
    ]


def test_table2_aggregation_matches_numpy():
    t = report.build_table2(_rows())
    assert t.columns == ["a", "b", "all"]
    m, s, n = t.stats[("iou_refined", "a")]
    assert n == 2 and m == pytest.approx(np.mean([0.6, 0.8])) and s == pytest.approx(0.1)
    m, s, n = t.stats[("iou_nominal", "all")]
    assert n == 3 and m == pytest.approx(np.mean([0.2, 0.4, 0.5]))
    assert s == pytest.approx(np.std([0.2, 0.4, 0.5]))
    assert t.cells["Optimised projection"]["a"] == "0.700 ± 0.100"
    assert t.cells["Optimised projection"]["b"] == "0.700 ± 0.000 | 0.900 ± 0.000"
    assert t.cells["Unoptimised projection"]["a"] == "0.300 ± 0.100"  # no adjusted part
    assert t.cells["Tip error, refined (mm)"]["a"] == "1.50 ± 0.50"
    assert t.cells["Tip error, refined (mm)"]["b"] == "n/a"
    assert t.cells["Frames (failed)"]["b"] == "2 (1)"
    assert t.cells["Frames (failed)"]["all"] == "4 (1)"
    assert t.cells["Median solver steps"]["a"] == "15"
    assert t.cells["Median time per frame (ms)"]["all"] == "200.0"
    md = report.table2_markdown(t)
    assert md.splitlines()[0] == "| | a | b | all |"
    rows = list(csv.DictReader(io.StringIO(report.table2_csv(t))))
    got = {(r["column"], r["metric"]): r for r in rows}
    assert float(got[("all", "iou_refined")]["mean"]) == pytest.approx(0.7)
    assert got[("b", "failed")]["mean"] == "1"


def test_paper_table_text():
    md = report.paper_table2_markdown()
    assert "0.665 ± 0.063" in md and "0.414 ± 0.104 \\| 0.636 ± 0.153" in md
    assert "0.300 ± 0.109 \\| 0.520 ± 0.171" in md
    assert all(line.count(" | ") == 4 for line in md.splitlines()[2:])  # 5 cells per row


def test_refine_config_from_cli_options():
    import argparse

    from jaxcr.cli.segment import refine_config
    from jaxcr.errors import InputError
    from jaxcr.segmentation.refine import RefineConfig

    base = RefineConfig()

    def cfg(**kw):
        return refine_config(argparse.Namespace(**({"basis": None, "levels": None,
                                                   "max_steps": None} | kw)))  # fmt: skip

    assert cfg() == base
    c = cfg(levels=2, max_steps=4, basis=3)
    assert c.levels == base.levels[-2:] and c.n_coeffs == 3
    assert c.steps[-1] == 4 and len(c.steps) == 2
    assert c.tau == base.tau[-2:]
    c = cfg(levels=len(base.levels) + 1)
    assert c.levels == (max(base.levels) + 1, *base.levels)
    assert cfg(prior_weight=2.5).g_reg == 2.5 and cfg(prior_weight=2.5).g_in == base.g_in
    bads = ({"levels": 0}, {"max_steps": 0}, {"basis": 0}, {"prior_weight": -1.0},
            {"prior_weight": float("nan")})  # fmt: skip
    for bad in bads:
        with pytest.raises(InputError):
            cfg(**bad)


def test_robot_hsv_option_sets_the_colour_mask():
    import argparse

    import jax.numpy as jnp

    from jaxcr.cli.segment import robot_hsv_ranges
    from jaxcr.errors import InputError
    from jaxcr.segmentation.batch import _background_fn

    def ranges(*texts, background="colour"):
        return robot_hsv_ranges(argparse.Namespace(robot_hsv=list(texts), background=background))

    assert robot_hsv_ranges(argparse.Namespace(robot_hsv=None, background="colour")) is None
    blue = ranges("190,250,0.3,1,0.1,1")
    assert len(blue) == 1 and (blue[0].h_lo, blue[0].s_hi) == (190.0, 1.0)
    # one blue (hue 220) pixel, one grey pixel, one red pixel: (1, 1, 3, 3) batch
    img = jnp.array([[[[0.1, 0.3, 0.8], [0.5, 0.5, 0.5], [0.8, 0.1, 0.1]]]])
    bg_default, _ = _background_fn("colour", None, "cam")(img)
    bg_blue, sub = _background_fn("colour", None, "cam", blue)(img)
    assert bg_default.tolist() == [[[True, False, True]]]  # greys are the default robot
    assert bg_blue.tolist() == [[[False, True, True]]]
    np.testing.assert_allclose(sub[0, 0, 1], 0.0)  # I' = I o M
    two = ranges("190,250,0.3,1,0.1,1", "0,360,0,0.3,0.06,1")
    assert _background_fn("colour", None, "cam", two)(img)[0].tolist() == [[[False, False, True]]]
    for bad in ("1,2,3", "0,360,0.5,0.2,0,1", "0,400,0,1,0,1", "a,b,c,d,e,f", "0,360,0,1,0,nan"):
        with pytest.raises(InputError, match="robot-hsv"):
            ranges(bad)
    with pytest.raises(InputError, match="needs --background colour"):
        ranges("190,250,0.3,1,0.1,1", background="gmm")
