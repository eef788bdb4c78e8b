"""Central camera models: the unified central projection (Barreto; Mei) with parameter xi.

``xi = 0`` is a pinhole camera, ``xi = 1`` a parabolic mirror seen by a telecentric lens.
Camera frame: x right, y down, z forward (OpenCV). Pixels: u right, v down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class CentralCamera:
    """Unified central projection: ``x = X / (Z + xi*rho)``, ``u = px*x + u0`` (pixels)."""

    px: float
    py: float
    u0: float
    v0: float
    xi: float = 0.0

    @classmethod
    def from_K(cls, K: ArrayLike, xi: float = 0.0) -> CentralCamera:
        """Camera from a 3x3 intrinsic matrix (pixels); skew is ignored."""
        K = np.asarray(K, dtype=float)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), xi)

    @property
    def K(self) -> F64:
        """3x3 intrinsic matrix (pixels)."""
        return np.array([[self.px, 0.0, self.u0], [0.0, self.py, self.v0], [0.0, 0.0, 1.0]])

    def normalized(self, p_in_cam: ArrayLike) -> F64:
        """N x 2 normalised coordinates of N x 3 points in the camera frame (metres)."""
        P = np.asarray(p_in_cam, dtype=float).reshape(-1, 3)
        if self.xi == 0.0:  # pinhole: no norm needed
            return P[:, :2] / P[:, 2:3]
        denom = P[:, 2] + self.xi * np.linalg.norm(P, axis=1)
        return P[:, :2] / denom[:, None]

    def project(self, p_in_cam: ArrayLike) -> F64:
        """N x 2 pixel coordinates of N x 3 points in the camera frame (metres)."""
        xy = self.normalized(p_in_cam)
        return np.column_stack([self.px * xy[:, 0] + self.u0, self.py * xy[:, 1] + self.v0])

    def in_front(self, p_in_cam: ArrayLike) -> NDArray[np.bool_]:
        """Which points have a valid projection (positive denominator ``Z + xi*rho``)."""
        P = np.asarray(p_in_cam, dtype=float).reshape(-1, 3)
        return np.asarray(P[:, 2] + self.xi * np.linalg.norm(P, axis=1) > 1e-9)

    def project_jacobian(self, p_in_cam: ArrayLike) -> F64:
        """N x 2 x 3 Jacobian of the pixel coordinates w.r.t. the camera-frame point."""
        P = np.asarray(p_in_cam, dtype=float).reshape(-1, 3)
        if self.xi == 0.0:  # pinhole fast path (same values as the general formula)
            iz = 1.0 / P[:, 2]
            J = np.zeros((P.shape[0], 2, 3))
            J[:, 0, 0] = self.px * iz
            J[:, 0, 2] = -self.px * P[:, 0] * iz * iz
            J[:, 1, 1] = self.py * iz
            J[:, 1, 2] = -self.py * P[:, 1] * iz * iz
            return J
        rho = np.linalg.norm(P, axis=1)
        d = P[:, 2] + self.xi * rho
        safe_rho = np.where(rho > 0, rho, 1.0)
        dd = np.column_stack(
            [self.xi * P[:, 0] / safe_rho, self.xi * P[:, 1] / safe_rho, 1 + self.xi * P[:, 2] / safe_rho]
        )
        J = np.zeros((P.shape[0], 2, 3))
        for r, f in ((0, self.px), (1, self.py)):
            J[:, r, :] = -f * (P[:, r] / d**2)[:, None] * dd
            J[:, r, r] += f / d
        return J

    def lift(self, uv_px: ArrayLike) -> F64:
        """N x 3 unit rays (camera frame) of N x 2 pixels; inverse of :meth:`project`."""
        uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
        x = (uv[:, 0] - self.u0) / self.px
        y = (uv[:, 1] - self.v0) / self.py
        r2 = x * x + y * y
        eta = (self.xi + np.sqrt(np.maximum(1.0 + (1.0 - self.xi**2) * r2, 0.0))) / (r2 + 1.0)
        rays = np.column_stack([eta * x, eta * y, eta - self.xi])
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)
