"""Batch plans: sequences x configuration variants, expanded into tasks with stable identities.

A plan is a YAML file::

    sequences:                      # paths or globs, relative to the plan file
      - ../data/kitti_clip
      - path: scans/*.mcap
        config: configs/sim.yaml    # optional per-sequence config layer (file or mapping)
    base: configs/default.yaml      # optional base config (file or mapping)
    grid:                           # every combination is one variant ...
      frontend.max_features: [500, 1000]
      backend.kind: [isam2, both]
    variants:                       # ... and/or explicit variants
      - name: coarse
        set: {frontend.max_features: 300}
    max_frames: 40                  # optional, per task
    threads_per_task: 1             # OpenCV/numba/BLAS threads a task may use
    retries: 1                      # Dask retries of a task that raises outside the pipeline

The effective config of a task is, in order: the code defaults, the batch defaults
(:data:`BATCH_DEFAULTS`), ``base``, the sequence's ``config``, the variant's overrides.
A task's results folder is named ``<sequence>__<variant>__<hash>`` where the hash covers the
sequence's identity (names, sizes and head/tail bytes of its files), the effective config
(without ``output.out_dir``), ``max_frames`` and the package version.
"""

from __future__ import annotations

import glob
import hashlib
import itertools
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from loopmodel import __version__
from loopmodel.config import Config, LoopConfig, config_from_dict, merge_nested
from loopmodel.errors import InputError, LoopmodelError

#: the most configuration variants a plan may have (each one a task per sequence)
MAX_VARIANTS = 1000

PLAN_KEYS = ("sequences", "base", "grid", "variants", "max_frames", "threads_per_task", "retries", "name")

# loop closing's global BA in a process of its own: off in a batch where tasks already fill
# the cores (and where its result would depend on timing); a plan may turn it back on
BATCH_DEFAULTS: dict[str, Any] = (
    {"loop": {"background_ba": False}} if "background_ba" in LoopConfig.model_fields else {}
)
# issue 33: a batch already keeps every core busy with one task each, so a task's back end runs
# inline (no worker beside the tracker): the same frames then give the same numbers, run after run
BATCH_DEFAULTS["backend"] = {"worker": "inline"}

_HASH_CHUNK_BYTES = 1 << 16


@dataclass(frozen=True)
class TaskSpec:
    """One (sequence, variant) run: everything a worker needs, picklable."""

    task_id: str
    sequence_path: str
    sequence_name: str
    variant: str
    overrides: dict[str, Any]
    config: dict[str, Any]
    max_frames: int | None
    threads: int
    out_dir: str
    version: str

    @property
    def folder(self) -> Path:
        """The finished results folder of the task."""
        return Path(self.out_dir) / "tasks" / self.task_id


@dataclass
class Variant:
    """A named set of dotted config overrides."""

    name: str
    overrides: dict[str, Any]


@dataclass
class SequenceEntry:
    """A sequence of the plan with its optional config layer."""

    path: Path
    name: str
    config: dict[str, Any] = field(default_factory=dict)


@dataclass
class Plan:
    """A parsed plan (paths absolute)."""

    source: Path
    sequences: list[SequenceEntry]
    variants: list[Variant]
    base: dict[str, Any]
    max_frames: int | None = None
    threads_per_task: int = 1
    retries: int = 1
    name: str = "batch"

    def tasks(self, out_dir: str | Path) -> list[TaskSpec]:
        """Every (sequence, variant) task, in plan order; effective configs validated here."""
        out = str(Path(out_dir).resolve())
        specs: list[TaskSpec] = []
        ident_cache: dict[Path, str] = {}
        for seq in self.sequences:
            ident = ident_cache.setdefault(seq.path, sequence_identity(seq.path))
            for var in self.variants:
                layers = [BATCH_DEFAULTS, self.base, seq.config, nested_from_dotted(var.overrides, self.source)]
                cfg = effective_config(layers, self.source)
                cfg_dict = cfg.model_dump(mode="json")
                digest = task_hash(ident, cfg_dict, self.max_frames, __version__)
                task_id = f"{_slug(seq.name)}__{_slug(var.name)}__{digest[:12]}"
                specs.append(
                    TaskSpec(
                        task_id,
                        str(seq.path),
                        seq.name,
                        var.name,
                        dict(var.overrides),
                        cfg_dict,
                        self.max_frames,
                        self.threads_per_task,
                        out,
                        __version__,
                    )
                )
        ids = [s.task_id for s in specs]
        dup = {i for i in ids if ids.count(i) > 1}
        if dup:
            raise InputError(self.source, f"tasks with the same sequence and effective config: {sorted(dup)}")
        return specs


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._=-]+", "-", text).strip("-")[:60] or "x"


def nested_from_dotted(overrides: dict[str, Any], source: str | Path | None = None) -> dict[str, Any]:
    """``{"frontend.max_features": 500}`` -> ``{"frontend": {"max_features": 500}}``."""
    nested: dict[str, Any] = {}
    for key, value in overrides.items():
        parts = str(key).split(".")
        if not all(parts):
            raise InputError(source, f"override key '{key}' must be dotted section names, e.g. frontend.max_features")
        node = nested
        for p in parts[:-1]:
            child = node.setdefault(p, {})
            if not isinstance(child, dict):
                raise InputError(source, f"override key '{key}' conflicts with another override")
            node = child
        node[parts[-1]] = value
    return nested


def effective_config(layers: list[dict[str, Any]], source: str | Path | None = None) -> Config:
    """The code defaults overridden by each nested layer in turn (validated; errors name the key)."""
    merged: dict[str, Any] = {}
    for layer in layers:
        merged = merge_nested(merged, layer)
    return config_from_dict(merged, source)


def _hash_payload(cfg_dict: dict[str, Any]) -> dict[str, Any]:
    """The config without settings that do not change a run's results (where it is written)."""
    c = json.loads(json.dumps(cfg_dict))
    c.get("output", {}).pop("out_dir", None)
    return c


def task_hash(sequence_ident: str, cfg_dict: dict[str, Any], max_frames: int | None, version: str) -> str:
    """SHA-256 (hex) of a task's identity: sequence, effective config, frame limit, version."""
    payload = {
        "sequence": sequence_ident,
        "config": _hash_payload(cfg_dict),
        "max_frames": max_frames,
        "version": version,
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def sequence_identity(path: Path) -> str:
    """SHA-256 over the sequence's files: relative names, sizes and their first and last 64 KiB.

    Independent of where the sequence lives and of file times (a copy keeps its identity);
    reading only the ends keeps a re-run of a large batch fast.
    """
    if not path.exists():
        return "missing:" + path.name
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    h = hashlib.sha256()
    for f in files:
        rel = f.name if f == path else f.relative_to(path).as_posix()
        size = f.stat().st_size
        h.update(f"{rel}\0{size}\0".encode())
        with open(f, "rb") as fh:
            h.update(fh.read(_HASH_CHUNK_BYTES))
            if size > 2 * _HASH_CHUNK_BYTES:
                fh.seek(size - _HASH_CHUNK_BYTES)
                h.update(fh.read(_HASH_CHUNK_BYTES))
    return h.hexdigest()


def _config_layer(value: Any, base_dir: Path, key: str, source: Path) -> dict[str, Any]:
    """A config layer given as a mapping (nested or dotted keys) or a YAML file path."""
    if value is None:
        return {}
    if isinstance(value, str):
        p = (base_dir / value).resolve()
        if not p.is_file():
            raise InputError(source, f"'{key}': config file {p} does not exist")
        try:
            data = yaml.safe_load(p.read_text()) or {}
        except yaml.YAMLError as exc:
            raise InputError(p, f"not valid YAML ({str(exc).splitlines()[0]})") from None
        if not isinstance(data, dict):
            raise InputError(p, "expected a mapping of config sections")
        return data
    if isinstance(value, dict):
        flat = {k: v for k, v in value.items() if "." in str(k)}
        nested = {k: v for k, v in value.items() if "." not in str(k)}
        return merge_nested(nested, nested_from_dotted(flat, source))
    raise InputError(source, f"'{key}' must be a config file path or a mapping, got {type(value).__name__}")


def _variant_name(overrides: dict[str, Any]) -> str:
    """``backend.kind=isam2,frontend.max_features=300``: the whole dotted key, section included."""
    return ",".join(f"{k}={v}" for k, v in overrides.items()) or "base"


def _variants(data: dict[str, Any], source: Path) -> list[Variant]:
    out: list[Variant] = []
    grid = data.get("grid")
    if grid is not None:
        if not isinstance(grid, dict) or not grid:
            raise InputError(source, "'grid' must map dotted config keys to lists of values")
        keys = list(grid)
        for k in keys:
            if not isinstance(grid[k], list) or not grid[k]:
                raise InputError(source, f"grid key '{k}' must have a non-empty list of values")
        count = 1
        for k in keys:  # counted before anything is expanded (issue 34: 10 keys x 10 values)
            count *= len(grid[k])
        count += len(data.get("variants") or [])
        if count > MAX_VARIANTS:
            raise InputError(
                source,
                f"the grid makes {count} variants ({' x '.join(str(len(grid[k])) for k in keys)}), "
                f"more than the limit of {MAX_VARIANTS}; split the plan",
            )
        for combo in itertools.product(*(grid[k] for k in keys)):
            ov = dict(zip(keys, combo, strict=True))
            out.append(Variant(_variant_name(ov), ov))
    for k, v in enumerate(data.get("variants") or []):
        if not isinstance(v, dict):
            raise InputError(source, f"variants[{k}] must be a mapping with 'name' and 'set'")
        unknown = set(v) - {"name", "set"}
        if unknown:
            raise InputError(source, f"variants[{k}]: unknown key(s) {sorted(unknown)} (use 'name' and 'set')")
        ov = v.get("set") or {}
        if not isinstance(ov, dict):
            raise InputError(source, f"variants[{k}].set must map dotted config keys to values")
        out.append(Variant(str(v.get("name") or _variant_name(ov)), dict(ov)))
    if not out:
        out.append(Variant("base", {}))
    names = [v.name for v in out]
    if len(set(names)) != len(names):
        raise InputError(source, f"variant names must be distinct, got {names}")
    return out


def _sequences(data: dict[str, Any], base_dir: Path, source: Path) -> list[SequenceEntry]:
    items = data.get("sequences")
    if not isinstance(items, list) or not items:
        raise InputError(source, "'sequences' must be a non-empty list of paths, globs or {path, config}")
    out: list[SequenceEntry] = []
    for k, item in enumerate(items):
        cfg: dict[str, Any] = {}
        name = None
        if isinstance(item, dict):
            unknown = set(item) - {"path", "config", "name"}
            if unknown or "path" not in item:
                raise InputError(source, f"sequences[{k}] needs 'path' (and optional 'config', 'name')")
            pattern, name = str(item["path"]), item.get("name")
            cfg = _config_layer(item.get("config"), base_dir, f"sequences[{k}].config", source)
        elif isinstance(item, str):
            pattern = item
        else:
            raise InputError(source, f"sequences[{k}] must be a path, a glob or a mapping")
        full = str(base_dir / pattern) if not Path(pattern).is_absolute() else pattern
        if glob.has_magic(full):
            matches = sorted(glob.glob(full))
            if not matches:
                raise InputError(source, f"sequences[{k}]: the glob '{pattern}' matches nothing")
            paths = [Path(m).resolve() for m in matches]
        else:
            paths = [Path(full).resolve()]
        for p in paths:
            seq_name = str(name) if name and len(paths) == 1 else p.stem
            out.append(SequenceEntry(p, seq_name, cfg))
    names = [s.name for s in out]
    for n in set(names):
        if names.count(n) > 1:  # same stem in different folders: add the parent folder
            for s in out:
                if s.name == n:
                    s.name = f"{s.path.parent.name}-{s.path.stem}"
    return out


def load_plan(path: str | Path) -> Plan:
    """Read and check a plan file (see the module docstring); errors name the file and key."""
    from loopmodel.io.text import read_text_file

    p = Path(path)
    if not p.exists():
        raise InputError(p, "plan file does not exist")
    try:
        data = yaml.safe_load(read_text_file(p, "plan file"))
    except yaml.YAMLError as exc:
        raise InputError(p, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    except RecursionError:
        raise InputError(p, "not valid YAML (nested too deeply)") from None
    if not isinstance(data, dict):
        raise InputError(p, "a plan is a mapping with 'sequences' and 'grid' or 'variants'")
    unknown = set(data) - set(PLAN_KEYS)
    if unknown:
        raise InputError(p, f"unknown key(s) {sorted(unknown)}; expected {', '.join(PLAN_KEYS)}")
    base_dir = p.resolve().parent
    max_frames = data.get("max_frames")
    if max_frames is not None and (not isinstance(max_frames, int) or max_frames < 1):
        raise InputError(p, f"'max_frames' must be a positive integer, got {max_frames!r}")
    threads = data.get("threads_per_task", 1)
    if not isinstance(threads, int) or threads < 1:
        raise InputError(p, f"'threads_per_task' must be a positive integer, got {threads!r}")
    retries = data.get("retries", 1)
    if not isinstance(retries, int) or retries < 0:
        raise InputError(p, f"'retries' must be an integer >= 0, got {retries!r}")
    plan = Plan(
        p.resolve(),
        _sequences(data, base_dir, p),
        _variants(data, p),
        _config_layer(data.get("base"), base_dir, "base", p),
        max_frames,
        threads,
        retries,
        str(data.get("name") or p.stem),
    )
    try:  # every effective config is valid before anything runs
        for seq in plan.sequences:
            for var in plan.variants:
                effective_config([BATCH_DEFAULTS, plan.base, seq.config, nested_from_dotted(var.overrides, p)], p)
    except LoopmodelError as exc:
        msg = exc.problem if isinstance(exc, InputError) else str(exc)
        raise InputError(p, f"variant '{var.name}' with sequence '{seq.name}': {msg}") from None
    for seq in plan.sequences:  # refused with the plan, not found only when its task runs (issue 34)
        if not seq.path.exists():
            raise InputError(p, f"sequence '{seq.name}': {seq.path} does not exist")
    return plan
