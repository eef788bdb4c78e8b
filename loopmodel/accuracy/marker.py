"""Planar markers made of polygons and circles, their JSON description and validation.

The marker lies in the plane ``z = 0`` of the marker frame (metres); the camera aims at the
marker-frame origin. Brightness is 1 on the marker and 0 elsewhere. A marker is a list of
shapes; a shape with ``"hole": true`` is a dark region cut out of the shape that contains it.
Boundaries must not touch or cross each other, holes must lie inside a bright shape and bright
shapes outside any other bright shape (or inside a hole), so the brightness alternates from one
boundary to the next and every boundary is an edge of contrast 1.

JSON layout (unknown keys are errors)::

    {"name": "triangle",
     "shapes": [
        {"type": "polygon", "points": [[-1, -1], [1, -1], [0, 2]]},
        {"type": "circle", "center": [0, 0], "radius": 0.3, "hole": true}]}
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import InputError

F64 = NDArray[np.float64]

#: Radius (m) of the dark round spot in the centre of the paper's triangle marker. The paper
#: does not give it; 0.3 m keeps a 0.33 m bright rim between the spot and the nearest side
#: (the centroid lies 0.632 m from the slanted sides) and is large enough (about 11 px at 50 m
#: with f = 18 mm and 10 um pixels) to be resolved at every grid point.
TRIANGLE_SPOT_RADIUS_M = 0.3


@dataclass(frozen=True)
class Polygon:
    """A simple polygon in the marker plane: ``vertices`` (N x 2, metres), any orientation."""

    vertices: F64
    hole: bool = False

    @property
    def signed_area(self) -> float:
        """Shoelace area (m^2), positive when counter-clockwise."""
        x, y = self.vertices[:, 0], self.vertices[:, 1]
        return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))

    @property
    def area(self) -> float:
        """Area (m^2)."""
        return abs(self.signed_area)

    @property
    def perimeter(self) -> float:
        """Perimeter (m)."""
        return float(
            np.sum(np.linalg.norm(np.roll(self.vertices, -1, axis=0) - self.vertices, axis=1))
        )

    def outline(self, n_circle: int = 0) -> F64:
        """Vertices of the boundary (N x 2, metres)."""
        return self.vertices


@dataclass(frozen=True)
class Circle:
    """A disc in the marker plane: ``center`` (metres), ``radius`` (metres)."""

    center: F64
    radius: float
    hole: bool = False

    @property
    def area(self) -> float:
        """Area (m^2)."""
        return math.pi * self.radius**2

    @property
    def perimeter(self) -> float:
        """Circumference (m)."""
        return 2.0 * math.pi * self.radius

    def outline(self, n_circle: int = 256) -> F64:
        """Regular ``n_circle``-gon inscribed in the circle, counter-clockwise (N x 2, metres)."""
        t = np.arange(n_circle) * (2.0 * np.pi / n_circle)
        return self.center + self.radius * np.column_stack([np.cos(t), np.sin(t)])


Shape = Polygon | Circle


@dataclass(frozen=True)
class ContourSamples:
    """Points of every boundary for the trapezoid rule, in the marker plane.

    ``points`` (M x 2, m), ``tangents`` (M x 2, dP/dt in m per unit parameter t) and
    ``weights`` (M,): the integral of g over the boundary is ``sum(w * g * |dP/dt|)`` in the
    plane, and ``sum(w * g * |d(image)/dt|)`` in the image. Polygons are integrated edge by
    edge (the corner points appear once per edge); circles with the periodic trapezoid rule.
    """

    points: F64
    tangents: F64
    weights: F64


@dataclass(frozen=True)
class Marker:
    """A planar marker: bright shapes and dark holes, in metres in the marker plane."""

    name: str
    shapes: tuple[Shape, ...]

    @property
    def area(self) -> float:
        """Bright area (m^2): bright shapes minus holes."""
        return sum(-s.area if s.hole else s.area for s in self.shapes)

    @property
    def perimeter(self) -> float:
        """Total boundary length (m), holes included."""
        return sum(s.perimeter for s in self.shapes)

    @property
    def centroid(self) -> F64:
        """Centroid of the bright area (m)."""
        acc = np.zeros(2)
        for s in self.shapes:
            sign = -1.0 if s.hole else 1.0
            if isinstance(s, Circle):
                acc += sign * s.area * s.center
            else:
                v, w = s.vertices, np.roll(s.vertices, -1, axis=0)
                cr = v[:, 0] * w[:, 1] - w[:, 0] * v[:, 1]
                c = np.sum((v + w) * cr[:, None], axis=0) / (6.0 * s.signed_area)
                acc += sign * s.area * c
        return acc / self.area

    def contour(self, n_edge: int = 64, n_circle: int = 256) -> ContourSamples:
        """Trapezoid-rule samples of all boundaries.

        ``n_edge`` sub-intervals per polygon edge, ``n_circle`` points per circle.
        """
        pts, tans, wts = [], [], []
        t = np.linspace(0.0, 1.0, n_edge + 1)
        w_edge = np.full(n_edge + 1, 1.0 / n_edge)
        w_edge[[0, -1]] *= 0.5
        for s in self.shapes:
            if isinstance(s, Circle):
                a = np.arange(n_circle) * (2.0 * np.pi / n_circle)
                cs = np.column_stack([np.cos(a), np.sin(a)])
                pts.append(s.center + s.radius * cs)
                tans.append(s.radius * np.column_stack([-cs[:, 1], cs[:, 0]]))
                wts.append(np.full(n_circle, 2.0 * np.pi / n_circle))
            else:
                v0 = s.vertices
                d = np.roll(v0, -1, axis=0) - v0
                pts.append((v0[:, None, :] + t[None, :, None] * d[:, None, :]).reshape(-1, 2))
                tans.append(np.repeat(d, n_edge + 1, axis=0))
                wts.append(np.tile(w_edge, len(v0)))
        return ContourSamples(np.concatenate(pts), np.concatenate(tans), np.concatenate(wts))

    def outlines(self, n_circle: int = 256) -> list[tuple[F64, bool]]:
        """Every boundary as a closed polygon (vertices N x 2, metres) with its hole flag.

        Circles become inscribed ``n_circle``-gons.
        """
        return [(s.outline(n_circle), s.hole) for s in self.shapes]


# ---------------------------------------------------------------------------------------------
# Built-in markers of the paper (seed 001)


def triangle_marker(spot_radius_m: float = TRIANGLE_SPOT_RADIUS_M) -> Marker:
    """The paper's isosceles triangle (base 2 m, height 3 m) with a dark round spot of radius
    ``spot_radius_m`` at its centroid; the centroid is the marker-frame origin."""
    tri = np.array([[-1.0, -1.0], [1.0, -1.0], [0.0, 2.0]])
    shapes: list[Shape] = [Polygon(tri)]
    if spot_radius_m > 0:
        shapes.append(Circle(np.zeros(2), float(spot_radius_m), hole=True))
    return Marker("triangle", tuple(shapes))


def t_marker(area_m2: float | None = None) -> Marker:
    """A T of the same bright area as :func:`triangle_marker` (unless ``area_m2`` is given),
    inside the triangle's 2 m x 3 m bounding box: a 2 m bar on a stem, bar thickness equal to
    stem width ``w`` with ``2 w + (3 - w) w = area``. The area centroid is the origin."""
    area = triangle_marker().area if area_m2 is None else float(area_m2)
    w = (5.0 - math.sqrt(25.0 - 4.0 * area)) / 2.0
    h = w / 2.0
    pts = np.array(
        [
            [-1.0, 3.0],
            [-1.0, 3.0 - w],
            [-h, 3.0 - w],
            [-h, 0.0],
            [h, 0.0],
            [h, 3.0 - w],
            [1.0, 3.0 - w],
            [1.0, 3.0],
        ]
    )
    m = Marker("t", (Polygon(pts),))
    return Marker("t", (Polygon(pts - m.centroid),))


BUILTIN_MARKERS = {"triangle": triangle_marker, "t": t_marker}


# ---------------------------------------------------------------------------------------------
# JSON loading and validation


def _fail(source: str | Path | None, problem: str) -> InputError:
    return InputError(source, problem)


def _point(value: Any, where: str, source: str | Path | None) -> F64:
    if (
        not isinstance(value, list | tuple)
        or len(value) != 2
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        raise _fail(source, f"key '{where}': expected a point [x, y] of two numbers (metres)")
    p = np.array(value, dtype=float)
    if not np.all(np.isfinite(p)):
        raise _fail(source, f"key '{where}': coordinates must be finite")
    return p


def _segments_intersect(p: F64, q: F64, r: F64, s: F64, eps: float) -> NDArray[np.bool_]:
    """Whether segments p->q and r->s (arrays of shape K x 2) touch or cross (tolerance eps)."""

    def orient(a: F64, b: F64, c: F64) -> F64:
        return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])

    def on_seg(a: F64, b: F64, c: F64) -> NDArray[np.bool_]:
        lo, hi = np.minimum(a, b) - eps, np.maximum(a, b) + eps
        return np.all((c >= lo) & (c <= hi), axis=1)

    d1, d2 = orient(r, s, p), orient(r, s, q)
    d3, d4 = orient(p, q, r), orient(p, q, s)
    scale = eps * (np.linalg.norm(q - p, axis=1) + np.linalg.norm(s - r, axis=1) + 1.0)
    proper = (((d1 > scale) & (d2 < -scale)) | ((d1 < -scale) & (d2 > scale))) & (
        ((d3 > scale) & (d4 < -scale)) | ((d3 < -scale) & (d4 > scale))
    )
    touch = (
        ((np.abs(d1) <= scale) & on_seg(r, s, p))
        | ((np.abs(d2) <= scale) & on_seg(r, s, q))
        | ((np.abs(d3) <= scale) & on_seg(p, q, r))
        | ((np.abs(d4) <= scale) & on_seg(p, q, s))
    )
    return np.asarray(proper | touch)


def _polygon_self_intersects(v: F64, eps: float) -> bool:
    n = len(v)
    i, j = np.triu_indices(n, k=1)
    adjacent = (j == i + 1) | ((i == 0) & (j == n - 1))
    i, j = i[~adjacent], j[~adjacent]
    if len(i) and np.any(_segments_intersect(v[i], v[(i + 1) % n], v[j], v[(j + 1) % n], eps)):
        return True
    # adjacent edges folding back onto each other (a zero-width spike)
    a, b, c = np.roll(v, 1, axis=0), v, np.roll(v, -1, axis=0)
    u, w = a - b, c - b
    cross = u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]
    dot = np.sum(u * w, axis=1)
    return bool(
        np.any(
            (np.abs(cross) <= eps * (np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1) + eps))
            & (dot > 0)
        )
    )


def _point_in_shape(p: F64, s: Shape) -> bool:
    if isinstance(s, Circle):
        return bool(np.hypot(*(p - s.center)) < s.radius)
    v = s.vertices
    w = np.roll(v, -1, axis=0)
    crosses = (v[:, 1] > p[1]) != (w[:, 1] > p[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = v[:, 0] + (p[1] - v[:, 1]) * (w[:, 0] - v[:, 0]) / (w[:, 1] - v[:, 1])
    return bool(np.count_nonzero(crosses & (p[0] < xc)) % 2)


def _boundaries_meet(s1: Shape, s2: Shape, eps: float) -> bool:
    if isinstance(s1, Circle) and isinstance(s2, Circle):
        d = float(np.hypot(*(s1.center - s2.center)))
        return abs(s1.radius - s2.radius) - eps <= d <= s1.radius + s2.radius + eps
    if isinstance(s1, Circle) or isinstance(s2, Circle):
        poly, circ = (s2, s1) if isinstance(s1, Circle) else (s1, s2)
        assert isinstance(poly, Polygon) and isinstance(circ, Circle)
        v = poly.vertices
        w = np.roll(v, -1, axis=0)
        c = circ.center
        dv = w - v
        t = np.sum((c - v) * dv, axis=1) / np.maximum(np.sum(dv * dv, axis=1), 1e-300)
        t = np.clip(t, 0.0, 1.0)
        dmin = np.linalg.norm(v + t[:, None] * dv - c, axis=1)
        dmax = np.maximum(np.linalg.norm(v - c, axis=1), np.linalg.norm(w - c, axis=1))
        return bool(np.any((dmin <= circ.radius + eps) & (dmax >= circ.radius - eps)))
    v1, v2 = s1.vertices, s2.vertices
    ii, jj = np.meshgrid(np.arange(len(v1)), np.arange(len(v2)), indexing="ij")
    i, j = ii.ravel(), jj.ravel()
    return bool(
        np.any(_segments_intersect(v1[i], v1[(i + 1) % len(v1)], v2[j], v2[(j + 1) % len(v2)], eps))
    )


def validate_marker(marker: Marker, source: str | Path | None = None) -> Marker:
    """Check that every boundary is simple with non-zero area, that boundaries do not meet and
    that brightness alternates across nested boundaries; raise :class:`InputError` otherwise."""
    if not marker.shapes:
        raise _fail(source, "key 'shapes': a marker needs at least one shape")
    extent = max(float(np.max(np.abs(s.outline(8)))) for s in marker.shapes) + 1.0
    eps = 1e-9 * extent
    for k, s in enumerate(marker.shapes):
        where = f"shapes[{k}]"
        if isinstance(s, Circle):
            if not (s.radius > eps):
                raise _fail(
                    source, f"key '{where}.radius': circle has zero area (radius must be > 0)"
                )
            continue
        if len(s.vertices) < 3:
            raise _fail(source, f"key '{where}.points': a polygon needs at least 3 points")
        seg = np.linalg.norm(np.roll(s.vertices, -1, axis=0) - s.vertices, axis=1)
        if np.any(seg <= eps):
            k_rep = int(np.argmax(seg <= eps))
            raise _fail(source, f"key '{where}.points[{k_rep}]': repeated point (zero-length edge)")
        rel = s.vertices - s.vertices[0]
        spread = np.abs(rel[:, None, 0] * rel[None, :, 1] - rel[:, None, 1] * rel[None, :, 0])
        if spread.max() <= eps * extent:
            raise _fail(source, f"key '{where}.points': polygon has zero area (collinear points)")
        if _polygon_self_intersects(s.vertices, eps):
            raise _fail(source, f"key '{where}.points': polygon is self-intersecting")
        if s.area <= eps * extent:
            raise _fail(source, f"key '{where}.points': polygon has zero area")
    for a in range(len(marker.shapes)):
        for b in range(a + 1, len(marker.shapes)):
            if _boundaries_meet(marker.shapes[a], marker.shapes[b], eps):
                raise _fail(
                    source, f"keys 'shapes[{a}]' and 'shapes[{b}]': boundaries touch or cross"
                )
    for k, s in enumerate(marker.shapes):
        # boundaries do not meet, so any one boundary point decides containment
        probe = s.outline(8)[0]
        depth = sum(_point_in_shape(probe, o) for j, o in enumerate(marker.shapes) if j != k)
        if s.hole and depth % 2 == 0:
            raise _fail(source, f"key 'shapes[{k}].hole': a hole must lie inside a bright shape")
        if not s.hole and depth % 2 == 1:
            raise _fail(
                source,
                f"key 'shapes[{k}]': a bright shape overlaps another bright shape "
                "(put it inside a hole or mark it as a hole)",
            )
    if marker.area <= eps * extent:
        raise _fail(source, "marker has zero bright area")
    return marker


_SHAPE_KEYS = {
    "polygon": {"type", "points", "hole"},
    "circle": {"type", "center", "radius", "hole"},
}


def marker_from_dict(data: Any, source: str | Path | None = None) -> Marker:
    """Build and validate a marker from its JSON structure (see the module docstring)."""
    if not isinstance(data, dict):
        raise _fail(source, "expected a JSON object with keys 'name' and 'shapes'")
    unknown = sorted(set(data) - {"name", "shapes"})
    if unknown:
        raise _fail(source, f"unknown key '{unknown[0]}' (allowed: name, shapes)")
    name = data.get("name", Path(source).stem if source else "marker")
    if not isinstance(name, str) or not name:
        raise _fail(source, "key 'name': expected a non-empty string")
    raw = data.get("shapes")
    if not isinstance(raw, list):
        raise _fail(source, "key 'shapes': expected a list of shapes")
    shapes: list[Shape] = []
    for k, sh in enumerate(raw):
        where = f"shapes[{k}]"
        if not isinstance(sh, dict):
            raise _fail(source, f"key '{where}': expected an object")
        kind = sh.get("type")
        if kind not in _SHAPE_KEYS:
            raise _fail(source, f"key '{where}.type': expected 'polygon' or 'circle', got {kind!r}")
        extra = sorted(set(sh) - _SHAPE_KEYS[kind])
        if extra:
            allowed = ", ".join(sorted(_SHAPE_KEYS[kind]))
            raise _fail(
                source, f"unknown key '{where}.{extra[0]}' (allowed for a {kind}: {allowed})"
            )
        hole = sh.get("hole", False)
        if not isinstance(hole, bool):
            raise _fail(source, f"key '{where}.hole': expected true or false")
        if kind == "polygon":
            pts = sh.get("points")
            if not isinstance(pts, list):
                raise _fail(source, f"key '{where}.points': expected a list of [x, y] points")
            verts = np.array([_point(p, f"{where}.points[{i}]", source) for i, p in enumerate(pts)])
            shapes.append(Polygon(verts.reshape(-1, 2), hole))
        else:
            if "center" not in sh or "radius" not in sh:
                raise _fail(source, f"key '{where}': a circle needs 'center' and 'radius'")
            c = _point(sh["center"], f"{where}.center", source)
            r = sh["radius"]
            if not isinstance(r, int | float) or isinstance(r, bool) or not math.isfinite(r):
                raise _fail(source, f"key '{where}.radius': expected a finite number (metres)")
            shapes.append(Circle(c, float(r), hole))
    return validate_marker(Marker(name, tuple(shapes)), source)


def load_marker(spec: str | Path) -> Marker:
    """A built-in marker by name (``triangle``, ``t``) or a marker from a JSON file."""
    key = str(spec).lower()
    if key in BUILTIN_MARKERS:
        return BUILTIN_MARKERS[key]()
    path = Path(spec)
    if not path.is_file():
        raise InputError(
            path, f"no such marker file (built-in markers: {', '.join(BUILTIN_MARKERS)})"
        )
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not valid JSON ({str(exc).splitlines()[0]})") from None
    return marker_from_dict(data, path)


def marker_to_dict(marker: Marker) -> dict[str, Any]:
    """The JSON structure of a marker (inverse of :func:`marker_from_dict`)."""
    shapes: list[dict[str, Any]] = []
    for s in marker.shapes:
        if isinstance(s, Circle):
            shapes.append(
                {"type": "circle", "center": s.center.tolist(), "radius": s.radius, "hole": s.hole}
            )
        else:
            shapes.append({"type": "polygon", "points": s.vertices.tolist(), "hole": s.hole})
    return {"name": marker.name, "shapes": shapes}
