"""The estimation tools: ``bound`` (seed 001), ``givens-sim`` (seed 000), ``depth`` (seed 003)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from loopmodel.cli.common import (
    ConfigOption,
    app,
    console,
    err_console,
    progress_bar,
)
from loopmodel.config import apply_overrides, dump_config, load_config
from loopmodel.errors import InputError

_MARKER_HELP = "triangle, t or a marker JSON file; repeat to compare (default: triangle and t)"
_NOISE_HELP = "N0/2 [contrast^2 px^2]: noise variance of a 1 px x 1 px cell (default 0.2)"


@app.command()
def bound(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder")],
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
    from loopmodel.backend.testfield import make_testfield, screen_testfield

    if frames < 2 or points < 5:
        raise InputError(None, "--frames must be >= 2 and --points >= 5")
    if not 0.0 <= blunders < 1.0:
        raise InputError(None, f"--blunders must be in [0, 1), got {blunders}")
    cfg = load_config(config).givens
    tf = make_testfield(n_frames=frames, n_points=points, blunder_fraction=blunders, seed=seed)
    scr = GivensScreen.from_config(tf.camera, apply_overrides(cfg, {"sigma_px": tf.sigma_px}))
    with progress_bar() as bar:
        task = bar.add_task("frames", total=frames)
        outcome = screen_testfield(tf, scr, lambda f: bar.update(task, completed=f))
    est = scr.bundle.est
    table = Table(title="sequential Givens bundle")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for k, v in (
        ("unknowns", est.n_parameters),
        ("observation rows", est.n_observations),
        ("sigma0 (a posteriori)", f"{est.variance_factor() ** 0.5:.3f}"),
        ("tested / rejected", f"{scr.stats.tested} / {scr.stats.rejected}"),
        ("blunders injected / caught", f"{len(outcome.blunders)} / {outcome.caught}"),
        ("false alarms", outcome.false_alarms),
        ("kernels", __import__("loopmodel.backend.givens", fromlist=["KERNELS"]).KERNELS),
    ):
        table.add_row(k, str(v))
    console.print(table)


depth_app = typer.Typer(
    help="Lyapunov-based adaptive depth estimation from one moving camera (seed 003).", no_args_is_help=True
)

app.add_typer(depth_app, name="depth")


@depth_app.command("simulate")
def depth_simulate(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder")] = Path("results/depth_sim"),
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
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder")] = Path("results/depth_track"),
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
