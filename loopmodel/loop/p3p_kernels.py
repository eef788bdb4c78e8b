"""Compiled kernels of the P3P bank.

One Grunert P3P per minimal sample, MSAC scoring with early exit, adaptive sample count, and a
robust Gauss-Newton refinement on unit rays.

The P3P solver is the scalar form of :func:`loopmodel.loop.p3p.p3p_grunert` (same
equations: the quartic in ``v``, ``s1`` from the ``b`` equation, ``u`` from ``c``, a Newton
polish of the three distances, the pose from the two triangles' frames). Ray errors are the
squared sines of the angle between an observed unit ray and the direction of the
transformed point (4 for points behind the camera).
Poses are ``cam_from_world``: ``p_cam = R p_world + t``.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@nb.njit(cache=True)
def _mm3(A: F64, B: F64) -> F64:
    """3x3 matrix product (explicit loops: no BLAS binding to compile)."""
    out = np.zeros((3, 3))
    for i in range(3):
        for k in range(3):
            a = A[i, k]
            for j in range(3):
                out[i, j] += a * B[k, j]
    return out


@nb.njit(cache=True)
def _mv3(A: F64, x: F64) -> F64:
    """3x3 matrix times 3-vector."""
    out = np.zeros(3)
    for i in range(3):
        out[i] = A[i, 0] * x[0] + A[i, 1] * x[1] + A[i, 2] * x[2]
    return out


@nb.njit(cache=True)
def _solve_spd(H: F64, g: F64) -> tuple[bool, F64]:
    """Solve H x = g for a symmetric positive definite H (Cholesky, explicit loops)."""
    n = H.shape[0]
    L = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            acc = H[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i == j:
                if acc <= 0:
                    return False, np.zeros(n)
                L[i, i] = np.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
    y = np.zeros(n)
    for i in range(n):
        acc = g[i]
        for k in range(i):
            acc -= L[i, k] * y[k]
        y[i] = acc / L[i, i]
    x = np.zeros(n)
    for i in range(n - 1, -1, -1):
        acc = y[i]
        for k in range(i + 1, n):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]
    return True, x


@nb.njit(cache=True)
def _frame(p0: F64, p1: F64, p2: F64, out: F64) -> bool:
    """Orthonormal frame (columns) of a triangle; False when degenerate."""
    e1 = p1 - p0
    d = p2 - p0
    n = np.array([e1[1] * d[2] - e1[2] * d[1], e1[2] * d[0] - e1[0] * d[2], e1[0] * d[1] - e1[1] * d[0]])
    l1 = np.sqrt(np.sum(e1 * e1))
    ln = np.sqrt(np.sum(n * n))
    if l1 <= 1e-300 or ln <= 1e-300:
        return False
    e1 = e1 / l1
    e3 = n / ln
    e2 = np.array([e3[1] * e1[2] - e3[2] * e1[1], e3[2] * e1[0] - e3[0] * e1[2], e3[0] * e1[1] - e3[1] * e1[0]])
    for r in range(3):
        out[r, 0] = e1[r]
        out[r, 1] = e2[r]
        out[r, 2] = e3[r]
    return True


@nb.njit(cache=True)
def _cubic_max_root(b: float, c: float, d: float) -> float:
    """Largest real root of x^3 + b x^2 + c x + d (Cardano / trigonometric form)."""
    p = c - b * b / 3.0
    q = 2.0 * b**3 / 27.0 - b * c / 3.0 + d
    disc = q * q / 4.0 + p**3 / 27.0
    if disc > 0:
        sq = np.sqrt(disc)
        y = np.cbrt(-q / 2.0 + sq) + np.cbrt(-q / 2.0 - sq)
    elif p < 0:
        r = 2.0 * np.sqrt(-p / 3.0)
        arg = min(max(3.0 * q / (p * r), -1.0), 1.0)
        y = r * np.cos(np.arccos(arg) / 3.0)
    else:
        y = np.cbrt(-q)
    x = y - b / 3.0
    for _ in range(2):  # Newton polish
        f = ((x + b) * x + c) * x + d
        df = (3.0 * x + 2.0 * b) * x + c
        if df == 0:
            break
        x -= f / df
    return x


@nb.njit(cache=True, inline="always")
def _biquadratic_roots(p: float, r: float, ys: F64) -> int:
    """Real roots y of y^4 + p y^2 + r (the depressed quartic without its linear term) -> ``ys``."""
    n = 0
    disc = p * p - 4.0 * r
    if disc >= 0:
        for z in ((-p + np.sqrt(disc)) / 2.0, (-p - np.sqrt(disc)) / 2.0):
            if z >= 0:
                ys[n] = np.sqrt(z)
                ys[n + 1] = -np.sqrt(z)
                n += 2
    return n


@nb.njit(cache=True, inline="always")
def _ferrari_roots(p: float, q: float, r: float, ys: F64) -> int:
    """Real roots y of y^4 + p y^2 + q y + r by Ferrari (resolvent cubic, two quadratics) -> ``ys``."""
    n = 0
    m = _cubic_max_root(p, p * p / 4.0 - r, -q * q / 8.0)
    if m <= 0:
        m = 1e-300
    s2 = np.sqrt(2.0 * m)
    for sg in (1.0, -1.0):
        # y^2 + sg s2 y + (p/2 + m - sg q / (2 s2)) = 0
        cc = p / 2.0 + m - sg * q / (2.0 * s2)
        disc = 2.0 * m - 4.0 * cc
        if disc < 0 and disc > -1e-9 * (2.0 * m + 4.0 * abs(cc)):
            disc = 0.0
        if disc >= 0:
            sq = np.sqrt(disc)
            ys[n] = (-sg * s2 + sq) / 2.0
            ys[n + 1] = (-sg * s2 - sq) / 2.0
            n += 2
    return n


@nb.njit(cache=True)
def quartic_real_roots(A4: float, A3: float, A2: float, A1: float, A0: float, out: F64) -> int:
    """Real roots of A4 v^4 + ...

    + A0 (Ferrari: depressed quartic, resolvent cubic, two quadratics; each root polished by Newton
    on the original quartic) -> ``out`` (4,), returns their number.
    """
    if A4 == 0:
        return 0
    a, b, c, d = A3 / A4, A2 / A4, A1 / A4, A0 / A4
    p = b - 3.0 * a * a / 8.0
    q = c - a * b / 2.0 + a**3 / 8.0
    r = d - a * c / 4.0 + a * a * b / 16.0 - 3.0 * a**4 / 256.0
    ys = np.empty(4)
    if abs(q) < 1e-14 * max(1.0, abs(p), abs(r)):
        n = _biquadratic_roots(p, r, ys)
    else:
        n = _ferrari_roots(p, q, r, ys)
    for k in range(n):
        x = ys[k] - a / 4.0
        for _ in range(2):
            f = (((x + a) * x + b) * x + c) * x + d
            df = ((4.0 * x + 3.0 * a) * x + 2.0 * b) * x + c
            if df == 0:
                break
            x -= f / df
        out[k] = x
    return n


@nb.njit(cache=True, inline="always")
def _degenerate(j: F64, P: F64, b2: float, side2: float) -> bool:
    """Whether the three points are (nearly) collinear or coincident, or the three rays coplanar."""
    if side2 <= 0 or b2 <= 1e-12 * side2:
        return True
    e1 = P[1] - P[0]
    e2 = P[2] - P[0]
    cx = e1[1] * e2[2] - e1[2] * e2[1]
    cy = e1[2] * e2[0] - e1[0] * e2[2]
    cz = e1[0] * e2[1] - e1[1] * e2[0]
    if cx * cx + cy * cy + cz * cz <= (1e-6 * side2) ** 2:
        return True
    tx = j[1, 1] * j[2, 2] - j[1, 2] * j[2, 1]
    ty = j[1, 2] * j[2, 0] - j[1, 0] * j[2, 2]
    tz = j[1, 0] * j[2, 1] - j[1, 1] * j[2, 0]
    return abs(j[0, 0] * tx + j[0, 1] * ty + j[0, 2] * tz) <= 1e-6


@nb.njit(cache=True, inline="always")
def _grunert_quartic(
    a2: float, b2: float, c2: float, ca: float, cb: float, cg: float
) -> tuple[float, float, float, float, float]:
    """Grunert's quartic in v = s3 / s1 from the squared sides and the rays' cosines: (A4, A3, A2, A1, A0)."""
    amc = (a2 - c2) / b2
    apc = (a2 + c2) / b2
    A4 = (amc - 1.0) ** 2 - 4.0 * c2 / b2 * ca**2
    A3 = 4.0 * (amc * (1.0 - amc) * cb - (1.0 - apc) * ca * cg + 2.0 * c2 / b2 * ca**2 * cb)
    A2 = 2.0 * (
        amc**2
        - 1.0
        + 2.0 * amc**2 * cb**2
        + 2.0 * (b2 - c2) / b2 * ca**2
        - 4.0 * apc * ca * cb * cg
        + 2.0 * (b2 - a2) / b2 * cg**2
    )
    A1 = 4.0 * (-amc * (1.0 + amc) * cb + 2.0 * a2 / b2 * cg**2 * cb - (1.0 - apc) * ca * cg)
    A0 = (1.0 + amc) ** 2 - 4.0 * a2 / b2 * cg**2
    return A4, A3, A2, A1, A0


@nb.njit(cache=True, inline="always")
def _distances_of_root(
    v: float, a2: float, b2: float, c2: float, ca: float, cb: float, cg: float, side2: float
) -> tuple[bool, float, float]:
    """The root ``v``'s distance s1 and ratio u = s2 / s1 (the better of two); False when it gives none."""
    if v <= 0:
        return False, 0.0, 0.0
    den = 1.0 + v * v - 2.0 * v * cb
    if den <= 1e-12:
        return False, 0.0, 0.0
    s1sq = b2 / den
    disc = cg * cg - 1.0 + c2 / s1sq
    if disc < -1e-6:
        return False, 0.0, 0.0
    root = np.sqrt(max(disc, 0.0))
    best_u = 0.0
    best_res = np.inf
    for sign in (1.0, -1.0):
        u = cg + sign * root
        res = abs(s1sq * (u * u + v * v - 2.0 * u * v * ca) - a2)
        if u > 0 and res < best_res:
            best_u = u
            best_res = res
    return best_res <= 1e-2 * side2 + 1e-9, s1sq, best_u


@nb.njit(cache=True, inline="always")
def _polish_distances(s: F64, a2: float, b2: float, c2: float, ca: float, cb: float, cg: float, side2: float) -> None:
    """Newton polish of the distances ``s`` (3,) on the law-of-cosines equations, in place."""
    for _ in range(3):
        f0 = s[0] ** 2 + s[1] ** 2 - 2 * s[0] * s[1] * cg - c2
        f1 = s[0] ** 2 + s[2] ** 2 - 2 * s[0] * s[2] * cb - b2
        f2 = s[1] ** 2 + s[2] ** 2 - 2 * s[1] * s[2] * ca - a2
        # Jacobian [[p, q, 0], [r, 0, u], [0, w, z]]; Cramer's rule
        jp = 2 * s[0] - 2 * s[1] * cg
        jq = 2 * s[1] - 2 * s[0] * cg
        jr = 2 * s[0] - 2 * s[2] * cb
        ju = 2 * s[2] - 2 * s[0] * cb
        jw = 2 * s[1] - 2 * s[2] * ca
        jz = 2 * s[2] - 2 * s[1] * ca
        det = -jp * ju * jw - jq * jr * jz
        if abs(det) <= 1e-14 * side2**1.5:
            break
        d0 = (-f0 * ju * jw - jq * (f1 * jz - ju * f2)) / det
        d1 = (jp * (f1 * jz - ju * f2) - f0 * jr * jz) / det
        d2 = (-jp * f1 * jw - jq * jr * f2 + f0 * jr * jw) / det
        s[0] -= d0
        s[1] -= d1
        s[2] -= d2


@nb.njit(cache=True)
def p3p_one(j: F64, P: F64, Rs: F64, ts: F64) -> int:
    """All valid P3P poses (at most 4) of three unit rays and world points; returns their number.

    Rays ``j`` (3, 3) and world points ``P`` (3, 3) -> ``Rs`` (4, 3, 3), ``ts`` (4, 3).
    """
    a2 = np.sum((P[1] - P[2]) ** 2)
    b2 = np.sum((P[0] - P[2]) ** 2)
    c2 = np.sum((P[0] - P[1]) ** 2)
    ca = np.sum(j[1] * j[2])
    cb = np.sum(j[0] * j[2])
    cg = np.sum(j[0] * j[1])
    side2 = max(a2, b2, c2)
    if _degenerate(j, P, b2, side2):
        return 0
    A4, A3, A2, A1, A0 = _grunert_quartic(a2, b2, c2, ca, cb, cg)
    sc = max(abs(A4), abs(A3), abs(A2), abs(A1), abs(A0))
    if sc <= 0 or abs(A4) < 1e-12 * sc:
        return 0
    roots = np.empty(4)
    n_roots = quartic_real_roots(A4, A3, A2, A1, A0, roots)
    Fp = np.empty((3, 3))
    if not _frame(P[0], P[1], P[2], Fp):
        return 0
    n = 0
    X = np.empty((3, 3))
    Fx = np.empty((3, 3))
    for q in range(n_roots):
        v = roots[q]
        ok, s1sq, best_u = _distances_of_root(v, a2, b2, c2, ca, cb, cg, side2)
        if not ok:
            continue
        s1 = np.sqrt(s1sq)
        s = np.array([s1, best_u * s1, v * s1])
        _polish_distances(s, a2, b2, c2, ca, cb, cg, side2)
        if not (s[0] > 0 and s[1] > 0 and s[2] > 0):
            continue
        for r in range(3):
            X[r] = s[r] * j[r]
        if not _frame(X[0], X[1], X[2], Fx):
            continue
        R = _mm3(Fx, Fp.T.copy())
        t = X[0] - _mv3(R, P[0])
        err = 0.0
        for r in range(3):
            d = _mv3(R, P[r]) + t - X[r]
            err = max(err, np.sqrt(np.sum(d * d)))
        if err > 1e-5 * np.sqrt(side2) + 1e-9:
            continue
        Rs[n] = R
        ts[n] = t
        n += 1
    return n


@nb.njit(cache=True)
def _ray_err(R: F64, t: F64, b: F64, p: F64) -> float:
    x0 = R[0, 0] * p[0] + R[0, 1] * p[1] + R[0, 2] * p[2] + t[0]
    x1 = R[1, 0] * p[0] + R[1, 1] * p[1] + R[1, 2] * p[2] + t[1]
    x2 = R[2, 0] * p[0] + R[2, 1] * p[1] + R[2, 2] * p[2] + t[2]
    if x0 * b[0] + x1 * b[1] + x2 * b[2] <= 0:
        return 4.0
    c0 = b[1] * x2 - b[2] * x1
    c1 = b[2] * x0 - b[0] * x2
    c2 = b[0] * x1 - b[1] * x0
    return (c0 * c0 + c1 * c1 + c2 * c2) / max(x0 * x0 + x1 * x1 + x2 * x2, 1e-30)


@nb.njit(cache=True)
def ransac_p3p(
    rays: F64, P: F64, thr2: float, max_samples: int, confidence: float, seed: int, order: NDArray[np.int64]
) -> tuple[F64, F64, int, int, int]:
    """MSAC over P3P minimal samples with the adaptive sample bound of the best inlier ratio.

    Each candidate is scored over the correspondences in ``order`` and abandoned as soon
    as its truncated cost exceeds the best one's (the cost only grows, so the winner is the
    same as with full scoring). Returns the best (R, t), its inlier count, the samples
    drawn and the poses scored."""
    m = rays.shape[0]
    np.random.seed(seed)
    Rs = np.empty((4, 3, 3))
    ts = np.empty((4, 3))
    best_R = np.eye(3)
    best_t = np.zeros(3)
    best_cost = np.inf
    best_n = 0
    needed = max_samples
    samples = 0
    poses = 0
    j = np.empty((3, 3))
    Q = np.empty((3, 3))
    log1c = np.log(1.0 - confidence) if confidence < 1.0 else -np.inf
    while samples < needed and samples < max_samples:
        i0 = np.random.randint(m)
        i1 = np.random.randint(m)
        i2 = np.random.randint(m)
        if i0 == i1 or i0 == i2 or i1 == i2:
            continue
        samples += 1
        for c in range(3):
            j[0, c] = rays[i0, c]
            j[1, c] = rays[i1, c]
            j[2, c] = rays[i2, c]
            Q[0, c] = P[i0, c]
            Q[1, c] = P[i1, c]
            Q[2, c] = P[i2, c]
        ns = p3p_one(j, Q, Rs, ts)
        for h in range(ns):
            poses += 1
            R = Rs[h]
            t = ts[h]
            cost = 0.0
            n_in = 0
            done = True
            for q in range(m):
                k = order[q]
                e = _ray_err(R, t, rays[k], P[k])
                if e < thr2:
                    cost += e
                    n_in += 1
                else:
                    cost += thr2
                if cost >= best_cost:
                    done = False
                    break
            if done:
                best_cost = cost
                best_n = n_in
                best_R = R.copy()
                best_t = t.copy()
                w = best_n / m
                p3 = w * w * w
                if p3 >= 1.0:
                    needed = 0
                elif p3 > 0 and confidence < 1.0:
                    needed = min(max_samples, int(np.ceil(log1c / np.log(1.0 - p3))))
    return best_R, best_t, best_n, samples, poses


@nb.njit(cache=True)
def inlier_mask(R: F64, t: F64, rays: F64, P: F64, thr2: float) -> NDArray[np.bool_]:
    """Correspondences whose ray error is below ``thr2``."""
    out = np.zeros(rays.shape[0], np.bool_)
    for k in range(rays.shape[0]):
        out[k] = _ray_err(R, t, rays[k], P[k]) < thr2
    return out


@nb.njit(cache=True)
def _tangent_residual(R: F64, t: F64, p: F64, e: F64) -> tuple[float, float, float, float, float, float]:
    """Transformed point x = R p + t and the tangent-plane residuals of its direction.

    Residuals (e0 . u, e1 . u) of u = x / |x| on the tangent basis ``e`` (6,) of the observed
    ray -> (r0, r1, x0, x1, x2, |x|).
    """
    x0 = R[0, 0] * p[0] + R[0, 1] * p[1] + R[0, 2] * p[2] + t[0]
    x1 = R[1, 0] * p[0] + R[1, 1] * p[1] + R[1, 2] * p[2] + t[1]
    x2 = R[2, 0] * p[0] + R[2, 1] * p[1] + R[2, 2] * p[2] + t[2]
    nx = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    if nx <= 0:
        return 0.0, 0.0, x0, x1, x2, 0.0
    r0 = (e[0] * x0 + e[1] * x1 + e[2] * x2) / nx
    r1 = (e[3] * x0 + e[4] * x1 + e[5] * x2) / nx
    return r0, r1, x0, x1, x2, nx


@nb.njit(cache=True)
def _huber_cost(R: F64, t: F64, P: F64, E: F64, c: float) -> float:
    """Huber cost (cutoff ``c``) of the tangent-plane ray errors (bases ``E`` (m, 6))."""
    tot = 0.0
    for k in range(P.shape[0]):
        r0, r1, _, _, _, nx = _tangent_residual(R, t, P[k], E[k])
        if nx <= 0:
            continue
        d = np.sqrt(r0 * r0 + r1 * r1)
        tot += 0.5 * d * d if d <= c else c * (d - 0.5 * c)
    return tot


@nb.njit(cache=True, inline="always")
def _tangent_bases(rays: F64) -> F64:
    """Per unit ray: two unit vectors (e1, e2) orthogonal to it and to each other -> (m, 6)."""
    m = rays.shape[0]
    E = np.empty((m, 6))
    for k in range(m):
        b0, b1, b2 = rays[k, 0], rays[k, 1], rays[k, 2]
        if abs(b0) < 0.9:
            a0, a1, a2 = 1.0, 0.0, 0.0
        else:
            a0, a1, a2 = 0.0, 1.0, 0.0
        ab = a0 * b0 + a1 * b1 + a2 * b2
        e0, e1, e2 = a0 - ab * b0, a1 - ab * b1, a2 - ab * b2
        ne = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        e0, e1, e2 = e0 / ne, e1 / ne, e2 / ne
        E[k, 0], E[k, 1], E[k, 2] = e0, e1, e2
        E[k, 3] = b1 * e2 - b2 * e1
        E[k, 4] = b2 * e0 - b0 * e2
        E[k, 5] = b0 * e1 - b1 * e0
    return E


@nb.njit(cache=True, inline="always")
def _rotation_of(om0: float, om1: float, om2: float) -> F64:
    """The rotation exp([omega]x) (Rodrigues; first order below 1e-12 rad)."""
    th = np.sqrt(om0 * om0 + om1 * om1 + om2 * om2)
    K = np.array([[0.0, -om2, om1], [om2, 0.0, -om0], [-om1, om0, 0.0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * _mm3(K, K)


@nb.njit(cache=True)
def refine_rays(R: F64, t: F64, rays: F64, P: F64, sigma: float, iterations: int) -> tuple[F64, F64]:
    """Gauss-Newton with Huber weights on the tangent-plane errors of unit rays -> (R, t).

    Huber cutoff 1.345 ``sigma`` (radians). A step that raises the robust cost stops it.
    """
    m = rays.shape[0]
    E = _tangent_bases(rays)  # tangent bases (e1, e2) of the observed rays
    c = 1.345 * sigma
    R = R.copy()
    t = t.copy()
    cur = _huber_cost(R, t, P, E, c)
    H = np.zeros((6, 6))
    g = np.zeros(6)
    J = np.zeros(6)
    for _ in range(iterations):
        H[:] = 0.0
        g[:] = 0.0
        for k in range(m):
            r0, r1, x0, x1, x2, nx = _tangent_residual(R, t, P[k], E[k])
            if nx <= 0:
                continue
            d = np.sqrt(r0 * r0 + r1 * r1)
            w = 1.0 if d <= c else c / d
            u0, u1, u2 = x0 / nx, x1 / nx, x2 / nx
            for a in range(2):
                ea0, ea1, ea2 = E[k, 3 * a], E[k, 3 * a + 1], E[k, 3 * a + 2]
                eu = ea0 * u0 + ea1 * u1 + ea2 * u2
                # d r_a / d x = (e - (e . u) u) / |x|; x moves by omega x x + v
                g0 = (ea0 - eu * u0) / nx
                g1 = (ea1 - eu * u1) / nx
                g2 = (ea2 - eu * u2) / nx
                J[0] = x1 * g2 - x2 * g1
                J[1] = x2 * g0 - x0 * g2
                J[2] = x0 * g1 - x1 * g0
                J[3] = g0
                J[4] = g1
                J[5] = g2
                r = r0 if a == 0 else r1
                for q in range(6):
                    g[q] += w * J[q] * r
                    for q2 in range(q, 6):
                        H[q, q2] += w * J[q] * J[q2]
        for q in range(6):
            for q2 in range(q):
                H[q, q2] = H[q2, q]
            H[q, q] *= 1.0 + 1e-9
        ok, sol = _solve_spd(H, g)
        if not ok:
            break
        delta = -sol
        th = np.sqrt(delta[0] * delta[0] + delta[1] * delta[1] + delta[2] * delta[2])
        dR = _rotation_of(delta[0], delta[1], delta[2])
        R_new = _mm3(dR, R)
        t_new = _mv3(dR, t) + delta[3:]
        new = _huber_cost(R_new, t_new, P, E, c)
        if new > cur:
            break
        R, t = R_new, t_new
        done = cur - new <= 1e-9 * max(cur, 1e-30)
        cur = new
        if done or th < 1e-10:
            break
    return R, t
