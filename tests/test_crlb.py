"""Marker-pose Cramér–Rao bound (seed 001): closed forms, flows, scaling, markers, Monte-Carlo."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from loopmodel.accuracy import (
    PSF_SIGMA_PX,
    Circle,
    Marker,
    Polygon,
    bound_grid,
    crlb,
    fisher_contour,
    flows,
    load_marker,
    marker_from_dict,
    project,
    stabilised_views,
    t_marker,
    triangle_marker,
)
from loopmodel.accuracy.marker import marker_to_dict
from loopmodel.accuracy.view import normal_flows
from loopmodel.errors import InputError
from loopmodel.geometry import so3_exp

F = 1800.0  # focal length in px: 18 mm with 10 um pixels


def square(b: float = 1.0) -> Marker:
    return Marker("square", (Polygon(np.array([[-b, -b], [b, -b], [b, b], [-b, b]])),))


# ------------------------------------------------------------------------------------------
# geometry


def test_camera_frame_is_the_rotated_initial_frame() -> None:
    th, ph = 35.0, 110.0
    v = stabilised_views(50.0, th, ph, F)
    axis = np.array([-math.sin(math.radians(ph)), math.cos(math.radians(ph)), 0.0])
    Rot = so3_exp(math.radians(th) * axis)
    np.testing.assert_allclose(v.e1[0], Rot @ [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(v.n2[0], Rot @ [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(v.n3[0], Rot @ [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(v.centre[0], -50.0 * v.e1[0], atol=1e-12)
    # the marker origin projects to the image centre (space-stabilised camera)
    np.testing.assert_allclose(project(v, np.zeros((1, 2)))[0, 0], 0.0, atol=1e-12)


@pytest.mark.parametrize("params", [np.zeros(4), np.array([0.3, -0.02, 0.05, 0.01])])
def test_flows_match_finite_differences(params: np.ndarray, rng: np.random.Generator) -> None:
    views = stabilised_views(50.0, np.array([5.0, 35.0, 65.0]), np.array([0.0, 130.0, 250.0]), F)
    views = views.with_params(params)
    pts = rng.uniform(-1.5, 1.5, size=(20, 2))
    Q = flows(views, pts)
    for i, eps in enumerate((1e-4, 1e-6, 1e-6, 1e-7)):
        d = np.zeros(4)
        d[i] = eps
        fd = (
            project(views.with_params(params + d), pts)
            - project(views.with_params(params - d), pts)
        ) / (2 * eps)
        np.testing.assert_allclose(Q[:, :, i, :], fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())
    # the contour integrand |adot| n.Q = adot x Q, with adot from finite differences along a tangent
    tang = rng.normal(size=(20, 2))
    h = 1e-6
    adot = (project(views, pts + h * tang) - project(views, pts - h * tang)) / (2 * h)
    c, speed = normal_flows(views, pts, tang)
    cross = adot[..., None, 0] * Q[..., 1] - adot[..., None, 1] * Q[..., 0]
    np.testing.assert_allclose(c, cross, rtol=1e-6, atol=1e-6 * np.abs(cross).max())
    np.testing.assert_allclose(speed, np.linalg.norm(adot, axis=-1), rtol=1e-6)


# ------------------------------------------------------------------------------------------
# Fisher information


def test_square_seen_frontally_has_the_closed_form() -> None:
    b, R, noise = 1.0, 50.0, 0.2
    v = stabilised_views(R, 0.0, 0.0, F)
    bp = F * b / R  # image half-side (px)
    expected = (
        np.diag([8 * bp**3 / R**2, 4 * bp * (F / R) ** 2, 4 * bp * (F / R) ** 2, 8 * bp**3 / 3])
        / noise
    )
    J = fisher_contour(square(b), v, noise, n_edge=64)[0]
    np.testing.assert_allclose(J, expected, rtol=1e-3, atol=1e-9 * expected.max())
    J_fine = fisher_contour(square(b), v, noise, n_edge=1024)[0]
    np.testing.assert_allclose(J_fine, expected, rtol=2e-6, atol=1e-9 * expected.max())
    sig = crlb(J_fine).sigma
    np.testing.assert_allclose(sig[0], 1 / math.sqrt(expected[0, 0]), rtol=1e-5)
    np.testing.assert_allclose(sig[3], math.degrees(1 / math.sqrt(expected[3, 3])), rtol=1e-5)


def test_circle_seen_frontally_has_the_closed_form_and_no_roll_information() -> None:
    rho, R, noise = 0.8, 40.0, 0.5
    v = stabilised_views(R, 0.0, 0.0, F)
    rp = F * rho / R
    J = fisher_contour(Marker("disc", (Circle(np.zeros(2), rho),)), v, noise, n_circle=64)[0]
    expected = np.diag(
        [2 * math.pi * rp**3 / R**2, math.pi * rp * (F / R) ** 2, math.pi * rp * (F / R) ** 2, 0.0]
    )
    np.testing.assert_allclose(J, expected / noise, rtol=1e-10, atol=1e-9 * expected.max())


def test_fisher_is_symmetric_positive_definite() -> None:
    for m in (triangle_marker(), t_marker()):
        J = bound_grid(m).J
        np.testing.assert_allclose(J, np.swapaxes(J, -1, -2), rtol=0, atol=1e-12 * np.abs(J).max())
        assert np.all(np.linalg.eigvalsh(J) > 0)


def test_trapezoid_converges_to_gauss_legendre() -> None:
    """Independent quadrature: 8-point Gauss-Legendre per edge with normals from project()."""
    m, noise = triangle_marker(spot_radius_m=0.0), 0.2
    v = stabilised_views(50.0, 45.0, 200.0, F)
    x, w = np.polynomial.legendre.leggauss(8)
    t, w = (x + 1) / 2, w / 2
    J = np.zeros((4, 4))
    verts = m.shapes[0].vertices
    for k in range(3):
        a, b = verts[k], verts[(k + 1) % 3]
        pts = a + t[:, None] * (b - a)
        img = project(v, np.vstack([a, b]))[0]
        tang = (img[1] - img[0]) / np.linalg.norm(img[1] - img[0])
        n = np.array([tang[1], -tang[0]])
        length = np.linalg.norm(img[1] - img[0])
        # image arc length is not affine in t under perspective: dl = |d img/dt| dt
        eps = 1e-6
        speed = np.linalg.norm(
            project(v, pts + eps * (b - a))[0] - project(v, pts - eps * (b - a))[0], axis=1
        ) / (2 * eps)
        nq = flows(v, pts)[0] @ n
        J += np.einsum("m,mi,mj->ij", w * speed, nq, nq) / noise
        assert abs(np.sum(w * speed) - length) < 1e-6 * length
    J_trap = fisher_contour(m, v, noise, n_edge=256)[0]
    np.testing.assert_allclose(J_trap, J, rtol=1e-4, atol=1e-6 * np.abs(J).max())


def test_sigma_scales_with_sqrt_noise() -> None:
    g1 = bound_grid(triangle_marker(), noise=0.2)
    g4 = bound_grid(triangle_marker(), noise=0.8)
    np.testing.assert_allclose(g4.bound.sigma, 2.0 * g1.bound.sigma, rtol=1e-12)
    np.testing.assert_allclose(g4.bound.rho, g1.bound.rho, atol=1e-12)


def test_distance_scaling_follows_the_geometry() -> None:
    # exact similarity: marker and distance scaled by k -> same image, sigma_(r,v,u) x k
    k = 3.0
    big = Marker(
        "tri3",
        tuple(
            Polygon(s.vertices * k)
            if isinstance(s, Polygon)
            else Circle(s.center * k, s.radius * k, s.hole)
            for s in triangle_marker().shapes
        ),
    )
    g1 = bound_grid(triangle_marker(), distance_m=50.0)
    gk = bound_grid(big, distance_m=50.0 * k)
    np.testing.assert_allclose(gk.bound.sigma[..., :3], k * g1.bound.sigma[..., :3], rtol=1e-9)
    np.testing.assert_allclose(gk.bound.sigma[..., 3], g1.bound.sigma[..., 3], rtol=1e-9)
    # frontal square: image size ~ 1/R, so J_rr ~ R^-5 and J_vv, J_gg ~ R^-3 exactly
    s50 = bound_grid(square(), distance_m=50.0, theta_deg=[0.0], phi_deg=[0.0]).bound.sigma[0, 0]
    s100 = bound_grid(square(), distance_m=100.0, theta_deg=[0.0], phi_deg=[0.0]).bound.sigma[0, 0]
    np.testing.assert_allclose(s100 / s50, 2.0 ** np.array([2.5, 1.5, 1.5, 1.5]), rtol=1e-9)
    # oblique views obey the same law once the marker is small against the distance
    a = bound_grid(triangle_marker(), distance_m=500.0).bound.sigma
    b = bound_grid(triangle_marker(), distance_m=1000.0).bound.sigma
    np.testing.assert_allclose(
        b / a, np.broadcast_to(2.0 ** np.array([2.5, 1.5, 1.5, 1.5]), a.shape), rtol=0.01
    )


def test_t_marker_beats_triangle_on_most_of_the_grid() -> None:
    tri, T = triangle_marker(), t_marker()
    assert abs(tri.area - T.area) < 1e-9
    bt, bT = bound_grid(tri).bound, bound_grid(T).bound
    pos_t = np.sqrt(np.sum(bt.sigma[..., :3] ** 2, axis=-1))
    pos_T = np.sqrt(np.sum(bT.sigma[..., :3] ** 2, axis=-1))
    assert np.mean(pos_T < pos_t) > 0.5  # position error sqrt(s_r^2 + s_v^2 + s_u^2)
    assert np.mean(np.linalg.det(bT.cov) < np.linalg.det(bt.cov)) > 0.5  # generalised variance
    assert np.mean(bT.sigma[..., 0] < bt.sigma[..., 0]) > 0.5  # range


def test_grid_shapes_and_correlations_are_valid() -> None:
    g = bound_grid(triangle_marker())
    assert g.bound.sigma.shape == (7, 36, 4) and g.bound.rho.shape == (7, 36, 6)
    assert np.all(np.abs(g.bound.rho) < 1.0)
    # azimuth symmetry of the isosceles triangle (mirror x -> -x): phi and 180 - phi agree
    s = g.bound.sigma
    np.testing.assert_allclose(s[:, 1], s[:, 17], rtol=1e-9)  # 10 deg and 170 deg


# ------------------------------------------------------------------------------------------
# markers


def test_builtin_markers_and_json_round_trip(tmp_path: Path) -> None:
    tri = triangle_marker()
    assert tri.area == pytest.approx(3.0 - math.pi * 0.3**2)
    np.testing.assert_allclose(t_marker().centroid, 0.0, atol=1e-12)
    p = tmp_path / "tri.json"
    p.write_text(json.dumps(marker_to_dict(tri)))
    back = load_marker(p)
    np.testing.assert_allclose(bound_grid(back).J, bound_grid(tri).J, rtol=1e-12)
    assert load_marker("T").name == "t"
    examples = sorted((Path(__file__).resolve().parents[1] / "datasets" / "markers").glob("*.json"))
    assert len(examples) >= 3
    for f in examples:
        m = load_marker(f)
        assert m.area > 0 and np.all(np.isfinite(bound_grid(m, theta_deg=[25.0], phi_deg=[0.0]).J))
    np.testing.assert_allclose(
        load_marker(examples[-1]).area, tri.area, rtol=1e-12
    )  # triangle_spot


BAD = {
    "self_intersecting": (
        {"shapes": [{"type": "polygon", "points": [[0, 0], [1, 1], [1, 0], [0, 1]]}]},
        "self-intersecting",
    ),
    "zero_area": (
        {"shapes": [{"type": "polygon", "points": [[0, 0], [1, 1], [2, 2]]}]},
        "zero area",
    ),
    "zero_radius": ({"shapes": [{"type": "circle", "center": [0, 0], "radius": 0}]}, "zero area"),
    "unknown_top_key": ({"shapes": [], "colour": "red"}, "unknown key 'colour'"),
    "unknown_shape_key": (
        {"shapes": [{"type": "circle", "center": [0, 0], "radius": 1, "radus": 2}]},
        "unknown key 'shapes[0].radus'",
    ),
    "bad_type": ({"shapes": [{"type": "ellipse"}]}, "shapes[0].type"),
    "hole_outside": (
        {
            "shapes": [
                {"type": "circle", "center": [0, 0], "radius": 1},
                {"type": "circle", "center": [5, 0], "radius": 1, "hole": True},
            ]
        },
        "hole must lie inside",
    ),
    "crossing": (
        {
            "shapes": [
                {"type": "circle", "center": [0, 0], "radius": 1},
                {"type": "circle", "center": [1, 0], "radius": 1},
            ]
        },
        "touch or cross",
    ),
    "repeated_point": (
        {"shapes": [{"type": "polygon", "points": [[0, 0], [1, 0], [1, 0], [0, 1]]}]},
        "repeated point",
    ),
    "bad_point": ({"shapes": [{"type": "polygon", "points": [[0, 0], [1], [0, 1]]}]}, "points[1]"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_marker_descriptions_raise_input_error(case: str, tmp_path: Path) -> None:
    data, needle = BAD[case]
    p = tmp_path / f"{case}.json"
    p.write_text(json.dumps(data))
    with pytest.raises(InputError) as exc:
        load_marker(p)
    msg = str(exc.value)
    assert needle in msg and str(p) in msg and "\n" not in msg


def test_bad_marker_file_gives_one_line_cli_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from loopmodel.cli import main

    p = tmp_path / "bow.json"
    p.write_text(json.dumps(BAD["self_intersecting"][0]))
    assert main(["bound", "--marker", str(p), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "self-intersecting" in err
    q = tmp_path / "broken.json"
    q.write_text("{not json")
    assert main(["bound", "--marker", str(q), "--out", str(tmp_path / "o")]) == 2
    assert "not valid JSON" in capsys.readouterr().err
    with pytest.raises(InputError):
        marker_from_dict([1, 2])


def test_nested_hole_and_island_are_valid() -> None:
    m = marker_from_dict(
        {
            "shapes": [
                {"type": "polygon", "points": [[-2, -2], [2, -2], [2, 2], [-2, 2]]},
                {"type": "circle", "center": [0, 0], "radius": 1.5, "hole": True},
                {"type": "circle", "center": [0, 0], "radius": 0.5},
            ]
        }
    )
    assert m.area == pytest.approx(16 - math.pi * 2.25 + math.pi * 0.25)


# ------------------------------------------------------------------------------------------
# rendering, Monte-Carlo, finite pixels


def test_renderer_values_and_jacobian(rng: np.random.Generator) -> None:
    from matplotlib.path import Path as MplPath

    from loopmodel.accuracy.render import BlurredRenderer

    m = triangle_marker()
    v = stabilised_views(50.0, 35.0, 70.0, F)
    R = BlurredRenderer(m, v, PSF_SIGMA_PX, n_circle=96)
    val, jac = R.render(np.zeros(4))
    # brute force: fine supersampling of the sharp image weighted by the Gaussian
    polys = [(project(v, o)[0], hole) for o, hole in m.outlines(96)]
    sg, st = PSF_SIGMA_PX, 0.02
    g = np.arange(-6 * sg, 6 * sg + st / 2, st)
    gx, gy = np.meshgrid(g, g)
    w = np.exp(-(gx**2 + gy**2) / (2 * sg**2)).ravel()
    w /= w.sum()
    for k in rng.choice(R.n_samples, 40, replace=False):
        pts = np.column_stack([gx.ravel() + R.samples[k, 0], gy.ravel() + R.samples[k, 1]])
        inside = np.zeros(len(pts), bool)
        for poly, _ in polys:
            inside ^= MplPath(poly).contains_points(pts)
        assert abs(w @ inside - val[k]) < 0.01
    for i, eps in enumerate((1e-3, 1e-5, 1e-5, 1e-5)):
        d = np.zeros(4)
        d[i] = eps
        fd = (R.render(d)[0] - R.render(-d)[0]) / (2 * eps)
        assert np.abs(fd - jac[:, i]).max() < 1e-4 * np.abs(jac[:, i]).max()


def test_monte_carlo_agrees_with_the_bound(rng: np.random.Generator) -> None:
    from loopmodel.accuracy.montecarlo import run_trials

    res = run_trials(triangle_marker(), 35.0, 70.0, trials=24, rng=rng)
    # the sampled model's exact bound matches the contour formula (deterministic)
    np.testing.assert_allclose(res.sigma_sampled, res.sigma_crlb, rtol=0.03)
    # 24 trials: the sd of an RMS estimate is ~15 %; allow a loose band around 1
    assert np.all(res.ratio > 0.6) and np.all(res.ratio < 1.6)
    assert 0.75 < np.exp(np.mean(np.log(res.ratio))) < 1.3


def test_finite_pixels_tend_to_the_bound_and_degrade() -> None:
    from loopmodel.accuracy.pixels import fisher_pixels

    v = stabilised_views(50.0, 0.0, 0.0, F)
    m = square()
    ref = crlb(fisher_contour(m, v, 0.2)[0]).sigma
    # a sharp image on 1 px pixels equals the contour formula for edges along pixel rows
    box = crlb(fisher_pixels(m, v, 0.2, 1.0, psf_sigma_px=0.0)).sigma
    np.testing.assert_allclose(box, ref, rtol=0.03)
    ratios = [crlb(fisher_pixels(m, v, 0.2, p)).sigma / ref for p in (0.5, 1.0, 2.0)]
    np.testing.assert_allclose(ratios[0], 1.0, atol=0.1)
    assert np.all(ratios[1] > ratios[0]) and np.all(ratios[2] > ratios[1])


@pytest.mark.slow
def test_cli_bound_writes_csv_plots_and_summary(tmp_path: Path) -> None:
    from loopmodel.cli import main

    out = tmp_path / "b"
    assert (
        main(
            [
                "bound",
                "--marker",
                "triangle",
                "--marker",
                "t",
                "--distance-m",
                "50",
                "--focal-mm",
                "18",
                "--noise",
                "0.2",
                "--out",
                str(out),
                "--no-pixel-study",
            ]
        )
        == 0
    )
    for name in ("triangle", "t"):
        rows = (out / f"bound_{name}.csv").read_text().strip().splitlines()
        assert len(rows) == 1 + 7 * 36 and rows[0].startswith("marker,theta_deg,phi_deg,sigma_r_m")
        assert (out / f"{name}_sigma.png").stat().st_size > 1000
        assert (out / f"{name}_rho.png").stat().st_size > 1000
    text = (out / "summary.md").read_text()
    assert "triangle vs t" in text and "N0/2 = 0.2" in text
