"""Mesh files: binary PLY (default), OBJ, STL and GLB written by open3d, atomically.

Meshes are in metres in the world frame of the run. PLY and OBJ files say so in a header
comment, STL in its 80-byte header; glTF (GLB) is metres by definition.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import open3d as o3d

from loopmodel.errors import InputError

MESH_FORMATS = ("ply", "obj", "stl", "glb")
UNITS_NOTE = "loopmodel mesh: units metres, world frame of the run"


def _add_header_note(path: Path, fmt: str, note: str) -> None:
    data = path.read_bytes()
    if fmt == "ply":
        head_end = data.find(b"end_header")
        first_nl = data.find(b"\n")
        if head_end < 0 or first_nl < 0:
            return
        # after the "format ..." line (line 2)
        second_nl = data.find(b"\n", first_nl + 1)
        line = f"comment {note}\n".encode("ascii")
        data = data[: second_nl + 1] + line + data[second_nl + 1 :]
    elif fmt == "obj":
        data = f"# {note}\n".encode("ascii") + data
    elif fmt == "stl" and not data.lstrip().startswith(b"solid"):
        data = note.encode("ascii")[:80].ljust(80, b" ") + data[80:]
    else:
        return
    path.write_bytes(data)


def write_mesh(path: str | Path, mesh: o3d.geometry.TriangleMesh, fmt: str | None = None) -> Path:
    """Write ``mesh`` to ``path`` in ``fmt`` (default: from the extension, else PLY) without
    ever leaving an empty or half-written file."""
    p = Path(path)
    fmt = (fmt or p.suffix.lstrip(".") or "ply").lower()
    if fmt not in MESH_FORMATS:
        raise InputError(p, f"unknown mesh format '{fmt}'; use one of {', '.join(MESH_FORMATS)}")
    if len(mesh.triangles) == 0 or len(mesh.vertices) == 0:
        raise InputError(p, "refusing to write an empty mesh (no triangles)")
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.stem}.tmp-{os.getpid()}.{fmt}")
    try:
        if fmt == "stl" and not mesh.has_triangle_normals():
            mesh = o3d.geometry.TriangleMesh(mesh)
            mesh.compute_triangle_normals()
        ok = o3d.io.write_triangle_mesh(
            str(tmp), mesh, write_ascii=False, compressed=False, print_progress=False
        )
        if not ok or not tmp.is_file() or tmp.stat().st_size == 0:
            raise InputError(p, f"open3d could not write a {fmt} mesh")
        _add_header_note(tmp, fmt, UNITS_NOTE)
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    return p


def read_mesh(path: str | Path) -> o3d.geometry.TriangleMesh:
    """Read a triangle mesh with open3d; raises :class:`InputError` if missing or empty."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "mesh file does not exist")
    mesh = o3d.io.read_triangle_mesh(str(p))
    if len(mesh.triangles) == 0:
        raise InputError(p, "no triangles could be read from this mesh file")
    return mesh
