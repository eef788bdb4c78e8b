"""Surfaces from world-frame stripe points with open3d.

Points are voxel down-sampled, normals estimated from neighbours and oriented towards the
sensor position at each point's capture time, then the signed-distance surface (``sdf``: the zero set of
the samples' weighted plane distances on a sparse grid, :mod:`loopmodel.mapping._sdf_kernels`; trimmed
by distance to the samples and by piece size), screened Poisson reconstruction (trimmed by vertex
density and by distance to the samples) or ball pivoting.
All lengths in metres, world frame.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from loopmodel.config import MappingConfig
from loopmodel.errors import InputError

F64 = NDArray[np.float64]
logger = logging.getLogger(__name__)


def oriented_cloud(points_w: F64, sensors_w: F64, config: MappingConfig) -> o3d.geometry.PointCloud:
    """Voxel down-sampled cloud with normals oriented towards the capturing sensor.

    ``points_w`` and ``sensors_w`` are P x 3 (world, metres): each point and the camera
    centre at the time it was captured.
    """
    points_w = np.ascontiguousarray(points_w, dtype=np.float64).reshape(-1, 3)
    sensors_w = np.ascontiguousarray(sensors_w, dtype=np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(points_w)):
        raise InputError(None, "stripe points contain non-finite values")
    view = sensors_w - points_w
    view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-12)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_w))
    pcd.normals = o3d.utility.Vector3dVector(view)
    down = pcd.voxel_down_sample(config.voxel_m) if config.voxel_m > 0 else pcd
    view_d = np.asarray(down.normals).copy()
    view_d /= np.maximum(np.linalg.norm(view_d, axis=1, keepdims=True), 1e-12)
    n = _grid_normals(np.asarray(down.points), view_d, config)
    if n is None:
        n = _open3d_normals(down, view_d, config)
    down.normals = o3d.utility.Vector3dVector(n)
    return down


def _open3d_normals(cloud: o3d.geometry.PointCloud, view: F64, config: MappingConfig) -> F64:
    """:func:`_grid_normals` by open3d's k-d tree search and numpy's eigen-decomposition (a grid too large)."""
    cloud.estimate_covariances(
        o3d.geometry.KDTreeSearchParamHybrid(radius=config.normal_radius_m, max_nn=config.normal_max_nn)
    )
    evals, evecs = np.linalg.eigh(np.asarray(cloud.covariances))  # ascending eigenvalues
    n = evecs[:, :, 0].copy()
    # Where the neighbourhood is (nearly) a line - one stripe with no neighbour stripe within
    # reach - its normal is undetermined; take the view direction made perpendicular to the
    # line instead, the best guess the sensor geometry gives.
    line = evals[:, 1] < config.line_ratio * np.maximum(evals[:, 2], 1e-30)
    if np.any(line):
        tangent = evecs[line, :, 2]
        v = view[line]
        nv = v - np.einsum("ij,ij->i", v, tangent)[:, None] * tangent
        n[line] = nv / np.maximum(np.linalg.norm(nv, axis=1, keepdims=True), 1e-12)
    n[np.einsum("ij,ij->i", n, view) < 0] *= -1.0
    return np.asarray(n, np.float64)


def _grid_normals(points_w: F64, view: F64, config: MappingConfig) -> F64 | None:
    """Unit normals (P x 3) of the ``normal_max_nn`` nearest points within ``normal_radius_m``, toward ``view``.

    The covariance's least eigenvector (a line-like neighbourhood: ``view`` made perpendicular to the line),
    as :func:`_open3d_normals`, by a search over a grid of cells half the radius
    (:func:`loopmodel.mapping._sdf_kernels.normals`; fin18: 0.17 -> 0.08 s CPU on the 150-frame orbit's final
    cloud, the same neighbours). None when the points span too many cells for the grid. World frame, metres.
    """
    from loopmodel.mapping import _sdf_kernels as k

    if points_w.shape[0] == 0:
        return np.zeros((0, 3))
    pts = np.ascontiguousarray(points_w, dtype=np.float64)
    h = config.normal_radius_m / 2.0
    origin = pts.min(axis=0) - h
    bdims = (np.floor((pts.max(axis=0) - origin) / h).astype(np.int64) + 2 >> k.SHIFT) + 1
    if float(np.prod(bdims.astype(np.float64))) > _NORMAL_MAX_BLOCKS:
        return None
    bmap, blocks = k.mark_blocks(pts, origin, h, h, bdims)
    order, start = k.bucket_points(pts, origin, h, bmap, blocks.shape[0])
    view = np.ascontiguousarray(view, dtype=np.float64)
    return np.asarray(
        k.normals(pts, view, config.normal_radius_m, config.normal_max_nn, config.line_ratio, origin, h, bmap,
                  order, start),
        np.float64,
    )


#: most blocks (of 8^3 cells) the normals' search grid may span (an int32 each: 32 MB); beyond, open3d's k-d tree
_NORMAL_MAX_BLOCKS = 8_000_000


def poisson_depth(cloud: o3d.geometry.PointCloud, config: MappingConfig) -> int:
    """Octree depth whose finest cell is closest to ``poisson_cell_voxels`` x ``voxel_m`` (or the configured depth)."""
    if config.poisson_depth > 0:
        return config.poisson_depth
    ext = float(np.max(cloud.get_max_bound() - cloud.get_min_bound()))
    cell_m = config.poisson_cell_voxels * config.voxel_m
    depth = round(math.log2(max(ext * config.poisson_scale / cell_m, 2.0)))
    return int(min(max(depth, 5), config.poisson_max_depth))


def _poisson(cloud: o3d.geometry.PointCloud, config: MappingConfig) -> o3d.geometry.TriangleMesh:
    # PoissonRecon's warnings ("Extract bad average roots", with open3d's build paths) say nothing
    # a user can act on: errors only while it runs (issue 35)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, dens_vec = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud,
            depth=poisson_depth(cloud, config),
            scale=config.poisson_scale,
            linear_fit=config.poisson_linear_fit,
            n_threads=config.poisson_threads or -1,
        )
    if len(mesh.vertices) == 0:
        return mesh
    dens = np.asarray(dens_vec, dtype=np.float64)
    remove = np.zeros(dens.shape[0], dtype=bool)
    if config.density_quantile > 0:
        remove |= dens < np.quantile(dens, config.density_quantile)
    mesh.remove_vertices_by_mask(remove | _far_from_samples(mesh, cloud, config))  # type: ignore[arg-type]
    return mesh


def _far_from_samples(
    mesh: o3d.geometry.TriangleMesh, cloud: o3d.geometry.PointCloud, config: MappingConfig
) -> np.ndarray:
    """Per vertex: farther than :func:`_trim_distance_m` from every sample (Poisson's trim)."""
    trim = _trim_distance_m(config)
    dist = np.asarray(o3d.geometry.PointCloud(mesh.vertices).compute_point_cloud_distance(cloud))
    return dist > trim


def _trim_distance_m(config: MappingConfig) -> float:
    """How far (m) a vertex may be from every sample: ``trim_distance_m``, 0: 2.5 ``voxel_m`` (both surfaces)."""
    return config.trim_distance_m or 2.5 * config.voxel_m


def preload_kernels() -> None:
    """The sdf surface's compiled kernels loaded from numba's cache into this process (a worker about to mesh).

    Their first call in a process otherwise loads them then (0.5 s CPU); ``loopmodel run`` compiles them up front
    when the cache lacks them.
    """
    from loopmodel.mapping._sdf_kernels import warm_up

    warm_up()


def _sdf(cloud: o3d.geometry.PointCloud, config: MappingConfig) -> o3d.geometry.TriangleMesh:
    """The zero set of the samples' weighted mean tangent-plane distance (``method: sdf``), trimmed as Poisson's.

    Grid cell ``poisson_cell_voxels`` x ``voxel_m`` (Poisson's finest cell); each oriented sample adds
    ``n . (x - p)`` with weight ``exp(-|x - p|^2 / (2 sigma^2))`` to the corners within ``sdf_reach_cells``
    cells (``sigma``: ``sdf_sigma_cells`` cells); corners of summed weight below ``sdf_min_weight`` have no
    value; surface nets extract the zero set (:mod:`loopmodel.mapping._sdf_kernels`). World frame, metres.
    """
    from loopmodel.mapping import _sdf_kernels as k

    pts = np.ascontiguousarray(np.asarray(cloud.points), dtype=np.float64)
    nrm = np.ascontiguousarray(np.asarray(cloud.normals), dtype=np.float64)
    h = config.poisson_cell_voxels * config.voxel_m
    reach_m = config.sdf_reach_cells * h
    origin = pts.min(axis=0) - reach_m - 2.0 * h
    dims = np.floor((pts.max(axis=0) + reach_m - origin) / h).astype(np.int64) + 3
    bdims = (dims >> k.SHIFT) + 1
    if float(np.prod(bdims.astype(np.float64))) > _SDF_MAX_BLOCKS:
        logger.warning(
            "the samples span %s cells of %.2f mm, too many for the sdf grid: screened Poisson instead",
            dims.tolist(), h * 1e3,
        )
        return _poisson(cloud, config)
    # the samples in block order: the corners each one updates are then mostly in memory the last one touched
    cell = np.floor((pts - origin) / (h * k.B)).astype(np.int64)
    by_block = np.argsort((cell[:, 0] * bdims[1] + cell[:, 1]) * bdims[2] + cell[:, 2], kind="stable")
    pts, nrm = pts[by_block], nrm[by_block]
    bmap, blocks = k.mark_blocks(pts, origin, h, reach_m, bdims)
    acc = k.splat(pts, nrm, origin, h, reach_m, config.sdf_sigma_cells * h, bmap, blocks.shape[0])
    value = k.corner_values(acc, config.sdf_min_weight)
    verts, index = k.vertices(bmap, blocks, value, origin, h)
    tris = k.faces(bmap, blocks, value, index, verts.shape[0])
    order, start = k.bucket_points(pts, origin, h, bmap, blocks.shape[0])
    if config.sdf_project_steps > 0:
        k.project(verts, pts, nrm, order, start, bmap, origin, h, reach_m, config.sdf_sigma_cells * h,
                  config.sdf_min_weight, config.sdf_project_steps)
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris.astype(np.int32))
    )
    if len(mesh.vertices) == 0:
        return mesh
    # Poisson's distance trim (_far_from_samples) on the samples' cells (fin18: 0.03 s -> ~0.005 s CPU)
    far = ~k.near_samples(verts, pts, _trim_distance_m(config), origin, h, bmap, order, start)
    mesh.remove_vertices_by_mask(far)  # type: ignore[arg-type]
    if config.sdf_min_component_cells > 0 and len(mesh.triangles):
        # a lone sample (a stray laser peak) makes a small disc of its own; Poisson's density trim drops those
        area = k.component_areas(np.asarray(mesh.vertices), np.asarray(mesh.triangles).astype(np.int64))
        mesh.remove_triangles_by_mask(area < config.sdf_min_component_cells * h * h)  # type: ignore[arg-type]
    return mesh


#: most blocks (of 8^3 corners) the sdf grid's block map may span (an int32 each: 256 MB); beyond, Poisson
_SDF_MAX_BLOCKS = 64_000_000


def _ball_pivoting(cloud: o3d.geometry.PointCloud, config: MappingConfig) -> o3d.geometry.TriangleMesh:
    radii = config.bpa_radii_m or [1.5 * config.voxel_m, 3.0 * config.voxel_m, 6.0 * config.voxel_m]
    return o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(
        cloud, o3d.utility.DoubleVector([float(r) for r in radii])
    )


def mesh_cloud(cloud: o3d.geometry.PointCloud, config: MappingConfig) -> o3d.geometry.TriangleMesh:
    """Surface of an oriented cloud with the configured method; cleaned, with vertex normals."""
    if len(cloud.points) < config.min_points:
        raise InputError(
            None,
            f"{len(cloud.points)} points after down-sampling; at least {config.min_points} are needed for a surface",
        )
    if config.method == "poisson":
        mesh = _poisson(cloud, config)
    elif config.method == "sdf":
        mesh = _sdf(cloud, config)
    else:
        mesh = _ball_pivoting(cloud, config)
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    mesh.compute_vertex_normals()
    return mesh


def mesh_from_points(points_w: F64, sensors_w: F64, config: MappingConfig) -> o3d.geometry.TriangleMesh:
    """Triangle mesh (world, metres) of stripe points seen from the given sensor positions.

    Raises :class:`InputError` when there is too little data or no surface comes out.
    """
    if np.asarray(points_w).size == 0:
        raise InputError(None, "no stripe points to mesh")
    t0 = time.perf_counter()
    cloud = oriented_cloud(points_w, sensors_w, config)
    t1 = time.perf_counter()
    mesh = mesh_cloud(cloud, config)
    logger.debug(
        "meshed %d points (%d after down-sampling): cloud+normals %.3f s, %s %.3f s, %d vertices",
        len(points_w),
        len(cloud.points),
        t1 - t0,
        config.method,
        time.perf_counter() - t1,
        len(mesh.vertices),
    )
    if len(mesh.triangles) == 0:
        raise InputError(None, "surface reconstruction produced no triangles")
    return mesh


BlockKey = tuple[int, int, int]


def live_mesh_config(config: MappingConfig) -> MappingConfig:
    """The settings of live-mesh updates.

    ``live_voxel_m`` resolution with octree cells of that size (``poisson_cell_voxels`` 1: the
    final mesh's coarser cells are not the live mesh's), one Poisson thread (the other core keeps
    tracking), the surface method ``live_method``.
    """
    update = {
        "voxel_m": config.live_voxel_m, "poisson_threads": 1, "poisson_cell_voxels": 1.0, "method": config.live_method
    }
    return config.model_copy(update=update)


def mesh_blocks(
    points_w: F64, sensors_w: F64, blocks: set[BlockKey], config: MappingConfig
) -> dict[BlockKey, o3d.geometry.TriangleMesh | None]:
    """Meshes of the live blocks ``blocks``, all from one surface reconstruction.

    Blocks are cubes of edge ``chunk_m``, keyed by ``floor(p / chunk_m)``; ONE surface
    reconstruction of the points in these blocks and their 26 neighbours (context for the surface
    near block faces); each block keeps the triangles whose centroid lies inside it. None for a
    block without triangles or when the selection is too small for a surface. Points and sensors:
    P x 3, world, metres.
    """
    out: dict[BlockKey, o3d.geometry.TriangleMesh | None] = dict.fromkeys(blocks)
    if not blocks or points_w.shape[0] == 0:
        return out
    keys = np.floor(points_w / config.chunk_m).astype(np.int64)
    wanted = np.array(sorted(blocks), dtype=np.int64)
    offs = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    context, _ = _unique_rows((wanted[:, None, :] + offs[None]).reshape(-1, 3))
    near = _rows_in(keys, context)
    if np.count_nonzero(near) < config.min_points:
        return out
    try:
        mesh = mesh_from_points(points_w[near], sensors_w[near], config)
    except InputError:
        return out
    v = np.asarray(mesh.vertices)
    t = np.asarray(mesh.triangles)
    tri_key = np.floor(v[t].mean(axis=1) / config.chunk_m).astype(np.int64)
    normals = np.asarray(mesh.vertex_normals)
    # the triangles grouped by block once (live19: a comparison of every triangle with every block took
    # 2.0 of a 7.0 s live update on the 600-frame sample, 1.1 of 2.2 s with the sdf), each block's in order
    wanted_tri = _rows_in(tri_key, wanted)
    idx = np.flatnonzero(wanted_tri)
    if idx.size == 0:
        return out
    uniq, inverse = _unique_rows(tri_key[idx])
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(uniq) + 1))
    for b, key_row in enumerate(uniq.tolist()):
        key = (key_row[0], key_row[1], key_row[2])
        if key not in out:
            continue
        sel = idx[order[bounds[b] : bounds[b + 1]]]
        used, inv = np.unique(t[sel], return_inverse=True)
        part = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(v[used]), o3d.utility.Vector3iVector(inv.reshape(-1, 3).astype(np.int32))
        )
        part.vertex_normals = o3d.utility.Vector3dVector(normals[used])
        out[key] = part
    return out


def _row_codes(*arrays: NDArray[np.int64]) -> list[NDArray[np.int64]]:
    """One int64 a row of each N x 3 int array (one at least not empty), in lexicographic row order."""
    full = [x for x in arrays if x.size]
    lo = np.min([x.min(axis=0) for x in full], axis=0)
    span = np.max([x.max(axis=0) for x in full], axis=0) - lo + 1
    return [((x[:, 0] - lo[0]) * span[1] + (x[:, 1] - lo[1])) * span[2] + (x[:, 2] - lo[2]) for x in arrays]


def _rows_in(rows: NDArray[np.int64], table: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Which rows of ``rows`` (N x 3 ints) occur in ``table`` (M x 3 ints)."""
    a, b = _row_codes(rows, table)
    return np.isin(a, b)


def _unique_rows(rows: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.intp]]:
    """``np.unique(rows, axis=0, return_inverse=True)`` of N x 3 ints (N >= 1), the inverse flat.

    By one int64 a row (live20: 5 vs 63 ms for the 97,000 triangles of a 197-block live update).
    """
    (code,) = _row_codes(rows)
    _, first, inverse = np.unique(code, return_index=True, return_inverse=True)
    return rows[first], inverse.reshape(-1)
