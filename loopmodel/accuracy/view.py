"""Observation geometry of seed 001: a space-stabilised camera looking at a planar marker.

Marker frame: the marker lies in ``z = 0``, its origin is the aim point, ``z`` is its normal.
The camera's projection centre sits at distance ``R`` in the direction
``d = (sin(theta) cos(phi), sin(theta) sin(phi), cos(theta))``: the frontal position
``(0, 0, R)`` turned by the elevation ``theta`` in the plane through the normal rotated by the
azimuth ``phi`` about the normal (rotation axis ``(-sin(phi), cos(phi), 0)``). The camera axes
start as ``e1 = (0, 0, -1)`` (optical axis, towards the marker), ``e2 = (1, 0, 0)``,
``e3 = (0, 1, 0)`` and turn with it. Image coordinates (pixels, origin at the principal
point) are ``a = F (X.e2, X.e3) / X.e1`` with ``X = P - C`` and ``F`` the focal length in
pixels; ``a[0]`` runs along ``e2`` and ``a[1]`` along ``e3``.

The four estimated parameters ``A = (r, v, u, gamma)`` (metres, metres, metres, radians):
``r`` moves the camera away from the marker along ``-e1`` (the range), ``v`` and ``u`` move it
along the nominal ``e2`` and ``e3`` with fixed orientation, ``gamma`` turns the image axes about
``e1`` (``e2 -> cos(gamma) e2 + sin(gamma) e3``). The camera is space-stabilised, so the two
other rotations are not estimated (they are near-collinear with ``u`` and ``v`` at long range).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]

PARAMS = ("r", "v", "u", "gamma")


@dataclass(frozen=True)
class Views:
    """``n`` cameras: nominal frames from (R, theta, phi) and the parameter offsets ``A``.

    ``e1``, ``n2``, ``n3``: (n, 3) nominal axes in the marker frame; ``params``: (n, 4)
    offsets ``A = (r, v, u, gamma)`` from the nominal pose (m, m, m, rad).
    """

    distance_m: float
    focal_px: float
    e1: F64
    n2: F64
    n3: F64
    params: F64

    @property
    def n(self) -> int:
        """Number of cameras."""
        return len(self.e1)

    @property
    def centre(self) -> F64:
        """(n, 3) projection centres in the marker frame (m)."""
        A = self.params
        return -(self.distance_m + A[:, :1]) * self.e1 + A[:, 1:2] * self.n2 + A[:, 2:3] * self.n3

    @property
    def e2(self) -> F64:
        """(n, 3) first image axis after the roll ``gamma``."""
        g = self.params[:, 3:4]
        return np.cos(g) * self.n2 + np.sin(g) * self.n3

    @property
    def e3(self) -> F64:
        """(n, 3) second image axis after the roll ``gamma``."""
        g = self.params[:, 3:4]
        return -np.sin(g) * self.n2 + np.cos(g) * self.n3

    def with_params(self, params: ArrayLike) -> Views:
        """The same cameras with offsets ``params`` ((4,) or (n, 4)) from the nominal pose."""
        A = np.broadcast_to(np.asarray(params, dtype=float), (self.n, 4)).copy()
        return replace(self, params=A)

    def take(self, index: ArrayLike) -> Views:
        """A subset of the cameras."""
        i = np.atleast_1d(np.asarray(index))
        return Views(
            self.distance_m, self.focal_px, self.e1[i], self.n2[i], self.n3[i], self.params[i]
        )


def focal_px(focal_mm: float, pixel_um: float) -> float:
    """Focal length in pixels from the focal length (mm) and pixel pitch (micrometres)."""
    return focal_mm * 1000.0 / pixel_um


def stabilised_views(
    distance_m: float, theta_deg: ArrayLike, phi_deg: ArrayLike, focal_length_px: float
) -> Views:
    """Cameras at distance ``distance_m`` for every pair of the broadcast ``theta_deg`` and
    ``phi_deg`` arrays (flattened in C order), aimed at the marker origin."""
    th, ph = np.broadcast_arrays(
        np.radians(np.asarray(theta_deg, float)), np.radians(np.asarray(phi_deg, float))
    )
    th, ph = th.ravel(), ph.ravel()
    ct, st, cp, sp = np.cos(th), np.sin(th), np.cos(ph), np.sin(ph)
    d = np.column_stack([st * cp, st * sp, ct])
    n2 = np.column_stack([ct + sp**2 * (1 - ct), -sp * cp * (1 - ct), -cp * st])
    n3 = np.column_stack([-sp * cp * (1 - ct), ct + cp**2 * (1 - ct), -sp * st])
    return Views(float(distance_m), float(focal_length_px), -d, n2, n3, np.zeros((len(th), 4)))


def _lift(points: ArrayLike) -> F64:
    P = np.asarray(points, dtype=float)
    return np.concatenate([P, np.zeros(P.shape[:-1] + (1,))], axis=-1) if P.shape[-1] == 2 else P


def camera_coords(views: Views, points: ArrayLike) -> tuple[F64, F64, F64]:
    """Coordinates ``(x1, x2, x3)`` of marker points (M x 2 or M x 3, metres) along the camera
    axes, each (n, M)."""
    P = _lift(points).reshape(-1, 3)
    C = views.centre
    out = []
    for e in (views.e1, views.e2, views.e3):
        out.append(e @ P.T - np.sum(C * e, axis=1)[:, None])
    return out[0], out[1], out[2]


def project(views: Views, points: ArrayLike) -> F64:
    """(n, M, 2) image coordinates (pixels) of marker points (M x 2, metres)."""
    x1, x2, x3 = camera_coords(views, points)
    return views.focal_px * np.stack([x2 / x1, x3 / x1], axis=-1)


def flows(views: Views, points: ArrayLike) -> F64:
    """(n, M, 4, 2) image flows ``Q_i = d a / d A_i`` of marker points (pixels per metre for
    r, v, u; pixels per radian for gamma), exact at the current parameters of ``views``."""
    x1, x2, x3 = camera_coords(views, points)
    F = views.focal_px
    a2, a3 = F * x2 / x1, F * x3 / x1
    e1, e2, e3 = views.e1, views.e2, views.e3
    Q = np.empty(x1.shape + (4, 2))
    # a translation g of the centre changes X by -g: da = (F/x1) (-g.e2 + a2 g.e1 / F, ...)
    for i, g in enumerate((-views.e1, views.n2, views.n3)):
        g1, g2, g3 = (np.sum(g * e, axis=1)[:, None] for e in (e1, e2, e3))
        Q[..., i, 0] = (F / x1) * (-g2 + a2 * g1 / F)
        Q[..., i, 1] = (F / x1) * (-g3 + a3 * g1 / F)
    Q[..., 3, 0] = a3
    Q[..., 3, 1] = -a2
    return Q


def image_tangents(views: Views, points: ArrayLike, tangents: ArrayLike) -> F64:
    """(n, M, 2) image velocity (pixels per unit t) of marker-plane tangents dP/dt (M x 2)."""
    x1, x2, x3 = camera_coords(views, points)
    T = _lift(tangents).reshape(-1, 3)
    t1, t2, t3 = (e @ T.T for e in (views.e1, views.e2, views.e3))
    F = views.focal_px
    return (F / x1)[..., None] * np.stack([t2 - x2 / x1 * t1, t3 - x3 / x1 * t1], axis=-1)


def normal_flows(views: Views, points: ArrayLike, tangents: ArrayLike) -> tuple[F64, F64]:
    """``(c, speed)``.

    ``c`` (n, M, 4) = ``adot x Q_i`` = ``|adot| (n.Q_i)`` (up to one common sign) and ``speed`` (n,
    M) = ``|adot|``, for marker points with plane tangents dP/dt; the cheap form of :func:`flows`
    and :func:`image_tangents` used by the contour integral.
    """
    x1, x2, x3 = camera_coords(views, points)
    T = _lift(tangents).reshape(-1, 3)
    F = views.focal_px
    inv = 1.0 / x1
    a2, a3 = F * x2 * inv, F * x3 * inv
    t1, t2, t3 = (e @ T.T for e in (views.e1, views.e2, views.e3))
    ax = F * inv * (t2 - x2 * inv * t1)
    ay = F * inv * (t3 - x3 * inv * t1)
    c = np.empty(x1.shape + (4,))
    for i, g in enumerate((-views.e1, views.n2, views.n3)):
        g1, g2, g3 = (np.sum(g * e, axis=1)[:, None] for e in (views.e1, views.e2, views.e3))
        c[..., i] = F * inv * (ax * (a3 * g1 / F - g3) - ay * (a2 * g1 / F - g2))
    c[..., 3] = -(ax * a2 + ay * a3)
    return c, np.hypot(ax, ay)
