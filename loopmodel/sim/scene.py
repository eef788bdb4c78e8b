"""Synthetic scene.

An object (bust, box or a mix of shapes) about 0.5 m tall on a table in a room, as one triangle mesh
with a material per triangle.

World frame: metres, z up, origin at the centre of the table top (the object stands on it).
Each material maps a procedural texture onto the surface by tri-planar projection of the 3-D
surface point (``texel_m`` metres per texel), so the appearance is a fixed function of the
surface point and identical from every view.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from loopmodel.sim.texture import make_texture

F64 = NDArray[np.float64]

TABLE_SIZE_M = (1.2, 0.8, 0.04)
TABLE_HEIGHT_M = 0.75
ROOM_HALF_M = (2.2, 2.6)
ROOM_TOP_M = 1.85
CREASE_DEG = 35.0


@dataclass(frozen=True)
class Material:
    """How a texture is put on a surface: texture index, metres per texel, albedo gain."""

    texture: int
    texel_m: float
    gain: float = 1.0


@dataclass
class Part:
    """One named mesh piece with its material."""

    name: str
    vertices: F64
    triangles: NDArray[np.int32]
    material: int
    is_object: bool = False


@dataclass
class Scene:
    """The whole scene.

    Merged mesh (world frame, metres), per-triangle material and corner normals, the materials and
    their textures, and which triangles belong to the object.
    """

    vertices: F64
    triangles: NDArray[np.int32]
    corner_normals: NDArray[np.float32]  # T x 3 x 3, unit, outward
    triangle_material: NDArray[np.int32]
    object_mask: NDArray[np.bool_]
    materials: list[Material]
    textures: list[NDArray[np.float32]]
    texture_offsets: NDArray[np.float32]  # M x 3 x 2 texel offsets per projection axis
    parts: list[str] = field(default_factory=list)

    @property
    def object_bounds_m(self) -> tuple[F64, F64]:
        """Axis-aligned bounds (min, max) of the object (world, metres)."""
        v = self.vertices[np.unique(self.triangles[self.object_mask])]
        return v.min(axis=0), v.max(axis=0)

    def legacy_mesh(self, object_only: bool = False) -> o3d.geometry.TriangleMesh:
        """open3d legacy mesh of the scene (or only of the object)."""
        tris = self.triangles[self.object_mask] if object_only else self.triangles
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices), o3d.utility.Vector3iVector(tris))
        if object_only:
            mesh.remove_unreferenced_vertices()
        return mesh

    def ply_bytes(self, object_only: bool = False) -> bytes:
        """Binary little-endian PLY (vertices float64 x, y, z; faces) of the scene surface."""
        tris = self.triangles[self.object_mask] if object_only else self.triangles
        used = np.unique(tris)
        remap = np.full(self.vertices.shape[0], -1, np.int64)
        remap[used] = np.arange(used.size)
        verts = self.vertices[used]
        faces = remap[tris].astype(np.int32)
        head = (
            "ply\nformat binary_little_endian 1.0\ncomment loopmodel synthetic scene, world frame, metres\n"
            f"element vertex {verts.shape[0]}\nproperty double x\nproperty double y\nproperty double z\n"
            f"element face {faces.shape[0]}\nproperty list uchar int vertex_indices\nend_header\n"
        )
        buf = io.BytesIO()
        buf.write(head.encode("ascii"))
        buf.write(np.ascontiguousarray(verts, dtype="<f8").tobytes())
        rec = np.zeros(faces.shape[0], dtype=[("n", "u1"), ("i", "<i4", (3,))])
        rec["n"] = 3
        rec["i"] = faces
        buf.write(rec.tobytes())
        return buf.getvalue()


# ----------------------------------------------------------------------------- shapes


def _o3d_arrays(mesh: o3d.geometry.TriangleMesh) -> tuple[F64, NDArray[np.int32]]:
    return np.asarray(mesh.vertices, dtype=float).copy(), np.asarray(mesh.triangles, dtype=np.int32).copy()


def _box(size: tuple[float, float, float], centre: tuple[float, float, float]) -> tuple[F64, NDArray[np.int32]]:
    """Closed box (outward faces) of the given size centred at ``centre`` (metres)."""
    v, t = _o3d_arrays(o3d.geometry.TriangleMesh.create_box(*size))
    v += np.asarray(centre) - np.asarray(size) / 2
    return v, t


def _rot_z(v: F64, angle: float, about: F64 | None = None) -> F64:
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    a = np.zeros(3) if about is None else np.asarray(about)
    return (v - a) @ R.T + a


def _bust(height: float, rng: np.random.Generator) -> tuple[F64, NDArray[np.int32]]:
    """Sculpture-like bust.

    A lathe surface with elliptic sections (pedestal, torso with shoulders, neck, head) plus nose,
    ears, chin and seeded low-frequency asymmetry. Base at z = 0, front towards -y. Open at the
    bottom (it stands on the table).
    """
    key = np.array(
        [
            # z, rx, ry (fractions of the height)
            (0.000, 0.200, 0.200),
            (0.090, 0.200, 0.200),
            (0.110, 0.185, 0.185),
            (0.125, 0.150, 0.150),
            (0.145, 0.190, 0.140),
            (0.300, 0.290, 0.165),
            (0.420, 0.320, 0.175),
            (0.480, 0.270, 0.160),
            (0.530, 0.140, 0.110),
            (0.560, 0.090, 0.085),
            (0.620, 0.085, 0.090),
            (0.680, 0.118, 0.128),
            (0.790, 0.135, 0.150),
            (0.900, 0.118, 0.125),
            (0.960, 0.080, 0.085),
            (0.990, 0.035, 0.037),
            (1.000, 0.000, 0.000),
        ]
    )
    nz, nphi = 220, 240
    # denser rings where the profile bends: parametrise by arc length of the profile
    zz = np.linspace(0, 1, 2000)
    from scipy.interpolate import PchipInterpolator  # here: render workers never import scipy

    rx_f, ry_f = PchipInterpolator(key[:, 0], key[:, 1]), PchipInterpolator(key[:, 0], key[:, 2])
    ds = np.hypot(np.gradient(zz), np.gradient(0.5 * (rx_f(zz) + ry_f(zz))))
    s = np.concatenate([[0.0], np.cumsum(0.5 * (ds[1:] + ds[:-1]))])
    z = np.interp(np.linspace(0, s[-1], nz), s, zz)[:-1]  # last ring replaced by the apex
    phi = np.linspace(0, 2 * np.pi, nphi, endpoint=False)
    Z, P = np.meshgrid(z, phi, indexing="ij")
    rx, ry = rx_f(Z), ry_f(Z)

    def bump(zc: float, pc: float, sz: float, sp: float) -> F64:
        dp = np.angle(np.exp(1j * (P - pc)))
        return np.exp(-0.5 * (((Z - zc) / sz) ** 2 + (dp / sp) ** 2))

    front = -np.pi / 2  # -y
    gain = np.ones_like(Z)
    gain += 0.28 * bump(0.775, front, 0.035, 0.17)  # nose
    gain += 0.10 * bump(0.715, front, 0.02, 0.35)  # chin
    gain += 0.10 * bump(0.83, front + 0.45, 0.015, 0.08) + 0.10 * bump(0.83, front - 0.45, 0.015, 0.08)  # brows
    gain += 0.16 * bump(0.79, 0.0, 0.04, 0.12) + 0.16 * bump(0.79, np.pi, 0.04, 0.12)  # ears
    gain += 0.08 * bump(0.36, front + 0.5, 0.06, 0.3) + 0.08 * bump(0.36, front - 0.5, 0.06, 0.3)  # chest
    # seeded asymmetry on the sculpture (not on the pedestal)
    body = np.clip((Z - 0.14) / 0.05, 0, 1)
    for _ in range(6):
        k, m = int(rng.integers(1, 4)), int(rng.integers(1, 5))
        a, b = rng.uniform(0, 2 * np.pi, 2)
        gain += body * 0.03 * np.sin(k * np.pi * Z * 2 + a) * np.cos(m * P + b)
    x = rx * gain * np.cos(P)
    y = ry * gain * np.sin(P)
    verts = np.column_stack([x.ravel(), y.ravel(), Z.ravel()])
    verts = np.vstack([verts, [0.0, 0.0, 1.0]]) * height
    idx = np.arange(Z.size).reshape(Z.shape)
    a, b = idx[:-1, :], idx[1:, :]
    c, d = np.roll(a, -1, axis=1), np.roll(b, -1, axis=1)
    tris = np.vstack(
        [
            np.column_stack([a.ravel(), c.ravel(), b.ravel()]),
            np.column_stack([c.ravel(), d.ravel(), b.ravel()]),
        ]
    )
    apex = verts.shape[0] - 1
    top = idx[-1, :]
    cap = np.column_stack([top, np.roll(top, -1), np.full(nphi, apex)])
    tris32: NDArray[np.int32] = np.vstack([tris, cap]).astype(np.int32)
    return verts, _orient_outward(verts, tris32, np.array([0, 0, 0.5 * height]))


def _orient_outward(v: F64, t: NDArray[np.int32], centre: F64) -> NDArray[np.int32]:
    """Flip the winding if most faces point towards ``centre`` (star-shaped solids)."""
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    c = v[t].mean(axis=1) - centre
    return t[:, ::-1].copy() if np.sum(np.einsum("ij,ij->i", n, c)) < 0 else t


def _prim(mesh: o3d.geometry.TriangleMesh, at: tuple[float, float, float]) -> tuple[F64, NDArray[np.int32]]:
    v, t = _o3d_arrays(mesh)
    v[:, 2] -= v[:, 2].min()
    v += np.asarray(at)
    return v, t


def _object_parts(kind: str, height: float, rng: np.random.Generator) -> list[tuple[str, F64, NDArray[np.int32]]]:
    s = height / 0.5
    if kind == "bust":
        v, t = _bust(height, rng)
        return [("bust", _rot_z(v, rng.uniform(-0.3, 0.3)), t)]
    if kind == "box":
        v, t = _box((0.30 * s, 0.22 * s, 0.5 * s), (0.0, 0.0, 0.25 * s))
        return [("box", _rot_z(v, rng.uniform(0.2, 0.6)), t)]
    if kind == "mix":
        G = o3d.geometry.TriangleMesh
        parts = [
            ("box", *_box((0.18 * s, 0.14 * s, 0.26 * s), (0.05 * s, 0.04 * s, 0.13 * s))),
            ("sphere", *_prim(G.create_sphere(0.09 * s, 60), (-0.17 * s, 0.12 * s, 0.0))),
            (
                "cylinder",
                *_prim(G.create_cylinder(0.055 * s, 0.5 * s, 64, 24), (0.17 * s, -0.1 * s, 0.0)),
            ),
            ("cone", *_prim(G.create_cone(0.09 * s, 0.2 * s, 64, 8), (-0.12 * s, -0.16 * s, 0.0))),
            ("torus", *_prim(G.create_torus(0.07 * s, 0.03 * s, 60, 30), (0.2 * s, 0.17 * s, 0.0))),
            ("tetra", *_prim(G.create_tetrahedron(0.09 * s), (-0.02 * s, 0.2 * s, 0.0))),
        ]
        angle = rng.uniform(0, 2 * np.pi)
        return [(n, _rot_z(v, angle), t) for n, v, t in parts]
    raise ValueError(f"unknown scene kind {kind!r}")


def _room_parts(rng: np.random.Generator) -> list[tuple[str, F64, NDArray[np.int32], int]]:
    """Table legs, floor/walls/ceiling (inward) and shelves.

    Material index 1 = wood, 2 = walls, 3 = furniture.
    """
    out: list[tuple[str, F64, NDArray[np.int32], int]] = []
    tx, ty, _ = TABLE_SIZE_M
    leg_h = TABLE_HEIGHT_M - TABLE_SIZE_M[2]
    for i, (sx, sy) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
        c = (sx * (tx / 2 - 0.06), sy * (ty / 2 - 0.06), -TABLE_SIZE_M[2] - leg_h / 2)
        out.append((f"leg{i}", *_box((0.05, 0.05, leg_h), c), 1))
    hx, hy = ROOM_HALF_M
    zc = (ROOM_TOP_M - TABLE_HEIGHT_M) / 2
    v, t = _box((2 * hx, 2 * hy, ROOM_TOP_M + TABLE_HEIGHT_M), (0.0, 0.0, zc))
    out.append(("room", v, t[:, ::-1].copy(), 2))
    for i in range(7):  # cabinets and shelves along the walls
        w, d, h = rng.uniform(0.4, 1.2), rng.uniform(0.25, 0.5), rng.uniform(0.3, 1.8)
        side = int(rng.integers(0, 4))
        along = rng.uniform(-0.7, 0.7)
        z0 = -TABLE_HEIGHT_M if rng.random() < 0.6 else rng.uniform(0.0, 0.8)
        h = min(h, ROOM_TOP_M - z0 - 0.05)
        if side < 2:
            c = (along * hx, (1 if side == 0 else -1) * (hy - d / 2 - 0.01), z0 + h / 2)
            size = (w, d, h)
        else:
            c = ((1 if side == 2 else -1) * (hx - d / 2 - 0.01), along * hy, z0 + h / 2)
            size = (d, w, h)
        out.append((f"shelf{i}", *_box(size, c), 3))
    return out


def _corner_normals(v: F64, t: NDArray[np.int32]) -> NDArray[np.float32]:
    """Per-corner normals.

    The smooth vertex normal where the surface is smooth, the face normal across creases sharper
    than ``CREASE_DEG``.
    """
    fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])  # area-weighted
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, t[:, k], fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
    fnu = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    cn = vn[t]  # T x 3 x 3
    smooth = np.einsum("tkc,tc->tk", cn, fnu) > np.cos(np.radians(CREASE_DEG))
    cn = np.where(smooth[:, :, None], cn, fnu[:, None, :])
    return cn.astype(np.float32)


def build_scene(
    kind: str = "bust",
    seed: int = 0,
    object_height_m: float = 0.5,
    room: bool = True,
    texture_size_px: int = 2048,
) -> Scene:
    """The scene of a scan.

    ``kind`` object (``bust``, ``box``, ``mix``) of the given height on the table, with the room
    when ``room``; textures and shape details come from ``seed``.
    """
    ss = np.random.SeedSequence([int(seed), 3])
    shape_seed, tex_seed, place_seed = ss.spawn(3)
    rng = np.random.default_rng(shape_seed)
    materials = [
        Material(0, 0.0006),  # object: stone
        Material(1, 0.0012, 0.9),  # table: wood
        Material(2, 0.0045, 1.0),  # walls: posters
        Material(0, 0.0025, 0.8),  # furniture: coarse stone
    ]
    styles = ("stone", "wood", "poster")
    tex_seeds = tex_seed.spawn(len(styles))
    textures = [make_texture(s, texture_size_px, st) for s, st in zip(tex_seeds, styles, strict=True)]
    prng = np.random.default_rng(place_seed)
    offsets = prng.uniform(0, texture_size_px, size=(len(materials), 3, 2)).astype(np.float32)

    parts: list[Part] = [Part(n, v, t, 0, True) for n, v, t in _object_parts(kind, object_height_m, rng)]
    tx, ty, tz = TABLE_SIZE_M
    parts.append(Part("table", *_box((tx, ty, tz), (0.0, 0.0, -tz / 2)), 1))
    if room:
        parts += [Part(n, v, t, m) for n, v, t, m in _room_parts(rng)]

    verts, tris, mats, objm, cns = [], [], [], [], []
    base = 0
    for p in parts:
        t = p.triangles
        if p.is_object:  # drop faces lying on the table top: never visible, not surface
            fz = np.cross(p.vertices[t[:, 1]] - p.vertices[t[:, 0]], p.vertices[t[:, 2]] - p.vertices[t[:, 0]])
            fz /= np.maximum(np.linalg.norm(fz, axis=1, keepdims=True), 1e-300)
            on_table = (fz[:, 2] < -0.99) & np.all(p.vertices[t][:, :, 2] < 1e-6, axis=1)
            t = t[~on_table]
        cns.append(_corner_normals(p.vertices, t))
        verts.append(p.vertices)
        tris.append(t + base)
        mats.append(np.full(t.shape[0], p.material, np.int32))
        objm.append(np.full(t.shape[0], p.is_object))
        base += p.vertices.shape[0]
    return Scene(
        vertices=np.vstack(verts),
        triangles=np.vstack(tris).astype(np.int32),
        corner_normals=np.concatenate(cns),
        triangle_material=np.concatenate(mats),
        object_mask=np.concatenate(objm),
        materials=materials,
        textures=textures,
        texture_offsets=offsets,
        parts=[p.name for p in parts],
    )
