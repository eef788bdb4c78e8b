"""Depth of features the right camera cannot see (``frontend.mono_depth: observer``).

Corners of a keyframe that find no stereo match are tracked by KLT in the left image; the
seed-003 adaptive depth update with known motion (:class:`KnownMotionDepthObserver`, poses
from the tracker itself) estimates their inverse depth in their keyframe; once a depth has
converged (persistent excitation and a small predicted uncertainty) the feature joins the
per-frame pose solve as a 3-D point, down-weighted by its depth uncertainty like the stereo
points. These points stay in the front end: keyframes, the local BA and the back end see only
stereo landmarks.

The poses come from the tracker, so the depths inherit its scale and its pose errors; the
observer's velocity estimator is not used (see :mod:`loopmodel.observers.known_motion`).
``mono_sigma_px`` (default 3 px) is the image noise of the depth uncertainty and so of the
convergence test and the pose weights: KLT noise alone (~0.5 px) made the predicted depth
uncertainty 4-27x too small on KITTI, where the tracker's frame-to-frame pose errors
(~0.03-0.08 deg rotation, ~0.4 deg translation direction) dominate; with 3 px the median
ratio of actual (against stereo) to predicted depth error is ~0.7 on the half-masked clip.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import FrontendConfig
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose
from loopmodel.imaging.klt import Pyramid, track_klt
from loopmodel.observers.depth_observer import ObserverConfig
from loopmodel.observers.known_motion import KnownMotionDepthObserver

F64 = NDArray[np.float64]
MIN_VIEWS = 2  # views after the reference before a depth may be used


class MonoDepthTracks:
    """Left-image tracks without stereo depth and their observer depths (rectified frames).

    ``ref_kf`` (N,) keyframe id of each feature's reference view; ``uv`` (N, 2) its pixel
    in the last successfully tracked frame."""

    def __init__(self, config: FrontendConfig, camera: CentralCamera, image_size: tuple[int, int]) -> None:
        self.cfg = config
        self.camera = camera
        self.image_size = image_size
        self.K_inv = np.linalg.inv(np.array([[camera.px, 0, camera.u0], [0, camera.py, camera.v0], [0, 0, 1.0]]))
        self.sigma_norm = config.mono_sigma_px / camera.px
        self.obs = KnownMotionDepthObserver(beta=ObserverConfig().beta)  # the paper's beta = 1.5
        self.ref_kf = np.zeros(0, dtype=np.int64)
        self.uv_ref = np.zeros((0, 2))
        self.uv = np.zeros((0, 2))
        self._pending: tuple[F64, NDArray[np.bool_]] | None = None

    def __len__(self) -> int:
        return int(self.ref_kf.size)

    def reset(self) -> None:
        """Forget every track (after an unconnected keyframe: the poses are not related)."""
        self.keep(np.zeros(len(self), bool))

    def keep(self, mask: NDArray[np.bool_]) -> None:
        self.obs.keep(mask)
        self.ref_kf, self.uv_ref, self.uv = self.ref_kf[mask], self.uv_ref[mask], self.uv[mask]

    def _norm(self, uv: F64) -> F64:
        return (np.column_stack([uv, np.ones(len(uv))]) @ self.K_inv.T)[:, :2]

    def spawn(self, kf_id: int, corners_px: F64, median_depth_m: float, avoid_px: F64) -> None:
        """Start tracks at the corners of keyframe ``kf_id`` that found no stereo match.

        Away from existing tracks and the keyframe's stereo points (``avoid_px``), up to
        ``mono_max_features``; initial depth: the keyframe's median stereo depth.
        """
        room = self.cfg.mono_max_features - len(self)
        if room <= 0 or len(corners_px) == 0:
            return
        others = np.vstack([self.uv, avoid_px.reshape(-1, 2)])
        c = np.asarray(corners_px, dtype=float).reshape(-1, 2)
        if len(others):
            d2 = ((c[:, None, :] - others[None, :, :]) ** 2).sum(-1).min(axis=1)
            c = c[d2 >= self.cfg.min_distance_px**2]
        c = c[:room]
        self.obs.add(self._norm(c), 1.0 / median_depth_m)
        self.ref_kf = np.concatenate([self.ref_kf, np.full(len(c), kf_id, dtype=np.int64)])
        self.uv_ref = np.vstack([self.uv_ref, c])
        self.uv = np.vstack([self.uv, c])

    def _points_ref(self) -> F64:
        z = self.obs.depth_m()
        return self.obs.m_ref * np.where(np.isfinite(z), z, 1e6)[:, None]

    def points_in(self, kf_from_ref: dict[int, F64]) -> F64:
        """(N, 3) points in the frame ``kf_from_ref`` maps into (metres)."""
        P = self._points_ref()
        out = np.zeros_like(P)
        for k, T in kf_from_ref.items():
            sel = self.ref_kf == k
            out[sel] = P[sel] @ T[:3, :3].T + T[:3, 3]
        return out

    def converged(self) -> NDArray[np.bool_]:
        """Depths usable as 3-D points: excited, enough views, small predicted uncertainty."""
        return (
            (self.obs.views >= MIN_VIEWS)
            & self.obs.excited(np.radians(self.cfg.mono_min_parallax_deg))
            & (self.obs.rel_sigma(self.sigma_norm) <= self.cfg.mono_max_rel_sigma)
            & (self.obs.theta > 0)
        )

    def sigma_z_m(self) -> F64:
        """Depth standard deviation (m) of every feature."""
        return self.obs.rel_sigma(self.sigma_norm) * self.obs.depth_m()

    def track(
        self, prev: Pyramid, cur: Pyramid, pred_from_kf: F64, kf_from_ref: dict[int, F64]
    ) -> tuple[F64, NDArray[np.bool_]]:
        """KLT from the last good frame.

        The search starts at the projection of the current depth estimate at the predicted pose.
        Held until :meth:`commit`.
        """
        cfg = self.cfg
        if len(self) == 0:
            self._pending = (np.zeros((0, 2)), np.zeros(0, bool))
            return self._pending
        P = self.points_in(kf_from_ref)
        p = P @ pred_from_kf[:3, :3].T + pred_from_kf[:3, 3]
        front = p[:, 2] > 1e-3
        guess = self.uv.copy()
        guess[front] = self.camera.project(p[front])
        uv, ok, _fb = track_klt(prev, cur, self.uv, guess, cfg.klt_window_px, cfg.klt_levels,
                                cfg.fb_threshold_px, cfg.klt_iterations, self.image_size)
        self._pending = (uv, ok & front)
        return self._pending

    def commit(self, cur_from_kf: F64, kf_from_ref: dict[int, F64], dt_s: float, keep: NDArray[np.bool_]) -> None:
        """After a measured pose.

        Update the depths of the tracks kept (KLT and pose checks passed) with ``cur_from_ref`` =
        ``cur_from_kf @ kf_from_ref``; drop the others.
        """
        assert self._pending is not None
        uv, _ok = self._pending
        self._pending = None
        self.keep(keep)
        if len(self) == 0:
            return
        self.uv = uv[keep]
        R = np.zeros((len(self), 3, 3))
        t = np.zeros((len(self), 3))
        for k, T in kf_from_ref.items():
            sel = self.ref_kf == k
            c = cur_from_kf @ T
            R[sel], t[sel] = c[:3, :3], c[:3, 3]
        self.obs.update(R, t, self._norm(self.uv), dt_s)


def kf_from_ref_map(world_from_kf_rect: dict[int, F64], active_kf: int, refs: NDArray[np.int64]) -> dict[int, F64]:
    """Transforms from each reference keyframe (rectified frame) into the active one."""
    kf_from_world = invert_pose(world_from_kf_rect[active_kf])
    return {int(k): kf_from_world @ world_from_kf_rect[int(k)] for k in np.unique(refs)}
