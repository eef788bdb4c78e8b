"""``loopmodel batch PLAN.yaml`` and ``loopmodel batch status DIR``: many runs on Dask."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table
from typer.core import TyperGroup


class _PlanFirstGroup(TyperGroup):
    """``loopmodel batch PLAN.yaml ...`` is ``loopmodel batch run PLAN.yaml ...``."""

    def parse_args(self, ctx: Any, args: list[str]) -> list[str]:  # ctx: typer's vendored click Context
        if args and args[0] not in self.commands and not args[0].startswith("-"):
            args = ["run", *args]
        return super().parse_args(ctx, args)


batch_app = typer.Typer(
    cls=_PlanFirstGroup,
    help="Many runs: sequences x configuration variants on Dask (LocalCluster or a scheduler address).",
    no_args_is_help=True,
)


def _console() -> tuple[Any, Any]:
    from loopmodel.cli.common import console, err_console

    return console, err_console


@batch_app.command("run")
def batch_run(
    plan_path: Annotated[Path, typer.Argument(metavar="PLAN.yaml", help="Batch plan (sequences, base, grid/variants)")],
    scheduler: Annotated[
        str, typer.Option("--scheduler", help="local (a LocalCluster here) or tcp://HOST:PORT of a running cluster")
    ] = "local",
    workers: Annotated[
        int | None,
        typer.Option("--workers", min=1, help="local: worker processes (default one per core); tcp: wait for N"),
    ] = None,
    out: Annotated[
        Path | None, typer.Option("--out", "-o", help="Results folder (default results/<plan name>)")
    ] = None,
    plots: Annotated[bool, typer.Option("--plots/--no-plots", help="Also draw the summary's pictures")] = True,
) -> None:
    """Run every (sequence, variant) task of a plan.

    Each into its own results folder keyed by its identity, evaluated against ground truth; finished
    tasks are skipped; writes summary.csv, summary.md and plots. Ctrl-C cancels and keeps every
    finished result.
    """
    from loopmodel.batch import load_manifest, load_plan, open_client, run_batch, write_summary
    from loopmodel.batch.runner import BatchState, dashboard_address

    console, err_console = _console()
    plan = load_plan(plan_path)
    out_dir = out or Path("results") / plan.name
    n_tasks = len(plan.sequences) * len(plan.variants)
    progress = Progress(
        TextColumn("[bold]tasks"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[done]} done, {task.fields[running]} running, {task.fields[failed]} failed"),
        TextColumn("{task.fields[skipped]} skipped"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err_console,
    )
    bar = progress.add_task("tasks", total=n_tasks, done=0, running=0, failed=0, skipped=0)

    def update(state: BatchState) -> None:
        progress.update(
            bar,
            completed=state.finished,
            total=state.total,
            done=state.done,
            running=state.running,
            failed=state.failed,
            skipped=state.skipped,
        )

    with contextlib.ExitStack() as stack:

        def client_factory() -> Any:
            client = stack.enter_context(open_client(scheduler, workers, plan.threads_per_task))
            link = dashboard_address(client)
            n = len(client.scheduler_info().get("workers", {}))
            err_console.print(f"Dask scheduler {client.scheduler.address}, {n} worker(s)")
            err_console.print(
                f"dashboard: {link}" if link else "dashboard: unavailable (the scheduler runs none; pip install bokeh)"
            )
            return client

        try:
            with progress:
                outcome = run_batch(plan, out_dir, client_factory, update)
        except KeyboardInterrupt:
            err_console.print(f"interrupted; finished results are kept in {out_dir}; run the same command to continue")
            raise
    paths = write_summary(load_manifest(out_dir.resolve()), out_dir, plots=plots)
    done = sum(r.get("status") == "done" for r in outcome.records)
    failed = [r for r in outcome.records if r.get("status") != "done"]
    for r in failed:
        err_console.print(f"[red]failed[/red] {r['task']}: {r.get('error')}", highlight=False, soft_wrap=True)
    console.print(
        f"{len(outcome.records)} tasks: {done} done ({outcome.skipped} already finished), {len(failed)} failed "
        f"in {outcome.wall_s:.1f} s"
    )
    console.print(f"summary: {paths['csv']} {paths['md']}")
    if failed:
        raise typer.Exit(1)


@batch_app.command("status")
def batch_status_cmd(
    folder: Annotated[Path, typer.Argument(help="Results folder of a batch (holds batch.json)")],
    show_all: Annotated[bool, typer.Option("--all", help="List every task, not only unfinished ones")] = False,
) -> None:
    """State of a batch that is running, was interrupted or has finished.

    Tasks done, running, failed and pending.
    """
    import json

    from loopmodel.batch import batch_status, load_manifest
    from loopmodel.batch.runner import RUNNING_FILE
    from loopmodel.io.atomic import pid_alive

    console, _ = _console()
    tasks = load_manifest(folder.resolve())
    states = batch_status(tasks)
    counts: dict[str, int] = {}
    for _, s, _ in states:
        counts[s] = counts.get(s, 0) + 1
    client = None
    marker = folder / RUNNING_FILE
    if marker.is_file():
        try:
            client = json.loads(marker.read_text())
        except ValueError:
            client = None
    if client is not None and pid_alive(int(client.get("pid", -1))):
        state = f"running (client pid {client['pid']} on {client.get('host')}, scheduler {client.get('scheduler')})"
    elif counts.get("done", 0) == len(tasks):
        state = "finished"
    else:
        state = "stopped (run the plan again to continue)"
    table = Table(title=f"batch {folder}: {state}")
    for col in ("task", "sequence", "variant", "status", "detail"):
        table.add_column(col)
    from loopmodel.batch.summary import eval_metrics
    from loopmodel.display import Formatter, num

    every = show_all or all(s == "done" for _, s, _ in states)  # a finished batch: list its tasks
    for t, s, rec in states:
        if every or s != "done":
            detail = (rec or {}).get("error") or ""
            if s == "done" and rec is not None and rec.get("ate_rmse_m") is not None:
                fmt = Formatter.for_scale((eval_metrics(t) or {}).get("ground_truth_extent_m"))
                detail = f"ATE RMSE {fmt.length_text(rec['ate_rmse_m'])}, task {num(rec.get('task_s'))} s (run + eval)"
            table.add_row(t.task_id, t.sequence_name, t.variant, s, str(detail))
    console.print(table)
    console.print(", ".join(f"{counts.get(s, 0)} {s}" for s in ("done", "running", "failed", "pending")))
