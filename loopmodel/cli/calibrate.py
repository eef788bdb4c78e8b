"""``loopmodel calibrate stereo|laser`` and ``loopmodel turntable scan|convert``: real rigs."""

from __future__ import annotations

import glob
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from loopmodel.cli import console, err_console
from loopmodel.errors import InputError

calibrate_app = typer.Typer(help="Calibrate a real rig: stereo cameras, the laser plane.", no_args_is_help=True)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".tif", ".tiff")


def image_list(spec: str, what: str) -> list[Path]:
    """Images named by a folder, a glob pattern (quote it) or one file, sorted by name."""
    p = Path(spec)
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
    elif p.is_file():
        files = [p]
    else:
        files = sorted(Path(f) for f in glob.glob(spec) if Path(f).suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise InputError(spec, f"no {what} images (expected a folder, a glob pattern or an image file)")
    return files


@calibrate_app.command("stereo")
def stereo(
    images_left: Annotated[str, typer.Argument(help="Left images: folder, quoted glob or file")],
    images_right: Annotated[str, typer.Argument(help="Right images: folder, quoted glob or file")],
    board: Annotated[str, typer.Option("--board", help="Inner corners WxH")] = "9x6",
    square_m: Annotated[float, typer.Option("--square-m", help="Square side (metres; 1 = board units)")] = 1.0,
    out: Annotated[Path, typer.Option("--out", "-o", help="Summary YAML (ROS/KITTI files, plot beside)")] = Path(
        "calib.yaml"
    ),
) -> None:
    """Calibrate a stereo rig from chessboard pairs: intrinsics, distortion, extrinsics, rectification."""
    from loopmodel.calib.chessboard import parse_board
    from loopmodel.calib.stereo import calibrate_stereo, pair_images, write_stereo_outputs

    pairs = pair_images(image_list(images_left, "left"), image_list(images_right, "right"))
    res = calibrate_stereo(pairs, parse_board(board), square_m)
    for r in res.rejected:
        err_console.print(f"rejected {r.path}: {r.reason}", highlight=False)
    table = Table("view", "left RMS (px)", "right RMS (px)")
    for v in res.views:
        table.add_row(Path(v.left_path).name, f"{v.rms_left_px:.3f}", f"{v.rms_right_px:.3f}")
    console.print(table)
    c = res.calibration
    console.print(
        f"{len(res.views)} views; RMS left {res.rms_left_px:.3f} px, right {res.rms_right_px:.3f} px, "
        f"stereo {res.rms_stereo_px:.3f} px (plain OpenCV on the same corners: {res.reference_rms_left_px:.3f} / "
        f"{res.reference_rms_right_px:.3f} / {res.reference_rms_stereo_px:.3f} px)"
    )
    console.print(
        f"baseline {c.baseline_m:.6g} (square = {square_m:g}); epipolar error after rectification "
        f"RMS {res.epipolar_err_px_rms:.3f} px, max {res.epipolar_err_px_max:.3f} px"
    )
    for p in write_stereo_outputs(res, out):
        console.print(f"wrote {p}")
