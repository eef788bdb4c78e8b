"""The results folder of a run (DESIGN.md).

``<out>/<run-name>/`` with trajectories, metrics, the effective configuration and the run log, every
file written atomically.
"""

from __future__ import annotations

import contextlib
import glob
import json
import logging
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from loopmodel.config import Config, dump_config, pipeline_sections
from loopmodel.errors import InputError
from loopmodel.io.atomic import atomic_path, pid_alive, write_text_atomic
from loopmodel.io.trajectory_io import TrajectoryFormat, write_trajectory
from loopmodel.types import Trajectory

if TYPE_CHECKING:
    from loopmodel.result import RunResult


class ResultsFolder:
    """Writer for ``<out>/<name>/``; never leaves half-written files, never mixes runs.

    With ``staged`` (the default) files go to a fresh ``<out>/.<name>.tmp-<pid>/`` and
    :meth:`commit` moves it to ``<out>/<name>/``, replacing an older run's folder only then
    (``overwrite=False`` refuses an existing folder up front instead). A lock file
    ``<out>/.<name>.lock`` (holding the PID) stops a second concurrent run of the same name;
    the staging folders and locks of dead processes are removed at the next start."""

    def __init__(self, out_dir: str | Path, name: str, staged: bool = True, overwrite: bool = True) -> None:
        out = Path(out_dir)
        self.final = check_results_folder(out, name, overwrite)
        #: the folder asked for; ``final`` differs from it when an incomplete run is kept beside
        self.requested = self.final
        try:
            out.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            raise InputError(out, "--out is a file, not a folder") from None
        except OSError as exc:
            raise InputError(out, f"cannot create the results folder: {exc.strerror}") from None
        if not os.access(out, os.W_OK | os.X_OK):
            raise InputError(out, "results folder is not writable")
        self.staged = staged
        self._lock: Path | None = None
        self.committed = False
        if staged:
            self._lock = _acquire_lock(out / f".{name}.lock", self.final)
            _remove_dead_staging(out, name)
            self.path = out / f".{name}.tmp-{os.getpid()}"
            if self.path.exists():
                shutil.rmtree(self.path)
            self.path.mkdir()
        else:
            self.path = self.final
            self.path.mkdir(parents=True, exist_ok=True)

    def commit(self, complete: bool = True, looks_complete: bool = True) -> Path:
        """Move the staged folder to ``<out>/<name>/`` (replacing an older one) and release the lock.

        Returns the final path. Without staging: nothing to do. An incomplete run (``complete``
        False: interrupted, stopped by an error, a file not written) never replaces an older
        folder: it goes beside it as ``<name>-incomplete`` (``-incomplete-2``, ...); so does a
        folder whose files were not all written (``looks_complete`` False), older folder or not,
        so that its name says so.
        """
        if not self.staged or self.committed:
            return self.final
        if (not complete and self.final.exists()) or not looks_complete:
            self.final = _free_name(self.final.with_name(f"{self.final.name}-incomplete"))
        old = None
        if self.final.exists():
            old = self.final.with_name(f".{self.final.name}.old-{os.getpid()}")
            if old.exists():
                shutil.rmtree(old)
            os.replace(self.final, old)
        os.replace(self.path, self.final)
        self.path = self.final
        self.committed = True
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        self.release()
        return self.final

    def abandon(self) -> None:
        """Drop the staged folder (the older run's folder stays) and release the lock."""
        if self.staged and not self.committed:
            shutil.rmtree(self.path, ignore_errors=True)
        self.release()

    def release(self) -> None:
        """Release the lock (also done by :meth:`commit`)."""
        if self._lock is not None:
            _HELD.discard(self._lock)
            with contextlib.suppress(FileNotFoundError):
                self._lock.unlink()
            self._lock = None

    def file(self, name: str) -> Path:
        """Path of a file in the folder."""
        return self.path / name

    def write_trajectory(self, name: str, traj: Trajectory, fmt: TrajectoryFormat = "tum") -> Path:
        """A trajectory file (TUM by default)."""
        return write_trajectory(self.file(name), traj, fmt)

    def write_json(self, name: str, data: dict[str, Any]) -> Path:
        """A JSON file (indented, keys in insertion order)."""
        return write_text_atomic(self.file(name), json.dumps(data, indent=2, default=_json_default) + "\n")

    def write_text(self, name: str, text: str) -> Path:
        """A text file."""
        return write_text_atomic(self.file(name), text)

    def write_npz(self, name: str, arrays: dict[str, Any]) -> Path:
        """A numpy ``.npz`` archive of named arrays (uncompressed)."""
        import numpy as np

        with atomic_path(self.file(name)) as tmp, open(tmp, "wb") as f:
            np.savez(f, **arrays)
        return self.file(name)

    def write_config(self, config: Config) -> Path:
        """``config.yaml``.

        The effective configuration of the run (the sections the pipeline reads,
        :func:`loopmodel.config.pipeline_sections`).
        """
        return self.write_text("config.yaml", dump_config(config, pipeline_sections()))


def _free_name(path: Path) -> Path:
    """``path``, or ``path-2``, ``path-3``, ... whichever does not exist yet."""
    k, candidate = 1, path
    while candidate.exists() or candidate.is_symlink():
        k += 1
        candidate = path.with_name(f"{path.name}-{k}")
    return candidate


def _early_values(run: RunResult) -> tuple[Any, ...]:
    """The values of ``run`` the files of :func:`write_results_early` are made of."""
    return (
        run.config, run.online, run.final, run.keyframes, run.localized, run.keyframe_ids, run.landmark_ids,
        run.landmarks_in_world, run.calibration_refined, run.calibration_report, run.stripes, run.session_map,
        run.live_mesh,
    )


@dataclass
class EarlyFiles:
    """What :func:`write_results_early` wrote (file and folder names in the results folder) and of what."""

    names: list[str]
    of: tuple[Any, ...]
    #: wall time of the early writes (s)
    seconds: float = 0.0

    def holds_for(self, run: RunResult) -> bool:
        """Whether ``run`` still has the values the files were written from (the same objects)."""
        now = _early_values(run)
        return len(now) == len(self.of) and all(a is b for a, b in zip(self.of, now, strict=True))

    def remove(self, folder: ResultsFolder) -> None:
        """The early files taken out of ``folder`` (e.g. the run's result was replaced after them)."""
        for name in self.names:
            path = folder.file(name)
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()


def _write_small(folder: ResultsFolder, run: RunResult, kitti_input: bool, names: list[str]) -> None:
    """The small files known before the mesh and the metrics (``names`` gets each one written)."""
    names.append("config.yaml")  # each name before its write: a write cut short is removed too
    folder.write_config(run.config)
    trajectories = [("trajectory_online.tum", run.online), ("trajectory_final.tum", run.final)]
    trajectories.append(("keyframes.tum", run.keyframes))
    if run.localized is not None:
        trajectories.append(("trajectory_in_map.tum", run.localized))
    for name, traj in trajectories:
        names.append(name)
        folder.write_trajectory(name, traj)
    write_kitti = run.config.output.write_kitti
    if write_kitti or (write_kitti is None and kitti_input):
        names += ["trajectory_online.kitti", "trajectory_final.kitti"]
        folder.write_trajectory("trajectory_online.kitti", run.online, "kitti")
        folder.write_trajectory("trajectory_final.kitti", run.final, "kitti")
        if len(run.final) != len(run.frames):  # KITTI rows carry no times: say they are not one per image
            logging.getLogger(__name__).warning(
                "trajectory_final.kitti: %d rows for %d frames (untracked frames have none; "
                "trajectory_final.tum has the times)", len(run.final), len(run.frames)
            )
    names.append("map.npz")
    folder.write_npz("map.npz", run.map_arrays())
    if run.calibration_refined is not None:  # issue 31: calibration.refine
        from loopmodel.io.calib_files import refined_calibration_yaml

        names.append("calibration_refined.yaml")
        folder.write_text(
            "calibration_refined.yaml", refined_calibration_yaml(run.calibration_refined, run.calibration_report)
        )


def _write_large(folder: ResultsFolder, run: RunResult, names: list[str]) -> None:
    """``stripes.npz``, the session map's folder and ``mesh_live.ply`` (``names`` gets each one written)."""
    if run.stripes:
        from loopmodel.io.stripes_io import STRIPES_FILE, save_stripes

        names.append(STRIPES_FILE)
        save_stripes(folder.file(STRIPES_FILE), run.stripes)
    if run.session_map is not None:
        from loopmodel.io.map_file import save_session_map

        names.append("map")
        save_session_map(folder.file("map"), run.session_map)
    if run.live_mesh is not None:
        from loopmodel.io.mesh_io import write_mesh

        names.append("mesh_live.ply")
        write_mesh(folder.file("mesh_live.ply"), run.live_mesh, "ply")


def write_results_early(folder: ResultsFolder, run: RunResult, kitti_input: bool = False) -> EarlyFiles | None:
    """The files of :func:`write_results` that need neither the final mesh nor the metrics, written now.

    pre16 (issue 32): called while the final mesh is made in another process, so that only
    ``metrics.json``, ``run.log`` and ``mesh.ply`` are left for after it (a Ctrl-C here removes what
    was written and is raised). Pass the returned record to
    :func:`write_results` (which writes these again, or removes them, when ``run`` changed since).
    None when a file could not be written (what was written is removed; :func:`write_results`
    then writes everything and reports the error as usual).
    """
    t0 = time.perf_counter()
    names: list[str] = []
    try:
        _write_small(folder, run, kitti_input, names)
        _write_large(folder, run, names)
    except OSError as exc:
        logging.getLogger(__name__).warning("results not written beside the mesh: %s", exc)
        EarlyFiles(names, ()).remove(folder)
        return None
    except BaseException:  # e.g. a Ctrl-C: the result written later may not have these files
        EarlyFiles(names, ()).remove(folder)
        raise
    return EarlyFiles(names, _early_values(run), time.perf_counter() - t0)


def write_results(
    folder: ResultsFolder, run: RunResult, kitti_input: bool = False, early: EarlyFiles | None = None
) -> Path:
    """Write a run into ``folder``, the small files first.

    ``config.yaml`` (the pipeline's configuration), ``trajectory_online.tum``,
    ``trajectory_final.tum``, ``keyframes.tum``, ``trajectory_in_map.tum`` (frames localized in a
    base map), KITTI variants of the first two (``poses.txt`` rows: when ``output.write_kitti``,
    or when it is unset and ``kitti_input``: the sequence is a KITTI folder), ``map.npz``,
    ``calibration_refined.yaml`` (with ``calibration.refine``),
    ``metrics.json``, ``run.log``, then ``stripes.npz`` (when the run has laser profiles), the
    session map folder ``map/`` (when made), ``mesh_live.ply`` and ``mesh.ply`` (when made). Returns the folder's path.
    ``early``: :func:`write_results_early` of this run (its files are not written again while
    ``run`` holds the values they were made of; else they are removed first and written again).

    A staged folder (:class:`ResultsFolder`) replaces the older run's folder once the small
    files through ``run.log`` are written, even when a large file then fails (a full disk:
    the error is raised after the commit); when a small file fails, the older folder stays
    and the staging is removed."""
    done = early is not None and early.holds_for(run)
    if early is not None and not done:
        early.remove(folder)
    try:
        if not done:
            _write_small(folder, run, kitti_input, [])
        folder.write_json("metrics.json", run.metrics)
        folder.write_text("run.log", run.log)
    except OSError as exc:  # a full disk: nothing kept, the line names the file and the folder
        folder.abandon()
        where = exc.filename or folder.requested
        raise OSError(exc.errno, f"{exc.strerror or exc}; {folder.requested} not written", where) from None
    except BaseException:
        folder.abandon()
        raise
    complete = not run.interrupted and run.error is None
    try:
        if not done:
            _write_large(folder, run, [])
        if run.mesh is not None:
            from loopmodel.io.mesh_io import write_mesh

            write_mesh(folder.file("mesh.ply"), run.mesh, "ply")
    except OSError as exc:  # a full disk: the folder is kept under a name that says it is incomplete
        with contextlib.suppress(OSError):
            with open(folder.file("run.log"), "a") as log:
                log.write(f"INCOMPLETE: writing the results failed: {exc}\n")
        where = folder.commit(complete=False, looks_complete=False)
        note = f"the results so far are in {where}" + (
            f" ({folder.requested} was not replaced)" if folder.requested.exists() else ""
        )
        raise OSError(exc.errno, f"{exc.strerror or exc}; {note}", exc.filename) from None
    except BaseException:
        folder.commit(complete=False, looks_complete=False)
        raise
    folder.commit(complete=complete)
    return folder.path


def check_results_folder(out_dir: str | Path, name: str, overwrite: bool = True) -> Path:
    """``<out_dir>/<name>``, checked before any work: a plain name, not a file, and (unless ``overwrite``) new.

    Raises :class:`InputError` naming the folder (or ``--name``).
    """
    if not name or "/" in name or name in (".", "..") or name.startswith("."):
        raise InputError("--name", f"run name must be a plain folder name, got '{name}'")
    final = Path(out_dir) / name
    if final.exists() and not final.is_dir():
        raise InputError(final, "results path exists and is not a folder")
    if not overwrite and final.exists():
        raise InputError(final, "results folder exists; choose another --name or pass --overwrite")
    return final


#: lock files held by this process (a lock with our PID but not in here is stale)
_HELD: set[Path] = set()


def _acquire_lock(lock: Path, final: Path) -> Path:
    """Create ``lock`` exclusively with our PID; a lock of a dead process is taken over."""
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid = int(lock.read_text().strip() or "0")
            except (OSError, ValueError):
                pid = 0
            ours = pid == os.getpid() and lock not in _HELD
            if pid > 0 and not ours and pid_alive(pid):
                raise InputError(final, f"another run (pid {pid}) is writing this results folder") from None
            with contextlib.suppress(FileNotFoundError):
                lock.unlink()
            continue
        with os.fdopen(fd, "w") as f:
            f.write(str(os.getpid()))
        _HELD.add(lock)
        return lock
    raise InputError(final, f"cannot take the lock {lock}")


def _remove_dead_staging(out: Path, name: str) -> None:
    """Delete ``.<name>.tmp-<pid>`` / ``.<name>.old-<pid>`` folders of processes that died."""
    for kind in ("tmp", "old"):
        prefix = f".{name}.{kind}-"
        for p in out.glob(glob.escape(prefix) + "*"):
            pid = p.name[len(prefix) :]
            if pid.isdigit() and int(pid) != os.getpid() and not pid_alive(int(pid)) and p.is_dir():
                shutil.rmtree(p, ignore_errors=True)


def _json_default(obj: Any) -> Any:
    try:
        import numpy as np

        if isinstance(obj, np.generic):
            return obj.item()
        if isinstance(obj, np.ndarray):
            return obj.tolist()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


class LogCapture(logging.Handler):
    """Collects the package's log records of a run for ``run.log``."""

    def __init__(self, level: int = logging.INFO) -> None:
        super().__init__(level)
        self.lines: list[str] = []
        self.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(self.format(record))
        # pass on what the console would have shown without the capture
        if record.levelno >= self._console_level:
            for h in logging.getLogger().handlers:
                if record.levelno >= h.level:
                    h.handle(record)

    def __enter__(self) -> LogCapture:
        logger = logging.getLogger("loopmodel")
        self._console_level = logger.getEffectiveLevel()
        self._old = (logger.level, logger.propagate)
        logger.setLevel(min(self.level, self._console_level))
        logger.propagate = False
        logger.addHandler(self)
        return self

    def __exit__(self, *exc: object) -> None:
        logger = logging.getLogger("loopmodel")
        logger.removeHandler(self)
        logger.setLevel(self._old[0])
        logger.propagate = self._old[1]

    def text(self) -> str:
        """All captured lines."""
        return "\n".join(self.lines) + ("\n" if self.lines else "")
