"""The back end of a front-end-only run (``backend.kind: none``).

It keeps every keyframe at the pose the front end gave it and estimates nothing (no landmarks, no
loop constraints).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from loopmodel.backend.base import BackendEstimate, BackendUpdate, Observation
from loopmodel.config import RefineConfig
from loopmodel.errors import ConfigError
from loopmodel.types import Keyframe

F64 = np.ndarray


class FrontEndPoses:
    """Keyframe poses exactly as tracked (``world_from_kf``, 4x4, metres)."""

    def __init__(self) -> None:
        self._world_from_kf: dict[int, F64] = {}
        self._new: set[int] = set()

    def add_keyframe(self, keyframe: Keyframe) -> BackendUpdate:
        """Record the keyframe's pose."""
        self._world_from_kf[int(keyframe.id)] = np.asarray(keyframe.world_from_kf, dtype=float).reshape(4, 4).copy()
        self._new.add(int(keyframe.id))
        return BackendUpdate(int(keyframe.id))

    def add_observations(self, keyframe_id: int, mono_obs: F64) -> BackendUpdate:
        """Nothing is estimated from observations: they are ignored."""
        return BackendUpdate(int(keyframe_id))

    def add_loop_constraint(self, kf_a: int, kf_b: int, a_from_b: F64, sigmas: F64 | None = None) -> int:
        """Loop constraints need an estimator: configure ``backend.kind`` isam2, givens or both."""
        raise ConfigError("backend.kind", "'none' keeps the front end's poses and cannot close loops")

    def remove_observations(self, observations: Iterable[Observation]) -> int:
        """Nothing is estimated from observations: nothing to remove."""
        return 0

    def estimate(self, landmarks: bool = True) -> BackendEstimate:
        """The recorded poses; keyframes added since the last call count as changed."""
        changed, self._new = self._new, set()
        return BackendEstimate({k: T.copy() for k, T in self._world_from_kf.items()}, changed_keyframes=changed)

    def final_estimate(self, refine: RefineConfig | None) -> BackendEstimate:
        """The recorded poses (nothing to refine)."""
        return self.estimate()

    def metrics(self) -> dict[str, Any]:
        """No figures of its own."""
        return {}
