"""The project's robust pose solver: pose of an N-camera central rig from feature terms.

Levenberg–Marquardt on SE(3) with IRLS M-estimation (Tukey with a MAD scale, or Huber),
analytic Jacobians, left perturbations ``rig_from_ref <- exp(delta) rig_from_ref`` with
``delta = (v, w)`` (metres, radians). :func:`estimate_pose` adds a RANSAC start
(P3P/AP3P) when no initial pose is given or the given one is poor.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import EstimationError
from loopmodel.geometry.se3 import nearest_rigid, se3_exp
from loopmodel.pose._point_kernels import refine_points, weighted_cost, weighted_normal_equations
from loopmodel.pose.rig import F64, PointTerm, PoseTerm
from loopmodel.pose.robust import Loss, default_cutoff, rho, robust_scale, weights


@dataclass
class PoseOptions:
    """Settings of the robust refinement (scales in the terms' units, pixels for points)."""

    loss: Loss = "tukey"
    cutoff: float | None = None  # tuning constant in units of sigma (Tukey 4.685, Huber 1.345)
    min_scale: float = 0.5  # floor of the MAD scale (pixels)
    fixed_scale: float | None = None  # use this sigma instead of the MAD estimate
    max_iterations: int = 15
    lm_lambda0: float = 1e-4
    step_tolerance: float = 1e-6  # stop when |delta| (m, rad) is below
    huber_warmup: int = 2  # first IRLS iterations use Huber (Tukey needs a start near the basin)
    inlier_cutoff: float = 4.6851  # inlier: residual norm below this many sigma
    reweight_iterations: int = 4  # IRLS weight updates; then the weights are frozen


@dataclass
class PoseResult:
    """Estimated ``rig_from_ref`` (4x4) with weights, inlier flags, scales and covariance.

    Per-feature weights and inlier flags (one list entry per term), the final scale(s), and the 6x6
    covariance of a left twist (v, w).
    """

    rig_from_ref: F64
    inliers: list[NDArray[np.bool_]]
    weights: list[F64]
    residual_norms: list[F64]
    scales: list[float]
    covariance: F64
    cost: float
    iterations: int
    converged: bool
    used_ransac: bool = False
    ransac_inliers: int = 0
    info: dict[str, float] = field(default_factory=dict)

    @property
    def num_inliers(self) -> int:
        """Inlier count over all terms."""
        return int(sum(int(m.sum()) for m in self.inliers))


def _as_terms(terms: PoseTerm | Sequence[PoseTerm]) -> list[PoseTerm]:
    if isinstance(terms, Sequence):
        return list(terms)
    return [terms]


def _irls_weights(term: PoseTerm, r: F64, it: int, opt: PoseOptions, c: float, scales: list[float], k: int) -> F64:
    """IRLS weights of term ``k``'s residuals ``r`` in iteration ``it`` (updates its scale ``scales[k]``).

    Huber during the warm-up of a Tukey loss; the MAD scale re-estimated during the warm-up and
    frozen after the first Tukey iteration; times the term's ``prior_weight`` when it has one.
    """
    loss: Loss = "huber" if (opt.loss == "tukey" and it <= opt.huber_warmup) else opt.loss
    cc = default_cutoff("huber") if loss != opt.loss else c
    n = np.linalg.norm(r, axis=1)
    if it <= opt.huber_warmup + 1 or opt.loss != "tukey":
        scales[k] = opt.fixed_scale or robust_scale(n, term.dim, opt.min_scale)
    w = weights(n / scales[k], loss, cc)
    pw = getattr(term, "prior_weight", None)
    return w if pw is None else w * pw


def _weighted_cost(rs: list[F64], ws: list[F64]) -> float:
    """``sum w |r|^2`` over the terms (residuals (n, dim) or (n,), weights (n,))."""
    return float(sum(weighted_cost(r.reshape(w.shape[0], -1), w) for r, w in zip(rs, ws, strict=True)))


def _normal_equations(J: F64, r: F64, w: F64) -> tuple[F64, F64]:
    """``(J^T W J, J^T W r)`` (6x6, 6) of one term: Jacobian (n, dim, 6) or (n * dim, 6), per-feature weights ``w``.

    One compiled pass (issue 33: the numpy form, a repeat, a product and two matrix products, was
    most of the pose solve's time at a few hundred points).
    """
    n = w.shape[0]
    return weighted_normal_equations(  # type: ignore[no-any-return]
        np.ascontiguousarray(J).reshape(n, -1, 6), np.ascontiguousarray(r).reshape(n, -1),
        np.ascontiguousarray(w, dtype=np.float64),
    )


def _lm_step(
    tlist: list[PoseTerm], wlist: list[F64], rs: list[F64], H: F64, g: F64, T: F64, lam: float
) -> tuple[F64, float, bool, F64]:
    """One Levenberg-Marquardt step of the weighted problem (weights ``wlist``, residuals ``rs`` at ``T``).

    Up to 8 damping increases; returns the pose (moved when the weighted cost did not grow), the
    damping, whether the step was taken and the last twist tried.
    """
    cost = _weighted_cost(rs, wlist)
    delta = np.zeros(6)
    for _ in range(8):
        Hd = H + lam * np.diag(np.maximum(np.diag(H), 1e-9))
        try:
            delta = np.asarray(-np.linalg.solve(Hd, g), dtype=np.float64)
        except np.linalg.LinAlgError:
            lam *= 10.0
            continue
        T_new = se3_exp(delta) @ T
        if _weighted_cost([t.residuals(T_new) for t in tlist], wlist) <= cost:
            return T_new, max(lam * 0.3, 1e-9), True, delta
        lam *= 10.0
    return T, lam, False, delta


def _one_camera_points(tlist: list[PoseTerm]) -> tuple | None:  # type: ignore[type-arg]
    """:func:`refine_points`'s arrays when every term is a :class:`PointTerm` of the same rig's first camera."""
    if not tlist or not all(isinstance(t, PointTerm) and t._single and t.dim == 2 for t in tlist):
        return None
    pts = [t for t in tlist if isinstance(t, PointTerm)]
    rig = pts[0].rig
    if any(t.rig is not rig for t in pts):
        return None
    C, cam = rig.cam_from_rig[0], rig.cameras[0]
    return (
        np.ascontiguousarray(np.vstack([t.p_in_ref for t in pts]), dtype=np.float64),
        np.concatenate([np.ones(len(t)) if t.inverse_depth_per_m is None else t.inverse_depth_per_m for t in pts]),
        np.ascontiguousarray(np.vstack([t.uv_px for t in pts]), dtype=np.float64),
        np.concatenate([np.ones(len(t)) if t.prior_weight is None else t.prior_weight for t in pts]).astype(np.float64),
        np.cumsum([0] + [len(t) for t in pts]).astype(np.int64),
    ), (np.ascontiguousarray(C[:3, :3], dtype=np.float64), np.ascontiguousarray(C[:3, 3], dtype=np.float64),
        float(cam.px), float(cam.py), float(cam.u0), float(cam.v0), float(cam.xi))


def _irls_loop(
    tlist: list[PoseTerm], T: F64, opt: PoseOptions, c: float, lam: float
) -> tuple[F64, list[float], int, bool]:
    """:func:`refine_pose`'s IRLS / Levenberg-Marquardt iterations from ``T``.

    The pose, each term's scale, the iterations and whether it converged (``refine_points`` is this
    loop compiled, for point terms of one camera).
    """
    converged = False
    it = 0
    scales = [opt.min_scale] * len(tlist)
    wlist: list[F64] = [np.ones(len(t)) for t in tlist]
    for it in range(1, opt.max_iterations + 1):
        reweight = it <= opt.reweight_iterations
        H = np.zeros((6, 6))
        g = np.zeros(6)
        rs: list[F64] = []
        for k, term in enumerate(tlist):
            r, J = term.residuals_and_jacobian(T)
            if reweight:
                wlist[k] = _irls_weights(term, r, it, opt, c, scales, k)
            Hk, gk = _normal_equations(J, r, wlist[k])
            H += Hk
            g += gk
            rs.append(r)
        # IRLS: each step solves the weighted least-squares problem of the current weights;
        # after ``reweight_iterations`` the weights are frozen and Gauss-Newton converges
        # quadratically on that problem
        T, lam, accepted, delta = _lm_step(tlist, wlist, rs, H, g, T, lam)
        small = float(np.linalg.norm(delta)) < opt.step_tolerance
        if (not accepted or small) and it >= min(opt.reweight_iterations, opt.max_iterations):
            converged = True
            break
    return T, scales, it, converged


def refine_pose(
    terms: PoseTerm | Sequence[PoseTerm],
    rig_from_ref_init: F64,
    options: PoseOptions | None = None,
) -> PoseResult:
    """Robust LM refinement of ``rig_from_ref`` (4x4, metres) from an initial pose."""
    opt = options or PoseOptions()
    tlist = _as_terms(terms)
    total = sum(len(t) for t in tlist)
    if total < 3:
        raise EstimationError(f"pose needs at least 3 features, got {total}")
    c = opt.cutoff if opt.cutoff is not None else default_cutoff(opt.loss)
    T = nearest_rigid(np.asarray(rig_from_ref_init, dtype=float))
    lam = opt.lm_lambda0
    points = _one_camera_points(tlist)
    if points is not None:  # the loop of _irls_loop, compiled (issues 33/36: ~1 ms of Python a KITTI frame)
        (P, rho_, uv, pw, start), cam = points
        loss_code = {"l2": 0, "huber": 1, "tukey": 2}[opt.loss]
        T, sc, it, converged = refine_points(  # type: ignore[call-arg]
            P, rho_, uv, pw, start, T, *cam, loss_code, float(c), float(default_cutoff("huber")),
            float(opt.min_scale), float(opt.fixed_scale or 0.0), opt.max_iterations, float(lam),
            float(opt.step_tolerance), opt.huber_warmup, opt.reweight_iterations,
        )
        scales = [float(x) for x in sc]
    else:
        T, scales, it, converged = _irls_loop(tlist, T, opt, c, lam)

    # final weights, inliers and covariance at the solution
    H = np.zeros((6, 6))
    inl, wts, norms = [], [], []
    cost = 0.0
    for k, term in enumerate(tlist):
        r, J = term.residuals_and_jacobian(T)
        n = np.linalg.norm(r, axis=1)
        s = scales[k]
        w = weights(n / s, opt.loss, c)
        pw = getattr(term, "prior_weight", None)
        if pw is not None:
            w = w * pw
        H += _normal_equations(J, r, w)[0] / (s * s)
        cost += float(np.sum(rho(n / s, opt.loss, c)) * s * s)
        inl.append(n < opt.inlier_cutoff * s)
        wts.append(w)
        norms.append(n)
    try:
        cov = np.asarray(np.linalg.inv(H), dtype=np.float64)
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.inf)
    return PoseResult(T, inl, wts, norms, list(scales), cov, cost, it, converged)


def estimate_pose(
    term: PointTerm,
    rig_from_ref_init: F64 | None = None,
    options: PoseOptions | None = None,
    ransac_threshold_px: float = 2.0,
    prediction_gate_px: float = 3.0,
    min_predicted_fraction: float = 0.5,
    ransac_iterations: int = 200,
    seed: int = 0,
    extra_terms: Sequence[PoseTerm] = (),
) -> PoseResult:
    """Robust pose from point correspondences (plus optional other terms).

    With ``rig_from_ref_init`` given and at least ``min_predicted_fraction`` of the points
    reprojecting within ``prediction_gate_px`` of their measurement, the initial pose is
    refined directly; otherwise a P3P RANSAC gives the start.
    """
    from loopmodel.pose.ransac import ransac_pose

    start = None
    if rig_from_ref_init is not None and len(term) >= 3:
        n = np.linalg.norm(term.residuals(rig_from_ref_init), axis=1)
        ok = np.isfinite(n) & (term.depths(rig_from_ref_init) > 0)
        if np.mean(ok & (n < prediction_gate_px)) >= min_predicted_fraction:
            start = rig_from_ref_init
    used_ransac = False
    n_ransac = 0
    if start is None:
        hyp = ransac_pose(term, ransac_threshold_px, ransac_iterations, seed=seed)
        if hyp is None:
            raise EstimationError("RANSAC found no pose hypothesis")
        start, inl = hyp
        used_ransac = True
        n_ransac = int(inl.sum())
        if rig_from_ref_init is None or n_ransac >= 3:
            # refine on the RANSAC inliers first so Tukey starts in the right basin
            pre = refine_pose(term.subset(inl), start, options)
            start = pre.rig_from_ref
    res = refine_pose([term, *extra_terms], start, options)
    res.used_ransac = used_ransac
    res.ransac_inliers = n_ransac
    return res
