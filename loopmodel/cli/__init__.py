"""Command line of loopmodel (typer + rich). The only module that prints."""

from __future__ import annotations

import json
import logging
import math
import sys
import warnings
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from loopmodel import __version__
from loopmodel.cli.view import RerunConnectOption, RerunFileOption, RerunSpawnOption, rerun_listeners
from loopmodel.cli.view import view as view_results
from loopmodel.config import apply_overrides, dump_config, load_config
from loopmodel.errors import InputError, LoopmodelError

console = Console()
err_console = Console(stderr=True)

app = typer.Typer(
    name="loopmodel",
    help="Close-range 3-D modelling with a hand-held stereo camera and a laser-stripe profiler.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
config_app = typer.Typer(help="Configuration.", no_args_is_help=True)
app.add_typer(config_app, name="config")

ConfigOption = Annotated[Path | None, typer.Option("--config", "-c", help="YAML file overriding defaults")]
LeftTopicOption = Annotated[str | None, typer.Option("--left", help="Left image topic of a bag (default: guessed)")]
RightTopicOption = Annotated[str | None, typer.Option("--right", help="Right image topic of a bag (default: guessed)")]
CalibOption = Annotated[
    Path | None,
    typer.Option("--calib", help="Bag without CameraInfo: EuRoC sensor.yaml folder, camchain.yaml or calib.txt"),
]


def _version_callback(value: bool) -> None:
    if value:
        console.print(f"loopmodel {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_version_callback, is_eager=True, help="Print the version")
    ] = False,
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks and debug logging")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Info logging")] = False,
) -> None:
    level = logging.DEBUG if debug else logging.INFO if verbose else logging.WARNING
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


def progress_bar(*extra: Any) -> Progress:
    """The project's progress bar (frames done / total, rate, time left)."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        *extra,
        TimeRemainingColumn(),
        console=err_console,
        transient=False,
    )


def _length(v_m: float | None) -> str:
    """A length for people: millimetres below 10 cm (close-range scans), metres above."""
    if v_m is None or not math.isfinite(v_m):
        return "-"
    return f"{v_m * 1e3:.3g} mm" if abs(v_m) < 0.1 else f"{v_m:.4g} m"


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, dict):
        return ", ".join(f"{k}={_fmt(x)}" for k, x in v.items())
    if isinstance(v, list):
        return "x".join(str(x) for x in v) if all(isinstance(x, int) for x in v) else ", ".join(map(str, v))
    return str(v)


@app.command()
def info(
    path: Annotated[Path, typer.Argument(help="MCAP file, ROS 1/ROS 2 bag, EuRoC or KITTI folder")],
    config: ConfigOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table")] = False,
    left: LeftTopicOption = None,
    right: RightTopicOption = None,
    calib: CalibOption = None,
) -> None:
    """Describe a sequence: format, frames, duration, image size, calibration, ground truth, stripes;
    for a bag its image and camera_info topics with rates and sizes, and the stereo pair chosen."""
    from loopmodel.io.sequence import open_sequence

    cfg = load_config(config)
    desc = open_sequence(path, cfg.sequence, left, right, calib).describe()
    if as_json:
        console.print_json(json.dumps(desc))
        return
    table = Table(title=str(path), show_header=False)
    for k, v in desc.items():
        if k == "topics" and isinstance(v, dict):
            v = ", ".join(f"{t} [{d['type'].split('/')[-1]}: {d['messages']}]" for t, d in v.items())
        if k == "image_topics" and isinstance(v, dict):
            v = "; ".join(f"{t} " + ", ".join(f"{a} {_fmt(b)}" for a, b in d.items()) for t, d in v.items())
        table.add_row(k, _fmt(v))
    console.print(table)


@app.command()
def convert(
    src: Annotated[Path, typer.Argument(help="EuRoC or KITTI folder, MCAP file or ROS bag")],
    dst: Annotated[Path, typer.Argument(help="Output: .mcap, .bag (ROS 1) or a ROS 2 bag folder")],
    config: ConfigOption = None,
    image_format: Annotated[
        str,
        typer.Option("--image-format", help="raw, png, jpeg; bags also mono8, mono16, bgr8, rgb8, bgra8, bayer_rggb8"),
    ] = "png",
    to: Annotated[
        str | None, typer.Option("--to", help="mcap, ros2-sqlite3, ros2-mcap or ros1 (default: from the name)")
    ] = None,
    keep_topics: Annotated[bool, typer.Option("--keep-topics", help="Keep the source's topic names")] = False,
    left: LeftTopicOption = None,
    right: RightTopicOption = None,
    calib: CalibOption = None,
) -> None:
    """Convert a sequence to MCAP with ROS 2 messages (topics of DESIGN.md) or to a ROS bag."""
    from loopmodel.io.convert import OUTPUT_KINDS, convert_sequence, output_kind
    from loopmodel.io.rosbag_writer import ENCODINGS
    from loopmodel.io.sequence import open_sequence

    kind = output_kind(dst, to)
    if kind not in OUTPUT_KINDS:
        raise InputError("--to", f"must be one of {', '.join(OUTPUT_KINDS)}, got '{kind}'")
    if kind == "mcap" and dst.suffix.lower() != ".mcap":
        raise InputError(dst, "output must end in .mcap")
    if kind == "ros1" and dst.suffix.lower() != ".bag":
        raise InputError(dst, "a ROS 1 bag must end in .bag")
    allowed = ("raw", "png", "jpeg") if kind == "mcap" else ENCODINGS
    if image_format not in allowed:
        raise InputError("--image-format", f"must be one of {', '.join(allowed)} for {kind}, got '{image_format}'")
    if dst.exists() and kind != "mcap":
        raise InputError(dst, "exists already; choose a new name")
    from loopmodel.cli.signals import sigterm_as_interrupt
    from loopmodel.io.atomic import check_output_file

    if kind == "mcap":
        check_output_file(dst)  # before the work, not after it
    cfg = load_config(config)
    seq = open_sequence(src, cfg.sequence, left, right, calib)
    done = [0]

    def step(i: int) -> None:
        done[0] = i
        bar.update(task, completed=i)

    try:
        with sigterm_as_interrupt(), progress_bar() as bar:
            task = bar.add_task("convert", total=len(seq))
            convert_sequence(seq, dst, kind, cfg.sequence, image_format, keep_topics, progress=step)
    except KeyboardInterrupt:
        err_console.print(f"interrupted after {done[0]} frames; {dst} not written")
        raise typer.Exit(130) from None
    size = sum(p.stat().st_size for p in dst.rglob("*")) if dst.is_dir() else dst.stat().st_size
    console.print(f"wrote {dst} ({kind}, {size / 2**20:.1f} MiB, {len(seq)} frames)")


@app.command()
def run(
    path: Annotated[Path, typer.Argument(help="MCAP file, ROS 1/ROS 2 bag, EuRoC or KITTI folder")],
    config: ConfigOption = None,
    frontend_only: Annotated[bool, typer.Option("--frontend-only", help="Run only the visual front end")] = False,
    out: Annotated[Path | None, typer.Option("--out", help="Results root (default: output.out_dir)")] = None,
    name: Annotated[str | None, typer.Option("--name", help="Run name (folder under --out)")] = None,
    max_frames: Annotated[int | None, typer.Option("--max-frames", help="Stop after this many frames")] = None,
    left: LeftTopicOption = None,
    right: RightTopicOption = None,
    rerun: RerunFileOption = None,
    rerun_spawn: RerunSpawnOption = False,
    rerun_connect: RerunConnectOption = None,
    calib: CalibOption = None,
) -> None:
    """Process a sequence (front end, back end); writes config, trajectories, keyframes, map,
    metrics and log into <out>/<name>/. Ctrl-C or SIGTERM stops it after writing what it has."""
    from rich.progress import TextColumn as _Text

    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import run_frontend, run_pipeline

    if max_frames is not None and max_frames < 1:
        raise InputError("--max-frames", f"must be at least 1, got {max_frames}")
    cfg = load_config(config)
    seq = open_sequence(path, cfg.sequence, left, right, calib)
    if getattr(seq, "choice", None):
        console.print(f"{seq.format_name}: {seq.choice}")  # type: ignore[attr-defined]
    total = len(seq) if max_frames is None else min(len(seq), max_frames)
    if frontend_only:
        run_name = name or f"{path.stem}_frontend"
        with progress_bar(_Text("{task.fields[fps]:.1f} fps")) as bar:
            task = bar.add_task("front end", total=total, fps=0.0)
            result = run_frontend(
                seq,
                cfg,
                out,
                run_name,
                max_frames=max_frames,
                progress=lambda i, n, fps: bar.update(task, completed=i, fps=fps),
            )
        m = result.metrics
        console.print(
            f"wrote {result.folder}: {m['frames']} frames ({m['lost_frames']} lost), "
            f"{m['keyframes']} keyframes, {_fmt(m['fps'])} fps"
            + (f", ATE {m['ate_rmse_m']:.3f} m, drift {m['drift_pct']:.2f} %" if "ate_rmse_m" in m else "")
        )
        return
    run_name = name or path.stem
    folder = Path(out if out is not None else cfg.output.out_dir) / run_name
    with progress_bar(_Text("{task.fields[fps]:.1f} fps"), _Text("{task.fields[kf]} keyframes")) as bar:
        task = bar.add_task("run", total=total, fps=0.0, kf=0)
        try:
            result = run_pipeline(
                seq,
                cfg,
                out,
                run_name,
                max_frames=max_frames,
                progress=lambda i, n, fps, kf: bar.update(task, completed=i, fps=fps, kf=kf),
                listeners=rerun_listeners(seq.calibration, rerun, rerun_spawn, rerun_connect),
            )
        except KeyboardInterrupt:
            err_console.print(f"results up to the last processed frame are in {folder}")
            raise
    m = result.metrics
    table = Table(title=f"loopmodel run {path.name}", show_header=False)
    rows: list[tuple[str, Any]] = [
        ("frames", f"{m['frames']} ({m['lost_frames']} lost)"),
        ("keyframes", m["keyframes"]),
        ("landmarks", m["landmarks"]),
        ("fps", m["fps"]),
        ("back end", f"{m['backend']}, {_fmt(m['backend_ms_median'])} ms per keyframe (median)"),
    ]
    if "loop_closure_count" in m:
        rows.append(
            (
                "loops / relocalizations",
                f"{m['loop_closure_count']} / {m['relocalization_count']} "
                f"({m['loop_candidates_rejected']} candidates rejected)",
            )
        )
    if "ate_rmse_m" in m:
        rows.append(("ATE online / final", f"{_length(m['ate_rmse_m_online'])} / {_length(m['ate_rmse_m'])}"))
        rows.append(("drift final [%]", m["drift_pct"]))
    for k, v in rows:
        table.add_row(k, _fmt(v))
    console.print(table)
    console.print(f"results in {result.folder}")


@app.command()
def mesh(
    source: Annotated[
        Path, typer.Argument(help="Results folder (stripes.npz + trajectory) or a sequence with ground truth")
    ],
    fmt: Annotated[str, typer.Option("--format", "-f", help="ply (binary), obj, stl or glb")] = "ply",
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output file (default RESULTS_DIR/mesh.FMT)")] = None,
    trajectory: Annotated[str, typer.Option("--trajectory", help="final or online poses of a run")] = "final",
    gt_mesh: Annotated[
        Path | None,
        typer.Option("--gt-mesh", help="Ground-truth mesh (.ply, or .mcap with scene.ply): print accuracy"),
    ] = None,
    gt_attachment: Annotated[
        str, typer.Option("--gt-attachment", help="Attachment of an .mcap --gt-mesh (e.g. object.ply)")
    ] = "scene.ply",
    picture: Annotated[
        bool, typer.Option("--picture/--no-picture", help="Also write a PNG picture of the mesh beside it")
    ] = True,
    config: ConfigOption = None,
) -> None:
    """Mesh the laser stripes of a run with its trajectory (metres, world frame of the run)."""
    from loopmodel.io.mesh_io import MESH_FORMATS, read_mesh, write_mesh
    from loopmodel.io.stripes_io import load_stripes_and_poses
    from loopmodel.mapping.stripe_map import StripeMap

    fmt = fmt.lower()
    if fmt not in MESH_FORMATS:
        raise InputError(None, f"--format must be one of {', '.join(MESH_FORMATS)}, got '{fmt}'")
    cfg = load_config(config)
    stripes, traj, poses = load_stripes_and_poses(source, trajectory, cfg.sequence, cfg.mapping)
    smap = StripeMap.from_trajectory(traj, stripes, cfg.mapping)
    smap.check_nonempty()
    surface = smap.mesh()
    target = out or (source / f"mesh.{fmt}" if source.is_dir() else source.with_name(f"{source.stem}_mesh.{fmt}"))
    write_mesh(target, surface, fmt)
    console.print(
        f"wrote {target} ({len(surface.vertices)} vertices, {len(surface.triangles)} triangles, "
        f"{int(smap.placed_mask.sum())}/{smap.stripe_count} stripes, poses: {poses})"
    )
    truth = read_mesh(gt_mesh, gt_attachment) if gt_mesh is not None else None
    if truth is not None:
        from loopmodel.mapping.accuracy import mesh_accuracy

        acc = mesh_accuracy(surface, truth)
        console.print(
            f"accuracy: mean {acc.mean_mm:.3f} mm, p95 {acc.p95_mm:.3f} mm, "
            f"completeness {100 * acc.completeness:.1f} % within {acc.completeness_tol_mm:g} mm"
        )
    if picture:
        from loopmodel.io.atomic import write_bytes_atomic
        from loopmodel.viz.mesh_render import mesh_picture_png

        png = target.with_suffix(".png")
        write_bytes_atomic(png, mesh_picture_png(surface, target.name, truth))
        console.print(f"wrote {png} (the mesh from three viewpoints)")


simulate_app = typer.Typer(help="Synthetic data.", no_args_is_help=True)
app.add_typer(simulate_app, name="simulate")


@simulate_app.command("scan")
def simulate_scan_cmd(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output .mcap file")],
    preset: Annotated[str | None, typer.Option("--preset", help="orbit, sweeps, browse or modeler")] = None,
    realism: Annotated[
        str | None,
        typer.Option("--realism", help="clean or realistic (default: realistic with a preset, else the config's)"),
    ] = None,
    frames: Annotated[int | None, typer.Option("--frames", help="Number of frames")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Random seed")] = None,
    scene: Annotated[str | None, typer.Option("--scene", help="bust, box or mix")] = None,
    width: Annotated[int | None, typer.Option("--width", help="Image width (px)")] = None,
    height: Annotated[int | None, typer.Option("--height", help="Image height (px)")] = None,
    baseline: Annotated[float | None, typer.Option("--baseline", help="Stereo baseline (m)")] = None,
    rate: Annotated[float | None, typer.Option("--rate", help="Frame rate (Hz)")] = None,
    noise: Annotated[float | None, typer.Option("--noise", help="Image noise sigma (grey levels)")] = None,
    fault: Annotated[
        list[str] | None,
        typer.Option(
            "--fault",
            help="KIND:FIRST[-LAST], repeatable; KIND: dropped, blackout, blur, occluder, duplicate_timestamp",
        ),
    ] = None,
    laser_image: Annotated[
        bool | None, typer.Option("--laser-image/--no-laser-image", help="Also write /laser/image")
    ] = None,
    workers: Annotated[int | None, typer.Option("--workers", help="Render processes (0: one per core)")] = None,
    image_format: Annotated[str | None, typer.Option("--image-format", help="png, jpeg or raw")] = None,
    config: ConfigOption = None,
) -> None:
    """Generate a synthetic hand-held scan (stereo, laser stripes, ground truth) as MCAP."""
    from loopmodel.sim.generate import resolve_config, simulate_scan

    cfg = load_config(config)
    sim = resolve_config(
        cfg.simulation,
        preset,
        {
            "trajectory": {"frames": frames, "rate_hz": rate},
            "scene": {"kind": scene},
            "camera": {"width_px": width, "height_px": height, "baseline_m": baseline},
            "render": {"noise_sigma": noise},
            "laser": {"image": laser_image},
        },
        fault,
        realism,
    )
    updates: dict[str, Any] = {}
    if seed is not None:
        updates["seed"] = seed
    if workers is not None:
        updates["workers"] = workers
    if image_format is not None:
        updates["image_format"] = image_format
    if updates:
        sim = resolve_config(apply_overrides(sim, updates, {k: "--" + k.replace("_", "-") for k in updates}))
    from loopmodel.cli.signals import sigterm_as_interrupt

    done = [0]

    def step(k: int, n: int) -> None:
        done[0] = k
        bar.update(task, completed=k)

    try:
        with sigterm_as_interrupt(), progress_bar() as bar:
            task = bar.add_task("simulate", total=sim.trajectory.frames)
            res = simulate_scan(sim, out, cfg.sequence.topics, step, preset)
    except KeyboardInterrupt:
        err_console.print(f"interrupted after {done[0]} frames; {out} not written")
        raise typer.Exit(130) from None
    console.print(
        f"wrote {res.path} ({res.size_bytes / 2**20:.1f} MiB, {res.frames_written} frames, "
        f"{res.stripes_written} stripes, {len(res.faults)} faults) in {res.seconds:.1f} s: "
        f"{res.ms_per_frame:.1f} ms/frame (setup {res.setup_seconds:.1f} s, "
        f"render {res.render_ms_median:.1f} ms/frame per worker)"
    )


_MARKER_HELP = "triangle, t or a marker JSON file; repeat to compare (default: triangle and t)"
_NOISE_HELP = "N0/2 [contrast^2 px^2]: noise variance of a 1 px x 1 px cell (default 0.2)"


@app.command()
def bound(
    out: Annotated[Path, typer.Option("--out", help="Output folder")],
    marker: Annotated[list[str] | None, typer.Option("--marker", help=_MARKER_HELP)] = None,
    distance_m: Annotated[float | None, typer.Option("--distance-m", help="Distance R [m]")] = None,
    focal_mm: Annotated[float | None, typer.Option("--focal-mm", help="Focal length [mm]")] = None,
    noise: Annotated[float | None, typer.Option("--noise", help=_NOISE_HELP)] = None,
    pixel_um: Annotated[
        float | None, typer.Option("--pixel-um", help="Pixel pitch [um]: the image length unit")
    ] = None,
    pixel_study: Annotated[
        bool, typer.Option("--pixel-study/--no-pixel-study", help="Also the finite-pixel bound")
    ] = True,
    config: ConfigOption = None,
) -> None:
    """Cramér–Rao bound of camera position from a marker contour over the (θ, φ) grid (seed 001)."""
    import time

    import numpy as np

    from loopmodel.accuracy.fisher import bound_grid
    from loopmodel.accuracy.marker import load_marker
    from loopmodel.accuracy.report import (
        pixel_study as run_pixel_study,
    )
    from loopmodel.accuracy.report import (
        plot_pixel_study,
        summary_markdown,
        write_grid_outputs,
        write_summary,
    )
    from loopmodel.io.atomic import write_text_atomic

    cfg = load_config(config)
    given = {"distance_m": distance_m, "focal_mm": focal_mm, "noise": noise, "pixel_um": pixel_um}
    for key, val in given.items():
        if val is not None and not val > 0:
            raise InputError(None, f"--{key.replace('_', '-')} must be > 0, got {val}")
    acc = apply_overrides(cfg.accuracy, given, {k: "--" + k.replace("_", "-") for k in given})
    cfg = apply_overrides(cfg, {"accuracy": acc.model_dump()})
    markers = [load_marker(m) for m in (marker or ["triangle", "t"])]
    if len({m.name for m in markers}) != len(markers):
        raise InputError(None, "two markers share a name; give each JSON file a distinct 'name'")
    t0 = time.perf_counter()
    grids = [
        bound_grid(
            m,
            acc.distance_m,
            acc.focal_mm,
            acc.noise,
            acc.pixel_um,
            acc.theta_deg,
            acc.phi_deg,
            acc.edge_subdivisions,
            acc.circle_points,
        )
        for m in markers
    ]
    grid_ms = (time.perf_counter() - t0) * 1e3
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "config.yaml", dump_config(cfg))
    for g in grids:
        write_grid_outputs(g, out)
    studies = {}
    if pixel_study:
        with progress_bar() as bar:
            task = bar.add_task("pixel-size study", total=len(markers))
            for m, g in zip(markers, grids, strict=True):
                studies[m.name] = run_pixel_study(m, g, acc.pixel_study_px)
                bar.advance(task)
        plot_pixel_study(studies, acc.pixel_um, out / "pixel_size.png")
    write_summary(summary_markdown(grids, studies, grid_ms), out)
    table = Table(title=f"CRLB over {len(acc.theta_deg)}x{len(acc.phi_deg)} grid (median)")
    for col in ("marker", "σ_r [m]", "σ_v [m]", "σ_u [m]", "σ_γ [deg]"):
        table.add_column(col)
    for g in grids:
        med = np.median(g.bound.sigma, axis=(0, 1))
        table.add_row(g.marker, *(f"{float(x):.4g}" for x in med))
    console.print(table)
    console.print(f"wrote {out} (grid in {grid_ms:.1f} ms)")


@app.command("givens-sim")
def givens_sim(
    frames: Annotated[int, typer.Option(help="frames along the two strips")] = 88,
    points: Annotated[int, typer.Option(help="object points of the test field")] = 166,
    blunders: Annotated[float, typer.Option(help="fraction of image points with a blunder")] = 0.02,
    seed: Annotated[int, typer.Option(help="random seed")] = 0,
    config: ConfigOption = None,
) -> None:
    """Sequential Givens bundle with data snooping on the synthetic OLTRIS-size test field."""
    from loopmodel.backend.givens_bundle import GivensScreen
    from loopmodel.backend.testfield import make_testfield

    if frames < 2 or points < 5:
        raise InputError(None, "--frames must be >= 2 and --points >= 5")
    if not 0.0 <= blunders < 1.0:
        raise InputError(None, f"--blunders must be in [0, 1), got {blunders}")
    cfg = load_config(config).givens
    tf = make_testfield(n_frames=frames, n_points=points, blunder_fraction=blunders, seed=seed)
    scr = GivensScreen.from_config(tf.camera, apply_overrides(cfg, {"sigma_px": tf.sigma_px}))
    ctrl = set(tf.control.tolist())
    flagged: set[tuple[int, int]] = set()
    truth: set[tuple[int, int]] = set()
    with progress_bar() as bar:
        task = bar.add_task("frames", total=frames)
        for f, (ids, uv) in enumerate(tf.observations):
            for i in ids.tolist():
                if i not in scr.bundle.points:
                    scr.add_point(i, tf.points_world[i], 1e-4 if i in ctrl else None)
            mask = scr.screen(f, tf.world_from_cam[f], ids.tolist(), uv, first_frame=(f == 0))
            truth |= {(f, i) for i, b in zip(ids.tolist(), tf.blunder[f], strict=True) if b}
            flagged |= {(f, i) for i, ok in zip(ids.tolist(), mask, strict=True) if not ok}
            flagged |= {(int(a), int(b)) for a, b in scr.late_rejections()}  # type: ignore[call-overload]
            bar.update(task, completed=f + 1)
    est = scr.bundle.est
    table = Table(title="sequential Givens bundle")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for k, v in (
        ("unknowns", est.n_parameters),
        ("observation rows", est.n_observations),
        ("sigma0 (a posteriori)", f"{est.variance_factor() ** 0.5:.3f}"),
        ("tested / rejected", f"{scr.stats.tested} / {scr.stats.rejected}"),
        ("blunders injected / caught", f"{len(truth)} / {len(truth & flagged)}"),
        ("false alarms", len(flagged - truth)),
        ("kernels", __import__("loopmodel.backend.givens", fromlist=["KERNELS"]).KERNELS),
    ):
        table.add_row(k, str(v))
    console.print(table)


@config_app.command("dump")
def config_dump(config: ConfigOption = None) -> None:
    """Print the effective configuration (defaults overridden by --config) as YAML."""
    sys.stdout.write(dump_config(load_config(config)))


depth_app = typer.Typer(
    help="Lyapunov-based adaptive depth estimation from one moving camera (seed 003).", no_args_is_help=True
)
app.add_typer(depth_app, name="depth")


@depth_app.command("simulate")
def depth_simulate(
    out: Annotated[Path, typer.Option("--out", help="Output folder")] = Path("results/depth_sim"),
    duration_s: Annotated[float, typer.Option("--duration-s", min=0.1)] = 10.0,
    rate_hz: Annotated[float, typer.Option("--rate-hz", min=1.0, help="measurement rate")] = 1000.0,
    seed: Annotated[int, typer.Option("--seed")] = 3,
) -> None:
    """The seed's simulation: 12 features, v_cam = (cos t, -sin t, 0.1 sin t) m/s; plots + CSV."""
    import numpy as np

    from loopmodel.io.atomic import save_figure_atomic, write_text_atomic
    from loopmodel.observers.plots import convergence_figures
    from loopmodel.observers.simulation import simulate

    res = simulate(duration_s, rate_hz, seed=seed)
    f1, f2 = convergence_figures(res)
    save_figure_atomic(out / "lambda_convergence.png", f1)
    save_figure_atomic(out / "depth_error.png", f2)
    n = res.lambda_hat.shape[1]
    header = (
        "t_s," + ",".join(f"lambda_hat_{i}" for i in range(n)) + "," + ",".join(f"lambda_true_{i}" for i in range(n))
    )
    rows = [
        ",".join(repr(float(x)) for x in [t, *lam, *res.lambda_true])
        for t, lam in zip(res.t_s, res.lambda_hat, strict=True)
    ]
    write_text_atomic(out / "lambda.csv", header + "\n" + "\n".join(rows) + "\n")
    conv = res.converge_time_s(0.05)
    console.print(
        f"converged to 5 % after {conv:.2f} s; final relative error max {res.rel_err[-1].max():.4f}, "
        f"median {float(np.median(res.rel_err[-1])):.4f}; excitation {'ok' if res.observer.excited else 'MISSING'}"
    )
    console.print(f"results in {out}")


@depth_app.command("track")
def depth_track(
    seq_path: Annotated[Path, typer.Argument(help="Rectified stereo sequence (KITTI, MCAP)")],
    out: Annotated[Path, typer.Option("--out", help="Output folder")] = Path("results/depth_track"),
    window: Annotated[int, typer.Option("--window", min=3, help="frames per reference view")] = 6,
    stride: Annotated[int, typer.Option("--stride", min=3, help="frames between reference views")] = 10,
    config: ConfigOption = None,
) -> None:
    """Observer depths of KLT-tracked left-camera features vs stereo depths; scale from one stereo depth."""
    import numpy as np

    from loopmodel.io.atomic import save_figure_atomic, write_text_atomic
    from loopmodel.io.sequence import open_sequence
    from loopmodel.observers.plots import stereo_comparison_figure
    from loopmodel.observers.real_tracks import observe_sequence

    cfg = load_config(config)
    seq = open_sequence(seq_path, cfg.sequence)
    results, skipped = observe_sequence(seq.frames(), seq.calibration, window, stride)
    for s in skipped:
        err_console.print(f"skipped window at {s}")
    if not results:
        raise InputError(seq_path, "no window had enough tracked features")
    rows = ["ref_frame,feature,depth_observer_m,depth_stereo_m"]
    for r in results:
        rows += [
            f"{r.start_index},{i},{a!r},{b!r}"
            for i, (a, b) in enumerate(zip(r.depth_observer_m, r.depth_stereo_m, strict=True))
        ]
    write_text_atomic(out / "depths.csv", "\n".join(rows) + "\n")
    save_figure_atomic(out / "observer_vs_stereo.png", stereo_comparison_figure(results))
    errs = np.concatenate([r.rel_err for r in results])
    console.print(
        f"{len(results)} windows, {errs.size} features: median relative depth error {float(np.median(errs)):.3f}"
    )
    console.print(f"results in {out}")


@app.command("eval")
def eval_command(
    runs: Annotated[list[Path] | None, typer.Argument(help="Results folders")] = None,
    gt: Annotated[Path | None, typer.Option("--gt", help="Ground truth file or sequence")] = None,
    ref: Annotated[Path | None, typer.Option("--ref", help="Reference trajectory")] = None,
    est: Annotated[Path | None, typer.Option("--est", help="Estimated trajectory")] = None,
    align: Annotated[str | None, typer.Option("--align", help="se3, sim3, origin, none")] = None,
    first_n: Annotated[int | None, typer.Option("--first-n", help="Align on N poses")] = None,
    max_dt_ms: Annotated[float | None, typer.Option("--max-dt-ms", help="Max time gap")] = None,
    rpe_delta_m: Annotated[float | None, typer.Option("--rpe-delta-m", help="RPE metres")] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder")] = None,
    no_plots: Annotated[bool, typer.Option("--no-plots", help="Skip the pictures")] = False,
    config: ConfigOption = None,
) -> None:
    """Evaluate trajectories against ground truth: ATE, RPE, drift, loop-closure effect, report."""
    from loopmodel.eval import report as rep

    cfg = load_config(config)
    overrides = {"align": align, "first_n": first_n, "max_dt_ms": max_dt_ms, "rpe_delta_m": rpe_delta_m}
    ecfg = apply_overrides(cfg.eval, overrides, {k: "--" + k.replace("_", "-") for k in overrides})
    if no_plots:
        ecfg.plots = False
    runs = list(runs or [])
    if (ref is None) != (est is None):
        raise InputError("--ref/--est", "give both --ref and --est")
    if ref is not None and (runs or gt is not None):
        raise InputError("--ref/--est", "use --ref/--est or results folders with --gt, not both")
    if ref is None and not runs:
        raise InputError(None, "nothing to evaluate: give results folders or --ref FILE --est FILE")
    evals = []
    if ref is not None and est is not None:
        g = rep.load_ground_truth(ref, cfg.sequence)
        e = rep.load_trajectory_file(est, cfg.sequence.kitti_rate_hz)
        ev = rep.evaluate_run(rep.plain_run(e), g, ecfg)
        target = out or Path("eval_" + est.stem)
        rep.write_outputs(ev, target)
        evals.append((ev, target))
    else:
        for run_path in runs:
            run = rep.load_run(run_path, cfg.sequence.kitti_rate_hz)
            gt_path = gt or rep.ground_truth_hint(run)
            if gt_path is None:
                raise InputError(run_path, "no ground truth: pass --gt FILE|SEQUENCE")
            g = rep.load_ground_truth(gt_path, cfg.sequence)
            ev = rep.evaluate_run(run, g, ecfg)
            if out is None:
                target = run_path / "eval"
            else:
                target = out / run.name if len(runs) > 1 else out
            rep.write_outputs(ev, target)
            evals.append((ev, target))
    table = Table(title="loopmodel eval")
    cols = ("run", "matched", "ATE final", "ATE online", "RPE/frame", "closures")
    for col in (*cols, "report"):
        table.add_column(col)
    for ev, target in evals:
        m = ev.metrics
        tr = m["trajectories"]
        online = tr.get("online", {}).get("ate_m", {}).get("rmse")
        table.add_row(
            m["run"],
            str(tr["final"]["matched"]),
            _length(m["ate_rmse_m"]),
            _length(online),
            _length(tr["final"].get("rpe_frames", {}).get("trans_m", {}).get("rmse")),
            str(m["loop_closure_count"]),
            str(target / "report.md"),
        )
    console.print(table)
    if len(evals) > 1:
        cmp_dir = out or Path("eval_comparison")
        csv_path, md_path = rep.write_comparison([e for e, _ in evals], cmp_dir)
        console.print(f"comparison: {csv_path} {md_path}")


loop_app = typer.Typer(help="Place recognition, relocalization and loop detection.", no_args_is_help=True)
app.add_typer(loop_app, name="loop")


def _image_files(folder: Path) -> list[Path]:
    import re

    if not folder.is_dir():
        raise InputError(folder, "is not a folder of images")
    files = [p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".pgm")]
    if not files:
        raise InputError(folder, "holds no .png/.jpg/.bmp/.pgm image")

    def key(p: Path) -> tuple[int, str]:
        m = re.search(r"(\d+)", p.stem)
        return (int(m.group(1)) if m else -1, p.name)

    return sorted(files, key=key)


@loop_app.command("detect")
def loop_detect(
    folder: Annotated[Path, typer.Argument(help="Folder of images in time order (numbered names)")],
    out: Annotated[Path | None, typer.Option("--out", help="CSV of accepted loops")] = None,
    vocabulary: Annotated[Path | None, typer.Option("--vocabulary", help="trained vocabulary .npz")] = None,
    config: ConfigOption = None,
) -> None:
    """Loop detection on an image sequence (monocular: fundamental-matrix verification)."""
    import cv2

    from loopmodel.io.atomic import write_text_atomic
    from loopmodel.loop.closure import detector_from_config
    from loopmodel.loop.features import detect_and_describe, make_extractor

    cfg = load_config(config).loop
    if vocabulary is not None:
        cfg = apply_overrides(cfg, {"vocabulary_path": str(vocabulary)}, {"vocabulary_path": "--vocabulary"})
    files = _image_files(folder)
    ex = make_extractor(cfg.descriptor, cfg.n_features)
    det = None
    rows = ["query_index,query_file,match_index,match_file,inliers"]
    with progress_bar() as bar:
        task = bar.add_task("images", total=len(files))
        for i, f in enumerate(files):
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise InputError(f, "cannot be read as an image")
            if det is None:
                det = detector_from_config(cfg, None, image_width_px=float(img.shape[1]))
            ev = det.process(i, detect_and_describe(img, cfg.descriptor, cfg.n_features, ex))
            if ev is not None:
                rows.append(f"{i},{f.name},{ev.match_id},{files[ev.match_id].name},{ev.n_inliers}")
            bar.advance(task)
    assert det is not None
    for r in rows[1:]:
        q, qf, m, mf, n = r.split(",")
        console.print(f"loop: {qf} -> {mf} ({n} inliers)")
    console.print(f"{len(rows) - 1} loops accepted, {len(det.rejected)} candidates rejected")
    if out is not None:
        write_text_atomic(out, "\n".join(rows) + "\n")
        console.print(f"loops written to {out}")


@loop_app.command("vocabulary")
def loop_vocabulary(
    folder: Annotated[Path, typer.Argument(help="Folder of training images")],
    out: Annotated[Path, typer.Argument(help="Output vocabulary (.npz)")],
    source: Annotated[str, typer.Option("--source", help="what the images are (kept in the file)")] = "",
    seed: Annotated[int, typer.Option("--seed", help="random seed of the clustering")] = 0,
    config: ConfigOption = None,
) -> None:
    """Train a vocabulary tree (k-majority for ORB, k-means for SIFT/SURF) on a folder of
    images, for ``loop.descriptor`` with ``loop.n_features`` per image (reproducible)."""
    from collections.abc import Iterator

    import cv2

    from loopmodel.loop.vocabulary import train_from_images

    cfg = load_config(config).loop
    files = _image_files(folder)

    def images() -> Iterator[Any]:
        for f in files:
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise InputError(f, "cannot be read as an image")
            yield img

    voc = train_from_images(
        images(),
        cfg.descriptor,
        cfg.n_features,
        cfg.vocabulary_branching,
        cfg.vocabulary_levels,
        seed,
        source=source or folder.name,
    )
    voc.save(out)
    console.print(f"{voc.n_words} {cfg.descriptor} words from {voc.info['images']} images written to {out}")


_PROGRAM = [False]


def _ignore_further_interrupts() -> None:
    """Once a command was interrupted, another Ctrl-C must not break the exit (worker pools
    and temporary files are being cleaned up). Only for the program itself (``_PROGRAM``),
    not for ``main`` called from Python."""
    import signal
    import threading

    if _PROGRAM[0] and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def main(argv: list[str] | None = None) -> int:
    """Entry point: runs the app, turns loopmodel errors into one line and exit status 2."""
    args = list(sys.argv[1:] if argv is None else argv)
    _PROGRAM[0] = argv is None
    debug = "--debug" in args
    if not debug:  # numeric warnings are for developers; the results say what went wrong
        warnings.filterwarnings("ignore", category=RuntimeWarning)
    from loopmodel.cli.signals import sigterm_as_interrupt

    try:
        with sigterm_as_interrupt():  # SIGTERM is Ctrl-C everywhere (temporary files removed)
            rv = app(args=args, prog_name="loopmodel", standalone_mode=False)
        # typer turns KeyboardInterrupt into Exit(130) and, outside standalone mode, returns
        # the code instead of raising it
        if isinstance(rv, int) and rv != 0:
            if rv == 130:
                _ignore_further_interrupts()
                err_console.print("interrupted")
            return rv
    except LoopmodelError as exc:
        if debug:
            raise
        err_console.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        return 2
    except typer.Exit as exc:
        if exc.exit_code == 130:
            _ignore_further_interrupts()
        return int(exc.exit_code)
    except (typer.Abort, KeyboardInterrupt):
        _ignore_further_interrupts()
        err_console.print("interrupted")
        return 130
    except typer.exceptions.TyperException as exc:  # usage errors (click's, vendored by typer)
        show = getattr(exc, "show", None)
        if callable(show):
            show()
        else:
            err_console.print(f"error: {exc}")
        return int(getattr(exc, "exit_code", 2))
    except OSError as exc:  # the environment (full disk, read-only folder): one line naming the path
        if debug:
            raise
        where = f"{exc.filename}: " if exc.filename else ""
        err_console.print(f"[red]I/O error:[/red] {where}{exc.strerror or exc}", highlight=False, soft_wrap=True)
        return 1
    except Exception as exc:  # a bug, not bad input: say so in one line unless --debug
        if debug:
            raise
        err_console.print(
            f"[red]internal error:[/red] {type(exc).__name__}: {exc} (rerun with --debug for the traceback)",
            highlight=False,
        )
        return 1
    return 0




vvs_app = typer.Typer(help="Virtual visual servoing for N-camera central rigs (seed 002).", no_args_is_help=True)
app.add_typer(vvs_app, name="vvs")


@vvs_app.command("simulate")
def vvs_simulate(
    out: Annotated[Path, typer.Option("--out", help="Output folder")] = Path("results/vvs_sim"),
    mirrors: Annotated[list[int] | None, typer.Option("--mirrors", help="4 and/or 2 (repeatable)")] = None,
    frames: Annotated[int, typer.Option("--frames", min=2, help="sequence length")] = 312,
    seed: Annotated[int, typer.Option("--seed")] = 0,
    config: ConfigOption = None,
) -> None:
    """Track the hand-held box with the simulated 4-mirror sensor (or its 2 diagonal mirrors):
    per-frame pose errors as CSV and PNG."""
    import numpy as np

    from loopmodel.io.atomic import save_figure_atomic, write_text_atomic
    from loopmodel.pose.tracking import TrackerOptions
    from loopmodel.pose.vvs import VvsOptions
    from loopmodel.sim.omni import simulate_tracking, tracking_csv, tracking_figure

    cfg = load_config(config).vvs
    counts = mirrors or [4]
    for m in counts:
        if m not in (2, 4):
            raise InputError("--mirrors", f"{m}: use 4 (all mirrors) or 2 (the diagonal pair 1 and 4)")
    opt = TrackerOptions(
        sample_step_px=cfg.sample_step_px,
        min_features=cfg.min_features,
        vvs=VvsOptions(loss=cfg.loss, huber_warmup=cfg.huber_warmup, max_iterations=cfg.max_iterations),  # type: ignore[arg-type]
    )
    runs = []
    for m in counts:
        sel = (0, 1, 2, 3) if m == 4 else (0, 3)
        with progress_bar() as bar:
            task = bar.add_task(f"{m} mirrors", total=frames)
            run = simulate_tracking(
                sel,
                frames,
                seed,
                cfg.lost_rot_deg,
                cfg.lost_pos_mm,
                opt,
                cfg.search_px,
                cfg.edge_noise_px,
                progress=lambda _k, bar=bar, task=task: bar.advance(task),  # type: ignore[misc]
            )
        runs.append(run)
        first = np.flatnonzero(run.lost)
        console.print(
            f"{m} mirrors: median rotation error {float(np.median(run.rot_err_deg)):.3f} deg, "
            f"position {float(np.median(run.pos_err_mm)):.2f} mm, lost frames {int(run.lost.sum())}"
            + (f" (first {int(first[0])})" if first.size else "")
            + f", VVS iteration {float(np.nanmedian(run.iter_ms)):.2f} ms"
        )
    write_text_atomic(out / "pose_errors.csv", tracking_csv(runs))
    save_figure_atomic(out / "pose_errors.png", tracking_figure(runs))
    console.print(f"results in {out}")


@vvs_app.command("calibrate")
def vvs_calibrate(
    out: Annotated[Path, typer.Option("--out", help="Output folder")] = Path("results/vvs_calib"),
    points: Annotated[Path | None, typer.Option("--points", help="npz: p_in_ref, uv_px, cam_index, view_index")] = None,
    views: Annotated[int, typer.Option("--views", min=2, help="simulated views (without --points)")] = 8,
    noise_px: Annotated[float, typer.Option("--noise-px", min=0.0, help="simulated image noise")] = 0.3,
    seed: Annotated[int, typer.Option("--seed")] = 0,
) -> None:
    """Calibrate the 4-mirror rig (intrinsics of every mirror and jM1) from known 3-D points
    (eq. 16), starting from the nominal sensor design; writes rig.json."""
    import numpy as np

    from loopmodel.errors import CalibrationError
    from loopmodel.geometry.se3 import se3_log
    from loopmodel.io.atomic import write_text_atomic
    from loopmodel.pose import PointTerm, estimate_pose
    from loopmodel.pose.calibration import CalibrationView, calibrate_rig
    from loopmodel.sim.omni import calibration_views, manufactured_rig, omni_sensor

    sensor = omni_sensor()
    truth = None
    if points is not None:
        try:
            data = np.load(points)
            arrays = [np.asarray(data[k]) for k in ("p_in_ref", "uv_px", "cam_index", "view_index")]
        except (OSError, KeyError, ValueError) as exc:
            raise InputError(points, f"cannot read calibration points: {exc}") from exc
        P, uv, ci, vi = arrays
        if P.ndim != 2 or P.shape[1] != 3 or uv.shape != (len(P), 2) or ci.shape != (len(P),) or vi.shape != (len(P),):
            raise InputError(points, "expected p_in_ref (N,3), uv_px (N,2), cam_index (N,), view_index (N,)")
        if ci.min() < 0 or ci.max() > 3:
            raise InputError(points, "cam_index must be 0..3 (mirror)")
        obs = [(P[vi == v], uv[vi == v], ci[vi == v].astype(np.int64)) for v in np.unique(vi)]
        nominal = sensor.rig()
    else:
        # the sensor as built differs from its design; calibration starts from the design
        truth = manufactured_rig(sensor, seed)
        obs, _truth_poses = calibration_views(sensor, views, noise_px, seed, rig=truth)
        nominal = sensor.rig()
    starts = []
    for k, (P, uv, ci) in enumerate(obs):
        try:
            starts.append(estimate_pose(PointTerm(nominal, P, uv, ci), ransac_threshold_px=8.0).rig_from_ref)
        except LoopmodelError as exc:
            raise CalibrationError(points or "simulated views", f"view {k}: no initial pose ({exc})") from exc
    cal = calibrate_rig([CalibrationView(*o) for o in obs], nominal, starts)
    rig_json = {
        "cameras": [{"px": c.px, "py": c.py, "u0": c.u0, "v0": c.v0, "xi": c.xi} for c in cal.rig.cameras],
        "cam_from_rig": [T.tolist() for T in cal.rig.cam_from_rig],
        "rms_px": cal.rms_px,
        "iterations": cal.iterations,
    }
    write_text_atomic(out / "rig.json", json.dumps(rig_json, indent=2) + "\n")
    console.print(f"{len(obs)} views, RMS reprojection error {cal.rms_px:.3f} px after {cal.iterations} iterations")
    if truth is not None:
        table = Table("mirror", "d px", "d py", "d u0", "d v0", "d xi", "jM1 trans err (mm)", "jM1 rot err (deg)")
        for j, (c, t) in enumerate(zip(cal.rig.cameras, truth.cameras, strict=True)):
            e = se3_log(cal.rig.cam_from_rig[j] @ np.linalg.inv(truth.cam_from_rig[j]))
            table.add_row(
                str(j + 1),
                f"{c.px - t.px:+.3f}",
                f"{c.py - t.py:+.3f}",
                f"{c.u0 - t.u0:+.3f}",
                f"{c.v0 - t.v0:+.3f}",
                f"{c.xi - t.xi:+.5f}",
                f"{1e3 * np.linalg.norm(e[:3]):.3f}",
                f"{np.degrees(np.linalg.norm(e[3:])):.4f}",
            )
        console.print(table)
    console.print(f"results in {out}")


app.command("view")(view_results)

from loopmodel.cli.calibrate import calibrate_app, turntable_app  # noqa: E402

app.add_typer(calibrate_app, name="calibrate")
app.add_typer(turntable_app, name="turntable")

from loopmodel.cli.batch import batch_app  # noqa: E402

app.add_typer(batch_app, name="batch")

from loopmodel.cli.vvs_images import vvs_render, vvs_track  # noqa: E402

vvs_app.command("render")(vvs_render)
vvs_app.command("track")(vvs_track)

if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
