"""Comparison tables of many runs (CSV and Markdown)."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

from loopmodel.display import Formatter, num
from loopmodel.eval.evaluation import (
    RunEvaluation,
    _get,
)
from loopmodel.eval.render import _md_table, report_formatter
from loopmodel.io.atomic import write_text_atomic

COMPARISON_COLUMNS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("ate_rmse_m", ("ate_rmse_m",)),
    ("online_ate_rmse_m", ("trajectories", "online", "ate_m", "rmse")),
    ("final_ate_mean_m", ("trajectories", "final", "ate_m", "mean")),
    ("final_ate_max_m", ("trajectories", "final", "ate_m", "max")),
    ("rpe_frames_rmse_m", ("trajectories", "final", "rpe_frames", "trans_m", "rmse")),
    ("rpe_distance_m", ("trajectories", "final", "rpe_distance", "delta_m")),
    ("rpe_distance_rmse_m", ("trajectories", "final", "rpe_distance", "trans_m", "rmse")),
    ("kitti_t_err_pct", ("trajectories", "final", "kitti_segments", "t_err_pct")),
    ("kitti_r_err_deg_per_100m", ("trajectories", "final", "kitti_segments", "r_err_deg_per_100m")),
    ("end_point_origin_m", ("trajectories", "final", "end_point", "error_origin_aligned_m")),
    ("loop_closures", ("loop_closure_count",)),
    ("ground_truth_extent_m", ("ground_truth_extent_m",)),
)


def comparison_rows(evals: list[RunEvaluation]) -> tuple[list[str], list[list[Any]]]:
    """Header and rows of the comparison table of many runs (one row per run)."""
    return comparison_rows_from_metrics([e.metrics for e in evals])


def comparison_rows_from_metrics(metrics: list[dict[str, Any]]) -> tuple[list[str], list[list[Any]]]:
    """:func:`comparison_rows` from the evaluations' ``metrics.json`` contents."""
    mesh_keys = sorted({k for m in metrics for k in m.get("mesh") or {}})
    head = ["run", "matched", *(c for c, _ in COMPARISON_COLUMNS), "ate_change_pct", *mesh_keys]
    rows: list[list[Any]] = []
    for m in metrics:
        vals = [_get(m, *path) for _, path in COMPARISON_COLUMNS]
        before = _get(m, "trajectories", "online", "ate_m", "rmse")
        after = _get(m, "trajectories", "final", "ate_m", "rmse")
        change = (after - before) / before * 100.0 if before and after is not None else None
        rows.append(
            [
                m["run"],
                _get(m, "trajectories", "final", "matched"),
                *vals,
                change,
                *((m.get("mesh") or {}).get(k) for k in mesh_keys),
            ]
        )
    return head, rows


def write_comparison(evals: list[RunEvaluation], out_dir: str | Path) -> tuple[Path, Path]:
    """``comparison.csv`` and ``comparison.md`` of many runs in ``out_dir``."""
    out = Path(out_dir)
    head, rows = comparison_rows(evals)
    csv_path = write_text_atomic(out / "comparison.csv", csv_text(head, rows))
    fmt = report_formatter(evals[0])
    md = [
        "# Comparison of runs",
        "",
        f"Alignment {evals[0].config.align}; ATE RMSE of the final trajectory; the ATE change compares "
        f"final with online ATE RMSE; lengths in {fmt.length.symbol} (`comparison.csv`: metres).",
        "",
        markdown_table(head, rows, fmt),
    ]
    md_path = write_text_atomic(out / "comparison.md", "\n".join(md))
    return csv_path, md_path


def markdown_table(head: list[str], rows: list[list[Any]], fmt: Formatter | None = None) -> str:
    """A Markdown table of values, numbers formatted as in the reports (None as a dash).

    With ``fmt`` the header names are ``metrics.json`` keys: shown as human labels with their
    unit, and each column's values converted to it (lengths in mm or m).
    """
    if fmt is None:
        return _md_table(head, [[num(v) if not isinstance(v, str) else v for v in r] for r in rows])
    cells = [[v if isinstance(v, str) else fmt.value(k, v) for k, v in zip(head, r, strict=True)] for r in rows]
    return _md_table([fmt.header(k) for k in head], cells)


def csv_text(head: list[str], rows: list[list[Any]]) -> str:
    """CSV text of a table: floats in full precision (``repr``), None empty."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(head)
    for r in rows:
        w.writerow(["" if v is None else (repr(v) if isinstance(v, float) else v) for v in r])
    return buf.getvalue()
