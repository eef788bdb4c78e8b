"""Sequential bundle adjustment on the Givens estimator, and the blunder screen built on it.

Unknowns: object points (3 coordinates, world frame, metres; *local* blocks reduced point by
point) and the exterior orientation of every frame (6 parameters; *global* blocks). A frame's
parameters are corrections ``(θ, c)`` to its reference pose: ``world_from_cam =
(R0 exp([θ]x), C0 + c)``; a point's are corrections ``Δ`` to its reference ``X0``.

Observations: image coordinates (pixels), linearised when they are inserted at the *current*
estimate (``A Δ = uv - π(x̂) + A Δ̂``); point priors (control points with a small σ, every
other point with a weak prior from its approximate value, as the seed's object-coordinate
observations) and weak priors on each frame's exterior orientation (its approximate values
from resection). The datum comes from the control points (or, without them, the priors).

When re-linearisation happens: :meth:`SequentialBundle.maybe_relinearize` is called once per
frame (before screening). It measures, for every image row, the error of its linearisation at
the current estimate, ``|π(x̂) - π(x_lin) - A (x̂ - x_lin)|`` (pixels). Rows above ``relin_px``
(default 0.1 σ) are re-linearised: if they are few (≤ 5 % of the rows, typically the rays of
points seen from a short baseline so far) each is replaced in the factor by an update with the
new row and a downdate of the old one; otherwise :meth:`SequentialBundle.relinearize` does a
batch re-factorisation: every reference moves to the current estimate, every row is rebuilt
there and ``R`` is re-factorised from the stored observations (a Gauss–Newton step).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from loopmodel.backend.givens import GivensEstimator
from loopmodel.backend.snooping import SnoopResult, normalized_residuals, snoop
from loopmodel.config import GivensConfig
from loopmodel.errors import EstimationError
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import hat, so3_exp, so3_log
from loopmodel.types import Keyframe

F64 = NDArray[np.float64]


@dataclass
class _FrameRef:
    R0: F64  # world_from_cam rotation (reference)
    C0: F64  # camera centre in world (reference), metres
    prior: tuple[F64, F64, float, float] | None = None  # (R, C, sigma_rad, sigma_m)
    prior_obs: int | None = None


@dataclass
class _PointRef:
    X0: F64
    prior: tuple[F64, float] | None = None  # (X, sigma_m)
    prior_obs: int | None = None
    image_obs: set[int] = field(default_factory=set)


@dataclass
class _ImageObs:
    frame: Hashable
    point: Hashable
    uv_px: F64
    sigma_px: float
    a_lin: F64 = field(default_factory=lambda: np.zeros((2, 9)))  # [A_f | A_p] at linearisation
    x_lin: F64 = field(default_factory=lambda: np.zeros(9))  # corrections (frame, point) there
    uv_lin: F64 = field(default_factory=lambda: np.zeros(2))  # predicted pixels there
    right: bool = False  # observed by the right camera of the stereo rig (``right_from_left``)


def _fkey(fid: Hashable) -> tuple[str, Hashable]:
    return ("frame", fid)


def _pkey(pid: Hashable) -> tuple[str, Hashable]:
    return ("point", pid)


class SequentialBundle:
    """Bundle adjustment updated image point by image point (seed 000)."""

    def __init__(
        self,
        camera: CentralCamera,
        sigma_px: float = 0.5,
        relin_px: float | None = None,
        min_downdate_cos2: float = 1e-6,
    ) -> None:
        self.camera = camera
        self.sigma_px = float(sigma_px)
        self.relin_px = 0.1 * self.sigma_px if relin_px is None else float(relin_px)
        self.est = GivensEstimator(local_block_max=3, min_downdate_cos2=min_downdate_cos2)
        self.frames: dict[Hashable, _FrameRef] = {}
        self.points: dict[Hashable, _PointRef] = {}
        self.image_obs: dict[int, _ImageObs] = {}
        self.n_relinearizations = 0
        self.n_local_relinearizations = 0
        self.right_from_left: F64 | None = None  # 4x4; set to take right-image observations

    # ---------------------------------------------------------------- unknowns
    def add_frame(
        self,
        fid: Hashable,
        world_from_cam: ArrayLike,
        prior_sigma_rad: float | None = 0.05,
        prior_sigma_m: float | None = 0.1,
    ) -> None:
        """New exterior orientation (approximate ``world_from_cam``, 4x4) with an optional prior."""
        if fid in self.frames:
            raise EstimationError(f"frame {fid!r} already exists")
        T = np.asarray(world_from_cam, dtype=float)
        ref = _FrameRef(R0=T[:3, :3].copy(), C0=T[:3, 3].copy())
        self.est.add_parameters(_fkey(fid), 6)
        self.frames[fid] = ref
        if prior_sigma_rad is not None and prior_sigma_m is not None:
            ref.prior = (ref.R0.copy(), ref.C0.copy(), float(prior_sigma_rad), float(prior_sigma_m))
            A, l, sig = self._frame_prior_row(ref)
            ref.prior_obs = self.est.add_observation({_fkey(fid): A}, l, sigma=sig)

    def add_point(self, pid: Hashable, p_in_world: ArrayLike, prior_sigma_m: float | None = 1.0) -> None:
        """New object point (approximate coordinates, metres); small σ makes it a control point."""
        if pid in self.points:
            raise EstimationError(f"point {pid!r} already exists")
        X = np.asarray(p_in_world, dtype=float).reshape(3).copy()
        ref = _PointRef(X0=X)
        self.est.add_parameters(_pkey(pid), 3, local=True)
        self.points[pid] = ref
        if prior_sigma_m is not None:
            ref.prior = (X.copy(), float(prior_sigma_m))
            ref.prior_obs = self.est.add_observation({_pkey(pid): np.eye(3)}, np.zeros(3), sigma=float(prior_sigma_m))

    def _frame_prior_row(self, ref: _FrameRef) -> tuple[F64, F64, F64]:
        assert ref.prior is not None
        Rp, Cp, sr, sm = ref.prior
        l = np.concatenate([so3_log(ref.R0.T @ Rp), Cp - ref.C0])
        return np.eye(6), l, np.array([sr] * 3 + [sm] * 3)

    # ---------------------------------------------------------------- estimates
    def world_from_cam(self, fid: Hashable) -> F64:
        """Current estimate of a frame's pose (4x4)."""
        ref = self.frames[fid]
        x = self.est.block_solution(_fkey(fid))
        T = np.eye(4)
        T[:3, :3] = ref.R0 @ so3_exp(x[:3])
        T[:3, 3] = ref.C0 + x[3:]
        return T

    def point(self, pid: Hashable) -> F64:
        """Current estimate of an object point (world, metres)."""
        return self.points[pid].X0 + self.est.block_solution(_pkey(pid))

    def _linearize(self, o: _ImageObs, with_current: bool = True) -> tuple[dict, F64]:
        fref = self.frames[o.frame]
        pref = self.points[o.point]
        if with_current:
            xf = self.est.block_solution(_fkey(o.frame))
            xp = self.est.block_solution(_pkey(o.point))
        else:
            xf = np.zeros(6)
            xp = np.zeros(3)
        R = fref.R0 @ so3_exp(xf[:3]) if with_current else fref.R0
        C = fref.C0 + xf[3:]
        X = pref.X0 + xp
        p_cam = R.T @ (X - C)
        p_obs, R_obs = p_cam, np.eye(3)
        if o.right:
            if self.right_from_left is None:
                raise EstimationError("right-image observation without a stereo rig (right_from_left)")
            R_obs = self.right_from_left[:3, :3]
            p_obs = R_obs @ p_cam + self.right_from_left[:3, 3]
        if p_obs[2] <= 1e-9:
            raise EstimationError(f"point {o.point!r} is behind frame {o.frame!r}")
        J = self.camera.project_jacobian(p_obs)[0] @ R_obs
        uv = self.camera.project(p_obs)[0]
        A = np.empty((2, 9))
        A[:, 6:] = J @ R.T  # d uv / d X
        A[:, 3:6] = -A[:, 6:]  # d uv / d C
        A[:, :3] = J @ hat(p_cam)  # d uv / d theta (right perturbation)
        x_lin = np.concatenate([xf, xp])
        l = o.uv_px - uv + A @ x_lin
        o.a_lin, o.x_lin, o.uv_lin = A, x_lin, uv
        return {_fkey(o.frame): A[:, :6], _pkey(o.point): A[:, 6:]}, l

    # ------------------------------------------------------------- observations
    def add_image_point(
        self, fid: Hashable, pid: Hashable, uv_px: ArrayLike, sigma_px: float | None = None, right: bool = False
    ) -> int:
        """Insert one image point (u, v pixels) of ``pid`` in ``fid`` (its right camera when ``right``).

        Returns its id.
        """
        if fid not in self.frames:
            raise EstimationError(f"unknown frame {fid!r}")
        if pid not in self.points:
            raise EstimationError(f"unknown point {pid!r}")
        o = _ImageObs(
            fid,
            pid,
            np.asarray(uv_px, dtype=float).reshape(2).copy(),
            self.sigma_px if sigma_px is None else float(sigma_px),
            right=right,
        )
        coeffs, l = self._linearize(o)
        oid = self.est.add_observation(coeffs, l, sigma=o.sigma_px)
        self.image_obs[oid] = o
        self.points[pid].image_obs.add(oid)
        return oid

    def delete_image_point(self, oid: int) -> None:
        """Remove an image point observation (downdating)."""
        o = self.image_obs.get(oid)
        if o is None:
            raise EstimationError(f"image observation {oid!r} was never added or is already deleted")
        self.est.delete_observation(oid)
        del self.image_obs[oid]
        self.points[o.point].image_obs.discard(oid)

    # ---------------------------------------------------------- linearisation
    def linearization_errors(self) -> dict[int, float]:
        """Per image observation: max |π(x̂) - (π(x_lin) + A (x̂ - x_lin))| (pixels).

        The error of the linearised image rows at the current estimate: the quantity that
        decides when re-linearisation is due.
        """
        if not self.image_obs:
            return {}
        sol = self.est.solution()
        obs = list(self.image_obs.values())
        fidx = {fid: i for i, fid in enumerate(self.frames)}
        pidx = {pid: i for i, pid in enumerate(self.points)}
        Rs = np.empty((len(fidx), 3, 3))
        Cs = np.empty((len(fidx), 3))
        xf = np.empty((len(fidx), 6))
        for fid, i in fidx.items():
            ref = self.frames[fid]
            xf[i] = sol[_fkey(fid)]
            Rs[i] = ref.R0 @ so3_exp(xf[i, :3])
            Cs[i] = ref.C0 + xf[i, 3:]
        Xs = np.empty((len(pidx), 3))
        xp = np.empty((len(pidx), 3))
        for pid, i in pidx.items():
            xp[i] = sol[_pkey(pid)]
            Xs[i] = self.points[pid].X0 + xp[i]
        fi = np.array([fidx[o.frame] for o in obs])
        pi = np.array([pidx[o.point] for o in obs])
        p_cam = np.einsum("nji,nj->ni", Rs[fi], Xs[pi] - Cs[fi])
        right = np.array([o.right for o in obs])
        if right.any() and self.right_from_left is not None:
            p_cam[right] = p_cam[right] @ self.right_from_left[:3, :3].T + self.right_from_left[:3, 3]
        uv_now = self.camera.project(p_cam)
        A = np.stack([o.a_lin for o in obs])
        dx = np.hstack([xf[fi], xp[pi]]) - np.stack([o.x_lin for o in obs])
        uv_lin = np.stack([o.uv_lin for o in obs])
        err = uv_now - uv_lin - np.einsum("nij,nj->ni", A, dx)
        return dict(zip(self.image_obs, np.max(np.abs(err), axis=1), strict=True))

    def linearization_error_px(self) -> float:
        """Largest linearisation error of the image rows at the current estimate (pixels)."""
        e = self.linearization_errors()
        return max(e.values(), default=0.0)

    def maybe_relinearize(self, max_local_fraction: float = 0.05) -> str:
        """Re-linearise the rows whose linearisation error exceeds ``relin_px``.

        Few such rows (at most ``max_local_fraction`` of all): each is replaced in the factor
        by its linearisation at the current estimate (update + downdate, *local*). More: a
        batch re-factorisation at the current estimate (:meth:`relinearize`). Returns
        ``"none"``, ``"local"`` or ``"batch"``.
        """
        errs = self.linearization_errors()
        bad = [oid for oid, e in errs.items() if e > self.relin_px]
        if not bad:
            return "none"
        if len(bad) <= max_local_fraction * len(errs):
            for oid in bad:
                o = self.image_obs[oid]
                coeffs, l = self._linearize(o)
                self.est.update_observation(oid, coeffs, l, sigma=o.sigma_px)
            self.n_local_relinearizations += len(bad)
            return "local"
        self.relinearize()
        return "batch"

    def relinearize(self) -> None:
        """Move all references to the current estimate, rebuild every row there, re-factorise."""
        sol = self.est.solution()
        for fid, ref in self.frames.items():
            x = sol[_fkey(fid)]
            ref.R0 = ref.R0 @ so3_exp(x[:3])
            ref.C0 = ref.C0 + x[3:]
        for pid, pref in self.points.items():
            pref.X0 = pref.X0 + sol[_pkey(pid)]
        for fid, ref in self.frames.items():
            if ref.prior_obs is not None:
                A, l, sig = self._frame_prior_row(ref)
                self.est.replace_observation(ref.prior_obs, {_fkey(fid): A}, l, sigma=sig, refactor=False)
        for pid, pref in self.points.items():
            if pref.prior_obs is not None and pref.prior is not None:
                Xp, sm = pref.prior
                self.est.replace_observation(
                    pref.prior_obs, {_pkey(pid): np.eye(3)}, Xp - pref.X0, sigma=sm, refactor=False
                )
        for oid, o in self.image_obs.items():
            coeffs, l = self._linearize(o, with_current=False)
            self.est.replace_observation(oid, coeffs, l, sigma=o.sigma_px, refactor=False)
        self.est.refactorize()
        self.n_relinearizations += 1

    # ---------------------------------------------------------------- snooping
    def snoop(
        self,
        oids: Sequence[int] | None = None,
        *,
        alpha: float = 0.001,
        min_redundancy: float = 0.05,
        max_rejections: int | None = None,
    ) -> SnoopResult:
        """Data snooping (:func:`~loopmodel.backend.snooping.snoop`, significance level
        ``alpha``) on image observations (default: all) whose redundancy reaches
        ``min_redundancy``; rejected ones (at most ``max_rejections``) are deleted."""
        ids = list(self.image_obs) if oids is None else list(oids)
        res = snoop(self.est, ids, alpha=alpha, min_redundancy=min_redundancy, max_rejections=max_rejections)
        for oid in res.rejected:
            o = self.image_obs.pop(oid, None)
            if o is not None:
                self.points[o.point].image_obs.discard(oid)
        return res


@dataclass
class ScreenStats:
    """Counts of a :class:`GivensScreen` (for metrics.json)."""

    tested: int = 0
    rejected: int = 0
    untested: int = 0


class GivensScreen:
    """Blunder screen for a tracking back end: per-keyframe batches in, accepted masks out.

    Every image observation goes into a :class:`SequentialBundle`; once its redundancy number
    reaches ``min_redundancy`` it is tested once by iterative data snooping (α0, default 0.1 %)
    together with the other newly testable ones. ``screen`` returns which of the batch's
    observations are accepted (not rejected so far); observations of earlier batches that
    are rejected later are returned by :meth:`late_rejections` so the caller can remove them.
    """

    def __init__(
        self, camera: CentralCamera, config: GivensConfig, right_from_left: ArrayLike | None = None
    ) -> None:
        """The screen configured by a :class:`loopmodel.config.GivensConfig` section.

        With ``right_from_left`` (4x4, rectified rig) the right-image coordinates of stereo
        observations are screened too.
        """
        self.bundle = SequentialBundle(camera, sigma_px=config.sigma_px)
        self.bundle.relin_px = config.relin_px
        if right_from_left is not None:
            self.bundle.right_from_left = np.asarray(right_from_left, dtype=float).reshape(4, 4)
        self.bundle.est.min_downdate_cos2 = config.min_downdate_cos2
        self.alpha = float(config.alpha)
        self.min_redundancy = float(config.min_redundancy)
        self.point_prior_sigma_m = float(config.point_prior_sigma_m)
        self.frame_prior = (float(config.frame_prior_sigma_rad), float(config.frame_prior_sigma_m))
        self.stats = ScreenStats()
        self._pending: list[int] = []
        self._key: dict[int, tuple[Hashable, Hashable]] = {}
        self._late: list[tuple[Hashable, Hashable]] = []

    @classmethod
    def from_config(
        cls, camera: CentralCamera, config: GivensConfig, right_from_left: ArrayLike | None = None
    ) -> GivensScreen:
        """The screen of a :class:`loopmodel.config.GivensConfig` section (the constructor)."""
        return cls(camera, config, right_from_left)

    def screen_keyframe(self, keyframe: Keyframe) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """Screen one front-end keyframe, its pose and points in its rectified left camera.

        Reads ``id``, ``world_from_kf`` (4x4), ``landmark_ids`` (M,), ``points_in_kf`` (M x 3,
        metres, keyframe frame), ``stereo_px`` (M x 3: u_left, u_right, v) and ``mono_obs``
        (K x 3: landmark id, u, v). New landmarks enter with their stereo point as approximate
        value (weak prior); the left-image coordinates are screened. Returns the accepted masks
        of the stereo and the monocular observations; earlier observations rejected now are in
        :meth:`late_rejections` as ``(keyframe_id, landmark_id)``.
        """
        T = np.asarray(keyframe.world_from_kf, dtype=float)
        lids = np.asarray(keyframe.landmark_ids, dtype=np.int64).reshape(-1)
        pts = np.asarray(keyframe.points_in_kf, dtype=float).reshape(-1, 3)
        st = np.asarray(keyframe.stereo_px, dtype=float).reshape(-1, 3)
        mono = np.asarray(keyframe.mono_obs, dtype=float).reshape(-1, 3)
        p_world = pts @ T[:3, :3].T + T[:3, 3]
        for lid, pw in zip(lids.tolist(), p_world, strict=True):
            if lid not in self.bundle.points:
                self.add_point(lid, pw)
        mono_ids = mono[:, 0].astype(np.int64)
        keep_mono = np.array([m in self.bundle.points for m in mono_ids.tolist()], dtype=bool)
        stereo = self.bundle.right_from_left is not None
        n_st = lids.size
        ids = [*lids.tolist(), *(lids.tolist() if stereo else []), *mono_ids[keep_mono].tolist()]
        uv = np.vstack([st[:, [0, 2]], *([st[:, [1, 2]]] if stereo else []), mono[keep_mono, 1:3]])
        right = [False] * n_st + [True] * (n_st if stereo else 0) + [False] * int(keep_mono.sum())
        first = not self.bundle.frames
        mask = self.screen(int(keyframe.id), T, ids, uv, first_frame=first, right=right)
        m_st = mask[:n_st] & (mask[n_st : 2 * n_st] if stereo else True)
        m_mono = np.ones(mono_ids.size, dtype=bool)
        m_mono[np.flatnonzero(keep_mono)] = mask[(2 if stereo else 1) * n_st :]
        return m_st, m_mono

    def add_point(self, pid: Hashable, p_in_world: ArrayLike, prior_sigma_m: float | None = None) -> None:
        """Register an object point (approximate world coordinates, metres)."""
        self.bundle.add_point(pid, p_in_world, self.point_prior_sigma_m if prior_sigma_m is None else prior_sigma_m)

    def screen(
        self,
        frame_id: Hashable,
        world_from_cam: ArrayLike,
        point_ids: Sequence[Hashable],
        uv_px: ArrayLike,
        first_frame: bool = False,
        right: Sequence[bool] | None = None,
    ) -> NDArray[np.bool_]:
        """Insert one keyframe's observations (N point ids, N x 2 pixels, optionally flagged as
        right-image observations); return the accepted mask."""
        b = self.bundle
        sr, sm = self.frame_prior
        if first_frame:
            sr, sm = sr * 1e-3, sm * 1e-3
        b.add_frame(frame_id, world_from_cam, sr, sm)
        uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
        if len(point_ids) != uv.shape[0]:
            raise EstimationError("screen: point_ids and uv_px differ in length")
        flags = list(right) if right is not None else [False] * len(point_ids)
        oids = [b.add_image_point(frame_id, pid, uv[i], right=flags[i]) for i, pid in enumerate(point_ids)]
        for oid, pid in zip(oids, point_ids, strict=True):
            self._key[oid] = (frame_id, pid)
        self._pending.extend(oids)
        b.maybe_relinearize()
        rejected = set(self._test_pending())
        for oid in rejected:
            if oid not in oids:
                self._late.append(self._key[oid])
        self.stats.untested = len(self._pending)
        return np.array([oid not in rejected for oid in oids], dtype=bool)

    def _test_pending(self) -> list[int]:
        b = self.bundle
        if not self._pending:
            return []
        try:
            _, q = normalized_residuals(b.est, self._pending)
        except EstimationError:
            return []  # not yet regular: keep everything pending
        ready = [i for i in self._pending if float(np.min(q[i])) >= self.min_redundancy]
        if not ready:
            return []
        res = b.snoop(ready, alpha=self.alpha, min_redundancy=self.min_redundancy)
        done = set(ready)
        self._pending = [i for i in self._pending if i not in done]
        self.stats.tested += len(ready)
        self.stats.rejected += len(res.rejected)
        return res.rejected

    def late_rejections(self) -> list[tuple[Hashable, Hashable]]:
        """(frame id, point id) of observations of earlier batches rejected since the last call."""
        out, self._late = self._late, []
        return out
