"""Numbers for people: the one formatter of every table and report (issue 35).

A length is shown in one unit per table, chosen from the scale of the sequence (millimetres for a
close-range scan, metres for a car) and stated in the column header or row label, never beside
each number. Every number has 3–4 significant digits; a missing value is a dash, never ``None``.
Keys of ``metrics.json`` get human labels (:func:`label`) and their unit from their name
(``_m``, ``_mm``, ``_deg``, ``_pct``, ``_ms``, ``_s``, ``_px``, ``_mib``; :func:`quantity`).

Files meant for programs (``metrics.json``, ``*.csv``) keep full precision and SI units; this
module is only for what is read by people (terminal tables, ``report.md``/``.html``, ``summary.md``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

MISSING = "–"

# Below this extent of the camera path (bounding-box diagonal, metres) lengths are shown in
# millimetres. Measured: the simulated orbit scan spans 2.0 m (errors of 2–12 mm), the KITTI
# clip 60 m (errors of 0.1 m); a room-size hand-held scan (~5 m) still reads better in mm, a
# street in m.
CLOSE_RANGE_EXTENT_M = 10.0


@dataclass(frozen=True)
class LengthUnit:
    """A display unit of length: its symbol and how many of it make a metre."""

    symbol: str
    per_m: float


MM = LengthUnit("mm", 1e3)

M = LengthUnit("m", 1.0)


def num(v: Any, sig: int = 4) -> str:
    """A number with ``sig`` significant digits (3–4 in tables), plain notation; None/NaN as a dash.

    Integers (and integral floats of 1000 and more, such as counts read back from CSV) print
    without decimals; booleans as yes/no; strings as they are.
    """
    if v is None:
        return MISSING
    if isinstance(v, bool | np.bool_):
        return "yes" if v else "no"
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        x = float(v)
        if not math.isfinite(x):
            return MISSING if math.isnan(x) else ("∞" if x > 0 else "-∞")
        if x == 0.0:
            return "0"
        a = abs(x)
        if a >= 10 ** (sig - 1):
            return f"{x:.0f}" if a < 1e9 else f"{x:.{sig - 1}e}"
        if a < 1e-4:
            return f"{x:.{sig - 1}e}"
        decimals = sig - 1 - math.floor(math.log10(a))
        return f"{x:.{decimals}f}"
    if isinstance(v, list | tuple):
        return " x ".join(num(x, sig) for x in v)
    return str(v)


def extent_m(positions_m: ArrayLike) -> float | None:
    """Bounding-box diagonal of positions (N x 3, metres); None without positions."""
    p = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) == 0:
        return None
    return float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))


def length_unit(scale_m: float | None) -> LengthUnit:
    """Millimetres for a close-range sequence (extent below :data:`CLOSE_RANGE_EXTENT_M`), else metres.

    ``scale_m``: the extent of the camera path or of the scene, metres (None: metres).
    """
    if scale_m is None or not math.isfinite(scale_m):
        return M
    return MM if scale_m < CLOSE_RANGE_EXTENT_M else M


# Quantities: how a value is stored (the key's unit) and how it is shown.
LENGTH_M = "length_m"
LENGTH_MM = "length_mm"
ANGLE = "deg"
PERCENT = "pct"
RATIO = "ratio"  # a fraction 0..1 shown in per cent
MILLISECONDS = "ms"
SECONDS = "s"
PIXELS = "px"
MEBIBYTES = "mib"
RATE = "fps"
HERTZ = "hz"
ANGLE_PER_100M = "deg_per_100m"
COUNT = "count"
PLAIN = "plain"

_SUFFIXES: tuple[tuple[str, str], ...] = (
    ("deg_per_100m", ANGLE_PER_100M),
    ("mm", LENGTH_MM),
    ("m", LENGTH_M),
    ("deg", ANGLE),
    ("pct", PERCENT),
    ("ms", MILLISECONDS),
    ("s", SECONDS),
    ("px", PIXELS),
    ("mib", MEBIBYTES),
    ("fps", RATE),
    ("hz", HERTZ),
)

_STAT_SUFFIXES = ("rmse", "rms", "mean", "median", "max", "min", "std", "p95", "p99", "online", "before", "after")

_KNOWN: dict[str, tuple[str, str]] = {
    "ate_rmse_m": ("ATE RMSE", LENGTH_M),
    "ate_rmse_m_online": ("ATE RMSE online", LENGTH_M),
    "online_ate_rmse_m": ("ATE RMSE online", LENGTH_M),
    "final_ate_mean_m": ("ATE mean", LENGTH_M),
    "final_ate_max_m": ("ATE max", LENGTH_M),
    "rpe_frames_rmse_m": ("RPE per frame RMSE", LENGTH_M),
    "rpe_distance_m": ("RPE distance Δ", LENGTH_M),
    "rpe_distance_rmse_m": ("RPE per distance RMSE", LENGTH_M),
    "kitti_t_err_pct": ("KITTI t error", PERCENT),
    "kitti_r_err_deg_per_100m": ("KITTI r error", ANGLE_PER_100M),
    "end_point_origin_m": ("end-point error (origin aligned)", LENGTH_M),
    "loop_closures": ("loop closures", COUNT),
    "loop_closure_count": ("loop closures", COUNT),
    "ate_change_pct": ("ATE change by closing", PERCENT),
    "drift_pct": ("drift", PERCENT),
    "drift_pct_online": ("drift online", PERCENT),
    "mesh_vertices": ("mesh vertices", COUNT),
    # the reference mesh: the stripes placed with the ground-truth poses (eval.mesh_references)
    "mesh_err_gt_mm": ("mesh error with true poses, mean", LENGTH_MM),
    "mesh_err_gt_mm_p95": ("mesh error with true poses, p95", LENGTH_MM),
    "mesh_completeness_gt": ("mesh completeness with true poses", RATIO),
    "mesh_completeness_swept_gt": ("mesh completeness of the swept truth with true poses", RATIO),
    "mesh_err_mm": ("mesh error vs truth, mean", LENGTH_MM),
    "mesh_err_mm_p95": ("mesh error vs truth, p95", LENGTH_MM),
    "mesh_completeness": ("mesh completeness vs truth", RATIO),
    "mesh_completeness_swept": ("mesh completeness of the swept truth", RATIO),
    "mesh_err_before_mm": ("mesh error before closing, mean", LENGTH_MM),
    "mesh_err_before_mm_p95": ("mesh error before closing, p95", LENGTH_MM),
    "mesh_completeness_before": ("mesh completeness before closing", RATIO),
    "mesh_completeness_swept_before": ("mesh completeness of the swept truth before closing", RATIO),
    "mesh_err_after_mm": ("mesh error after closing, mean", LENGTH_MM),
    "mesh_err_after_mm_p95": ("mesh error after closing, p95", LENGTH_MM),
    "mesh_completeness_after": ("mesh completeness after closing", RATIO),
    "mesh_completeness_swept_after": ("mesh completeness of the swept truth after closing", RATIO),
    "peak_rss_mib": ("peak memory", MEBIBYTES),
    "task_s": ("task time", SECONDS),
    "run_s": ("run time", SECONDS),
    "fps": ("speed", RATE),
    "frames": ("frames", COUNT),
    "matched": ("poses matched", COUNT),
    "keyframe_extent_m": ("keyframe extent", LENGTH_M),
    "ground_truth_extent_m": ("extent of the ground truth", LENGTH_M),
    "path_length_m": ("path length", LENGTH_M),
    "size_mib": ("size", MEBIBYTES),
    "load_s": ("load time", SECONDS),
    "baseline_m": ("baseline", LENGTH_M),
    "rms_px": ("reprojection RMS", PIXELS),
}


def quantity(key: str) -> str:
    """The quantity of a ``metrics.json`` key, from the known keys or the unit in its name."""
    if key in _KNOWN:
        return _KNOWN[key][1]
    parts = key.lower().split("_")
    while len(parts) > 1 and parts[-1] in _STAT_SUFFIXES:  # mesh_err_gt_mm_p95: the unit before the statistic
        parts.pop()
    tail = "_".join(parts)
    for suffix, q in _SUFFIXES:
        if tail.endswith("_" + suffix):
            return q
    if key.startswith(("mesh_completeness", "completeness")):
        return RATIO
    return PLAIN


def label(key: str) -> str:
    """A human label for a ``metrics.json`` key, without its unit (see :meth:`Formatter.header`)."""
    if key in _KNOWN:
        return _KNOWN[key][0]
    units = {s for s, _ in _SUFFIXES} | {"per", "100m"}
    words = [w for w in key.split("_") if w.lower() not in units] or key.split("_")
    return " ".join(_WORDS.get(w.lower(), w) for w in words)


_WORDS = {"ate": "ATE", "rpe": "RPE", "rmse": "RMSE", "klt": "KLT", "kf": "keyframe", "gt": "vs truth"}


@dataclass(frozen=True)
class Formatter:
    """Formats the numbers of one table: lengths in :attr:`length` (mm or m), the rest in their own units."""

    length: LengthUnit = M

    @classmethod
    def for_scale(cls, scale_m: float | None) -> Formatter:
        """The formatter of a sequence whose camera path (or scene) extends ``scale_m`` metres."""
        return cls(length_unit(scale_m))

    @classmethod
    def for_positions(cls, positions_m: ArrayLike) -> Formatter:
        """The formatter of a sequence from its camera positions (N x 3, metres)."""
        return cls.for_scale(extent_m(positions_m))

    def unit(self, q: str) -> str:
        """The display unit of a quantity (empty for counts and plain values)."""
        return {
            LENGTH_M: self.length.symbol,
            LENGTH_MM: self.length.symbol,
            ANGLE: "°",
            PERCENT: "%",
            RATIO: "%",
            MILLISECONDS: "ms",
            SECONDS: "s",
            PIXELS: "px",
            MEBIBYTES: "MiB",
            RATE: "fps",
            HERTZ: "Hz",
            ANGLE_PER_100M: "°/100 m",
        }.get(q, "")

    def scaled(self, q: str, v: Any) -> Any:
        """A value of quantity ``q`` converted to its display unit (non-numbers as they are)."""
        if not isinstance(v, int | float | np.integer | np.floating) or isinstance(v, bool):
            return v
        x = float(v)
        if q == LENGTH_M:
            return x * self.length.per_m
        if q == LENGTH_MM:
            return x * 1e-3 * self.length.per_m
        if q == RATIO:
            return x * 100.0
        if q == COUNT and x.is_integer():
            return int(x)
        return v

    def value(self, key: str, v: Any, sig: int = 4) -> str:
        """The value of a ``metrics.json`` key as shown in a column headed by :meth:`header`."""
        q = quantity(key)
        if isinstance(v, list | tuple):
            return " x ".join(num(self.scaled(q, x), sig) for x in v)
        return num(self.scaled(q, v), sig)

    def header(self, key: str, text: str | None = None) -> str:
        """Column header of a key: its label (or ``text``) and the display unit in brackets."""
        u = self.unit(quantity(key))
        name = text if text is not None else label(key)
        return f"{name} [{u}]" if u else name

    def length_text(self, v_m: float | None) -> str:
        """A length with its unit, for prose (``12.21 mm``)."""
        return MISSING if v_m is None else f"{num(self.scaled(LENGTH_M, v_m))} {self.length.symbol}"


def key_values(values: Mapping[str, Any], fmt: Formatter | None = None) -> str:
    """``fx 469.4 px, baseline 59.94 mm, image size 640 x 480``: a small mapping in one line.

    Keys are shown by their label, values in their unit (lengths in ``fmt``'s unit); nested
    mappings in parentheses. The same text wherever a calibration or a count mapping is shown.
    """
    f = fmt or Formatter()
    parts = []
    for k, v in values.items():
        key = str(k)
        if isinstance(v, Mapping):
            parts.append(f"{label(key)} ({key_values(v, f)})")
            continue
        u = f.unit(quantity(key))
        text = v if isinstance(v, str) else f.value(key, v)
        parts.append(f"{label(key)} {text}" + (f" {u}" if u and not isinstance(v, str) else ""))
    return ", ".join(parts)


def describe_rows(desc: Mapping[str, Any], fmt: Formatter | None = None) -> list[tuple[str, str]]:
    """(label with unit, value) rows of a description (``info``, ``map info``): no raw keys, no None."""
    f = fmt or Formatter()
    rows = []
    for k, v in desc.items():
        if v is None:
            continue
        if isinstance(v, Mapping):
            rows.append((label(k), key_values(v, f)))
        elif isinstance(v, str):
            rows.append((label(k), v))
        else:
            rows.append((f.header(k), f.value(k, v)))
    return rows


def table_cells(row: Iterable[Any], sig: int = 4) -> list[str]:
    """Strings of a row of plain values (numbers formatted by :func:`num`)."""
    return [v if isinstance(v, str) else num(v, sig) for v in row]


__all__ = [
    "CLOSE_RANGE_EXTENT_M",
    "M",
    "MISSING",
    "MM",
    "Formatter",
    "LengthUnit",
    "extent_m",
    "describe_rows",
    "key_values",
    "label",
    "length_unit",
    "num",
    "quantity",
    "table_cells",
]
