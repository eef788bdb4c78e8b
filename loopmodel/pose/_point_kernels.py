"""Compiled residuals and Jacobian of :class:`loopmodel.pose.rig.PointTerm` (numba, GIL released).

One pass over the points: the point in the rig (``R p + rho t``, ``rho`` 1 for Euclidean points),
in the camera (``Rc q + rho tc``), its unified central projection (``xi`` 0: pinhole) less the
measurement (pixels), and the (2, 6) Jacobian with respect to a left twist ``(v, w)`` of
``rig_from_ref``. The numpy form it replaces made about 15 temporaries per call; the front end calls
it ~40 times a frame (issue 33: the robust pose was 7-8 ms of the tracking thread's 28-33 ms a frame).
"""

from __future__ import annotations

import math

import numba
import numpy as np


def _project_py(q0, q1, q2, px, py, u0, v0, xi):  # type: ignore[no-untyped-def]
    """Pixel of the camera-frame point (q0, q1, q2) and the projection's denominator."""
    d = q2
    if xi != 0.0:
        d = q2 + xi * math.sqrt(q0 * q0 + q1 * q1 + q2 * q2)
    return px * q0 / d + u0, py * q1 / d + v0, d


_project = numba.njit(cache=True, nogil=True, inline="always")(_project_py)


def _in_rig_and_camera_py(p, s, R, t, Rc, tc):  # type: ignore[no-untyped-def]
    """The point ``p`` (homogeneous weight ``s``) in the rig (``R p + s t``) and in the camera (``Rc a + s tc``)."""
    a0 = R[0, 0] * p[0] + R[0, 1] * p[1] + R[0, 2] * p[2] + s * t[0]
    a1 = R[1, 0] * p[0] + R[1, 1] * p[1] + R[1, 2] * p[2] + s * t[1]
    a2 = R[2, 0] * p[0] + R[2, 1] * p[1] + R[2, 2] * p[2] + s * t[2]
    q0 = Rc[0, 0] * a0 + Rc[0, 1] * a1 + Rc[0, 2] * a2 + s * tc[0]
    q1 = Rc[1, 0] * a0 + Rc[1, 1] * a1 + Rc[1, 2] * a2 + s * tc[1]
    q2 = Rc[2, 0] * a0 + Rc[2, 1] * a1 + Rc[2, 2] * a2 + s * tc[2]
    return a0, a1, a2, q0, q1, q2


_in_rig_and_camera = numba.njit(cache=True, nogil=True, inline="always")(_in_rig_and_camera_py)


def _point_residuals_py(P, rho, uv, R, t, Rc, tc, px, py, u0, v0, xi):  # type: ignore[no-untyped-def]
    n = P.shape[0]
    out = np.empty((n, 2))
    for i in range(n):
        s = rho[i]
        a0, a1, a2, q0, q1, q2 = _in_rig_and_camera(P[i], s, R, t, Rc, tc)
        u, v, _ = _project(q0, q1, q2, px, py, u0, v0, xi)
        out[i, 0] = u - uv[i, 0]
        out[i, 1] = v - uv[i, 1]
    return out


def _point_jacobian_py(P, rho, uv, R, t, Rc, tc, px, py, u0, v0, xi):  # type: ignore[no-untyped-def]
    n = P.shape[0]
    out = np.empty((n, 2))
    J = np.empty((n, 2, 6))
    A = np.empty((2, 3))
    for i in range(n):
        s = rho[i]
        a0, a1, a2, q0, q1, q2 = _in_rig_and_camera(P[i], s, R, t, Rc, tc)
        u, v, d = _project(q0, q1, q2, px, py, u0, v0, xi)
        out[i, 0] = u - uv[i, 0]
        out[i, 1] = v - uv[i, 1]
        # d uv / d q (2, 3): pinhole rows (f/d, 0, -f x/d^2); unified adds xi q/|q| to d's gradient
        g0, g1, g2 = 0.0, 0.0, 1.0
        if xi != 0.0:
            nq = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2)
            if nq > 0.0:
                g0, g1, g2 = xi * q0 / nq, xi * q1 / nq, 1.0 + xi * q2 / nq
        e0 = -px * q0 / (d * d)
        e1 = -py * q1 / (d * d)
        j00, j01, j02 = px / d + e0 * g0, e0 * g1, e0 * g2
        j10, j11, j12 = e1 * g0, py / d + e1 * g1, e1 * g2
        # A = (d uv / d q) Rc: the projection's derivative w.r.t. the rig-frame point
        for c in range(3):
            A[0, c] = j00 * Rc[0, c] + j01 * Rc[1, c] + j02 * Rc[2, c]
            A[1, c] = j10 * Rc[0, c] + j11 * Rc[1, c] + j12 * Rc[2, c]
        for r in range(2):
            J[i, r, 0] = s * A[r, 0]
            J[i, r, 1] = s * A[r, 1]
            J[i, r, 2] = s * A[r, 2]
            # rows a x ... : -A [a]x  ==  a_rig x A_row
            J[i, r, 3] = a1 * A[r, 2] - a2 * A[r, 1]
            J[i, r, 4] = a2 * A[r, 0] - a0 * A[r, 2]
            J[i, r, 5] = a0 * A[r, 1] - a1 * A[r, 0]
    return out, J


def _weighted_normal_equations_py(J, r, w):  # type: ignore[no-untyped-def]
    """``H = sum_i w_i J_i^T J_i`` (6, 6) and ``g = sum_i w_i J_i^T r_i`` (6) of (n, d, 6) Jacobians."""
    n, d = r.shape
    H = np.zeros((6, 6))
    g = np.zeros(6)
    for i in range(n):
        wi = w[i]
        for k in range(d):
            rk = wi * r[i, k]
            for a in range(6):
                ja = wi * J[i, k, a]
                g[a] += J[i, k, a] * rk
                for b in range(a, 6):
                    H[a, b] += ja * J[i, k, b]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g


def _weighted_cost_py(r, w):  # type: ignore[no-untyped-def]
    """``sum_i w_i |r_i|^2`` of (n, d) residuals."""
    n, d = r.shape
    c = 0.0
    for i in range(n):
        s = 0.0
        for k in range(d):
            s += r[i, k] * r[i, k]
        c += w[i] * s
    return c


point_residuals = numba.njit(cache=True, nogil=True)(_point_residuals_py)
point_jacobian = numba.njit(cache=True, nogil=True)(_point_jacobian_py)
weighted_normal_equations = numba.njit(cache=True, nogil=True)(_weighted_normal_equations_py)
weighted_cost = numba.njit(cache=True, nogil=True)(_weighted_cost_py)

#: ``robust.RAYLEIGH_MEDIAN`` (the median of a 2-D standard normal vector's norm)
_RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))


def _se3_exp_py(xi):  # type: ignore[no-untyped-def]
    """:func:`loopmodel.geometry.se3.se3_exp` of the twist ``xi`` (v, w), written out (4, 4)."""
    w0, w1, w2 = xi[3], xi[4], xi[5]
    theta2 = w0 * w0 + w1 * w1 + w2 * w2
    K = np.zeros((3, 3))
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -w2, w1, w2, -w0, -w1, w0
    KK = K @ K
    if theta2 < 1e-16:
        a, b = 1.0, 0.5
    else:
        theta = math.sqrt(theta2)
        a, b = math.sin(theta) / theta, (1.0 - math.cos(theta)) / theta2
    if theta2 < 1e-12:
        c, d = 0.5, 1.0 / 6.0
        V = np.eye(3) + c * K + KK / 6.0
    else:
        theta = math.sqrt(theta2)
        c, d = (1.0 - math.cos(theta)) / theta2, (theta - math.sin(theta)) / (theta2 * theta)
        V = np.eye(3) + c * K + d * KK
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + a * K + b * KK
    T[:3, 3] = V @ xi[:3].copy()
    return T


def _irls_weights_py(r, pw, scale, loss, cc):  # type: ignore[no-untyped-def]
    """``robust.weights(|r| / scale, loss, cc) * pw`` with loss 0 l2, 1 Huber, 2 Tukey."""
    n = r.shape[0]
    w = np.empty(n)
    for i in range(n):
        s = math.sqrt(r[i, 0] * r[i, 0] + r[i, 1] * r[i, 1]) / scale
        if loss == 0:
            wi = 1.0
        elif loss == 1:
            wi = 1.0 if s <= cc else cc / max(s, 1e-300)
        else:
            u = s / cc
            wi = (1.0 - u * u) ** 2 if u < 1.0 else 0.0
        w[i] = wi * pw[i]
    return w


def _term_scale_py(rk, fixed_scale, min_scale):  # type: ignore[no-untyped-def]
    """A term's residual scale: ``fixed_scale``, or the MAD scale of its residuals ``rk`` (at least ``min_scale``)."""
    if fixed_scale > 0.0:
        return fixed_scale
    if rk.shape[0] == 0:
        return min_scale
    norms = np.empty(rk.shape[0])
    for i in range(rk.shape[0]):
        norms[i] = math.sqrt(rk[i, 0] * rk[i, 0] + rk[i, 1] * rk[i, 1])
    return max(np.median(norms) / _RAYLEIGH_MEDIAN, min_scale)


def _lm_step_py(  # type: ignore[no-untyped-def]
    H, g, T, lam, cost, P, rho, uv, w, start, Rc, tc, px, py, u0, v0, xi
):
    """One Levenberg-Marquardt step from ``T``: up to 8 damping increases until the cost does not rise.

    Returns (pose, damping, step, accepted).
    """
    nt = start.shape[0] - 1
    delta = np.zeros(6)
    for _ in range(8):
        Hd = H.copy()
        for i in range(6):
            Hd[i, i] = H[i, i] + lam * max(H[i, i], 1e-9)
        try:
            delta = -np.linalg.solve(Hd, g)
        except Exception:  # singular
            lam *= 10.0
            continue
        T_new = _se3_exp(delta) @ T
        R_new = np.ascontiguousarray(T_new[:3, :3])
        t_new = np.ascontiguousarray(T_new[:3, 3])
        new_cost = 0.0
        for k in range(nt):
            a, b = start[k], start[k + 1]
            rn = point_residuals(P[a:b], rho[a:b], uv[a:b], R_new, t_new, Rc, tc, px, py, u0, v0, xi)
            new_cost += weighted_cost(rn, w[a:b])
        if new_cost <= cost:
            return T_new, max(lam * 0.3, 1e-9), delta, True
        lam *= 10.0
    return T, lam, delta, False


def _refine_points_py(  # type: ignore[no-untyped-def]
    P, rho, uv, pw, start, T0, Rc, tc, px, py, u0, v0, xi, loss, c, huber_c, min_scale, fixed_scale, max_iterations,
    lam0, step_tolerance, huber_warmup, reweight_iterations,
):
    """:func:`loopmodel.pose.solver.refine_pose`'s IRLS / Levenberg-Marquardt loop for point terms of one camera.

    Term k is rows ``start[k]:start[k + 1]`` of the points ``P`` (homogeneous weights ``rho``), pixels
    ``uv`` and prior weights ``pw``; ``loss`` 0 l2, 1 Huber, 2 Tukey (Huber with ``huber_c`` during the
    warm-up); ``fixed_scale`` 0: the MAD scale. Every step as the Python loop takes it, in the same
    order. Returns the pose, each term's scale, the iterations and whether it converged.
    """
    nt = start.shape[0] - 1
    n = P.shape[0]
    T = T0.copy()
    lam = lam0
    scales = np.full(nt, min_scale)
    w = np.ones(n)
    r = np.empty((n, 2))
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):
        reweight = it <= reweight_iterations
        H = np.zeros((6, 6))
        g = np.zeros(6)
        R = np.ascontiguousarray(T[:3, :3])
        t = np.ascontiguousarray(T[:3, 3])
        warm = loss == 2 and it <= huber_warmup
        for k in range(nt):
            a, b = start[k], start[k + 1]
            rk, J = point_jacobian(P[a:b], rho[a:b], uv[a:b], R, t, Rc, tc, px, py, u0, v0, xi)
            r[a:b] = rk
            if reweight:
                if it <= huber_warmup + 1 or loss != 2:
                    scales[k] = _term_scale(rk, fixed_scale, min_scale)
                w[a:b] = _irls_weights(rk, pw[a:b], scales[k], 1 if warm else loss, huber_c if warm else c)
            Hk, gk = weighted_normal_equations(J, rk, w[a:b])
            H += Hk
            g += gk
        cost = 0.0
        for k in range(nt):
            cost += weighted_cost(r[start[k] : start[k + 1]], w[start[k] : start[k + 1]])
        T, lam, delta, accepted = _lm_step(H, g, T, lam, cost, P, rho, uv, w, start, Rc, tc, px, py, u0, v0, xi)
        small = math.sqrt(np.dot(delta, delta)) < step_tolerance
        if (not accepted or small) and it >= min(reweight_iterations, max_iterations):
            converged = True
            break
    return T, scales, it, converged


_se3_exp = numba.njit(cache=True, nogil=True)(_se3_exp_py)
_irls_weights = numba.njit(cache=True, nogil=True)(_irls_weights_py)
_term_scale = numba.njit(cache=True, nogil=True)(_term_scale_py)
_lm_step = numba.njit(cache=True, nogil=True)(_lm_step_py)
refine_points = numba.njit(cache=True, nogil=True)(_refine_points_py)


def warm_up() -> None:
    """Load (or compile) the kernels for float64 arrays: the first call's cost, up front.

    ``point_residuals`` / ``point_jacobian`` get their rotations and translations as
    :meth:`loopmodel.pose.rig.PointTerm._kernel_args` passes them, views of (4, 4) matrices (non-contiguous,
    a type of their own for numba: contiguous ones here left the run's types to compile in its first
    frames, 1-5 s; cx13).
    """
    P = np.array([[0.1, -0.2, 3.0]])
    one = np.ones(1)
    uv = np.zeros((1, 2))
    R = np.eye(3)
    t = np.zeros(3)
    T = np.eye(4)
    point_residuals(P, one, uv, T[:3, :3], T[:3, 3], T[:3, :3], T[:3, 3], 500.0, 500.0, 320.0, 240.0, 0.0)
    r, J = point_jacobian(P, one, uv, T[:3, :3], T[:3, 3], T[:3, :3], T[:3, 3], 500.0, 500.0, 320.0, 240.0, 0.0)
    weighted_normal_equations(J, r, one)
    weighted_cost(r, one)
    refine_points(P, one, uv, one, np.array([0, 1]), np.eye(4), R, t, 500.0, 500.0, 320.0, 240.0, 0.0, 2, 4.6851,
                  1.345, 0.5, 0.0, 2, 1e-4, 1e-6, 2, 4)
