"""Summary of a batch: ``summary.csv``, ``summary.md`` and plots.

``summary.csv``: one row per task: status, time, peak memory and the ``loopmodel eval`` comparison
columns (SI units, full precision). ``summary.md``: per sequence its variants ranked by ATE (in the
sequence's unit, mesh columns included); variants across sequences by rank and relative ATE, never
by absolute values of sequences of different scales; failures. Plots: ATE per variant and sequence,
box plots of relative measures.
"""

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
from loopmodel.display import MISSING, Formatter, num
from loopmodel.eval import report as rep
from loopmodel.eval.render import _md_table
from loopmodel.io.atomic import write_bytes_atomic, write_text_atomic

TASK_COLUMNS = ("task", "sequence", "variant", "status", "error", "task_s", "run_s", "peak_rss_mib", "frames", "fps")
PLOT_ATE = "ate_by_variant.png"
PLOT_BOXES = "boxes_by_variant.png"
SUMMARY_KEY_FILE = ".summary_inputs"


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


def _sequence_formatter(head: list[str], rows: list[list[Any]]) -> Formatter:
    """Lengths of one sequence's tasks in mm or m, from the extent of its ground truth."""
    extents = [v for v in _col(head, rows, "ground_truth_extent_m") if _finite(v)] if rows else []
    return Formatter.for_scale(float(extents[0]) if extents else None)


def _relative_to_best(head: list[str], rows: list[list[Any]], metric: str) -> dict[str, dict[str, float]]:
    """``metric`` of each (variant, sequence) divided by the sequence's best (1 = the best variant there)."""
    per_var = _by_variant(head, rows, metric)
    best: dict[str, float] = {}
    for vals in per_var.values():
        for seq, v in vals.items():
            best[seq] = min(best.get(seq, math.inf), v)
    return {var: {seq: v / best[seq] for seq, v in vals.items() if best[seq] > 0} for var, vals in per_var.items()}


def _ranks(head: list[str], rows: list[list[Any]], metric: str) -> dict[str, dict[str, int]]:
    """Rank (1 = lowest ``metric``) of each variant within each sequence."""
    per_seq: dict[str, list[tuple[float, str]]] = {}
    for var, vals in _by_variant(head, rows, metric).items():
        for seq, v in vals.items():
            per_seq.setdefault(seq, []).append((v, var))
    out: dict[str, dict[str, int]] = {}
    for seq, pairs in per_seq.items():
        for k, (_, var) in enumerate(sorted(pairs), start=1):
            out.setdefault(var, {})[seq] = k
    return out


SEQUENCE_COLUMNS = (
    "variant",
    "status",
    "ate_rmse_m",
    "rpe_frames_rmse_m",
    "kitti_t_err_pct",
    "loop_closures",
    "run_s",
    "task_s",
    "peak_rss_mib",
)


def summary_markdown(head: list[str], rows: list[list[Any]], plots: bool) -> str:
    """``summary.md`` of the rows of ``summary.csv``.

    Per sequence its variants ranked by ATE (lengths in its own unit, mesh columns included), then
    the variants across sequences by rank and by ATE relative to each sequence's best.
    """
    status = _col(head, rows, "status")
    counts = {s: status.count(s) for s in ("done", "failed", "running", "pending")}
    md = [
        f"# Batch summary: {len(rows)} tasks",
        "",
        ", ".join(f"{n} {s}" for s, n in counts.items() if n) + ".",
        "ATE: RMSE of the final trajectory after SE(3) alignment (`loopmodel eval`); run time: the pipeline; "
        "task time: the run, its evaluation and writing the results; peak memory: resident, of the task. "
        "Lengths in each sequence's unit (mm for close range, m beyond 10 m); `summary.csv` has every "
        "number in SI units at full precision.",
        "",
    ]
    mesh_cols = [c for c in head if c.startswith("mesh") and any(_finite(v) for v in _col(head, rows, c))]
    seqs = list(dict.fromkeys(_col(head, rows, "sequence")))
    for seq in seqs:
        seq_rows = [r for r in rows if r[head.index("sequence")] == seq]
        fmt = _sequence_formatter(head, seq_rows)
        cols = [c for c in SEQUENCE_COLUMNS if c in head and any(r[head.index(c)] is not None for r in seq_rows)]
        cols += [c for c in mesh_cols if any(_finite(r[head.index(c)]) for r in seq_rows)]
        ate = [r[head.index("ate_rmse_m")] for r in seq_rows]
        order = sorted(range(len(seq_rows)), key=lambda i: (not _finite(ate[i]), ate[i] if _finite(ate[i]) else 0.0))
        table = [["rank", *(fmt.header(c) for c in cols)]]
        for k, i in enumerate(order, start=1):
            table.append([str(k), *(_cell(fmt, c, seq_rows[i][head.index(c)]) for c in cols)])
        md += [f"## {seq} (lengths in {fmt.length.symbol})", "", _md_table(table[0], table[1:])]
    ranks = _ranks(head, rows, "ate_rmse_m")
    rel = _relative_to_best(head, rows, "ate_rmse_m")
    if any(ranks.values()) and len(seqs) > 1:
        md += [
            "## Variants across sequences",
            "",
            "Sequences differ in scale (a scan in mm, a drive in m), so variants are compared by their rank "
            "within each sequence (1: lowest ATE) and by their ATE relative to the sequence's best (1.0: best).",
            "",
        ]
        names = list(ranks)
        vrows = []
        for var in names:
            r = list(ranks[var].values())
            vrows.append(
                [
                    var,
                    num(statistics.mean(r)) if r else MISSING,
                    num(statistics.median(rel[var].values())) if rel.get(var) else MISSING,
                    *(num(ranks[var].get(s)) for s in seqs),
                ]
            )
        vrows.sort(key=lambda r: (r[1] == MISSING, float(r[1]) if r[1] != MISSING else 0.0))
        md.append(_md_table(["variant", "mean rank", "median ATE / best", *(f"rank in {s}" for s in seqs)], vrows))
    failed = [r for r in rows if r[3] == "failed"]
    if failed:
        md += ["## Failed tasks", ""]
        md.append(rep.markdown_table(["task", "error"], [[r[0], str(r[4])] for r in failed]))
    if plots:
        md += [
            "## Plots",
            "",
            f"![ATE per variant]({PLOT_ATE})",
            "",
            "*ATE RMSE of each variant (markers) in each sequence (columns), logarithmic axis.*",
            "",
            f"![box plots]({PLOT_BOXES})",
            "",
            "*Per variant across sequences: ATE and RPE relative to the sequence's best variant, run time, "
            "peak memory.*",
            "",
        ]
    return "\n".join(md) + "\n"


def _cell(fmt: Formatter, key: str, v: Any) -> str:
    return v if isinstance(v, str) else fmt.value(key, v)


def _write_summary(tasks: list[TaskSpec], out: Path, plots: bool) -> dict[str, Path]:
    head, rows = summary_table(tasks)
    paths = {"csv": write_text_atomic(out / "summary.csv", rep.csv_text(head, rows))}
    per_var = _by_variant(head, rows, "ate_rmse_m")
    drawn = plots and any(per_var.values())
    if drawn:
        from loopmodel.eval.plots import plot_boxes, plot_metric_by_group

        paths["ate_plot"] = write_bytes_atomic(
            out / PLOT_ATE, plot_metric_by_group(per_var, "ATE RMSE [m]", "ATE per variant and sequence", log=True)
        )
        panels = {
            "ATE / best ATE of the sequence": {
                v: list(d.values()) for v, d in _relative_to_best(head, rows, "ate_rmse_m").items()
            },
            "RPE per frame / best of the sequence": {
                v: list(d.values()) for v, d in _relative_to_best(head, rows, "rpe_frames_rmse_m").items()
            },
            "run time [s]": {v: list(d.values()) for v, d in _by_variant(head, rows, "run_s").items()},
            "peak memory [MiB]": {v: list(d.values()) for v, d in _by_variant(head, rows, "peak_rss_mib").items()},
        }
        paths["box_plot"] = write_bytes_atomic(out / PLOT_BOXES, plot_boxes(panels, "per variant, across sequences"))
    paths["md"] = write_text_atomic(out / "summary.md", summary_markdown(head, rows, drawn))
    return paths


def batch_status(tasks: list[TaskSpec]) -> list[tuple[TaskSpec, str, dict[str, Any] | None]]:
    """Each task of a batch folder with its state (done, failed, running, pending)."""
    running = running_tmp(Path(tasks[0].out_dir)) if tasks else {}
    return [(t, *task_status(t, running)) for t in tasks]


__all__ = ["batch_status", "read_record", "summary_table", "write_summary"]
