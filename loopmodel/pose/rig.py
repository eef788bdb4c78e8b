"""A rig of N central cameras with known ``cam_from_rig`` transforms, and a point feature term.

The point feature term of the pose solver (2-D/3-D correspondences).

The solver (:mod:`loopmodel.pose.solver`) works on *terms*: anything that returns, for a
pose ``rig_from_ref``, residual vectors and their Jacobian with respect to a left
perturbation ``rig_from_ref <- exp(delta) rig_from_ref`` (``delta = (v, w)``, metres and
radians). Points are one term; line/conic features plug in the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose
from loopmodel.pose._point_kernels import point_jacobian, point_residuals

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class CameraRig:
    """N central cameras rigidly mounted.

    ``cam_from_rig[j]`` maps rig-frame points (metres) into camera j's frame.
    """

    cameras: tuple[CentralCamera, ...]
    cam_from_rig: tuple[F64, ...]

    def __post_init__(self) -> None:
        if len(self.cameras) != len(self.cam_from_rig) or not self.cameras:
            raise ValueError("a rig needs one cam_from_rig transform per camera (at least one)")
        poses = tuple(np.asarray(T, dtype=float).reshape(4, 4) for T in self.cam_from_rig)
        object.__setattr__(self, "cam_from_rig", poses)

    @classmethod
    def single(cls, camera: CentralCamera) -> CameraRig:
        """One camera whose frame is the rig frame."""
        return cls((camera,), (np.eye(4),))

    @classmethod
    def stereo(
        cls, left: CentralCamera, right: CentralCamera, right_from_left: ArrayLike
    ) -> CameraRig:
        """Stereo pair; the rig frame is the left camera frame."""
        return cls((left, right), (np.eye(4), np.asarray(right_from_left, dtype=float)))

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def is_single_pinhole(self) -> bool:
        """True for one pinhole camera (xi = 0) at the rig origin."""
        return (
            len(self.cameras) == 1
            and self.cameras[0].xi == 0.0
            and np.allclose(self.cam_from_rig[0], np.eye(4))
        )

    def rig_from_cam(self, j: int) -> F64:
        """Pose of camera j in the rig frame."""
        return invert_pose(self.cam_from_rig[j])


def point_cross_rows(p: F64, A: F64) -> F64:
    """Rows ``p_i x a_ik`` for points p (N, 3) and row stacks A (N, K, 3).

    Equals ``-A_i [p_i]x``, the rotation block of a left-perturbation Jacobian.
    """
    px, py, pz = p[:, 0, None], p[:, 1, None], p[:, 2, None]
    ax, ay, az = A[:, :, 0], A[:, :, 1], A[:, :, 2]
    return np.stack([py * az - pz * ay, pz * ax - px * az, px * ay - py * ax], axis=2)


class PoseTerm(Protocol):
    """A group of features that constrains the rig pose (points, lines, ...)."""

    dim: int  # dimension of one residual vector

    def __len__(self) -> int: ...

    def residuals(self, rig_from_ref: F64) -> F64:
        """(K, dim) residuals (measured units, e.g. pixels) at the pose."""
        ...

    def residuals_and_jacobian(self, rig_from_ref: F64) -> tuple[F64, F64]:
        """(K, dim) residuals and (K, dim, 6) Jacobian w.r.t. a left twist ``(v, w)``."""
        ...


@dataclass
class PointTerm:
    """2-D/3-D point correspondences.

    ``p_in_ref`` (N, 3, metres, reference frame) seen at ``uv_px`` (N, 2, pixels) by camera
    ``cam_index`` (N,) of the rig. Residual = projection - measurement (pixels). ``prior_weight``
    (optional, N) multiplies the robust weights (e.g. the ratio of pixel variance to
    pixel-plus-depth variance).

    With ``inverse_depth_per_m`` (N,) the points are homogeneous: ``p_in_ref`` holds bearing rays
    and the point is ``ray / inverse_depth``; an inverse depth of 0 is a point at infinity (a
    bearing-only observation that constrains the rotation alone). Residuals and Jacobians use
    ``R ray + inverse_depth t``, which projects like the point for a positive inverse depth.
    """

    rig: CameraRig
    p_in_ref: F64
    uv_px: F64
    cam_index: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    prior_weight: F64 | None = None  # (N,) in (0, 1]: e.g. down-weights points of uncertain depth
    dim: int = 2
    inverse_depth_per_m: F64 | None = None  # (N,) >= 0: p_in_ref are rays (homogeneous points)

    def __post_init__(self) -> None:
        self.p_in_ref = np.asarray(self.p_in_ref, dtype=float).reshape(-1, 3)
        self.uv_px = np.asarray(self.uv_px, dtype=float).reshape(-1, 2)
        n = self.p_in_ref.shape[0]
        if self.uv_px.shape[0] != n:
            raise ValueError(f"{n} points but {self.uv_px.shape[0]} image measurements")
        ci = np.asarray(self.cam_index, dtype=np.int64).ravel()
        self.cam_index = np.zeros(n, dtype=np.int64) if ci.size == 0 else ci
        if self.cam_index.shape[0] != n:
            raise ValueError("cam_index must have one entry per point")
        if self.inverse_depth_per_m is not None:
            self.inverse_depth_per_m = np.asarray(self.inverse_depth_per_m, dtype=float).ravel()
            if self.inverse_depth_per_m.shape[0] != n:
                raise ValueError("inverse_depth_per_m must have one entry per point")
        self._groups = [np.flatnonzero(self.cam_index == j) for j in range(len(self.rig))]
        self._single = len(self._groups[0]) == n

    def __len__(self) -> int:
        return int(self.p_in_ref.shape[0])

    def subset(self, mask: NDArray[np.bool_] | NDArray[np.int64]) -> PointTerm:
        """The term restricted to some of its correspondences."""
        pw = None if self.prior_weight is None else self.prior_weight[mask]
        rho = None if self.inverse_depth_per_m is None else self.inverse_depth_per_m[mask]
        return PointTerm(
            self.rig, self.p_in_ref[mask], self.uv_px[mask], self.cam_index[mask], pw, inverse_depth_per_m=rho
        )

    def _rho(self, idx: NDArray[np.int64] | None) -> F64 | None:
        """(k, 1) inverse depths of the selected points (None: Euclidean points)."""
        if self.inverse_depth_per_m is None:
            return None
        rho = self.inverse_depth_per_m if idx is None else self.inverse_depth_per_m[idx]
        return rho[:, None]

    def _cam_points(
        self, rig_from_ref: F64, j: int, idx: NDArray[np.int64] | None
    ) -> tuple[F64, F64]:
        """Points in the rig and in camera j (homogeneous points: scaled by their inverse depth)."""
        P = self.p_in_ref if idx is None else self.p_in_ref[idx]
        rho = self._rho(idx)
        T = self.rig.cam_from_rig[j]
        if rho is None:
            p_rig = P @ rig_from_ref[:3, :3].T + rig_from_ref[:3, 3]
            return p_rig, p_rig @ T[:3, :3].T + T[:3, 3]
        q_rig = P @ rig_from_ref[:3, :3].T + rho * rig_from_ref[:3, 3]
        return q_rig, q_rig @ T[:3, :3].T + rho * T[:3, 3]

    def _kernel_args(self, rig_from_ref: F64, j: int, idx: NDArray[np.int64] | None) -> tuple:  # type: ignore[type-arg]
        """Arguments of the compiled kernels for camera j's points (all when ``idx`` is None)."""
        P = self.p_in_ref if idx is None else self.p_in_ref[idx]
        uv = self.uv_px if idx is None else self.uv_px[idx]
        if self.inverse_depth_per_m is None:
            rho = np.ones(P.shape[0])
        else:
            rho = self.inverse_depth_per_m if idx is None else self.inverse_depth_per_m[idx]
        # contiguous blocks: the signature the warm-up compiles (slices of the 4 x 4 poses were another,
        # which every cold run compiled in its frames; fin13)
        T = np.asarray(rig_from_ref, dtype=np.float64)
        C = self.rig.cam_from_rig[j]
        cam = self.rig.cameras[j]
        c = np.ascontiguousarray
        f64 = np.float64
        return (P, c(rho, dtype=f64), uv, c(T[:3, :3]), c(T[:3, 3]), c(C[:3, :3], dtype=f64), c(C[:3, 3], dtype=f64),
                float(cam.px), float(cam.py), float(cam.u0), float(cam.v0), float(cam.xi))

    def residuals(self, rig_from_ref: F64) -> F64:
        if self._single:
            return point_residuals(*self._kernel_args(rig_from_ref, 0, None))  # type: ignore[no-any-return]
        out = np.empty((len(self), 2))
        for j, idx in enumerate(self._groups):
            if idx.size:
                out[idx] = point_residuals(*self._kernel_args(rig_from_ref, j, idx))
        return out

    def residuals_and_jacobian(self, rig_from_ref: F64) -> tuple[F64, F64]:
        # d uv / d(v, w) = A [I, -[p_rig]x] with A = d uv / d p_rig; -A [p]x rows = p x a_row
        # (homogeneous points: d q_rig / d(v, w) = [rho I, -[q_rig]x]); compiled in _point_kernels
        if self._single:
            return point_jacobian(*self._kernel_args(rig_from_ref, 0, None))  # type: ignore[no-any-return]
        n = len(self)
        r = np.empty((n, 2))
        J = np.empty((n, 2, 6))
        for j, idx in enumerate(self._groups):
            if idx.size:
                r[idx], J[idx] = point_jacobian(*self._kernel_args(rig_from_ref, j, idx))
        return r, J

    def depths(self, rig_from_ref: F64) -> F64:
        """Validity denominator (Z + xi*rho) of every point in its camera (> 0: in front)."""
        out = np.empty(len(self))
        for j, idx in enumerate(self._groups):
            if idx.size == 0:
                continue
            _, p_cam = self._cam_points(rig_from_ref, j, idx)
            xi = self.rig.cameras[j].xi
            out[idx] = p_cam[:, 2] + xi * np.linalg.norm(p_cam, axis=1)
        return out
