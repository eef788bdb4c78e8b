"""Commands on sequences: ``info``, ``convert``, ``run``, ``mesh``, ``simulate scan``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.table import Table

from loopmodel.cli.common import (
    CalibOption,
    ConfigOption,
    LeftTopicOption,
    RightTopicOption,
    _fmt,
    _length,
    app,
    console,
    err_console,
    progress_bar,
)
from loopmodel.cli.view import RerunConnectOption, RerunFileOption, RerunSpawnOption, rerun_listeners
from loopmodel.config import Config, apply_overrides, load_config
from loopmodel.errors import InputError

if TYPE_CHECKING:
    from loopmodel.loop.session_map import SessionMap


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


OverwriteOption = Annotated[
    bool, typer.Option("--overwrite", help="Replace an existing output (only once the new one is complete)")
]


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
    overwrite: OverwriteOption = False,
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
    if dst.exists() and not overwrite:
        raise InputError(dst, "exists already; choose a new name or pass --overwrite")
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
    base_map: Annotated[
        Path | None, typer.Option("--map", help="Saved map (RESULTS_DIR or RESULTS_DIR/map) to localize in or extend")
    ] = None,
    mode: Annotated[
        str | None, typer.Option("--mode", help="With --map: localize (nothing added) or extend (merged map, mesh)")
    ] = None,
    resume: Annotated[
        Path | None, typer.Option("--resume", help="Continue the interrupted run RESULTS_DIR from its last keyframe")
    ] = None,
    overwrite: OverwriteOption = False,
) -> None:
    """Process a sequence (front end, back end).

    Writes config, trajectories, keyframes, map, metrics and log into <out>/<name>/. Ctrl-C or
    SIGTERM stops it after writing what it has. With --map the run localizes in a saved map
    (trajectory_in_map.tum, per-frame status in metrics.json) or extends it (map/ is the merged map,
    mesh.ply the mesh of both sessions).
    """
    from rich.progress import TextColumn as _Text

    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import run_frontend, run_pipeline

    if max_frames is not None and max_frames < 1:
        raise InputError("--max-frames", f"must be at least 1, got {max_frames}")
    resume_point = None
    if resume is not None:
        from loopmodel.loop.session_map import read_resume_point

        resume_point = read_resume_point(resume)
        out, name = resume.parent, name or resume.name
        if config is None and (resume / "config.yaml").is_file():
            config = resume / "config.yaml"  # the interrupted run's configuration
    cfg, session_map = _session_config(load_config(config), base_map, mode)
    from loopmodel.io.results import check_results_folder

    run_name = name or (f"{path.stem}_frontend" if frontend_only else path.stem)
    # a resumed run replaces the folder it continues
    check_results_folder(out if out is not None else cfg.output.out_dir, run_name, overwrite or resume is not None)
    seq = open_sequence(path, cfg.sequence, left, right, calib)
    from loopmodel.frontend.tracker import check_sizes_against_image

    check_sizes_against_image(cfg.frontend, *seq.calibration.image_size)  # before the progress bar
    if getattr(seq, "choice", None):
        console.print(f"{seq.format_name}: {seq.choice}")  # type: ignore[attr-defined]
    total = len(seq) if max_frames is None else min(len(seq), max_frames)
    if frontend_only:
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
                base_map=session_map,
                resume=resume_point,
            )
        except KeyboardInterrupt as exc:
            note = getattr(exc, "note", "")  # kept beside a complete older run (issue 34)
            where = note or f"results up to the last processed frame are in {folder}"
            err_console.print(where, highlight=False, soft_wrap=True)  # one line, paths unbroken
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
    rows += _session_rows(m)
    for k, v in rows:
        table.add_row(k, _fmt(v))
    console.print(table)
    console.print(f"results in {result.folder}")


def _session_config(cfg: Config, base_map: Path | None, mode: str | None) -> tuple[Config, SessionMap | None]:
    """The configuration with ``--mode`` applied, and the loaded ``--map`` (None without)."""
    if mode is not None:
        if base_map is None:
            raise InputError("--mode", "needs --map")
        cfg = apply_overrides(cfg, {"session.mode": mode}, {"session.mode": "--mode"})
    if base_map is None:
        return cfg, None
    from loopmodel.loop.session_map import SessionMap

    return cfg, SessionMap.load(base_map)


def _session_rows(m: dict[str, Any]) -> list[tuple[str, Any]]:
    """Rows of a run in a saved map (localize or extend)."""
    rows: list[tuple[str, Any]] = []
    if "localized_frames" in m:
        first = m.get("map_first_localized_frame")
        rows.append(("localized in the map", f"{m['localized_frames']} frames (first at frame {_fmt(first)})"))
        if not m.get("map_localized"):
            rows.append(("map", "never relocalized: poses in this session's own frame"))
    if "merged" in m:
        rows.append(
            ("merged with the map", f"{m.get('merge_links')} links" if m["merged"] else "no shared view: not merged")
        )
    return rows


@app.command()
def mesh(
    source: Annotated[
        Path,
        typer.Argument(help="Results folder (stripes.npz + trajectory), session map, or a sequence with ground truth"),
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
    overwrite: OverwriteOption = False,
) -> None:
    """Mesh the laser stripes of a run with its trajectory (metres, world frame of the run), or of a (merged) map."""
    from loopmodel.io.mesh_io import MESH_FORMATS, read_mesh, write_mesh
    from loopmodel.mapping.sources import load_stripes_and_poses
    from loopmodel.mapping.stripe_map import StripeMap

    fmt = fmt.lower()
    if fmt not in MESH_FORMATS:
        raise InputError(None, f"--format must be one of {', '.join(MESH_FORMATS)}, got '{fmt}'")
    cfg = load_config(config)
    from loopmodel.io.atomic import check_output_file

    target = out or (source / f"mesh.{fmt}" if source.is_dir() else source.with_name(f"{source.stem}_mesh.{fmt}"))
    for p in [target] + ([target.with_suffix(".png")] if picture else []):
        check_output_file(p, overwrite)  # before the work
    if (source / "map.json").is_file():  # a saved (merged) session map: its stripes at their anchors
        from loopmodel.loop.session_map import SessionMap
        from loopmodel.mapping.final import posed_stripes_mesh

        session_map = SessionMap.load(source)
        map_stripes, map_poses = session_map.stripes_with_poses()
        surface = posed_stripes_mesh(map_stripes, map_poses, cfg.mapping)
        if surface is None:
            raise InputError(source, "the map holds no laser stripes to mesh")
        sessions = len(set(session_map.session.tolist()))
        placed, poses = f"{len(map_stripes)} stripes", f"map keyframes of {sessions} sessions"
    else:
        stripes, traj, poses = load_stripes_and_poses(source, trajectory, cfg.sequence, cfg.mapping)
        smap = StripeMap.from_trajectory(traj, stripes, cfg.mapping)
        smap.check_nonempty()
        surface = smap.mesh()
        placed = f"{int(smap.placed_mask.sum())}/{smap.stripe_count} stripes"
    write_mesh(target, surface, fmt)
    console.print(
        f"wrote {target} ({len(surface.vertices)} vertices, {len(surface.triangles)} triangles, "
        f"{placed}, poses: {poses})"
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
