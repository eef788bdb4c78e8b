"""``loopmodel vvs``: virtual visual servoing for N-camera central rigs (seed 002)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from loopmodel.cli.common import (
    ConfigOption,
    app,
    console,
    progress_bar,
)
from loopmodel.config import load_config
from loopmodel.errors import InputError, LoopmodelError

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
    """Track the hand-held box with the simulated 4-mirror sensor (or its 2 diagonal mirrors).

    Writes per-frame pose errors as CSV and PNG.
    """
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
    """Calibrate the 4-mirror rig (intrinsics of every mirror and jM1) from known 3-D points (eq. 16).

    Starts from the nominal sensor design; writes rig.json.
    """
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
