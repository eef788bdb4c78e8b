"""Fisher information of the marker contour and the Cramér–Rao bound (seed 001, eq. 2-3).

``J_ij = (2/N0) * contour_integral (n.Q_i)(n.Q_j) dl`` over every boundary (holes included),
with ``Q_i`` the image flow of a boundary point under a change of ``A_i`` and ``n`` the unit
normal (the sign of ``n`` cancels in the product). The integral is evaluated boundary segment
by boundary segment with the trapezoid rule. ``CRLB = J^-1``.

Units (see also ``loopmodel.accuracy``): image lengths are pixels of pitch ``pixel_um``;
``noise`` is ``N0/2`` in contrast^2 * px^2 (the variance of the white image noise averaged over
one 1 px x 1 px cell, for a marker of contrast 1), hence ``2/N0 = 1/noise``. J is in SI:
1/m^2 for (r, v, u), 1/(m rad) and 1/rad^2 for gamma.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from loopmodel.accuracy.marker import Marker
from loopmodel.accuracy.view import Views, focal_px, normal_flows, stabilised_views
from loopmodel.errors import InputError

F64 = NDArray[np.float64]

#: Names of the six normalised correlations, in the order of :attr:`Bound.rho`.
RHO_NAMES = ("rho_rv", "rho_ru", "rho_rgamma", "rho_uv", "rho_vgamma", "rho_ugamma")
_RHO_PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))

#: The paper's grid: elevation 5..65 deg (7 values), azimuth 0..350 deg (36 values).
THETA_GRID_DEG = np.arange(5.0, 66.0, 10.0)
PHI_GRID_DEG = np.arange(0.0, 360.0, 10.0)


def fisher_contour(
    marker: Marker, views: Views, noise: float, n_edge: int = 64, n_circle: int = 256
) -> F64:
    """(n, 4, 4) Fisher information of ``A = (r, v, u, gamma)`` for every camera of ``views``.

    ``noise`` is ``N0/2`` (contrast^2 px^2); ``n_edge`` trapezoid sub-intervals per polygon
    edge, ``n_circle`` points per circle.
    """
    cs = marker.contour(n_edge, n_circle)
    c, speed = normal_flows(views, cs.points, cs.tangents)  # |adot| n.Q_i (n, M, 4); dl = |adot| dt
    w = cs.weights[None, :] / speed
    return np.matmul(np.swapaxes(c * w[..., None], 1, 2), c) / noise


@dataclass(frozen=True)
class Bound:
    """Cramér–Rao bound of ``A = (r, v, u, gamma)``.

    ``cov``: (..., 4, 4) in SI (m, rad); ``sigma``: (..., 4) standard deviations with
    sigma_gamma in DEGREES (as the paper reports); ``rho``: (..., 6) normalised correlations in
    the order of :data:`RHO_NAMES`.
    """

    cov: F64
    sigma: F64
    rho: F64


def crlb(J: ArrayLike) -> Bound:
    """The bound ``J^-1`` for a stack of (..., 4, 4) Fisher matrices."""
    cov = np.linalg.inv(np.asarray(J, dtype=float))
    sd = np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1))
    rho = np.stack([cov[..., i, j] / (sd[..., i] * sd[..., j]) for i, j in _RHO_PAIRS], axis=-1)
    sigma = sd.copy()
    sigma[..., 3] = np.degrees(sigma[..., 3])
    return Bound(cov, sigma, rho)


@dataclass(frozen=True)
class GridBound:
    """The bound over a (theta, phi) grid: arrays shaped (n_theta, n_phi, ...)."""

    marker: str
    theta_deg: F64
    phi_deg: F64
    distance_m: float
    focal_mm: float
    pixel_um: float
    noise: float
    area_m2: float
    perimeter_m: float
    J: F64
    bound: Bound


def bound_grid(
    marker: Marker,
    distance_m: float = 50.0,
    focal_mm: float = 18.0,
    noise: float = 0.2,
    pixel_um: float = 10.0,
    theta_deg: ArrayLike = THETA_GRID_DEG,
    phi_deg: ArrayLike = PHI_GRID_DEG,
    n_edge: int = 64,
    n_circle: int = 256,
) -> GridBound:
    """The bound for every (theta, phi) of the grid, vectorised over all cameras."""
    for key, val in (
        ("distance_m", distance_m),
        ("focal_mm", focal_mm),
        ("noise", noise),
        ("pixel_um", pixel_um),
    ):
        if not (np.isfinite(val) and val > 0):
            raise InputError(None, f"{key} must be a positive number, got {val}")
    reach = max(float(np.max(np.linalg.norm(v, axis=1))) for v, _ in marker.outlines(64))
    if distance_m <= 2.0 * reach:
        raise InputError(
            None,
            f"distance_m = {distance_m:g} m is too small for marker '{marker.name}' "
            f"(it reaches {reach:.3g} m from its origin; the bound assumes a distant marker)",
        )
    th = np.asarray(theta_deg, dtype=float).ravel()
    ph = np.asarray(phi_deg, dtype=float).ravel()
    views = stabilised_views(distance_m, th[:, None], ph[None, :], focal_px(focal_mm, pixel_um))
    J = fisher_contour(marker, views, noise, n_edge, n_circle).reshape(len(th), len(ph), 4, 4)
    return GridBound(
        marker.name,
        th,
        ph,
        distance_m,
        focal_mm,
        pixel_um,
        noise,
        marker.area,
        marker.perimeter,
        J,
        crlb(J),
    )
