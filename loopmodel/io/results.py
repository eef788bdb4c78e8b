"""The results folder of a run (DESIGN.md): ``<out>/<run-name>/`` with trajectories,
metrics, the effective configuration and the run log, every file written atomically."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from loopmodel.config import Config, dump_config
from loopmodel.errors import InputError
from loopmodel.io.atomic import atomic_path, write_text_atomic
from loopmodel.io.trajectory_io import TrajectoryFormat, write_trajectory
from loopmodel.types import Trajectory


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
        """``config.yaml``: the effective configuration of the run."""
        return self.write_text("config.yaml", dump_config(config))


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
