"""Evaluation of results folders and trajectory files against ground truth.

Inputs, the before/after (online/final) comparison, per-loop-closure corrections, mesh error, and
the outputs (``metrics.json``, ``report.md``, self-contained ``report.html``, PNG plots, comparison
tables of many runs).

A results folder (DESIGN.md) holds ``trajectory_online.tum`` (poses as estimated live),
``trajectory_final.tum`` (after every loop closure), ``keyframes.tum`` and ``metrics.json``
whose optional ``loop_closures`` list holds one object per closure. The time of a closure
is read from ``timestamp_ns``/``time_ns``/``t_ns``/``stamp_ns`` (or ``*_s`` in seconds,
``frame`` as an index into the online trajectory, ``keyframe``/``kf`` as an index into
``keyframes.tum``), optionally prefixed with ``query_``/``current_``; the matched old place
likewise with a ``match_``/``matched_``/``candidate_``/``old_`` prefix. Other numbers of an
event (inliers, correction size, optimisation time) are carried into the report. Mesh
errors are every number of ``metrics.json`` whose key starts with ``mesh`` (or inside a
``mesh`` object).
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import EvalConfig, SequenceConfig
from loopmodel.errors import FormatError, InputError
from loopmodel.eval.trajectory_metrics import (
    ALIGN_MODES,
    PairEvaluation,
    evaluate_pair,
    pose_difference,
    se3_ate_rmse_m,
)
from loopmodel.io.atomic import write_bytes_atomic, write_text_atomic
from loopmodel.io.trajectory_io import guess_format, read_trajectory
from loopmodel.types import Trajectory

logger = logging.getLogger(__name__)

ONLINE_FILE = "trajectory_online.tum"
FINAL_FILE = "trajectory_final.tum"
KEYFRAMES_FILE = "keyframes.tum"
RUN_METRICS_FILE = "metrics.json"

PLOT_TOP = "trajectories_top.png"
PLOT_ERROR_TIME = "error_over_time.png"
PLOT_ERROR_COLORED = "error_colored.png"

TRACK_LABELS = {
    "online": "online (before closing)",
    "final": "final (after closing)",
    "keyframes": "keyframes (final)",
}


# --------------------------------------------------------------------------- inputs


@dataclass
class TimedTrajectory:
    """A trajectory with where it came from and whether its times are real (KITTI files
    carry none; their poses are numbered at a fixed rate)."""

    traj: Trajectory
    source: str
    has_times: bool


def _bag_trajectory(spec: str | Path) -> TimedTrajectory | None:
    """A ``BAG:TOPIC`` trajectory (pose topics or ``/tf:PARENT.CHILD``), or None for other specs."""
    from loopmodel.io.bag_trajectory import parse_bag_spec, read_bag_trajectory

    parsed = parse_bag_spec(spec)
    if parsed is None:
        return None
    return TimedTrajectory(read_bag_trajectory(*parsed), str(spec), True)


def load_trajectory_file(path: str | Path, rate_hz: float = 10.0) -> TimedTrajectory:
    """Read a TUM, KITTI or EuRoC trajectory for evaluation.

    Repeated timestamps are kept (some estimators write them), times going backwards are an error.
    """
    bag = _bag_trajectory(path)
    if bag is not None:
        return bag
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "trajectory file does not exist")
    fmt = guess_format(p)
    traj = read_trajectory(p, fmt, rate_hz=rate_hz)  # repeated times allowed, no going back
    if len(traj) < 2:
        raise InputError(p, f"trajectory has {len(traj)} pose(s); at least 2 are needed")
    return TimedTrajectory(traj, str(p), fmt != "kitti")


def load_ground_truth(spec: str | Path, sequence_config: SequenceConfig | None = None) -> TimedTrajectory:
    """Ground truth from a trajectory file (TUM, KITTI, EuRoC) or from a sequence (MCAP file,
    EuRoC or KITTI folder) read with :func:`loopmodel.io.open_sequence`."""
    bag = _bag_trajectory(spec)
    if bag is not None:
        return bag
    p = Path(spec)
    if not p.exists():
        raise InputError(p, "ground truth path does not exist")
    if p.is_dir() or p.suffix.lower() in (".mcap", ".bag", ".db3"):
        from loopmodel.io.sequence import open_sequence

        seq = open_sequence(p, sequence_config)
        gt = seq.ground_truth
        if gt is None:
            raise InputError(p, f"the {seq.format_name} sequence has no ground truth")
        if len(gt) < 2:
            raise InputError(p, f"ground truth has {len(gt)} pose(s); at least 2 are needed")
        return TimedTrajectory(gt, str(p), True)
    rate = sequence_config.kitti_rate_hz if sequence_config else 10.0
    return load_trajectory_file(p, rate)


def check_comparable(ref: TimedTrajectory, est: TimedTrajectory) -> None:
    """Raise :class:`FormatError` when the two cannot be associated.

    A KITTI file (no times) against a timed one, or two KITTI files of different lengths.
    """
    if ref.has_times != est.has_times:
        untimed, timed = (ref, est) if not ref.has_times else (est, ref)
        raise FormatError(
            untimed.source,
            f"unequal formats: a KITTI pose file has no timestamps and cannot be associated with "
            f"the timed trajectory {timed.source} (give the sequence folder or a TUM/EuRoC file)",
        )
    if not ref.has_times and len(ref.traj) != len(est.traj):
        raise FormatError(
            est.source,
            f"KITTI pose files are matched by index and need equal lengths: {len(est.traj)} poses "
            f"vs {len(ref.traj)} in {ref.source}",
        )


@dataclass
class LoopClosureEvent:
    """One recorded loop closure: query (current) time, matched old time, other numbers."""

    index: int
    time_ns: int | None
    match_time_ns: int | None
    fields: dict[str, Any]


@dataclass
class RunData:
    """A results folder (or a plain estimate, as a run with only a final trajectory)."""

    name: str
    path: Path | None
    final: TimedTrajectory | None
    online: TimedTrajectory | None = None
    keyframes: TimedTrajectory | None = None
    run_metrics: dict[str, Any] = field(default_factory=dict)
    loop_closures: list[LoopClosureEvent] = field(default_factory=list)
    loop_closures_recorded: bool = False


_QUERY_PREFIXES = ("", "query_", "current_", "cur_", "new_")
_MATCH_PREFIXES = ("match_", "matched_", "candidate_", "old_", "loop_", "ref_")
_NS_KEYS = ("timestamp_ns", "time_ns", "t_ns", "stamp_ns")
_S_KEYS = ("timestamp_s", "time_s", "t_s", "stamp_s")
_FRAME_KEYS = ("frame", "frame_index", "frame_idx")
_KF_KEYS = ("keyframe", "kf", "keyframe_index", "kf_index", "keyframe_id", "kf_id")


def _event_time_ns(ev: dict[str, Any], prefixes: tuple[str, ...], run: RunData) -> int | None:
    for pre in prefixes:
        for k in _NS_KEYS:
            v = ev.get(pre + k)
            if isinstance(v, int | float) and not isinstance(v, bool):
                return int(v)
        for k in _S_KEYS:
            v = ev.get(pre + k)
            if isinstance(v, int | float) and not isinstance(v, bool):
                return int(round(float(v) * 1e9))
        for keys, tt in ((_FRAME_KEYS, run.online or run.final), (_KF_KEYS, run.keyframes)):
            for k in keys:
                v = ev.get(pre + k)
                if isinstance(v, int) and not isinstance(v, bool) and tt is not None:
                    if 0 <= v < len(tt.traj):
                        return int(tt.traj.timestamps_ns[v])
    return None


def parse_loop_closures(events: Any, run: RunData, source: str) -> list[LoopClosureEvent]:
    """Loop-closure events of a run's ``metrics.json`` (see the module docstring)."""
    if events is None:
        return []
    if not isinstance(events, list):
        raise FormatError(source, "'loop_closures' must be a list of objects")
    out: list[LoopClosureEvent] = []
    for k, ev in enumerate(events):
        if not isinstance(ev, dict):
            raise FormatError(source, f"loop_closures[{k}] must be an object, got {type(ev).__name__}")
        out.append(
            LoopClosureEvent(
                k,
                _event_time_ns(ev, _QUERY_PREFIXES, run),
                _event_time_ns(ev, _MATCH_PREFIXES, run),
                ev,
            )
        )
    return out


def load_run(path: str | Path, rate_hz: float = 10.0) -> RunData:
    """Read a results folder.

    The online, final and keyframe trajectories (those present; one of online/final is required),
    ``metrics.json`` and its loop-closure events.
    """
    p = Path(path)
    if not p.is_dir():
        raise InputError(p, "results folder does not exist (or is not a folder)")
    tt: dict[str, TimedTrajectory | None] = {}
    for key, name in (
        ("online", ONLINE_FILE),
        ("final", FINAL_FILE),
        ("keyframes", KEYFRAMES_FILE),
    ):
        f = p / name
        tt[key] = load_trajectory_file(f, rate_hz) if f.is_file() else None
    if tt["final"] is None and tt["online"] is None:
        raise InputError(p, f"results folder has neither {FINAL_FILE} nor {ONLINE_FILE}")
    run = RunData(p.resolve().name, p, tt["final"] or tt["online"], tt["online"], tt["keyframes"])
    mpath = p / RUN_METRICS_FILE
    if mpath.is_file():
        try:
            data = json.loads(mpath.read_text())
        except json.JSONDecodeError as exc:
            raise FormatError(mpath, f"not valid JSON ({exc.msg} at line {exc.lineno})") from None
        if not isinstance(data, dict):
            raise FormatError(mpath, "expected a JSON object")
        run.run_metrics = data
        # the pipeline records every loop-closing event in ``loop_events`` (type "loop" or
        # "relocalization"); a plain ``loop_closures`` list is read too
        events = data.get("loop_closures")
        if events is None and isinstance(data.get("loop_events"), list):
            events = [e for e in data["loop_events"] if isinstance(e, dict) and e.get("type", "loop") == "loop"]
        run.loop_closures_recorded = events is not None
        run.loop_closures = parse_loop_closures(events, run, str(mpath))
    return run


def ground_truth_hint(run: RunData) -> Path | None:
    """The sequence a run was made from, when its ``metrics.json`` names an existing path."""
    for key in ("sequence_path", "sequence", "input", "source"):
        v = run.run_metrics.get(key)
        if isinstance(v, str) and v and Path(v).exists():
            return Path(v)
    return None


# --------------------------------------------------------------------------- evaluation


@dataclass
class RunEvaluation:
    """Numbers and pictures of one evaluated run."""

    run: RunData
    gt: TimedTrajectory
    config: EvalConfig
    pairs: dict[str, PairEvaluation]
    metrics: dict[str, Any]
    plots: dict[str, bytes] = field(default_factory=dict)


def _eval_one(gt: TimedTrajectory, est: TimedTrajectory, cfg: EvalConfig) -> PairEvaluation:
    check_comparable(gt, est)
    try:
        return evaluate_pair(
            gt.traj.timestamps_ns,
            gt.traj.world_from_cam,
            est.traj.timestamps_ns,
            est.traj.world_from_cam,
            max_dt_ns=int(round(cfg.max_dt_ms * 1e6)),
            align_mode=cfg.align,
            first_n=cfg.first_n,
            rpe_delta_frames=cfg.rpe_delta_frames,
            rpe_delta_m=cfg.rpe_delta_m,
            kitti_lengths_m=tuple(cfg.kitti_segment_lengths_m),
        )
    except InputError as exc:
        if exc.source is None:
            raise InputError(f"{est.source} vs {gt.source}", exc.problem) from None
        raise


def _nearest_index(times_ns: NDArray[np.int64], t_ns: int, max_dt_ns: int) -> int | None:
    if len(times_ns) == 0:
        return None
    k = int(np.searchsorted(times_ns, t_ns))
    best = None
    for c in (k - 1, k):
        if 0 <= c < len(times_ns) and (best is None or abs(times_ns[c] - t_ns) < abs(times_ns[best] - t_ns)):
            best = c
    if best is None or abs(int(times_ns[best]) - t_ns) > max_dt_ns:
        return None
    return best


def _closure_numbers(run: RunData, pairs: dict[str, PairEvaluation], cfg: EvalConfig) -> list[dict[str, Any]]:
    """Per closure.

    The correction it made (final minus online pose at the closure time, in the run's own world
    frame) and the ground-truth error there before and after.
    """
    out: list[dict[str, Any]] = []
    max_dt_ns = int(round(cfg.max_dt_ms * 1e6))
    for ev in run.loop_closures:
        rec: dict[str, Any] = {
            "index": ev.index,
            "time_ns": ev.time_ns,
            "match_time_ns": ev.match_time_ns,
        }
        rec["recorded"] = {k: v for k, v in ev.fields.items() if isinstance(v, int | float | str | bool)}
        if ev.time_ns is not None and run.online is not None and run.final is not None:
            io_ = _nearest_index(run.online.traj.timestamps_ns, ev.time_ns, max_dt_ns)
            if_ = _nearest_index(run.final.traj.timestamps_ns, ev.time_ns, max_dt_ns)
            if io_ is not None and if_ is not None:
                dt, dr = pose_difference(
                    run.online.traj.world_from_cam[io_ : io_ + 1],
                    run.final.traj.world_from_cam[if_ : if_ + 1],
                )
                rec["correction_m"] = float(dt[0])
                rec["correction_deg"] = float(dr[0])
        for key, name in (("online", "ate_before_m"), ("final", "ate_after_m")):
            pe = pairs.get(key)
            if pe is not None and ev.time_ns is not None:
                k = _nearest_index(pe.times_ns, ev.time_ns, max_dt_ns)
                rec[name] = float(pe.ate_m[k]) if k is not None else None
        out.append(rec)
    return out


def _mesh_numbers(run_metrics: dict[str, Any]) -> dict[str, float]:
    out: dict[str, float] = {}
    for k, v in run_metrics.items():
        if k.lower().startswith("mesh"):
            if isinstance(v, int | float) and not isinstance(v, bool):
                out[k] = float(v)
            elif isinstance(v, dict):
                for k2, v2 in v.items():
                    if isinstance(v2, int | float) and not isinstance(v2, bool):
                        out[f"{k}.{k2}"] = float(v2)
    return out


def _mesh_before_after(mesh: dict[str, float]) -> list[dict[str, Any]]:
    """Before/after rows from recorded mesh errors named ``..before..``/``..after..``."""
    rows = []
    for k, before in mesh.items():
        if "before" not in k:
            continue
        after = mesh.get(k.replace("before", "after"))
        if after is None:
            continue
        change = (after - before) / abs(before) * 100.0 if before else None
        label = k.replace("_before", "").replace("before_", "")
        rows.append(
            {
                "metric": f"{label} (recorded)",
                "key": f"mesh.{k}",
                "before": before,
                "after": after,
                "change_pct": change,
            }
        )
    return rows


def _get(d: Any, *keys: str) -> Any:
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


BEFORE_AFTER_ROWS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("ATE RMSE [m]", ("ate_m", "rmse")),
    ("ATE mean [m]", ("ate_m", "mean")),
    ("ATE median [m]", ("ate_m", "median")),
    ("ATE max [m]", ("ate_m", "max")),
    ("rotation error RMSE [deg]", ("are_deg", "rmse")),
    ("RPE per frame delta, RMSE [m]", ("rpe_frames", "trans_m", "rmse")),
    ("RPE per frame delta, RMSE [deg]", ("rpe_frames", "rot_deg", "rmse")),
    ("RPE per distance, RMSE [m]", ("rpe_distance", "trans_m", "rmse")),
    ("RPE per distance, mean [%]", ("rpe_distance", "trans_pct", "mean")),
    ("KITTI translational error [%]", ("kitti_segments", "t_err_pct")),
    ("KITTI rotational error [deg/100 m]", ("kitti_segments", "r_err_deg_per_100m")),
    ("end-point error [m]", ("end_point", "error_m")),
    ("end-point error, origin aligned [m]", ("end_point", "error_origin_aligned_m")),
)


def _before_after(pairs: dict[str, PairEvaluation]) -> list[dict[str, Any]]:
    rows = []
    for label, path in BEFORE_AFTER_ROWS:
        before = _get(pairs["online"].metrics, *path) if "online" in pairs else None
        after = _get(pairs["final"].metrics, *path) if "final" in pairs else None
        if before is None and after is None:
            continue
        change = None
        if isinstance(before, float) and isinstance(after, float) and before != 0:
            change = (after - before) / abs(before) * 100.0
        rows.append(
            {
                "metric": label,
                "key": ".".join(path),
                "before": before,
                "after": after,
                "change_pct": change,
            }
        )
    return rows


def evaluate_run(run: RunData, gt: TimedTrajectory, cfg: EvalConfig | None = None) -> RunEvaluation:
    """Evaluate the trajectories of a run against ground truth (numbers and pictures)."""
    cfg = cfg or EvalConfig()
    if cfg.align not in ALIGN_MODES:
        raise InputError("--align", f"must be one of {', '.join(ALIGN_MODES)}, got '{cfg.align}'")
    pairs: dict[str, PairEvaluation] = {}
    tracks = {"final": run.final, "online": run.online, "keyframes": run.keyframes}
    if run.online is not None and run.final is run.online:
        tracks["online"] = None
    for key, tt in tracks.items():
        if tt is not None:
            pairs[key] = _eval_one(gt, tt, cfg)
    assert run.final is not None
    max_dt_ns = int(round(cfg.max_dt_ms * 1e6))
    ate_rmse = se3_ate_rmse_m(
        gt.traj.timestamps_ns,
        gt.traj.world_from_cam,
        run.final.traj.timestamps_ns,
        run.final.traj.world_from_cam,
        max_dt_ns,
    )
    metrics: dict[str, Any] = {
        "ate_rmse_m": ate_rmse,
        "run": run.name,
        "run_path": str(run.path) if run.path else None,
        "ground_truth": gt.source,
        "estimate": run.final.source,
        "options": cfg.model_dump(),
        "trajectories": {k: v.metrics for k, v in pairs.items()},
        "loop_closures_recorded": run.loop_closures_recorded,
        "loop_closure_count": len(run.loop_closures),
        "loop_closures": _closure_numbers(run, pairs, cfg),
        "before_after": _before_after(pairs) if "online" in pairs else None,
        "mesh": _mesh_numbers(run.run_metrics),
    }
    if metrics["before_after"] is not None:
        metrics["before_after"] += _mesh_before_after(metrics["mesh"])
    ev = RunEvaluation(run, gt, cfg, pairs, metrics)
    if cfg.plots:
        ev.plots = make_plots(ev)
    return ev


# --------------------------------------------------------------------------- pictures


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


# --------------------------------------------------------------------------- outputs


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
    """Write ``metrics.json``, ``report.md``, ``report.html`` and the PNGs into ``out_dir``
    (atomically, file by file)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name, png in ev.plots.items():
        write_bytes_atomic(out / name, png)
    write_text_atomic(out / "metrics.json", json.dumps(_json_clean(ev.metrics), indent=2, allow_nan=False) + "\n")
    write_text_atomic(out / "report.md", render_markdown(ev))
    write_text_atomic(out / "report.html", render_html(ev))
    return out


# --------------------------------------------------------------------------- many runs

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
    md = [
        "# Comparison of runs",
        "",
        f"Alignment {evals[0].config.align}; `ate_rmse_m` is the SE(3)-aligned ATE RMSE of the "
        "final trajectory; ate_change_pct compares final with online ATE RMSE.",
        "",
        markdown_table(head, rows),
    ]
    md_path = write_text_atomic(out / "comparison.md", "\n".join(md))
    return csv_path, md_path


def markdown_table(head: list[str], rows: list[list[Any]]) -> str:
    """A Markdown table of values, numbers formatted as in the reports (None as a dash)."""
    return _md_table(head, [[_num(v) if not isinstance(v, str) else v for v in r] for r in rows])


def csv_text(head: list[str], rows: list[list[Any]]) -> str:
    """CSV text of a table: floats in full precision (``repr``), None empty."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(head)
    for r in rows:
        w.writerow(["" if v is None else (repr(v) if isinstance(v, float) else v) for v in r])
    return buf.getvalue()


def plain_run(est: TimedTrajectory) -> RunData:
    """A single estimate (``--ref/--est``) as a run with only a final trajectory."""
    return RunData(Path(est.source).stem, None, est)
