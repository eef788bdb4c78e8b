"""Faults on demand.

Which generated frames are dropped, blacked out, blurred, occluded or carry a duplicated timestamp.
Frame indices count generated frames from 0; ranges are inclusive.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import SimFaultsConfig
from loopmodel.errors import ConfigError

F64 = NDArray[np.float64]

KINDS = ("dropped", "blackout", "blur", "occluder", "duplicate_timestamp")


@dataclass(frozen=True)
class Fault:
    """One fault over the generated frames ``first``..``last`` (inclusive)."""

    kind: str
    first: int
    last: int

    def frames(self) -> range:
        return range(self.first, self.last + 1)


@dataclass
class FaultPlan:
    """All faults of a run, with per-frame lookups."""

    faults: list[Fault] = field(default_factory=list)
    frames: int = 0

    @classmethod
    def from_config(cls, cfg: SimFaultsConfig, frames: int, source: str = "simulation.faults") -> FaultPlan:
        """Validated plan; a range outside ``0..frames-1`` raises :class:`ConfigError`."""
        out: list[Fault] = []

        def check(kind: str, a: int, b: int) -> None:
            if a > b:
                raise ConfigError(source, f"{kind}: range {a}-{b} is empty (first > last)")
            if a < 0 or b >= frames:
                raise ConfigError(source, f"{kind}: frames {a}-{b} outside 0-{frames - 1}")
            out.append(Fault(kind, int(a), int(b)))

        for i in cfg.dropped:
            check("dropped", i, i)
        for a, b in cfg.blackout:
            check("blackout", a, b)
        for a, b in cfg.blur:
            check("blur", a, b)
        for a, b in cfg.occluder:
            check("occluder", a, b)
        for i in cfg.duplicate_timestamp:
            if i < 1:
                raise ConfigError(source, f"duplicate_timestamp: frame {i} has no predecessor (use >= 1)")
            check("duplicate_timestamp", i, i)
        out.sort(key=lambda f: (f.first, f.kind))
        return cls(out, frames)

    def kinds_at(self, index: int) -> set[str]:
        """Fault kinds active at generated frame ``index``."""
        return {f.kind for f in self.faults if f.first <= index <= f.last}

    def occluder_fraction(self, index: int) -> float | None:
        """Progress (0..1) of the occluder across the view at ``index``, None when absent."""
        for f in self.faults:
            if f.kind == "occluder" and f.first <= index <= f.last:
                return (index - f.first) / max(f.last - f.first, 1)
        return None

    def records(self, start_time_ns: int, period_ns: float) -> list[dict[str, int | str]]:
        """JSON-able descriptions with frame and time ranges."""
        return [
            {
                "kind": f.kind,
                "first_frame": f.first,
                "last_frame": f.last,
                "first_time_ns": start_time_ns + round(f.first * period_ns),
                "last_time_ns": start_time_ns + round(f.last * period_ns),
            }
            for f in self.faults
        ]


def cam_from_occluder(fraction: float) -> F64:
    """Pose of the occluder (a hand-sized ellipsoid) in the left-camera frame.

    It crosses the view from left to right 0.2 m in front of the camera (always in view) as
    ``fraction`` goes 0 -> 1.
    """
    T = np.eye(4)
    T[:3, 3] = [-0.1 + 0.2 * fraction, 0.04 - 0.06 * fraction, 0.2]
    a = 0.6 * fraction - 0.3
    c, s = np.cos(a), np.sin(a)
    T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return T
