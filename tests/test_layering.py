"""The package layout's rules, by a walk over the source's imports (AST; nothing is imported).

Stages never read or write files (issue 32): no module of ``frontend``, ``backend``, ``loop``,
``mapping`` or ``pose`` imports ``loopmodel.io`` or calls a file function itself (``open``,
``Path.read_text``, ``np.load``, ``cv2.imread``, ...); and no two packages import each other,
directly or round a cycle. Every import counts, also inside functions and under ``TYPE_CHECKING``.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "loopmodel"
STAGES = ("frontend", "backend", "loop", "mapping", "pose")


def _unit(path: Path) -> str:
    """The package (or top-level module) a source file belongs to: ``loop``, ``pipeline``, ..."""
    return path.relative_to(PACKAGE).with_suffix("").parts[0]


def _imports(path: Path) -> list[tuple[str, int]]:
    """The ``loopmodel.*`` modules a file imports, with their line numbers."""
    out: list[tuple[str, int]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module == "loopmodel":  # from loopmodel import io
                out += [(f"loopmodel.{a.name}", node.lineno) for a in node.names]
            else:
                out.append((node.module, node.lineno))
    return [(m, n) for m, n in out if m.startswith("loopmodel.")]


#: Calls that read or write files: plain names and attribute names (``x.read_text()``, ``np.load``).
FILE_CALLS = {"open"}
FILE_ATTRS = {
    "read_text", "read_bytes", "write_text", "write_bytes", "open", "unlink", "mkdir",
    "load", "save", "savez", "savez_compressed", "loadtxt", "savetxt", "fromfile", "tofile",
    "imread", "imwrite", "read_point_cloud", "write_point_cloud", "read_triangle_mesh", "write_triangle_mesh",
}  # fmt: skip


def _file_calls(path: Path) -> list[str]:
    """The calls of a file that read or write files (``name:line``)."""
    out: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        if isinstance(f, ast.Name) and f.id in FILE_CALLS:
            out.append(f"{f.id}:{node.lineno}")
        elif isinstance(f, ast.Attribute) and f.attr in FILE_ATTRS:
            out.append(f"{f.attr}:{node.lineno}")
    return out


def _graph() -> tuple[dict[str, set[str]], list[str]]:
    """Package -> the packages it imports, and each stage import of ``loopmodel.io`` (file:line module)."""
    edges: dict[str, set[str]] = {}
    io_imports: list[str] = []
    for path in sorted(PACKAGE.rglob("*.py")):
        unit = _unit(path)
        for module, line in _imports(path):
            target = module.split(".")[1]
            if target != unit:
                edges.setdefault(unit, set()).add(target)
            if unit in STAGES and target == "io":
                io_imports.append(f"{path.relative_to(PACKAGE.parent)}:{line} {module}")
    return edges, io_imports


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """One path per package edge that closes a cycle (depth-first search)."""
    found: list[list[str]] = []
    for start in sorted(edges):
        stack = [(start, [start])]
        seen: set[str] = set()
        while stack:
            node, path = stack.pop()
            for nxt in sorted(edges.get(node, ())):
                if nxt == start:
                    found.append([*path, start])
                elif nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, [*path, nxt]))
    return found


def test_no_stage_imports_io() -> None:
    _, io_imports = _graph()
    assert not io_imports, "stages read or write files through loopmodel.io:\n" + "\n".join(io_imports)


def test_no_stage_opens_files() -> None:
    found = [
        f"{path.relative_to(PACKAGE.parent)} {call}"
        for path in sorted(PACKAGE.rglob("*.py"))
        if _unit(path) in STAGES
        for call in _file_calls(path)
    ]
    assert not found, "stages read or write files themselves:\n" + "\n".join(found)


def test_no_import_cycle_between_packages() -> None:
    edges, _ = _graph()
    assert {"pipeline", "io", "loop", "mapping"} <= set(edges)  # the walk sees the layout
    cycles = _cycles(edges)
    assert not cycles, "package import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_the_walk_finds_what_it_looks_for(tmp_path: Path) -> None:
    """The two rules fail on a stage importing io and on a cycle (the checks can fail)."""
    src = tmp_path / "m.py"
    text = "from loopmodel.io.atomic import atomic_path\nimport loopmodel.loop.stage\nfrom loopmodel import io\n"
    src.write_text(text)
    assert [m for m, _ in _imports(src)] == ["loopmodel.io.atomic", "loopmodel.loop.stage", "loopmodel.io"]
    cycles = _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}})
    assert cycles == [["a", "b", "c", "a"], ["b", "c", "a", "b"], ["c", "a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": {"c"}}) == []
    text = "import numpy as np\nwith open('x') as f:\n    pass\nv = np.load(p)\nt = p.read_text()\nnp.sum(v)\n"
    src.write_text(text)
    assert sorted(_file_calls(src)) == ["load:4", "open:2", "read_text:5"]
