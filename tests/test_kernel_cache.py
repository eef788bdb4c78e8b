"""numba's on-disk cache of the compiled kernels (issue 33 item 2: no compiling inside the first run's frames).

- every module with ``cache=True`` kernels is in :data:`loopmodel.kernels.KERNEL_MODULES`;
- with an empty cache folder every module is reported cold, and warming one module makes exactly it
  warm (a subprocess with its own ``NUMBA_CACHE_DIR``, so the suite's cache is untouched);
- after :func:`warm_up` no module is cold (every module has a warm-up that reaches it); a run warms only the
  modules its configuration calls;
- a run after :func:`warm_up` compiles nothing more: the warm-ups call the kernels with the argument types the run
  does (numba compiles per type, and a module with one warm entry counts as warm).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from loopmodel.config import Config
from loopmodel.kernels import KERNEL_MODULES, cold_kernel_modules, modules_for, warm_up

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "loopmodel"


def test_every_cached_kernel_module_is_listed() -> None:
    found = {
        ".".join(p.relative_to(PACKAGE.parent).with_suffix("").parts)
        for p in PACKAGE.rglob("*.py")
        if "cache=True" in p.read_text() and p.name != "kernels.py"
    }
    assert found == set(KERNEL_MODULES)


def test_an_empty_cache_is_cold_and_one_warmed_module_is_not(tmp_path: Path) -> None:
    code = (
        "import json\n"
        "from loopmodel.kernels import cold_kernel_modules\n"
        "before = cold_kernel_modules()\n"
        "from loopmodel.imaging._klt_kernels import warm_up\n"
        "warm_up()\n"
        "print(json.dumps([before, cold_kernel_modules()]))\n"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True, timeout=300)
    before, after = json.loads(out.stdout.strip().splitlines()[-1])
    assert before == list(KERNEL_MODULES)
    assert after == [m for m in KERNEL_MODULES if m != "loopmodel.imaging._klt_kernels"]
    assert any(tmp_path.rglob("*.nbi"))  # the cache went where NUMBA_CACHE_DIR says


def test_after_warming_all_no_module_is_cold() -> None:
    steps: list[str] = []
    warm_up(on_step=lambda i, n, label: steps.append(label))
    assert len(steps) == len(KERNEL_MODULES)
    assert cold_kernel_modules() == []


def test_a_run_warms_only_the_kernels_its_configuration_calls() -> None:
    default = modules_for(Config())  # ORB loop descriptors, iSAM2, no KLT share
    assert "loopmodel.loop.surf" not in default and "loopmodel.backend._givens_kernels" not in default
    surf = Config.model_validate({"loop": {"descriptor": "surf"}, "backend": {"kind": "both"}})
    assert {"loopmodel.loop.surf", "loopmodel.backend._givens_kernels"} <= set(modules_for(surf))


def test_a_run_after_warming_compiles_nothing_more() -> None:
    """After the warm-up, the tiny KITTI sequence's run in a fresh interpreter adds no type to any kernel.

    cx13 (issue 33): the KITTI clip's first run after ``python -m loopmodel.kernels`` compiled the robust pose's
    kernels for the views of (4, 4) matrices it passes (the warm-up's were contiguous) and the PNG kernel for a
    read-only buffer, in its frames (frame 1: 1-5 s). The run's worker processes are not checked here.
    """
    code = (
        "import importlib, json\n"
        "from numba.core.registry import CPUDispatcher\n"
        "from loopmodel.config import load_config\n"
        "from loopmodel.io.sequence import open_sequence\n"
        "from loopmodel.kernels import KERNEL_MODULES, modules_for, warm_up\n"
        "from loopmodel.pipeline import process\n"
        f"cfg = load_config({str(ROOT / 'configs' / 'kitti.yaml')!r})\n"
        "warm_up(modules_for(cfg))\n"
        "def types():\n"
        "    return {f'{m}.{k}': set(map(str, v.signatures)) for m in KERNEL_MODULES\n"
        "            for k, v in vars(importlib.import_module(m)).items() if isinstance(v, CPUDispatcher)}\n"
        "before = types()\n"
        f"result = process(open_sequence({str(ROOT / 'datasets' / 'tiny_kitti')!r}), cfg)\n"
        "added = {k: sorted(v - before.get(k, set())) for k, v in types().items() if v - before.get(k, set())}\n"
        "print(json.dumps([result.metrics['frames'], result.metrics['keyframes'], added]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    frames, keyframes, added = json.loads(out.stdout.strip().splitlines()[-1])
    assert frames == 8 and keyframes >= 2  # tracked frames and a local BA were reached
    assert added == {}


def test_kernels_compiled_in_a_pool_are_cached_for_the_next_process(tmp_path: Path) -> None:
    """Two processes compile cold modules; a later process finds them in numba's cache.

    The two cheapest modules, in this test's own cache folder.
    """
    small = ("loopmodel.imaging._klt_kernels", "loopmodel.loop._vocabulary_kernels")
    # the modules imported (as `cold_kernel_modules` does in a run) before the pool compiles: this
    # process then loads them from the cache (hits, no miss), it does not compile them again
    code = (
        "import json\n"
        "from loopmodel.kernels import _dispatchers, _warm_ups, cold_kernel_modules, compile_in_processes\n"
        f"assert cold_kernel_modules({small!r}) == list({small!r})\n"
        "done = []\n"
        f"compile_in_processes({small!r}, lambda i, n, label: done.append([i, n, label]), processes=2)\n"
        "import importlib\n"
        f"for m in {small!r}:\n"
        "    _warm_ups()[m][1]()\n"
        "    ds = _dispatchers(importlib.import_module(m))\n"
        "    assert all(not d.stats.cache_misses for d in ds) and any(d.stats.cache_hits for d in ds), m\n"
        "print(json.dumps(done))\n"
    )
    check = (
        "import json\n"
        "from loopmodel.kernels import cold_kernel_modules\n"
        f"print(json.dumps(cold_kernel_modules({small!r})))\n"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}

    def last_line(source: str) -> list:
        out = subprocess.run(
            [sys.executable, "-c", source], env=env, capture_output=True, text=True, check=True, timeout=300
        )
        return json.loads(out.stdout.strip().splitlines()[-1])

    done = last_line(code)
    assert [d[:2] for d in done] == [[1, 2], [2, 2]] and {d[2] for d in done} == {"KLT share", "vocabulary"}
    assert last_line(check) == []


def test_the_command_compiles_only_what_a_configuration_calls(tmp_path: Path) -> None:
    """``--config``: the modules of :func:`modules_for` that are cold, no others (none cold: "cached")."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("frontend:\n  klt_share_px: 2.0\n")
    code = (
        "import loopmodel.kernels as k\n"
        "share = ('loopmodel.imaging._klt_kernels',)\n"
        "k.modules_for = lambda config: share if config.frontend.klt_share_px > 0 else ()\n"
        f"k.main(['--config', {str(cfg)!r}, '--processes', '1'])\n"
        f"k.main(['--config', {str(cfg)!r}])\n"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True, timeout=300)
    lines = out.stdout.strip().splitlines()
    assert "1 of 1 modules" in lines[0] and "KLT share" in lines[1] and "done" in lines[2], lines
    assert lines[-1] == "loopmodel kernels: cached"


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (Linux /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat[stat.rindex(")") + 2 :].split()[1]) == pid:
                found.append(int(entry.name))
    return found


def test_sigterm_stops_the_command_and_its_compiling_pool(tmp_path: Path) -> None:
    """tools/demo.sh stops a compile it started beside the sample's generation: no pool process outlives it."""
    import signal
    import time

    if not Path("/proc/self/stat").exists():
        import pytest

        pytest.skip("needs Linux /proc")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "loopmodel.kernels", "--processes", "2"],
        env=env, stdout=subprocess.PIPE, text=True, cwd=ROOT,
    )
    try:
        assert proc.stdout is not None and "compiling" in proc.stdout.readline()
        deadline = time.monotonic() + 60
        while len(_children(proc.pid)) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        pool = _children(proc.pid)
        assert len(pool) >= 2, pool  # the two compiling processes (and multiprocessing's resource tracker)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 128 + signal.SIGTERM
        deadline = time.monotonic() + 10
        while any(Path(f"/proc/{p}").exists() and "Z" not in _state(p) for p in pool) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [p for p in pool if Path(f"/proc/{p}").exists() and "Z" not in _state(p)]
    finally:
        proc.kill()
        proc.wait()


def _state(pid: int) -> str:
    """A process's state letter ('' once gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return ""
    return stat[stat.rindex(")") + 2]
