"""Outputs of ``loopmodel bound``: CSV of the grid, surface plots (paper Fig. 7/9), summary."""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from loopmodel.accuracy.fisher import RHO_NAMES, GridBound, crlb, fisher_contour
from loopmodel.accuracy.marker import Marker
from loopmodel.accuracy.pixels import fisher_pixels
from loopmodel.accuracy.view import focal_px, stabilised_views
from loopmodel.io.atomic import atomic_path, write_text_atomic

SIGMA_NAMES = ("sigma_r_m", "sigma_v_m", "sigma_u_m", "sigma_gamma_deg")
SIGMA_LABELS = ("σ_r [m]", "σ_v [m]", "σ_u [m]", "σ_γ [deg]")
RHO_LABELS = ("ρ_rv", "ρ_ru", "ρ_rγ", "ρ_uv", "ρ_vγ", "ρ_uγ")


def grid_csv(grid: GridBound) -> str:
    """The grid as CSV text: one row per (theta, phi), sigmas and the six correlations."""
    buf = io.StringIO()
    buf.write(",".join(("marker", "theta_deg", "phi_deg") + SIGMA_NAMES + RHO_NAMES) + "\n")
    s, r = grid.bound.sigma, grid.bound.rho
    for i, th in enumerate(grid.theta_deg):
        for j, ph in enumerate(grid.phi_deg):
            vals = [f"{x:.9g}" for x in (*s[i, j], *r[i, j])]
            buf.write(f"{grid.marker},{th:g},{ph:g}," + ",".join(vals) + "\n")
    return buf.getvalue()


def _surfaces(
    grid: GridBound, values: np.ndarray, labels: Sequence[str], ncols: int, path: Path
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nrows = (len(labels) + ncols - 1) // ncols
    fig = plt.figure(figsize=(4.6 * ncols, 3.8 * nrows))
    PH, TH = np.meshgrid(grid.phi_deg, grid.theta_deg)
    for k, label in enumerate(labels):
        ax = fig.add_subplot(nrows, ncols, k + 1, projection="3d")
        ax.plot_surface(PH, TH, values[..., k], cmap="viridis", linewidth=0, antialiased=False)
        ax.set_xlabel("φ [deg]")
        ax.set_ylabel("θ [deg]")
        ax.set_title(label)
        ax.tick_params(labelsize=7)
    fig.suptitle(
        f"marker '{grid.marker}': R = {grid.distance_m:g} m, f = {grid.focal_mm:g} mm, "
        f"N0/2 = {grid.noise:g} px², pixel {grid.pixel_um:g} µm"
    )
    fig.subplots_adjust(left=0.02, right=0.95, bottom=0.05, top=0.9, wspace=0.12, hspace=0.2)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)


def write_grid_outputs(grid: GridBound, out_dir: Path) -> list[Path]:
    """Write ``bound_<marker>.csv``, ``<marker>_sigma.png`` and ``<marker>_rho.png``."""
    out_dir = Path(out_dir)
    csv = write_text_atomic(out_dir / f"bound_{grid.marker}.csv", grid_csv(grid))
    ps = out_dir / f"{grid.marker}_sigma.png"
    pr = out_dir / f"{grid.marker}_rho.png"
    _surfaces(grid, grid.bound.sigma, SIGMA_LABELS, 2, ps)
    _surfaces(grid, grid.bound.rho, RHO_LABELS, 3, pr)
    return [csv, ps, pr]


def pixel_study(
    marker: Marker,
    grid: GridBound,
    pixel_sizes_px: Sequence[float] = (0.25, 0.5, 1.0, 2.0, 4.0),
    theta_deg: float = 35.0,
    phi_deg: float = 40.0,
) -> list[tuple[float, np.ndarray]]:
    """sigma(pixel size) / sigma(contour bound) per parameter at one grid point."""
    view = stabilised_views(
        grid.distance_m, theta_deg, phi_deg, focal_px(grid.focal_mm, grid.pixel_um)
    )
    ref = crlb(fisher_contour(marker, view, grid.noise)[0]).sigma
    rows = []
    for p in pixel_sizes_px:
        s = crlb(fisher_pixels(marker, view, grid.noise, p)).sigma
        rows.append((float(p), s / ref))
    return rows


def plot_pixel_study(
    studies: dict[str, list[tuple[float, np.ndarray]]], pixel_um: float, path: Path
) -> None:
    """σ(pixel size)/σ(contour) curves for every marker and parameter."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    styles = ["-", "--", ":", "-."]
    for (name, rows), ls in zip(studies.items(), styles * 4, strict=False):
        p = [r[0] for r in rows]
        for k, label in enumerate(SIGMA_LABELS):
            ax.plot(
                p, [r[1][k] for r in rows], ls, marker="o", ms=3, label=f"{name} {label.split()[0]}"
            )
    ax.set_xscale("log", base=2)
    ax.set_xlabel(f"pixel size [reference px of {pixel_um:g} µm]")
    ax.set_ylabel("σ(pixel) / σ(contour bound)")
    ax.axhline(1.1, color="gray", lw=0.7)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)


def summary_markdown(
    grids: Sequence[GridBound],
    studies: dict[str, list[tuple[float, np.ndarray]]] | None = None,
    grid_ms: float | None = None,
) -> str:
    """A short Markdown comparison of the markers over the grid."""
    g0 = grids[0]
    lines = [
        "# Marker-pose accuracy bound (Cramér–Rao, seed 001)",
        "",
        f"Distance R = {g0.distance_m:g} m, focal length f = {g0.focal_mm:g} mm, "
        f"pixel pitch {g0.pixel_um:g} µm (F = {focal_px(g0.focal_mm, g0.pixel_um):g} px), "
        f"noise N0/2 = {g0.noise:g} contrast²·px² (variance of the noise averaged over one "
        "1 px × 1 px cell; marker contrast 1). "
        f"Grid: θ = {', '.join(f'{t:g}' for t in g0.theta_deg)}°, "
        f"φ = {g0.phi_deg[0]:g}…{g0.phi_deg[-1]:g}° "
        f"({len(g0.phi_deg)} values).",
        "",
        "Parameters: r = range along the optical axis e1, v and u = displacements along e2 and e3 "
        "(m), γ = roll about e1 (deg). The bound J = (2/N0)∮(n·Q_i)(n·Q_j)dl is the Fisher "
        "information of the image blurred by a Gaussian PSF of σ = 0.282 px and sampled "
        "infinitely finely (see `loopmodel.accuracy`).",
        "",
        "| marker | area m² | perimeter m | "
        + " | ".join(f"{lab} median (min–max)" for lab in SIGMA_LABELS)
        + " |",
        "|---|---|---|" + "---|" * 4,
    ]
    for g in grids:
        s = g.bound.sigma
        cells = [
            f"{np.median(s[..., k]):.3g} ({s[..., k].min():.3g}–{s[..., k].max():.3g})"
            for k in range(4)
        ]
        lines.append(
            f"| {g.marker} | {g.area_m2:.3f} | {g.perimeter_m:.3f} | " + " | ".join(cells) + " |"
        )
    lines.append("")
    lines.append("| marker | " + " | ".join(f"max abs {lab}" for lab in RHO_LABELS) + " |")
    lines.append("|---|" + "---|" * 6)
    for g in grids:
        lines.append(
            f"| {g.marker} | "
            + " | ".join(f"{np.abs(g.bound.rho[..., k]).max():.2f}" for k in range(6))
            + " |"
        )
    if len(grids) > 1:
        lines += [
            "",
            "Pairwise comparison: share of the grid where the first marker has the smaller σ, "
            'and the median ratio σ_first/σ_second. "position" is √(σ_r²+σ_v²+σ_u²), '
            '"det" the generalised variance det(J⁻¹).',
            "",
        ]
        lines.append("| first vs second | " + " | ".join(SIGMA_LABELS) + " | position | det |")
        lines.append("|---|" + "---|" * 6)
        for a in grids:
            for b in grids:
                if a is b:
                    continue
                sa, sb = a.bound.sigma, b.bound.sigma
                share = [np.mean(sa[..., k] < sb[..., k]) for k in range(4)]
                ratio = [np.median(sa[..., k] / sb[..., k]) for k in range(4)]
                cells = [f"{x:.0%} (×{q:.3f})" for x, q in zip(share, ratio, strict=True)]
                pa = np.sqrt(np.sum(sa[..., :3] ** 2, axis=-1))
                pb = np.sqrt(np.sum(sb[..., :3] ** 2, axis=-1))
                da, db = np.linalg.det(a.bound.cov), np.linalg.det(b.bound.cov)
                cells.append(f"{np.mean(pa < pb):.0%} (×{np.median(pa / pb):.3f})")
                cells.append(f"{np.mean(da < db):.0%}")
                lines.append(f"| {a.marker} vs {b.marker} | " + " | ".join(cells) + " |")
    if studies:
        lines += [
            "",
            "## Finite pixel size (beyond the paper)",
            "",
            "σ for square pixels of the given size (image with the PSF above, integrated over "
            "each pixel, noise variance (N0/2)/p² per pixel) divided by the contour bound, at "
            "θ = 35°, φ = 40°:",
            "",
        ]
        lines.append("| marker | pixel [px] | " + " | ".join(SIGMA_LABELS) + " |")
        lines.append("|---|---|" + "---|" * 4)
        for name, rows in studies.items():
            for p, rel in rows:
                lines.append(f"| {name} | {p:g} | " + " | ".join(f"{x:.3f}" for x in rel) + " |")
        lines.append("")
        for name, rows in studies.items():
            worst = [max(r[1]) for r in rows]
            over = [p for (p, _), w in zip(rows, worst, strict=True) if w > 1.1]
            if over:
                lines.append(
                    f"- {name}: the bound degrades by more than 10 % from a pixel size of "
                    f"{over[0]:g} px ({over[0] * g0.pixel_um:g} µm) on."
                )
    if grid_ms is not None:
        lines += ["", f"Whole grid for all markers computed in {grid_ms:.1f} ms."]
    return "\n".join(lines) + "\n"


def write_summary(text: str, out_dir: Path) -> Path:
    """Write ``summary.md``."""
    return write_text_atomic(Path(out_dir) / "summary.md", text)
