"""Local hybrid keyframe bundle adjustment (seed 004, eq. 1).

For one feature set i: its M 3-D points (keyframe i's rectified left camera frame) and the
transform ``f_from_kf`` to the final monocular frame (the left image of keyframe i+1)
are refined together from the left and right projections at keyframe i and the final
left projections. Optionally (an extension of eq. 1) the final right projections too, when
the final frame is a stereo keyframe: this anchors the scale at both ends of the set.
Minimal rotation parameters (a left twist on ``f_from_kf``), Huber loss, analytic
Jacobians, the points eliminated by the Schur complement (a 6x6 reduced system).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import se3_exp
from loopmodel.pose.rig import point_cross_rows

F64 = NDArray[np.float64]


@dataclass
class HybridBAResult:
    """Refined ``f_from_kf`` (4x4), points, iterations, RMS errors and inlier flags.

    Points (M, 3, metres, keyframe frame), RMS reprojection error (pixels) before and after, and
    per-point inlier flags.
    """

    f_from_kf: F64
    points_in_kf: F64
    iterations: int
    initial_rms_px: float
    final_rms_px: float
    inliers: NDArray[np.bool_]
    # with estimate_disparity_offset: the right images' column offset (px; measured = projected + offset)
    # and its variance (px^2, the normal equations' inverse times the residual variance per coordinate)
    disparity_offset_px: float = 0.0
    disparity_offset_var_px2: float = float("inf")


def _huber_w(n: F64, k: float) -> F64:
    return np.where(n <= k, 1.0, k / np.maximum(n, 1e-300))


def _huber_rho(n: F64, k: float) -> F64:
    return np.where(n <= k, 0.5 * n * n, k * (n - 0.5 * k))


def _relative_weights(sigma_px: F64 | None) -> F64 | None:
    """(median / sigma)^2 clipped to [1/4, 4]; None stays None."""
    if sigma_px is None or len(sigma_px) == 0:
        return None
    s = np.asarray(sigma_px, dtype=float)
    return np.clip((np.median(s) / np.maximum(s, 1e-9)) ** 2, 0.25, 4.0)


@dataclass
class _Block:
    camera: CentralCamera
    fixed: F64  # camera_from_(kf or final left) transform, 4x4
    moving: bool  # True: the block's camera sees the points through f_from_kf
    is_right: bool  # a right image: its column carries the disparity offset
    uv: F64  # (M, 2) measurements
    valid: F64  # (M,) 1.0 where measured
    weight: F64 | None = None  # (M,) relative weights (inverse variances); None: 1


#: per block: residuals (M, 2), camera-frame points (M, 3), d uv / d point (M, 2, 3), d uv / d parameters
#: (M, 2, n_par) or None
_Eval = list[tuple[F64, F64, F64 | None, F64 | None]]


def _make_blocks(
    own: NDArray[np.int64],
    frames: F64,
    uv_left: F64,
    uv_right: F64,
    uv_final: F64,
    uv_final_right: F64 | None,
    left: CentralCamera,
    right: CentralCamera,
    rfl: F64,
    right_w: F64 | None,
) -> list[_Block]:
    """The measurement blocks: each owner keyframe's left and right images, the final left (and right) image."""
    blocks = []
    for k, own_from in enumerate(frames):
        valid = (own == k).astype(float)
        if valid.any():
            blocks.append(_Block(left, own_from, False, False, np.asarray(uv_left, float), valid))
            blocks.append(_Block(right, rfl @ own_from, False, True, np.asarray(uv_right, float), valid, right_w))
    f_valid = np.all(np.isfinite(uv_final), axis=1).astype(float)
    blocks.append(_Block(left, np.eye(4), True, False, np.where(np.isfinite(uv_final), uv_final, 0.0), f_valid))
    if uv_final_right is not None:
        fr = np.asarray(uv_final_right, dtype=float)
        valid = np.all(np.isfinite(fr), axis=1).astype(float)
        blocks.append(_Block(right, rfl, True, True, np.where(np.isfinite(fr), fr, 0.0), valid))
    return blocks


@dataclass
class _Normal:
    """The normal equations of the points (M, 3) and the parameters (pose twist, [disparity offset])."""

    Hxx: F64
    gx: F64
    Hpx: F64
    Hpp: F64
    gp: F64


class _Problem:
    """Eq. (1) over the blocks: residuals, Jacobians, Huber cost, normal equations and one damped step."""

    def __init__(self, blocks: list[_Block], M: int, n_par: int, huber_px: float) -> None:
        self.blocks, self.M, self.n_par, self.huber_px = blocks, M, n_par, huber_px
        self.valid_all = np.stack([b.valid for b in blocks]) > 0
        self.prior_w = 0.0
        self.prior_mean = 0.0

    def evaluate(self, Xc: F64, Tc: F64, jac: bool, dc: float) -> _Eval:
        """Each block's residuals at points ``Xc``, ``f_from_kf`` ``Tc`` and offset ``dc`` (Jacobians with ``jac``)."""
        pf = Xc @ Tc[:3, :3].T + Tc[:3, 3]
        return [self._block(b, Xc, pf, Tc, jac, dc) for b in self.blocks]

    def _block(
        self, b: _Block, Xc: F64, pf: F64, Tc: F64, jac: bool, dc: float
    ) -> tuple[F64, F64, F64 | None, F64 | None]:
        base = pf if b.moving else Xc
        p = base @ b.fixed[:3, :3].T + b.fixed[:3, 3]
        # rows a block does not measure are projected from a harmless point (no inf, no NaN)
        p = np.where(b.valid[:, None] > 0, p, np.array([0.0, 0.0, 1.0]))
        pr = b.camera.project(p)
        if b.is_right and dc != 0.0:
            pr[:, 0] += dc
        r = (pr - b.uv) * b.valid[:, None]
        if not jac:
            return r, p, None, None
        Jc = b.camera.project_jacobian(p) @ b.fixed[:3, :3]  # d uv / d base point
        JX = Jc @ Tc[:3, :3] if b.moving else Jc
        Jp: F64 | None = None
        offset = b.is_right and self.n_par == 7
        if b.moving or offset:
            Jp = np.zeros((self.M, 2, self.n_par))
            if b.moving:
                Jp[:, :, :6] = np.concatenate([Jc, point_cross_rows(pf, Jc)], axis=2)
            if offset:
                Jp[:, 0, 6] = b.valid
        return r, p, JX, Jp

    @staticmethod
    def norms(ev: _Eval) -> F64:
        """Residual norms (blocks, M), pixels."""
        return np.stack([np.linalg.norm(e[0], axis=1) for e in ev])

    def cost(self, nrm: F64, dc: float) -> float:
        """Huber cost of the residual norms plus the offset prior's."""
        return float(np.sum(_huber_rho(nrm, self.huber_px))) + 0.5 * self.prior_w * (dc - self.prior_mean) ** 2

    def weights(self, nrm: F64) -> F64:
        """Huber weights times validity and relative weights (blocks, M)."""
        return _huber_w(nrm, self.huber_px) * np.stack(
            [b.valid if b.weight is None else b.valid * b.weight for b in self.blocks]
        )

    def normal(self, ev: _Eval, w: F64, delta: float) -> _Normal:
        """The Gauss-Newton normal equations at ``ev`` with weights ``w`` (the offset prior included)."""
        M, n_par = self.M, self.n_par
        ne = _Normal(np.zeros((M, 3, 3)), np.zeros((M, 3)), np.zeros((M, n_par, 3)), np.zeros((n_par, n_par)),
                     np.zeros(n_par))
        for k, (r, _p, JX, Jp) in enumerate(ev):
            assert JX is not None
            wk = w[k]
            JXw = JX * wk[:, None, None]
            ne.Hxx += np.matmul(JXw.transpose(0, 2, 1), JX)
            ne.gx += np.einsum("mki,mk->mi", JXw, r)
            if Jp is not None:
                Jpw = Jp * wk[:, None, None]
                ne.Hpx += np.matmul(Jpw.transpose(0, 2, 1), JX)
                ne.Hpp += np.einsum("mki,mkj->ij", Jpw, Jp)
                ne.gp += np.einsum("mki,mk->i", Jpw, r)
        if self.prior_w > 0:
            ne.Hpp[6, 6] += self.prior_w
            ne.gp[6] += self.prior_w * (delta - self.prior_mean)
        return ne

    def solve(self, ne: _Normal, lam: float) -> tuple[F64, F64] | None:
        """The damped step (parameters, points) by the Schur complement; None when singular."""
        n_par = self.n_par
        Hxx_d = ne.Hxx + lam * (ne.Hxx * np.eye(3)) + 1e-9 * np.eye(3)
        Hpp_d = ne.Hpp + lam * np.diag(np.diag(ne.Hpp)) + 1e-12 * np.eye(n_par)
        Hxx_inv = np.linalg.inv(Hxx_d)
        HpxHi = np.matmul(ne.Hpx, Hxx_inv)  # (M, 6, 3)
        S = Hpp_d - np.einsum("mij,mkj->ik", HpxHi, ne.Hpx)
        b = -ne.gp + np.einsum("mij,mj->i", HpxHi, ne.gx)
        try:
            dp = np.linalg.solve(S, b)
        except np.linalg.LinAlgError:
            return None
        dx = -np.einsum("mij,mj->mi", Hxx_inv, ne.gx + np.einsum("mji,j->mi", ne.Hpx, dp))
        return dp, dx

    def offset_variance(self, X: F64, T: F64, nrm: F64, delta: float, sigma2: float) -> float:
        """The offset's variance: the reduced system at the solution (Huber weights), times ``sigma2``."""
        ne = self.normal(self.evaluate(X, T, True, delta), self.weights(nrm), delta)
        if self.prior_w < 0:  # normal() adds only a positive prior; the information has it whatever its sign
            ne.Hpp[6, 6] += self.prior_w
        HpxHi = np.matmul(ne.Hpx, np.linalg.inv(ne.Hxx + 1e-9 * np.eye(3)))
        S = ne.Hpp - np.einsum("mij,mkj->ik", HpxHi, ne.Hpx)
        try:
            return float(np.linalg.inv(S)[6, 6]) * sigma2
        except np.linalg.LinAlgError:
            return float("inf")


@dataclass
class _State:
    """The current solution: points, ``f_from_kf``, residual norms, offset, cost, damping."""

    X: F64
    T: F64
    nrm: F64
    delta: float
    cost: float
    lam: float = 1e-3


def _lm_iteration(pb: _Problem, st: _State, ev: _Eval) -> tuple[bool, bool]:
    """One Levenberg-Marquardt iteration from ``ev`` (at ``st``); returns (improved, converged)."""
    ne = pb.normal(ev, pb.weights(st.nrm), st.delta)
    for _ in range(6):
        step = pb.solve(ne, st.lam)
        if step is None:
            st.lam *= 10
            continue
        dp, dx = step
        T_new = se3_exp(dp[:6]) @ st.T
        X_new = st.X + dx
        d_new = st.delta + (float(dp[6]) if pb.n_par == 7 else 0.0)
        ev_new = pb.evaluate(X_new, T_new, False, d_new)
        nrm_new = pb.norms(ev_new)
        in_front = all(np.all(e[1][:, 2] > 0) for e in ev_new)
        c_new = pb.cost(nrm_new, d_new)
        if in_front and c_new < st.cost:
            converged = st.cost - c_new < 1e-4 * st.cost
            st.X, st.T, st.nrm, st.delta, st.cost = X_new, T_new, nrm_new, d_new, c_new
            st.lam = max(st.lam * 0.3, 1e-9)
            return True, converged
        st.lam *= 10.0
    return False, False


class _Compiled:
    """The blocks of a :class:`_Problem` as arrays for :mod:`loopmodel.frontend._ba_kernels` (fe11)."""

    def __init__(self, pb: _Problem) -> None:
        b = pb.blocks
        self.pb = pb
        self.fixed = np.ascontiguousarray(np.stack([k.fixed for k in b]), dtype=float)
        self.moving = np.array([k.moving for k in b])
        self.is_right = np.array([k.is_right for k in b])
        self.uv = np.ascontiguousarray(np.stack([k.uv for k in b]), dtype=float)
        self.valid = np.ascontiguousarray(np.stack([k.valid for k in b]), dtype=float)
        self.weight = np.ascontiguousarray(np.stack([k.valid if k.weight is None else k.valid * k.weight for k in b]))
        self.cams = np.array([[k.camera.px, k.camera.py, k.camera.u0, k.camera.v0, k.camera.xi] for k in b], float)

    def norms(self, X: F64, T: F64) -> F64:
        """:meth:`_Problem.norms` of the evaluation at (X, T), offset 0."""
        from loopmodel.frontend._ba_kernels import initial  # numba: imported when first needed

        return np.asarray(initial(X, T, self.fixed, self.moving, self.is_right, self.uv, self.valid, self.cams,
                                  self.pb.n_par))

    def lm(self, X: F64, T: F64, iterations: int) -> tuple[F64, F64, float, F64, int]:
        """:func:`_lm_iteration` repeated as :func:`hybrid_keyframe_ba` does: (X, T, offset, norms, iterations)."""
        from loopmodel.frontend._ba_kernels import lm

        pb = self.pb
        Xo, To, delta, nrm, it = lm(
            X, T, self.fixed, self.moving, self.is_right, self.uv, self.valid, self.weight, self.cams, pb.n_par,
            float(pb.huber_px), int(iterations), float(pb.prior_w), float(pb.prior_mean),
        )
        return Xo, To, float(delta), nrm, int(it)

    def offset_variance(self, X: F64, T: F64, nrm: F64, delta: float, sigma2: float) -> float:
        """:meth:`_Problem.offset_variance`."""
        from loopmodel.frontend._ba_kernels import offset_variance

        pb = self.pb
        return float(offset_variance(
            X, T, self.fixed, self.moving, self.is_right, self.uv, self.valid, self.weight, self.cams,
            float(pb.huber_px), float(pb.prior_w), float(pb.prior_mean), float(delta), nrm, float(sigma2),
        ))


def hybrid_keyframe_ba(
    points_in_kf: F64,
    uv_left: F64,
    uv_right: F64,
    uv_final: F64,
    f_from_kf: F64,
    left: CentralCamera,
    right: CentralCamera,
    right_from_left: F64,
    iterations: int = 10,
    huber_px: float = 1.0,
    uv_final_right: F64 | None = None,
    right_sigma_px: F64 | None = None,
    estimate_disparity_offset: bool = False,
    offset_prior: tuple[float, float] = (0.0, 0.0),
    owner: NDArray[np.int64] | None = None,
    own_from_kf: F64 | None = None,
    compiled: bool = True,
) -> HybridBAResult:
    """Minimise eq. (1) of seed 004 over the points and ``f_from_kf``.

    All pixels are undistorted (rectified) coordinates. ``uv_final_right`` (M, 2; NaN rows where
    unmatched) adds the final right projections. ``right_sigma_px`` (M,): each point's disparity
    standard deviation (px, from its stereo match): its keyframe right projection is weighted by
    (median / own)^2, clipped to [1/4, 4], so a doubtful match counts less (issue 36).
    ``estimate_disparity_offset`` adds one unknown: a column offset of every right projection (a
    disparity offset, e.g. from an error in the right camera's principal point), observable from
    the motion parallax of points at different depths (issue 36); ``offset_prior`` = (mean px,
    information 1/px^2) is a Gaussian prior on it, and the result's variance is the posterior's.
    A wider window (issue 36, item 4): ``owner`` (M,) names the keyframe whose stereo pair
    measured each point's ``uv_left``/``uv_right``, and ``own_from_kf`` (K, 4, 4) those keyframes'
    left cameras from keyframe i's (held fixed; owner 0 is keyframe i itself, identity);
    ``uv_final`` may then have NaN rows (not seen at the end). ``compiled``: the Levenberg-Marquardt
    loop in :mod:`loopmodel.frontend._ba_kernels` (False: numpy, the same steps; sums in another order).
    """
    X = np.asarray(points_in_kf, dtype=float).copy()
    M = X.shape[0]
    own = np.zeros(M, np.int64) if owner is None else np.asarray(owner, np.int64)
    frames = np.eye(4)[None] if own_from_kf is None else np.asarray(own_from_kf, float).reshape(-1, 4, 4)
    blocks = _make_blocks(
        own, frames, uv_left, uv_right, np.asarray(uv_final, float), uv_final_right, left, right,
        np.asarray(right_from_left, dtype=float), _relative_weights(right_sigma_px),
    )
    n_par = 7 if estimate_disparity_offset else 6
    pb = _Problem(blocks, M, n_par, huber_px)
    T = np.asarray(f_from_kf, dtype=float).copy()
    # fe11: compiled, the same loop in one call (4.5 -> ~0.5 ms a KITTI keyframe's BA)
    comp = _Compiled(pb) if compiled else None
    ev = pb.evaluate(X, T, True, 0.0) if comp is None else []
    nrm = pb.norms(ev) if comp is None else comp.norms(X, T)
    init_rms = float(np.sqrt(np.mean(nrm[pb.valid_all] ** 2)))
    # the prior in the cost's units (pixels^2): scaled by the residual variance per coordinate, from
    # the starting residuals (conservative: they carry the tracked pose's error too); the posterior
    # variance uses the same scale
    pb.prior_mean, prior_info = offset_prior
    dof = max(int(pb.valid_all.sum()) * 2 - 3 * M - n_par, 1)
    sigma2 = max(float(np.sum(nrm**2)) / dof, 0.01)
    pb.prior_w = prior_info * sigma2 if n_par == 7 else 0.0
    st = _State(X, T, nrm, 0.0, pb.cost(nrm, 0.0))
    it = 0
    if comp is not None:
        st.X, st.T, st.delta, st.nrm, it = comp.lm(X, T, iterations)
    else:
        for it in range(1, iterations + 1):  # noqa: B007 (it is reported)
            improved, converged = _lm_iteration(pb, st, ev)
            if not improved or converged:
                break
            ev = pb.evaluate(st.X, st.T, True, st.delta)
    inliers = np.all((st.nrm < 3.0 * huber_px) | ~pb.valid_all, axis=0)
    final_rms = float(np.sqrt(np.mean(st.nrm[pb.valid_all] ** 2)))
    var = float("inf")
    if n_par == 7:
        var = (pb if comp is None else comp).offset_variance(st.X, st.T, st.nrm, st.delta, sigma2)
    return HybridBAResult(st.T, st.X, it, init_rms, final_rms, inliers, st.delta, var)
