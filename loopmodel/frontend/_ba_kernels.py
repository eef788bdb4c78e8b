"""Compiled Levenberg-Marquardt loop of :func:`loopmodel.frontend.hybrid_ba.hybrid_keyframe_ba` (numba, GIL released).

The numpy form evaluates each measurement block, builds the normal equations and solves the
Schur-reduced system with some sixty small-array calls an iteration (4.5 ms a KITTI keyframe's BA
of ~100 points, 3-5 iterations, nearly all of it call overhead). Here one pass per point, the same
steps in the same order: residuals and Jacobians of every block (a central camera with the unified
model's ``xi``), Huber weights, the per-point 3x3 blocks eliminated, the 6x6 (7x7 with the
disparity offset) reduced system solved by LU with partial pivoting, the twist applied on the left
(``se3_exp``), the step kept when the points stay in front and the Huber cost falls. Only the order
of the sums differs from numpy's (results within ~1e-12 relative; fe11's tests).

Blocks (``B`` of them) as :class:`~loopmodel.frontend.hybrid_ba._Block`: ``fixed`` (B, 4, 4),
``moving`` / ``is_right`` (B,) flags, ``uv`` (B, M, 2), ``valid`` (B, M), ``weight`` (B, M) (valid
times relative weight), ``cams`` (B, 5) = (px, py, u0, v0, xi).
"""

from __future__ import annotations

import math

import numba
import numpy as np


def _project_py(cam, x, y, z, out):  # type: ignore[no-untyped-def]
    """Pixel (u, v) of a camera-frame point into ``out`` (2,); as ``CentralCamera.project``."""
    xi = cam[4]
    if xi == 0.0:
        out[0] = cam[0] * (x / z) + cam[2]
        out[1] = cam[1] * (y / z) + cam[3]
    else:
        d = z + xi * math.sqrt(x * x + y * y + z * z)
        out[0] = cam[0] * (x / d) + cam[2]
        out[1] = cam[1] * (y / d) + cam[3]


def _project_jacobian_py(cam, x, y, z, J):  # type: ignore[no-untyped-def]
    """d (u, v) / d point (2, 3) into ``J``; as ``CentralCamera.project_jacobian``."""
    xi = cam[4]
    if xi == 0.0:
        iz = 1.0 / z
        J[0, 0] = cam[0] * iz
        J[0, 1] = 0.0
        J[0, 2] = -cam[0] * x * iz * iz
        J[1, 0] = 0.0
        J[1, 1] = cam[1] * iz
        J[1, 2] = -cam[1] * y * iz * iz
        return
    rho = math.sqrt(x * x + y * y + z * z)
    d = z + xi * rho
    safe = rho if rho > 0 else 1.0
    dd0, dd1, dd2 = xi * x / safe, xi * y / safe, 1 + xi * z / safe
    for r in range(2):
        f = cam[r]
        pr = x if r == 0 else y
        c = -f * (pr / d**2)
        J[r, 0] = c * dd0
        J[r, 1] = c * dd1
        J[r, 2] = c * dd2
        J[r, r] += f / d


def _in_block_py(F, x, y, z, measured):  # type: ignore[no-untyped-def]
    """A point (x, y, z) in a block's fixed frame ``F`` (4, 4); a harmless (0, 0, 1) in a row it does not measure."""
    if not measured:
        return 0.0, 0.0, 1.0
    px = F[0, 0] * x + F[0, 1] * y + F[0, 2] * z + F[0, 3]
    py = F[1, 0] * x + F[1, 1] * y + F[1, 2] * z + F[1, 3]
    pz = F[2, 0] * x + F[2, 1] * y + F[2, 2] * z + F[2, 3]
    return px, py, pz


def _chain_fixed_py(Jcam, F, Jc):  # type: ignore[no-untyped-def]
    """``Jc`` (2, 3) = ``Jcam`` (2, 3) times the rotation of ``F``: d pixel / d point in the block's input frame."""
    for a in range(2):
        for c in range(3):
            Jc[a, c] = Jcam[a, 0] * F[0, c] + Jcam[a, 1] * F[1, c] + Jcam[a, 2] * F[2, c]


def _fill_jacobians_py(Jc, T, moving, fx, fy, fz, n_par, JX, Jp, b, i):  # type: ignore[no-untyped-def]
    """Measurement (b, i)'s ``JX[b, i]`` (2, 3) d pixel / d point, ``Jp[b, i]`` (2, n_par) d pixel / d (twist, offset).

    ``Jc`` (2, 3) is d pixel / d point in the block's input frame; a moving block's input is the
    point moved by ``T`` (at (fx, fy, fz)), whose twist is applied on the left.
    """
    for a in range(2):
        for c in range(3):
            if moving:
                JX[b, i, a, c] = Jc[a, 0] * T[0, c] + Jc[a, 1] * T[1, c] + Jc[a, 2] * T[2, c]
            else:
                JX[b, i, a, c] = Jc[a, c]
        for k in range(n_par):
            Jp[b, i, a, k] = 0.0
        if moving:
            for c in range(3):
                Jp[b, i, a, c] = Jc[a, c]
            Jp[b, i, a, 3] = fy * Jc[a, 2] - fz * Jc[a, 1]
            Jp[b, i, a, 4] = fz * Jc[a, 0] - fx * Jc[a, 2]
            Jp[b, i, a, 5] = fx * Jc[a, 1] - fy * Jc[a, 0]


def _evaluate_py(X, T, fixed, moving, is_right, uv, valid, cams, dc, n_par, jac, r, pz, JX, Jp):  # type: ignore[no-untyped-def]
    """Residuals ``r`` (B, M, 2), depths ``pz`` (B, M) and with ``jac`` ``JX`` (B, M, 2, 3), ``Jp`` (B, M, 2, n_par)."""
    nb, m = valid.shape
    pr = np.empty(2)
    Jc = np.empty((2, 3))
    Jcam = np.empty((2, 3))
    for i in range(m):
        fx = T[0, 0] * X[i, 0] + T[0, 1] * X[i, 1] + T[0, 2] * X[i, 2] + T[0, 3]
        fy = T[1, 0] * X[i, 0] + T[1, 1] * X[i, 1] + T[1, 2] * X[i, 2] + T[1, 3]
        fz = T[2, 0] * X[i, 0] + T[2, 1] * X[i, 1] + T[2, 2] * X[i, 2] + T[2, 3]
        for b in range(nb):
            bx, by, bz = (fx, fy, fz) if moving[b] else (X[i, 0], X[i, 1], X[i, 2])
            F = fixed[b]
            px, py, pzz = _in_block(F, bx, by, bz, valid[b, i] > 0)
            pz[b, i] = pzz
            _project(cams[b], px, py, pzz, pr)
            if is_right[b] and dc != 0.0:
                pr[0] += dc
            r[b, i, 0] = (pr[0] - uv[b, i, 0]) * valid[b, i]
            r[b, i, 1] = (pr[1] - uv[b, i, 1]) * valid[b, i]
            if not jac:
                continue
            _project_jacobian(cams[b], px, py, pzz, Jcam)
            _chain_fixed(Jcam, F, Jc)
            _fill_jacobians(Jc, T, moving[b], fx, fy, fz, n_par, JX, Jp, b, i)
            if is_right[b] and n_par == 7:
                Jp[b, i, 0, 6] = valid[b, i]


def _huber_rho_py(n, k):  # type: ignore[no-untyped-def]
    return 0.5 * n * n if n <= k else k * (n - 0.5 * k)


def _huber_w_py(n, k):  # type: ignore[no-untyped-def]
    return 1.0 if n <= k else k / max(n, 1e-300)


def _norms_cost_py(r, huber, prior_w, prior_mean, dc, nrm):  # type: ignore[no-untyped-def]
    """Residual norms into ``nrm`` (B, M); returns the Huber cost plus the offset prior's."""
    nb, m = nrm.shape
    cost = 0.0
    for b in range(nb):
        for i in range(m):
            nrm[b, i] = math.sqrt(r[b, i, 0] * r[b, i, 0] + r[b, i, 1] * r[b, i, 1])
            cost += _huber_rho(nrm[b, i], huber)
    return cost + 0.5 * prior_w * (dc - prior_mean) ** 2


def _solve_lu_py(A, b, out):  # type: ignore[no-untyped-def]
    """``out`` = A^-1 b by LU with partial pivoting (A, b overwritten); False when a pivot is zero."""
    n = b.shape[0]
    for k in range(n):
        p = k
        best = abs(A[k, k])
        for i in range(k + 1, n):
            if abs(A[i, k]) > best:
                best = abs(A[i, k])
                p = i
        if A[p, k] == 0.0:
            return False
        if p != k:
            for j in range(n):
                A[k, j], A[p, j] = A[p, j], A[k, j]
            b[k], b[p] = b[p], b[k]
        for i in range(k + 1, n):
            f = A[i, k] / A[k, k]
            for j in range(k + 1, n):
                A[i, j] -= f * A[k, j]
            b[i] -= f * b[k]
    for i in range(n - 1, -1, -1):
        acc = b[i]
        for j in range(i + 1, n):
            acc -= A[i, j] * out[j]
        out[i] = acc / A[i, i]
    return True


def _inv3_py(A, out):  # type: ignore[no-untyped-def]
    """``out`` = A^-1 of a 3x3 matrix by its adjugate; False when singular."""
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    if det == 0.0 or not math.isfinite(det):
        return False
    inv = 1.0 / det
    out[0, 0] = c00 * inv
    out[1, 0] = c01 * inv
    out[2, 0] = c02 * inv
    out[0, 1] = (A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]) * inv
    out[1, 1] = (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) * inv
    out[2, 1] = (A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]) * inv
    out[0, 2] = (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) * inv
    out[1, 2] = (A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]) * inv
    out[2, 2] = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) * inv
    return True


def _normal_py(r, JX, Jp, nrm, weight, moving, is_right, huber, prior_w, prior_mean, delta, Hxx, gx, Hpx, Hpp, gp):  # type: ignore[no-untyped-def]
    """The Gauss-Newton normal equations (Huber weights times ``weight``), the offset prior's included."""
    nb, m = nrm.shape
    n_par = gp.shape[0]
    Hxx[:] = 0.0
    gx[:] = 0.0
    Hpx[:] = 0.0
    Hpp[:] = 0.0
    gp[:] = 0.0
    for b in range(nb):
        par = moving[b] or (is_right[b] and n_par == 7)
        for i in range(m):
            w = _huber_w(nrm[b, i], huber) * weight[b, i]
            for a in range(2):
                ra = r[b, i, a]
                for c in range(3):
                    jw = JX[b, i, a, c] * w
                    gx[i, c] += jw * ra
                    for e in range(3):
                        Hxx[i, c, e] += jw * JX[b, i, a, e]
                if par:
                    for k in range(n_par):
                        pw = Jp[b, i, a, k] * w
                        gp[k] += pw * ra
                        for c in range(3):
                            Hpx[i, k, c] += pw * JX[b, i, a, c]
                        for k2 in range(n_par):
                            Hpp[k, k2] += pw * Jp[b, i, a, k2]
    if prior_w > 0:
        Hpp[6, 6] += prior_w
        gp[6] += prior_w * (delta - prior_mean)


def _initial_py(X, T, fixed, moving, is_right, uv, valid, cams, n_par):  # type: ignore[no-untyped-def]
    """The residual norms (B, M) at the start (offset 0)."""
    nb, m = valid.shape
    r = np.zeros((nb, m, 2))
    nrm = np.zeros((nb, m))
    _evaluate(X, T, fixed, moving, is_right, uv, valid, cams, 0.0, n_par, False, r, np.zeros((nb, m)),
              np.zeros((nb, m, 2, 3)), np.zeros((nb, m, 2, n_par)))
    _norms_cost(r, 1.0, 0.0, 0.0, 0.0, nrm)
    return nrm


def _offset_variance_py(X, T, fixed, moving, is_right, uv, valid, weight, cams, huber, prior_w, prior_mean, delta,
                        nrm, sigma2):  # type: ignore[no-untyped-def]
    """The disparity offset's variance at the solution: (S^-1)[6, 6] of the reduced system times ``sigma2``."""
    nb, m = valid.shape
    n_par = 7
    r = np.zeros((nb, m, 2))
    JX = np.zeros((nb, m, 2, 3))
    Jp = np.zeros((nb, m, 2, n_par))
    _evaluate(X, T, fixed, moving, is_right, uv, valid, cams, delta, n_par, True, r, np.zeros((nb, m)), JX, Jp)
    Hxx = np.zeros((m, 3, 3))
    gx = np.zeros((m, 3))
    Hpx = np.zeros((m, n_par, 3))
    S = np.zeros((n_par, n_par))
    gp = np.zeros(n_par)
    _normal(r, JX, Jp, nrm, weight, moving, is_right, huber, prior_w, prior_mean, delta, Hxx, gx, Hpx, S, gp)
    if prior_w < 0:
        S[6, 6] += prior_w
    A3 = np.zeros((3, 3))
    Hi = np.zeros((3, 3))
    for i in range(m):
        for c in range(3):
            for e in range(3):
                A3[c, e] = Hxx[i, c, e] + (1e-9 if c == e else 0.0)
        if not _inv3(A3, Hi):
            return np.inf
        for k in range(n_par):
            h0 = Hpx[i, k, 0] * Hi[0, 0] + Hpx[i, k, 1] * Hi[1, 0] + Hpx[i, k, 2] * Hi[2, 0]
            h1 = Hpx[i, k, 0] * Hi[0, 1] + Hpx[i, k, 1] * Hi[1, 1] + Hpx[i, k, 2] * Hi[2, 1]
            h2 = Hpx[i, k, 0] * Hi[0, 2] + Hpx[i, k, 1] * Hi[1, 2] + Hpx[i, k, 2] * Hi[2, 2]
            for k2 in range(n_par):
                S[k, k2] -= h0 * Hpx[i, k2, 0] + h1 * Hpx[i, k2, 1] + h2 * Hpx[i, k2, 2]
    e6 = np.zeros(n_par)
    e6[6] = 1.0
    col = np.zeros(n_par)
    if not _solve_lu(S, e6, col):
        return np.inf
    return col[6] * sigma2


def _se3_exp_py(xi, T):  # type: ignore[no-untyped-def]
    """``T`` (4, 4) = se3_exp(xi), xi = (v, w); as :func:`loopmodel.geometry.se3.se3_exp`."""
    wx, wy, wz = xi[3], xi[4], xi[5]
    K = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
    K2 = K @ K
    theta2 = wx * wx + wy * wy + wz * wz
    if theta2 < 1e-16:
        a, b = 1.0, 0.5
    else:
        th = math.sqrt(theta2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / theta2
    if theta2 < 1e-12:
        c, d = 0.5, 1.0 / 6.0
    else:
        th = math.sqrt(theta2)
        c, d = (1.0 - math.cos(th)) / theta2, (th - math.sin(th)) / (theta2 * th)
    for i in range(4):
        for j in range(4):
            T[i, j] = 0.0
    T[3, 3] = 1.0
    for i in range(3):
        for j in range(3):
            e = 1.0 if i == j else 0.0
            T[i, j] = e + a * K[i, j] + b * K2[i, j]
    for i in range(3):
        acc = 0.0
        for j in range(3):
            e = 1.0 if i == j else 0.0
            acc += (e + c * K[i, j] + d * K2[i, j]) * xi[j]
        T[i, 3] = acc


def _schur_py(Hxx, gx, Hpx, Hpp, gp, lam, S, bv, Hi, HpxHi, A3):  # type: ignore[no-untyped-def]
    """The damped system reduced to the pose (and offset) by the Schur complement of the points.

    ``S`` (P, P), ``bv`` (P,): the reduced system S dp = bv; ``Hi`` (M, 3, 3) the damped point blocks'
    inverses, ``HpxHi`` (M, P, 3) their products with ``Hpx``. False when a point block is singular.
    """
    m = Hxx.shape[0]
    n_par = gp.shape[0]
    for k in range(n_par):
        for k2 in range(n_par):
            S[k, k2] = Hpp[k, k2] + (lam * Hpp[k, k] if k == k2 else 0.0) + (1e-12 if k == k2 else 0.0)
        bv[k] = -gp[k]
    for i in range(m):
        for c in range(3):
            for e in range(3):
                A3[c, e] = Hxx[i, c, e] + (lam * Hxx[i, c, c] + 1e-9 if c == e else 0.0)
        if not _inv3(A3, Hi[i]):
            return False
        for k in range(n_par):
            for e in range(3):
                HpxHi[i, k, e] = Hpx[i, k, 0] * Hi[i, 0, e] + Hpx[i, k, 1] * Hi[i, 1, e] + Hpx[i, k, 2] * Hi[i, 2, e]
        for k in range(n_par):
            for k2 in range(n_par):
                S[k, k2] -= (HpxHi[i, k, 0] * Hpx[i, k2, 0] + HpxHi[i, k, 1] * Hpx[i, k2, 1]
                             + HpxHi[i, k, 2] * Hpx[i, k2, 2])
            bv[k] += HpxHi[i, k, 0] * gx[i, 0] + HpxHi[i, k, 1] * gx[i, 1] + HpxHi[i, k, 2] * gx[i, 2]
    return True


def _back_substitute_py(gx, Hpx, Hi, dp, dx, A3):  # type: ignore[no-untyped-def]
    """The points' steps ``dx`` (M, 3) = -Hi_i (gx_i + Hpx_i^T dp) given the pose step ``dp`` (P,)."""
    m = gx.shape[0]
    n_par = dp.shape[0]
    for i in range(m):
        for c in range(3):
            acc = gx[i, c]
            for k in range(n_par):
                acc += Hpx[i, k, c] * dp[k]
            A3[0, c] = acc
        for c in range(3):
            dx[i, c] = -(Hi[i, c, 0] * A3[0, 0] + Hi[i, c, 1] * A3[0, 1] + Hi[i, c, 2] * A3[0, 2])


def _compose_py(dT, T, Tn):  # type: ignore[no-untyped-def]
    """``Tn`` (4, 4) = dT @ T, the twist applied on the left."""
    for a in range(4):
        for c in range(4):
            Tn[a, c] = dT[a, 0] * T[0, c] + dT[a, 1] * T[1, c] + dT[a, 2] * T[2, c] + dT[a, 3] * T[3, c]


def _all_in_front_py(pz):  # type: ignore[no-untyped-def]
    """True when every depth of ``pz`` (B, M) is positive (NaN counts as behind)."""
    nb, m = pz.shape
    in_front = True
    for b in range(nb):
        for i in range(m):
            if not pz[b, i] > 0:
                in_front = False
    return in_front


def _lm_py(X, T, fixed, moving, is_right, uv, valid, weight, cams, n_par, huber, iterations, prior_w, prior_mean):  # type: ignore[no-untyped-def]
    """The LM loop from (X, T, offset 0): returns (X, T, offset, residual norms (B, M), iterations)."""
    nb, m = valid.shape
    r = np.zeros((nb, m, 2))
    pz = np.zeros((nb, m))
    JX = np.zeros((nb, m, 2, 3))
    Jp = np.zeros((nb, m, 2, n_par))
    nrm = np.zeros((nb, m))
    X = X.copy()
    T = T.copy()
    delta = 0.0
    _evaluate(X, T, fixed, moving, is_right, uv, valid, cams, delta, n_par, True, r, pz, JX, Jp)
    cost = _norms_cost(r, huber, prior_w, prior_mean, delta, nrm)
    lam = 1e-3
    Hxx = np.zeros((m, 3, 3))
    gx = np.zeros((m, 3))
    Hpx = np.zeros((m, n_par, 3))
    Hpp = np.zeros((n_par, n_par))
    gp = np.zeros(n_par)
    Hi = np.zeros((m, 3, 3))
    HpxHi = np.zeros((m, n_par, 3))
    A3 = np.zeros((3, 3))
    S = np.zeros((n_par, n_par))
    bv = np.zeros(n_par)
    dp = np.zeros(n_par)
    dx = np.zeros((m, 3))
    Tn = np.zeros((4, 4))
    dT = np.zeros((4, 4))
    r2 = np.zeros((nb, m, 2))
    pz2 = np.zeros((nb, m))
    nrm2 = np.zeros((nb, m))
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 (it is returned)
        _normal(r, JX, Jp, nrm, weight, moving, is_right, huber, prior_w, prior_mean, delta, Hxx, gx, Hpx, Hpp, gp)
        improved = False
        converged = False
        for _ in range(6):
            # the damped step by the Schur complement of the points
            if not _schur(Hxx, gx, Hpx, Hpp, gp, lam, S, bv, Hi, HpxHi, A3) or not _solve_lu(S, bv, dp):
                lam *= 10
                continue
            _back_substitute(gx, Hpx, Hi, dp, dx, A3)
            _se3_exp(dp, dT)
            _compose(dT, T, Tn)
            Xn = X + dx
            d_new = delta + (dp[6] if n_par == 7 else 0.0)
            _evaluate(Xn, Tn, fixed, moving, is_right, uv, valid, cams, d_new, n_par, False, r2, pz2, JX, Jp)
            c_new = _norms_cost(r2, huber, prior_w, prior_mean, d_new, nrm2)
            if _all_in_front(pz2) and c_new < cost:
                converged = cost - c_new < 1e-4 * cost
                X = Xn
                T = Tn.copy()
                nrm[:] = nrm2
                delta = d_new
                cost = c_new
                lam = max(lam * 0.3, 1e-9)
                improved = True
                break
            lam *= 10.0
        if not improved or converged:
            break
        _evaluate(X, T, fixed, moving, is_right, uv, valid, cams, delta, n_par, True, r, pz, JX, Jp)
    return X, T, delta, nrm, it


_project = numba.njit(cache=True, nogil=True, inline="always")(_project_py)
_huber_rho = numba.njit(cache=True, nogil=True, inline="always")(_huber_rho_py)
_huber_w = numba.njit(cache=True, nogil=True, inline="always")(_huber_w_py)
_project_jacobian = numba.njit(cache=True, nogil=True, inline="always")(_project_jacobian_py)
_in_block = numba.njit(cache=True, nogil=True, inline="always")(_in_block_py)
_chain_fixed = numba.njit(cache=True, nogil=True, inline="always")(_chain_fixed_py)
_fill_jacobians = numba.njit(cache=True, nogil=True, inline="always")(_fill_jacobians_py)
_evaluate = numba.njit(cache=True, nogil=True)(_evaluate_py)
_norms_cost = numba.njit(cache=True, nogil=True)(_norms_cost_py)
_solve_lu = numba.njit(cache=True, nogil=True)(_solve_lu_py)
_inv3 = numba.njit(cache=True, nogil=True)(_inv3_py)
_se3_exp = numba.njit(cache=True, nogil=True)(_se3_exp_py)
_normal = numba.njit(cache=True, nogil=True)(_normal_py)
_schur = numba.njit(cache=True, nogil=True, inline="always")(_schur_py)
_back_substitute = numba.njit(cache=True, nogil=True, inline="always")(_back_substitute_py)
_compose = numba.njit(cache=True, nogil=True, inline="always")(_compose_py)
_all_in_front = numba.njit(cache=True, nogil=True, inline="always")(_all_in_front_py)
initial = numba.njit(cache=True, nogil=True)(_initial_py)
offset_variance = numba.njit(cache=True, nogil=True)(_offset_variance_py)
lm = numba.njit(cache=True, nogil=True)(_lm_py)


def warm_up() -> None:
    """Load (or compile) the loop for float64 arrays: the first call's cost, up front."""
    X = np.array([[0.1, 0.2, 5.0], [0.3, -0.1, 6.0], [-0.2, 0.1, 4.0], [0.0, 0.0, 7.0]])
    cams = np.array([[500.0, 500.0, 320.0, 240.0, 0.0]] * 2)
    fixed = np.stack([np.eye(4), np.eye(4)])
    uv = np.zeros((2, 4, 2))
    valid = np.ones((2, 4))
    moving, right = np.array([False, True]), np.array([True, False])
    initial(X, np.eye(4), fixed, moving, right, uv, valid, cams, 7)
    X1, T1, d1, nrm, _it = lm(X, np.eye(4), fixed, moving, right, uv, valid, valid, cams, 7, 1.0, 1, 0.0, 0.0)
    offset_variance(X1, T1, fixed, moving, right, uv, valid, valid, cams, 1.0, 0.0, 0.0, d1, nrm, 1.0)
