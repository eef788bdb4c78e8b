"""Mesh files: binary PLY (default), OBJ, STL and GLB written by open3d, atomically.

Meshes are in metres in the world frame of the run. PLY and OBJ files say so in a header
comment, STL in its 80-byte header, GLB in ``asset.extras`` (glTF is metres by definition).
"""

from __future__ import annotations

import base64
import json
import struct
import tempfile
from pathlib import Path

import open3d as o3d

from loopmodel.errors import InputError
from loopmodel.io.atomic import write_bytes_atomic
from loopmodel.io.text import require_existing_file

MESH_FORMATS = ("ply", "obj", "stl", "glb")
UNITS_NOTE = "loopmodel mesh: units metres, world frame of the run"


def _glb_embed_buffer(data: bytes, note: str) -> bytes:
    """Fix open3d 0.20 GLB files and record the units note in ``asset.extras``.

    GLB files written by open3d 0.20 have their buffer as a base64 data URI inside the JSON chunk,
    which readers (assimp, hence open3d itself) reject. Move that buffer into the binary chunk, as
    the GLB layout intends, and record the units note in ``asset.extras``.
    """
    magic, version, _ = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2:
        return data
    json_len, json_type = struct.unpack_from("<I4s", data, 12)
    if json_type != b"JSON":
        return data
    doc = json.loads(data[20 : 20 + json_len])
    rest = data[20 + json_len :]
    buffers = doc.get("buffers", [])
    uri = buffers[0].get("uri", "") if buffers else ""
    if rest or not uri.startswith("data:") or ";base64," not in uri:
        return data
    binary = base64.b64decode(uri.split(";base64,", 1)[1])
    del buffers[0]["uri"]
    buffers[0]["byteLength"] = len(binary)
    doc.setdefault("asset", {}).setdefault("extras", {})["loopmodel"] = note
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (
        struct.pack("<4sII", b"glTF", 2, total)
        + struct.pack("<I4s", len(js), b"JSON")
        + js
        + struct.pack("<I4s", len(binary), b"BIN\0")
        + binary
    )


def _add_header_note(data: bytes, fmt: str, note: str) -> bytes:
    """The file bytes with the units note in the header of the format."""
    if fmt == "ply":
        head_end = data.find(b"end_header")
        first_nl = data.find(b"\n")
        if head_end < 0 or first_nl < 0:
            return data
        # after the "format ..." line (line 2)
        second_nl = data.find(b"\n", first_nl + 1)
        line = f"comment {note}\n".encode("ascii")
        data = data[: second_nl + 1] + line + data[second_nl + 1 :]
    elif fmt == "obj":
        data = f"# {note}\n".encode("ascii") + data
    elif fmt == "stl" and not data.lstrip().startswith(b"solid"):
        data = note.encode("ascii")[:80].ljust(80, b" ") + data[80:]
    elif fmt == "glb":
        data = _glb_embed_buffer(data, note)
    return data


def write_mesh(path: str | Path, mesh: o3d.geometry.TriangleMesh, fmt: str | None = None) -> Path:
    """Write ``mesh`` to ``path`` in ``fmt`` without ever leaving an empty or half-written file.

    ``fmt`` defaults to the one of the extension, else PLY.
    """
    p = Path(path)
    fmt = (fmt or p.suffix.lstrip(".") or "ply").lower()
    if fmt not in MESH_FORMATS:
        raise InputError(p, f"unknown mesh format '{fmt}'; use one of {', '.join(MESH_FORMATS)}")
    if len(mesh.triangles) == 0 or len(mesh.vertices) == 0:
        raise InputError(p, "refusing to write an empty mesh (no triangles)")
    if fmt == "stl" and not mesh.has_triangle_normals():
        mesh = o3d.geometry.TriangleMesh(mesh)
        mesh.compute_triangle_normals()
    if fmt == "obj" and mesh.has_triangle_normals():  # OBJ has vertex normals only (open3d warns, issue 35)
        mesh = o3d.geometry.TriangleMesh(mesh)
        mesh.triangle_normals = o3d.utility.Vector3dVector()
    # open3d picks the format from the extension: let it write into a scratch folder, then
    # post-process the bytes and move them into place atomically
    with tempfile.TemporaryDirectory(prefix="loopmodel-mesh-") as d:
        tmp = Path(d) / f"{p.stem}.{fmt}"
        ok = o3d.io.write_triangle_mesh(tmp, mesh, write_ascii=False, compressed=False, print_progress=False)
        if not ok or not tmp.is_file() or tmp.stat().st_size == 0:
            raise InputError(p, f"open3d could not write a {fmt} mesh")
        data = _add_header_note(tmp.read_bytes(), fmt, UNITS_NOTE)
    write_bytes_atomic(p, data)
    return p


def mesh_from_bytes(data: bytes, fmt: str = "ply", source: str | Path | None = None) -> o3d.geometry.TriangleMesh:
    """Triangle mesh from the bytes of a mesh file (e.g. an MCAP attachment)."""
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d) / f"mesh.{fmt}"
        tmp.write_bytes(data)
        mesh = o3d.io.read_triangle_mesh(tmp)
    if len(mesh.triangles) == 0:
        raise InputError(source, "no triangles could be read from this mesh")
    return mesh


def _mcap_attachment(path: Path, name: str) -> bytes:
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            for att in make_reader(f).iter_attachments():
                if att.name == name:
                    return bytes(att.data)
    except Exception as exc:  # the mcap library raises several types for corrupt files
        raise InputError(path, f"cannot read MCAP attachments ({exc})") from None
    raise InputError(path, f"no attachment named '{name}' (the ground-truth scene mesh)")


def read_mesh(path: str | Path, attachment: str = "scene.ply") -> o3d.geometry.TriangleMesh:
    """Read a triangle mesh with open3d.

    From an ``.mcap`` file, its attachment of that name (the simulator's ground-truth scene). Raises
    :class:`InputError` if missing or empty.
    """
    p = Path(path)
    require_existing_file(p, "mesh file")  # a device or FIFO was "does not exist" (issue 34)
    if p.suffix.lower() == ".mcap":
        data = _mcap_attachment(p, attachment)
        return mesh_from_bytes(data, Path(attachment).suffix.lstrip(".") or "ply", f"{p}:{attachment}")
    mesh = o3d.io.read_triangle_mesh(p)
    if len(mesh.triangles) == 0:
        raise InputError(p, "no triangles could be read from this mesh file")
    return mesh
