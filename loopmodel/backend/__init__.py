"""Back ends: the :class:`Backend` protocol, the iSAM2 implementation and a factory."""

from __future__ import annotations

from loopmodel.backend.base import (
    Backend,
    BackendEstimate,
    BackendUpdate,
    KeyframeLike,
    Observation,
)
from loopmodel.config import BackendConfig
from loopmodel.errors import ConfigError
from loopmodel.types import StereoCalibration

__all__ = [
    "Backend",
    "BackendEstimate",
    "BackendUpdate",
    "KeyframeLike",
    "Observation",
    "create_backend",
]


def create_backend(config: BackendConfig, calibration: StereoCalibration) -> Backend:
    """The back end named by ``config.kind`` for the rectified stereo ``calibration`` in which
    keyframe pixels are expressed."""
    if config.kind == "isam2":
        from loopmodel.backend.isam2 import Isam2Backend

        return Isam2Backend(calibration, config)
    raise ConfigError(None, f"key 'backend.kind': back end '{config.kind}' is not available in this build")
