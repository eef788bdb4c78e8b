"""Back ends: the :class:`Backend` protocol and its iSAM2 implementation."""

from loopmodel.backend.base import (
    Backend,
    BackendEstimate,
    BackendUpdate,
    KeyframeLike,
    Observation,
)

__all__ = ["Backend", "BackendEstimate", "BackendUpdate", "KeyframeLike", "Observation"]
