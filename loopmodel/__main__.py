"""``python -m loopmodel`` and the ``loopmodel`` script: the command line.

The signals are set up before the (slow) import of the command line, so that a Ctrl-C or a
SIGTERM while it loads exits 130 with one line, not a traceback or the default action's 143.
"""

import os
import signal
import sys
from typing import NoReturn


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def _exit_interrupted() -> NoReturn:
    """Exit 130 after the exit handlers, without the interpreter's own finalisation.

    An extension module that ran Python code while the Ctrl-C landed leaves the interpreter's
    "unhandled KeyboardInterrupt" mark set although the interrupt was handled, and a plain exit then
    dies by SIGINT (-2): seen with the signal inside the command line's imports and, 0.3 s after
    numpy loaded, inside the command (test_ctrl_c_while_the_cli_imports, 1 run in about 20).
    """
    import atexit

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    sys.stdout.flush()
    sys.stderr.flush()
    atexit._run_exitfuncs()  # worker pools, temporary folders: as a normal exit would
    os._exit(130)


def entry() -> int:
    """Install the SIGTERM handler, import the command line, run it."""
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        from loopmodel.cli import main

        code = main()
    except KeyboardInterrupt:  # while importing, or one arriving as main() returns
        sys.stderr.write("interrupted\n")
        _exit_interrupted()
    if code == 130:  # interrupted, its one line written
        _exit_interrupted()
    return code


if __name__ == "__main__":
    sys.exit(entry())
