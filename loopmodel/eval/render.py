"""Outputs of an evaluation: PNG plots, ``report.md``, self-contained ``report.html``, ``metrics.json``."""

from __future__ import annotations

import base64
import html
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from loopmodel.eval.evaluation import (
    RunEvaluation,
    _get,
    _nearest_index,
)
from loopmodel.eval.inputs import (
    _FRAME_KEYS,
    _KF_KEYS,
    _MATCH_PREFIXES,
    _NS_KEYS,
    _QUERY_PREFIXES,
    _S_KEYS,
)
from loopmodel.io.atomic import write_bytes_atomic, write_text_atomic

PLOT_TOP = "trajectories_top.png"

PLOT_ERROR_TIME = "error_over_time.png"

PLOT_ERROR_COLORED = "error_colored.png"

TRACK_LABELS = {
    "online": "online (before closing)",
    "final": "final (after closing)",
    "keyframes": "keyframes (final)",
}


def make_plots(ev: RunEvaluation) -> dict[str, bytes]:
    """The three pictures of a run evaluation, as PNG bytes by file name."""
    from loopmodel.eval.plots import (
        PlotClosure,
        PlotTrack,
        plot_error_colored,
        plot_error_over_time,
        plot_top_view,
    )

    gt = ev.gt.traj
    ref = ev.pairs["final"].ref_poses[:, :3, 3]
    ref_full = gt.positions_m
    lo = min(int(ev.pairs[k].i_ref.min()) for k in ev.pairs)
    hi = max(int(ev.pairs[k].i_ref.max()) for k in ev.pairs)
    ref_span = ref_full[lo : hi + 1] if hi > lo else ref
    t0 = int(ev.pairs["final"].times_ns[0])
    styles = {"online": ("--", "C1"), "final": ("-", "C0")}
    tracks: list[PlotTrack] = []
    for key in ("online", "final"):
        pe = ev.pairs.get(key)
        if pe is None:
            continue
        st, col = styles[key]
        label = TRACK_LABELS[key] if "online" in ev.pairs else "estimate"
        tracks.append(
            PlotTrack(
                label,
                pe.est_aligned[:, :3, 3],
                (pe.times_ns - t0).astype(np.float64) * 1e-9,
                pe.ate_m,
                st,
                col,
            )
        )
    closures: list[PlotClosure] = []
    final = ev.pairs["final"]
    max_dt_ns = int(round(ev.config.max_dt_ms * 1e6))
    for lc in ev.run.loop_closures:
        if lc.time_ns is None:
            continue
        k = _nearest_index(final.times_ns, lc.time_ns, max(max_dt_ns, 10**9))
        if k is None:
            continue
        m = None
        if lc.match_time_ns is not None:
            km = _nearest_index(final.times_ns, lc.match_time_ns, max(max_dt_ns, 10**9))
            m = final.est_aligned[km, :3, 3] if km is not None else None
        closures.append(PlotClosure((lc.time_ns - t0) * 1e-9, final.est_aligned[k, :3, 3], m))
    align = ev.config.align
    title = f"{ev.run.name}: top view ({align} aligned)"
    out = {
        PLOT_TOP: plot_top_view(ref_span, tracks, closures, title),
        PLOT_ERROR_TIME: plot_error_over_time(tracks, closures, f"{ev.run.name}: ATE over time ({align})"),
        PLOT_ERROR_COLORED: plot_error_colored(
            ref_span, tracks[-1], f"{ev.run.name}: {tracks[-1].label}, coloured by ATE ({align})"
        ),
    }
    if ev.run.path is not None and ev.run.final is not None:
        from loopmodel.eval.mesh_pictures import PLOT_MESH, mesh_before_after_png

        on = ev.pairs.get("online")
        png = mesh_before_after_png(
            ev.run.path,
            ev.run.online.traj if ev.run.online is not None and on is not None else None,
            on.alignment if on is not None else None,
            ev.run.final.traj,
            ev.pairs["final"].alignment,
            ev.gt.source,
        )
        if png is not None:
            out[PLOT_MESH] = png
    return out


def _num(v: Any, digits: int = 4) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        if v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e5):
            return f"{v:.{digits}g}"
        return f"{v:.{digits}f}"
    return str(v)


def _json_clean(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _json_clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_json_clean(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _tables(ev: RunEvaluation) -> list[tuple[str, list[str], list[list[str]], str]]:
    """(heading, header, rows, note) of every table of the report."""
    m = ev.metrics
    tables: list[tuple[str, list[str], list[list[str]], str]] = []
    if m["before_after"] is not None:
        rows = [
            [
                r["metric"],
                _num(r["before"]),
                _num(r["after"]),
                _num(r["change_pct"], 1) if r["change_pct"] is not None else "–",
            ]
            for r in m["before_after"]
        ]
        if m["loop_closure_count"] == 0:
            note = (
                "No loop closure was recorded in this run"
                + ("" if m["loop_closures_recorded"] else " (metrics.json has no 'loop_closures')")
                + ": the final trajectory differs from the online one only by the optimiser's "
                "smoothing, so before and after show no loop-closure effect."
            )
        else:
            note = f"{m['loop_closure_count']} loop closure(s) recorded in this run."
        tables.append(
            (
                "Before / after loop closing",
                ["metric", "online (before)", "final (after)", "change %"],
                rows,
                note,
            )
        )
    else:
        tables.append(
            (
                "Before / after loop closing",
                [],
                [],
                "No loop closure to compare: only one trajectory was evaluated "
                "(no online trajectory), so there is no before/after.",
            )
        )
    # per trajectory summary
    head = [
        "trajectory",
        "poses",
        "matched",
        "align",
        "scale",
        "ATE RMSE [m]",
        "ATE mean",
        "ATE median",
        "ATE max",
        "RPE frames RMSE [m]",
        "RPE dist RMSE [m]",
        "KITTI t [%]",
        "KITTI r [deg/100m]",
        "end-point (origin) [m]",
    ]
    rows = []
    for key, tm in m["trajectories"].items():
        rows.append(
            [
                key,
                str(tm["poses_estimate"]),
                str(tm["matched"]),
                tm["alignment"]["mode"],
                _num(tm["alignment"]["scale"], 6),
                _num(_get(tm, "ate_m", "rmse")),
                _num(_get(tm, "ate_m", "mean")),
                _num(_get(tm, "ate_m", "median")),
                _num(_get(tm, "ate_m", "max")),
                _num(_get(tm, "rpe_frames", "trans_m", "rmse")),
                _num(_get(tm, "rpe_distance", "trans_m", "rmse"))
                + f" (Δ={_num(_get(tm, 'rpe_distance', 'delta_m'), 2)} m)",
                _num(_get(tm, "kitti_segments", "t_err_pct")),
                _num(_get(tm, "kitti_segments", "r_err_deg_per_100m")),
                _num(_get(tm, "end_point", "error_origin_aligned_m")),
            ]
        )
    tables.append(
        (
            "Trajectories",
            head,
            rows,
            "SE(3)-aligned ATE RMSE of the final trajectory (`ate_rmse_m`): "
            f"{_num(m['ate_rmse_m'], 6)} m. "
            "KITTI errors need a path longer than the shortest segment (100 m).",
        )
    )
    ks = _get(m["trajectories"].get("final", {}), "kitti_segments", "per_length_m")
    if ks:
        tables.append(
            (
                "KITTI segment errors (final)",
                ["length [m]", "t_err [%]", "r_err [deg/100 m]", "segments"],
                [[k, _num(v["t_err_pct"]), _num(v["r_err_deg_per_100m"]), str(v["segments"])] for k, v in ks.items()],
                "",
            )
        )
    if m["loop_closures"]:
        extra = sorted(
            {
                k
                for c in m["loop_closures"]
                for k, v in c["recorded"].items()
                if isinstance(v, int | float) and not isinstance(v, bool)
            }
            - set(_ALL_TIME_KEYS)
        )[:6]
        head = [
            "#",
            "time [s]",
            "correction [m]",
            "correction [deg]",
            "ATE before [m]",
            "ATE after [m]",
            *extra,
        ]
        t0 = int(ev.pairs["final"].times_ns[0])
        rows = []
        for c in m["loop_closures"]:
            ts = _num((c["time_ns"] - t0) * 1e-9, 3) if c["time_ns"] is not None else "–"
            rows.append(
                [
                    str(c["index"]),
                    ts,
                    _num(c.get("correction_m")),
                    _num(c.get("correction_deg")),
                    _num(c.get("ate_before_m")),
                    _num(c.get("ate_after_m")),
                    *[_num(c["recorded"].get(k)) for k in extra],
                ]
            )
        tables.append(
            (
                "Loop closures",
                head,
                rows,
                "Correction: distance between the online and the final pose at the closure time "
                "(same run, same world frame); ATE before/after: aligned error there.",
            )
        )
    if m["mesh"]:
        tables.append(
            (
                "Mesh error (recorded by the pipeline)",
                ["key", "value"],
                [[k, _num(v)] for k, v in m["mesh"].items()],
                "",
            )
        )
    return tables


_ALL_TIME_KEYS = tuple(
    p + k for p in (*_QUERY_PREFIXES, *_MATCH_PREFIXES) for k in (*_NS_KEYS, *_S_KEYS, *_FRAME_KEYS, *_KF_KEYS)
) + ("index",)


def _md_table(head: list[str], rows: list[list[str]]) -> str:
    if not head:
        return ""
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _intro(ev: RunEvaluation) -> list[str]:
    m = ev.metrics
    return [
        f"- run: `{m['run_path'] or m['estimate']}`",
        f"- ground truth: `{m['ground_truth']}` ({len(ev.gt.traj)} poses)",
        f"- alignment: {ev.config.align}"
        + (f" on the first {ev.config.first_n} poses" if ev.config.first_n else "")
        + f"; association max Δt {ev.config.max_dt_ms:g} ms",
        f"- **ATE RMSE (final, SE(3) aligned): {_num(m['ate_rmse_m'], 6)} m**",
    ]


def render_markdown(ev: RunEvaluation) -> str:
    """``report.md`` text (pictures referenced as PNG files beside it)."""
    out = [f"# Evaluation: {ev.run.name}", "", *_intro(ev), ""]
    for heading, head, rows, note in _tables(ev):
        out += [f"## {heading}", ""]
        if note:
            out += [note, ""]
        if head:
            out += [_md_table(head, rows)]
    if ev.plots:
        out += ["## Pictures", ""]
        for name in ev.plots:
            out += [f"![{name}]({name})", ""]
    return "\n".join(out)


def render_html(ev: RunEvaluation) -> str:
    """Self-contained ``report.html`` (pictures embedded as base64 PNG)."""
    esc = html.escape
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>Evaluation: {esc(ev.run.name)}</title><style>"
        "body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
        "table{border-collapse:collapse;margin:0.5em 0 1.5em;display:block;overflow-x:auto;max-width:100%}"
        "td,th{border:1px solid #bbb;padding:3px 8px;"
        "text-align:right}th{background:#eee}td:first-child{text-align:left}img{max-width:100%}"
        "</style></head><body>",
        f"<h1>Evaluation: {esc(ev.run.name)}</h1><ul>",
    ]
    for line in _intro(ev):
        text = esc(line[2:]).replace("**", "")
        parts.append(f"<li>{text}</li>")
    parts.append("</ul>")
    for heading, head, rows, note in _tables(ev):
        parts.append(f"<h2>{esc(heading)}</h2>")
        if note:
            parts.append(f"<p>{esc(note)}</p>")
        if head:
            parts.append("<table><tr>" + "".join(f"<th>{esc(h)}</th>" for h in head) + "</tr>")
            for r in rows:
                parts.append("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>")
            parts.append("</table>")
    if ev.plots:
        parts.append("<h2>Pictures</h2>")
        for name, png in ev.plots.items():
            b64 = base64.b64encode(png).decode("ascii")
            parts.append(f"<p><img alt='{esc(name)}' src='data:image/png;base64,{b64}'></p>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write_outputs(ev: RunEvaluation, out_dir: str | Path) -> Path:
    """Write ``metrics.json``, ``report.md``, ``report.html`` and the PNGs into ``out_dir``.

    Atomically, file by file.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name, png in ev.plots.items():
        write_bytes_atomic(out / name, png)
    write_text_atomic(out / "metrics.json", json.dumps(_json_clean(ev.metrics), indent=2, allow_nan=False) + "\n")
    write_text_atomic(out / "report.md", render_markdown(ev))
    write_text_atomic(out / "report.html", render_html(ev))
    return out
