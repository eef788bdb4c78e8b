"""Commands on sequences: ``info``, ``convert``, ``run``, ``mesh``, ``simulate scan``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import typer
from rich.markup import escape
from rich.progress import TimeElapsedColumn
from rich.table import Table

from loopmodel.cli.common import (
    CalibOption,
    ConfigOption,
    LeftTopicOption,
    RightTopicOption,
    app,
    console,
    err_console,
    progress_bar,
)
from loopmodel.cli.summary import frontend_summary, run_summary_rows
from loopmodel.cli.view import RerunConnectOption, RerunFileOption, RerunSpawnOption, rerun_listeners
from loopmodel.config import Config, apply_overrides, load_config
from loopmodel.display import Formatter, describe_rows, key_values, num
from loopmodel.errors import InputError, LoopmodelError

if TYPE_CHECKING:
    from loopmodel.loop.session_map import SessionMap
    from loopmodel.result import RunResult


@app.command()
def info(
    path: Annotated[Path, typer.Argument(help="MCAP file, ROS 1/ROS 2 bag, EuRoC or KITTI folder")],
    config: ConfigOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table")] = False,
    left: LeftTopicOption = None,
    right: RightTopicOption = None,
    calib: CalibOption = None,
) -> None:
    """Describe a sequence: format, frames, duration, image size, calibration, ground truth, stripes.

    For a bag its image and camera_info topics with rates and sizes, and the stereo pair chosen.
    """
    from loopmodel.io.rosbag_io import NoImageTopicsError, describe_recording
    from loopmodel.io.sequence import open_sequence

    cfg = load_config(config)
    fmt = Formatter()
    try:
        seq = open_sequence(path, cfg.sequence, left, right, calib)
        desc = seq.describe()
        if seq.ground_truth is not None and len(seq.ground_truth):  # mm for a close-range scan (issue 35)
            fmt = Formatter.for_positions(seq.ground_truth.world_from_cam[:, :3, 3])
    except NoImageTopicsError:  # not a sequence to run, still a recording to describe (as ros2 bag info)
        desc = describe_recording(path)
    if as_json:
        console.print_json(json.dumps(desc))
        return
    table = Table(title=str(path), show_header=False)
    for k, v in desc.items():
        if k == "topics" and isinstance(v, dict):
            desc[k] = ", ".join(f"{t} ({_topic_text(d)})" for t, d in v.items())
        if k == "image_topics" and isinstance(v, dict):
            desc[k] = "; ".join(f"{t}: {key_values(d, fmt)}" for t, d in v.items())
        if isinstance(v, list) and v and all(isinstance(x, str) for x in v):
            desc[k] = ", ".join(v)
    if desc.get("laser_images") and not desc.get("stripes"):
        desc.pop("stripes", None)  # measured from the laser images by the run: "stripes 0" would mislead
    if not desc.get("laser_images"):
        desc.pop("laser_images", None)
    for k, text in describe_rows(desc, fmt):
        table.add_row(escape(k), escape(text))
    console.print(table)


def _topic_text(d: dict[str, Any]) -> str:
    """``PoseStamped: 120 messages, 10.00 Hz`` of a topic row."""
    text = f"{str(d['type']).split('/')[-1]}: {d['messages']}"
    return text + (f", {num(d['rate_hz'])} Hz" if d.get("rate_hz") else "")


OverwriteOption = Annotated[
    bool, typer.Option("--overwrite", help="Replace an existing output (only once the new one is complete)")
]


@app.command()
def convert(
    src: Annotated[Path, typer.Argument(help="EuRoC or KITTI folder, MCAP file or ROS bag")],
    dst: Annotated[Path, typer.Argument(help="Output: .mcap, .bag (ROS 1) or a ROS 2 bag folder")],
    config: ConfigOption = None,
    image_format: Annotated[
        Literal["raw", "png", "jpeg", "mono8", "mono16", "bgr8", "rgb8", "bgra8", "bayer_rggb8"] | None,
        typer.Option(
            "--image-format",
            help="Image encoding (default: raw sensor_msgs/Image in bags, png in MCAP); png and jpeg go to "
            "<image topic>/compressed in bags; mono8 ... bayer_rggb8 only in bags",
        ),
    ] = None,
    epoch: Annotated[
        str | None,
        typer.Option(
            "--epoch",
            help="Bags: add this date (ISO 8601 UTC, or seconds) to every stamp, for sources with relative "
            "times such as KITTI (else ROS tools read them as 1970)",
        ),
    ] = None,
    to: Annotated[
        Literal["mcap", "ros2-sqlite3", "ros2-mcap", "ros1"] | None,
        typer.Option("--to", help="Output kind (default: from the name)"),
    ] = None,
    keep_topics: Annotated[bool, typer.Option("--keep-topics", help="Keep the source's topic names")] = False,
    left: LeftTopicOption = None,
    right: RightTopicOption = None,
    calib: CalibOption = None,
    overwrite: OverwriteOption = False,
) -> None:
    """Convert a sequence to MCAP with ROS 2 messages or to a ROS 1/ROS 2 bag (topics: README, Input formats)."""
    from loopmodel.io.convert import OUTPUT_KINDS, convert_sequence, output_kind, parse_epoch_ns, relative_times
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
    if image_format is not None and image_format not in allowed:
        raise InputError("--image-format", f"must be one of {', '.join(allowed)} for {kind}, got '{image_format}'")
    if dst.exists() and not overwrite:
        raise InputError(dst, "exists already; choose a new name or pass --overwrite")
    from loopmodel.cli.signals import caused_by_interrupt, sigterm_as_interrupt
    from loopmodel.io.atomic import check_output_file

    if kind == "mcap":
        check_output_file(dst)  # before the work, not after it
    epoch_ns = None
    if epoch is not None:
        if kind == "mcap":
            raise InputError("--epoch", "applies to bags only (the project's MCAP keeps the source's stamps)")
        try:
            epoch_ns = parse_epoch_ns(epoch)
        except ValueError:
            raise InputError(
                "--epoch", f"expected an ISO 8601 date such as 2011-10-03T12:55:00Z or seconds, got '{epoch}'"
            ) from None
    cfg = load_config(config)
    seq = open_sequence(src, cfg.sequence, left, right, calib)
    done = [0]

    def step(i: int) -> None:
        done[0] = i
        bar.update(task, completed=i)

    try:
        with sigterm_as_interrupt(), progress_bar() as bar:
            task = bar.add_task("convert", total=len(seq))
            convert_sequence(seq, dst, kind, cfg.sequence, image_format, keep_topics, progress=step, epoch_ns=epoch_ns)
    except BaseException as exc:  # an interrupt may surface as a clean-up's error (1 run in ~100)
        if not caused_by_interrupt(exc):
            raise
        err_console.print(f"interrupted after {done[0]} frames; {dst} not written")
        raise typer.Exit(130) from None
    size = sum(p.stat().st_size for p in dst.rglob("*")) if dst.is_dir() else dst.stat().st_size
    console.print(f"wrote {dst} ({kind}, {size / 2**20:.1f} MiB, {len(seq)} frames)")
    if kind != "mcap" and epoch_ns is None and relative_times(seq):
        err_console.print(
            f"note: the stamps of {src} are relative (from 0 s), so ROS tools read them as 1970; "
            "--epoch DATE places them at a stated date",
            highlight=False,
            soft_wrap=True,
        )


@app.command()
def run(
    path: Annotated[Path, typer.Argument(help="MCAP file, ROS 1/ROS 2 bag, EuRoC or KITTI folder")],
    config: ConfigOption = None,
    frontend_only: Annotated[bool, typer.Option("--frontend-only", help="Run only the visual front end")] = False,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Results root (default: output.out_dir)")] = None,
    name: Annotated[str | None, typer.Option("--name", help="Run name (folder under --out)")] = None,
    max_frames: Annotated[int | None, typer.Option("--max-frames", help="Stop after this many frames")] = None,
    left: LeftTopicOption = None,
    right: RightTopicOption = None,
    rerun: RerunFileOption = None,
    rerun_spawn: RerunSpawnOption = False,
    rerun_connect: RerunConnectOption = None,
    calib: CalibOption = None,
    base_map: Annotated[
        Path | None, typer.Option("--map", help="Saved map (RESULTS_DIR or RESULTS_DIR/map) to localize in or extend")
    ] = None,
    mode: Annotated[
        Literal["localize", "extend"] | None,
        typer.Option("--mode", help="With --map: localize (nothing added) or extend (merged map, mesh)"),
    ] = None,
    resume: Annotated[
        Path | None, typer.Option("--resume", help="Continue the interrupted run RESULTS_DIR from its last keyframe")
    ] = None,
    overwrite: OverwriteOption = False,
    no_eval: Annotated[
        bool, typer.Option("--no-eval", help="Skip the evaluation against the sequence's ground truth")
    ] = False,
) -> None:
    """Process a sequence: track, close loops, optimise, mesh the laser stripes.

    Writes config, trajectories, keyframes, map, metrics and log into <out>/<name>/. Ctrl-C or
    SIGTERM stops it after writing what it has. After the frames, one line per finishing step with
    its time; when the sequence has ground truth the run is evaluated against it (errors in
    metrics.json) unless --no-eval. With --map the run localizes in a saved map
    (trajectory_in_map.tum, per-frame status in metrics.json) or extends it (map/ is the merged map,
    mesh.ply the mesh of both sessions).
    """
    from rich.progress import TextColumn as _Text

    import loopmodel
    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import frontend_only as frontend_config
    from loopmodel.pipeline import interrupted_error

    if max_frames is not None and max_frames < 1:
        raise InputError("--max-frames", f"must be at least 1, got {max_frames}")
    resume_point = None
    if resume is not None:
        from loopmodel.io.map_file import read_resume_point

        resume_point = read_resume_point(resume)
        out, name = resume.parent, name or resume.name
        if config is None and (resume / "config.yaml").is_file():
            config = [resume / "config.yaml"]  # the interrupted run's configuration
    cfg, session_map = _session_config(load_config(config), base_map, mode)
    from loopmodel.io.results import check_results_folder

    run_name = name or (f"{path.stem}_frontend" if frontend_only else path.stem)
    # a resumed run replaces the folder it continues
    check_results_folder(out if out is not None else cfg.output.out_dir, run_name, overwrite or resume is not None)
    seq = open_sequence(path, cfg.sequence, left, right, calib)
    from loopmodel.frontend.tracker import check_sizes_against_image

    check_sizes_against_image(cfg.frontend, *seq.calibration.image_size)  # before the progress bar
    compile_kernels_if_cold(cfg)
    if getattr(seq, "choice", None):
        console.print(f"{seq.format_name}: {seq.choice}")  # type: ignore[attr-defined]
    total = len(seq) if max_frames is None else min(len(seq), max_frames)
    folder = Path(out if out is not None else cfg.output.out_dir) / run_name
    if frontend_only:
        with progress_bar(_Text("{task.fields[fps]:.1f} fps")) as bar, FinishLines(bar) as finishing:
            task = bar.add_task("front end", total=total, fps=0.0)
            result = loopmodel.run(
                seq,
                frontend_config(cfg),
                out if out is not None else cfg.output.out_dir,
                name=run_name,
                max_frames=max_frames,
                progress=lambda i, n, fps, _kf: bar.update(task, completed=i, fps=fps),
                handle_signals=True,
                evaluate=not no_eval,
                finishing=finishing,
            )
            if result.interrupted:
                raise interrupted_error(result, folder)
        console.print(frontend_summary(result.metrics, result.folder, _run_formatter(result)))
        return
    frame_columns = (_Text("{task.fields[fps]:.1f} fps"), _Text("{task.fields[kf]} keyframes"))
    with progress_bar(*frame_columns) as bar, FinishLines(bar) as finishing:
        task = bar.add_task("run", total=total, fps=0.0, kf=0)
        try:
            result = loopmodel.run(
                seq,
                cfg,
                out if out is not None else cfg.output.out_dir,
                name=run_name,
                max_frames=max_frames,
                progress=lambda i, n, fps, kf: bar.update(task, completed=i, fps=fps, kf=kf),
                listeners=rerun_listeners(seq.calibration, rerun, rerun_spawn, rerun_connect, seq.ground_truth),
                base_map=session_map,
                resume=resume_point,
                handle_signals=True,
                evaluate=not no_eval,
                finishing=finishing,
            )
            if result.interrupted:
                raise interrupted_error(result, folder)
        except KeyboardInterrupt as exc:
            finishing.close()
            note = getattr(exc, "note", "")  # kept beside a complete older run (issue 34)
            where = note or f"results up to the last processed frame are in {folder}"
            err_console.print(where, highlight=False, soft_wrap=True)  # one line, paths unbroken
            raise
    table = Table(title=f"loopmodel run {path.name}", show_header=False)
    for k, v in run_summary_rows(result.metrics, result.folder, _run_formatter(result), rerun):
        table.add_row(escape(k), escape(v))
    console.print(table)
    console.print(f"results in {result.folder}")


def compile_kernels_if_cold(cfg: Config) -> None:
    """Compile the run's numba kernels that numba's cache lacks (after an install or update) before the frames.

    Otherwise they compiled inside the first run's frames and its workers (issue 33 item 2). They compile
    in a process per core; the run loads them from the cache in its warm-ups, as a run with a warm cache.
    """
    from loopmodel.kernels import cold_kernel_modules, compile_in_processes, modules_for

    cold = cold_kernel_modules(modules_for(cfg))
    if not cold:
        return
    with progress_bar(TimeElapsedColumn()) as bar:
        task = bar.add_task("compiling kernels (once after an install or update)", total=len(cold))
        compile_in_processes(tuple(cold), lambda i, _n, _label: bar.update(task, completed=i))


#: What the finishing steps (:data:`loopmodel.pipeline.FINISH_STEPS`) are called on the terminal.
FINISH_LABELS = {
    "workers": "loop and live-mesh workers",
    "final_refinement": "final refinement",
    "mesh": "final mesh",
    "map": "session map",
    "evaluation": "evaluation against ground truth",
    "write": "results files",
}


class FinishLines:
    """The finishing steps after the frames' bar: one line each, a spinner and its time while it runs, then its time.

    A :data:`loopmodel.pipeline.FinishFn`; the frames' bar stops at the first step.
    """

    def __init__(self, frames_bar: Any) -> None:
        self._frames_bar = frames_bar
        self._steps: Any = None
        self._tasks: dict[str, Any] = {}

    def __call__(self, step: str, seconds: float | None) -> None:
        from rich.progress import Progress, SpinnerColumn, TextColumn

        if self._steps is None:
            self._frames_bar.stop()
            self._steps = Progress(
                SpinnerColumn(finished_text="[green]done"),
                TextColumn("{task.description}"),
                TextColumn("{task.fields[time]}"),
                console=err_console,
            )
            self._steps.start()
        label = FINISH_LABELS.get(step, step)
        if seconds is None:
            self._tasks[step] = self._steps.add_task(label, total=1, time="")
        elif step in self._tasks:
            self._steps.update(self._tasks[step], completed=1, time=f"{seconds:.1f} s")

    def close(self) -> None:
        """Leave the lines as they are."""
        if self._steps is not None:
            self._steps.stop()

    def __enter__(self) -> FinishLines:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _run_formatter(result: RunResult) -> Formatter:
    """Lengths of a run in mm or m, from the extent of its path."""
    return Formatter.for_positions(result.final.world_from_cam[:, :3, 3])


def _session_config(cfg: Config, base_map: Path | None, mode: str | None) -> tuple[Config, SessionMap | None]:
    """The configuration with ``--mode`` applied, and the loaded ``--map`` (None without)."""
    if mode is not None:
        if base_map is None:
            raise InputError("--mode", "needs --map")
        cfg = apply_overrides(cfg, {"session.mode": mode}, {"session.mode": "--mode"})
    if base_map is None:
        return cfg, None
    from loopmodel.io.map_file import load_session_map

    return cfg, load_session_map(base_map)


@app.command()
def mesh(
    source: Annotated[
        Path,
        typer.Argument(help="Results folder (stripes.npz + trajectory), session map, or a sequence with ground truth"),
    ],
    fmt: Annotated[Literal["ply", "obj", "stl", "glb"], typer.Option("--format", "-f", help="ply is binary")] = "ply",
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output file (default RESULTS_DIR/mesh.FMT)")] = None,
    trajectory: Annotated[
        Literal["final", "online"], typer.Option("--trajectory", help="Poses of a run to place the stripes with")
    ] = "final",
    gt_mesh: Annotated[
        Path | None,
        typer.Option("--gt-mesh", help="Ground-truth mesh (.ply, or .mcap with scene.ply): print accuracy"),
    ] = None,
    gt_attachment: Annotated[
        str, typer.Option("--gt-attachment", help="Attachment of an .mcap --gt-mesh (e.g. object.ply)")
    ] = "scene.ply",
    plots: Annotated[
        bool, typer.Option("--plots/--no-plots", help="Also write a PNG picture of the mesh beside it")
    ] = True,
    picture: Annotated[bool | None, typer.Option("--picture/--no-picture", hidden=True)] = None,  # old spelling
    config: ConfigOption = None,
    overwrite: OverwriteOption = False,
) -> None:
    """Mesh the laser stripes of a run with its trajectory (metres, world frame of the run), or of a (merged) map."""
    import numpy as np

    from loopmodel.geometry.se3 import up_from_poses
    from loopmodel.io.atomic import check_output_file
    from loopmodel.io.mesh_io import read_mesh
    from loopmodel.meshes import export_mesh

    picture = plots if picture is None else picture
    cfg = load_config(config)
    target = out or (source / f"mesh.{fmt}" if source.is_dir() else source.with_name(f"{source.stem}_mesh.{fmt}"))
    check_output_file(target, overwrite)  # before the work
    made = export_mesh(source, target, fmt, trajectory, cfg, remesh=gt_mesh is not None)
    surface = made.surface
    if made.converted_from is not None:
        console.print(f"wrote {target} ({num(len(surface.vertices))} vertices, converted from {made.converted_from})")
        _mesh_picture(target, surface, None, picture, overwrite, _run_up(source))
        return
    console.print(
        f"wrote {target} ({len(surface.vertices)} vertices, {len(surface.triangles)} triangles, "
        f"{made.placed}, poses: {made.poses})"
    )
    truth = read_mesh(gt_mesh, gt_attachment) if gt_mesh is not None else None
    if truth is not None:
        from loopmodel.mapping.accuracy import mesh_accuracy

        acc = mesh_accuracy(surface, truth)
        console.print(
            f"accuracy: mean {acc.mean_mm:.3f} mm, p95 {acc.p95_mm:.3f} mm, "
            f"completeness {100 * acc.completeness:.1f} % within {acc.completeness_tol_mm:g} mm"
        )
    # a run or a map is in its first camera's world (y down, no gravity: up from the path's principal
    # axes), as is ground truth starting at the identity (KITTI); other ground truth (simulator,
    # motion capture) is z up
    up = (
        up_from_poses(made.path_poses)
        if made.camera_world and made.path_poses is not None
        else np.array([0.0, 0.0, 1.0])
    )
    _mesh_picture(target, surface, truth, picture, overwrite, up)


def _run_up(run_path: Path) -> Any:
    """Up in a run's world (its first camera's) from its path's principal axes; the first camera's -y without one."""
    from loopmodel.geometry.se3 import Y_DOWN_UP, up_from_poses
    from loopmodel.io.trajectory_io import read_trajectory

    for name in ("trajectory_final.tum", "trajectory_online.tum"):
        if (run_path / name).is_file():
            try:
                return up_from_poses(read_trajectory(run_path / name).world_from_cam)
            except LoopmodelError:  # the mesh is the product; its picture is upright or not
                break
    return Y_DOWN_UP


def _mesh_picture(target: Path, surface: Any, truth: Any, picture: bool, overwrite: bool, up: Any) -> None:
    """The PNG beside an exported mesh; an existing one (of the same mesh, another format) is kept."""
    if not picture:
        return
    from loopmodel.io.atomic import write_bytes_atomic
    from loopmodel.viz.mesh_render import mesh_picture_png

    png = target.with_suffix(".png")
    if png.exists() and not overwrite:
        console.print(f"kept {png} (exists; --overwrite redraws it)")
        return
    write_bytes_atomic(png, mesh_picture_png(surface, target.name, truth, up=up))
    console.print(f"wrote {png} (the mesh from three viewpoints)")


simulate_app = typer.Typer(help="Synthetic data.", no_args_is_help=True)

app.add_typer(simulate_app, name="simulate")


@simulate_app.command("scan")
def simulate_scan_cmd(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output .mcap file")],
    preset: Annotated[
        Literal["orbit", "sweeps", "browse", "modeler", "rounds"] | None, typer.Option("--preset", help="Camera motion")
    ] = None,
    realism: Annotated[
        Literal["clean", "realistic"] | None,
        typer.Option("--realism", help="Image model (default: realistic with a preset, else the config's)"),
    ] = None,
    frames: Annotated[int | None, typer.Option("--frames", help="Number of frames")] = None,
    seed: Annotated[
        int | None,
        typer.Option("--seed", help="Random seed of the scan (motion, noise; the object too unless --scene-seed)"),
    ] = None,
    scene_seed: Annotated[
        int | None,
        typer.Option("--scene-seed", help="Seed of the object and room alone: keep it, change --seed: a rescan"),
    ] = None,
    scene: Annotated[Literal["bust", "box", "mix"] | None, typer.Option("--scene", help="Scanned object")] = None,
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
    image_format: Annotated[
        Literal["png", "jpeg", "raw"] | None, typer.Option("--image-format", help="Image encoding in the MCAP")
    ] = None,
    config: ConfigOption = None,
    overwrite: OverwriteOption = False,
) -> None:
    """Generate a synthetic hand-held scan (stereo, laser stripes, ground truth) as MCAP."""
    from loopmodel.io.atomic import check_output_file
    from loopmodel.sim.generate import resolve_config, simulate_scan

    check_output_file(out, overwrite)  # before the work
    cfg = load_config(config)
    sim = resolve_config(
        cfg.simulation,
        preset,
        {
            "trajectory": {"frames": frames, "rate_hz": rate},
            "scene": {"kind": scene, "seed": scene_seed},
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
    from loopmodel.cli.signals import caused_by_interrupt, sigterm_as_interrupt

    done = [0]

    def step(k: int, n: int) -> None:
        done[0] = k
        bar.update(task, completed=k)

    try:
        with sigterm_as_interrupt(), progress_bar() as bar:
            task = bar.add_task("simulate", total=sim.trajectory.frames)
            res = simulate_scan(sim, out, cfg.sequence.topics, step, preset)
    except BaseException as exc:  # an interrupt may surface as a clean-up's error (1 run in ~100)
        if not caused_by_interrupt(exc):
            raise
        err_console.print(f"interrupted after {done[0]} frames; {out} not written")
        raise typer.Exit(130) from None
    console.print(
        f"wrote {res.path} ({res.size_bytes / 2**20:.1f} MiB, {res.frames_written} frames, "
        + (f"{res.laser_images_written} laser images, " if res.laser_images_written else "")
        + (f"{res.stripes_written} stripes, " if res.stripes_written or not res.laser_images_written else "")
        + f"{len(res.faults)} faults) in {res.seconds:.1f} s: "
        f"{res.ms_per_frame:.1f} ms/frame (setup {res.setup_seconds:.1f} s, "
        f"render {res.render_ms_median:.1f} ms/frame per worker)"
    )
