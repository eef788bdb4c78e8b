"""Turntable laser-scan folders: frames, camera calibration, laser plane(s), step and markers.

Folder layout (paths in the layout file are relative to the folder)::

    FOLDER/
      turntable.yaml          the layout (or pass one with --layout)
      frames/*.jpg|png        one colour frame per motor step, ordered by the number in the name
      <camera>.yaml           intrinsics of the frames (ROS camera_info or OpenCV camera_matrix/dist_coeff)
      <planes>.json|yaml      the laser plane: one plane YAML of `loopmodel calibrate laser`, or a JSON
                              of candidate planes {"planes": {name: [a, b, c, d]}} (camera frame, m)

The layout file::

    frames: frames/step_num*.jpg
    camera: calibration4.yaml
    laser_planes: laser_planes.json      # or laser_plane: plane.yaml
    step_deg: 1.125                      # motor step about the table axis (default 360 / frames)
    laser_colour: green
    markers: {dictionary: DICT_4X4_50, side_m: 0.03, ids: [5, 42, 27, 18],
              centre_in_marker_m: {5: [-0.09, 0], 42: [0.09, 0], 27: [0, -0.09], 18: [0, 0.09]}}
    table_radius_m: 0.125
    volume: {radius_m: 0.085, z_min_m: 0.004, z_max_m: 0.2}

``centre_in_marker_m`` is the nominal table centre in each marker's frame (x right, y up on
the printed marker, metres); the scan refines the layout from the rotation itself.
"""

from __future__ import annotations

import glob
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from loopmodel.errors import FormatError, InputError
from loopmodel.io.camera_yaml import read_intrinsics
from loopmodel.io.images import read_image
from loopmodel.mapping.extraction import LightPlane

F64 = NDArray[np.float64]


@dataclass
class MarkerLayout:
    """ArUco markers on the table top.

    Dictionary, side (m), ids and the nominal table centre in each marker's frame (m).
    """

    dictionary: str = "DICT_4X4_50"
    side_m: float = 0.03
    ids: list[int] = field(default_factory=list)
    centre_in_marker_m: dict[int, tuple[float, float]] = field(default_factory=dict)


@dataclass
class WorkingVolume:
    """Cylinder above the table (table frame, metres) where object points are kept."""

    radius_m: float = 0.085
    z_min_m: float = 0.004
    z_max_m: float = 0.2


@dataclass
class TurntableScan:
    """A turntable scan folder opened through its layout."""

    folder: Path
    frame_paths: list[Path]
    K: F64
    dist: F64
    image_size: tuple[int, int]
    planes: dict[str, LightPlane]
    step_deg: float
    markers: MarkerLayout
    laser_colour: str = "green"
    table_radius_m: float = 0.125
    volume: WorkingVolume = field(default_factory=WorkingVolume)
    layout_path: Path | None = None

    def __len__(self) -> int:
        return len(self.frame_paths)

    def frames(self) -> Iterator[tuple[int, NDArray[np.uint8]]]:
        """(index, BGR image) of every frame; each must have the calibration's size."""
        for k, p in enumerate(self.frame_paths):
            img = read_image(p)
            if img.ndim != 3 or (img.shape[1], img.shape[0]) != self.image_size:
                raise InputError(
                    p, f"expected a {self.image_size[0]}x{self.image_size[1]} colour image, got shape {img.shape}"
                )
            yield k, img

    def timestamps_ns(self) -> list[int]:
        """Synthetic frame times: one step per second (the scan has no clock)."""
        return [k * 1_000_000_000 for k in range(len(self.frame_paths))]


def _number(p: Path) -> tuple[int, str]:
    m = re.findall(r"\d+", p.stem)
    return (int(m[-1]) if m else -1, p.name)


def _planes(path: Path) -> dict[str, LightPlane]:
    if path.suffix.lower() == ".json":
        from loopmodel.calibration.laser import read_laser_planes_json

        return read_laser_planes_json(path)
    from loopmodel.io.text import one_line, read_text_file

    try:
        data = yaml.safe_load(read_text_file(path, "plane YAML"))
    except (OSError, yaml.YAMLError, RecursionError) as exc:
        raise FormatError(path, f"cannot read plane YAML ({one_line(exc)})") from None
    abcd = data.get("plane_abcd") if isinstance(data, dict) else None
    if not isinstance(abcd, list) or len(abcd) != 4:
        raise FormatError(path, "expected 'plane_abcd: [a, b, c, d]' (a plane of `loopmodel calibrate laser`)")
    return {path.stem: LightPlane(np.asarray(abcd[:3], dtype=float), float(abcd[3]))}


def _get(data: dict[str, Any], key: str, kind: type, source: Path, default: Any = None) -> Any:
    v = data.get(key, default)
    if v is None:
        raise InputError(source, f"missing '{key}'")
    if kind is float and isinstance(v, int):
        v = float(v)
    if not isinstance(v, kind):
        raise InputError(source, f"'{key}' must be a {kind.__name__}, got {v!r}")
    return v


def _inside(relative: str, key: str, lp: Path) -> str:
    """A path the layout names, confined to the scan folder: relative, without '..' (issue 34)."""
    if Path(relative).is_absolute() or ".." in Path(relative).parts or "\0" in relative:
        raise InputError(lp, f"'{key}' must be a path inside the scan folder, got '{relative}'")
    return relative


def _read_layout_yaml(lp: Path) -> dict[str, Any]:
    """The layout file's mapping; one line naming the file for anything else."""
    from loopmodel.io.text import one_line, read_text_file

    try:
        data = yaml.safe_load(read_text_file(lp, "turntable layout"))
    except yaml.YAMLError as exc:
        raise FormatError(lp, f"cannot parse YAML ({one_line(exc)})") from None
    except RecursionError:
        raise FormatError(lp, "cannot parse YAML (nested too deeply)") from None
    if not isinstance(data, dict):
        raise FormatError(lp, "expected a YAML mapping")
    return data


def _check_layout_values(
    lp: Path, markers: MarkerLayout, volume: WorkingVolume, step_deg: float, table_radius_m: float
) -> None:
    """Physically possible layout values (issue 34: a NaN, zero or negative step; a negative radius)."""
    if not (math.isfinite(step_deg) and 0 < abs(step_deg) <= 360):
        raise InputError(lp, f"'step_deg' must be a finite angle in (0, 360] degrees, got {step_deg}")
    if not (math.isfinite(markers.side_m) and markers.side_m > 0):
        raise InputError(lp, f"'markers.side_m' must be a positive length, got {markers.side_m}")
    if not (math.isfinite(table_radius_m) and table_radius_m > 0):
        raise InputError(lp, f"'table_radius_m' must be a positive length, got {table_radius_m}")
    if not (math.isfinite(volume.radius_m) and volume.radius_m > 0):
        raise InputError(lp, f"'volume.radius_m' must be a positive length, got {volume.radius_m}")
    if not (math.isfinite(volume.z_min_m) and math.isfinite(volume.z_max_m) and volume.z_min_m < volume.z_max_m):
        raise InputError(lp, f"'volume' needs finite z_min_m < z_max_m, got {volume.z_min_m}, {volume.z_max_m}")


def open_turntable(
    folder: str | Path, layout: str | Path | None = None, extra_planes: Sequence[Path] = ()
) -> TurntableScan:
    """Open a turntable scan folder with its layout file (``FOLDER/turntable.yaml`` by default)."""
    root = Path(folder)
    if not root.is_dir():
        raise InputError(root, "is not a turntable scan folder")
    lp = Path(layout) if layout is not None else root / "turntable.yaml"
    if not lp.is_file():
        raise InputError(lp, "turntable layout file not found (pass --layout; see loopmodel.turntable.reader)")
    data = _read_layout_yaml(lp)
    pattern = _inside(_get(data, "frames", str, lp), "frames", lp)
    frames = sorted((Path(f) for f in glob.glob(str(root / pattern))), key=_number)
    if not frames:
        raise InputError(root / pattern, "no frames match")
    K, dist, size = read_intrinsics(root / _inside(_get(data, "camera", str, lp), "camera", lp))
    if size is None:
        img = read_image(frames[0])
        size = (int(img.shape[1]), int(img.shape[0]))
    planes: dict[str, LightPlane] = {}
    for key in ("laser_planes", "laser_plane"):
        if key in data:
            planes.update(_planes(root / _inside(_get(data, key, str, lp), key, lp)))
    for p in extra_planes:
        planes.update(_planes(Path(p)))
    if not planes:
        raise InputError(lp, "no laser plane ('laser_plane' or 'laser_planes')")
    m = data.get("markers") or {}
    if not isinstance(m, dict) or not m.get("ids"):
        raise InputError(lp, "'markers' needs 'ids' (and dictionary, side_m, centre_in_marker_m)")
    try:
        centres = {int(k): (float(v[0]), float(v[1])) for k, v in (m.get("centre_in_marker_m") or {}).items()}
        markers = MarkerLayout(
            str(m.get("dictionary", "DICT_4X4_50")), float(m.get("side_m", 0.03)), [int(i) for i in m["ids"]], centres
        )
        vol = data.get("volume") or {}
        volume = WorkingVolume(**{k: float(v) for k, v in vol.items() if k in ("radius_m", "z_min_m", "z_max_m")})
        step = float(data.get("step_deg", 360.0 / len(frames)))
        table_radius_m = float(data.get("table_radius_m", 0.125))
    except (TypeError, ValueError, AttributeError, IndexError, KeyError) as exc:
        raise FormatError(lp, f"malformed layout value ({type(exc).__name__}: {exc})") from None
    _check_layout_values(lp, markers, volume, step, table_radius_m)
    scan = TurntableScan(
        root,
        frames,
        K,
        dist,
        size,
        planes,
        step,
        markers,
        str(data.get("laser_colour", "green")),
        table_radius_m,
        volume,
        lp,
    )
    from loopmodel.calibration.laser import check_intrinsics_fit

    check_intrinsics_fit(frames[0], size, K, None)
    return scan
