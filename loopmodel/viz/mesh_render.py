"""Pictures of a triangle mesh for reports, rendered headless.

open3d's offscreen renderer needs a GPU context (EGL/Vulkan), which a headless machine often
lacks (here: "Failed to load vulkan library"). :func:`render_mesh` therefore tries it only when
asked and otherwise rasterises on the CPU: triangles projected with a pinhole camera, drawn far
to near (painter's order) with OpenCV's polygon fill, flat-shaded by a head light, or coloured
per vertex (for example by the distance to a ground-truth surface). Large meshes are decimated
first (open3d quadric decimation, once per mesh for all its viewpoints) so a picture takes well
under a second.

Frames: vertices in the mesh's world frame (metres); ``cam_from_world`` maps them into an
OpenCV camera (x right, y down, z forward); ``K`` in pixels.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from loopmodel.geometry.se3 import invert_pose, look_at

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]

BACKGROUND = (255, 255, 255)
MAX_TRIANGLES = 80_000

#: One row of a before/after picture: title, vertices (V x 3), triangles (T x 3), vertex colours or None.
Panel = tuple[str, F64, NDArray[np.int64], F64 | None]


@dataclass(frozen=True)
class View:
    """A pinhole view of a mesh: intrinsics (pixels), pose and image size."""

    K: F64
    cam_from_world: F64
    width_px: int
    height_px: int


def fixed_views(
    vertices: F64,
    n_views: int = 3,
    elevation_deg: float = 30.0,
    width_px: int = 480,
    height_px: int = 400,
    up: ArrayLike = (0.0, 0.0, 1.0),
) -> list[View]:
    """``n_views`` cameras around the mesh's bounding sphere, the whole mesh in view.

    At equal azimuth steps about ``up`` (world frame; z for a z-up world, from the camera path's
    principal axes for a run's world: :func:`loopmodel.geometry.se3.world_up`), looking at its
    centre from ``elevation_deg`` above the plane normal to ``up``.
    """
    u = np.asarray(up, float) / np.linalg.norm(up)
    a = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(u, a)  # (a, b, u) right-handed: a, b span the ground plane
    v = np.asarray(vertices, float)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(v - centre, axis=1).max()), 1e-6)
    f = 0.5 * min(width_px, height_px) / np.tan(np.radians(18.0))
    dist = radius / np.sin(np.radians(18.0)) * 0.9  # the bounding sphere is loose
    K = np.array([[f, 0, width_px / 2], [0, f, height_px / 2], [0, 0, 1.0]])
    views = []
    el = np.radians(elevation_deg)
    for k in range(n_views):
        az = 2 * np.pi * k / n_views - np.pi / 2
        eye = centre + dist * (np.cos(el) * np.cos(az) * a + np.cos(el) * np.sin(az) * b + np.sin(el) * u)
        views.append(View(K, invert_pose(look_at(eye, centre, u)), width_px, height_px))
    return views


def _decimate(
    vertices: F64, triangles: NDArray[np.int64], colors: F64 | None
) -> tuple[F64, NDArray[np.int64], F64 | None]:
    if len(triangles) <= MAX_TRIANGLES:
        return vertices, triangles, colors
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    if colors is not None:
        m.vertex_colors = o3d.utility.Vector3dVector(colors)
    d = m.simplify_quadric_decimation(MAX_TRIANGLES)
    c = np.asarray(d.vertex_colors) if colors is not None else None
    return np.asarray(d.vertices), np.asarray(d.triangles), c


def render_mesh(
    vertices: F64,
    triangles: NDArray[np.int64],
    view: View,
    vertex_colors: F64 | None = None,
) -> tuple[U8, NDArray[np.bool_]]:
    """RGB picture (H x W x 3) of the mesh seen from ``view`` and its foreground mask.

    ``vertex_colors`` (V x 3 in [0, 1]) colour the triangles (mean of their vertices) and are
    modulated by shading; without them the mesh is light grey. CPU rasteriser, painter's order.
    """
    v, t, c = _decimate(np.asarray(vertices, float), np.asarray(triangles, np.int64), vertex_colors)
    img, mask = _rasterise(v, t, view, c, with_mask=True)
    assert mask is not None
    return img, mask


def _rasterise(
    v: F64, t: NDArray[np.int64], view: View, c: F64 | None, with_mask: bool
) -> tuple[U8, NDArray[np.bool_] | None]:
    """:func:`render_mesh` of an already decimated mesh; the mask only ``with_mask`` (it doubles the fills)."""
    import cv2

    W, H = view.width_px, view.height_px
    img = np.empty((H, W, 3), np.uint8)
    img[:] = BACKGROUND
    mask = np.zeros((H, W), np.uint8)
    if len(t) == 0:
        return img, mask.astype(bool) if with_mask else None
    p_cam = v @ view.cam_from_world[:3, :3].T + view.cam_from_world[:3, 3]
    tri_cam = p_cam[t]  # T x 3 x 3
    depth = tri_cam[:, :, 2]
    keep = np.all(depth > 1e-6, axis=1)
    n = np.cross(tri_cam[:, 1] - tri_cam[:, 0], tri_cam[:, 2] - tri_cam[:, 0])
    nn = np.linalg.norm(n, axis=1)
    keep &= nn > 0
    centre = tri_cam.mean(axis=1)
    n_unit = n / np.maximum(nn, 1e-300)[:, None]
    # head light: |cos| between the normal and the viewing ray (two-sided surfaces)
    ray = centre / np.maximum(np.linalg.norm(centre, axis=1), 1e-300)[:, None]
    shade = 0.25 + 0.75 * np.abs(np.einsum("ij,ij->i", n_unit, ray))
    base = np.full((len(t), 3), 0.82) if c is None else np.asarray(c, float)[t].mean(axis=1)
    rgb = np.clip(base * shade[:, None] * 255, 0, 255).astype(np.uint8)
    uv = (tri_cam @ view.K.T)[:, :, :2] / depth[:, :, None]
    order = np.argsort(-centre[:, 2])
    order = order[keep[order]]
    pts = np.round(uv[order] * 16).astype(np.int32)  # 4 fractional bits for cv2's shift
    bgr = rgb[order, ::-1].tolist()  # cv2 draws BGR; plain ints: no conversion per call
    fill = cv2.fillConvexPoly
    for poly, col in zip(pts, bgr, strict=True):  # far to near
        fill(img, poly, col, cv2.LINE_AA, 4)
    if not with_mask:
        return _bgr_to_rgb(img), None
    for poly in pts:
        fill(mask, poly, 1, cv2.LINE_8, 4)
    return _bgr_to_rgb(img), mask.astype(bool)


def _bgr_to_rgb(img: U8) -> U8:
    return np.ascontiguousarray(img[..., ::-1])


def distance_colors(distance_m: F64, scale_m: float) -> F64:
    """Vertex colours (V x 3 in [0, 1]) for distances: 0 blue → ``scale_m`` and beyond red."""
    from matplotlib import colormaps

    x = np.clip(np.asarray(distance_m, float) / max(scale_m, 1e-12), 0, 1)
    return np.asarray(colormaps["turbo"](x))[:, :3]


def before_after_png(
    panels: list[Panel],
    n_views: int = 3,
    colorbar_mm: float | None = None,
    up: ArrayLike = (0.0, 0.0, 1.0),
) -> bytes:
    """One PNG.

    A row per panel (title, vertices, triangles, vertex colours) and a column per fixed viewpoint;
    all panels share the viewpoints of the first so they compare directly.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    views = fixed_views(panels[0][1], n_views, up=up)
    fig = Figure(figsize=(3.2 * n_views, 2.8 * len(panels) + (0.5 if colorbar_mm else 0)), dpi=100)
    FigureCanvasAgg(fig)
    for r, (title, v_full, t_full, c_full) in enumerate(panels):
        # decimated once per mesh, the same small mesh drawn from every viewpoint
        v, t, c = _decimate(np.asarray(v_full, float), np.asarray(t_full, np.int64), c_full)
        for k, view in enumerate(views):
            ax = fig.add_subplot(len(panels), n_views, r * n_views + k + 1)
            img, _ = _rasterise(v, t, view, c, with_mask=False)
            ax.imshow(img)
            ax.set_axis_off()
            if k == 0:
                ax.set_title(title, loc="left", fontsize=9)
    if colorbar_mm:
        from matplotlib import colormaps
        from matplotlib.cm import ScalarMappable
        from matplotlib.colors import Normalize

        sm = ScalarMappable(Normalize(0, colorbar_mm), colormaps["turbo"])
        fig.colorbar(
            sm, ax=fig.axes, orientation="horizontal", fraction=0.04, pad=0.02, label="distance to ground truth [mm]"
        )
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def mesh_picture_png(
    mesh: object,
    title: str,
    gt_mesh: object | None = None,
    n_views: int = 3,
    up: ArrayLike = (0.0, 0.0, 1.0),
) -> bytes:
    """A picture of one open3d mesh from ``n_views`` fixed viewpoints around ``up`` (world frame).

    Coloured by the distance to ``gt_mesh`` (same world frame) when given, shaded grey otherwise.
    """
    v = np.asarray(mesh.vertices)  # type: ignore[attr-defined]
    t = np.asarray(mesh.triangles)  # type: ignore[attr-defined]
    if gt_mesh is None:
        return before_after_png([(title, v, t, None)], n_views, up=up)
    from loopmodel.mapping.accuracy import distances_to_mesh

    d = distances_to_mesh(v, gt_mesh)  # type: ignore[arg-type]
    scale_mm = max(1.0, float(np.percentile(d, 95)) * 1e3)
    label = f"{title}: mean {1e3 * d.mean():.2f} mm to the true surface"
    return before_after_png([(label, v, t, distance_colors(d, scale_mm * 1e-3))], n_views, colorbar_mm=scale_mm, up=up)
