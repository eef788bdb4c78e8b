"""``loopmodel eval``: trajectory and mesh errors of runs against ground truth, reports."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import typer
from rich.table import Table

from loopmodel.cli.common import (
    ConfigOption,
    app,
    console,
)
from loopmodel.config import AlignMode, apply_overrides, load_config
from loopmodel.errors import InputError

if TYPE_CHECKING:
    from loopmodel.display import Formatter
    from loopmodel.eval.evaluation import RunEvaluation


@app.command("eval")
def eval_command(
    runs: Annotated[list[Path] | None, typer.Argument(help="Results folders")] = None,
    gt: Annotated[Path | None, typer.Option("--gt", help="Ground truth file or sequence")] = None,
    ref: Annotated[Path | None, typer.Option("--ref", help="Reference trajectory")] = None,
    est: Annotated[Path | None, typer.Option("--est", help="Estimated trajectory")] = None,
    align: Annotated[AlignMode | None, typer.Option("--align", help="Alignment to the ground truth")] = None,
    first_n: Annotated[int | None, typer.Option("--first-n", help="Align on N poses")] = None,
    max_dt_ms: Annotated[float | None, typer.Option("--max-dt-ms", help="Max time gap")] = None,
    rpe_delta_m: Annotated[float | None, typer.Option("--rpe-delta-m", help="RPE metres")] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder")] = None,
    plots: Annotated[bool, typer.Option("--plots/--no-plots", help="Also draw the pictures")] = True,
    plot_mode: Annotated[
        Literal["auto", "xy", "xz", "yz", "xyz"] | None,
        typer.Option(
            "--plot-mode",
            help="Plane of the path plots, as evo's --plot_mode (default auto: xz for camera-frame ground truth "
            "such as KITTI, xy for z-up worlds)",
        ),
    ] = None,
    config: ConfigOption = None,
) -> None:
    """Evaluate trajectories against ground truth: ATE, RPE, drift, loop-closure effect, report."""
    from loopmodel.eval import report as rep

    cfg = load_config(config)
    overrides = {
        "align": align,
        "first_n": first_n,
        "max_dt_ms": max_dt_ms,
        "rpe_delta_m": rpe_delta_m,
        "plot_mode": plot_mode,
    }
    ecfg = apply_overrides(cfg.eval, overrides, {k: "--" + k.replace("_", "-") for k in overrides})
    if not plots:
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
    console.print(eval_table(evals))
    for ev, target in evals:  # below the table: a path never wraps inside a column
        line = f"report: {target / 'report.html'}" + (f" ({ev.metrics['run']})" if len(evals) > 1 else "")
        console.print(line, soft_wrap=True, highlight=False)
    if len(evals) > 1:
        cmp_dir = out or Path("eval_comparison")
        csv_path, md_path = rep.write_comparison([e for e, _ in evals], cmp_dir)
        console.print(f"comparison: {csv_path} {md_path}")


def eval_table(evals: list[tuple[RunEvaluation, Path]]) -> Table:
    """The table printed by ``loopmodel eval``: one row per run, lengths in the unit of its sequence.

    The reports' paths are printed below it.
    """
    from rich.markup import escape

    from loopmodel.display import num
    from loopmodel.eval.evaluation import _get
    from loopmodel.eval.render import report_formatter

    fmts = [report_formatter(ev) for ev, _ in evals]
    same = len({f.length.symbol for f in fmts}) == 1
    u = f" [{fmts[0].length.symbol}]" if same and fmts else ""
    table = Table(title="loopmodel eval")
    for col in ("run", "matched", f"ATE RMSE final{u}", f"ATE RMSE online{u}", f"RPE per frame{u}", "closures"):
        table.add_column(escape(col), justify="left" if col == "run" else "right")
    for (ev, _target), fmt in zip(evals, fmts, strict=True):
        m = ev.metrics
        tr = m["trajectories"]

        def length(v: float | None, f: Formatter = fmt) -> str:
            return f.value("ate_m", v) if same else f.length_text(v)

        table.add_row(
            m["run"],
            num(tr["final"]["matched"]),
            length(m["ate_rmse_m"]),
            length(_get(tr, "online", "ate_m", "rmse")),
            length(_get(tr, "final", "rpe_frames", "trans_m", "rmse")),
            num(m["loop_closure_count"]),
        )
    return table
