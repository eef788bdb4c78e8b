"""Compiled kernels of the signed-distance surface (``mapping.method: sdf``; numba, GIL released).

The signed distance is sampled at the corners of a grid of cell ``h`` (metres, world frame): corner
``(i, j, k)`` is at ``origin + h * (i, j, k)``. Only blocks of ``B^3`` corners near a sample are stored:
``bmap[bi, bj, bk]`` is the slot of block ``(bi, bj, bk)`` (``i >> 3`` ...) in the per-corner arrays of
shape (blocks, ``B^3``), or -1. Corner ``(i, j, k)`` is entry ``((i & 7) * B + (j & 7)) * B + (k & 7)`` of its slot.

- :func:`mark_blocks` makes ``bmap`` (blocks within ``reach_m`` of a sample);
- :func:`splat` adds each oriented sample, with a Gaussian weight of its distance ``|x - p|``, to the sums
  of every corner within ``reach_m``; :func:`corner_values` turns them into the signed distance: the mean
  of the distance to the samples' tangent planes ``<n . (x - p)>`` and to the plane of the mean normal
  through the weighted centroid (an implicit moving least-squares surface: Hoppe et al. 1992, Kolluri 2008);
- :func:`vertices` and :func:`faces` extract its zero set over corners of enough weight (surface nets):
  one vertex per cell the surface crosses, two triangles per crossed edge, oriented so that their
  normals point to the positive (sensor) side; :func:`project` moves each vertex by Newton steps onto the
  field evaluated at it;
- :func:`component_areas` gives each triangle the area of its vertex-connected piece (small pieces dropped).
- :func:`near_samples` tells the vertices within the trim distance of a sample (the samples bucketed by cell);
- :func:`normals` gives each sample the normal of its nearest samples within a radius (the covariance's least
  eigenvector by Jacobi rotations), searched over the same kind of grid (fin18: in place of open3d's k-d tree).
"""

from __future__ import annotations

import math

import numba
import numpy as np

B = 8  # corners per block edge
SHIFT = 3  # log2(B)
MASK = B - 1


def _slot_py(bmap, i, j, k):  # type: ignore[no-untyped-def]
    """The block slot of corner (i, j, k), -1 outside the grid or in an unstored block."""
    if i < 0 or j < 0 or k < 0:
        return -1
    bi, bj, bk = i >> SHIFT, j >> SHIFT, k >> SHIFT
    if bi >= bmap.shape[0] or bj >= bmap.shape[1] or bk >= bmap.shape[2]:
        return -1
    return bmap[bi, bj, bk]


_slot = numba.njit(cache=True, nogil=True, inline="always")(_slot_py)


def _local_py(i, j, k):  # type: ignore[no-untyped-def]
    """The entry of corner (i, j, k) in its block's row."""
    return (((i & MASK) << SHIFT) + (j & MASK)) * B + (k & MASK)


_local = numba.njit(cache=True, nogil=True, inline="always")(_local_py)


def _value_py(bmap, value, i, j, k):  # type: ignore[no-untyped-def]
    """The field at corner (i, j, k); NaN where there is none."""
    s = _slot(bmap, i, j, k)
    if s < 0:
        return np.nan
    return value[s, _local(i, j, k)]


_value = numba.njit(cache=True, nogil=True, inline="always")(_value_py)


def _mark_blocks_py(points, origin, h, reach_m, bdims):  # type: ignore[no-untyped-def]
    """The block map and the stored blocks' coordinates (slot order, blocks x 3).

    ``bmap`` (``bdims``, int32) has a slot for every block holding a corner within ``reach_m`` of a point.
    """
    bmap = np.full((bdims[0], bdims[1], bdims[2]), -1, np.int32)
    count = 0
    lo = np.zeros(3, np.int64)
    hi = np.zeros(3, np.int64)
    for p in range(points.shape[0]):
        for a in range(3):
            lo[a] = max(int(math.ceil((points[p, a] - reach_m - origin[a]) / h)), 0) >> SHIFT
            hi[a] = min(int(math.floor((points[p, a] + reach_m - origin[a]) / h)) >> SHIFT, bdims[a] - 1)
        for bi in range(lo[0], hi[0] + 1):
            for bj in range(lo[1], hi[1] + 1):
                for bk in range(lo[2], hi[2] + 1):
                    if bmap[bi, bj, bk] < 0:
                        bmap[bi, bj, bk] = count
                        count += 1
    blocks = np.zeros((count, 3), np.int64)
    for bi in range(bdims[0]):
        for bj in range(bdims[1]):
            for bk in range(bdims[2]):
                s = bmap[bi, bj, bk]
                if s >= 0:
                    blocks[s, 0], blocks[s, 1], blocks[s, 2] = bi, bj, bk
    return bmap, blocks


mark_blocks = numba.njit(cache=True, nogil=True)(_mark_blocks_py)


def _splat_py(points, normals, origin, h, reach_m, sigma_m, bmap, nblocks):  # type: ignore[no-untyped-def]
    """Per corner (blocks x B^3 x 8) the Gaussian-weighted sums of the samples within ``reach_m``.

    The sums: weight, normal (3), position (3, relative to the corner) and ``n . (p - x)``. The weight
    ``exp(-|x - p|^2 / (2 sigma^2))`` as the product of its three axes' factors, each made once a sample
    (fin17: 21 exponentials a sample instead of one a corner within reach, ~113; the splat 0.112 -> 0.087 s
    CPU on the 150-frame orbit's cloud, the sums within 4e-16 of each corner's own exponential).
    """
    acc = np.zeros((nblocks, B * B * B, 8))
    r2max = reach_m * reach_m
    inv2s2 = 0.5 / (sigma_m * sigma_m)
    n_axis = int(math.ceil(2.0 * reach_m / h)) + 2  # the corners within reach along one axis, at most
    ex = np.empty(n_axis)
    ey = np.empty(n_axis)
    ez = np.empty(n_axis)
    for p in range(points.shape[0]):
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        nx, ny, nz = normals[p, 0], normals[p, 1], normals[p, 2]
        i0 = max(int(math.ceil((px - reach_m - origin[0]) / h)), 0)
        j0 = max(int(math.ceil((py - reach_m - origin[1]) / h)), 0)
        z0 = max(int(math.ceil((pz - reach_m - origin[2]) / h)), 0)
        i1 = int(math.floor((px + reach_m - origin[0]) / h))
        j1 = int(math.floor((py + reach_m - origin[1]) / h))
        z1 = int(math.floor((pz + reach_m - origin[2]) / h))
        for i in range(i0, i1 + 1):
            dx = px - origin[0] - i * h
            ex[i - i0] = math.exp(-dx * dx * inv2s2)
        for j in range(j0, j1 + 1):
            dy = py - origin[1] - j * h
            ey[j - j0] = math.exp(-dy * dy * inv2s2)
        for k in range(z0, z1 + 1):
            dz = pz - origin[2] - k * h
            ez[k - z0] = math.exp(-dz * dz * inv2s2)
        for i in range(i0, i1 + 1):
            dx = px - origin[0] - i * h
            for j in range(j0, j1 + 1):
                dy = py - origin[1] - j * h
                rest = r2max - dx * dx - dy * dy
                if rest < 0.0:
                    continue
                half = math.sqrt(rest)  # the corners of this column within reach
                k0 = max(int(math.ceil((pz - half - origin[2]) / h)), 0)
                k1 = int(math.floor((pz + half - origin[2]) / h))
                wxy = ex[i - i0] * ey[j - j0]
                for k in range(k0, k1 + 1):
                    s = _slot(bmap, i, j, k)
                    if s < 0:
                        continue
                    dz = pz - origin[2] - k * h
                    w = wxy * ez[k - z0]
                    e = _local(i, j, k)
                    acc[s, e, 0] += w
                    acc[s, e, 1] += w * nx
                    acc[s, e, 2] += w * ny
                    acc[s, e, 3] += w * nz
                    acc[s, e, 4] += w * dx
                    acc[s, e, 5] += w * dy
                    acc[s, e, 6] += w * dz
                    acc[s, e, 7] += w * (nx * dx + ny * dy + nz * dz)
    return acc


splat = numba.njit(cache=True, nogil=True)(_splat_py)


def _corner_values_py(acc, min_weight):  # type: ignore[no-untyped-def]
    """The signed distance per corner (blocks x B^3); NaN below ``min_weight``.

    The mean of two estimates at the corner ``x``: the weighted mean distance to the samples' tangent planes,
    ``<n . (x - p)>``, and the distance to the plane of the mean normal through the weighted centroid,
    ``<n> . (x - <p>)``. On a curved surface they are off to opposite sides by the same amount to second
    order (for a surface ``z = (k1 u^2 + k2 v^2) / 2`` sampled evenly about the corner: ``-/+ <k1 u^2 + k2 v^2> / 2``),
    so their mean has no curvature bias of that order.
    """
    value = np.full(acc.shape[:2], np.nan)
    for s in range(acc.shape[0]):
        for e in range(acc.shape[1]):
            a = acc[s, e]
            w = a[0]
            if w < min_weight or w <= 0.0:
                continue
            f_planes = -a[7] / w
            f_centroid = -(a[1] * a[4] + a[2] * a[5] + a[3] * a[6]) / (w * w)
            value[s, e] = 0.5 * (f_planes + f_centroid)
    return value


corner_values = numba.njit(cache=True, nogil=True)(_corner_values_py)


def _cell_values_py(bmap, value, i, j, k, f):  # type: ignore[no-untyped-def]
    """Whether all 8 corner values of cell (i, j, k) are there and the surface crosses the cell.

    The values into ``f`` (corner ``c``: offset bits x=4, y=2, z=1).
    """
    neg = 0
    for c in range(8):
        v = _value(bmap, value, i + (c >> 2), j + ((c >> 1) & 1), k + (c & 1))
        if np.isnan(v):
            return False
        f[c] = v
        if v < 0.0:
            neg += 1
    return 0 < neg < 8


_cell_values = numba.njit(cache=True, nogil=True)(_cell_values_py)


def _cell_vertex_py(f, out):  # type: ignore[no-untyped-def]
    """The surface's point in a unit cell of corner values ``f``, into ``out`` (cell units).

    The mean of its edges' zero crossings, then one Newton step of the trilinear field towards zero along its
    gradient, kept in the cell.
    """
    sx = sy = sz = 0.0
    n = 0
    for c in range(8):
        for bit in (4, 2, 1):
            if c & bit:
                continue
            d = c | bit
            if (f[c] < 0.0) == (f[d] < 0.0):
                continue
            t = f[c] / (f[c] - f[d])
            x, y, z = float(c >> 2), float((c >> 1) & 1), float(c & 1)
            if bit == 4:
                x = t
            elif bit == 2:
                y = t
            else:
                z = t
            sx += x
            sy += y
            sz += z
            n += 1
    x, y, z = sx / n, sy / n, sz / n
    # trilinear value and gradient at (x, y, z)
    val = gx = gy = gz = 0.0
    for c in range(8):
        cx, cy, cz = c >> 2, (c >> 1) & 1, c & 1
        wx = x if cx else 1.0 - x
        wy = y if cy else 1.0 - y
        wz = z if cz else 1.0 - z
        sgx = 1.0 if cx else -1.0
        sgy = 1.0 if cy else -1.0
        sgz = 1.0 if cz else -1.0
        val += f[c] * wx * wy * wz
        gx += f[c] * sgx * wy * wz
        gy += f[c] * wx * sgy * wz
        gz += f[c] * wx * wy * sgz
    g2 = gx * gx + gy * gy + gz * gz
    if g2 > 0.0:
        x = min(max(x - val * gx / g2, 0.0), 1.0)
        y = min(max(y - val * gy / g2, 0.0), 1.0)
        z = min(max(z - val * gz / g2, 0.0), 1.0)
    out[0], out[1], out[2] = x, y, z


_cell_vertex = numba.njit(cache=True, nogil=True)(_cell_vertex_py)


def _vertices_py(bmap, blocks, value, origin, h):  # type: ignore[no-untyped-def]
    """One vertex (world, metres) per crossed cell; the cells' vertex indices (blocks x B^3, -1 where none)."""
    nb = blocks.shape[0]
    index = np.full((nb, B * B * B), -1, np.int64)
    f = np.zeros(8)
    count = 0
    for s in range(nb):
        for e in range(B * B * B):
            i = (blocks[s, 0] << SHIFT) + (e >> (2 * SHIFT))
            j = (blocks[s, 1] << SHIFT) + ((e >> SHIFT) & MASK)
            k = (blocks[s, 2] << SHIFT) + (e & MASK)
            if _cell_values(bmap, value, i, j, k, f):
                index[s, e] = count
                count += 1
    verts = np.zeros((count, 3))
    u = np.zeros(3)
    for s in range(nb):
        for e in range(B * B * B):
            v = index[s, e]
            if v < 0:
                continue
            i = (blocks[s, 0] << SHIFT) + (e >> (2 * SHIFT))
            j = (blocks[s, 1] << SHIFT) + ((e >> SHIFT) & MASK)
            k = (blocks[s, 2] << SHIFT) + (e & MASK)
            _cell_values(bmap, value, i, j, k, f)
            _cell_vertex(f, u)
            verts[v, 0] = origin[0] + (i + u[0]) * h
            verts[v, 1] = origin[1] + (j + u[1]) * h
            verts[v, 2] = origin[2] + (k + u[2]) * h
    return verts, index


vertices = numba.njit(cache=True, nogil=True)(_vertices_py)


def _cell_index_py(bmap, index, i, j, k):  # type: ignore[no-untyped-def]
    """The vertex of cell (i, j, k), -1 when none."""
    s = _slot(bmap, i, j, k)
    if s < 0:
        return -1
    return index[s, _local(i, j, k)]


_cell_index = numba.njit(cache=True, nogil=True, inline="always")(_cell_index_py)


def _quad_py(bmap, index, i, j, k, a, negative, quad):  # type: ignore[no-untyped-def]
    """Whether the 4 cells around the edge from corner (i, j, k) along axis ``a`` all have vertices.

    Their vertices into ``quad``, counter-clockwise about the surface's normal (towards positive values;
    ``negative``: the corner's value is below zero, the normal is +a).
    """
    for q in range(4):
        # (0, 0), (-1, 0), (-1, -1), (0, -1) in the axes (a + 1, a + 2): counter-clockwise about +a
        ob = -1 if q == 1 or q == 2 else 0
        od = -1 if q >= 2 else 0
        if a == 0:
            v = _cell_index(bmap, index, i, j + ob, k + od)
        elif a == 1:
            v = _cell_index(bmap, index, i + od, j, k + ob)
        else:
            v = _cell_index(bmap, index, i + ob, j + od, k)
        if v < 0:
            return False
        quad[q if negative else 3 - q] = v
    return True


_quad = numba.njit(cache=True, nogil=True, inline="always")(_quad_py)


def _faces_py(bmap, blocks, value, index, n_vertices):  # type: ignore[no-untyped-def]
    """Two triangles (vertex indices, T x 3) per crossed edge whose four cells have vertices.

    A cell's vertex has at most 12 crossed edges, each shared by 4 cells: at most 6 triangles a vertex.
    """
    tris = np.empty((6 * n_vertices, 3), np.int64)
    quad = np.zeros(4, np.int64)
    count = 0
    for s in range(blocks.shape[0]):
        for e in range(B * B * B):
            f0 = value[s, e]
            if np.isnan(f0):
                continue
            i = (blocks[s, 0] << SHIFT) + (e >> (2 * SHIFT))
            j = (blocks[s, 1] << SHIFT) + ((e >> SHIFT) & MASK)
            k = (blocks[s, 2] << SHIFT) + (e & MASK)
            for a in range(3):
                if a == 0:
                    f1 = _value(bmap, value, i + 1, j, k)
                elif a == 1:
                    f1 = _value(bmap, value, i, j + 1, k)
                else:
                    f1 = _value(bmap, value, i, j, k + 1)
                if np.isnan(f1) or (f0 < 0.0) == (f1 < 0.0):
                    continue
                if not _quad(bmap, index, i, j, k, a, f0 < 0.0, quad):
                    continue
                tris[count, 0], tris[count, 1], tris[count, 2] = quad[0], quad[1], quad[2]
                tris[count + 1, 0], tris[count + 1, 1], tris[count + 1, 2] = quad[0], quad[2], quad[3]
                count += 2
    return tris[:count].copy()


faces = numba.njit(cache=True, nogil=True)(_faces_py)


def _bucket_points_py(points, origin, h, bmap, nblocks):  # type: ignore[no-untyped-def]
    """The points by grid cell: the point indices in that order and each cell's first position in it.

    A cell is keyed by its lowest corner's entry ``slot * B^3 + local``; ``nblocks * B^3 + 1`` start positions.
    """
    n_cells = nblocks * B * B * B
    start = np.zeros(n_cells + 1, np.int64)
    key = np.full(points.shape[0], -1, np.int64)
    for p in range(points.shape[0]):
        i = int(math.floor((points[p, 0] - origin[0]) / h))
        j = int(math.floor((points[p, 1] - origin[1]) / h))
        k = int(math.floor((points[p, 2] - origin[2]) / h))
        s = _slot(bmap, i, j, k)
        if s >= 0:
            key[p] = s * (B * B * B) + _local(i, j, k)
            start[key[p] + 1] += 1
    for c in range(n_cells):
        start[c + 1] += start[c]
    order = np.zeros(start[n_cells], np.int64)
    fill = start[:-1].copy()
    for p in range(points.shape[0]):
        if key[p] >= 0:
            order[fill[key[p]]] = p
            fill[key[p]] += 1
    return order, start


bucket_points = numba.njit(cache=True, nogil=True)(_bucket_points_py)


def _field_at_py(x, points, normals, order, start, bmap, origin, h, reach_m, inv2s2, a):  # type: ignore[no-untyped-def]
    """The squared distance (m^2) from ``x`` to the nearest sample within ``reach_m`` (``inf`` without one).

    The weighted sums of :func:`splat` at the point ``x`` (world, metres) into ``a`` (8).
    """
    a[:] = 0.0
    r2max = reach_m * reach_m
    nearest = np.inf
    i0 = int(math.floor((x[0] - reach_m - origin[0]) / h))
    i1 = int(math.floor((x[0] + reach_m - origin[0]) / h))
    j0 = int(math.floor((x[1] - reach_m - origin[1]) / h))
    j1 = int(math.floor((x[1] + reach_m - origin[1]) / h))
    for i in range(i0, i1 + 1):
        # the distance from x to cell column (i, j)'s nearest side: cells wholly beyond reach are skipped
        gx = max(origin[0] + i * h - x[0], x[0] - origin[0] - (i + 1) * h, 0.0)
        for j in range(j0, j1 + 1):
            gy = max(origin[1] + j * h - x[1], x[1] - origin[1] - (j + 1) * h, 0.0)
            rest = r2max - gx * gx - gy * gy
            if rest < 0.0:
                continue
            half = math.sqrt(rest)
            k0 = int(math.floor((x[2] - half - origin[2]) / h))
            k1 = int(math.floor((x[2] + half - origin[2]) / h))
            for k in range(k0, k1 + 1):
                s = _slot(bmap, i, j, k)
                if s < 0:
                    continue
                c = s * (B * B * B) + _local(i, j, k)
                for q in range(start[c], start[c + 1]):
                    p = order[q]
                    dx = points[p, 0] - x[0]
                    dy = points[p, 1] - x[1]
                    dz = points[p, 2] - x[2]
                    r2 = dx * dx + dy * dy + dz * dz
                    if r2 > r2max:
                        continue
                    nearest = min(nearest, r2)
                    w = math.exp(-r2 * inv2s2)
                    nx, ny, nz = normals[p, 0], normals[p, 1], normals[p, 2]
                    a[0] += w
                    a[1] += w * nx
                    a[2] += w * ny
                    a[3] += w * nz
                    a[4] += w * dx
                    a[5] += w * dy
                    a[6] += w * dz
                    a[7] += w * (nx * dx + ny * dy + nz * dz)
    return nearest


_field_at = numba.njit(cache=True, nogil=True)(_field_at_py)


def _project_py(verts, points, normals, order, start, bmap, origin, h, reach_m, sigma_m, min_weight, steps):  # type: ignore[no-untyped-def]
    """The vertices moved onto the zero set of the field of :func:`corner_values`, in place (world frame, metres).

    The field evaluated at each vertex, not interpolated between corners (whose linear interpolation of a curved
    surface's distance puts the crossings inside it); ``steps`` Newton steps along the mean normal.
    """
    inv2s2 = 0.5 / (sigma_m * sigma_m)
    a = np.zeros(8)
    x = np.zeros(3)
    for v in range(verts.shape[0]):
        for _ in range(steps):
            x[0], x[1], x[2] = verts[v, 0], verts[v, 1], verts[v, 2]
            _field_at(x, points, normals, order, start, bmap, origin, h, reach_m, inv2s2, a)
            w = a[0]
            if w < min_weight or w <= 0.0:
                break
            f = 0.5 * (-a[7] / w - (a[1] * a[4] + a[2] * a[5] + a[3] * a[6]) / (w * w))
            gx, gy, gz = a[1] / w, a[2] / w, a[3] / w
            g2 = gx * gx + gy * gy + gz * gz
            if g2 < 0.25:  # normals that disagree: no reliable direction
                break
            verts[v, 0] -= f * gx / g2
            verts[v, 1] -= f * gy / g2
            verts[v, 2] -= f * gz / g2


project = numba.njit(cache=True, nogil=True)(_project_py)


def _nearest_insert_py(d2, o, n, max_nn, bd, bi):  # type: ignore[no-untyped-def]
    """Point ``o`` at squared distance ``d2`` into the ascending ``bd`` / ``bi`` of the ``n`` nearest; the new ``n``."""
    m = n if n < max_nn else max_nn - 1
    while m > 0 and bd[m - 1] > d2:
        bd[m] = bd[m - 1]
        bi[m] = bi[m - 1]
        m -= 1
    bd[m] = d2
    bi[m] = o
    return min(n + 1, max_nn)


_nearest_insert = numba.njit(cache=True, nogil=True, inline="always")(_nearest_insert_py)


def _cell_gap_py(x, origin, h, i):  # type: ignore[no-untyped-def]
    """The distance (m) from coordinate ``x`` to the cell span ``[origin + i h, origin + (i + 1) h]`` (0 inside)."""
    return max(origin + i * h - x, x - origin - (i + 1) * h, 0.0)


_cell_gap = numba.njit(cache=True, nogil=True, inline="always")(_cell_gap_py)


def _shell_py(points, p, c, R, bound, n, max_nn, bd, bi, origin, h, bmap, order, start):  # type: ignore[no-untyped-def]
    """The cells of the shell ``R`` cells around cell ``c`` of point ``p`` searched; the new count of nearest found."""
    px, py, pz = points[p, 0], points[p, 1], points[p, 2]
    for i in range(c[0] - R, c[0] + R + 1):
        gx = _cell_gap(px, origin[0], h, i)
        for j in range(c[1] - R, c[1] + R + 1):
            gy = _cell_gap(py, origin[1], h, j)
            gxy = gx * gx + gy * gy
            if gxy > bound[0]:
                continue
            face = R == 0 or i == c[0] - R or i == c[0] + R or j == c[1] - R or j == c[1] + R
            step = 1 if face else 2 * R  # inside the shell's side faces only its two caps along z
            for k in range(c[2] - R, c[2] + R + 1, max(step, 1)):
                gz = _cell_gap(pz, origin[2], h, k)
                s = _slot(bmap, i, j, k)
                if s < 0 or gxy + gz * gz > bound[0]:
                    continue
                e = s * (B * B * B) + _local(i, j, k)
                for q in range(start[e], start[e + 1]):
                    o = order[q]
                    dx, dy, dz = points[o, 0] - px, points[o, 1] - py, points[o, 2] - pz
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 > bound[0] or (n == max_nn and d2 >= bd[n - 1]):
                        continue
                    n = _nearest_insert(d2, o, n, max_nn, bd, bi)
                    if n == max_nn:
                        bound[0] = bd[n - 1]
    return n


_shell = numba.njit(cache=True, nogil=True, inline="always")(_shell_py)


def _nearest_py(points, p, radius_m, max_nn, bd, bi, c, bound, origin, h, bmap, order, start):  # type: ignore[no-untyped-def]
    """The ``max_nn`` points nearest to point ``p`` within ``radius_m`` (``p`` itself among them) into ``bi``; how many.

    Shells of cells around ``p``'s cell until every point nearer than the farthest kept one has been seen.
    ``c`` (3 ints) and ``bound`` (1) are work space.
    """
    for a in range(3):
        c[a] = int(math.floor((points[p, a] - origin[a]) / h))
    bound[0] = radius_m * radius_m
    n = 0
    for R in range(int(math.ceil(radius_m / h)) + 1):
        n = _shell(points, p, c, R, bound, n, max_nn, bd, bi, origin, h, bmap, order, start)
        seen = np.inf  # every point this near to p lies in the cells searched so far
        for a in range(3):
            seen = min(seen, points[p, a] - origin[a] - (c[a] - R) * h, origin[a] + (c[a] + R + 1) * h - points[p, a])
        if seen * seen >= bound[0]:
            break
    return n


_nearest = numba.njit(cache=True, nogil=True, inline="always")(_nearest_py)


def _jacobi3_py(a, vals, vecs, v):  # type: ignore[no-untyped-def]
    """Eigen-decomposition of the symmetric 3 x 3 ``a`` (overwritten) by cyclic Jacobi rotations.

    ``vals`` ascending, ``vecs[:, m]`` the unit eigenvector of ``vals[m]``; ``v`` (3 x 3) work space.
    """
    for r in range(3):
        for m in range(3):
            v[r, m] = 1.0 if r == m else 0.0
    for _ in range(50):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        diag = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= 1e-36 * diag or off == 0.0:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            if a[p, q] == 0.0:
                continue
            theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
            t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
            cs = 1.0 / math.sqrt(t * t + 1.0)
            sn = t * cs
            for r in range(3):  # a <- a J (columns p, q)
                arp, arq = a[r, p], a[r, q]
                a[r, p] = cs * arp - sn * arq
                a[r, q] = sn * arp + cs * arq
            for r in range(3):  # a <- J^T a (rows p, q)
                apr, aqr = a[p, r], a[q, r]
                a[p, r] = cs * apr - sn * aqr
                a[q, r] = sn * apr + cs * aqr
            for r in range(3):
                vrp, vrq = v[r, p], v[r, q]
                v[r, p] = cs * vrp - sn * vrq
                v[r, q] = sn * vrp + cs * vrq
    lo, hi = 0, 0  # the diagonal's order (ties: the lower index first, as a stable sort)
    for m in range(1, 3):
        if a[m, m] < a[lo, lo]:
            lo = m
        if a[m, m] >= a[hi, hi]:
            hi = m
    if lo == hi:  # all equal
        lo, hi = 0, 2
    mid = 3 - lo - hi
    for m, s in ((0, lo), (1, mid), (2, hi)):
        vals[m] = a[s, s]
        for r in range(3):
            vecs[r, m] = v[r, s]


_jacobi3 = numba.njit(cache=True, nogil=True, inline="always")(_jacobi3_py)


def _neighbour_covariance_py(points, bi, n, cov):  # type: ignore[no-untyped-def]
    """The covariance (m^2) of the ``n`` points ``bi`` into ``cov`` (3 x 3); the identity below 3 points (open3d's)."""
    cov[:, :] = 0.0
    if n < 3:
        for a in range(3):
            cov[a, a] = 1.0
        return
    mx = my = mz = 0.0
    for t in range(n):
        mx += points[bi[t], 0]
        my += points[bi[t], 1]
        mz += points[bi[t], 2]
    mx, my, mz = mx / n, my / n, mz / n
    for t in range(n):
        dx, dy, dz = points[bi[t], 0] - mx, points[bi[t], 1] - my, points[bi[t], 2] - mz
        cov[0, 0] += dx * dx
        cov[0, 1] += dx * dy
        cov[0, 2] += dx * dz
        cov[1, 1] += dy * dy
        cov[1, 2] += dy * dz
        cov[2, 2] += dz * dz
    for a in range(3):
        for b in range(a, 3):
            cov[a, b] /= n
            cov[b, a] = cov[a, b]


_neighbour_covariance = numba.njit(cache=True, nogil=True, inline="always")(_neighbour_covariance_py)


def _normals_py(points, view, radius_m, max_nn, line_ratio, origin, h, bmap, order, start):  # type: ignore[no-untyped-def]
    """Per point (P x 3, world, metres) the unit normal of its ``max_nn`` nearest points within ``radius_m``.

    The covariance's least eigenvector, turned toward ``view`` (P x 3, unit, to the sensor); where the
    neighbourhood is (nearly) a line (middle eigenvalue below ``line_ratio`` x the largest) the view direction
    made perpendicular to the line instead. ``order`` / ``start``: :func:`bucket_points` of ``points``.
    """
    out = np.empty_like(points)
    bd = np.empty(max_nn)
    bi = np.empty(max_nn, np.int64)
    cov = np.empty((3, 3))
    vals = np.empty(3)
    vecs = np.empty((3, 3))
    work = np.empty((3, 3))
    c = np.empty(3, np.int64)
    bound = np.empty(1)
    for q in range(order.shape[0]):  # in cell order: neighbouring queries touch the same cells
        p = order[q]
        n = _nearest(points, p, radius_m, max_nn, bd, bi, c, bound, origin, h, bmap, order, start)
        _neighbour_covariance(points, bi, n, cov)
        _jacobi3(cov, vals, vecs, work)
        nx, ny, nz = vecs[0, 0], vecs[1, 0], vecs[2, 0]
        if vals[1] < line_ratio * max(vals[2], 1e-30):
            tx, ty, tz = vecs[0, 2], vecs[1, 2], vecs[2, 2]
            along = view[p, 0] * tx + view[p, 1] * ty + view[p, 2] * tz
            nx, ny, nz = view[p, 0] - along * tx, view[p, 1] - along * ty, view[p, 2] - along * tz
            norm = max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-12)
            nx, ny, nz = nx / norm, ny / norm, nz / norm
        if nx * view[p, 0] + ny * view[p, 1] + nz * view[p, 2] < 0.0:
            nx, ny, nz = -nx, -ny, -nz
        out[p, 0], out[p, 1], out[p, 2] = nx, ny, nz
    return out


normals = numba.njit(cache=True, nogil=True)(_normals_py)


def _near_samples_py(verts, points, limit_m, origin, h, bmap, order, start):  # type: ignore[no-untyped-def]
    """Per vertex (V x 3, world, metres): whether a sample of ``points`` lies within ``limit_m`` of it."""
    out = np.zeros(verts.shape[0], np.bool_)
    l2 = limit_m * limit_m
    for v in range(verts.shape[0]):
        x, y, z = verts[v, 0], verts[v, 1], verts[v, 2]
        i0, i1 = int(math.floor((x - limit_m - origin[0]) / h)), int(math.floor((x + limit_m - origin[0]) / h))
        j0, j1 = int(math.floor((y - limit_m - origin[1]) / h)), int(math.floor((y + limit_m - origin[1]) / h))
        k0, k1 = int(math.floor((z - limit_m - origin[2]) / h)), int(math.floor((z + limit_m - origin[2]) / h))
        found = False
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                for k in range(k0, k1 + 1):
                    s = _slot(bmap, i, j, k)
                    if s < 0:
                        continue
                    e = s * (B * B * B) + _local(i, j, k)
                    for q in range(start[e], start[e + 1]):
                        p = order[q]
                        dx, dy, dz = points[p, 0] - x, points[p, 1] - y, points[p, 2] - z
                        if dx * dx + dy * dy + dz * dz <= l2:
                            found = True
                            break
                    if found:
                        break
                if found:
                    break
            if found:
                break
        out[v] = found
    return out


near_samples = numba.njit(cache=True, nogil=True)(_near_samples_py)


def _root_py(parent, v):  # type: ignore[no-untyped-def]
    """The root of ``v`` in the union-find forest ``parent`` (halving the path on the way)."""
    while parent[v] != v:
        parent[v] = parent[parent[v]]
        v = parent[v]
    return v


_root = numba.njit(cache=True, nogil=True, inline="always")(_root_py)


def _component_areas_py(verts, tris):  # type: ignore[no-untyped-def]
    """Per triangle, the area (m^2) of the edge-connected piece of the mesh it belongs to (union-find over vertices)."""
    parent = np.arange(verts.shape[0])
    for t in range(tris.shape[0]):
        r0 = _root(parent, tris[t, 0])
        for c in range(1, 3):
            r = _root(parent, tris[t, c])
            if r != r0:
                parent[r] = r0
    area = np.zeros(verts.shape[0])
    tri_area = np.zeros(tris.shape[0])
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ux, uy, uz = verts[b, 0] - verts[a, 0], verts[b, 1] - verts[a, 1], verts[b, 2] - verts[a, 2]
        vx, vy, vz = verts[c, 0] - verts[a, 0], verts[c, 1] - verts[a, 1], verts[c, 2] - verts[a, 2]
        cx, cy, cz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        tri_area[t] = 0.5 * math.sqrt(cx * cx + cy * cy + cz * cz)
        area[_root(parent, a)] += tri_area[t]
    out = np.zeros(tris.shape[0])
    for t in range(tris.shape[0]):
        out[t] = area[_root(parent, tris[t, 0])]
    return out


component_areas = numba.njit(cache=True, nogil=True)(_component_areas_py)


def warm_up() -> None:
    """Load (or compile) the kernels: their first call's cost, up front (a small plane)."""
    g = np.linspace(0.0, 0.02, 8)
    x, y = np.meshgrid(g, g)
    pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, 0.0101)], 1)
    nrm = np.tile(np.array([0.0, 0.0, 1.0]), (pts.shape[0], 1))
    origin = np.full(3, -0.01)
    h = 0.003
    bdims = np.full(3, 2, np.int64)
    bmap, blocks = mark_blocks(pts, origin, h, 0.006, bdims)
    acc = splat(pts, nrm, origin, h, 0.006, 0.003, bmap, blocks.shape[0])
    value = corner_values(acc, 0.1)
    v, index = vertices(bmap, blocks, value, origin, h)
    t = faces(bmap, blocks, value, index, v.shape[0])
    component_areas(v, t)
    order, start = bucket_points(pts, origin, h, bmap, blocks.shape[0])
    project(v, pts, nrm, order, start, bmap, origin, h, 0.006, 0.003, 0.1, 1)
    near_samples(v, pts, 0.004, origin, h, bmap, order, start)
    normals(pts, nrm, 0.012, 20, 0.003, origin, h, bmap, order, start)
