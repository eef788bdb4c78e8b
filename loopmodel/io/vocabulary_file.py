"""Vocabulary files (``.npz``): written here, atomically (the loop stage's vocabulary is a value)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from loopmodel.io.atomic import atomic_path
from loopmodel.loop.vocabulary import Vocabulary


def save_vocabulary(path: str | Path, vocabulary: Vocabulary) -> None:
    """Write ``vocabulary`` as a compressed ``.npz`` (atomic); :meth:`Vocabulary.load` reads it back."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **vocabulary.arrays())  # type: ignore[arg-type]
