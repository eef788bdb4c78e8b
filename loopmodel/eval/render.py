"""Outputs of an evaluation: PNG plots, ``report.md``, self-contained ``report.html``, ``metrics.json``."""

from __future__ import annotations

import base64
import html
import json
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from loopmodel.display import MISSING, Formatter, extent_m, label, num, quantity
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

PLOT_XYZ_RPY = "xyz_rpy_over_time.png"

PLOT_RPE_TIME = "rpe_over_time.png"

TRACK_LABELS = {
    "online": "online (before closing)",
    "final": "final (after closing)",
    "keyframes": "keyframes (final)",
}


def report_formatter(ev: RunEvaluation) -> Formatter:
    """The report's formatter: lengths in mm or m from the extent of the ground truth."""
    return Formatter.for_positions(ev.gt.traj.positions_m)


def _plot_mode(ev: RunEvaluation) -> str:
    from loopmodel.eval.plots import resolve_plot_mode

    return resolve_plot_mode(getattr(ev.config, "plot_mode", "auto"), ev.gt.traj.world_from_cam)


def make_plots(ev: RunEvaluation) -> dict[str, bytes]:
    """The pictures of a run evaluation, as PNG bytes by file name (captions: :func:`captions`)."""
    from loopmodel.eval.plots import (
        PlotClosure,
        PlotTrack,
        plot_error_colored,
        plot_error_over_time,
        plot_paths,
        plot_rpe_over_time,
        plot_xyz_rpy,
    )
    from loopmodel.eval.trajectory_metrics import pairs_by_frames, rpe

    unit = report_formatter(ev).length
    mode = _plot_mode(ev)
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
        times_s = (pe.times_ns - t0).astype(np.float64) * 1e-9
        i, j = pairs_by_frames(len(pe.times_ns), 1)
        rpe_m, rpe_deg = rpe(pe.ref_poses, pe.est_aligned, i, j)
        tracks.append(PlotTrack(label, pe.est_aligned, times_s, pe.ate_m, st, col, times_s[j], rpe_m, rpe_deg))
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
    span = slice(lo, hi + 1) if hi > lo else slice(None)
    reference = PlotTrack(
        "ground truth", gt.world_from_cam[span], (gt.timestamps_ns[span] - t0).astype(np.float64) * 1e-9
    )
    view = "3-D view" if mode == "xyz" else f"{mode} plane"
    out = {
        PLOT_TOP: plot_paths(ref_span, tracks, closures, f"{ev.run.name}: {view} ({align} aligned)", mode, unit),
        PLOT_ERROR_TIME: plot_error_over_time(tracks, closures, f"{ev.run.name}: ATE over time ({align})", unit),
        PLOT_ERROR_COLORED: plot_error_colored(
            ref_span, tracks[-1], f"{ev.run.name}: {tracks[-1].label}, coloured by ATE ({align})", mode, unit
        ),
        PLOT_XYZ_RPY: plot_xyz_rpy(reference, tracks, closures, f"{ev.run.name}: position and attitude", unit),
        PLOT_RPE_TIME: plot_rpe_over_time(tracks, closures, f"{ev.run.name}: RPE between consecutive poses", unit),
    }
    if ev.run.path is not None and ev.run.final is not None:
        from loopmodel.eval.mesh_pictures import PLOT_MESH, mesh_before_after_png
        from loopmodel.geometry.se3 import world_up

        on = ev.pairs.get("online")
        png = mesh_before_after_png(
            ev.run.path,
            ev.run.online.traj if ev.run.online is not None and on is not None else None,
            on.alignment if on is not None else None,
            ev.run.final.traj,
            ev.pairs["final"].alignment,
            ev.gt.source,
            world_up(gt.world_from_cam),
        )
        if png is not None:
            out[PLOT_MESH] = png
    return out


def captions(ev: RunEvaluation) -> dict[str, str]:
    """The caption under each picture of the report."""
    from loopmodel.eval.mesh_pictures import PLOT_MESH

    mode = _plot_mode(ev)
    unit = report_formatter(ev).length.symbol
    plane = (
        "in 3-D"
        if mode == "xyz"
        else f"in the {mode} plane"
        + (" (camera-frame ground truth: y points down, the ground is xz)" if mode == "xz" else "")
    )
    return {
        PLOT_TOP: f"The ground truth (black) and the estimated paths after {ev.config.align} alignment, {plane}; "
        "red stars: loop closures, a red line to the place recognised.",
        PLOT_ERROR_TIME: f"Absolute trajectory error (translation, {unit}) over time; red lines: loop closures.",
        PLOT_ERROR_COLORED: f"The {'final' if 'online' in ev.pairs else 'estimated'} path {plane}, "
        f"coloured by its absolute error ({unit}); dashed grey: the ground truth.",
        PLOT_XYZ_RPY: f"Position x, y, z ({unit}) and attitude roll, pitch, yaw (degrees, static x-y-z "
        "Euler angles) over time, ground truth in black.",
        PLOT_RPE_TIME: f"Relative pose error between consecutive poses over time: translation ({unit}, top) "
        "and rotation (degrees, bottom).",
        PLOT_MESH: "The mesh of the laser stripes placed with the online (before) and the final (after) "
        "trajectory, coloured by the distance to the ground-truth surface.",
    }


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


def _unit_of_path(path: str) -> str:
    """The ``metrics.json`` key in a dotted path that carries the unit (``rpe_frames.trans_m.rmse``: trans_m)."""
    from loopmodel.display import PLAIN, quantity

    parts = path.split(".")
    for part in reversed(parts):
        if quantity(part) != PLAIN:
            return part
    return parts[-1]


def _strip_unit(text: str) -> str:
    """A label without its ``[unit]`` (the unit goes into the header)."""
    return re.sub(r"\s*\[[^\]]*\]", "", text).strip()


def _human_metric(row: dict[str, Any]) -> str:
    key = str(row.get("key", ""))
    if key.startswith("mesh."):
        from loopmodel.display import label

        return label(key[5:].replace("_before", "")) + " (recorded by the run)"
    return _strip_unit(str(row["metric"]))


def _kitti_rows_empty(m: dict[str, Any]) -> bool:
    return all(_get(tm, "kitti_segments", "t_err_pct") is None for tm in m["trajectories"].values())


def _tables(ev: RunEvaluation) -> list[tuple[str, list[str], list[list[str]], str]]:
    """(heading, header, rows, note) of every table of the report, numbers in the report's units."""
    fmt = report_formatter(ev)
    m = ev.metrics
    tables: list[tuple[str, list[str], list[list[str]], str]] = []
    if m["before_after"] is not None:
        rows = []
        for r in m["before_after"]:
            if str(r.get("key", "")).startswith("kitti_segments") and r["before"] is None and r["after"] is None:
                continue
            unit_key = _unit_of_path(str(r.get("key", "")))
            u = fmt.unit(quantity(unit_key))
            rows.append(
                [
                    _human_metric(r) + (f" [{u}]" if u else ""),
                    fmt.value(unit_key, r["before"]),
                    fmt.value(unit_key, r["after"]),
                    num(r["change_pct"], 3),
                ]
            )
        if m["loop_closure_count"] == 0:
            note = (
                "No loop closure was recorded in this run"
                + ("" if m["loop_closures_recorded"] else " (metrics.json has no `loop_closures`)")
                + ": the final trajectory differs from the online one only by the optimiser's "
                "smoothing, so before and after show no loop-closure effect."
            )
        else:
            note = f"{m['loop_closure_count']} loop closure(s) recorded in this run."
        tables.append(
            (
                "Before / after loop closing",
                ["metric", "online (before)", "final (after)", "change [%]"],
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
    deltas = {_get(tm, "rpe_distance", "delta_m") for tm in m["trajectories"].values()}
    delta = next(iter(deltas)) if len(deltas) == 1 else None
    kitti = not _kitti_rows_empty(m)
    cols: list[tuple[str, tuple[str, ...], str]] = [
        ("ATE RMSE", ("ate_m", "rmse"), "ate_m"),
        ("ATE mean", ("ate_m", "mean"), "ate_m"),
        ("ATE median", ("ate_m", "median"), "ate_m"),
        ("ATE max", ("ate_m", "max"), "ate_m"),
        ("RPE per frame, RMSE", ("rpe_frames", "trans_m", "rmse"), "trans_m"),
        (
            "RPE per " + (fmt.length_text(delta) if delta is not None else "distance") + ", RMSE",
            ("rpe_distance", "trans_m", "rmse"),
            "trans_m",
        ),
    ]
    if kitti:
        cols += [
            ("KITTI t error", ("kitti_segments", "t_err_pct"), "t_err_pct"),
            ("KITTI r error", ("kitti_segments", "r_err_deg_per_100m"), "r_err_deg_per_100m"),
        ]
    cols.append(("end-point error, origin aligned", ("end_point", "error_origin_aligned_m"), "error_m"))
    head = ["trajectory", "poses", "matched", "alignment", "scale"] + [fmt.header(u, t) for t, _, u in cols]
    rows = []
    for key, tm in m["trajectories"].items():
        rows.append(
            [
                TRACK_LABELS.get(key, key),
                num(tm["poses_estimate"]),
                num(tm["matched"]),
                tm["alignment"]["mode"],
                num(tm["alignment"]["scale"]),
                *(fmt.value(u, _get(tm, *path)) for _, path, u in cols),
            ]
        )
    notes = [
        f"**ATE RMSE of the final trajectory ({ev.config.align} aligned): "
        f"{fmt.length_text(m['ate_rmse_m'])}** (`ate_rmse_m` in `metrics.json`, in metres)."
    ]
    if not kitti:
        shortest = min(ev.config.kitti_segment_lengths_m) if ev.config.kitti_segment_lengths_m else 100.0
        notes.append(
            f"KITTI segment errors are left out: the path is shorter than the shortest segment ({shortest:g} m)."
        )
    tables.append(("Trajectories", head, rows, " ".join(notes)))
    ks = _get(m["trajectories"].get("final", {}), "kitti_segments", "per_length_m")
    if ks:
        tables.append(
            (
                "KITTI segment errors (final)",
                ["segment length [m]", "t error [%]", "r error [°/100 m]", "segments"],
                [[k, num(v["t_err_pct"]), num(v["r_err_deg_per_100m"]), num(v["segments"])] for k, v in ks.items()],
                "",
            )
        )
    if m["loop_closures"]:
        # the recorded correction is the pipeline's own view of it; the report shows the measured one
        dropped = {"correction_m", "correction_deg"}
        extra = sorted(
            {
                k
                for c in m["loop_closures"]
                for k, v in c["recorded"].items()
                if isinstance(v, int | float) and not isinstance(v, bool)
            }
            - set(_ALL_TIME_KEYS)
            - dropped
        )[:6]
        head = [
            "#",
            "time [s]",
            fmt.header("correction_m", "correction"),
            "correction [°]",
            fmt.header("ate_m", "ATE before"),
            fmt.header("ate_m", "ATE after"),
            *(fmt.header(k) for k in extra),
        ]
        t0 = int(ev.pairs["final"].times_ns[0])
        rows = []
        for c in m["loop_closures"]:
            ts = num((c["time_ns"] - t0) * 1e-9) if c["time_ns"] is not None else MISSING
            rows.append(
                [
                    str(c["index"]),
                    ts,
                    fmt.value("correction_m", c.get("correction_m")),
                    num(c.get("correction_deg")),
                    fmt.value("ate_m", c.get("ate_before_m")),
                    fmt.value("ate_m", c.get("ate_after_m")),
                    *[fmt.value(k, c["recorded"].get(k)) for k in extra],
                ]
            )
        tables.append(
            (
                "Loop closures",
                head,
                rows,
                "Correction: distance and angle between the online and the final pose at the closure "
                "time (same run, same world frame); ATE before/after: the aligned error there.",
            )
        )
    if m["mesh"]:
        rows = []
        for k, v in m["mesh"].items():
            u = fmt.unit(quantity(k))
            rows.append([label(k) + (f" [{u}]" if u else ""), fmt.value(k, v)])
        tables.append(("Mesh (recorded by the run)", ["quantity", "value"], rows, ""))
    return tables


_ALL_TIME_KEYS = tuple(
    p + k for p in (*_QUERY_PREFIXES, *_MATCH_PREFIXES) for k in (*_NS_KEYS, *_S_KEYS, *_FRAME_KEYS, *_KF_KEYS)
) + ("index",)


def _md_cell(text: str) -> str:
    return text.replace("|", "\\|")


def _md_table(head: list[str], rows: list[list[str]]) -> str:
    if not head:
        return ""
    lines = ["| " + " | ".join(map(_md_cell, head)) + " |", "|" + "|".join("---" for _ in head) + "|"]
    lines += ["| " + " | ".join(map(_md_cell, r)) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _intro(ev: RunEvaluation) -> list[str]:
    m = ev.metrics
    fmt = report_formatter(ev)
    span = extent_m(ev.gt.traj.positions_m)
    return [
        f"- run: `{m['run_path'] or m['estimate']}`",
        f"- ground truth: `{m['ground_truth']}` ({len(ev.gt.traj)} poses)",
        f"- alignment: {ev.config.align}"
        + (f" on the first {ev.config.first_n} poses" if ev.config.first_n else "")
        + f"; association max Δt {ev.config.max_dt_ms:g} ms",
        f"- lengths in {fmt.length.symbol} (the ground truth spans {num(span)} m)",
        f"- **ATE RMSE (final, {ev.config.align} aligned): {fmt.length_text(m['ate_rmse_m'])}**",
    ]


def render_markdown(ev: RunEvaluation, image_src: Callable[[str], str] | None = None) -> str:
    """``report.md`` text; pictures referenced as PNG files beside it (or by ``image_src(name)``)."""
    src = image_src or (lambda name: name)
    out = [f"# Evaluation: {ev.run.name}", "", *_intro(ev), ""]
    for heading, head, rows, note in _tables(ev):
        out += [f"## {heading}", ""]
        if note:
            out += [note, ""]
        if head:
            out += [_md_table(head, rows)]
    if ev.plots:
        caps = captions(ev)
        out += ["## Pictures", ""]
        for name in ev.plots:
            out += [f"![{name}]({src(name)})", "", f"*{caps.get(name, name)}*", ""]
    return "\n".join(out)


_CSS = (
    "body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
    "table{border-collapse:collapse;margin:0.5em 0 1.5em;display:block;overflow-x:auto;max-width:100%}"
    "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}th{background:#eee}"
    "td:first-child,th:first-child{text-align:left}img{max-width:100%}"
    "code{background:#f3f3f3;padding:0 3px}p em{color:#555}"
)


def render_html(ev: RunEvaluation) -> str:
    """Self-contained ``report.html``: ``report.md`` rendered by markdown-it, pictures embedded as base64 PNG."""
    from markdown_it import MarkdownIt

    def data_uri(name: str) -> str:
        return "data:image/png;base64," + base64.b64encode(ev.plots[name]).decode("ascii")

    # rendered with short stand-ins for the pictures, then the data URIs put in: markdown-it's link
    # normalisation leaves a base64 URI as it is, but takes 0.13-0.17 s CPU to walk the sample's 1.5 MB
    # of them (demo21); the same bytes (ev22: report.html of the sample identical)
    token = {name: f"loopmodel-picture-{k}.png" for k, name in enumerate(ev.plots)}
    body = MarkdownIt("commonmark").enable("table").render(render_markdown(ev, token.__getitem__))
    for name, stand_in in token.items():
        body = body.replace(f'src="{stand_in}"', f'src="{data_uri(name)}"')
    return (
        "<!DOCTYPE html><html><head><meta charset='utf-8'>"
        f"<title>Evaluation: {html.escape(ev.run.name)}</title><style>{_CSS}</style></head><body>\n"
        f"{body}</body></html>\n"
    )


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
