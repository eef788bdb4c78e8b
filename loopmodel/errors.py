"""Exceptions of loopmodel.

Every problem with the user's input raises a subclass of :class:`LoopmodelError` whose
message names the file, topic or key and what was expected; the CLI prints that one line
and exits with status 2.
"""

from __future__ import annotations

from pathlib import Path


class LoopmodelError(Exception):
    """Base class of every error loopmodel raises on purpose."""


class InputError(LoopmodelError):
    """A file, folder, topic or value supplied by the user is not what was expected."""

    def __init__(self, source: str | Path | None, problem: str) -> None:
        self.source = str(source) if source is not None else None
        self.problem = problem
        super().__init__(f"{self.source}: {problem}" if self.source else problem)


class FormatError(InputError):
    """A file has an unknown layout, a wrong column count or corrupt content."""


class CalibrationError(InputError):
    """A calibration is missing, non-finite or physically impossible."""


class ConfigError(InputError):
    """A configuration file has an unknown key or an invalid value."""


class EstimationError(LoopmodelError):
    """An estimator was used in a way that would corrupt its state."""


class RunInterrupted(KeyboardInterrupt):
    """A run stopped by Ctrl-C or SIGTERM after writing its results into ``folder``.

    ``note``: where they are when that is not the requested folder (kept beside an older run).
    """

    def __init__(self, folder: Path | None, note: str = "") -> None:
        super().__init__(note or "interrupted")
        self.folder = folder
        self.note = note
