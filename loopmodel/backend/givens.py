"""Sequential least squares with Givens transformations (seed 000, Gruen & Kersten 1995).

Gauss–Markov model ``l - e = A x``, weights ``P``. The estimator keeps the orthogonal form
``Qᵀ[√P A | √P l] = [[R, d], [0, d_r]]`` (Lawson & Hanson): ``R x̂ = d`` by back substitution
and ``vᵀPv = d_rᵀ d_r``. Every new observation row is annihilated against ``R`` by Givens
rotations (updating ``R``, ``d`` and ``vᵀPv`` in place), a deleted one is removed by mixed
hyperbolic rotations (downdating) with a safety check and a re-factorisation fallback.

Structure (seed eq. 10–11): parameters are either *local* blocks (object points, 3 columns)
or *global* blocks (exterior orientations, 6 columns). Local blocks come first in the column
order and are reduced point by point, so ``R`` is

    [ R_pp(1)            R_pf(1) ]      R_pp(j): s x s upper triangular (s <= 3)
    [        ...           ...   ]      R_pf(j): s x n_f coupling to the global columns
    [            R_pp(P) R_pf(P) ]
    [                    R_ff    ]      R_ff: dense upper triangular over global columns

An observation may touch at most one local block and any global blocks. Inserting an image
point therefore rotates 3 point rows and then the rows of ``R_ff`` from the first global column
the point's coupling row touches (the first frame that saw the point) onward; nothing else is
read or written. Global columns are kept in insertion order (frames chronologically).

Observations are stored (whitened) so that they can be deleted, tested (data snooping),
re-linearised and re-factorised.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import qr as _qr
from scipy.linalg import solve_triangular

from loopmodel.backend import _givens_kernels as _k
from loopmodel.errors import EstimationError

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
KERNELS = _k.KERNELS
_NO_COLUMN = np.int64(2**62)


@dataclass
class _Block:
    name: Hashable
    size: int
    local: bool
    slot: int = -1  # local blocks: slot in the point arrays
    start: int = -1  # global blocks: first column in R_ff


@dataclass
class _Obs:
    """One stored observation (whitened: rows of √P A and √P l)."""

    local: Hashable | None
    a_local: F64 | None  # m x s
    a_global: dict[Hashable, F64] = field(default_factory=dict)  # name -> m x size
    l: F64 = field(default_factory=lambda: np.zeros(0))

    @property
    def rows(self) -> int:
        return int(self.l.shape[0])


def _whitener(m: int, sigma: ArrayLike | None, weight: ArrayLike | None) -> F64:
    """m x m (or length-m) factor W with WᵀW = P."""
    if sigma is not None and weight is not None:
        raise EstimationError("give either sigma or weight for an observation, not both")
    if weight is None:
        if sigma is None:
            return np.ones(m)
        if isinstance(sigma, float | int):
            if not (sigma > 0 and math.isfinite(sigma)):
                raise EstimationError(f"observation sigma must be positive and finite, got {sigma}")
            return np.full(m, 1.0 / sigma)
        s = np.broadcast_to(np.asarray(sigma, dtype=float), (m,)).copy()
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise EstimationError(f"observation sigma must be positive and finite, got {s}")
        return 1.0 / s
    P = np.asarray(weight, dtype=float)
    if P.ndim < 2:
        w = np.broadcast_to(P, (m,)).copy()
        if not np.all(np.isfinite(w)) or np.any(w <= 0):
            raise EstimationError(f"observation weights must be positive and finite, got {w}")
        return np.sqrt(w)
    if P.shape != (m, m):
        raise EstimationError(f"weight matrix must be {m}x{m}, got {P.shape}")
    try:
        L = np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise EstimationError("weight matrix is not positive definite") from None
    return np.ascontiguousarray(L.T)


def _apply_w(W: F64, M: F64) -> F64:
    if W.ndim == 1:
        return W * M if M.ndim == 1 else W[:, None] * M
    return W @ M


class GivensEstimator:
    """Sequential Gauss–Markov estimator on a Givens-updated triangular factor.

    Parameters are named blocks (any hashable name). ``local=True`` blocks (object points)
    are eliminated first, block by block; an observation may involve at most one of them.
    Observations are rows of ``A`` (per block) with ``l``; their weights come from ``sigma``
    (standard deviations) or ``weight`` (the weight matrix ``P`` or its diagonal).
    """

    def __init__(self, local_block_max: int = 3, min_downdate_cos2: float = 1e-6) -> None:
        if local_block_max < 1:
            raise EstimationError("local_block_max must be at least 1")
        self.smax = int(local_block_max)
        self.min_downdate_cos2 = float(min_downdate_cos2)
        self._blocks: dict[Hashable, _Block] = {}
        self._global_order: list[Hashable] = []
        self._n = 0  # active global columns
        self._gcap = 0
        self._pcap = 0
        self._free_slots: list[int] = []
        self._slot_used = 0  # high-water mark of local slots
        self._slot_name: list[Hashable | None] = []
        self._Rg = np.zeros((0, 0))
        self._dg = np.zeros(0)
        self._Rpp = np.zeros((0, self.smax, self.smax))
        self._Rpf = np.zeros((0, self.smax, 0))
        self._dp = np.zeros((0, self.smax))
        self._psize = np.zeros(0, dtype=np.int64)
        self._pfirst = np.zeros(0, dtype=np.int64)  # first non-zero column of R_pf(j)
        self._rss = 0.0
        self._obs: dict[int, _Obs] = {}
        self._next_id = 0
        self._n_rows = 0
        self._x_cache: tuple[F64, F64] | None = None
        self._empty_c = np.zeros((self.smax, 0))
        self._empty_z = np.zeros((1, 0))
        self.n_refactorizations = 0
        self.n_downdate_fallbacks = 0
        self._grow_global(16)
        self._grow_local(16)

    # ------------------------------------------------------------------ storage
    def _grow_global(self, need: int) -> None:
        if need <= self._gcap:
            return
        cap = max(need, 2 * self._gcap, 16)
        Rg = np.zeros((cap, cap))
        Rg[: self._n, : self._n] = self._Rg[: self._n, : self._n]
        dg = np.zeros(cap)
        dg[: self._n] = self._dg[: self._n]
        Rpf = np.zeros((self._pcap, self.smax, cap))
        Rpf[:, :, : self._n] = self._Rpf[:, :, : self._n]
        self._Rg, self._dg, self._Rpf, self._gcap = Rg, dg, Rpf, cap

    def _grow_local(self, need: int) -> None:
        if need <= self._pcap:
            return
        cap = max(need, 2 * self._pcap, 16)
        Rpp = np.zeros((cap, self.smax, self.smax))
        Rpp[:, np.arange(self.smax), np.arange(self.smax)] = 1.0  # unused rows: identity
        Rpp[: self._pcap] = self._Rpp
        Rpf = np.zeros((cap, self.smax, self._gcap))
        Rpf[: self._pcap] = self._Rpf
        dp = np.zeros((cap, self.smax))
        dp[: self._pcap] = self._dp
        psize = np.zeros(cap, dtype=np.int64)
        psize[: self._pcap] = self._psize
        pfirst = np.full(cap, _NO_COLUMN, dtype=np.int64)
        pfirst[: self._pcap] = self._pfirst
        self._pfirst = pfirst
        self._slot_name.extend([None] * (cap - self._pcap))
        self._Rpp, self._Rpf, self._dp, self._psize, self._pcap = Rpp, Rpf, dp, psize, cap

    def _reset_slot(self, j: int) -> None:
        self._pfirst[j] = _NO_COLUMN
        self._Rpp[j] = np.eye(self.smax)
        self._Rpf[j] = 0.0
        self._dp[j] = 0.0

    # --------------------------------------------------------------- parameters
    def add_parameters(self, name: Hashable, size: int, local: bool = False) -> None:
        """Add a parameter block (new zero columns of ``R``, zeros of ``d``; seed eq. 16)."""
        if name in self._blocks:
            raise EstimationError(f"parameter block {name!r} already exists")
        size = int(size)
        if size < 1:
            raise EstimationError(f"parameter block {name!r}: size must be positive")
        if local:
            if size > self.smax:
                raise EstimationError(f"local parameter block {name!r} has {size} columns, at most {self.smax}")
            if self._free_slots:
                j = self._free_slots.pop()
            else:
                j = self._slot_used
                self._slot_used += 1
                self._grow_local(self._slot_used)
            self._reset_slot(j)
            for i in range(size):
                self._Rpp[j, i, i] = 0.0
            self._psize[j] = size
            self._slot_name[j] = name
            self._blocks[name] = _Block(name, size, True, slot=j)
        else:
            self._grow_global(self._n + size)
            self._blocks[name] = _Block(name, size, False, start=self._n)
            self._global_order.append(name)
            self._n += size
        self._x_cache = None

    def has_parameters(self, name: Hashable) -> bool:
        """Whether a parameter block of that name is in the estimator."""
        return name in self._blocks

    @property
    def n_parameters(self) -> int:
        """Number of unknowns u."""
        return sum(b.size for b in self._blocks.values())

    @property
    def n_observations(self) -> int:
        """Number of observation rows n (each coordinate counts)."""
        return self._n_rows

    @property
    def redundancy(self) -> int:
        """r = n - u."""
        return self._n_rows - self.n_parameters

    def parameter_names(self) -> list[Hashable]:
        """Names of the blocks in column order (local blocks first, then global)."""
        loc = [self._slot_name[j] for j in range(self._slot_used) if self._slot_name[j] is not None]
        return [*loc, *self._global_order]

    def block_size(self, name: Hashable) -> int:
        """Number of columns of a block."""
        return self._block(name).size

    def _block(self, name: Hashable) -> _Block:
        try:
            return self._blocks[name]
        except KeyError:
            raise EstimationError(f"unknown parameter block {name!r}") from None

    def delete_parameters(self, name: Hashable) -> None:
        """Cut a block's columns out of ``R`` and re-triangularise (Lawson & Hanson).

        The parameters are removed from the model: observations that involved them keep
        their other coefficients (the removed parameters are held at their reference value).
        Delete a point's observations first to remove the point entirely.
        """
        blk = self._block(name)
        for rec in self._obs.values():
            if blk.local and rec.local == name:
                rec.local, rec.a_local = None, None
            elif not blk.local:
                rec.a_global.pop(name, None)
        n = self._n
        if blk.local:
            j, s = blk.slot, blk.size
            # the point's s rows lose their leading columns and become rows of the frame part
            Z = np.ascontiguousarray(self._Rpf[j, :s, :n])
            zl = self._dp[j, :s].copy()
            _k.rows_update(self._Rg, self._dg, self._empty_c, Z, self._empty_z, zl, n, 0)
            self._rss += float(zl @ zl)
            self._reset_slot(j)
            self._psize[j] = 0
            self._slot_name[j] = None
            self._free_slots.append(j)
        else:
            c, s = blk.start, blk.size
            keep = np.r_[0:c, c + s : n]
            M = self._Rg[:n, keep]  # n x (n - s), rows c.. have s sub-diagonals
            T = np.ascontiguousarray(M[c:, c:])
            dT = self._dg[c:n].copy()
            _k.retriangularize(T, dT, s)
            m_new = n - s
            Rg_new = np.zeros_like(self._Rg)
            Rg_new[:c, :m_new] = M[:c]
            Rg_new[c:m_new, c:m_new] = T[: m_new - c]
            dg_new = np.zeros_like(self._dg)
            dg_new[:c] = self._dg[:c]
            dg_new[c:m_new] = dT[: m_new - c]
            self._rss += float(dT[m_new - c :] @ dT[m_new - c :])
            self._Rg, self._dg = Rg_new, dg_new
            pf = self._pfirst
            pf[:] = np.where(pf >= c + s, pf - s, np.where(pf >= c, c, pf))
            pf[pf > m_new] = _NO_COLUMN
            self._Rpf[:, :, c:m_new] = self._Rpf[:, :, c + s : n]
            self._Rpf[:, :, m_new:n] = 0.0
            self._global_order.remove(name)
            self._n = m_new
            for b in self._blocks.values():
                if not b.local and b.start > c:
                    b.start -= s
        del self._blocks[name]
        self._x_cache = None

    # ------------------------------------------------------------- observations
    def _prepare(self, coeffs: Mapping[Hashable, ArrayLike], l: ArrayLike, sigma: Any, weight: Any) -> _Obs:
        lv = np.atleast_1d(np.asarray(l, dtype=float)).reshape(-1)
        m = lv.shape[0]
        if m == 0:
            raise EstimationError("an observation needs at least one row")
        if not np.all(np.isfinite(lv)):
            raise EstimationError("observation values must be finite")
        W = _whitener(m, sigma, weight)
        rec = _Obs(local=None, a_local=None, l=_apply_w(W, lv))
        if not coeffs:
            raise EstimationError("an observation needs coefficients of at least one block")
        total = 0.0
        for name, a in coeffs.items():
            blk = self._block(name)
            A = np.asarray(a, dtype=float)
            if A.shape != (m, blk.size):
                A = A.reshape(m, -1) if A.size else np.zeros((m, 0))
            if A.shape != (m, blk.size):
                raise EstimationError(f"coefficients of block {name!r} must be {m}x{blk.size}, got {A.shape}")
            Aw = _apply_w(W, A)
            total += float(Aw.sum())
            if blk.local:
                if rec.local is not None:
                    raise EstimationError(f"an observation may involve one local block; got {rec.local!r} and {name!r}")
                rec.local, rec.a_local = name, Aw
            else:
                rec.a_global[name] = Aw
        if not math.isfinite(total):
            raise EstimationError(f"coefficients of {list(coeffs)!r} are not finite")
        return rec

    def _rows_of(self, rec: _Obs) -> tuple[int, F64, int, F64, F64]:
        """(slot, Z_local, size, Z_global (m x n), zl) working copies of a stored observation."""
        m = rec.rows
        Zg = np.zeros((m, self._n))
        for name, A in rec.a_global.items():
            b = self._blocks[name]
            Zg[:, b.start : b.start + b.size] = A
        if rec.local is not None and rec.a_local is not None:
            b = self._blocks[rec.local]
            return b.slot, np.array(rec.a_local, order="C"), b.size, Zg, rec.l.copy()
        return -1, np.zeros((m, 0)), 0, Zg, rec.l.copy()

    def add_observation(
        self,
        coeffs: Mapping[Hashable, ArrayLike],
        l: ArrayLike,
        sigma: ArrayLike | None = None,
        weight: ArrayLike | None = None,
    ) -> int:
        """Add observation rows ``coeffs[block] (m x size)`` with values ``l`` (m); returns its id.

        The rows are annihilated against ``R`` by Givens rotations (seed eq. 16–19, 22).
        """
        rec = self._prepare(coeffs, l, sigma, weight)
        j, Zl, s, Zg, zl = self._rows_of(rec)
        n = self._n
        if j >= 0:
            self._touch(j, rec)
            _k.rows_update(self._Rpp[j], self._dp[j], self._Rpf[j], Zl, Zg, zl, s, n)
        _k.rows_update(self._Rg, self._dg, self._empty_c, Zg, self._empty_z, zl, n, 0)
        self._rss += float(zl @ zl)
        oid = self._next_id
        self._next_id += 1
        self._obs[oid] = rec
        self._n_rows += rec.rows
        self._x_cache = None
        return oid

    def delete_observation(self, obs_id: int) -> None:
        """Remove an observation by hyperbolic rotations (downdating).

        Raises :class:`EstimationError` for an id that is not (or no longer) in the estimator.
        If a hyperbolic pivot is unsafe (cos² below ``min_downdate_cos2``) the factor is rebuilt
        from the stored observations instead (:meth:`refactorize`).
        """
        rec = self._obs.pop(obs_id, None) if isinstance(obs_id, int | np.integer) else None
        if rec is None:
            raise EstimationError(f"observation {obs_id!r} was never added or is already deleted")
        self._n_rows -= rec.rows
        self._x_cache = None
        j, Zl, s, Zg, zl = self._rows_of(rec)
        n = self._n
        ok = True
        if j >= 0:
            self._touch(j, rec)
            ok = _k.rows_downdate(self._Rpp[j], self._dp[j], self._Rpf[j], Zl, Zg, zl, s, n, self.min_downdate_cos2)
        if ok:
            ok = _k.rows_downdate(
                self._Rg,
                self._dg,
                self._empty_c,
                Zg,
                self._empty_z,
                zl,
                n,
                0,
                self.min_downdate_cos2,
            )
        if ok:
            rss = self._rss - float(zl @ zl)
            if rss < -1e-9 * max(self._rss, 1.0):
                ok = False
            else:
                self._rss = max(rss, 0.0)
        if not ok:
            logger.debug("downdate of observation %s unsafe; re-factorising", obs_id)
            self.n_downdate_fallbacks += 1
            self.refactorize()

    def _touch(self, j: int, rec: _Obs) -> None:
        for name in rec.a_global:
            st = self._blocks[name].start
            if st < self._pfirst[j]:
                self._pfirst[j] = st

    def observation_ids(self) -> list[int]:
        """Ids of the observations currently in the estimator."""
        return list(self._obs)

    def has_observation(self, obs_id: int) -> bool:
        """Whether the observation id is active."""
        return obs_id in self._obs

    def observation_rows(self, obs_id: int) -> int:
        """Number of rows (coordinates) of an observation."""
        return self._get_obs(obs_id).rows

    def _get_obs(self, obs_id: int) -> _Obs:
        try:
            return self._obs[obs_id]
        except (KeyError, TypeError):
            raise EstimationError(f"unknown observation {obs_id!r}") from None

    def replace_observation(
        self,
        obs_id: int,
        coeffs: Mapping[Hashable, ArrayLike],
        l: ArrayLike,
        sigma: ArrayLike | None = None,
        weight: ArrayLike | None = None,
        refactor: bool = True,
    ) -> None:
        """Replace an observation's rows (re-linearisation); re-factorises unless told not to."""
        old = self._get_obs(obs_id)
        rec = self._prepare(coeffs, l, sigma, weight)
        if rec.rows != old.rows:
            raise EstimationError(f"observation {obs_id}: replacement has a different row count")
        self._obs[obs_id] = rec
        if refactor:
            self.refactorize()

    def update_observation(
        self,
        obs_id: int,
        coeffs: Mapping[Hashable, ArrayLike],
        l: ArrayLike,
        sigma: ArrayLike | None = None,
        weight: ArrayLike | None = None,
    ) -> None:
        """Replace an observation's rows in the factor (local re-linearisation), keeping its id.

        The new rows are added first (Givens), then the old ones removed (hyperbolic), which
        keeps the downdate well conditioned.
        """
        self._get_obs(obs_id)
        new_id = self.add_observation(coeffs, l, sigma=sigma, weight=weight)
        self.delete_observation(obs_id)
        self._obs[obs_id] = self._obs.pop(new_id)

    # ------------------------------------------------------------ factorisation
    def refactorize(self) -> None:
        """Rebuild ``R``, ``d`` and ``vᵀPv`` from the stored observations (batch QR).

        Point blocks are factorised one by one (QR of the rows that involve the point), their
        left-over rows and the frame-only rows then by a chunked QR of the frame part.
        """
        n = self._n
        self.n_refactorizations += 1
        self._Rg[:] = 0.0
        self._dg[:] = 0.0
        by_slot: dict[int, list[_Obs]] = {}
        global_rows: list[F64] = []
        for rec in self._obs.values():
            if rec.local is not None:
                by_slot.setdefault(self._blocks[rec.local].slot, []).append(rec)
            else:
                _, _, _, Zg, zl = self._rows_of(rec)
                global_rows.append(np.column_stack([Zg, zl]))
        for j in range(self._slot_used):
            if self._slot_name[j] is None:
                continue
            s = int(self._psize[j])
            self._reset_slot(j)
            for i in range(s):
                self._Rpp[j, i, i] = 0.0
            recs = by_slot.get(j)
            if not recs:
                continue
            used = sorted({nm for r in recs for nm in r.a_global}, key=lambda nm: self._blocks[nm].start)
            cols = (
                np.concatenate(
                    [np.arange(self._blocks[nm].start, self._blocks[nm].start + self._blocks[nm].size) for nm in used]
                )
                if used
                else np.zeros(0, dtype=int)
            )
            nu = cols.size
            M = np.vstack(
                [np.column_stack([r.a_local, self._rows_of(r)[3][:, cols], r.l]) for r in recs]  # type: ignore[list-item]
            )
            Rj = _qr(M, mode="r", check_finite=False)[0]
            k = min(s, Rj.shape[0])
            sign = np.where(np.diag(Rj[:k, :k]) < 0, -1.0, 1.0)
            Rj[:k] *= sign[:, None]
            self._Rpp[j, :k, :s] = Rj[:k, :s]
            self._Rpf[j][:k, cols] = Rj[:k, s : s + nu]
            self._pfirst[j] = int(cols.min()) if nu else _NO_COLUMN
            self._dp[j, :k] = Rj[:k, s + nu]
            if Rj.shape[0] > s:
                G = np.zeros((Rj.shape[0] - s, n + 1))
                G[:, cols] = Rj[s:, s : s + nu]
                G[:, n] = Rj[s:, s + nu]
                global_rows.append(G)
        acc = np.zeros((0, n + 1))
        chunk: list[F64] = []
        count = 0
        for g in global_rows:
            chunk.append(g)
            count += g.shape[0]
            if count >= 2048:
                acc = _qr(np.vstack([acc, *chunk]), mode="r", check_finite=False)[0][: n + 1]
                chunk, count = [], 0
        if chunk:
            acc = _qr(np.vstack([acc, *chunk]), mode="r", check_finite=False)[0][: n + 1]
        k = min(n, acc.shape[0])
        sign = np.where(np.diag(acc[:k, :k]) < 0, -1.0, 1.0)
        acc[:k] *= sign[:, None]
        self._Rg[:k, :n] = acc[:k, :n]
        self._dg[:k] = acc[:k, n]
        self._rss = float(acc[n, n] ** 2) if acc.shape[0] > n else 0.0
        self._x_cache = None

    # ----------------------------------------------------------------- solution
    def _singular(self, col: int) -> EstimationError:
        n = self._n
        if col < n:
            name = next(b.name for b in self._blocks.values() if not b.local and b.start <= col < b.start + b.size)
        else:
            name = self._slot_name[(col - n) // self.smax]
        return EstimationError(f"system is singular: parameter block {name!r} is not determined")

    def _check_regular(self) -> None:
        self._solve()

    def _solve(self) -> tuple[F64, F64]:
        if self._x_cache is not None:
            return self._x_cache
        xg, xp = self._back_substitute(self._slot_used)
        self._x_cache = (xp, xg)
        return self._x_cache

    def _back_substitute(self, n_local: int) -> tuple[F64, F64]:
        """x̂ of the global blocks and of the first ``n_local`` local slots (R x = d)."""
        xg = np.zeros(self._n)
        xp = np.zeros((n_local, self.smax))
        bad = _k.solve_structured(
            self._Rg, self._dg, self._n, self._Rpp, self._Rpf, self._dp, n_local,
            self._psize, self._pfirst, xg, xp, 1e-13,
        )  # fmt: skip
        if bad >= 0:
            raise self._singular(int(bad))
        return xg, xp

    def partial_solution(self, local_name: Hashable | None = None) -> tuple[F64, F64 | None]:
        """x̂ of all global blocks and (optionally) of one local block, without the other points.

        The cheap update an online system needs after an insertion (current poses and the
        point just observed); the other points follow on demand (:meth:`solution`).
        """
        if self._x_cache is not None:
            xp_all, xg = self._x_cache
            if local_name is None:
                return xg, None
            b = self._block(local_name)
            return xg, xp_all[b.slot, : b.size]
        n = self._n
        xg, _ = self._back_substitute(0)
        if local_name is None:
            return xg, None
        b = self._block(local_name)
        if not b.local:
            raise EstimationError(f"parameter block {local_name!r} is not a local block")
        s, j = b.size, b.slot
        y = self._dp[j, :s] - self._Rpf[j, :s, :n] @ xg
        return xg, solve_triangular(self._Rpp[j, :s, :s], y, check_finite=False)

    def solution(self, names: Iterable[Hashable] | None = None) -> dict[Hashable, F64]:
        """Estimated parameters x̂ per block (copies)."""
        xp, xg = self._solve()
        out: dict[Hashable, F64] = {}
        for name in self.parameter_names() if names is None else names:
            b = self._block(name)
            out[name] = xp[b.slot, : b.size].copy() if b.local else xg[b.start : b.start + b.size].copy()
        return out

    def solution_vector(self) -> F64:
        """x̂ in the order of :meth:`parameter_names`."""
        sol = self.solution()
        return np.concatenate([sol[k] for k in self.parameter_names()]) if sol else np.zeros(0)

    def block_solution(self, name: Hashable) -> F64:
        """x̂ of one block (no copy of the rest)."""
        xp, xg = self._solve()
        b = self._block(name)
        return xp[b.slot, : b.size] if b.local else xg[b.start : b.start + b.size]

    def vtpv(self) -> float:
        """Weighted sum of squared residuals vᵀPv (kept up to date by the rotations)."""
        return self._rss

    def variance_factor(self) -> float:
        """A-posteriori variance factor σ̂0² = vᵀPv / r (NaN when r <= 0)."""
        r = self.redundancy
        return self._rss / r if r > 0 else float("nan")

    # ------------------------------------------------------------- cofactors
    def _forward_global(self, B: F64) -> F64:
        n = self._n
        if n == 0:
            return np.zeros((0, B.shape[1]))
        return solve_triangular(self._Rg[:n, :n], B, trans="T", check_finite=False)

    def cofactor(self, selected: Sequence[Hashable]) -> F64:
        """Cofactor matrix Q_xx = (AᵀPA)⁻¹ of the selected blocks (in the given order).

        Computed as YᵀY with Y = R⁻ᵀ E_S (forward substitution for the selected unit vectors
        only), never forming the full inverse.
        """
        self._check_regular()
        n = self._n
        cols: list[tuple[_Block, int]] = []
        for name in selected:
            b = self._block(name)
            cols.extend((b, i) for i in range(b.size))
        k = len(cols)
        Bg = np.zeros((n, k))
        Yloc: dict[int, F64] = {}
        for c, (b, i) in enumerate(cols):
            if b.local:
                s = b.size
                e = np.zeros(s)
                e[i] = 1.0
                yl = solve_triangular(self._Rpp[b.slot, :s, :s], e, trans="T", check_finite=False)
                Yloc.setdefault(b.slot, np.zeros((s, k)))[:, c] = yl
                Bg[:, c] = -self._Rpf[b.slot, :s, :n].T @ yl
            else:
                Bg[b.start + i, c] = 1.0
        Yg = self._forward_global(Bg)
        Q = Yg.T @ Yg
        for Y in Yloc.values():
            Q += Y.T @ Y
        return Q

    # ------------------------------------------------- residuals and redundancy
    def residual_rows(self, ids: Sequence[int], leverage: bool = True) -> tuple[F64, F64, list[int]]:
        """For the rows of the observations ``ids``, concatenated.

        The whitened residuals v = a x̂ - l, the leverages a Q_xx aᵀ = ||R⁻ᵀ aᵀ||² (Gruen's unit
        observation vector method: forward substitutions with the rows, never the full cofactor
        matrix), and the number of rows of each observation.

        ``leverage=False`` skips the forward substitutions (the second array is then zeros).
        """
        need_q = leverage
        xp, xg = self._solve()
        n = self._n
        recs = [self._get_obs(i) for i in ids]
        counts = [r.rows for r in recs]
        total = sum(counts)
        v = np.zeros(total)
        pn = np.zeros(total)
        chunk_rows = max(1, 1_000_000 // max(n, 1)) if need_q else total + 1
        row = 0
        start = 0
        while start < len(recs):
            stop, rows = start, 0
            while stop < len(recs) and (rows == 0 or rows + counts[stop] <= chunk_rows):
                rows += counts[stop]
                stop += 1
            B = np.zeros((n, rows if need_q else 0))
            r0 = 0
            loc_rows: list[int] = []
            loc_slot: list[int] = []
            loc_a: list[F64] = []
            for rec in recs[start:stop]:
                m = rec.rows
                vv = -rec.l.copy()
                for name, A in rec.a_global.items():
                    b = self._blocks[name]
                    if need_q:
                        B[b.start : b.start + b.size, r0 : r0 + m] = A.T
                    vv += A @ xg[b.start : b.start + b.size]
                if rec.local is not None and rec.a_local is not None:
                    b = self._blocks[rec.local]
                    s = b.size
                    vv += rec.a_local @ xp[b.slot, :s]
                    if need_q:
                        pad = np.zeros((m, self.smax))
                        pad[:, :s] = rec.a_local
                        loc_a.append(pad)
                        loc_rows.extend(range(r0, r0 + m))
                        loc_slot.extend([b.slot] * m)
                v[row + r0 : row + r0 + m] = vv
                r0 += m
            if need_q and loc_rows:
                # batched forward substitution R_pp(j)ᵀ y = a_local (padded rows have R = I)
                sl = np.asarray(loc_slot)
                Rl = self._Rpp[sl]
                a_l = np.vstack(loc_a)
                y = np.zeros_like(a_l)
                for i in range(self.smax):
                    acc = a_l[:, i] - np.einsum("rk,rk->r", Rl[:, :i, i], y[:, :i])
                    y[:, i] = acc / Rl[:, i, i]
                lr = np.asarray(loc_rows)
                pn[row + lr] += np.einsum("rk,rk->r", y, y)
                B[:, lr] -= np.einsum("rk,rkn->nr", y, self._Rpf[sl, :, :n])
            if need_q:
                Yg = self._forward_global(B)
                pn[row : row + rows] += np.einsum("ij,ij->j", Yg, Yg)
            row += rows
            start = stop
        return v, pn, counts

    def residuals(self, ids: Sequence[int] | None = None) -> dict[int, F64]:
        """Whitened residuals √P v = √P (A x̂ - l) per observation."""
        ids = self.observation_ids() if ids is None else list(ids)
        v, _, counts = self.residual_rows(ids, leverage=False)
        return dict(zip(ids, np.split(v, np.cumsum(counts)[:-1]), strict=True))

    def redundancy_numbers(self, ids: Sequence[int] | None = None) -> dict[int, F64]:
        """Diagonal of Q_vv P (redundancy numbers r_i = 1 - a_i Q_xx a_iᵀ p_i) per observation."""
        ids = self.observation_ids() if ids is None else list(ids)
        _, pn, counts = self.residual_rows(ids)
        return dict(zip(ids, np.split(1.0 - pn, np.cumsum(counts)[:-1]), strict=True))

    # ------------------------------------------------------------ batch export
    def design_matrix(self) -> tuple[Any, F64, list[Hashable], list[int]]:
        """Whitened sparse design matrix (CSR), whitened l, column block order, observation ids.

        Columns follow :meth:`parameter_names`; rows follow the returned observation ids.
        Used to compare against a batch solution of the same linear system.
        """
        from scipy.sparse import csr_matrix

        names = self.parameter_names()
        offs: dict[Hashable, int] = {}
        o = 0
        for nm in names:
            offs[nm] = o
            o += self._blocks[nm].size
        rows_i: list[NDArray[np.int64]] = []
        cols_i: list[NDArray[np.int64]] = []
        vals: list[F64] = []
        ls: list[F64] = []
        ids = self.observation_ids()
        r = 0
        for oid in ids:
            rec = self._obs[oid]
            m = rec.rows
            parts = list(rec.a_global.items())
            if rec.local is not None and rec.a_local is not None:
                parts.append((rec.local, rec.a_local))
            for name, A in parts:
                rr, cc = np.meshgrid(np.arange(m), np.arange(A.shape[1]), indexing="ij")
                rows_i.append((rr + r).ravel())
                cols_i.append((cc + offs[name]).ravel())
                vals.append(A.ravel())
            ls.append(rec.l)
            r += m
        A = csr_matrix(
            (
                np.concatenate(vals) if vals else np.zeros(0),
                (
                    np.concatenate(rows_i) if rows_i else np.zeros(0, dtype=int),
                    np.concatenate(cols_i) if cols_i else np.zeros(0, dtype=int),
                ),
            ),
            shape=(r, o),
        )
        return A, (np.concatenate(ls) if ls else np.zeros(0)), names, ids
