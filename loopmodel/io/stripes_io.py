"""Laser-stripe profiles of a run as one ``stripes.npz`` in the results folder.

Arrays: ``timestamps_ns`` (S, int64), ``counts`` (S, int64: points per stripe, in order),
``points_in_cam`` (sum(counts) x 3, float32, metres, left-camera frame) and ``meta`` (a
short text saying so). Stripes stay in the sensor frame; the run's trajectories place them.
"""

from __future__ import annotations

import zipfile
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from loopmodel.errors import FormatError, InputError
from loopmodel.io.atomic import atomic_path
from loopmodel.types import StripeProfile

STRIPES_FILE = "stripes.npz"
META = "loopmodel stripes v1: points_in_cam float32 metres, left-camera frame (x right, y down, z forward)"


def save_stripes(path: str | Path, stripes: Iterable[StripeProfile]) -> Path:
    """Write the profiles atomically to ``path`` (a .npz file)."""
    stripes = list(stripes)
    t = np.array([s.timestamp_ns for s in stripes], dtype=np.int64)
    pts = [np.asarray(s.points_in_cam, dtype=np.float64).reshape(-1, 3) for s in stripes]
    counts = np.array([p.shape[0] for p in pts], dtype=np.int64)
    allp = np.concatenate(pts).astype(np.float32) if pts else np.zeros((0, 3), np.float32)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, timestamps_ns=t, counts=counts, points_in_cam=allp, meta=np.array(META))
    return Path(path)


def load_stripes(path: str | Path) -> list[StripeProfile]:
    """Read profiles written by :func:`save_stripes`; a folder means its ``stripes.npz``."""
    p = Path(path)
    if p.is_dir():
        p = p / STRIPES_FILE
    if not p.is_file():
        raise InputError(p, "no laser stripes here (expected a stripes.npz written by the pipeline)")
    try:
        with np.load(p, allow_pickle=False) as z:
            missing = {"timestamps_ns", "counts", "points_in_cam"} - set(z.files)
            if missing:
                raise FormatError(p, f"missing arrays {sorted(missing)}")
            t = z["timestamps_ns"].astype(np.int64).ravel()
            counts = z["counts"].astype(np.int64).ravel()
            pts = z["points_in_cam"].astype(np.float64)
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise FormatError(p, f"not a readable .npz file ({type(exc).__name__}: {exc})") from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FormatError(p, f"points_in_cam must be P x 3, got {pts.shape}")
    if t.shape != counts.shape or np.any(counts < 0) or int(counts.sum()) != pts.shape[0]:
        raise FormatError(p, "timestamps_ns, counts and points_in_cam do not agree")
    bad = np.flatnonzero(~np.all(np.isfinite(pts), axis=1))
    if bad.size:
        s = int(np.searchsorted(np.cumsum(counts), bad[0], side="right"))
        raise FormatError(p, f"stripe {s} (t={int(t[s])} ns) has non-finite points")
    bounds = np.concatenate([[0], np.cumsum(counts)])
    return [StripeProfile(int(t[i]), pts[bounds[i] : bounds[i + 1]]) for i in range(t.shape[0])]
