"""The numbers of an evaluation.

Trajectory errors before (online) and after (final) loop closure, per-closure corrections, and
the mesh errors a run recorded: every number of ``metrics.json`` whose key starts with
``mesh`` (or inside a ``mesh`` object).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import EvalConfig
from loopmodel.display import extent_m
from loopmodel.errors import InputError
from loopmodel.eval.inputs import (
    RunData,
    TimedTrajectory,
    check_comparable,
)
from loopmodel.eval.trajectory_metrics import (
    ALIGN_MODES,
    PairEvaluation,
    evaluate_pair,
    pose_difference,
    se3_ate_rmse_m,
)

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
        # the scale of the sequence: reports show lengths in mm below 10 m, else m (loopmodel.display)
        "ground_truth_extent_m": extent_m(gt.traj.positions_m),
    }
    if metrics["before_after"] is not None:
        metrics["before_after"] += _mesh_before_after(metrics["mesh"])
    ev = RunEvaluation(run, gt, cfg, pairs, metrics)
    if cfg.plots:
        from loopmodel.eval.render import make_plots  # render reads RunEvaluation: no cycle at import

        ev.plots = make_plots(ev)
    return ev
