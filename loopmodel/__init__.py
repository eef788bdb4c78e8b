"""loopmodel: close-range 3-D modelling with a hand-held stereo camera and a laser-stripe profiler.

The Python API (imported on first use, so ``import loopmodel`` stays light)::

    import loopmodel
    result = loopmodel.run("datasets/tiny_kitti")          # writes nothing
    result.final.positions_m, result.metrics["ate_rmse_m"]

``run(source, config=None, out_dir=None) -> RunResult`` (graded against the sequence's ground truth
unless ``evaluate=False``), ``process(sequence, config) -> RunResult`` (the run alone: writes and
grades nothing), ``evaluate(result, sequence) -> Evaluation``, ``open_sequence(path, config=None)``,
``load_config(path=None) -> Config``, ``export_mesh(source, target, fmt="ply") -> MeshExport`` (the
mesh of a results folder or a saved map, as ``loopmodel mesh`` writes it).

Trajectory files (TUM, KITTI, EuRoC; as evo's ``file_interface``): ``read_trajectory(path)``,
``write_trajectory(path, result.final)``.
"""

from __future__ import annotations

import importlib
import logging
from typing import TYPE_CHECKING, Any

from loopmodel._version import __version__

if TYPE_CHECKING:
    from loopmodel.config import Config, load_config
    from loopmodel.eval.of_run import Evaluation, evaluate
    from loopmodel.io.sequence import open_sequence
    from loopmodel.meshes import export_mesh
    from loopmodel.pipeline import process, run
    from loopmodel.result import RunResult
    from loopmodel.types import Keyframe, StereoCalibration, StereoFrame, StripeProfile, Trajectory

logging.getLogger(__name__).addHandler(logging.NullHandler())

_LAZY = {
    "run": "loopmodel.pipeline",
    "process": "loopmodel.pipeline",
    "evaluate": "loopmodel.eval.of_run",
    "export_mesh": "loopmodel.meshes",
    "Evaluation": "loopmodel.eval.of_run",
    "RunResult": "loopmodel.result",
    "open_sequence": "loopmodel.io.sequence",
    "load_config": "loopmodel.config",
    "Config": "loopmodel.config",
    "Keyframe": "loopmodel.types",
    "StereoCalibration": "loopmodel.types",
    "StereoFrame": "loopmodel.types",
    "StripeProfile": "loopmodel.types",
    "Trajectory": "loopmodel.types",
    "read_trajectory": "loopmodel.io.trajectory_io",
    "write_trajectory": "loopmodel.io.trajectory_io",
}

__all__ = [
    "Config",
    "Evaluation",
    "Keyframe",
    "RunResult",
    "StereoCalibration",
    "StereoFrame",
    "StripeProfile",
    "Trajectory",
    "__version__",
    "evaluate",
    "export_mesh",
    "load_config",
    "open_sequence",
    "process",
    "run",
    "read_trajectory",
    "write_trajectory",
]


def __getattr__(name: str) -> Any:
    """The public API, imported when first used."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'loopmodel' has no attribute '{name}'")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
