"""The results folder of a run (DESIGN.md): ``<out>/<run-name>/`` with trajectories,
metrics, the effective configuration and the run log, every file written atomically."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

from loopmodel.config import Config, dump_config, pipeline_sections
from loopmodel.errors import InputError
from loopmodel.io.atomic import atomic_path, write_text_atomic
from loopmodel.io.trajectory_io import TrajectoryFormat, write_trajectory
from loopmodel.types import Trajectory

if TYPE_CHECKING:
    from loopmodel.result import RunResult


class ResultsFolder:
    """Writer for ``<out>/<name>/``; creates the folder, never leaves half-written files."""

    def __init__(self, out_dir: str | Path, name: str) -> None:
        if not name or "/" in name or name in (".", ".."):
            raise InputError("--name", f"run name must be a plain folder name, got '{name}'")
        self.path = Path(out_dir) / name
        if self.path.exists() and not self.path.is_dir():
            raise InputError(self.path, "results path exists and is not a folder")
        self.path.mkdir(parents=True, exist_ok=True)

    def file(self, name: str) -> Path:
        """Path of a file in the folder."""
        return self.path / name

    def write_trajectory(self, name: str, traj: Trajectory, fmt: TrajectoryFormat = "tum") -> Path:
        """A trajectory file (TUM by default)."""
        return write_trajectory(self.file(name), traj, fmt)

    def write_json(self, name: str, data: dict[str, Any]) -> Path:
        """A JSON file (indented, keys in insertion order)."""
        return write_text_atomic(
            self.file(name), json.dumps(data, indent=2, default=_json_default) + "\n"
        )

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
        """``config.yaml``: the effective configuration of the run (the sections the
        pipeline reads, :func:`loopmodel.config.pipeline_sections`)."""
        return self.write_text("config.yaml", dump_config(config, pipeline_sections()))


def write_results(folder: ResultsFolder, run: RunResult) -> Path:
    """Write a run into ``folder``, the small files first: ``config.yaml`` (the pipeline's
    configuration), ``trajectory_online.tum``, ``trajectory_final.tum``, ``keyframes.tum``
    (KITTI variants of the first two when ``output.write_kitti``), ``map.npz``,
    ``metrics.json``, ``run.log``, then ``stripes.npz`` (when the run has laser profiles),
    ``mesh.ply`` and ``mesh_live.ply`` (when made). Returns the folder's path."""
    folder.write_config(run.config)
    folder.write_trajectory("trajectory_online.tum", run.online)
    folder.write_trajectory("trajectory_final.tum", run.final)
    folder.write_trajectory("keyframes.tum", run.keyframes)
    if run.config.output.write_kitti:
        folder.write_trajectory("trajectory_online.kitti", run.online, "kitti")
        folder.write_trajectory("trajectory_final.kitti", run.final, "kitti")
    folder.write_npz("map.npz", run.map_arrays())
    folder.write_json("metrics.json", run.metrics)
    folder.write_text("run.log", run.log)
    if run.stripes:
        from loopmodel.io.stripes_io import STRIPES_FILE, save_stripes

        save_stripes(folder.file(STRIPES_FILE), run.stripes)
    for name, mesh in (("mesh.ply", run.mesh), ("mesh_live.ply", run.live_mesh)):
        if mesh is not None:
            from loopmodel.io.mesh_io import write_mesh

            write_mesh(folder.file(name), mesh, "ply")
    return folder.path


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
