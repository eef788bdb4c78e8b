"""Atomic file writing.

Content goes to a temporary name and is renamed when complete, so an interrupted program never
leaves a half-written file.
"""

from __future__ import annotations

import contextlib
import glob
import os
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``.

    Rename it to ``path`` on success, delete it on any exception (KeyboardInterrupt included).
    """
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(final)
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def pid_alive(pid: int) -> bool:
    """Whether a process with this id runs (on this machine)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Delete ``.NAME.tmp-PID`` files beside ``path`` left by processes that no longer run (a SIGKILL leaves them).

    Returns what was removed.
    """
    final = Path(path)
    removed: list[Path] = []
    prefix = f".{final.name}.tmp-"
    with contextlib.suppress(OSError):
        for p in final.parent.glob(f"{glob.escape(prefix)}*"):
            pid = p.name[len(prefix) :]
            if pid.isdigit() and int(pid) != os.getpid() and not pid_alive(int(pid)):
                with contextlib.suppress(OSError):
                    p.unlink()
                    removed.append(p)
    return removed


def check_output_file(path: str | Path, overwrite: bool = True) -> Path:
    """Before any work.

    ``path`` must not be a folder, nor (unless ``overwrite``) exist, and its folder must be
    writable (created when missing). Raises :class:`InputError` naming the path.
    """
    from loopmodel.errors import InputError

    p = Path(path)
    if not overwrite and p.exists():
        raise InputError(p, "exists already; choose a new name or pass --overwrite")
    if p.is_dir():
        raise InputError(p, "output is a folder; give a file name")
    if p.exists() and not p.is_file():
        raise InputError(p, "output exists and is not a regular file")
    parent = p.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise InputError(parent, "is a file, not a folder for the output") from None
    except OSError as exc:
        raise InputError(parent, f"cannot create the output folder: {exc.strerror}") from None
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(parent, "output folder is not writable")
    return p


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def save_figure_atomic(path: str | Path, fig: object, dpi: int = 120) -> Path:
    """Save a matplotlib figure (PNG by extension) atomically and close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=Path(path).suffix.lstrip(".") or "png")  # type: ignore[attr-defined]
    plt.close(fig)  # type: ignore[arg-type]
    return Path(path)
