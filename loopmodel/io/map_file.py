"""The map file of a session: a folder with ``map.json`` and ``arrays.npz`` (issue 20).

``map.json`` holds the format name and version, the loopmodel version that wrote it, the run's
configuration (YAML text) and small descriptive fields; ``arrays.npz`` (uncompressed, read with
``allow_pickle=False``) holds every array by name. This module knows nothing of what the arrays
mean (:mod:`loopmodel.loop.session_map` turns a map into them and back); it writes atomically (a
staging folder renamed into place) and reads back with a clear :class:`~loopmodel.errors.InputError` naming the file on
a foreign, damaged or newer-version map.
"""

from __future__ import annotations

import json
import os
import shutil
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from loopmodel.errors import InputError
from loopmodel.io.text import read_text_file
from loopmodel.types import MapFileData, Trajectory

if TYPE_CHECKING:
    from loopmodel.loop.session_map import ResumePoint, SessionMap

__all__ = [
    "ARRAYS_FILE",
    "META_FILE",
    "MapFileData",
    "load_session_map",
    "map_folder",
    "map_size_bytes",
    "read_map_file",
    "read_map_meta",
    "read_resume_point",
    "save_session_map",
    "write_map_file",
]

FORMAT_NAME = "loopmodel-map"
#: Version of the layout written; a reader refuses a map with a higher one.
FORMAT_VERSION = 1
META_FILE = "map.json"
ARRAYS_FILE = "arrays.npz"


def write_map_file(path: str | Path, data: MapFileData) -> Path:
    """Write ``data`` as the map folder ``path`` (replacing an older one only once complete)."""
    from loopmodel._version import __version__

    final = Path(path)
    if final.exists() and not final.is_dir():
        raise InputError(final, "map path exists and is not a folder")
    final.parent.mkdir(parents=True, exist_ok=True)
    for a in data.arrays.values():
        if np.asarray(a).dtype == object:
            raise InputError(final, "map arrays must not hold Python objects")
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        meta = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "loopmodel_version": __version__, **data.meta}
        with open(tmp / ARRAYS_FILE, "wb") as f:
            np.savez(f, **data.arrays)  # type: ignore[arg-type]
        (tmp / META_FILE).write_text(json.dumps(meta, indent=2) + "\n")
        old = final.with_name(f".{final.name}.old-{os.getpid()}")
        if final.exists():
            os.replace(final, old)
        os.replace(tmp, final)
        shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def map_folder(path: str | Path) -> Path:
    """The map folder of ``path``: the folder itself, or ``<results folder>/map``."""
    p = Path(path)
    if p.is_dir() and not (p / META_FILE).is_file() and (p / "map" / META_FILE).is_file():
        return p / "map"
    return p


def read_map_meta(path: str | Path) -> tuple[Path, dict[str, Any]]:
    """The map folder and its checked ``map.json`` (format and version)."""
    folder = map_folder(path)
    meta_path = folder / META_FILE
    if not folder.is_dir():
        raise InputError(folder, "map folder does not exist")
    if not os.path.lexists(meta_path):
        raise InputError(meta_path, "not a loopmodel map (no map.json)")
    try:
        meta = json.loads(read_text_file(meta_path, "map description"))
    except RecursionError:  # nested past Python's limit
        raise InputError(meta_path, "damaged map description (nested too deeply)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(meta_path, f"damaged map description ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        raise InputError(meta_path, f"not a loopmodel map (format is not '{FORMAT_NAME}')")
    version = meta.get("version")
    if not isinstance(version, int):
        raise InputError(meta_path, "damaged map description (no integer version)")
    if version > FORMAT_VERSION:
        raise InputError(
            meta_path,
            f"map format version {version} is newer than this loopmodel reads ({FORMAT_VERSION}); update loopmodel",
        )
    return folder, meta


def read_map_file(path: str | Path, required: tuple[str, ...] = ()) -> MapFileData:
    """Read a map folder written by :func:`write_map_file`; every array is loaded (no pickle).

    ``required``: array names that must be present.
    """
    folder, meta = read_map_meta(path)
    arrays_path = folder / ARRAYS_FILE
    if not arrays_path.is_file():
        raise InputError(arrays_path, "map arrays missing")
    try:
        with np.load(arrays_path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise InputError(arrays_path, f"damaged map arrays ({type(exc).__name__}: {exc})") from None
    odd = [k for k, v in arrays.items() if v.dtype.kind not in "biuf"]
    if odd:  # complex, structured, text or time arrays are none of a map's
        raise InputError(arrays_path, f"damaged map arrays ({odd[0]} holds {arrays[odd[0]].dtype} values)")
    missing = [k for k in required if k not in arrays]
    if missing:
        raise InputError(arrays_path, f"damaged map arrays (missing {', '.join(missing[:5])})")
    return MapFileData(meta, arrays)


def map_size_bytes(path: str | Path) -> int:
    """Bytes of a map folder's files."""
    folder = map_folder(path)
    return sum(p.stat().st_size for p in folder.iterdir() if p.is_file())


def save_session_map(path: str | Path, smap: SessionMap) -> Path:
    """Write a session map as the map folder ``path`` (atomic)."""
    return write_map_file(path, smap.to_file_data())


def load_session_map(path: str | Path) -> SessionMap:
    """Read a map folder (or a results folder's ``map/``); damaged or newer maps raise InputError."""
    from loopmodel.loop.session_map import REQUIRED_ARRAYS, SessionMap

    data = read_map_file(path, REQUIRED_ARRAYS)
    try:
        return SessionMap.from_file_data(data)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise InputError(path, f"damaged map ({type(exc).__name__}: {exc})") from None


def read_resume_point(folder: str | Path) -> ResumePoint:
    """The map and trajectories of a results folder, for resuming it (``loopmodel run --resume``)."""
    from loopmodel.io.trajectory_io import read_trajectory
    from loopmodel.loop.session_map import ResumePoint

    p = Path(folder)
    if not p.is_dir():
        raise InputError(p, "results folder to resume does not exist")
    smap = load_session_map(p / "map")
    if len(smap) == 0:
        raise InputError(p / "map", "the map holds no keyframe to resume from")
    trajs: list[Trajectory] = []
    for name in ("trajectory_online.tum", "trajectory_final.tum", "keyframes.tum"):
        if not (p / name).is_file():
            raise InputError(p / name, "missing: cannot resume this run")
        trajs.append(read_trajectory(p / name))
    return ResumePoint(smap, *trajs)
