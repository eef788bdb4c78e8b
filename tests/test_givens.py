"""Sequential Givens estimator and data snooping (seed 000) against batch least squares."""

from __future__ import annotations

import numpy as np
import pytest

from loopmodel.backend.givens import GivensEstimator
from loopmodel.backend.givens_bundle import GivensScreen, SequentialBundle, _fkey, _pkey
from loopmodel.backend.snooping import critical_value, normalized_residuals
from loopmodel.backend.testfield import make_testfield
from loopmodel.errors import EstimationError
from loopmodel.geometry.se3 import so3_exp

TOL = 1e-9


class Mirror:
    """The test's own copy of the linear system (whitened rows per named block)."""

    def __init__(self) -> None:
        self.sizes: dict[object, int] = {}
        self.rows: dict[int, tuple[dict[object, np.ndarray], np.ndarray]] = {}

    def add_obs(self, oid: int, coeffs: dict, l: np.ndarray, sigma: np.ndarray) -> None:
        self.rows[oid] = ({k: v / sigma[:, None] for k, v in coeffs.items()}, l / sigma)

    def delete_params(self, name: object) -> None:
        del self.sizes[name]
        for c, _ in self.rows.values():
            c.pop(name, None)

    def batch(self) -> tuple[dict, float, np.ndarray, dict]:
        names = list(self.sizes)
        off, o = {}, 0
        for n in names:
            off[n] = o
            o += self.sizes[n]
        A = np.vstack(
            [np.hstack([c.get(n, np.zeros((len(l), self.sizes[n]))) for n in names]) for c, l in self.rows.values()]
        )
        l = np.concatenate([l for _, l in self.rows.values()])
        x = np.linalg.lstsq(A, l, rcond=None)[0]
        vtpv = float(np.sum((A @ x - l) ** 2))
        Q = np.linalg.inv(A.T @ A)
        sol = {n: x[off[n] : off[n] + self.sizes[n]] for n in names}
        return sol, vtpv, Q, off


def _compare(est: GivensEstimator, mir: Mirror, selected: list) -> None:
    sol, vtpv, Q, off = mir.batch()
    got = est.solution()
    assert set(got) == set(sol)
    scale = max(1.0, max(float(np.max(np.abs(v))) for v in sol.values()))
    for k, v in sol.items():
        np.testing.assert_allclose(got[k], v, rtol=0, atol=TOL * scale)
    assert est.vtpv() == pytest.approx(vtpv, rel=TOL, abs=TOL)
    idx = np.concatenate([np.arange(off[n], off[n] + mir.sizes[n]) for n in selected])
    Qs = est.cofactor(selected)
    np.testing.assert_allclose(Qs, Q[np.ix_(idx, idx)], rtol=0, atol=TOL * max(1.0, np.abs(Q).max()))
    assert est.redundancy == sum(len(l) for _, l in mir.rows.values()) - sum(mir.sizes.values())


def _random_obs(rng: np.random.Generator, est: GivensEstimator, mir: Mirror, locs: list, globs: list) -> int:
    m = int(rng.integers(1, 4))
    coeffs: dict = {}
    if locs and rng.random() < 0.8:
        p = locs[int(rng.integers(len(locs)))]
        coeffs[p] = rng.normal(size=(m, mir.sizes[p]))
    k = int(rng.integers(1, min(3, len(globs)) + 1))
    for gi in rng.choice(len(globs), size=k, replace=False):
        g = globs[int(gi)]
        coeffs[g] = rng.normal(size=(m, mir.sizes[g]))
    l = rng.normal(size=m)
    sigma = rng.uniform(0.3, 3.0, m)
    oid = est.add_observation(coeffs, l, sigma=sigma)
    mir.add_obs(oid, coeffs, l, sigma)
    return oid


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_sparse_mix_matches_batch(seed: int) -> None:
    rng = np.random.default_rng(seed)
    est = GivensEstimator()
    mir = Mirror()
    locs, globs = [], []
    for i in range(8):
        s = int(rng.integers(1, 4))
        est.add_parameters(("p", i), s, local=True)
        mir.sizes[("p", i)] = s
        locs.append(("p", i))
    for i in range(5):
        s = int(rng.integers(1, 7))
        est.add_parameters(("f", i), s)
        mir.sizes[("f", i)] = s
        globs.append(("f", i))
    ids = [_random_obs(rng, est, mir, locs, globs) for _ in range(70)]
    _compare(est, mir, [locs[0], globs[1], locs[3]])
    # delete a third of the observations (hyperbolic downdating)
    for oid in rng.choice(ids, size=len(ids) // 3, replace=False).tolist():
        est.delete_observation(oid)
        del mir.rows[oid]
    _compare(est, mir, [globs[0], locs[1]])
    # new parameters enter in the middle of the sequence
    est.add_parameters(("p", 99), 3, local=True)
    mir.sizes[("p", 99)] = 3
    est.add_parameters(("f", 99), 6)
    mir.sizes[("f", 99)] = 6
    locs.append(("p", 99))
    globs.append(("f", 99))
    for _ in range(40):
        _random_obs(rng, est, mir, locs, globs)
    _compare(est, mir, [("p", 99), ("f", 99), globs[2]])
    # delete parameters: a global block in the middle and a local block
    est.delete_parameters(globs[1])
    mir.delete_params(globs[1])
    globs.pop(1)
    est.delete_parameters(locs[2])
    mir.delete_params(locs[2])
    locs.pop(2)
    _compare(est, mir, [globs[0], locs[0], globs[-1]])
    for _ in range(20):
        _random_obs(rng, est, mir, locs, globs)
    for oid in list(mir.rows)[:10]:
        est.delete_observation(oid)
        del mir.rows[oid]
    _compare(est, mir, [globs[1], locs[-1]])


def test_full_weight_matrix_and_refactorize() -> None:
    rng = np.random.default_rng(5)
    est = GivensEstimator()
    est.add_parameters("a", 3, local=True)
    est.add_parameters("g", 4)
    rows_A, rows_l = [], []
    for _ in range(12):
        A1 = rng.normal(size=(2, 3))
        A2 = rng.normal(size=(2, 4))
        l = rng.normal(size=2)
        M = rng.normal(size=(2, 2))
        P = M @ M.T + np.eye(2)
        est.add_observation({"a": A1, "g": A2}, l, weight=P)
        L = np.linalg.cholesky(P).T
        rows_A.append(L @ np.hstack([A1, A2]))
        rows_l.append(L @ l)
    A = np.vstack(rows_A)
    l = np.concatenate(rows_l)
    x = np.linalg.lstsq(A, l, rcond=None)[0]
    np.testing.assert_allclose(est.solution_vector(), x, atol=1e-10)
    est.refactorize()
    np.testing.assert_allclose(est.solution_vector(), x, atol=1e-10)
    assert est.vtpv() == pytest.approx(float(np.sum((A @ x - l) ** 2)), rel=1e-10)


def test_unsafe_downdate_falls_back_to_refactorisation() -> None:
    rng = np.random.default_rng(3)
    est = GivensEstimator(min_downdate_cos2=1e-6)
    mir = Mirror()
    est.add_parameters("p", 3, local=True)
    est.add_parameters("f", 6)
    mir.sizes.update({"p": 3, "f": 6})
    for _ in range(30):
        _random_obs(rng, est, mir, ["p"], ["f"])
    # a row with an enormous weight dominates the factor: removing it is ill-conditioned
    coeffs = {"p": rng.normal(size=(1, 3)), "f": rng.normal(size=(1, 6))}
    sig = np.array([1e-7])
    oid = est.add_observation(coeffs, np.array([3.0]), sigma=sig)
    before = est.n_downdate_fallbacks
    est.delete_observation(oid)
    assert est.n_downdate_fallbacks == before + 1
    _compare(est, mir, ["p", "f"])


def test_deleting_unknown_observation_is_an_error() -> None:
    est = GivensEstimator()
    est.add_parameters("f", 2)
    oid = est.add_observation({"f": np.eye(2)}, np.ones(2))
    with pytest.raises(EstimationError, match="never added"):
        est.delete_observation(oid + 1)
    est.delete_observation(oid)
    with pytest.raises(EstimationError, match="never added"):
        est.delete_observation(oid)
    with pytest.raises(EstimationError):
        est.add_observation({"nope": np.eye(2)}, np.ones(2))
    est.add_parameters("a", 3, local=True)
    est.add_parameters("b", 3, local=True)
    with pytest.raises(EstimationError, match="one local block"):
        est.add_observation({"a": np.ones((1, 3)), "b": np.ones((1, 3))}, np.ones(1))
    with pytest.raises(EstimationError, match="singular"):
        est.solution()


def test_normalized_residuals_match_dense_formula() -> None:
    rng = np.random.default_rng(11)
    est = GivensEstimator()
    mir = Mirror()
    for i in range(4):
        est.add_parameters(("p", i), 3, local=True)
        mir.sizes[("p", i)] = 3
    for i in range(3):
        est.add_parameters(("f", i), 6)
        mir.sizes[("f", i)] = 6
    ids = [_random_obs(rng, est, mir, [("p", i) for i in range(4)], [("f", i) for i in range(3)]) for _ in range(40)]
    names = list(mir.sizes)
    A = np.vstack(
        [np.hstack([c.get(n, np.zeros((len(l), mir.sizes[n]))) for n in names]) for c, l in mir.rows.values()]
    )
    l = np.concatenate([l for _, l in mir.rows.values()])
    x = np.linalg.lstsq(A, l, rcond=None)[0]
    v = A @ x - l
    Qvv = np.eye(len(l)) - A @ np.linalg.inv(A.T @ A) @ A.T
    w_ref = v / np.sqrt(np.diag(Qvv))
    w, q = normalized_residuals(est, ids)
    np.testing.assert_allclose(np.concatenate([w[i] for i in ids]), w_ref, atol=1e-8)
    np.testing.assert_allclose(np.concatenate([q[i] for i in ids]), np.diag(Qvv), atol=1e-10)
    assert critical_value(0.001) == pytest.approx(3.2905, abs=1e-4)


def _build_bundle(n_frames: int, n_points: int, seed: int = 0, blunder_fraction: float = 0.0):
    tf = make_testfield(n_frames=n_frames, n_points=n_points, seed=seed, blunder_fraction=blunder_fraction)
    rng = np.random.default_rng(seed + 100)
    b = SequentialBundle(tf.camera, sigma_px=tf.sigma_px)
    ctrl = set(tf.control.tolist())
    keys: dict[int, tuple[int, int]] = {}
    for f, (ids, uv) in enumerate(tf.observations):
        T = tf.world_from_cam[f].copy()
        T[:3, 3] += rng.normal(0, 0.002, 3)
        T[:3, :3] = T[:3, :3] @ so3_exp(rng.normal(0, 0.001, 3))
        b.add_frame(f, T, 1e-3 if f == 0 else 0.05, 2e-3 if f == 0 else 0.1)
        for i, u in zip(ids.tolist(), uv, strict=True):
            if i not in b.points:
                if i in ctrl:
                    b.add_point(i, tf.points_world[i], 1e-4)
                else:
                    b.add_point(i, tf.points_world[i] + rng.normal(0, 0.01, 3), 1.0)
            keys[b.add_image_point(f, i, u)] = (f, i)
        b.maybe_relinearize()
    return tf, b, keys


def _batch_of(b: SequentialBundle) -> tuple[np.ndarray, float]:
    A, l, _, _ = b.est.design_matrix()
    Ad = A.toarray()
    x = np.linalg.lstsq(Ad, l, rcond=None)[0]
    return x, float(np.sum((Ad @ x - l) ** 2))


def test_bundle_jacobian_matches_finite_differences() -> None:
    tf = make_testfield(n_frames=4, n_points=30, seed=2)
    b = SequentialBundle(tf.camera)
    b.add_frame(0, tf.world_from_cam[1])
    b.add_point(7, tf.points_world[7] + 0.01)
    from loopmodel.backend.givens_bundle import _ImageObs

    o = _ImageObs(0, 7, np.zeros(2), 1.0)
    coeffs, _ = b._linearize(o, with_current=False)
    A = np.hstack([coeffs[_fkey(0)], coeffs[_pkey(7)]])

    def proj(d: np.ndarray) -> np.ndarray:
        ref = b.frames[0]
        R = ref.R0 @ so3_exp(d[:3])
        C = ref.C0 + d[3:6]
        X = b.points[7].X0 + d[6:]
        return tf.camera.project(R.T @ (X - C))[0]

    h = 1e-6
    J = np.column_stack([(proj(h * e) - proj(-h * e)) / (2 * h) for e in np.eye(9)])
    np.testing.assert_allclose(A, J, rtol=1e-5, atol=1e-4)


def test_bundle_with_deletions_matches_batch_and_truth() -> None:
    tf, b, keys = _build_bundle(12, 30)
    rng = np.random.default_rng(9)
    for oid in rng.choice(list(b.image_obs), size=15, replace=False).tolist():
        b.delete_image_point(oid)
    pid = next(p for p in b.points if p not in set(tf.control.tolist()))
    for oid in list(b.points[pid].image_obs):
        b.delete_image_point(oid)
    b.est.delete_observation(b.points[pid].prior_obs)
    b.est.delete_parameters(_pkey(pid))
    del b.points[pid]
    x, vtpv = _batch_of(b)
    xs = b.est.solution_vector()
    assert np.max(np.abs(xs - x)) <= TOL * max(1.0, np.max(np.abs(x)))
    assert b.est.vtpv() == pytest.approx(vtpv, rel=1e-9)
    sel = [_fkey(5), _pkey(next(iter(b.points)))]
    A, _, names, _ = b.est.design_matrix()
    N = (A.T @ A).toarray()
    Q = np.linalg.inv(N)
    off = np.cumsum([0] + [b.est.block_size(n) for n in names])
    idx = np.concatenate([np.arange(off[names.index(n)], off[names.index(n) + 1]) for n in sel])
    np.testing.assert_allclose(b.est.cofactor(sel), Q[np.ix_(idx, idx)], rtol=1e-7, atol=1e-12)
    # geometry against ground truth after re-linearisation (Gauss-Newton converged)
    b.relinearize()
    b.relinearize()
    err = np.array([b.point(p) - tf.points_world[p] for p in b.points])
    assert np.sqrt(np.mean(err**2)) < 0.005
    assert 0.5 < b.est.variance_factor() < 1.5


def test_snooping_finds_one_and_two_blunders() -> None:
    tf, b, keys = _build_bundle(10, 30, seed=4)
    oids = list(b.image_obs)
    rng = np.random.default_rng(2)
    picks = rng.choice(oids, size=2, replace=False).tolist()
    w0, q0 = normalized_residuals(b.est, oids)
    sig = tf.sigma_px

    def inject(oid: int, size_sigma: float) -> int:
        o = b.image_obs[oid]
        b.delete_image_point(oid)
        new = b.add_image_point(o.frame, o.point, o.uv_px + np.array([size_sigma * sig, 0.0]))
        return new

    one = inject(picks[0], 15.0)
    res = b.snoop(alpha=0.001, max_rejections=1)
    assert res.rejected == [one]
    assert res.rejected_w[0] > res.critical
    two = [inject(picks[1], 15.0)]
    # re-insert the first one with a blunder on the other coordinate as well
    o = b.image_obs[oids[5]] if oids[5] in b.image_obs else b.image_obs[next(iter(b.image_obs))]
    two.append(b.add_image_point(o.frame, o.point, o.uv_px + np.array([0.0, -15.0 * sig])))
    res2 = b.snoop(alpha=0.001, max_rejections=2)
    assert sorted(res2.rejected) == sorted(two)
    for oid in two:
        assert not b.est.has_observation(oid)


def test_screen_rejects_injected_blunders() -> None:
    tf = make_testfield(n_frames=14, n_points=40, seed=6, blunder_fraction=0.03, blunder_sigmas=(10.0, 15.0))
    rng = np.random.default_rng(0)
    scr = GivensScreen(tf.camera, sigma_px=tf.sigma_px)
    ctrl = set(tf.control.tolist())
    blunders, flagged = set(), set()
    for f, (ids, uv) in enumerate(tf.observations):
        for i in ids.tolist():
            if i not in scr.bundle.points:
                scr.add_point(
                    i,
                    tf.points_world[i] + (0 if i in ctrl else rng.normal(0, 0.01, 3)),
                    1e-4 if i in ctrl else None,
                )
        T = tf.world_from_cam[f].copy()
        T[:3, 3] += rng.normal(0, 0.002, 3)
        mask = scr.screen(f, T, ids.tolist(), uv, first_frame=(f == 0))
        blunders |= {(f, i) for i, bl in zip(ids.tolist(), tf.blunder[f], strict=True) if bl}
        flagged |= {(f, i) for i, ok in zip(ids.tolist(), mask, strict=True) if not ok}
        flagged |= set(scr.late_rejections())
    assert blunders, "the test needs blunders"
    assert len(flagged & blunders) >= 0.8 * len(blunders)
    assert len(flagged - blunders) <= 0.02 * sum(len(o[0]) for o in tf.observations)
    assert scr.stats.tested > 0 and scr.stats.rejected == len(flagged)


def test_screen_keyframe_adapter() -> None:
    """Front-end keyframes (stereo + mono observations) through the screen."""
    from loopmodel.types import Keyframe

    tf = make_testfield(n_frames=10, n_points=40, seed=8, blunder_fraction=0.0)
    rng = np.random.default_rng(4)
    scr = GivensScreen(tf.camera, sigma_px=tf.sigma_px)
    seen: set[int] = set()
    bad_key = None
    for f, (ids, uv) in enumerate(tf.observations):
        T = tf.world_from_cam[f]
        uv = uv.copy()
        if f == 6:  # one blunder on a monocular observation of an old landmark
            k = next(k for k, i in enumerate(ids.tolist()) if i in seen)
            uv[k, 0] += 20 * tf.sigma_px
            bad_key = (f, int(ids[k]))
        new = [k for k, i in enumerate(ids.tolist()) if i not in seen]
        old = [k for k, i in enumerate(ids.tolist()) if i in seen]
        p_kf = (tf.points_world[ids[new]] - T[:3, 3]) @ T[:3, :3] + rng.normal(0, 0.005, (len(new), 3))
        kf = Keyframe(
            id=f,
            timestamp_ns=f,
            world_from_kf=T,
            landmark_ids=ids[new],
            points_in_kf=p_kf,
            stereo_px=np.column_stack([uv[new, 0], uv[new, 0] - 30.0, uv[new, 1]]),
            mono_obs=np.column_stack([ids[old], uv[old]]),
        )
        m_st, m_mono = scr.screen_keyframe(kf)
        assert m_st.shape == (len(new),) and m_mono.shape == (len(old),)
        if f == 6:
            k_old = old.index(next(k for k in old if (f, int(ids[k])) == bad_key))
            rejected_now = not m_mono[k_old]
        seen |= set(ids.tolist())
    late = scr.late_rejections()
    assert rejected_now or bad_key in late
    assert scr.stats.rejected <= 3


def test_cli_givens_sim(capsys: pytest.CaptureFixture[str]) -> None:
    from loopmodel.cli import main

    assert main(["givens-sim", "--frames", "6", "--points", "20", "--blunders", "0.05"]) == 0
    out = capsys.readouterr().out
    assert "blunders injected / caught" in out
    assert main(["givens-sim", "--frames", "1"]) == 2


def test_partial_solution_matches_full() -> None:
    rng = np.random.default_rng(21)
    est = GivensEstimator()
    mir = Mirror()
    locs = [("p", i) for i in range(5)]
    globs = [("f", i) for i in range(3)]
    for n in locs:
        est.add_parameters(n, 3, local=True)
        mir.sizes[n] = 3
    for n in globs:
        est.add_parameters(n, 6)
        mir.sizes[n] = 6
    for _ in range(50):
        _random_obs(rng, est, mir, locs, globs)
    sol, _, _, _ = mir.batch()
    xg, xp = est.partial_solution(locs[3])
    np.testing.assert_allclose(xp, sol[locs[3]], atol=1e-9)
    np.testing.assert_allclose(xg, np.concatenate([sol[g] for g in globs]), atol=1e-9)
