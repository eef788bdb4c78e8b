"""Back ends: the :class:`Backend` protocol, the iSAM2 implementation and a factory."""

from __future__ import annotations

from loopmodel.backend.base import (
    Backend,
    BackendEstimate,
    BackendUpdate,
    Observation,
)
from loopmodel.config import BackendConfig, GivensConfig
from loopmodel.errors import ConfigError
from loopmodel.types import StereoCalibration

__all__ = [
    "Backend",
    "BackendEstimate",
    "BackendUpdate",
    "Observation",
    "create_backend",
]


def create_backend(
    config: BackendConfig, calibration: StereoCalibration, givens: GivensConfig | None = None
) -> Backend:
    """The back end named by ``config.kind``.

    For the rectified stereo ``calibration`` in which keyframe pixels are expressed: ``isam2``,
    ``givens`` (the sequential Givens estimator), ``both`` (iSAM2 behind the Givens blunder screen;
    ``givens`` configures the screen) or ``none`` (the front end's poses, for front-end-only runs).
    """
    if config.kind == "none":
        from loopmodel.backend.frontend_poses import FrontEndPoses

        return FrontEndPoses()
    if config.kind in ("givens", "both"):
        from loopmodel.backend.givens_bundle import GivensScreen
        from loopmodel.backend.screened import GivensBackend, ScreenedBackend

        screen = GivensScreen.from_config(
            calibration.left_camera(), givens or GivensConfig(), calibration.right_from_left
        )
        if config.kind == "givens":
            return GivensBackend(screen)
    if config.kind in ("isam2", "both"):
        from loopmodel.backend.isam2 import Isam2Backend

        inner = Isam2Backend(calibration, config)
        return inner if config.kind == "isam2" else ScreenedBackend(inner, screen)
    raise ConfigError(None, f"key 'backend.kind': back end '{config.kind}' is not available in this build")
