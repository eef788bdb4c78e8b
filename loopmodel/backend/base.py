"""The back-end contract: what every back end (iSAM2, Givens sequential estimator) offers.

A back end receives keyframes with their landmark observations from the front end, loop
constraints from loop closing and blunder verdicts from screening, and returns the current
estimate of keyframe poses (``world_from_kf``, 4x4, metres) and landmarks (world frame,
metres). The pipeline talks to a back end only through :class:`Backend`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import RefineConfig
from loopmodel.types import Keyframe

F64 = NDArray[np.float64]


@dataclass
class BackendUpdate:
    """What one ``add_keyframe`` did: factor and landmark counts and its wall time (ms)."""

    keyframe_id: int
    new_factors: int = 0
    new_landmarks: int = 0
    pending_landmarks: int = 0
    rejected_observations: int = 0
    removed_blunders: int = 0
    update_ms: float = 0.0


@dataclass
class BackendEstimate:
    """The current solution.

    ``world_from_kf``: keyframe id -> 4x4 pose (metres); ``landmark_ids`` (N,) and
    ``landmarks_in_world`` (N, 3, metres) of the landmarks in the graph (empty when not
    asked for);
    ``changed_keyframes``: ids whose pose moved by more than the back end's change
    tolerance since the previous ``estimate()`` call (new keyframes included).
    """

    world_from_kf: dict[int, F64]
    landmark_ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    landmarks_in_world: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    changed_keyframes: set[int] = field(default_factory=set)


Observation = tuple[int, int]
"""An observation is named by ``(keyframe_id, landmark_id)``."""


@runtime_checkable
class Backend(Protocol):
    """A keyframe/landmark estimator the pipeline can drive without knowing which it is."""

    def add_keyframe(self, keyframe: Keyframe) -> BackendUpdate:
        """Add a keyframe pose and its stereo and monocular observations; update the solution."""
        ...

    def add_observations(self, keyframe_id: int, mono_obs: F64) -> BackendUpdate:
        """Add monocular observations to a keyframe already in the back end; update the solution.

        ``mono_obs`` (N, 3): landmark id, u, v (rectified pixels of the keyframe's left image), as
        ``Keyframe.mono_obs``. For a loop whose observations of old landmarks were found after the
        keyframe was added (the loop worker's last detections).
        """
        ...

    def add_loop_constraint(self, kf_a: int, kf_b: int, a_from_b: F64, sigmas: F64 | None = None) -> int:
        """Add a relative-pose measurement ``kf_a_from_kf_b`` (4x4); returns a constraint id.

        Standard deviations ``sigmas`` = (rx, ry, rz [rad], tx, ty, tz [m]).
        """
        ...

    def remove_observations(self, observations: Iterable[Observation]) -> int:
        """Remove the named observations (blunders); returns how many were removed."""
        ...

    def estimate(self, landmarks: bool = True) -> BackendEstimate:
        """Current keyframe poses, landmarks and which keyframes changed since the last call.

        Landmarks are left out when ``landmarks`` is False, which is cheaper.
        """
        ...

    def final_estimate(self, refine: RefineConfig | None) -> BackendEstimate:
        """The end-of-run solution with landmarks.

        After the refinement ``refine`` asks for where the back end has one (None: none, e.g. after
        an interruption).
        """
        ...

    def metrics(self) -> dict[str, Any]:
        """The back end's own figures for ``metrics.json`` (may be empty)."""
        ...
