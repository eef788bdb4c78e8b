"""Command line of loopmodel (typer + rich). The only place that prints.

Command groups live in their own modules (``cli/sequences.py``, ``cli/evaluate.py``, ...); this
module imports them so that their commands register on :data:`app`, and holds :func:`main`.
"""

from __future__ import annotations

import sys
import warnings

import typer

from loopmodel.cli import configuration, estimation, evaluate, loop, sequences, vvs  # noqa: F401  (they register)
from loopmodel.cli.common import app, console, err_console, progress_bar
from loopmodel.cli.view import view as view_results
from loopmodel.cli.vvs import vvs_app
from loopmodel.errors import LoopmodelError

__all__ = ["app", "console", "err_console", "main", "progress_bar"]

_PROGRAM = [False]


def _ignore_further_interrupts() -> None:
    """Once a command was interrupted, another Ctrl-C must not break the exit.

    Worker pools and temporary files are being cleaned up. Only for the program itself
    (``_PROGRAM``), not for ``main`` called from Python.
    """
    import signal
    import threading

    if _PROGRAM[0] and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def main(argv: list[str] | None = None) -> int:
    """Entry point: runs the app, turns loopmodel errors into one line and exit status 2."""
    _PROGRAM[0] = argv is None
    if _PROGRAM[0]:
        from loopmodel.open3d_import import without_plotly_viewer

        without_plotly_viewer()  # no command draws with plotly: open3d's import 0.7 s CPU less (gen20)
    try:
        return _main(list(sys.argv[1:] if argv is None else argv))
    finally:
        if _PROGRAM[0]:
            _ignore_signals_at_exit()


def _ignore_signals_at_exit() -> None:
    """Ignore Ctrl-C and SIGTERM once the command is over and its exit status decided.

    Its files are complete: a signal arriving while the interpreter shuts down must neither kill it
    by the default action (exit 143) nor print a traceback (issue 34).
    """
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, signal.SIG_IGN)


def _main(args: list[str]) -> int:
    debug = "--debug" in args
    if not debug:  # numeric warnings are for developers; the results say what went wrong
        warnings.filterwarnings("ignore", category=RuntimeWarning)
    from loopmodel.cli.signals import caused_by_interrupt, sigterm_as_interrupt

    try:
        with sigterm_as_interrupt():  # SIGTERM is Ctrl-C everywhere (temporary files removed)
            rv = app(args=args, prog_name="loopmodel", standalone_mode=False)
        # typer turns KeyboardInterrupt into Exit(130) and, outside standalone mode, returns
        # the code instead of raising it
        if isinstance(rv, int) and rv != 0:
            if rv == 130:
                _ignore_further_interrupts()
                err_console.print("interrupted")
            return rv
    except LoopmodelError as exc:
        if debug:
            raise
        err_console.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        return 2
    except typer.Exit as exc:
        if exc.exit_code == 130:
            _ignore_further_interrupts()
        return int(exc.exit_code)
    except (typer.Abort, KeyboardInterrupt):
        _ignore_further_interrupts()
        err_console.print("interrupted")
        return 130
    except typer.exceptions.TyperException as exc:  # usage errors (click's, vendored by typer)
        show = getattr(exc, "show", None)
        message, ctx = getattr(exc, "format_message", None), getattr(exc, "ctx", None)
        if callable(message) and ctx is not None:  # bad usage: one line, and where to read more
            err_console.print(
                f"error: {message()} (see: {ctx.command_path} --help)", highlight=False, soft_wrap=True, markup=False
            )
        elif callable(show):
            show()
        else:
            err_console.print(f"error: {exc}")
        return int(getattr(exc, "exit_code", 2))
    except OSError as exc:  # the environment (full disk, read-only folder): one line naming the path
        if debug:
            raise
        where = f"{exc.filename}: " if exc.filename else ""
        err_console.print(f"[red]I/O error:[/red] {where}{exc.strerror or exc}", highlight=False, soft_wrap=True)
        return 1
    except Exception as exc:  # a bug, not bad input: say so in one line unless --debug
        if caused_by_interrupt(exc):  # a Ctrl-C inside an extension module's import
            _ignore_further_interrupts()
            err_console.print("interrupted")
            return 130
        if debug:
            raise
        err_console.print(
            f"[red]internal error:[/red] {type(exc).__name__}: {exc} (rerun with --debug for the traceback)",
            highlight=False,
        )
        return 1
    return 0


app.command("view")(view_results)

from loopmodel.cli.calibrate import calibrate_app, turntable_app  # noqa: E402

app.add_typer(calibrate_app, name="calibrate")

app.add_typer(turntable_app, name="turntable")

from loopmodel.cli.batch import batch_app  # noqa: E402

app.add_typer(batch_app, name="batch")

from loopmodel.cli.vvs_images import vvs_render, vvs_track  # noqa: E402

vvs_app.command("render")(vvs_render)

vvs_app.command("track")(vvs_track)

from loopmodel.cli.help import document  # noqa: E402
from loopmodel.cli.map import map_app  # noqa: E402, F401  (loopmodel map info|merge)

document(app)  # help panels, the flow's order and one example per command (issue 35)

if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
