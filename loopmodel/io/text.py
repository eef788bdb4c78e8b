"""Reading small text inputs (calibrations, pose lists, timestamps) with one-line errors."""

from __future__ import annotations

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
        if not p.is_file():
            raise InputError(p, f"expected a {what}, found {'a folder' if p.is_dir() else 'no regular file'}")
        if p.stat().st_size > MAX_TEXT_BYTES:
            raise InputError(p, f"{what} of {p.stat().st_size} bytes is larger than {MAX_TEXT_BYTES}")
        return p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FormatError(p, f"not a UTF-8 {what} (undecodable byte at offset {exc.start})") from None
    except OSError as exc:
        raise InputError(p, f"cannot read the {what}: {exc.strerror or exc.__class__.__name__}") from None
