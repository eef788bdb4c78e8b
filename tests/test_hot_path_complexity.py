"""Issue 32: every function on the per-frame and per-keyframe path at ruff complexity (C901) <= 12.

Which functions run on every frame and keyframe is traced (``tools/hot_path.py``: the KITTI clip and
the laser sample from frame 10 on, Python functions and the compiled kernels they call) into
``tests/hot_path.txt``; each of them, the functions of its module it calls (a kernel's inlined
helpers), and the whole modules of the run's recipe, the back-end worker and the live mapping are
checked by ruff's McCabe rule (the issue's measure) at the limit 12.
"""

from __future__ import annotations

import ast
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TRACED = Path(__file__).with_name("hot_path.txt")
#: whole modules kept at the limit (every function in them)
HOT = [
    "loopmodel/pipeline.py",
    "loopmodel/frontend/hybrid_ba.py",
    "loopmodel/backend/worker.py",
    "loopmodel/mapping/live.py",
    "loopmodel/mapping/anchored.py",
    "loopmodel/mapping/stripe_map.py",
]
#: traced functions still above the limit, left to another change (empty: cx13, 2026-12-04, split the local
#: BA's kernels of frontend/_ba_kernels.py, ``_evaluate_py`` 15 and ``_lm_py`` 25, into inlined helpers)
PENDING: set[tuple[str, str]] = set()
RETRACE = "trace them again: python tools/hot_path.py --write tests/hot_path.txt"


def _ruff() -> str | None:
    here = Path(sys.executable).parent / "ruff"
    return str(here) if here.is_file() else shutil.which("ruff")


def _c901(paths: list[Path], limit: int) -> subprocess.CompletedProcess[str]:
    ruff = _ruff()
    if ruff is None:
        pytest.skip("ruff is not installed")
    cmd = [ruff, "check", "--no-cache", "--isolated", "--select", "C901", "--output-format", "json",
           "--config", f"lint.mccabe.max-complexity={limit}", *map(str, paths)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60)


def _too_complex(paths: list[Path], limit: int) -> dict[tuple[Path, str], str]:
    """(file, function name) -> ruff's message, for every function of ``paths`` above ``limit``."""
    out = _c901(paths, limit)
    assert out.returncode in (0, 1), out.stderr
    found = {}
    for d in json.loads(out.stdout or "[]"):
        name = d["message"].split("`")[1]
        found[(Path(d["filename"]).resolve(), name)] = f"{d['filename']}:{d['location']['row']}: {d['message']}"
    return found


def _defs(tree: ast.Module) -> tuple[set[str], dict[str, str]]:
    """A module's function names and its aliases of them (``kernel = numba.njit(...)(_kernel_py)``)."""
    names = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)}
    alias = {}
    for node in tree.body:
        if (isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name)
                and isinstance(node.value, ast.Call) and node.value.args
                and isinstance(node.value.args[0], ast.Name) and node.value.args[0].id in names):
            alias[node.targets[0].id] = node.value.args[0].id
    return names, alias


def hot_functions(traced: list[str], root: Path) -> tuple[set[tuple[Path, str]], list[str]]:
    """The traced ``path:function`` entries with the functions of their modules they call, and the missing ones."""
    by_file: dict[str, set[str]] = {}
    for line in traced:
        path, _, name = line.strip().partition(":")
        if path:
            by_file.setdefault(path, set()).add(name)
    hot: set[tuple[Path, str]] = set()
    missing = []
    for path, wanted in sorted(by_file.items()):
        file = (root / path).resolve()
        if not file.is_file():
            missing += [f"{path}:{n}" for n in sorted(wanted)]
            continue
        tree = ast.parse(file.read_text())
        names, alias = _defs(tree)
        missing += [f"{path}:{n}" for n in sorted(wanted - names)]
        nodes: dict[str, list[ast.AST]] = {}
        for n in ast.walk(tree):
            if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef):
                nodes.setdefault(n.name, []).append(n)
        todo = sorted(wanted & names)
        while todo:
            name = todo.pop()
            if (file, name) in hot:
                continue
            hot.add((file, name))
            for node in nodes[name]:
                for call in ast.walk(node):
                    if isinstance(call, ast.Call) and isinstance(call.func, ast.Name):
                        callee = alias.get(call.func.id, call.func.id)
                        if callee in names:
                            todo.append(callee)
    return hot, missing


def _traced() -> list[str]:
    return TRACED.read_text().splitlines()


def test_the_check_finds_a_complex_function(tmp_path: Path) -> None:
    branches = "".join(f"    if a == {i}:\n        return {i}\n" for i in range(13))
    (tmp_path / "m.py").write_text(f"def f(a):\n{branches}    return -1\n")
    found = _too_complex([tmp_path / "m.py"], 12)
    assert list(found) == [((tmp_path / "m.py").resolve(), "f")]  # 14 > 12


def test_a_traced_function_and_its_helpers_are_checked(tmp_path: Path) -> None:
    """A complex helper of a traced kernel (called through its compiled alias) is found; an untraced one is not."""
    branches = "".join(f"    if a == {i}:\n        return {i}\n" for i in range(13))
    (tmp_path / "k.py").write_text(
        f"import numba\n\n\ndef _helper_py(a):\n{branches}    return -1\n\n\n"
        "_helper = numba.njit(inline='always')(_helper_py)\n\n\n"
        "def _kernel_py(a):\n    return _helper(a)\n\n\n"
        f"def _cold_py(a):\n{branches}    return -1\n"
    )
    hot, missing = hot_functions(["k.py:_kernel_py", "k.py:_gone"], tmp_path)
    assert missing == ["k.py:_gone"]
    k = (tmp_path / "k.py").resolve()
    assert hot == {(k, "_kernel_py"), (k, "_helper_py")}
    assert sorted(set(_too_complex([k], 12)) & hot) == [(k, "_helper_py")]


def test_traced_functions_exist() -> None:
    _hot, missing = hot_functions(_traced(), ROOT)
    assert not missing, f"per-frame functions renamed or moved ({RETRACE}): {missing}"


def test_hot_path_functions_are_at_most_12() -> None:
    hot, _missing = hot_functions(_traced(), ROOT)
    files = sorted({f for f, _ in hot} | {(ROOT / m).resolve() for m in HOT})
    found = _too_complex(files, 12)
    whole = {(ROOT / m).resolve() for m in HOT}
    pending = {((ROOT / f).resolve(), n) for f, n in PENDING}
    bad = [msg for key, msg in sorted(found.items()) if (key in hot or key[0] in whole) and key not in pending]
    assert not bad, "\n".join(bad)


@pytest.mark.slow
def test_a_fresh_trace_is_at_most_12(tmp_path: Path) -> None:
    """The functions a run of the laser sample calls (frames 10-60) traced now, each at most 12."""
    scan = ROOT / "datasets" / "sample" / "scan.mcap"
    if not scan.exists():
        pytest.skip("datasets/sample/scan.mcap not generated")
    out = tmp_path / "hot.txt"
    cmd = [sys.executable, str(ROOT / "tools" / "hot_path.py"), "--last", "60", "--write", str(out), str(scan)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    traced = out.read_text().splitlines()
    assert any("_peak_kernels.py:_profile_peaks_py" in t for t in traced)  # a compiled kernel was seen
    assert any("tracker.py:" in t for t in traced)
    hot, missing = hot_functions(traced, ROOT)
    assert not missing
    found = _too_complex(sorted({f for f, _ in hot}), 12)
    pending = {((ROOT / f).resolve(), n) for f, n in PENDING}
    bad = [msg for key, msg in sorted(found.items()) if key in hot and key not in pending]
    assert not bad, "\n".join(bad)
