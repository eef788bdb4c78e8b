"""Trajectory files in TUM, KITTI and EuRoC CSV form, read and written at full precision.

TUM: ``t tx ty tz qx qy qz qw`` (t in seconds, 9 decimals written). KITTI: 12 numbers,
row-major 3x4 ``world_from_cam``, no times. EuRoC: ``timestamp_ns, px, py, pz, qw, qx, qy,
qz`` (ground-truth files with 17 columns are read too). Poses are ``world_from_cam``.
"""

from __future__ import annotations

import os
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import FormatError, InputError
from loopmodel.geometry.se3 import quat_wxyz_from_rotation, rotation_from_quat_wxyz
from loopmodel.io.atomic import write_text_atomic
from loopmodel.io.text import read_text_file, require_regular_file
from loopmodel.types import Trajectory

TrajectoryFormat = Literal["tum", "kitti", "euroc"]


def seconds_text_to_ns(text: str) -> int:
    """Exact nanoseconds of a decimal seconds string (no float rounding)."""
    return int((Decimal(text) * 1_000_000_000).to_integral_value())


def ns_to_seconds_text(t_ns: int) -> str:
    """Seconds with 9 decimals for an integer nanosecond time (exact)."""
    sign = "-" if t_ns < 0 else ""
    a = abs(int(t_ns))
    return f"{sign}{a // 1_000_000_000}.{a % 1_000_000_000:09d}"


#: Below this a pose value is rounding noise (a femtometre; a quaternion component of 1e-15): the
#: first pose of a run, the world's origin, reads 0.0 instead of 2.11e-23 (issue 35).
NOISE_FLOOR = 1e-15


def _fmt(x: float) -> str:
    return "0.0" if abs(x) < NOISE_FLOOR else repr(float(x))


def guess_format(path: str | Path) -> TrajectoryFormat:
    """Format from the extension and the first data line."""
    p = Path(path)
    if p.suffix.lower() == ".csv":
        return "euroc"
    if p.suffix.lower() == ".tum":
        return "tum"
    for line in read_text_file(p, "trajectory file").splitlines():
        s = line.strip()
        if s and not s.startswith("#"):
            n = len(s.replace(",", " ").split())
            if "," in s:
                return "euroc"
            return "kitti" if n == 12 else "tum"
    raise FormatError(p, "trajectory file has no data lines")


def _rows(path: Path, sep: str | None, expected: tuple[int, ...]) -> list[list[str]]:
    rows: list[list[str]] = []
    for lineno, line in enumerate(read_text_file(path, "trajectory file").splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#") or (sep == "," and s[0].isalpha()):
            continue
        parts = [p.strip() for p in s.split(sep)] if sep else s.split()
        if len(parts) not in expected:
            want = " or ".join(str(e) for e in expected)
            raise FormatError(path, f"line {lineno}: expected {want} columns, found {len(parts)}")
        rows.append(parts)
    if not rows:
        raise FormatError(path, "trajectory file has no data lines")
    return rows


#: the largest position a trajectory file may hold (m): beyond Earth-centred coordinates (6.4e6 m)
MAX_POSITION_M = 1e8


def _floats(path: Path, rows: list[list[str]], cols: slice) -> NDArray[np.float64]:
    try:
        return np.array([[float(v) for v in r[cols]] for r in rows], dtype=float)
    except ValueError as exc:
        raise FormatError(path, f"non-numeric value ({exc})") from None


def _check_values(path: Path, position_m: NDArray[np.float64], quat: NDArray[np.float64] | None) -> None:
    """Positions within ``MAX_POSITION_M``, quaternions of a norm near 1 (issue 34: 1e298, 1e308)."""
    with np.errstate(over="ignore", invalid="ignore"):
        far = np.flatnonzero(~(np.abs(position_m) <= MAX_POSITION_M).all(axis=1))
        if far.size:
            raise FormatError(path, f"row {int(far[0]) + 1}: position beyond {MAX_POSITION_M:g} m")
        if quat is not None:
            norm = np.linalg.norm(quat, axis=1)
            bad = np.flatnonzero(~((norm > 0.5) & (norm < 2.0)))
            if bad.size:
                raise FormatError(path, f"row {int(bad[0]) + 1}: quaternion of norm {norm[bad[0]]:g}, not a rotation")


def read_trajectory(
    path: str | Path,
    fmt: TrajectoryFormat | None = None,
    timestamps_ns: NDArray[np.int64] | None = None,
    rate_hz: float = 10.0,
    check: bool = True,
) -> Trajectory:
    """Read a trajectory file.

    KITTI files take ``timestamps_ns`` or ``rate_hz`` for times. Repeated timestamps (found in real
    files) are kept; times going backwards are an error.
    """
    p = Path(path)
    if not os.path.lexists(p):
        raise InputError(p, "trajectory file does not exist")
    require_regular_file(p, "trajectory file")  # a FIFO, a device, a folder, a link loop: named as such
    fmt = fmt or guess_format(p)
    if fmt == "tum":
        rows = _rows(p, None, (8,))
        try:
            t = np.array([seconds_text_to_ns(r[0]) for r in rows], dtype=np.int64)
        except (InvalidOperation, ValueError, OverflowError):
            raise FormatError(p, "timestamp column is not a finite number") from None
        v = _floats(p, rows, slice(1, 8)).reshape(-1, 7)
        _check_values(p, v[:, :3], v[:, 3:7])
        T = np.tile(np.eye(4), (len(rows), 1, 1))
        T[:, :3, 3] = v[:, :3]
        T[:, :3, :3] = rotation_from_quat_wxyz(v[:, [6, 3, 4, 5]])
    elif fmt == "kitti":
        rows = _rows(p, None, (12,))
        v = _floats(p, rows, slice(0, 12)).reshape(-1, 12)
        _check_values(p, v[:, [3, 7, 11]], None)
        T = np.tile(np.eye(4), (len(rows), 1, 1))
        T[:, :3, :] = v.reshape(-1, 3, 4)
        if timestamps_ns is None:
            t = np.round(np.arange(len(rows)) * (1e9 / rate_hz)).astype(np.int64)
        else:
            t = np.asarray(timestamps_ns, dtype=np.int64)
            if t.shape[0] != len(rows):
                raise FormatError(p, f"{len(rows)} poses but {t.shape[0]} timestamps")
    elif fmt == "euroc":
        rows = _rows(p, ",", (8, 17))
        try:
            t = np.array([int(Decimal(r[0])) for r in rows], dtype=np.int64)
        except (InvalidOperation, ValueError, OverflowError):
            raise FormatError(p, "timestamp column is not an integer of nanoseconds") from None
        v = _floats(p, rows, slice(1, 8)).reshape(-1, 7)
        _check_values(p, v[:, :3], v[:, 3:7])
        T = np.tile(np.eye(4), (len(rows), 1, 1))
        T[:, :3, 3] = v[:, :3]
        T[:, :3, :3] = rotation_from_quat_wxyz(v[:, 3:7])
    else:
        raise FormatError(p, f"unknown trajectory format '{fmt}' (expected tum, kitti or euroc)")
    traj = Trajectory(t, T)
    return traj.check(str(p), strict=False) if check else traj


def format_trajectory(traj: Trajectory, fmt: TrajectoryFormat) -> str:
    """Text of a trajectory file in the given format (full precision)."""
    lines: list[str] = []
    if fmt == "tum":
        lines.append("# timestamp_s tx ty tz qx qy qz qw (world_from_cam)")
        q = quat_wxyz_from_rotation(traj.world_from_cam[:, :3, :3]) if len(traj) else np.zeros((0, 4))
        for t, T, qq in zip(traj.timestamps_ns, traj.world_from_cam, q, strict=True):
            vals = [*T[:3, 3], qq[1], qq[2], qq[3], qq[0]]
            lines.append(ns_to_seconds_text(int(t)) + " " + " ".join(_fmt(x) for x in vals))
    elif fmt == "kitti":
        for T in traj.world_from_cam:
            lines.append(" ".join(_fmt(x) for x in T[:3, :].ravel()))
    elif fmt == "euroc":
        lines.append("#timestamp [ns],p_x [m],p_y [m],p_z [m],q_w [],q_x [],q_y [],q_z []")
        q = quat_wxyz_from_rotation(traj.world_from_cam[:, :3, :3]) if len(traj) else np.zeros((0, 4))
        for t, T, qq in zip(traj.timestamps_ns, traj.world_from_cam, q, strict=True):
            lines.append(",".join([str(int(t)), *(_fmt(x) for x in [*T[:3, 3], *qq])]))
    else:
        raise ValueError(f"unknown trajectory format {fmt!r}")
    return "\n".join(lines) + "\n"


def write_trajectory(path: str | Path, traj: Trajectory, fmt: TrajectoryFormat | None = None) -> Path:
    """Write a trajectory atomically.

    The format defaults from the extension (.tum/.txt: TUM, .kitti: KITTI, .csv: EuRoC).
    """
    p = Path(path)
    if fmt is None:
        fmt = {".csv": "euroc", ".kitti": "kitti"}.get(p.suffix.lower(), "tum")  # type: ignore[assignment]
    return write_text_atomic(p, format_trajectory(traj, fmt))  # type: ignore[arg-type]
