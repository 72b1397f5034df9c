"""Watson et al. Table II style reports: aggregate per-frame metrics into mean ± std per column
(dataset tag set or dataset) and render them as Markdown, CSV and a rich table.

A per-frame *row* is a plain dict (one per frame and camera) with keys

    group, frame, camera, ok,
    iou_background, iou_nominal, iou_refined,            (Watson eq. 8, NaN if undefined)
    adj_iou_nominal, adj_iou_refined,                     (NaN when no occlusion info)
    tip_nominal_mm, tip_refined_mm, cl_nominal_mm, cl_refined_mm,   (NaN without truth)
    tip_lateral_nominal_mm, tip_lateral_refined_mm,       (tip error in the first camera's
    tip_depth_nominal_mm, tip_depth_refined_mm,           image plane / along its axis)
    num_steps, time_s

Failed frames (``ok`` False) carry NaN metrics and are counted separately; means and standard
deviations (population, ddof=0, as the paper does not say) are over the frames with a value.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

# Watson et al. Table II (mean ± std; adjusted IoU after "|" for the endoscopic sets).
PAPER_TABLE2 = {
    "columns": ["orthogonal", "orthogonal occluded", "endoscopic", "endoscopic occluded"],
    "Background subtraction": [
        ((0.016, 0.001), None),
        ((0.015, 0.001), None),
        ((0.022, 0.003), None),
        ((0.013, 0.003), None),
    ],
    "Unoptimised projection": [
        ((0.284, 0.087), None),
        ((0.292, 0.101), None),
        ((0.284, 0.092), (0.415, 0.143)),
        ((0.254, 0.088), (0.427, 0.157)),
    ],
    "Optimised projection": [
        ((0.665, 0.063), None),
        ((0.603, 0.134), None),
        ((0.414, 0.104), (0.636, 0.153)),
        ((0.3, 0.109), (0.52, 0.171)),
    ],
}

IOU_ROWS = [
    ("Background subtraction", "iou_background", None),
    ("Unoptimised projection", "iou_nominal", "adj_iou_nominal"),
    ("Optimised projection", "iou_refined", "adj_iou_refined"),
]
ERROR_ROWS = [
    ("Tip error, nominal (mm)", "tip_nominal_mm"),
    ("Tip error, refined (mm)", "tip_refined_mm"),
    ("Centreline error, nominal (mm)", "cl_nominal_mm"),
    ("Centreline error, refined (mm)", "cl_refined_mm"),
    ("Tip error in the image plane, nominal (mm)", "tip_lateral_nominal_mm"),
    ("Tip error in the image plane, refined (mm)", "tip_lateral_refined_mm"),
    ("Tip error along the optical axis, nominal (mm)", "tip_depth_nominal_mm"),
    ("Tip error along the optical axis, refined (mm)", "tip_depth_refined_mm"),
]


def mean_std(values: Iterable[float]) -> tuple[float, float, int]:
    """Mean and population std over the finite values; (nan, nan, 0) if none."""
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return math.nan, math.nan, 0
    return float(v.mean()), float(v.std()), int(v.size)


def format_ms(m: float, s: float, digits: int = 3) -> str:
    if not math.isfinite(m):
        return "n/a"
    return f"{m:.{digits}f} ± {s:.{digits}f}"


@dataclass
class Table2:
    """The aggregated report. ``stats[(row_key, column)] = (mean, std, n)`` for every metric
    key of a row dict; ``cells[row_label][column]`` the formatted text."""

    columns: list[str]
    stats: dict[tuple[str, str], tuple[float, float, int]] = field(default_factory=dict)
    cells: dict[str, dict[str, str]] = field(default_factory=dict)
    counts: dict[str, dict[str, int]] = field(default_factory=dict)

    @property
    def row_labels(self) -> list[str]:
        return list(self.cells)


def group_rows(rows: Sequence[dict], columns: Sequence[str] | None = None) -> dict[str, list]:
    """Rows per ``group`` (in first-seen order, or ``columns`` order), plus ``"all"`` when
    there is more than one group."""
    groups: dict[str, list[dict]] = {}
    if columns is not None:
        groups = {c: [] for c in columns}
    for r in rows:
        groups.setdefault(str(r["group"]), []).append(r)
    if len(groups) > 1:
        groups["all"] = list(rows)
    return groups


def build_table2(rows: Sequence[dict], columns: Sequence[str] | None = None) -> Table2:
    """Aggregate per-frame rows into the Table II layout (see module docstring)."""
    groups = group_rows(rows, columns)
    table = Table2(columns=list(groups))
    keys = [k for _, k, a in IOU_ROWS] + [a for _, _, a in IOU_ROWS if a]
    keys += [k for _, k in ERROR_ROWS] + ["num_steps", "time_s"]
    for col, rs in groups.items():
        ok_rows = [r for r in rs if r.get("ok", True)]
        for k in keys:
            table.stats[(k, col)] = mean_std(r.get(k, math.nan) for r in ok_rows)
        steps = [r["num_steps"] for r in ok_rows if r.get("num_steps") is not None]
        times = [r["time_s"] for r in ok_rows if r.get("time_s") is not None]
        frames = {(r.get("dataset"), r["frame"]) for r in rs}
        failed = {(r.get("dataset"), r["frame"]) for r in rs if not r.get("ok", True)}
        table.counts[col] = {"frames": len(frames), "failed": len(failed)}
        table.stats[("median_steps", col)] = (
            float(np.median(steps)) if steps else math.nan,
            math.nan,
            len(steps),
        )
        table.stats[("ms_per_frame", col)] = (
            1e3 * float(np.median(times)) if times else math.nan,
            math.nan,
            len(times),
        )

    for label, key, adj in IOU_ROWS:
        row = {}
        for col in table.columns:
            m, s, _ = table.stats[(key, col)]
            text = format_ms(m, s)
            if adj is not None:
                am, as_, an = table.stats[(adj, col)]
                if an > 0:
                    text += f" | {format_ms(am, as_)}"
            row[col] = text
        table.cells[label] = row
    for label, key in ERROR_ROWS:
        table.cells[label] = {
            c: format_ms(*table.stats[(key, c)][:2], digits=2) for c in table.columns
        }
    table.cells["Median solver steps"] = {
        c: _fmt_scalar(table.stats[("median_steps", c)][0], 0) for c in table.columns
    }
    table.cells["Median time per frame (ms)"] = {
        c: _fmt_scalar(table.stats[("ms_per_frame", c)][0], 1) for c in table.columns
    }
    table.cells["Frames (failed)"] = {
        c: f"{table.counts[c]['frames']} ({table.counts[c]['failed']})" for c in table.columns
    }
    return table


def _fmt_scalar(v: float, digits: int) -> str:
    return "n/a" if not math.isfinite(v) else f"{v:.{digits}f}"


def table2_markdown(table: Table2, title: str | None = None) -> str:
    """Markdown table: one row per report row, one column per group."""
    lines = []
    if title:
        lines += [f"### {title}", ""]
    lines.append("| | " + " | ".join(table.columns) + " |")
    lines.append("|---" * (len(table.columns) + 1) + "|")
    for label, row in table.cells.items():
        cells = [_md_cell(row[c]) for c in table.columns]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _md_cell(text: str) -> str:
    """Escape the "raw | adjusted" separator so it does not split a Markdown table cell."""
    return text.replace("|", "\\|")


def paper_table2_markdown() -> str:
    """Watson et al. Table II as published, in the same layout."""
    cols = PAPER_TABLE2["columns"]
    lines = ["| | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for label, _, _ in IOU_ROWS:
        cells = []
        for raw, adj in PAPER_TABLE2[label]:
            text = format_ms(*raw)
            if adj is not None:
                text += f" | {format_ms(*adj)}"
            cells.append(_md_cell(text))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def table2_csv(table: Table2) -> str:
    """Long-format CSV: ``column,metric,mean,std,n`` for every aggregated metric, plus
    ``frames`` and ``failed`` counts."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["column", "metric", "mean", "std", "n"])
    for (metric, col), (m, s, n) in table.stats.items():
        w.writerow([col, metric, _csv_num(m), _csv_num(s), n])
    for col, counts in table.counts.items():
        w.writerow([col, "frames", counts["frames"], "", ""])
        w.writerow([col, "failed", counts["failed"], "", ""])
    return buf.getvalue()


def _csv_num(v: float) -> str:
    return "" if not math.isfinite(v) else repr(float(v))


def table2_rich(table: Table2, title: str = "IoU (mean ± std; raw | adjusted)"):
    """A ``rich.table.Table`` for printing."""
    from rich.table import Table

    t = Table(title=title)
    t.add_column("")
    for c in table.columns:
        t.add_column(c, justify="right")
    for label, row in table.cells.items():
        t.add_row(label, *[row[c] for c in table.columns])
    return t
