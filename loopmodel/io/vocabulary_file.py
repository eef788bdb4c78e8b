"""Vocabulary files (``.npz``): read and written here (the loop stage's vocabulary is a value, issue 32).

:func:`loop_vocabulary` is what a run hands the loop stage and the session map: the configured
file, else the one shipped for the descriptor kind, else None (trained on the fly).
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import numpy as np

from loopmodel.config import LoopConfig
from loopmodel.errors import FormatError, InputError
from loopmodel.io.atomic import atomic_path
from loopmodel.loop.vocabulary import Vocabulary

logger = logging.getLogger(__name__)

#: Package data folder holding the shipped vocabularies (``vocabulary_<kind>.npz``).
DATA_DIR = Path(__file__).resolve().parents[1] / "data"


def save_vocabulary(path: str | Path, vocabulary: Vocabulary) -> None:
    """Write ``vocabulary`` as a compressed ``.npz`` (atomic); :func:`read_vocabulary` reads it back."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **vocabulary.arrays())  # type: ignore[arg-type]


def read_vocabulary(path: str | Path) -> Vocabulary:
    """Read a vocabulary file (written by :func:`save_vocabulary`).

    :class:`InputError` when it does not exist, :class:`FormatError` when it is not a vocabulary.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "vocabulary file does not exist")
    try:
        with np.load(p) as z:
            return Vocabulary.from_arrays({k: z[k] for k in z.files})
    except (KeyError, ValueError, OSError) as exc:
        raise FormatError(p, f"not a loopmodel vocabulary ({exc})") from None


def shipped_path(kind: str) -> Path:
    """Path of the vocabulary shipped for a descriptor kind (may not exist)."""
    return DATA_DIR / f"vocabulary_{kind.lower()}.npz"


@functools.lru_cache(maxsize=8)
def _read_cached(path: str, mtime_ns: int) -> Vocabulary:
    return read_vocabulary(path)


def shipped_vocabulary(kind: str) -> Vocabulary | None:
    """The pre-trained vocabulary shipped for ``kind`` (``orb``, ``sift``, ``surf``).

    None when the package has none for it (cached; do not modify the result).
    """
    p = shipped_path(kind)
    if not p.is_file():
        return None
    return _read_cached(str(p), p.stat().st_mtime_ns)


def loop_vocabulary(config: LoopConfig) -> Vocabulary | None:
    """The vocabulary of the ``loop`` section: ``vocabulary_path``, else the one shipped for the descriptor.

    None with ``vocabulary_online`` or when nothing is shipped for the kind (logged): the loop stage
    and the session map then train one on the fly. A configured file is cached too (by path and
    modification time; do not modify the result).
    """
    if config.vocabulary_path:
        p = Path(config.vocabulary_path)
        if not p.is_file():
            raise InputError(p, "vocabulary file does not exist")
        return _read_cached(str(p), p.stat().st_mtime_ns)
    if config.vocabulary_online:
        return None
    voc = shipped_vocabulary(config.descriptor)
    if voc is None:
        logger.warning("no vocabulary shipped for %s descriptors: training one on the fly", config.descriptor)
    return voc
