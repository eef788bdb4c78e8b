"""What the command line prints at the end of a run: the product first, numbers in one unit per row."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from loopmodel.display import Formatter, num


def _mesh_rows(m: dict[str, Any], folder: Path | None, fmt: Formatter) -> list[tuple[str, str]]:
    """The mesh (path, vertices) and its error against the truth when the run measured it."""
    rows: list[tuple[str, str]] = []
    mesh_path = folder / "mesh.ply" if folder is not None else None
    vertices = m.get("mesh_vertices")
    if mesh_path is not None and mesh_path.is_file():
        rows.append(("mesh", f"{mesh_path} ({num(vertices) if vertices is not None else '?'} vertices)"))
    elif vertices:
        rows.append(("mesh", f"{num(vertices)} vertices (not written)"))
    # the run's own mesh against the truth (mesh_err_after_mm: the evaluation after the run, issue
    # 32); mesh_err_gt_mm is the reference mesh of the stripes placed with ground-truth poses
    if m.get("mesh_err_after_mm") is not None:
        parts = [f"mean {fmt.value('mesh_err_after_mm', m['mesh_err_after_mm'])}"]
        if m.get("mesh_err_after_mm_p95") is not None:
            parts.append(f"p95 {fmt.value('mesh_err_after_mm_p95', m['mesh_err_after_mm_p95'])}")
        rows.append((f"mesh error vs truth [{fmt.length.symbol}]", ", ".join(parts)))
    if m.get("mesh_completeness_after") is not None:
        completeness = fmt.value("mesh_completeness_after", m["mesh_completeness_after"])
        rows.append(("mesh completeness vs truth [%]", completeness))
    return rows


def run_summary_rows(
    m: dict[str, Any], folder: Path | None, fmt: Formatter, rrd: Path | None = None
) -> list[tuple[str, str]]:
    """Rows (label with unit, value) of the table printed after ``loopmodel run``.

    ``m``: the run's ``metrics.json``; ``folder``: its results folder; ``rrd``: the rerun
    recording written beside it, if any. Missing numbers are left out, never printed as None.
    """
    rows: list[tuple[str, str]] = [("frames", f"{m.get('frames', 0)} ({m.get('lost_frames', 0)} lost)")]
    rows.append(("keyframes", num(m.get("keyframes"))))
    if m.get("landmarks"):
        rows.append(("landmarks", num(m["landmarks"])))
    if m.get("fps") is not None:
        rows.append(("speed [fps]", num(m["fps"])))
    backend = m.get("backend")
    if backend and backend != "none":
        ms = m.get("backend_ms_median")
        rows.append(("back end", backend + (f", {num(ms)} ms per keyframe (median)" if ms is not None else "")))
    elif backend == "none":
        rows.append(("back end", "none (the front end's poses)"))
    if "loop_closure_count" in m:
        rows.append(
            (
                "loops / relocalizations",
                f"{m['loop_closure_count']} / {m.get('relocalization_count', 0)} "
                f"({m.get('loop_candidates_rejected', 0)} candidates rejected)",
            )
        )
    unit = fmt.length.symbol
    if m.get("ate_rmse_m_online") is not None:
        rows.append((f"ATE RMSE online [{unit}]", fmt.value("ate_rmse_m", m["ate_rmse_m_online"])))
    if m.get("ate_rmse_m") is not None:
        rows.append((f"ATE RMSE final [{unit}]", fmt.value("ate_rmse_m", m["ate_rmse_m"])))
    if m.get("drift_pct") is not None:
        rows.append(("drift final [%]", num(m["drift_pct"])))
    rows += _session_rows(m)
    rows += _mesh_rows(m, folder, fmt)
    if m.get("frames_s") is not None:  # issue 32: the time after the frames is shown, step by step above
        finish = m.get("finish_s") or {}
        rows.append(("time [s]", f"frames {num(m['frames_s'])}, then {num(sum(finish.values()))} (steps above)"))
    if rrd is not None:
        rows.append(("rerun recording", f"{rrd} (open with: rerun {rrd})"))
    return rows


def _session_rows(m: dict[str, Any]) -> list[tuple[str, str]]:
    """Rows of a run in a saved map (localize or extend)."""
    rows: list[tuple[str, str]] = []
    if "localized_frames" in m:
        first = m.get("map_first_localized_frame")
        where = f" (first at frame {first})" if first is not None else ""
        rows.append(("localized in the map", f"{m['localized_frames']} frames{where}"))
        if not m.get("map_localized"):
            rows.append(("map", "never relocalized: poses in this session's own frame"))
    if "merged" in m:
        rows.append(
            ("merged with the map", f"{m.get('merge_links')} links" if m["merged"] else "no shared view: not merged")
        )
    return rows


def frontend_summary(m: dict[str, Any], folder: Path | None, fmt: Formatter) -> str:
    """The line printed after ``loopmodel run --frontend-only``."""
    text = (
        f"wrote {folder}: {m['frames']} frames ({m['lost_frames']} lost), "
        f"{m['keyframes']} keyframes, {num(m.get('fps'))} fps"
    )
    if m.get("ate_rmse_m") is not None:
        text += f", ATE RMSE {fmt.length_text(m['ate_rmse_m'])}, drift {num(m.get('drift_pct'))} %"
    return text
