"""The simulation of seed 003 section 6.

12 static features, a camera translating with ``v_cam(t) = (cos t, -sin t, 0.1 sin t)`` m/s and
rotating with ``w_cam(t) = (0.1 sin t, 0.1 cos t, 0.05)`` rad/s (our choice: the seed does not state
it), both in the camera frame; identity intrinsics; gains of eq. 49; 10 s.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import invert_pose, se3_exp
from loopmodel.observers.depth_observer import DepthObserver, ObserverConfig, ViewMeasurement

F64 = NDArray[np.float64]
Motion = Callable[[float], tuple[F64, F64]]


def paper_motion(t: float) -> tuple[F64, F64]:
    """Camera linear (m/s) and angular (rad/s) velocity in the camera frame at time t."""
    return (np.array([np.cos(t), -np.sin(t), 0.1 * np.sin(t)]), np.array([0.1 * np.sin(t), 0.1 * np.cos(t), 0.05]))


def pure_rotation(t: float) -> tuple[F64, F64]:
    """No translation: depths are not observable (for the excitation check)."""
    return np.zeros(3), np.array([0.1 * np.sin(t), 0.1 * np.cos(t), 0.05])


@dataclass
class SimulationResult:
    """Time series of a simulated run and its ground truth."""

    t_s: F64
    lambda_hat: F64  # T x N
    lambda_true: F64  # N
    points_ref_m: F64  # N x 3 ground truth in the reference camera frame
    observer: DepthObserver

    @property
    def rel_err(self) -> F64:
        """T x N relative errors of the depth ratios."""
        return np.abs(self.lambda_hat - self.lambda_true) / self.lambda_true

    def converge_time_s(self, tol: float = 0.05) -> float:
        """First time after which every feature's relative error stays below ``tol`` (inf if never)."""
        worst = self.rel_err.max(axis=1)
        bad = np.flatnonzero(worst > tol)
        if bad.size == 0:
            return float(self.t_s[0])
        if bad[-1] == len(worst) - 1:
            return float("inf")
        return float(self.t_s[bad[-1] + 1])


def simulate(
    duration_s: float = 10.0,
    rate_hz: float = 1000.0,
    n_features: int = 12,
    seed: int = 3,
    motion: Motion = paper_motion,
    config: ObserverConfig | None = None,
) -> SimulationResult:
    """Run the observer on exact measurements of a simulated scene fed at ``rate_hz``."""
    rng = np.random.default_rng(seed)
    points_ref = np.column_stack(
        [rng.uniform(-1.5, 1.5, n_features), rng.uniform(-1.0, 1.0, n_features), rng.uniform(3.0, 6.0, n_features)]
    )
    A = np.eye(3)
    p_ref = points_ref[:, :2] / points_ref[:, 2:3]
    obs = DepthObserver(A, p_ref, config)
    ref_from_cam = np.eye(4)
    steps_per_view = max(1, int(round(1.0 / (rate_hz * 1e-3))))  # true motion at >= 1 kHz
    dt_fine = 1.0 / (rate_hz * steps_per_view)
    n_views = int(round(duration_s * rate_hz))
    t = 0.0
    times, lams = [], []
    for k in range(n_views + 1):
        if k > 0:
            for _ in range(steps_per_view):  # integrate the true camera motion finely
                v, w = motion(t + dt_fine / 2)
                ref_from_cam = ref_from_cam @ se3_exp(np.concatenate([v, w]) * dt_fine)
                t += dt_fine
        cam_from_ref = invert_pose(ref_from_cam)
        P = points_ref @ cam_from_ref[:3, :3].T + cam_from_ref[:3, 3]
        obs.feed(ViewMeasurement(t, P[:, :2] / P[:, 2:3], points_ref[:, 2] / P[:, 2], cam_from_ref[:3, :3]))
        times.append(t)
        lams.append(obs.lambda_hat.copy())
    return SimulationResult(np.array(times), np.array(lams), points_ref[0, 2] / points_ref[:, 2], points_ref, obs)
