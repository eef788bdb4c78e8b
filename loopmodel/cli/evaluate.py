"""``loopmodel eval``: trajectory and mesh errors of runs against ground truth, reports."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from loopmodel.cli.common import (
    ConfigOption,
    _length,
    app,
    console,
)
from loopmodel.config import apply_overrides, load_config
from loopmodel.errors import InputError


@app.command("eval")
def eval_command(
    runs: Annotated[list[Path] | None, typer.Argument(help="Results folders")] = None,
    gt: Annotated[Path | None, typer.Option("--gt", help="Ground truth file or sequence")] = None,
    ref: Annotated[Path | None, typer.Option("--ref", help="Reference trajectory")] = None,
    est: Annotated[Path | None, typer.Option("--est", help="Estimated trajectory")] = None,
    align: Annotated[str | None, typer.Option("--align", help="se3, sim3, origin, none")] = None,
    first_n: Annotated[int | None, typer.Option("--first-n", help="Align on N poses")] = None,
    max_dt_ms: Annotated[float | None, typer.Option("--max-dt-ms", help="Max time gap")] = None,
    rpe_delta_m: Annotated[float | None, typer.Option("--rpe-delta-m", help="RPE metres")] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder")] = None,
    no_plots: Annotated[bool, typer.Option("--no-plots", help="Skip the pictures")] = False,
    config: ConfigOption = None,
) -> None:
    """Evaluate trajectories against ground truth: ATE, RPE, drift, loop-closure effect, report."""
    from loopmodel.eval import report as rep

    cfg = load_config(config)
    overrides = {"align": align, "first_n": first_n, "max_dt_ms": max_dt_ms, "rpe_delta_m": rpe_delta_m}
    ecfg = apply_overrides(cfg.eval, overrides, {k: "--" + k.replace("_", "-") for k in overrides})
    if no_plots:
        ecfg.plots = False
    runs = list(runs or [])
    if (ref is None) != (est is None):
        raise InputError("--ref/--est", "give both --ref and --est")
    if ref is not None and (runs or gt is not None):
        raise InputError("--ref/--est", "use --ref/--est or results folders with --gt, not both")
    if ref is None and not runs:
        raise InputError(None, "nothing to evaluate: give results folders or --ref FILE --est FILE")
    evals = []
    if ref is not None and est is not None:
        g = rep.load_ground_truth(ref, cfg.sequence)
        e = rep.load_trajectory_file(est, cfg.sequence.kitti_rate_hz)
        ev = rep.evaluate_run(rep.plain_run(e), g, ecfg)
        target = out or Path("eval_" + est.stem)
        rep.write_outputs(ev, target)
        evals.append((ev, target))
    else:
        for run_path in runs:
            run = rep.load_run(run_path, cfg.sequence.kitti_rate_hz)
            gt_path = gt or rep.ground_truth_hint(run)
            if gt_path is None:
                raise InputError(run_path, "no ground truth: pass --gt FILE|SEQUENCE")
            g = rep.load_ground_truth(gt_path, cfg.sequence)
            ev = rep.evaluate_run(run, g, ecfg)
            if out is None:
                target = run_path / "eval"
            else:
                target = out / run.name if len(runs) > 1 else out
            rep.write_outputs(ev, target)
            evals.append((ev, target))
    table = Table(title="loopmodel eval")
    cols = ("run", "matched", "ATE final", "ATE online", "RPE/frame", "closures")
    for col in (*cols, "report"):
        table.add_column(col)
    for ev, target in evals:
        m = ev.metrics
        tr = m["trajectories"]
        online = tr.get("online", {}).get("ate_m", {}).get("rmse")
        table.add_row(
            m["run"],
            str(tr["final"]["matched"]),
            _length(m["ate_rmse_m"]),
            _length(online),
            _length(tr["final"].get("rpe_frames", {}).get("trans_m", {}).get("rmse")),
            str(m["loop_closure_count"]),
            str(target / "report.md"),
        )
    console.print(table)
    if len(evals) > 1:
        cmp_dir = out or Path("eval_comparison")
        csv_path, md_path = rep.write_comparison([e for e, _ in evals], cmp_dir)
        console.print(f"comparison: {csv_path} {md_path}")
