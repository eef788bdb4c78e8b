"""``loopmodel calibrate stereo|laser`` and ``loopmodel turntable scan|convert``: real rigs."""

from __future__ import annotations

import glob
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from loopmodel.cli.common import console, err_console
from loopmodel.display import MM, Formatter, key_values, num
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
    from loopmodel.calibration.chessboard import parse_board
    from loopmodel.calibration.stereo import calibrate_stereo, pair_images, write_stereo_outputs

    pairs = pair_images(image_list(images_left, "left"), image_list(images_right, "right"))
    res = calibrate_stereo(pairs, parse_board(board), square_m)
    for r in res.rejected:
        err_console.print(f"rejected {r.path}: {r.reason}", highlight=False)
    table = Table("view", "left RMS [px]", "right RMS [px]")
    for v in res.views:
        table.add_row(Path(v.left_path).name, num(v.rms_left_px), num(v.rms_right_px))
    console.print(table)
    c = res.calibration
    console.print(
        f"{len(res.views)} views; RMS left {res.rms_left_px:.3f} px, right {res.rms_right_px:.3f} px, "
        f"stereo {res.rms_stereo_px:.3f} px (plain OpenCV on the same corners: {res.reference_rms_left_px:.3f} / "
        f"{res.reference_rms_right_px:.3f} / {res.reference_rms_stereo_px:.3f} px)"
    )
    unit = "board squares" if square_m == 1.0 else "m"  # --square-m 1: lengths in squares
    console.print(
        f"baseline {num(c.baseline_m)} {unit} (square {num(square_m)} m); "
        f"{key_values({k: v for k, v in c.summary().items() if k.endswith('_px')})}; epipolar error after "
        f"rectification RMS {num(res.epipolar_err_px_rms)} px, max {num(res.epipolar_err_px_max)} px"
    )
    for p in write_stereo_outputs(res, out):
        console.print(f"wrote {p}")


@calibrate_app.command("laser")
def laser(
    images: Annotated[str, typer.Argument(help="Chessboard images with the laser line: folder, quoted glob or file")],
    intrinsics: Annotated[Path, typer.Option("--intrinsics", help="Camera YAML (ROS camera_info, OpenCV or ours)")],
    board: Annotated[str, typer.Option("--board", help="Inner corners WxH")] = "8x6",
    square_m: Annotated[float, typer.Option("--square-m", help="Square side (metres)")] = 0.04,
    out: Annotated[Path, typer.Option("--out", "-o", help="Plane YAML")] = Path("plane.yaml"),
    compare: Annotated[
        Path | None, typer.Option("--compare", help="laser_planes.json of candidate planes to compare with")
    ] = None,
    colour: Annotated[str, typer.Option("--colour", help="Laser colour: green, red or blue")] = "green",
) -> None:
    """Calibrate the laser light plane from chessboard images with the laser line on the board."""
    from loopmodel.calibration.chessboard import parse_board
    from loopmodel.calibration.laser import calibrate_laser_plane, plane_summary, read_laser_planes_json
    from loopmodel.io.atomic import write_text_atomic
    from loopmodel.io.camera_yaml import dump_yaml, read_intrinsics

    K, dist, size = read_intrinsics(intrinsics)
    files = image_list(images, "laser calibration")
    res = calibrate_laser_plane(files, K, dist, parse_board(board), square_m, size, colour)
    for p, why in res.rejected:
        err_console.print(f"rejected {p}: {why}", highlight=False)
    table = Table("image", "corners", "board RMS [px]", "distance [m]", "laser points")
    for v in res.views:
        table.add_row(
            Path(v.path).name + (" (partial)" if v.partial else ""),
            str(v.corners),
            num(v.board_rms_px),
            num(float((v.cam_from_board[:3, 3] ** 2).sum()) ** 0.5),
            str(len(v.points_in_cam_m)),
        )
    console.print(table)
    n = res.plane.normal_in_cam
    console.print(
        f"plane {n[0]:+.5f} x {n[1]:+.5f} y {n[2]:+.5f} z {res.plane.d_m:+.5f} = 0 (camera frame, m); "
        f"RMS residual {res.rms_mm:.3f} mm ({100 * res.inlier_fraction:.1f} % inliers); per-image lines: "
        f"direction spread {res.line_angle_spread_deg:.2f} deg, "
        f"max angle to the plane {res.line_to_plane_deg_max:.3f} deg"
    )
    comparison = None
    if compare is not None:
        comparison = res.compare(read_laser_planes_json(compare))
        ctab = Table("candidate", "RMS to our points [mm]", "normal angle [°]", "|d| difference [mm]")
        for c in comparison:
            ctab.add_row(str(c["name"]), num(c["rms_mm"]), num(c["normal_angle_deg"]), num(c["offset_diff_mm"]))
        console.print(ctab)
    write_text_atomic(out, dump_yaml(plane_summary(res, comparison)))
    console.print(f"wrote {out}")


turntable_app = typer.Typer(help="Real laser-line turntable scans.", no_args_is_help=True)


def _open(folder: Path, layout: Path | None, plane: list[Path] | None):  # type: ignore[no-untyped-def]
    from loopmodel.turntable.reader import open_turntable

    return open_turntable(folder, layout, list(plane or []))


@turntable_app.command("scan")
def turntable_scan(
    folder: Annotated[Path, typer.Argument(help="Turntable scan folder")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder")] = Path("turntable_out"),
    layout: Annotated[Path | None, typer.Option("--layout", help="Layout YAML (default FOLDER/turntable.yaml)")] = None,
    plane: Annotated[list[Path] | None, typer.Option("--plane", help="Extra candidate plane YAML/JSON")] = None,
) -> None:
    """Scan: table poses from the markers, loop-closed pose graph, laser points, mesh, report."""
    from loopmodel.cli.common import progress_bar
    from loopmodel.turntable.report import write_outputs
    from loopmodel.turntable.run import scan_turntable

    scan = _open(folder, layout, plane)
    with progress_bar() as bar:
        tasks: dict[str, Any] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done)

        res = scan_turntable(scan, progress=progress)
    f = res.figures
    table = Table("figure", "value")
    fmt = Formatter(MM)  # a turntable scan is close range
    for k in (
        "step_angle_err_deg_rms_before",
        "step_angle_err_deg_rms_after",
        "loop_closure_err_deg",
        "laser_plane",
        "table_plane_residual_mm",
        "mesh_points",
        "mesh_err_self_mm",
        "azimuth_coverage",
        "marker_angle_scatter_deg_rms",
    ):
        v = f[k]
        table.add_row(escape(fmt.header(k)), fmt.value(k, v) if not isinstance(v, str) else v)
    console.print(table)
    for name, c in f["plane_candidates"].items():
        console.print(
            f"plane {name}: table residual {num(c['table_residual_mm'])} mm (median {num(c['table_median_mm'])} mm)"
        )
    paths = write_outputs(res, scan.step_deg, out, str(folder))
    console.print(f"wrote {len(paths)} files to {out} (report: {out / 'report.md'})")


@turntable_app.command("convert")
def turntable_convert(
    folder: Annotated[Path, typer.Argument(help="Turntable scan folder")],
    dst: Annotated[Path, typer.Argument(help="Output .mcap")],
    layout: Annotated[Path | None, typer.Option("--layout", help="Layout YAML (default FOLDER/turntable.yaml)")] = None,
    poses: Annotated[bool, typer.Option("--poses/--no-poses", help="Also write the per-frame table pose")] = True,
) -> None:
    """Convert a turntable scan to MCAP (/laser/image, camera_info, per-frame pose)."""
    from loopmodel.turntable.convert import write_turntable_mcap
    from loopmodel.turntable.markers import calibrate_layout, detect_markers, make_detector, table_poses
    from loopmodel.turntable.posegraph import optimise_turntable

    scan = _open(folder, layout, None)
    T = None
    if poses:
        det = make_detector(scan.markers.dictionary)
        dets = [detect_markers(img, det, scan.markers.ids) for _, img in scan.frames()]
        lay, _ = calibrate_layout(dets, scan.markers, scan.K, scan.dist)
        tp = table_poses(dets, lay, scan.markers, scan.K, scan.dist)
        T = optimise_turntable(tp.cam_from_table, tp.covariance, scan.step_deg).cam_from_table
    write_turntable_mcap(scan, T, dst)
    console.print(f"wrote {dst} ({len(scan)} frames)")
