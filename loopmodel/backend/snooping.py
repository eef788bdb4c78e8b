"""Baarda data snooping on a :class:`~loopmodel.backend.givens.GivensEstimator` (seed 000).

Normalised residual of observation row i (whitened, so p_i = 1):
``w_i = v_i / (σ0 · sqrt(q_vv,ii))`` with ``q_vv,ii = 1 - a_i Q_xx a_iᵀ``. The term
``a_i Q_xx a_iᵀ = ||R⁻ᵀ a_iᵀ||²`` is computed from ``R`` by forward substitution with the row
itself (Gruen's "unit observation vector" method), only for the observations under test,
never from the full cofactor matrix. ``|w_i|`` is compared with the two-sided normal critical
value (α0 = 0.1 % → 3.29). Several blunders (Gruen 1985b): delete the observation with the
largest ``|w|`` (downdating), which updates residuals and σ̂0², and test again.

An observation with several rows (an image point: x and y) is tested row by row and deleted
as a whole.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.stats import norm

from loopmodel.errors import EstimationError

if TYPE_CHECKING:
    from loopmodel.backend.givens import GivensEstimator


def critical_value(alpha: float = 0.001) -> float:
    """Two-sided standard-normal critical value for significance level α0 (0.001 → 3.29)."""
    if not 0.0 < alpha < 1.0:
        raise EstimationError(f"significance level must be in (0, 1), got {alpha}")
    return float(norm.isf(alpha / 2.0))


@dataclass
class SnoopResult:
    """Outcome of one snooping run."""

    tested: list[int] = field(default_factory=list)  # observation ids that were testable
    untestable: list[int] = field(default_factory=list)  # redundancy below the minimum
    rejected: list[int] = field(default_factory=list)  # deleted, in order of deletion
    rejected_w: list[float] = field(default_factory=list)  # their |w| when deleted
    max_abs_w: float = 0.0  # largest |w| among the accepted observations at the end
    critical: float = 0.0


def normalized_residuals(
    est: GivensEstimator, ids: Sequence[int], sigma0: float | None = None
) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """Per observation: normalised residuals w (per row) and redundancy numbers q_vv,ii.

    ``sigma0=None`` uses the a-priori σ0 = 1 of the whitened observations (Baarda's test);
    pass ``est.variance_factor() ** 0.5`` for Pope's τ variant.
    """
    s0 = 1.0 if sigma0 is None else float(sigma0)
    v, pn, counts = est.residual_rows(list(ids))
    q = 1.0 - pn
    w = v / (s0 * np.sqrt(np.maximum(q, 1e-300)))
    cut = np.cumsum(counts)[:-1]
    return (
        dict(zip(ids, np.split(w, cut), strict=True)),
        dict(zip(ids, np.split(q, cut), strict=True)),
    )


def snoop(
    est: GivensEstimator,
    ids: Sequence[int] | None = None,
    alpha: float = 0.001,
    sigma0: float | None = None,
    min_redundancy: float = 0.05,
    max_rejections: int | None = None,
    delete: bool = True,
    verify_top: int = 5,
) -> SnoopResult:
    """Iterative data snooping: test, delete the largest |w| above the critical value, repeat.

    ``ids``: the observations under test (default: all). Rows whose redundancy number is below
    ``min_redundancy`` cannot reveal a blunder and are reported as untestable. With
    ``delete=False`` only the first (largest) outlier is reported, nothing is changed.

    After a deletion the residuals of all observations under test are recomputed from the
    updated solution (cheap), while their redundancy numbers are kept from the previous
    evaluation for ranking only: the ``verify_top`` largest candidates are re-evaluated
    exactly before the largest is deleted, and a final exact pass over all of them confirms
    that no |w| exceeds the critical value (else the iteration continues).
    """
    crit = critical_value(alpha)
    pending = list(est.observation_ids() if ids is None else ids)
    for i in pending:
        if not est.has_observation(i):
            raise EstimationError(f"observation {i!r} is not in the estimator")
    result = SnoopResult(critical=crit)
    limit = len(pending) if max_rejections is None else int(max_rejections)
    s0 = 1.0 if sigma0 is None else float(sigma0)

    def exact(obs: list[int]) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        return normalized_residuals(est, obs, sigma0)

    w, q = exact(pending)
    result.tested = [i for i in pending if np.any(q[i] >= min_redundancy)]
    tested = set(result.tested)
    result.untestable = [i for i in pending if i not in tested]
    cand_ids = list(result.tested)
    fresh = True  # q is exact for every candidate
    while cand_ids:

        def score(i: int, ww: dict[int, np.ndarray], qq: dict[int, np.ndarray]) -> float:
            ok = qq[i] >= min_redundancy
            return float(np.max(np.abs(ww[i][ok]))) if np.any(ok) else 0.0

        ranked = sorted(cand_ids, key=lambda i: -score(i, w, q))
        if not ranked or score(ranked[0], w, q) <= crit or len(result.rejected) >= limit:
            if fresh:
                result.max_abs_w = score(ranked[0], w, q) if ranked else 0.0
                break
            w, q = exact(cand_ids)  # confirm with exact redundancy numbers
            fresh = True
            continue
        top = [i for i in ranked[:verify_top] if score(i, w, q) > crit]
        if not fresh:
            we, qe = exact(top)
            w.update(we)
            q.update(qe)
        best = max(top, key=lambda i: score(i, w, q))
        best_w = score(best, w, q)
        if best_w <= crit:
            continue  # the exact values of the top candidates are below: re-rank
        result.rejected.append(best)
        result.rejected_w.append(best_w)
        if not delete:
            break
        est.delete_observation(best)
        cand_ids = [i for i in cand_ids if i != best]
        if not cand_ids:
            break
        v, _, counts = est.residual_rows(cand_ids, leverage=False)
        for i, vi in zip(cand_ids, np.split(v, np.cumsum(counts)[:-1]), strict=True):
            w[i] = vi / (s0 * np.sqrt(np.maximum(q[i], 1e-300)))
        fresh = False
    return result
