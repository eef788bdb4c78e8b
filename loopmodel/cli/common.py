"""Shared pieces of the command line: the typer app, consoles, progress bar, common options."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from loopmodel import __version__
from loopmodel.cli.help import FlowGroup

console = Console()

err_console = Console(stderr=True)

app = typer.Typer(
    name="loopmodel",
    cls=FlowGroup,
    help="Close-range 3-D modelling with a hand-held stereo camera and a laser-stripe profiler.",
    epilog="Start with: loopmodel simulate scan --preset orbit -o scan.mcap; loopmodel run scan.mcap -o results; "
    "loopmodel eval results/scan",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)

config_app = typer.Typer(help="Configuration.", no_args_is_help=True)

app.add_typer(config_app, name="config")

ConfigOption = Annotated[
    list[Path] | None,
    typer.Option(
        "--config",
        "-c",
        metavar="FILE",
        help="YAML file overriding the defaults; give it again to layer files (later ones override earlier ones)",
    ),
]

LeftTopicOption = Annotated[str | None, typer.Option("--left", help="Left image topic of a bag (default: guessed)")]

RightTopicOption = Annotated[str | None, typer.Option("--right", help="Right image topic of a bag (default: guessed)")]

CalibOption = Annotated[
    Path | None,
    typer.Option(
        "--calib",
        help="Bag without CameraInfo: EuRoC sensor.yaml folder, camchain.yaml, calibrate-stereo YAML or calib.txt",
    ),
]


def _version_callback(value: bool) -> None:
    if value:
        console.print(f"loopmodel {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_version_callback, is_eager=True, help="Print the version")
    ] = False,
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks and debug logging")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Info logging")] = False,
) -> None:
    level = logging.DEBUG if debug else logging.INFO if verbose else logging.WARNING
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


def progress_bar(*extra: Any) -> Progress:
    """The project's progress bar (frames done / total, rate, time left).

    Redrawn ten times a second on a terminal only: elsewhere (a log file, a bench capturing the output)
    rich shows just the last state, and its refresh thread built the unseen bar all the same: 0.16 ms of
    CPU a frame, holding the interpreter beside the tracking thread (orb17: `bench peer`'s orbit run, load 10).
    """
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        *extra,
        TimeRemainingColumn(),
        console=err_console,
        transient=False,
        auto_refresh=err_console.is_terminal,
    )
