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


@app.command("givens-sim")
def givens_sim(
    frames: Annotated[int, typer.Option(help="frames along the two strips")] = 88,
    points: Annotated[int, typer.Option(help="object points of the test field")] = 166,
    blunders: Annotated[float, typer.Option(help="fraction of image points with a blunder")] = 0.02,
    seed: Annotated[int, typer.Option(help="random seed")] = 0,
    config: ConfigOption = None,
) -> None:
    """Sequential Givens bundle with data snooping on the synthetic OLTRIS-size test field."""
    from loopmodel.backend.givens_bundle import GivensScreen
    from loopmodel.backend.testfield import make_testfield

    if frames < 2 or points < 5:
        raise InputError(None, "--frames must be >= 2 and --points >= 5")
    if not 0.0 <= blunders < 1.0:
        raise InputError(None, f"--blunders must be in [0, 1), got {blunders}")
    cfg = load_config(config).givens
    tf = make_testfield(n_frames=frames, n_points=points, blunder_fraction=blunders, seed=seed)
    scr = GivensScreen.from_config(tf.camera, cfg.model_copy(update={"sigma_px": tf.sigma_px}))
    ctrl = set(tf.control.tolist())
    flagged: set[tuple[int, int]] = set()
    truth: set[tuple[int, int]] = set()
    with progress_bar() as bar:
        task = bar.add_task("frames", total=frames)
        for f, (ids, uv) in enumerate(tf.observations):
            for i in ids.tolist():
                if i not in scr.bundle.points:
                    scr.add_point(i, tf.points_world[i], 1e-4 if i in ctrl else None)
            mask = scr.screen(f, tf.world_from_cam[f], ids.tolist(), uv, first_frame=(f == 0))
            truth |= {(f, i) for i, b in zip(ids.tolist(), tf.blunder[f], strict=True) if b}
            flagged |= {(f, i) for i, ok in zip(ids.tolist(), mask, strict=True) if not ok}
            flagged |= set(scr.late_rejections())
            bar.update(task, completed=f + 1)
    est = scr.bundle.est
    table = Table(title="sequential Givens bundle")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for k, v in (
        ("unknowns", est.n_parameters),
        ("observation rows", est.n_observations),
        ("sigma0 (a posteriori)", f"{est.variance_factor() ** 0.5:.3f}"),
        ("tested / rejected", f"{scr.stats.tested} / {scr.stats.rejected}"),
        ("blunders injected / caught", f"{len(truth)} / {len(truth & flagged)}"),
        ("false alarms", len(flagged - truth)),
        ("kernels", __import__("loopmodel.backend.givens", fromlist=["KERNELS"]).KERNELS),
    ):
        table.add_row(k, str(v))
    console.print(table)


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
