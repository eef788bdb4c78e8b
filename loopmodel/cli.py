"""Command line of loopmodel (typer + rich). The only module that prints."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Annotated, Any

import click
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from loopmodel import __version__
from loopmodel.config import dump_config, load_config
from loopmodel.errors import InputError, LoopmodelError

console = Console()
err_console = Console(stderr=True)

app = typer.Typer(
    name="loopmodel",
    help="Close-range 3-D modelling with a hand-held stereo camera and a laser-stripe profiler.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
config_app = typer.Typer(help="Configuration.", no_args_is_help=True)
app.add_typer(config_app, name="config")

ConfigOption = Annotated[Path | None, typer.Option("--config", "-c", help="YAML file overriding defaults")]


def _version_callback(value: bool) -> None:
    if value:
        console.print(f"loopmodel {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[bool, typer.Option("--version", callback=_version_callback, is_eager=True, help="Print the version")] = False,
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks and debug logging")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Info logging")] = False,
) -> None:
    level = logging.DEBUG if debug else logging.INFO if verbose else logging.WARNING
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


def progress_bar(*extra: Any) -> Progress:
    """The project's progress bar (frames done / total, rate, time left)."""
    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        *extra, TimeRemainingColumn(), console=err_console, transient=False,
    )


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, dict):
        return ", ".join(f"{k}={_fmt(x)}" for k, x in v.items())
    if isinstance(v, list):
        return "x".join(str(x) for x in v) if all(isinstance(x, int) for x in v) else ", ".join(map(str, v))
    return str(v)


@app.command()
def info(
    path: Annotated[Path, typer.Argument(help="MCAP file, EuRoC or KITTI folder")],
    config: ConfigOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table")] = False,
) -> None:
    """Describe a sequence: format, frames, duration, image size, calibration, ground truth, stripes."""
    from loopmodel.io.sequence import open_sequence

    cfg = load_config(config)
    desc = open_sequence(path, cfg.sequence).describe()
    if as_json:
        console.print_json(json.dumps(desc))
        return
    table = Table(title=str(path), show_header=False)
    for k, v in desc.items():
        if k == "topics":
            v = ", ".join(f"{t} [{d['type'].split('/')[-1]}: {d['messages']}]" for t, d in v.items())
        table.add_row(k, _fmt(v))
    console.print(table)


@app.command()
def convert(
    src: Annotated[Path, typer.Argument(help="EuRoC or KITTI folder (or MCAP)")],
    dst: Annotated[Path, typer.Argument(help="Output .mcap file")],
    config: ConfigOption = None,
    image_format: Annotated[str, typer.Option("--image-format", help="raw, png or jpeg")] = "png",
) -> None:
    """Convert a sequence to MCAP with ROS 2 messages (topics of DESIGN.md)."""
    from loopmodel.io.sequence import convert_to_mcap, open_sequence

    if dst.suffix.lower() != ".mcap":
        raise InputError(dst, "output must end in .mcap")
    if image_format not in ("raw", "png", "jpeg"):
        raise InputError(None, f"--image-format must be raw, png or jpeg, got '{image_format}'")
    cfg = load_config(config)
    seq = open_sequence(src, cfg.sequence)
    with progress_bar() as bar:
        task = bar.add_task("convert", total=len(seq))
        convert_to_mcap(seq, dst, cfg.sequence, image_format, progress=lambda i: bar.update(task, completed=i))
    console.print(f"wrote {dst} ({dst.stat().st_size / 2**20:.1f} MiB, {len(seq)} frames)")


simulate_app = typer.Typer(help="Synthetic data.", no_args_is_help=True)
app.add_typer(simulate_app, name="simulate")


@simulate_app.command("scan")
def simulate_scan_cmd(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output .mcap file")],
    preset: Annotated[str | None, typer.Option("--preset", help="orbit, sweeps or browse")] = None,
    frames: Annotated[int | None, typer.Option("--frames", help="Number of frames")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Random seed")] = None,
    scene: Annotated[str | None, typer.Option("--scene", help="bust, box or mix")] = None,
    width: Annotated[int | None, typer.Option("--width", help="Image width (px)")] = None,
    height: Annotated[int | None, typer.Option("--height", help="Image height (px)")] = None,
    baseline: Annotated[float | None, typer.Option("--baseline", help="Stereo baseline (m)")] = None,
    rate: Annotated[float | None, typer.Option("--rate", help="Frame rate (Hz)")] = None,
    noise: Annotated[float | None, typer.Option("--noise", help="Image noise sigma (grey levels)")] = None,
    fault: Annotated[list[str] | None, typer.Option("--fault", help="KIND:FIRST[-LAST], repeatable; KIND: dropped, blackout, blur, occluder, duplicate_timestamp")] = None,
    laser_image: Annotated[bool | None, typer.Option("--laser-image/--no-laser-image", help="Also write /laser/image")] = None,
    workers: Annotated[int | None, typer.Option("--workers", help="Render processes (0: one per core)")] = None,
    image_format: Annotated[str | None, typer.Option("--image-format", help="png, jpeg or raw")] = None,
    config: ConfigOption = None,
) -> None:
    """Generate a synthetic hand-held scan (stereo, laser stripes, ground truth) as MCAP."""
    from loopmodel.sim.generate import resolve_config, simulate_scan

    cfg = load_config(config)
    sim = resolve_config(
        cfg.simulation, preset,
        {"trajectory": {"frames": frames, "rate_hz": rate}, "scene": {"kind": scene},
         "camera": {"width_px": width, "height_px": height, "baseline_m": baseline},
         "render": {"noise_sigma": noise}, "laser": {"image": laser_image}},
        fault,
    )
    updates: dict[str, Any] = {}
    if seed is not None:
        updates["seed"] = seed
    if workers is not None:
        updates["workers"] = workers
    if image_format is not None:
        updates["image_format"] = image_format
    if updates:
        sim = resolve_config(sim.model_copy(update=updates))
    with progress_bar() as bar:
        task = bar.add_task("simulate", total=sim.trajectory.frames)
        res = simulate_scan(sim, out, cfg.sequence.topics, lambda k, n: bar.update(task, completed=k), preset)
    console.print(
        f"wrote {res.path} ({res.size_bytes / 2**20:.1f} MiB, {res.frames_written} frames, "
        f"{res.stripes_written} stripes, {len(res.faults)} faults) in {res.seconds:.1f} s: "
        f"{res.ms_per_frame:.1f} ms/frame (setup {res.setup_seconds:.1f} s, render {res.render_ms_median:.1f} ms/frame per worker)"
    )


@config_app.command("dump")
def config_dump(config: ConfigOption = None) -> None:
    """Print the effective configuration (defaults overridden by --config) as YAML."""
    sys.stdout.write(dump_config(load_config(config)))


def main(argv: list[str] | None = None) -> int:
    """Entry point: runs the app, turns loopmodel errors into one line and exit status 2."""
    args = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in args
    try:
        app(args=args, prog_name="loopmodel", standalone_mode=False)
    except LoopmodelError as exc:
        if debug:
            raise
        err_console.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        return 2
    except click.exceptions.Exit as exc:
        return int(exc.exit_code)
    except click.ClickException as exc:
        exc.show()
        return 2
    except (click.exceptions.Abort, KeyboardInterrupt):
        err_console.print("interrupted")
        return 130
    except Exception as exc:  # a bug, not bad input: say so in one line unless --debug
        if debug:
            raise
        err_console.print(f"[red]internal error:[/red] {type(exc).__name__}: {exc} (rerun with --debug for the traceback)", highlight=False)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
