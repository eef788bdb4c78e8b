"""``python -m loopmodel`` and the ``loopmodel`` script: the command line.

The signals are set up before the (slow) import of the command line, so that a Ctrl-C or a
SIGTERM while it loads exits 130 with one line, not a traceback or the default action's 143.
"""

import os
import signal
import sys


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def entry() -> int:
    """Install the SIGTERM handler, import the command line, run it."""
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        from loopmodel.cli import main

        return main()
    except KeyboardInterrupt:  # while importing, or one arriving as main() returns
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        sys.stderr.write("interrupted\n")
        sys.stderr.flush()
        sys.stdout.flush()
        # nothing was started yet; a plain exit could still die by SIGINT: an extension module
        # that ran Python code while the Ctrl-C landed leaves the interpreter's "unhandled
        # KeyboardInterrupt" mark set although it was handled here
        os._exit(130)


if __name__ == "__main__":
    sys.exit(entry())
