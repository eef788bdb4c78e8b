"""Summary of a batch: ``summary.csv`` (one row per task: status, time, peak memory and the
``loopmodel eval`` comparison columns), ``summary.md`` (tasks ranked by ATE, the median per
variant across sequences, failures) and plots (ATE per variant across sequences, box plots)."""

from __future__ import annotations

import hashlib
import json
import math
import statistics
from pathlib import Path
from typing import Any

from loopmodel.batch.execute import FAILED_DIR, TASK_FILE, read_record
from loopmodel.batch.plan import TaskSpec
from loopmodel.batch.runner import running_tmp, task_status
from loopmodel.eval import report as rep
from loopmodel.io.atomic import write_bytes_atomic, write_text_atomic

TASK_COLUMNS = ("task", "sequence", "variant", "status", "error", "task_s", "run_s", "peak_rss_mib", "frames", "fps")
PLOT_ATE = "ate_by_variant.png"
PLOT_BOXES = "boxes_by_variant.png"
SUMMARY_KEY_FILE = ".summary_inputs"
BOX_METRICS = ("ate_rmse_m", "rpe_frames_rmse_m", "run_s", "peak_rss_mib")


def eval_metrics(spec: TaskSpec) -> dict[str, Any] | None:
    """The ``eval/metrics.json`` of a finished task, None when it was not evaluated."""
    try:
        return dict(json.loads((spec.folder / "eval" / "metrics.json").read_text()))
    except (OSError, ValueError):
        return None


def summary_table(tasks: list[TaskSpec]) -> tuple[list[str], list[list[Any]]]:
    """Header and rows (plan order) of ``summary.csv``."""
    running = running_tmp(Path(tasks[0].out_dir)) if tasks else {}
    states = [task_status(t, running) for t in tasks]
    evals = [eval_metrics(t) if s == "done" else None for t, (s, _) in zip(tasks, states, strict=True)]
    cmp_head, cmp_rows = rep.comparison_rows_from_metrics([e for e in evals if e is not None])
    cmp_iter = iter(cmp_rows)
    head = [*TASK_COLUMNS, *cmp_head[1:]]
    rows: list[list[Any]] = []
    for t, (status, rec), ev in zip(tasks, states, evals, strict=True):
        rec = rec or {}
        error = rec.get("error") or (f"not evaluated: {rec['eval_error']}" if rec.get("eval_error") else None)
        base = [t.task_id, t.sequence_name, t.variant, status, error]
        base += [rec.get(k) for k in TASK_COLUMNS[5:]]
        rows.append(base + (next(cmp_iter)[1:] if ev is not None else [None] * (len(cmp_head) - 1)))
    return head, rows


def _col(head: list[str], rows: list[list[Any]], name: str) -> list[Any]:
    i = head.index(name)
    return [r[i] for r in rows]


def _finite(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _by_variant(head: list[str], rows: list[list[Any]], metric: str) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    cols = (_col(head, rows, "variant"), _col(head, rows, "sequence"), _col(head, rows, metric))
    for var, seq, v in zip(*cols, strict=True):
        out.setdefault(var, {})
        if _finite(v):
            out[var][seq] = float(v)
    return out


def _inputs_key(tasks: list[TaskSpec], plots: bool) -> str:
    """Fingerprint of what a summary is made of: each task's record file (name, size, time)."""
    h = hashlib.sha256(f"{plots}".encode())
    for t in tasks:
        for f in (t.folder / TASK_FILE, Path(t.out_dir) / FAILED_DIR / f"{t.task_id}.json"):
            try:
                st = f.stat()
            except OSError:
                h.update(f"{t.task_id}:-;".encode())
            else:
                h.update(f"{t.task_id}:{f.name}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()


def write_summary(tasks: list[TaskSpec], out_dir: str | Path, plots: bool = True) -> dict[str, Path]:
    """Write ``summary.csv``, ``summary.md`` and the plots into ``out_dir``; returns their paths.

    Nothing is redrawn when the tasks' records are unchanged since the last summary (a re-run
    of a finished batch).
    """
    out = Path(out_dir)
    key = _inputs_key(tasks, plots)
    key_file = out / SUMMARY_KEY_FILE
    existing = {"csv": out / "summary.csv", "md": out / "summary.md"}
    if all(p.is_file() for p in existing.values()) and key_file.is_file() and key_file.read_text().strip() == key:
        if plots and (out / PLOT_ATE).is_file():
            existing.update({"ate_plot": out / PLOT_ATE, "box_plot": out / PLOT_BOXES})
        return existing
    paths = _write_summary(tasks, out, plots)
    write_text_atomic(key_file, key + "\n")
    return paths


def _write_summary(tasks: list[TaskSpec], out: Path, plots: bool) -> dict[str, Path]:
    head, rows = summary_table(tasks)
    paths = {"csv": write_text_atomic(out / "summary.csv", rep.csv_text(head, rows))}
    status = _col(head, rows, "status")
    counts = {s: status.count(s) for s in ("done", "failed", "running", "pending")}
    md = [
        f"# Batch summary: {len(tasks)} tasks",
        "",
        ", ".join(f"{n} {s}" for s, n in counts.items() if n) + ".",
        "`ate_rmse_m`: SE(3)-aligned ATE RMSE of the final trajectory (`loopmodel eval`); "
        "`peak_rss_mib`: peak resident memory of the task; times in seconds.",
        "",
        "## Tasks ranked by ATE",
        "",
    ]
    ate = _col(head, rows, "ate_rmse_m")
    order = sorted(range(len(rows)), key=lambda i: (not _finite(ate[i]), ate[i] if _finite(ate[i]) else 0.0))
    short = ["sequence", "variant", "status", "ate_rmse_m", "rpe_frames_rmse_m", "run_s", "peak_rss_mib", "task"]
    idx = [head.index(c) for c in short]
    ranked = [[str(k + 1), *(rows[i][j] for j in idx)] for k, i in enumerate(order)]
    md.append(rep.markdown_table(["rank", *short], ranked))
    per_var = _by_variant(head, rows, "ate_rmse_m")
    if any(per_var.values()):
        md += ["## Variants across sequences (ATE RMSE, m)", ""]
        seqs = sorted({s for v in per_var.values() for s in v})
        vrows = []
        for var, vals in per_var.items():
            med = statistics.median(vals.values()) if vals else None
            vrows.append([var, med, *(vals.get(s) for s in seqs)])
        vrows.sort(key=lambda r: (r[1] is None, r[1] or 0.0))
        md.append(rep.markdown_table(["variant", "median", *seqs], vrows))
    failed = [r for r in rows if r[3] == "failed"]
    if failed:
        md += ["## Failed tasks", ""]
        md.append(rep.markdown_table(["task", "error"], [[r[0], str(r[4])] for r in failed]))
    if plots and any(per_var.values()):
        from loopmodel.eval.plots import plot_boxes, plot_metric_by_group

        paths["ate_plot"] = write_bytes_atomic(
            out / PLOT_ATE, plot_metric_by_group(per_var, "ATE RMSE [m]", "ATE per variant across sequences", log=True)
        )
        panels = {}
        for metric in BOX_METRICS:
            by_var = _by_variant(head, rows, metric)
            panels[metric] = {v: list(d.values()) for v, d in by_var.items()}
        paths["box_plot"] = write_bytes_atomic(out / PLOT_BOXES, plot_boxes(panels, "per variant, across sequences"))
        md += ["## Plots", "", f"![ATE per variant]({PLOT_ATE})", "", f"![box plots]({PLOT_BOXES})", ""]
    paths["md"] = write_text_atomic(out / "summary.md", "\n".join(md) + "\n")
    return paths


def batch_status(tasks: list[TaskSpec]) -> list[tuple[TaskSpec, str, dict[str, Any] | None]]:
    """Each task of a batch folder with its state (done, failed, running, pending)."""
    running = running_tmp(Path(tasks[0].out_dir)) if tasks else {}
    return [(t, *task_status(t, running)) for t in tasks]


__all__ = ["batch_status", "read_record", "summary_table", "write_summary"]
