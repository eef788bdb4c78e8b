"""Virtual visual servoing (VVS, seed 002) for N-camera central rigs.

Features, interaction matrices and the stacked robust control law of Caron, Marchand and
Mouaddib, plugged into the shared pose core (:mod:`loopmodel.pose.rig`: terms that return
residuals and Jacobians; :mod:`loopmodel.pose.robust`: M-estimators).

Sign conventions (tested in ``tests/test_vvs.py``):

* ``rig_from_ref`` is the paper's ``1Mo`` (reference/object frame -> rig frame, which is
  camera 1 when ``cam_from_rig[0]`` is the identity). ``cam_from_rig[j]`` is ``jM1``.
* ``v = (upsilon, omega)`` is the velocity of the (virtual) rig frame, expressed in the
  rig frame (metres/s, rad/s, translation first). A static point then moves in the rig
  frame as ``dX/dt = -upsilon - omega x X``.
* Interaction matrices ``L`` give ``ds/dt = L v`` for that velocity (ViSP convention).
* Camera j moves with ``v_j = jV1 v`` where ``jV1 = [[R, [t]x R], [0, R]]`` for
  ``jM1 = (R, t)`` (eq. 10-11).
* Control law (eq. 14): ``v = -lambda (D L)^+ D e`` with ``e = s(r) - s*``; the pose update
  (eq. 15) moves the virtual camera by ``exp(v)``: ``ref_from_rig <- ref_from_rig exp(v)``,
  i.e. ``rig_from_ref <- exp(-v) rig_from_ref``.
* The shared solver's terms differentiate w.r.t. a left perturbation
  ``rig_from_ref <- exp(delta) rig_from_ref``; hence ``delta = -v`` and ``J = -L``, and with
  ``lambda = 1`` and ``D = diag(sqrt(w))`` the VVS step is exactly the IRLS Gauss-Newton step
  on SE(3). (The paper writes ``D = diag(w)``; ``VvsOptions.weighting = "paper"`` uses that.)
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from loopmodel.errors import EstimationError
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import cross_rows, hat, se3_exp
from loopmodel.pose.rig import F64, CameraRig, PoseTerm
from loopmodel.pose.robust import Loss, default_cutoff, mad_scale, rho, robust_scale, weights
from loopmodel.pose.solver import PoseResult

# --------------------------------------------------------------------------- matrices


def twist_transform(b_from_a: ArrayLike) -> F64:
    """6x6 velocity twist transform ``bVa = [[R, [t]x R], [0, R]]`` of ``b_from_a`` (eq. 11).

    Maps a velocity ``(upsilon, omega)`` of frame a, expressed in a, to frame b.
    """
    T = np.asarray(b_from_a, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    V = np.zeros((6, 6))
    V[:3, :3] = R
    V[:3, 3:] = hat(t) @ R
    V[3:, 3:] = R
    return V


def point_interaction_matrix(p_in_cam: ArrayLike, xi: float) -> F64:
    """(N, 2, 6) interaction matrix of the normalised unified-model coordinates of static points.

    Coordinates ``x = X / (Z + xi rho)`` of static points ``p_in_cam`` (N x 3, metres, camera frame)
    for the camera velocity ``(upsilon, omega)``. For ``xi = 0`` it is the classical
    ``[[-1/Z, 0, x/Z, xy, -(1+x^2), y], [0, -1/Z, y/Z, 1+y^2, -xy, -x]]``.
    """
    P = np.asarray(p_in_cam, dtype=float).reshape(-1, 3)
    X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
    rho_ = np.linalg.norm(P, axis=1)
    d = Z + xi * rho_
    x, y = X / d, Y / d
    # derivative of the normalised coordinates w.r.t. the point: dx/dP = (e_x - x grad d) / d
    inv_rho = 1.0 / np.where(rho_ > 0, rho_, 1.0)
    gd = np.column_stack([xi * X * inv_rho, xi * Y * inv_rho, 1.0 + xi * Z * inv_rho])
    Jx = -x[:, None] * gd
    Jx[:, 0] += 1.0
    Jy = -y[:, None] * gd
    Jy[:, 1] += 1.0
    Jx /= d[:, None]
    Jy /= d[:, None]
    # dP/dt = -upsilon + [P]x omega  ->  L = dx/dP [-I, [P]x];  a^T [P]x = (a x P)^T
    L = np.empty((P.shape[0], 2, 6))
    L[:, 0, :3] = -Jx
    L[:, 1, :3] = -Jy
    L[:, 0, 3:] = np.cross(Jx, P)
    L[:, 1, 3:] = np.cross(Jy, P)
    return L


def pixel_point_interaction_matrix(camera: CentralCamera, p_in_cam: ArrayLike) -> F64:
    """(N, 2, 6) interaction matrix of the pixel coordinates.

    ``diag(px, py)`` times the normalised one.
    """
    L = point_interaction_matrix(p_in_cam, camera.xi)
    L[:, 0] *= camera.px
    L[:, 1] *= camera.py
    return L


@dataclass
class LineConics:
    """Projection of 3-D lines in one camera (arrays over lines).

    Conic coefficients ``a = (a0..a4)`` of eq. 20-21 and their interaction matrices ``L_a`` (eq.
    22), plus the two planes (P1 through the sphere centre, P2 orthogonal to it: ``N2 . X + D2 =
    0``).
    """

    a: F64  # (M, 5)
    L_a: F64  # (M, 5, 6)
    n1: F64  # (M, 3) unit normal of P1
    n2: F64  # (M, 3) unit normal of P2
    d2: F64  # (M,)
    valid: NDArray[np.bool_]  # (M,) C1 not ~0 and the line does not pass through the centre


def line_conics(
    p0_in_cam: ArrayLike, p1_in_cam: ArrayLike, xi: float | ArrayLike
) -> LineConics:
    """Conics (normalised image coordinates) of 3-D lines through ``p0`` and ``p1``.

    ``p0``, ``p1``: M x 3, metres, camera frame; on the unified model with parameter ``xi`` (scalar
    or per line).

    ``Q(x, y) = a0 x^2 + a1 y^2 + 2 a2 xy + 2 a3 x + 2 a4 y + 1`` with ``a3 = A1/C1``,
    ``a4 = B1/C1``, ``a0 = (1-xi^2) a3^2 - xi^2``, ``a1 = (1-xi^2) a4^2 - xi^2``,
    ``a2 = (1-xi^2) a3 a4``. Interaction (camera velocity convention of this module)::

        L_a3 = [-alpha a3, -alpha a4, -alpha, a3 a4, -(1 + a3^2), a4]
        L_a4 = [-beta a3, -beta a4, -beta, 1 + a4^2, -a3 a4, -a3]

    with ``alpha = (A2 - a3 C2) / D2``, ``beta = (B2 - a4 C2) / D2``, and ``L_a0..L_a2`` by
    the chain rule. (The paper's eq. 22 has ``+alpha``/``+beta`` with the opposite sign of
    ``D2``.)
    """
    P0 = np.asarray(p0_in_cam, dtype=float).reshape(-1, 3)
    P1 = np.asarray(p1_in_cam, dtype=float).reshape(-1, 3)
    n1 = cross_rows(P0, P1)
    nn = np.sqrt(np.einsum("ij,ij->i", n1, n1))
    dirn = P1 - P0
    dirn /= np.sqrt(np.einsum("ij,ij->i", dirn, dirn))[:, None]
    n1 /= np.where(nn > 0, nn, 1.0)[:, None]
    n2 = cross_rows(n1, dirn)
    n2 /= np.maximum(np.sqrt(np.einsum("ij,ij->i", n2, n2)), 1e-300)[:, None]
    d2 = -np.einsum("ij,ij->i", n2, P0)
    A1, B1, C1 = n1[:, 0], n1[:, 1], n1[:, 2]
    valid = (np.abs(C1) > 1e-6) & (nn > 1e-12) & (np.abs(d2) > 1e-9)
    C1s = np.where(valid, C1, 1.0)
    d2s = np.where(valid, d2, 1.0)
    a3, a4 = A1 / C1s, B1 / C1s
    xi2 = np.asarray(xi, dtype=float) ** 2
    k = 1.0 - xi2
    M = P0.shape[0]
    a = np.empty((M, 5))
    a[:, 0] = k * a3 * a3 - xi2
    a[:, 1] = k * a4 * a4 - xi2
    a[:, 2] = k * a3 * a4
    a[:, 3] = a3
    a[:, 4] = a4
    alpha = (n2[:, 0] - a3 * n2[:, 2]) / d2s
    beta = (n2[:, 1] - a4 * n2[:, 2]) / d2s
    L = np.empty((M, 5, 6))
    L3, L4 = L[:, 3], L[:, 4]
    L3[:, 0], L3[:, 1], L3[:, 2] = -alpha * a3, -alpha * a4, -alpha
    L3[:, 3], L3[:, 4], L3[:, 5] = a3 * a4, -(1.0 + a3 * a3), a4
    L4[:, 0], L4[:, 1], L4[:, 2] = -beta * a3, -beta * a4, -beta
    L4[:, 3], L4[:, 4], L4[:, 5] = 1.0 + a4 * a4, -a3 * a4, -a3
    k2 = np.broadcast_to(k, (M,))[:, None]
    L[:, 0] = (2.0 * a3)[:, None] * k2 * L3
    L[:, 1] = (2.0 * a4)[:, None] * k2 * L4
    L[:, 2] = k2 * (a3[:, None] * L4 + a4[:, None] * L3)
    return LineConics(a, L, n1, n2, d2, valid)


def conic_value(a: F64, xy: F64) -> F64:
    """Algebraic distance ``Q(x, y)`` (eq. 20/23) of points ``xy`` (K x 2) to conics ``a``.

    ``a``: K x 5, one per point.
    """
    x, y = xy[:, 0], xy[:, 1]
    return (
        a[:, 0] * x * x + a[:, 1] * y * y + 2 * a[:, 2] * x * y + 2 * a[:, 3] * x
        + 2 * a[:, 4] * y + 1.0
    )


def conic_gradient(a: F64, xy: F64) -> F64:
    """(K, 2) gradient of ``Q`` (eq. 29): the conic normal direction at ``xy``."""
    x, y = xy[:, 0], xy[:, 1]
    return np.column_stack(
        [2 * a[:, 0] * x + 2 * a[:, 2] * y + 2 * a[:, 3], 2 * a[:, 1] * y + 2 * a[:, 2] * x + 2 * a[:, 4]]
    )


def distance_interaction_matrix(a: F64, L_a: F64, xy: F64) -> F64:
    """(K, 6) interaction matrix of the point-to-conic algebraic distance (eq. 25)."""
    x, y = xy[:, 0], xy[:, 1]
    c = np.column_stack([x * x, y * y, 2 * x * y, 2 * x, 2 * y])
    return np.einsum("kc,kcd->kd", c, L_a)


def conic_matrix(a: ArrayLike) -> F64:
    """3x3 symmetric matrix of a conic (eq. 26)."""
    a0, a1, a2, a3, a4 = np.asarray(a, dtype=float).ravel()
    return np.array([[a0, a2, a3], [a2, a1, a4], [a3, a4, 1.0]])


def sample_conic_arc(
    a: ArrayLike, xy_start: ArrayLike, xy_end: ArrayLike, xy_mid: ArrayLike, n: int
) -> F64 | None:
    """``n`` points (n x 2, normalised coordinates) along the arc of an elliptic conic.

    Regularly spaced in the circle parameter along the arc from ``xy_start`` to ``xy_end`` through
    ``xy_mid`` (eq. 26-28: ``C = R S R^T``, ``T = |S|^(1/2) R^T`` maps the conic onto the unit
    circle). None when the conic is not an ellipse (the caller then samples the 3-D segment).
    """
    C = conic_matrix(a)
    w, R = np.linalg.eigh(C)
    signs = np.sign(w)
    if np.any(w == 0) or abs(signs.sum()) != 1:
        return None
    odd = int(np.flatnonzero(signs != np.sign(signs.sum()))[0])
    order = [i for i in range(3) if i != odd] + [odd]
    T = (np.sqrt(np.abs(w[order]))[:, None]) * R[:, order].T

    def angle(p: ArrayLike) -> float:
        q = T @ np.array([*np.asarray(p, dtype=float).ravel()[:2], 1.0])
        return float(np.arctan2(q[1] / q[2], q[0] / q[2]))

    t0, t1, tm = angle(xy_start), angle(xy_end), angle(xy_mid)
    span = (t1 - t0) % (2 * np.pi)
    if (tm - t0) % (2 * np.pi) > span:  # the arc through the midpoint goes the other way
        span -= 2 * np.pi
    t = t0 + span * np.linspace(0.0, 1.0, n)
    Y = np.column_stack([np.cos(t), np.sin(t), np.ones(n)])
    Xh = np.linalg.solve(T, Y.T).T
    return Xh[:, :2] / Xh[:, 2:3]


# --------------------------------------------------------------------------- line term


@dataclass
class LineTerm:
    """Point-to-conic features (eq. 17-25).

    Edge points ``uv_px`` (K x 2, pixels) seen by camera ``cam_index`` and matched to model line
    ``line_index``; the model lines are segments ``lines_in_ref`` (M x 2 x 3, metres, reference
    frame). Residual = algebraic distance ``Q(x, y)`` of the normalised edge point to the projected
    conic (dimensionless, ``s* = 0``); Jacobian w.r.t. a left twist of ``rig_from_ref`` (``J = -L_da
    jV1``).

    ``distance = "normalized"`` divides ``Q`` by ``|grad Q| / px`` at the edge point (first-
    order geometric distance in pixels, exact Jacobian): the same zero set, but every line
    gets the same metric, whereas the
    algebraic distance grows with the conic's coefficients (lines whose interpretation plane
    nearly contains the optical axis dominate and Gauss-Newton converges poorly).
    """

    rig: CameraRig
    lines_in_ref: F64
    uv_px: F64
    line_index: NDArray[np.int64]
    cam_index: NDArray[np.int64]
    distance: Literal["algebraic", "normalized"] = "normalized"
    dim: int = 1
    min_scale: float | None = None  # MAD-scale floor; None: 1e-4 (algebraic) or 0.3 px
    xy: F64 = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.lines_in_ref = np.asarray(self.lines_in_ref, dtype=float).reshape(-1, 2, 3)
        self.uv_px = np.asarray(self.uv_px, dtype=float).reshape(-1, 2)
        self.line_index = np.asarray(self.line_index, dtype=np.int64).ravel()
        self.cam_index = np.asarray(self.cam_index, dtype=np.int64).ravel()
        k = self.uv_px.shape[0]
        if self.min_scale is None:
            self.min_scale = 1e-4 if self.distance == "algebraic" else 0.3
        if self.line_index.shape[0] != k or self.cam_index.shape[0] != k:
            raise ValueError("line_index and cam_index need one entry per edge point")
        cams = self.rig.cameras
        ci = self.cam_index
        f = np.array([[c.px, c.py] for c in cams]).reshape(-1, 2)
        c0 = np.array([[c.u0, c.v0] for c in cams]).reshape(-1, 2)
        self.xy = (self.uv_px - c0[ci]) / f[ci]
        self._px = f[ci, 0]
        # the (camera, line) pairs that are observed, and each point's pair
        n_lines = self.lines_in_ref.shape[0]
        pairs, self._pair = np.unique(ci * n_lines + self.line_index, return_inverse=True)
        self._pair_cam = pairs // n_lines
        self._pair_line = pairs % n_lines
        self._pair_xi = np.array([c.xi for c in cams])[self._pair_cam]
        E = np.stack(self.rig.cam_from_rig)
        self._R = E[self._pair_cam, :3, :3]
        self._t = E[self._pair_cam, :3, 3]
        self._Vp = np.stack([twist_transform(T) for T in self.rig.cam_from_rig])[self._pair_cam]

    def __len__(self) -> int:
        return int(self.uv_px.shape[0])

    def _pair_conics(self, rig_from_ref: F64) -> LineConics:
        ends = self.lines_in_ref[self._pair_line] @ rig_from_ref[:3, :3].T + rig_from_ref[:3, 3]
        ends = np.einsum("pij,pej->pei", self._R, ends) + self._t[:, None, :]
        return line_conics(ends[:, 0], ends[:, 1], self._pair_xi)

    def residuals(self, rig_from_ref: F64) -> F64:
        lc = self._pair_conics(rig_from_ref)
        a = lc.a[self._pair]
        q = conic_value(a, self.xy)
        if self.distance == "normalized":
            g = conic_gradient(a, self.xy)
            q = self._px * q / np.maximum(np.sqrt(np.einsum("ij,ij->i", g, g)), 1e-12)
        return np.where(lc.valid[self._pair], q, 0.0)[:, None]

    def residuals_and_jacobian(self, rig_from_ref: F64) -> tuple[F64, F64]:
        lc = self._pair_conics(rig_from_ref)
        # interaction matrices of the conic coefficients for the rig velocity: L_a jV1
        LaV = np.einsum("pcd,pde->pce", lc.L_a, self._Vp)[self._pair]
        a = lc.a[self._pair]
        x, y = self.xy[:, 0], self.xy[:, 1]
        # L_da = [x^2, y^2, 2xy, 2x, 2y] . L_a   (eq. 25)
        c = np.empty((len(x), 5))
        c[:, 0], c[:, 1], c[:, 2], c[:, 3], c[:, 4] = x * x, y * y, 2 * x * y, 2 * x, 2 * y
        q = np.einsum("kc,kc->k", c, a) + 1.0
        if self.distance == "normalized":
            # d = px Q / |grad Q|:  d' = px (Q' - (Q/|g|) (g/|g|) . g') / |g|, where
            # g' = ([2x, 0, 2y, 2, 0] . L_a, [0, 2y, 2x, 0, 2] . L_a)
            gx = 2 * (a[:, 0] * x + a[:, 2] * y + a[:, 3])
            gy = 2 * (a[:, 1] * y + a[:, 2] * x + a[:, 4])
            gn = np.maximum(np.hypot(gx, gy), 1e-12)
            f = q / (gn * gn)
            ux, uy = f * gx, f * gy
            c[:, 0] -= 2 * ux * x
            c[:, 1] -= 2 * uy * y
            c[:, 2] -= 2 * (ux * y + uy * x)
            c[:, 3] -= 2 * ux
            c[:, 4] -= 2 * uy
            scale = self._px / gn
            c *= scale[:, None]
            q = q * scale
        Ld = np.einsum("kc,kcd->kd", c, LaV)
        ok = lc.valid[self._pair]
        if ok.all():
            return q[:, None], -Ld[:, None, :]
        return np.where(ok, q, 0.0)[:, None], np.where(ok[:, None], -Ld, 0.0)[:, None, :]


# --------------------------------------------------------------------------- control law


@dataclass
class VvsOptions:
    """Settings of the VVS control law (eq. 14-15) with IRLS M-estimation."""

    gain: float = 1.0  # lambda; 1 = Gauss-Newton step
    loss: Loss = "tukey"
    cutoff: float | None = None  # in units of the scale (Tukey 4.685, Huber 1.345)
    min_scale: float = 0.5  # MAD-scale floor for terms without their own ``min_scale``
    scale: Literal["mad", "median_norm"] = "mad"  # centred MAD (dim 1) or median norm
    weighting: Literal["irls", "paper"] = "irls"  # D = diag(sqrt(w)) or the paper's diag(w)
    max_iterations: int = 30
    step_tolerance: float = 1e-5  # stop when |v| (m, rad) is below
    huber_warmup: int = 0  # first iterations with Huber (for starts far from the solution)
    freeze_scale_after: int = 3  # re-estimate the scale during the first iterations only
    inlier_cutoff: float = 4.6851


def _term_scale(term: PoseTerm, r: F64, norms: F64, opt: VvsOptions) -> float:
    floor = float(getattr(term, "min_scale", opt.min_scale))
    if opt.scale == "mad" and term.dim == 1:
        return mad_scale(r[:, 0], floor)
    return robust_scale(norms, term.dim, floor)


def vvs_pose(
    terms: PoseTerm | Sequence[PoseTerm],
    rig_from_ref_init: ArrayLike,
    options: VvsOptions | None = None,
) -> PoseResult:
    """Robust VVS pose ``rig_from_ref`` (= 1Mo) of an N-camera rig from feature terms.

    Feature terms: points, point-to-conic distances, ...; from an initial pose (4x4, metres).
    """
    opt = options or VvsOptions()
    tlist = [terms] if not isinstance(terms, Sequence) else list(terms)
    total = sum(len(t) for t in tlist)
    if total < 3:
        raise EstimationError(f"VVS needs at least 3 features, got {total}")
    c = opt.cutoff if opt.cutoff is not None else default_cutoff(opt.loss)
    T = np.asarray(rig_from_ref_init, dtype=float).copy()
    scales = [0.0] * len(tlist)
    converged = False
    it = 0
    t_start = time.perf_counter()
    last: list[tuple[F64, F64, F64]] = []  # (residuals, Jacobian, weights) of the last iteration
    H = np.zeros((6, 6))
    for it in range(1, opt.max_iterations + 1):
        loss: Loss = "huber" if it <= opt.huber_warmup else opt.loss
        cc = default_cutoff("huber") if it <= opt.huber_warmup else c
        H = np.zeros((6, 6))
        g = np.zeros(6)
        last = []
        for k, term in enumerate(tlist):
            r, J = term.residuals_and_jacobian(T)
            n = np.linalg.norm(r, axis=1) if term.dim > 1 else np.abs(r[:, 0])
            if it <= max(opt.freeze_scale_after, opt.huber_warmup + 1) or scales[k] == 0.0:
                scales[k] = _term_scale(term, r, n, opt)
            w = weights(n / scales[k], loss, cc)
            last.append((r, J, w))
            if opt.weighting == "paper":
                w = w * w  # (D L)^+ D e with D = diag(w) weights the normal equations by w^2
            # L = -J (camera velocity); v = -lambda (D L)^+ D e = -lambda (L^T W L)^-1 L^T W e
            Lf = -J.reshape(-1, 6) / scales[k]
            ef = r.ravel() / scales[k]
            Lw = Lf * np.repeat(w, term.dim)[:, None]
            H += Lw.T @ Lf
            g += Lw.T @ ef
        try:
            v = -opt.gain * np.linalg.solve(H + 1e-12 * np.eye(6), g)
        except np.linalg.LinAlgError as exc:
            raise EstimationError("VVS: singular interaction matrix (too few features)") from exc
        T = se3_exp(-v) @ T  # ref_from_rig <- ref_from_rig exp(v)   (eq. 15)
        if float(np.linalg.norm(v)) < opt.step_tolerance:
            converged = True
            break
    iter_ms = 1e3 * (time.perf_counter() - t_start) / max(it, 1)
    # weights, inliers, covariance: from the last iteration when it converged (the final
    # step is below the tolerance), else re-evaluated at the returned pose
    if not (converged and opt.loss == loss and opt.weighting == "irls"):
        last = []
        H = np.zeros((6, 6))
        for k, term in enumerate(tlist):
            r, J = term.residuals_and_jacobian(T)
            n = np.linalg.norm(r, axis=1)
            w = weights(n / scales[k], opt.loss, c)
            Jf = J.reshape(-1, 6) / scales[k]
            H += (Jf * np.repeat(w, term.dim)[:, None]).T @ Jf
            last.append((r, J, w))
    inl, wts, norms = [], [], []
    cost = 0.0
    for k, (r, _J, w) in enumerate(last):
        n = np.linalg.norm(r, axis=1)
        s = scales[k]
        cost += float(np.sum(rho(n / s, opt.loss, c)) * s * s)
        inl.append(n < opt.inlier_cutoff * s)
        wts.append(w)
        norms.append(n)
    try:
        cov: F64 = np.asarray(np.linalg.inv(H), dtype=float)
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.inf)
    return PoseResult(
        T, inl, wts, norms, list(scales), cov, cost, it, converged, info={"iter_ms": iter_ms}
    )
