"""The interfaces of the pipeline's stages that are not a back end.

The back end's is :class:`loopmodel.backend.Backend`. What the loop-closing stage is handed at a
keyframe and what it returns. Light on purpose (no OpenCV or GTSAM): the pipeline imports it at
start.

Data flow at a keyframe: the front end's keyframe and the current :class:`MapState` go to
:meth:`LoopStage.on_keyframe`; the :class:`LoopOutcome` it returns carries the keyframe to
hand on to the back end, the :class:`LoopConstraint` s for the back end, and pose corrections
for the front end and the map. No stage changes another one.
"""

from __future__ import annotations

from collections.abc import Mapping
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from loopmodel.types import Keyframe

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class MapState:
    """What the loop stage reads of the rest of the run when a keyframe arrives.

    ``world_from_kf``: the current pose (4x4, metres, left camera) of every keyframe so far,
    the new one included; ``last_update_ms``: wall time of the back end's update of the
    previous keyframe (its loop constraints included); ``last_constraint_ids``: the ids the
    back end gave the constraints of the previous :class:`LoopOutcome` (None where it took
    none), in their order."""

    world_from_kf: Mapping[int, F64]
    last_update_ms: float = 0.0
    last_constraint_ids: tuple[int | None, ...] = ()


@dataclass
class LoopConstraint:
    """A relative-pose measurement ``kf_a_from_kf_b`` (4x4, metres) between two keyframes' left cameras.

    For :meth:`loopmodel.backend.Backend.add_loop_constraint`. ``kf_a_mono_obs`` (N, 3: landmark id,
    u, v rectified px): ``kf_a``'s observations of ``kf_b``'s landmarks, for a loop found after
    ``kf_a`` reached the back end (:meth:`loopmodel.backend.Backend.add_observations`); None when
    they went with the keyframe itself.
    """

    kf_a: int
    kf_b: int
    a_from_b: F64
    kf_a_mono_obs: F64 | None = None


@dataclass
class ResumeFeatures:
    """An old keyframe's features found again in the current keyframe, for the front end to track on.

    Seed 004, section 5: after a relocalization or a verified revisit the tracker resumes the
    original feature set. ``keyframe``: the current keyframe, whose rectified left image the
    pixels ``uv_px`` (K, 2) refer to; ``match_keyframe``: the old keyframe that owns the
    landmarks ``landmark_ids`` (K,); ``points_in_match`` (K, 3) metres in the old keyframe's
    rectified left camera frame; ``match_uv_px`` (K, 2) their pixels in the old keyframe's
    rectified left image ``match_image`` (the templates); ``kf_from_match`` (4x4, metres) maps
    the old keyframe's rectified frame into the current keyframe's (the loop's pose).
    """

    keyframe: int
    match_keyframe: int
    landmark_ids: NDArray[np.int64]
    uv_px: F64
    points_in_match: F64
    match_uv_px: F64
    match_image: NDArray[np.uint8]
    kf_from_match: F64

    def __len__(self) -> int:
        return int(np.asarray(self.landmark_ids).size)


@dataclass
class LoopOutcome:
    """What one keyframe caused in loop closing.

    ``keyframe``: the keyframe to hand on to the back end (the input, or a copy at its
    relocalized pose with the loop's observations of old landmarks appended to
    ``mono_obs``); ``constraints`` for the back end; ``corrections``: keyframe id ->
    corrected ``world_from_kf`` for the tracker and the map (relocalization, a finished
    global BA); ``events``: the records of the closures and relocalizations it produced;
    ``resume``: the old features found again in this keyframe, for the front end's
    :meth:`~loopmodel.frontend.FrontEnd.resume_features` (None without a closure)."""

    keyframe: Keyframe
    constraints: list[LoopConstraint] = field(default_factory=list)
    corrections: dict[int, F64] = field(default_factory=dict)
    events: list[dict[str, Any]] = field(default_factory=list)
    resume: ResumeFeatures | None = None


class LoopStage(Protocol):
    """The pipeline's loop-closing stage: one call per keyframe, one at the end."""

    def on_keyframe(self, keyframe: Keyframe, state: MapState) -> LoopOutcome:
        """Process a new keyframe (after the front end, before the back end)."""
        ...

    def between_frames(self, state: MapState) -> LoopOutcome | None:
        """What its workers finished since the last call, to apply before the next frame, or None.

        The outcome's ``keyframe`` is the one its loops were applied at (the back end has it
        already); its constraints may carry that keyframe's observations of old landmarks
        (``LoopConstraint.kf_a_mono_obs``), its ``resume`` is for the front end's active keyframe.
        """
        ...

    def close(self, state: MapState) -> dict[int, F64]:
        """Finish pending work at the end of the run; returns its last corrections."""
        ...

    def final_constraints(self) -> list[LoopConstraint]:
        """Constraints of loops found after the last keyframe (read after :meth:`close`)."""
        ...

    def detection(self, kf_id: int) -> Future[Any] | None:
        """The running detection of keyframe ``kf_id`` if it was the last one given (its loop features)."""
        ...

    def metrics(self) -> dict[str, Any]:
        """Summary for ``metrics.json``."""
        ...


class NullLoopStage:
    """Loop closing switched off: every keyframe passes unchanged, nothing is recorded."""

    def on_keyframe(self, keyframe: Keyframe, state: MapState) -> LoopOutcome:
        """The keyframe as it came."""
        return LoopOutcome(keyframe)

    def between_frames(self, state: MapState) -> LoopOutcome | None:
        """Nothing runs beside."""
        return None

    def close(self, state: MapState) -> dict[int, F64]:
        """Nothing pending."""
        return {}

    def final_constraints(self) -> list[LoopConstraint]:
        """None."""
        return []

    def detection(self, kf_id: int) -> Future[Any] | None:
        """No detection."""
        return None

    def metrics(self) -> dict[str, Any]:
        """No loop-closing figures."""
        return {}
