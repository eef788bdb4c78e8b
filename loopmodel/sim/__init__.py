"""Synthetic scan generator.

Scene, ray-cast renderer, hand-held trajectories with loops, laser-stripe profiler, fault injection,
MCAP output (``loopmodel simulate scan``).
"""

from loopmodel.sim.generate import (
    PRESETS,
    SimulationResult,
    calibration_of,
    camera_of,
    simulate_scan,
)
from loopmodel.sim.render import Raycaster, pixel_rays
from loopmodel.sim.scene import Scene, build_scene

__all__ = [
    "PRESETS",
    "Raycaster",
    "Scene",
    "SimulationResult",
    "build_scene",
    "calibration_of",
    "camera_of",
    "pixel_rays",
    "simulate_scan",
]
