"""Listening to a run: what a visualiser or recorder is told, event by event.

The pipeline calls every listener after each step is done whole (a frame tracked, a keyframe
through loop closing and the back end, a correction applied, the run finished). A listener only
reads: it must not change what it is given. Every method is a no-op here, so a listener
overrides only what it needs.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from loopmodel.frontend import FrameResult, Keyframe, TrackedFeatures
    from loopmodel.result import RunResult
    from loopmodel.types import StereoFrame

F64 = np.ndarray


class RunListener:
    """Told what a run does; subclass and override the events of interest."""

    def on_frame(self, frame: StereoFrame, result: FrameResult, tracks: TrackedFeatures) -> None:
        """A frame was tracked (``tracks``: the features of the rectified left image)."""

    def on_keyframe(self, keyframe: Keyframe, result: FrameResult) -> None:
        """A keyframe went through loop closing and the back end."""

    def on_correction(self, world_from_kf: Mapping[int, F64]) -> None:
        """Keyframe poses (4x4 ``world_from_kf``, metres) were corrected."""

    def on_live_mesh(self, mesh: Any) -> None:
        """The live mesh (an open3d ``TriangleMesh``, world frame, metres) was updated."""

    def on_loop_events(self, events: list[dict[str, Any]]) -> None:
        """Loop closures or relocalizations happened (the records of ``metrics.json``)."""

    def on_finish(self, result: RunResult) -> None:
        """The run ended (final trajectory, mesh and metrics are in ``result``)."""
