"""Inner loops of the sequential Givens estimator (seed 000: Gruen & Kersten).

Three kernels on an upper-triangular factor ``R`` (first ``n`` rows/columns used) with its
right-hand side ``d`` and an optional coupling block ``C`` (the columns that follow ``R``'s own
columns, first ``nc`` used; the point rows of the bundle carry the frame columns there):

- :func:`rows_update` annihilates ``m`` new rows ``[Z | ZC | zl]`` with Givens rotations
  (Lawson & Hanson); what is left in ``zl`` is the rows' contribution to ``vᵀPv``.
- :func:`rows_downdate` removes ``m`` rows with mixed hyperbolic rotations (Bojanczyk, Brent,
  van Dooren, de Hoog 1987), refusing (returning ``False``) when a pivot's hyperbolic cosine²
  ``1 - (z_k / r_kk)²`` falls below ``min_cos2``: the caller then re-factorises.
- :func:`retriangularize` restores triangularity after columns were cut out of ``R``.

The loops are compiled by numba (a required dependency; an earlier numpy fallback never ran
and was removed).
"""

from __future__ import annotations

import math

import numba
import numpy as np


def _rows_update_py(R, d, C, Z, ZC, zl, n, nc):  # type: ignore[no-untyped-def]
    m = Z.shape[0]
    cs = np.empty(m)
    sn = np.empty(m)
    for k in range(n):
        any_active = False
        for r in range(m):
            a = Z[r, k]
            if a == 0.0:
                cs[r] = 1.0
                sn[r] = 0.0
                continue
            any_active = True
            rkk = R[k, k]
            h = math.hypot(rkk, a)
            cs[r] = rkk / h
            sn[r] = a / h
            R[k, k] = h
            Z[r, k] = 0.0
        if not any_active:
            continue
        if m == 2:  # an image point: both coordinates in one sweep over the row
            c0, s0, c1, s1 = cs[0], sn[0], cs[1], sn[1]
            for j in range(k + 1, n):
                t = R[k, j]
                u0 = Z[0, j]
                u1 = Z[1, j]
                t1 = c0 * t + s0 * u0
                Z[0, j] = c0 * u0 - s0 * t
                R[k, j] = c1 * t1 + s1 * u1
                Z[1, j] = c1 * u1 - s1 * t1
            for j in range(nc):
                t = C[k, j]
                u0 = ZC[0, j]
                u1 = ZC[1, j]
                t1 = c0 * t + s0 * u0
                ZC[0, j] = c0 * u0 - s0 * t
                C[k, j] = c1 * t1 + s1 * u1
                ZC[1, j] = c1 * u1 - s1 * t1
        else:
            for j in range(k + 1, n):
                t = R[k, j]
                for r in range(m):
                    u = Z[r, j]
                    Z[r, j] = cs[r] * u - sn[r] * t
                    t = cs[r] * t + sn[r] * u
                R[k, j] = t
            for j in range(nc):
                t = C[k, j]
                for r in range(m):
                    u = ZC[r, j]
                    ZC[r, j] = cs[r] * u - sn[r] * t
                    t = cs[r] * t + sn[r] * u
                C[k, j] = t
        t = d[k]
        for r in range(m):
            u = zl[r]
            zl[r] = cs[r] * u - sn[r] * t
            t = cs[r] * t + sn[r] * u
        d[k] = t


def _rows_downdate_py(R, d, C, Z, ZC, zl, n, nc, min_cos2):  # type: ignore[no-untyped-def]
    m = Z.shape[0]
    for k in range(n):
        for r in range(m):
            a = Z[r, k]
            if a == 0.0:
                continue
            rkk = R[k, k]
            if rkk == 0.0:
                return False
            t = a / rkk
            c2 = 1.0 - t * t
            if c2 < min_cos2:
                return False
            ch = math.sqrt(c2)
            R[k, k] = rkk * ch
            Z[r, k] = 0.0
            for j in range(k + 1, n):
                rk = (R[k, j] - t * Z[r, j]) / ch
                Z[r, j] = ch * Z[r, j] - t * rk
                R[k, j] = rk
            for j in range(nc):
                rk = (C[k, j] - t * ZC[r, j]) / ch
                ZC[r, j] = ch * ZC[r, j] - t * rk
                C[k, j] = rk
            rk = (d[k] - t * zl[r]) / ch
            zl[r] = ch * zl[r] - t * rk
            d[k] = rk
    return True


def _retriangularize_py(T, dT, band):  # type: ignore[no-untyped-def]
    rows, cols = T.shape
    for k in range(cols):
        for i in range(1, band + 1):
            rr = k + i
            if rr >= rows:
                break
            a = T[rr, k]
            if a == 0.0:
                continue
            rkk = T[k, k]
            h = math.hypot(rkk, a)
            c = rkk / h
            s = a / h
            T[k, k] = h
            T[rr, k] = 0.0
            for j in range(k + 1, cols):
                t = T[k, j]
                u = T[rr, j]
                T[k, j] = c * t + s * u
                T[rr, j] = c * u - s * t
            t = dT[k]
            u = dT[rr]
            dT[k] = c * t + s * u
            dT[rr] = c * u - s * t


def _solve_py(Rg, dg, n, Rpp, Rpf, dp, P, psize, pfirst, xg, xp, rel_tol):  # type: ignore[no-untyped-def]
    """Back substitution of the structured R x = d; returns -1 or the first singular column.

    Singular columns are numbered ``k`` (global) or ``n + slot * smax + i`` (local).
    """
    smax = Rpp.shape[1]
    scale = 0.0
    for k in range(n):
        a = abs(Rg[k, k])
        if a > scale:
            scale = a
    for k in range(n - 1, -1, -1):
        rkk = Rg[k, k]
        if abs(rkk) <= rel_tol * scale or rkk == 0.0:
            return k
        acc = dg[k]
        for j in range(k + 1, n):
            acc -= Rg[k, j] * xg[j]
        xg[k] = acc / rkk
    for p in range(P):
        s = psize[p]
        pscale = 0.0
        for i in range(s):
            a = abs(Rpp[p, i, i])
            if a > pscale:
                pscale = a
        j0 = min(pfirst[p], n)
        if s == 3:  # a point: its three coupling rows in one pass over x_g
            y0 = dp[p, 0]
            y1 = dp[p, 1]
            y2 = dp[p, 2]
            for j in range(j0, n):
                xj = xg[j]
                y0 -= Rpf[p, 0, j] * xj
                y1 -= Rpf[p, 1, j] * xj
                y2 -= Rpf[p, 2, j] * xj
            ys = (y0, y1, y2)
        else:
            ys = (0.0, 0.0, 0.0)
        for i in range(s - 1, -1, -1):
            rii = Rpp[p, i, i]
            if abs(rii) <= rel_tol * pscale or rii == 0.0:
                return n + p * smax + i
            if s == 3:
                acc = ys[i]
            else:
                acc = dp[p, i]
                for j in range(j0, n):
                    acc -= Rpf[p, i, j] * xg[j]
            for j in range(i + 1, s):
                acc -= Rpp[p, i, j] * xp[p, j]
            xp[p, i] = acc / rii
        for i in range(s, smax):
            xp[p, i] = 0.0
    return -1


_jit = numba.njit(cache=True, nogil=True)
rows_update = _jit(_rows_update_py)
rows_downdate = _jit(_rows_downdate_py)
retriangularize = _jit(_retriangularize_py)
solve_structured = numba.njit(cache=True, nogil=True, fastmath=True)(_solve_py)
KERNELS = "numba"
