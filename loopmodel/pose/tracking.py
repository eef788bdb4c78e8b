"""Model-based tracking of a known 3-D line model with an N-camera central rig (seed 002, sections IV-V).

Sample every visible projected edge on its conic (eq. 26-28), search the image along the conic
normal (eq. 29) for the matching edge (moving edges, supplied by the caller as a ``measure``
function so images or a feature-level simulator can be used), then estimate ``rig_from_ref`` by
robust VVS on the point-to-conic distances.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import EstimationError
from loopmodel.geometry.se3 import invert_pose
from loopmodel.pose.rig import F64, CameraRig
from loopmodel.pose.solver import PoseResult
from loopmodel.pose.vvs import LineTerm, VvsOptions, conic_gradient, line_conics, sample_conic_arc, vvs_pose

# measure(camera j, sample pixels (n,2), unit search normals in pixels (n,2), model line of
# each sample (n,)) -> (found, uv)
MeasureFn = Callable[[int, F64, F64, NDArray[np.int64]], tuple[NDArray[np.bool_], F64]]
# valid(camera j, pixels (n,2)) -> usable (inside the mirror rim, outside the image mask)
ValidFn = Callable[[int, F64], NDArray[np.bool_]]


@dataclass(frozen=True)
class PolyhedronModel:
    """A convex polyhedral object (metres, object frame).

    Vertices, edges as vertex index pairs, the two faces adjacent to each edge and the outward face
    normals.
    """

    vertices: F64
    edges: NDArray[np.int64]
    edge_faces: NDArray[np.int64]
    face_normals: F64
    face_points: F64

    @classmethod
    def box(cls, size_m: tuple[float, float, float]) -> PolyhedronModel:
        """A box of the given size centred at the origin, edges along the axes."""
        h = np.asarray(size_m, dtype=float) / 2.0
        V = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
        normals = np.array([[s * (a == k) for k in range(3)] for a in range(3) for s in (-1, 1)], float)
        points = normals * h
        edges, faces = [], []
        for i in range(8):
            for k in range(i + 1, 8):
                diff = np.abs(V[i] - V[k]) > 1e-12
                if diff.sum() != 1:
                    continue
                edges.append((i, k))
                mid = 0.5 * (V[i] + V[k])
                adj = [f for f in range(6) if abs(normals[f] @ (mid - points[f])) < 1e-12]
                faces.append(adj)
        return cls(V, np.array(edges), np.array(faces), normals, points)

    @property
    def lines(self) -> F64:
        """(E, 2, 3) edge endpoints."""
        return self.vertices[self.edges]

    def visible_edges(self, centre_in_ref: F64, min_view_angle_deg: float = 0.0) -> NDArray[np.bool_]:
        """Edges with at least one face turned towards a viewpoint (object frame) and seen
        at more than ``min_view_angle_deg`` from grazing: an edge whose only visible face is
        seen edge-on projects onto the face's opposite edge (ambiguous for edge search)."""
        d = centre_in_ref - self.face_points
        cos = np.einsum("fk,fk->f", self.face_normals, d) / np.linalg.norm(d, axis=1)
        front = cos > np.sin(np.deg2rad(min_view_angle_deg))
        return front[self.edge_faces].any(axis=1)


@dataclass
class EdgeSamples:
    """Samples of the projected model edges: camera, model line, pixel and unit normal."""

    cam_index: NDArray[np.int64]
    line_index: NDArray[np.int64]
    uv_px: F64
    normal_px: F64


def sample_model_edges(
    rig: CameraRig,
    model: PolyhedronModel,
    rig_from_ref: F64,
    step_px: float,
    valid: ValidFn | None = None,
    margin: float = 0.08,
    min_view_angle_deg: float = 8.0,
) -> EdgeSamples:
    """Sample the visible edges of the model at the pose, about every ``step_px`` pixels
    along each projected conic, leaving out a fraction ``margin`` at both ends (corners)."""
    cams, lines_i, uvs, normals = [], [], [], []
    L = model.lines
    for j, cam in enumerate(rig.cameras):
        cam_from_ref = rig.cam_from_rig[j] @ rig_from_ref
        centre = invert_pose(cam_from_ref)[:3, 3]
        vis = np.flatnonzero(model.visible_edges(centre, min_view_angle_deg))
        if vis.size == 0:
            continue
        E = L[vis] @ cam_from_ref[:3, :3].T + cam_from_ref[:3, 3]
        lc = line_conics(E[:, 0], E[:, 1], cam.xi)
        for k, m in enumerate(vis):
            P0, P1 = E[k]
            ends = np.array([P0 + margin * (P1 - P0), P1 - margin * (P1 - P0), 0.5 * (P0 + P1)])
            if not cam.in_front(ends).all() or not lc.valid[k]:
                continue
            xy = cam.normalized(ends)
            length_px = np.hypot(*((xy[1] - xy[0]) * [cam.px, cam.py]))
            n = max(int(np.ceil(1.25 * length_px / step_px)) + 1, 3)
            pts = sample_conic_arc(lc.a[k], xy[0], xy[1], xy[2], n)
            if pts is None:  # not an ellipse: sample the 3-D segment instead
                frac = np.linspace(margin, 1 - margin, n)
                pts = cam.normalized(P0 + frac[:, None] * (P1 - P0))
            g = conic_gradient(np.repeat(lc.a[k : k + 1], len(pts), axis=0), pts)
            g = g / np.array([cam.px, cam.py])
            g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-300)
            uv = pts * [cam.px, cam.py] + [cam.u0, cam.v0]
            cams.append(np.full(len(pts), j))
            lines_i.append(np.full(len(pts), m))
            uvs.append(uv)
            normals.append(g)
    if not cams:
        return EdgeSamples(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)))
    s = EdgeSamples(
        np.concatenate(cams), np.concatenate(lines_i), np.vstack(uvs), np.vstack(normals)
    )
    if valid is not None and len(s.uv_px):
        keep = np.zeros(len(s.uv_px), dtype=bool)
        for j in range(len(rig)):
            idx = np.flatnonzero(s.cam_index == j)
            if idx.size:
                keep[idx] = valid(j, s.uv_px[idx])
        s = EdgeSamples(s.cam_index[keep], s.line_index[keep], s.uv_px[keep], s.normal_px[keep])
    return s


@dataclass
class TrackerOptions:
    """Model-based tracker settings."""

    sample_step_px: float = 3.0
    min_view_angle_deg: float = 8.0  # skip edges whose visible faces are seen edge-on
    min_features: int = 20  # fewer matched edge points: the frame is declared lost
    vvs: VvsOptions = field(default_factory=lambda: VvsOptions(huber_warmup=1, max_iterations=20))


@dataclass
class TrackResult:
    """One frame.

    The pose, the VVS result (None when too few features), the samples and how many edge points were
    matched.
    """

    rig_from_ref: F64
    ok: bool
    num_samples: int
    num_matched: int
    num_inliers: int
    vvs: PoseResult | None


def track_frame(
    rig: CameraRig,
    model: PolyhedronModel,
    rig_from_ref_prev: F64,
    measure: MeasureFn,
    options: TrackerOptions | None = None,
    valid: ValidFn | None = None,
) -> TrackResult:
    """Track the model over one frame from the previous pose (no motion model)."""
    opt = options or TrackerOptions()
    samples = sample_model_edges(
        rig, model, rig_from_ref_prev, opt.sample_step_px, valid, min_view_angle_deg=opt.min_view_angle_deg
    )
    found = np.zeros(len(samples.uv_px), dtype=bool)
    meas = np.zeros_like(samples.uv_px)
    for j in range(len(rig)):
        idx = np.flatnonzero(samples.cam_index == j)
        if idx.size:
            f, uv = measure(j, samples.uv_px[idx], samples.normal_px[idx], samples.line_index[idx])
            found[idx] = f
            meas[idx] = uv
    n_found = int(found.sum())
    if n_found < opt.min_features:
        return TrackResult(rig_from_ref_prev, False, len(found), n_found, 0, None)
    term = LineTerm(rig, model.lines, meas[found], samples.line_index[found], samples.cam_index[found])
    try:
        res = vvs_pose(term, rig_from_ref_prev, opt.vvs)
    except EstimationError:
        return TrackResult(rig_from_ref_prev, False, len(found), n_found, 0, None)
    n_inl = res.num_inliers
    ok = n_inl >= opt.min_features and bool(np.all(np.isfinite(res.rig_from_ref)))
    return TrackResult(res.rig_from_ref, ok, len(found), n_found, n_inl, res)
