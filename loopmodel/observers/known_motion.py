"""The seed-003 adaptive depth update when the camera motion is known (e.g. from a visual odometry front end).

Inverse depths of tracked features, each feature with its own reference view.

With the motion unknown, seed 003 estimates the signal rates (eq. 20) and regresses them on
the scaled velocity, ``y = lambda h1 + h2 + eta``. When the pose ``cur_from_ref = (R, t)``
(metres) of every view is known, the same relation holds integrated, without rates: a
static point ``P = z* m*`` seen at normalised ``m = (x, y, 1)`` satisfies

    theta * (m_xy t_z - t_xy) = (R m*)_xy - m_xy (R m*)_z,     theta = 1 / z*,

linear in the inverse depth ``theta`` with regressor ``h = m_xy t_z - t_xy`` (nonzero only
when the camera has translated: the persistent-excitation condition of eq. 37). No velocity
estimator is needed (so no estimator lag ``eta`` and no interpolation between views), and the
depth-ratio measurements ``alpha`` of the homography stage, unavailable for a feature the
right camera cannot see, are not needed either. The adaptive least-squares law of eq. 35-36
(``adaptive_ls_step``) updates ``theta`` at each view; a windowed mean of the squared parallax
``(theta |h|)^2`` is the excitation monitor; the relative depth uncertainty follows from the
accumulated information ``sum |h|^2`` and a pixel noise.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from loopmodel.observers.depth_observer import adaptive_ls_step

F64 = NDArray[np.float64]


class KnownMotionDepthObserver:
    """Inverse depths ``theta_i = 1/z*_i`` (1/m) of features along reference rays ``m*_i``
    (normalised, z = 1, each in its own reference camera frame) from views of known pose."""

    def __init__(self, beta: float = 1.5, l_inv0: float = 1e-4, excitation_window_s: float = 1.0) -> None:
        self.beta = beta
        self.l_inv0 = l_inv0
        self.window_s = excitation_window_s
        self.m_ref = np.zeros((0, 3))
        self.theta = np.zeros(0)
        self.l_inv = np.zeros(0)
        self.info = np.zeros(0)  # sum over views of |h|^2 / (1 + (theta t_z)^2)  (m^2)
        self.h_max2 = np.zeros(0)  # largest |h|^2 seen (m^2)
        self.parallax2 = np.zeros(0)  # windowed mean of (theta |h|)^2 (rad^2)
        self.views = np.zeros(0, dtype=np.int64)

    def __len__(self) -> int:
        return int(self.theta.size)

    def add(self, m_ref: ArrayLike, theta0: ArrayLike) -> None:
        """Append features.

        Reference rays (N x 2 normalised or N x 3 with z = 1) and initial inverse depths (1/m,
        scalar or N).
        """
        m = np.asarray(m_ref, dtype=float)
        m = m.reshape(-1, m.shape[-1]) if m.size else np.zeros((0, 2))
        if m.shape[1] == 2:
            m = np.column_stack([m, np.ones(len(m))])
        n = len(m)
        self.m_ref = np.vstack([self.m_ref, m / m[:, 2:3]])
        self.theta = np.concatenate([self.theta, np.broadcast_to(np.asarray(theta0, dtype=float), (n,))])
        self.l_inv = np.concatenate([self.l_inv, np.full(n, self.l_inv0)])
        self.info = np.concatenate([self.info, np.zeros(n)])
        self.h_max2 = np.concatenate([self.h_max2, np.zeros(n)])
        self.parallax2 = np.concatenate([self.parallax2, np.zeros(n)])
        self.views = np.concatenate([self.views, np.zeros(n, dtype=np.int64)])

    def keep(self, mask: NDArray[np.bool_]) -> None:
        """Drop the features where ``mask`` is False."""
        for name in ("m_ref", "theta", "l_inv", "info", "h_max2", "parallax2", "views"):
            setattr(self, name, getattr(self, name)[mask])

    def update(self, cur_from_ref_rot: ArrayLike, cur_from_ref_t: ArrayLike, m_cur: ArrayLike, dt_s: float,
               which: NDArray[np.int64] | None = None) -> None:
        """One view.

        Per-feature rotations (N x 3 x 3 or 3 x 3), translations (N x 3 or 3, metres) of
        ``cur_from_ref`` and the current normalised image points (N x 2) of the features ``which``
        (default: all); ``dt_s`` the time since the previous view.
        """
        idx = np.arange(len(self)) if which is None else np.asarray(which, dtype=np.int64)
        if idx.size == 0:
            return
        R = np.broadcast_to(np.asarray(cur_from_ref_rot, dtype=float), (idx.size, 3, 3))
        t = np.broadcast_to(np.asarray(cur_from_ref_t, dtype=float), (idx.size, 3))
        m = np.asarray(m_cur, dtype=float).reshape(-1, 2)
        q = np.einsum("nij,nj->ni", R, self.m_ref[idx])
        y = q[:, :2] - m * q[:, 2:3]
        h = m * t[:, 2:3] - t[:, :2]
        th = self.theta[idx]
        step, l_new = adaptive_ls_step(self.l_inv[idx], h, y - th[:, None] * h, dt_s, self.beta)
        self.theta[idx] = th + step
        self.l_inv[idx] = l_new
        hh = np.einsum("ni,ni->n", h, h)
        # errors-in-variables: the current pixel enters both y and h (through m t_z)
        self.info[idx] += hh / (1.0 + (self.theta[idx] * t[:, 2]) ** 2)
        self.h_max2[idx] = np.maximum(self.h_max2[idx], hh)
        a = float(np.exp(-dt_s / self.window_s))
        self.parallax2[idx] = a * self.parallax2[idx] + (1 - a) * hh * self.theta[idx] ** 2
        self.views[idx] += 1

    def depth_m(self) -> F64:
        """Reference-frame depths ``z*`` (m); NaN where the estimate is not positive."""
        with np.errstate(divide="ignore"):
            return np.where(self.theta > 0, 1.0 / np.where(self.theta > 0, self.theta, 1.0), np.nan)

    def rel_sigma(self, sigma_norm: float) -> F64:
        """Relative standard deviation of the depths for a normalised image noise
        ``sigma_norm`` (pixels / focal length): independent noise of the current views through
        the accumulated information, plus the reference pixel's error, common to all views."""
        with np.errstate(divide="ignore", invalid="ignore"):
            var = sigma_norm**2 * (1.0 / self.info + 1.0 / self.h_max2)
            out = np.sqrt(var) / np.abs(self.theta)
        return np.where(np.isfinite(out), out, np.inf)

    def excited(self, min_parallax_rad: float) -> NDArray[np.bool_]:
        """Persistent-excitation monitor: the recent mean parallax is at least ``min_parallax_rad``."""
        return np.asarray(self.parallax2 >= min_parallax_rad**2)
