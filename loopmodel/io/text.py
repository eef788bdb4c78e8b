"""Reading small text inputs (calibrations, pose lists, timestamps) with one-line errors."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from loopmodel.errors import FormatError, InputError

#: Larger "text" inputs are refused before reading (a pose list of 10^6 rows is ~150 MB).
MAX_TEXT_BYTES = 1 << 30


def read_text_file(path: str | Path, what: str = "text file") -> str:
    """The UTF-8 text of ``path``.

    :class:`FormatError` when it is not text (random bytes), :class:`InputError` when it cannot be
    read (a folder, a FIFO, no permission, too large).
    """
    p = Path(path)
    try:
        require_existing_file(p, what)
        if p.stat().st_size > MAX_TEXT_BYTES:
            raise InputError(p, f"{what} of {p.stat().st_size} bytes is larger than {MAX_TEXT_BYTES}")
        return p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FormatError(p, f"not a UTF-8 {what} (undecodable byte at offset {exc.start})") from None
    except OSError as exc:
        raise InputError(p, f"cannot read the {what}: {exc.strerror or exc.__class__.__name__}") from None


def require_regular_file(path: Path, what: str = "file") -> os.stat_result:
    """``os.stat`` of ``path``; :class:`InputError` unless it is a regular file.

    A FIFO, a device, a folder or a symbolic-link loop are named as such, before anything opens them.
    """
    try:
        st = os.stat(path)
    except OSError as exc:
        raise InputError(path, f"cannot read the {what}: {exc.strerror or type(exc).__name__}") from None
    if not stat.S_ISREG(st.st_mode):
        kind = (
            "a folder"
            if stat.S_ISDIR(st.st_mode)
            else "a pipe (FIFO)"
            if stat.S_ISFIFO(st.st_mode)
            else "a device or socket"
        )
        raise InputError(path, f"{kind}, not a regular {what}")
    return st


def require_existing_file(path: Path, what: str = "file") -> os.stat_result:
    """:func:`require_regular_file`, with "does not exist" only when nothing is there.

    An existing FIFO or device was reported as absent where callers tested ``Path.is_file()``.
    """
    if not os.path.lexists(path):
        raise InputError(path, f"{what} does not exist")
    return require_regular_file(path, what)


def one_line(exc: BaseException) -> str:
    """An exception's message on one line (a YAML error spans four: the context and a caret)."""
    return " ".join(str(exc).split())
