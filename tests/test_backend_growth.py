"""Issue 33 (scale): the iSAM2 back end's cost per keyframe and per loop stays bounded as the map grows.

A synthetic multi-round keyframe scan (``loopmodel.sim.loop_problem.rounds_problem``: rounds at
other heights and distances around a cylinder, the local map's monocular observations, a loop
constraint to the previous round every 12 keyframes) fed to the back end as the pipeline feeds it;
CPU time (``time.process_time``: GTSAM runs in the calling thread here; the load does not change it).
"""

from __future__ import annotations

import time

import gtsam
import numpy as np

from loopmodel.backend.isam2 import Isam2Backend
from loopmodel.backend.worker import BackgroundBackend
from loopmodel.config import BackendConfig
from loopmodel.sim.loop_problem import SynthRoundsProblem, rounds_problem
from loopmodel.types import StereoCalibration


def _loops_by_query(prob: SynthRoundsProblem) -> dict[int, list[tuple[int, np.ndarray]]]:
    """``prob.loops`` by query keyframe: (old keyframe, query_from_old) of each loop."""
    loops: dict[int, list[tuple[int, np.ndarray]]] = {}
    for q, o, rel in prob.loops:
        loops.setdefault(q, []).append((o, rel))
    return loops


def _ate_m(world_from_kf: dict[int, np.ndarray], truth_in_world: np.ndarray) -> float:
    """Position RMSE (m) of keyframes 0..n-1 against their true positions (no alignment)."""
    p = np.array([world_from_kf[i][:3, 3] for i in range(len(truth_in_world))])
    return float(np.sqrt(np.mean(np.sum((p - truth_in_world) ** 2, axis=1))))

def _calibration() -> StereoCalibration:
    K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
    right_from_left = np.eye(4)
    right_from_left[0, 3] = -0.06
    return StereoCalibration(K, K, right_from_left, (640, 480))


def _feed(n: int, config: BackendConfig) -> tuple[list[float], list[float], float, float]:
    """CPU ms per keyframe (add_keyframe, its loops, estimate), per loop; ATE (m) before and after."""
    prob = rounds_problem(n, features_per_kf=100, local_map_kf=2)
    loops = _loops_by_query(prob)
    backend = Isam2Backend(_calibration(), config)
    kf_ms, loop_ms = [], []
    for kf in prob.keyframes:
        t0 = time.process_time()
        backend.add_keyframe(kf)
        t1 = time.process_time()
        for old, rel in loops.get(kf.id, []):
            backend.add_loop_constraint(kf.id, old, rel)
        t2 = time.process_time()
        backend.estimate(landmarks=False)
        kf_ms.append((time.process_time() - t0) * 1e3)
        if kf.id in loops:
            loop_ms.append((t2 - t1) * 1e3)
    est = backend.estimate(landmarks=False).world_from_kf
    truth = np.array([T[:3, 3] for T in prob.true_world_from_kf])
    before = np.array([kf.world_from_kf[:3, 3] for kf in prob.keyframes])
    after = np.array([est[i][:3, 3] for i in range(n)])
    rms = [float(np.sqrt(np.mean(np.sum((p - truth) ** 2, axis=1)))) for p in (before, after)]
    return kf_ms, loop_ms, rms[0], rms[1]


def test_cost_per_keyframe_and_loop_stays_bounded() -> None:
    # 175 keyframes (7 rounds, 13 loops). Measured (CPU ms, load 33): per keyframe 32.2 (keyframes
    # 25-50) -> 34.1 (last 25), ratio 1.06; loops 2-5 median 98, the last three at most 135 (1.38);
    # ATE 39.3 mm dead reckoning -> 12.3 mm (loop_policy isam2). Under the default local (window9, load 6):
    # loops 2-5 median 6.3 ms, the last three at most 13.2 (a prior on the newer keyframe: a few ms,
    # whose timing noise the absolute slack covers)
    kf_ms, loop_ms, ate_before, ate_after = _feed(175, BackendConfig())
    first, last = np.median(kf_ms[25:50]), np.median(kf_ms[-25:])
    assert last / first < 1.5, (first, last)
    assert np.max(loop_ms[-3:]) < 2.0 * np.median(loop_ms[2:6]) + 10.0, loop_ms
    # the loops correct the drift (ground truth, not the back end's own output)
    assert ate_after < 0.5 * ate_before, (ate_before, ate_after)


def test_worker_reports_its_calls() -> None:
    prob = rounds_problem(30, features_per_kf=60, local_map_kf=1)
    backend = BackgroundBackend(lambda: Isam2Backend(_calibration(), BackendConfig()), "thread")
    for kf in prob.keyframes:
        backend.add_keyframe(kf)
        for q, old, rel in prob.loops:
            if q == kf.id:
                backend.add_loop_constraint(q, old, rel)
    backend.wait_idle()
    kinds = [c[0] for c in backend.call_ms]
    assert kinds.count("kf") == 30 and kinds.count("loop") == len(prob.loops) == 1
    assert "estimate" in kinds
    # every call charged to the keyframes handed over so far, in order; CPU ms are non-negative
    counts = [c[1] for c in backend.call_ms]
    assert counts == sorted(counts) and counts[-1] == 30
    assert all(c[2] >= 0 for c in backend.call_ms)
    backend.close()



def test_worker_poses_stay_rigid() -> None:
    """Keyframe poses slightly off SE(3) (a tracker's long products) come back rigid, however often moved.

    The rounds scan of the scale bench stopped at its 34th keyframe: a pose moved by corrections
    reached a rotation error of 1.0e-5, past the anchored map's bound.
    """
    from loopmodel.geometry.se3 import is_rotation

    prob = rounds_problem(30, features_per_kf=60, local_map_kf=1)
    rng = np.random.default_rng(3)
    backend = BackgroundBackend(lambda: Isam2Backend(_calibration(), BackendConfig()), "thread")
    for kf in prob.keyframes:
        T = kf.world_from_kf.copy()
        T[:3, :3] += rng.normal(0, 1e-6, (3, 3))  # off SO(3) by about 1e-6
        kf.world_from_kf = T
        backend.add_keyframe(kf)
        est = backend.estimate(landmarks=False)
        assert all(is_rotation(P[:3, :3], 1e-9) for P in est.world_from_kf.values())
    backend.wait_idle()
    est = backend.estimate(landmarks=False)
    assert all(is_rotation(P[:3, :3], 1e-9) for P in est.world_from_kf.values())
    backend.close()


def _feed_revisits(policy: str) -> tuple[list[float], float, float, float]:
    """4 rounds that see the previous round's points (150 a keyframe), a loop every 6 keyframes.

    CPU ms per keyframe; ATE (m) of the dead reckoning, of the estimate at the end of the stream and
    of the final estimate (iSAM2 iterated, no batch bundle adjustment).
    """
    from loopmodel.config import RefineConfig

    n = 100
    prob = rounds_problem(n, features_per_kf=100, local_map_kf=2, loop_every_kf=6, revisit_points=150)
    loops = _loops_by_query(prob)
    backend = Isam2Backend(_calibration(), BackendConfig(loop_policy=policy))  # type: ignore[arg-type]
    kf_ms = []
    for kf in prob.keyframes:
        t0 = time.process_time()
        backend.add_keyframe(kf)
        for old, rel in loops.get(kf.id, []):
            backend.add_loop_constraint(kf.id, old, rel)
        backend.estimate(landmarks=False)
        kf_ms.append((time.process_time() - t0) * 1e3)
    truth = np.array([T[:3, 3] for T in prob.true_world_from_kf])

    def ate(world_from_kf: dict[int, np.ndarray]) -> float:
        return _ate_m(world_from_kf, truth)

    before = ate({kf.id: kf.world_from_kf for kf in prob.keyframes})
    online = ate(backend.estimate(landmarks=False).world_from_kf)
    final = backend.final_estimate(RefineConfig(batch_ba=False, distribute_loops=False))
    return kf_ms, before, online, ate(final.world_from_kf)


def test_local_policy_bounds_cost_where_rounds_revisit_the_map() -> None:
    """``loop_policy: local`` keeps the cost flat where the default's grows; the final accuracy holds.

    The rounds see the previous round's points (as the real rounds scan does: 100-250 of a
    keyframe's observations are of landmarks 18-90 keyframes old), which the default iSAM2 links
    into every update.
    """
    full_ms, before, full_online, full_final = _feed_revisits("isam2")
    local_ms, before_local, local_online, local_final = _feed_revisits("local")
    assert before == before_local
    first = lambda ms: float(np.median(ms[5:25]))  # noqa: E731 - the first round: no revisit
    second = lambda ms: float(np.median(ms[25:50]))  # noqa: E731
    last = lambda ms: float(np.median(ms[-25:]))  # noqa: E731
    # measured (CPU ms, load 14; 100 keyframes, 4 rounds): the default 11.6 (keyframes 5-25) -> 41.5
    # (second round) -> 62.2 (last 25); local 10.2 -> 17.6 -> 18.5: the revisits cost a step (their
    # proxies), then no growth
    assert last(full_ms) > 3.0 * first(full_ms), full_ms  # the stream reproduces the growth
    assert last(local_ms) < 1.5 * second(local_ms), local_ms
    assert last(local_ms) < 0.6 * last(full_ms), (local_ms, full_ms)
    # accuracy against the ground truth (m); measured: dead reckoning 26.9 mm; the default 2.88 mm
    # online, 2.87 mm final; local 4.25 mm online (the old map waits for the final estimate), 2.35 mm final
    assert local_online < 0.25 * before, (before, local_online)
    assert local_final < 1.1 * full_final, (full_final, local_final)


def _feed_proxies(bound: int) -> tuple[Isam2Backend, list[int], float, float, float]:
    """60 keyframes of 4 rounds seeing the previous round's points, ``local_proxies_per_kf`` ``bound``.

    The backend after its final estimate; the proxy observations each keyframe's updates made; ATE
    (m) of the dead reckoning, of the estimate at the end of the stream and of the final estimate.
    """
    from loopmodel.config import RefineConfig

    prob = rounds_problem(60, per_round=15, features_per_kf=80, local_map_kf=2, loop_every_kf=6, revisit_points=120)
    loops = _loops_by_query(prob)
    backend = Isam2Backend(_calibration(), BackendConfig(loop_policy="local", local_proxies_per_kf=bound))
    proxies = []
    for kf in prob.keyframes:
        before = sum(1 for r in backend._factors.values() if r.kind == "proxy" and r.factor.size() == 2)
        backend.add_keyframe(kf)
        for old, rel in loops.get(kf.id, []):
            backend.add_loop_constraint(kf.id, old, rel)
        backend.estimate(landmarks=False)
        proxies.append(sum(1 for r in backend._factors.values() if r.kind == "proxy" and r.factor.size() == 2) - before)
    truth = np.array([T[:3, 3] for T in prob.true_world_from_kf])
    before_m = _ate_m({kf.id: kf.world_from_kf for kf in prob.keyframes}, truth)
    online = _ate_m(backend.estimate(landmarks=False).world_from_kf, truth)
    final = backend.final_estimate(RefineConfig(batch_ba=False, distribute_loops=False))
    return backend, proxies, before_m, online, _ate_m(final.world_from_kf, truth)


def test_local_proxies_per_kf_bounds_a_keyframes_proxies_and_every_observation_joins_at_the_end() -> None:
    """``local_proxies_per_kf`` (issue 33, be16): a keyframe sees at most that many old landmarks in iSAM2.

    The rest of its revisit observations wait outside iSAM2 as every revisit observation does under
    ``local``: the final estimate holds the same factors; only the online estimate loses the links.
    """
    full, full_proxies, before, full_online, full_final = _feed_proxies(0)
    bounded, proxies, before_b, online, final = _feed_proxies(25)
    assert before == before_b
    assert max(full_proxies) > 60, full_proxies  # the stream's revisits: about 100 a keyframe from round 2 on
    assert max(proxies) == 25 and all(p <= 25 for p in proxies), proxies
    # what the bound left out (a few proxy observations leave with their landmark in either run)
    assert abs(bounded.proxies_skipped - (sum(full_proxies) - sum(proxies))) < 0.01 * sum(full_proxies)
    # every real observation joined the final estimate (a few landmarks' initial gate, at other online
    # poses, differs: measured 16886 factors against 16914)
    assert abs(bounded.num_factors - full.num_factors) < 0.005 * full.num_factors
    assert not any(r.kind == "proxy" for r in bounded._factors.values())
    # accuracy against the ground truth (m); measured: dead reckoning 19.10 mm; all proxies 4.24 mm online,
    # 3.08 mm final; 25 a keyframe 4.67 mm online, 3.12 mm final
    assert online < 0.3 * before, (before, full_online, online)
    assert final < 1.03 * full_final, (full_final, final)


def test_local_policy_keeps_revisits_and_loops_outside_isam2_until_the_end() -> None:
    """Revisits reach iSAM2 through proxies, loops not at all, until the final estimate.

    A removed revisit takes its proxy's observation along; the final estimate holds every live
    factor and no proxy.
    """
    from loopmodel.config import RefineConfig

    prob = rounds_problem(45, per_round=15, features_per_kf=60, local_map_kf=1, loop_every_kf=5, revisit_points=40)
    # without rebuilds (local_rebuild_kf), which would leave older proxies out of iSAM2 too
    backend = Isam2Backend(_calibration(), BackendConfig(loop_policy="local", local_rebuild_kf=0))
    for kf in prob.keyframes:
        backend.add_keyframe(kf)
        for q, old, rel in prob.loops:
            if q == kf.id:
                backend.add_loop_constraint(q, old, rel)
        backend.estimate(landmarks=False)  # as the worker does (a keyframe's update may wait for it)
    assert len(backend.loop_constraints()) == len(prob.loops) == 6

    def in_isam2() -> int:
        graph = backend._isam.getFactorsUnsafe()
        return sum(1 for i in range(graph.size()) if graph.exists(i))

    revisits = [  # observations in the back end of landmarks first seen more than 11 keyframes before
        (kf.id, int(lm))
        for kf in prob.keyframes[15:]
        for lm in kf.mono_obs[:, 0]
        if int(lm) < 60 * (kf.id - 11) and (kf.id, int(lm)) in backend._obs_fid
    ]
    assert revisits and all(backend.observation_factor_index(o) is None for o in revisits)
    n_isam2 = in_isam2()
    assert n_isam2 < backend.num_factors  # the loops and the real revisit observations wait
    assert backend.remove_observations(revisits[:1]) == 1
    assert in_isam2() == n_isam2 - 1  # its proxy's observation went with it
    # the landmarks during the run (the proxies are Point3 values too: they must not be taken for landmarks)
    est = backend.estimate(landmarks=True)
    assert est.landmark_ids.size == backend.num_landmarks
    # against each point's stereo triangulation placed by its keyframe's true pose (m)
    seen = {
        int(i): T[:3, :3] @ p + T[:3, 3]
        for kf, T in zip(prob.keyframes, prob.true_world_from_kf, strict=True)
        for i, p in zip(kf.landmark_ids, kf.points_in_kf, strict=True)
    }
    err = [np.linalg.norm(p - seen[int(i)]) for i, p in zip(est.landmark_ids, est.landmarks_in_world, strict=True)]
    assert np.median(err) < 0.008, np.median(err)  # measured 5.2 mm (the triangulations' own noise)
    backend.final_estimate(RefineConfig(batch_ba=False, distribute_loops=False))
    assert in_isam2() == backend.num_factors  # every live factor, no proxy
    assert all(backend.observation_factor_index(o) is not None for o in revisits[1:])


class _CountingIsam:
    """An iSAM2 whose single-pose reads are counted."""

    def __init__(self, inner: object) -> None:
        self._inner, self.reads = inner, 0

    def __getattr__(self, name: str) -> object:
        return getattr(self._inner, name)

    def calculateEstimatePose3(self, key: int) -> object:  # noqa: N802 - GTSAM's name
        self.reads += 1
        return self._inner.calculateEstimatePose3(key)  # type: ignore[attr-defined]


def test_estimate_reads_a_bounded_number_of_poses_and_refreshes_after_a_loop() -> None:
    """``estimate_window_kf``: the newest N poses and N older ones in turn; all of them after a loop.

    Fed like the pipeline (a loop every 12 keyframes from the second round); the same updates as a
    back end that reads every pose (``estimate_window_kf: 0``), so its poses are the reference.
    """
    n, window = 60, 5
    prob = rounds_problem(n, features_per_kf=60, local_map_kf=2)
    loops = _loops_by_query(prob)
    # loop_policy isam2: there a loop moves the whole map (under local it moves only the window, whose
    # poses are read anyway)
    full = Isam2Backend(_calibration(), BackendConfig(estimate_window_kf=0, loop_policy="isam2"))
    part = Isam2Backend(_calibration(), BackendConfig(estimate_window_kf=window, loop_policy="isam2"))
    reads, stale_m = [], []
    for kf in prob.keyframes:
        for b in (full, part):
            b.add_keyframe(kf)
            for old, rel in loops.get(kf.id, []):
                b.add_loop_constraint(kf.id, old, rel)
        counter = _CountingIsam(part._isam)
        part._isam = counter  # type: ignore[assignment]
        got = part.estimate(landmarks=False).world_from_kf
        part._isam = counter._inner  # type: ignore[assignment]
        ref = full.estimate(landmarks=False).world_from_kf
        reads.append(counter.reads)
        assert got.keys() == ref.keys()
        newest = [k.id for k in prob.keyframes[max(kf.id - window + 1, 0) : kf.id + 1]]
        for k in newest:  # the newest ones read now: the reference's poses
            np.testing.assert_allclose(got[k], ref[k], atol=1e-12)
        if kf.id in loops:  # a loop may move every keyframe: all read again
            assert reads[-1] == kf.id + 1
            for k in ref:
                np.testing.assert_allclose(got[k], ref[k], atol=1e-12)
        stale_m.append(max(float(np.linalg.norm(got[k][:3, 3] - ref[k][:3, 3])) for k in ref))
    plain = [r for i, r in enumerate(reads) if i not in loops]
    assert max(plain[2 * window + 1 :]) == 2 * window  # bounded: not the keyframe count
    assert reads[-1] <= 2 * window or (n - 1) in loops
    # older poses are at most a few calls stale: measured 0.2 mm typically, 1.24 mm at most (the
    # keyframe after a loop, whose update relinearises the moved map; keyframes ~10 cm apart)
    assert max(stale_m) < 2e-3, max(stale_m)


def _feed_budget(
    budget: int, policy: str, overflow: str = "final"
) -> tuple[Isam2Backend, list[tuple[int, int, int]], float, float, float]:
    """50 keyframes, each seeing the points of the 3 keyframes before it, with ``keyframe_obs_budget``.

    Per keyframe (id, its observations of landmarks older than the previous keyframe's in iSAM2, those
    outside); ATE (m) of the dead reckoning, at the end of the stream and of the final estimate.
    """
    from loopmodel.config import RefineConfig

    n, per_kf = 50, 60
    prob = rounds_problem(n, features_per_kf=per_kf, local_map_kf=3, loop_every_kf=6, revisit_points=0)
    config = BackendConfig(
        keyframe_obs_budget=budget,
        keyframe_obs_redundant_kf=0,  # the budget alone
        loop_policy=policy,  # type: ignore[arg-type]
        keyframe_obs_overflow=overflow,  # type: ignore[arg-type]
    )
    backend = Isam2Backend(_calibration(), config)
    counts = []
    for kf in prob.keyframes:
        backend.add_keyframe(kf)
        for q, old, rel in prob.loops:
            if q == kf.id:
                backend.add_loop_constraint(q, old, rel)
        # landmarks of keyframes before the previous one were in the graph before this update
        old = [(kf.id, int(lm)) for lm in kf.mono_obs[:, 0] if int(lm) < per_kf * (kf.id - 1)]
        slots = [backend.observation_factor_index(o) for o in old if o in backend._obs_fid]
        counts.append((kf.id, sum(s is not None for s in slots), sum(s is None for s in slots)))
    truth = np.array([T[:3, 3] for T in prob.true_world_from_kf])

    def ate(world_from_kf: dict[int, np.ndarray]) -> float:
        return _ate_m(world_from_kf, truth)

    before = ate({kf.id: kf.world_from_kf for kf in prob.keyframes})
    online = ate(backend.estimate(landmarks=False).world_from_kf)
    final = ate(backend.final_estimate(RefineConfig(batch_ba=False, distribute_loops=False)).world_from_kf)
    return backend, counts, before, online, final


def test_keyframe_obs_budget_bounds_each_update_and_the_rest_joins_at_the_end() -> None:
    """``keyframe_obs_budget`` (issue 33, scale8): an update takes at most that many known landmarks' observations.

    The keyframe's other monocular ones wait outside iSAM2 and join for the final estimate.
    """
    full, full_counts, before, full_online, full_final = _feed_budget(0, "isam2")
    assert all(out == 0 for _, _, out in full_counts)
    assert max(inside for _, inside, _ in full_counts) > 100  # 2 older keyframes' 60 points each
    budget, counts, before_b, online, final = _feed_budget(60, "isam2")
    assert before_b == before
    # (stereo observations of known landmarks count too: none here, each keyframe's points are new; a
    # landmark of an older keyframe created in this update brings its observations whole: 61 once in 40)
    assert all(inside <= 62 for _, inside, _ in counts), counts
    assert sum(out for _, _, out in counts) > 40 * 48, counts  # about 60 a keyframe waited
    # the final estimate holds every observation (what waited joined)
    assert all(budget.observation_factor_index(o) is not None for o in budget._obs_fid)
    assert budget.num_factors == full.num_factors
    # accuracy (m) against the truth; measured: dead reckoning 14.80 mm; without the budget 2.71 mm online
    # and final; with it 3.18 mm online (half the older points wait), 2.63 mm final (40 keyframes: 2.17 ->
    # 2.69 mm, the same factors iterated from other points: the final iSAM2 estimate is not converged)
    assert online < 1.3 * full_online, (full_online, online)
    assert final < 1.1 * full_final, (full_final, final)
    # the same under loop_policy local (revisits through proxies, loops at the end): measured 6.97 mm
    # online (3.28 mm without the budget), 2.64 mm final
    _, counts, _, online_local, final_local = _feed_budget(60, "local")
    assert all(inside <= 62 for _, inside, _ in counts), counts
    assert online_local < 0.6 * before, (before, online_local)
    assert final_local < 1.1 * full_final, (full_final, final_local)


def test_keyframe_obs_budget_drop_leaves_the_rest_out_for_good() -> None:
    """``keyframe_obs_overflow: drop`` (issue 33, be15): what is over a keyframe's budget never enters the graph.

    Each update bounded as with ``final``; nothing waits outside iSAM2 for the final estimate, whose
    graph holds that many observations fewer (so its cost is bounded too).
    """
    full, _, before, full_online, full_final = _feed_budget(0, "local")
    backend, counts, before_b, online, final = _feed_budget(60, "local", "drop")
    assert before_b == before
    assert all(inside <= 62 for _, inside, _ in counts), counts
    assert backend.budget_dropped > 40 * 48, backend.budget_dropped  # about 60 a keyframe left out
    assert backend.num_factors == full.num_factors - backend.budget_dropped
    # measured: dead reckoning 14.80 mm; without the budget (local) 2.60 mm online, 2.72 mm final;
    # dropping 2802 of the older points' observations (about half): 2.78 mm online, 3.03 mm final
    assert online < 0.6 * before, (before, online)
    assert final < 1.3 * full_final, (full_final, final)



def _feed_redundant(
    redundant: int, policy: str, budget: int = 0
) -> tuple[Isam2Backend, dict[int, tuple[int, int]], float, float, float]:
    """40 keyframes, each seeing the points of the 4 before it, with ``keyframe_obs_redundant_kf`` (be22).

    Returns the back end; per age (1-4 keyframes: whose points) the observations of them in iSAM2 and
    outside; ATE (m) of the dead reckoning, at the end of the stream and of the final estimate.
    """
    from loopmodel.config import RefineConfig

    n, per_kf = 40, 60
    prob = rounds_problem(n, features_per_kf=per_kf, local_map_kf=4, loop_every_kf=6, revisit_points=0)
    config = BackendConfig(
        keyframe_obs_redundant_kf=redundant, keyframe_obs_budget=budget, loop_policy=policy  # type: ignore[arg-type]
    )
    backend = Isam2Backend(_calibration(), config)
    by_age: dict[int, tuple[int, int]] = {age: (0, 0) for age in range(1, 5)}
    for kf in prob.keyframes:
        backend.add_keyframe(kf)
        for q, old, rel in prob.loops:
            if q == kf.id:
                backend.add_loop_constraint(q, old, rel)
        backend.estimate(landmarks=False)  # as the worker: a deferred update runs
        for lm in kf.mono_obs[:, 0].astype(int).tolist():
            age = kf.id - lm // per_kf
            if (kf.id, lm) in backend._obs_fid and 1 <= age <= 4:
                inside = backend.observation_factor_index((kf.id, lm)) is not None
                a, b = by_age[age]
                by_age[age] = (a + inside, b + (not inside))
    truth = np.array([T[:3, 3] for T in prob.true_world_from_kf])
    before = _ate_m({kf.id: kf.world_from_kf for kf in prob.keyframes}, truth)
    online = _ate_m(backend.estimate(landmarks=False).world_from_kf, truth)
    final = backend.final_estimate(RefineConfig(batch_ba=False, distribute_loops=False)).world_from_kf
    return backend, by_age, before, online, _ate_m(final, truth)


def test_redundant_rule_holds_nothing_back_without_a_budget() -> None:
    """``keyframe_obs_redundant_kf`` 3 without ``keyframe_obs_budget`` (be22): every observation enters iSAM2.

    The rule only says which observations a budget may hold back; alone (every observation of a landmark 3
    observations fix held back: a point's 4th and 5th here) it cost the KITTI clip and, here, the online
    estimate (measured 1.41 -> 2.67 mm: the oldest points' observations, the longest baselines, waited).
    """
    _, by_age, _, online, final = _feed_redundant(3, "isam2")
    assert all(out == 0 for _, out in by_age.values()), by_age
    assert all(inside > 2000 for inside, _ in by_age.values()), by_age
    # measured: 1.41 mm online and final, as with every observation (dead reckoning 13.23 mm)
    assert online < 2e-3 and final < 2e-3, (online, final)


def test_with_a_budget_only_redundant_observations_wait_once_it_is_reached() -> None:
    """``keyframe_obs_redundant_kf`` 3 with ``keyframe_obs_budget`` 150 (be22): the budget holds back only those.

    A keyframe's observations of its 2 previous keyframes' points (fixed by fewer than 3) all enter iSAM2,
    over the budget; of the older points' (redundant) those up to the budget enter, the rest wait.
    """
    full, _, _, _, _ = _feed_redundant(0, "isam2")
    _, by_age, _, online_b, final_b = _feed_redundant(0, "isam2", budget=150)
    assert by_age[2][1] > 500, by_age  # the budget alone holds back the newest too (measured 768 of 2273)
    backend, by_age, _, online, final = _feed_redundant(3, "isam2", budget=150)
    assert by_age[1][1] == 0 and by_age[2][1] == 0, by_age
    inside, out = by_age[3][0] + by_age[4][0], by_age[3][1] + by_age[4][1]
    assert inside > 2000 and out > 500, by_age  # measured: 3306 in, 1059 out
    # what waited joins the final estimate
    assert all(backend.observation_factor_index(o) is not None for o in backend._obs_fid)
    assert backend.num_factors == full.num_factors
    # measured (mm): budget alone 1.37 online, 1.35 final; with the rule 1.40, 1.36 (every observation: 1.41)
    assert online < 1.1 * online_b and final < 1.1 * final_b, (online_b, online, final_b, final)
    # the same under loop_policy local
    _, by_age, _, _, _ = _feed_redundant(3, "local", budget=150)
    assert by_age[1][1] == 0 and by_age[2][1] == 0 and by_age[3][1] + by_age[4][1] > 500, by_age


def _feed_tied(resumed: bool) -> tuple[Isam2Backend, np.ndarray, list[int], int]:
    """10 keyframes, each seeing the points of the 3 before it, under a budget of 30 (be19).

    Keyframe 8 marked as resuming keyframe 5's features (``ba_info["resumed_from_keyframe"]``) when
    ``resumed``; keyframe 9's observations of keyframe 6's points handed late (``add_observations``,
    as a loop's). Returns the back end, those late rows, keyframe 5's landmark ids, points a keyframe.
    """
    import dataclasses

    per_kf = 60
    prob = rounds_problem(10, features_per_kf=per_kf, local_map_kf=3, loop_every_kf=1000)
    backend = Isam2Backend(_calibration(), BackendConfig(keyframe_obs_budget=30, keyframe_obs_redundant_kf=0))
    late = np.zeros((0, 3))
    for kf in prob.keyframes:
        if kf.id == 8 and resumed:
            kf = dataclasses.replace(kf, ba_info={**kf.ba_info, "resumed_from_keyframe": 5.0})
        if kf.id == 9:
            mono = np.asarray(kf.mono_obs, float)
            of_6 = (mono[:, 0] >= 6 * per_kf) & (mono[:, 0] < 7 * per_kf)
            late, kf = mono[of_6], dataclasses.replace(kf, mono_obs=mono[~of_6])
        backend.add_keyframe(kf)
    backend.add_observations(9, late)
    backend.estimate()  # every deferred update run
    return backend, late, list(range(5 * per_kf, 6 * per_kf)), per_kf


def test_budget_never_holds_back_what_ties_a_keyframe_to_a_resumed_or_looped_keyframe() -> None:
    """``keyframe_obs_budget`` (be19): a resumed old keyframe's landmarks and a loop's late observations enter iSAM2.

    Without the resumed mark keyframe 8's observations of keyframe 5's landmarks are held back like the
    rest of its local map's; with it every one enters iSAM2 and the budget still holds back others.
    """
    plain, late, of_5, per_kf = _feed_tied(False)
    tied, _, _, _ = _feed_tied(True)

    def in_isam2(backend: Isam2Backend, kf: int, ids: list[int]) -> tuple[int, int]:
        seen = [(kf, i) for i in ids if (kf, i) in backend._obs_fid]
        return sum(backend.observation_factor_index(o) is not None for o in seen), len(seen)

    inside, seen = in_isam2(plain, 8, of_5)
    # measured: 25 of 59 in iSAM2 without the mark, 59 of 59 with it; keyframe 6's 5 of 60 both ways;
    # keyframe 9's late rows 60 of 60, its own of keyframe 7's 30 of 60
    assert seen > 40 and inside < 0.75 * seen, (inside, seen)  # held back like the local map's
    inside, seen = in_isam2(tied, 8, of_5)
    assert seen > 40 and inside == seen, (inside, seen)
    of_6, of_7 = list(range(6 * per_kf, 7 * per_kf)), list(range(7 * per_kf, 8 * per_kf))
    inside, seen = in_isam2(tied, 8, of_6)  # (keyframe 7's points enter the graph in 8's update: not counted)
    assert seen > 40 and inside < seen / 2, (inside, seen)  # the budget still binds on the rest
    # keyframe 9's late observations (a loop's) all enter; its own observations of keyframe 7's are budgeted
    late_ids = late[:, 0].astype(int).tolist()
    assert len(late_ids) > 40
    for backend in (plain, tied):
        assert in_isam2(backend, 9, late_ids) == (len(late_ids), len(late_ids))
        inside, seen = in_isam2(backend, 9, of_7)
        assert inside < seen, (inside, seen)


def test_budget_keeps_observations_spread_over_the_image_best_supported_first() -> None:
    """``keyframe_obs_budget`` takes a keyframe's observations round robin over an 8 x 4 grid of the image.

    In each cell those of the landmarks with the most factors first (issue 33, be13): 30 observations
    crowding one cell and 10 in ten other cells; the first 11 taken are the crowded cell's best-supported
    one and the 10 others, then the crowded cell's next; a non-finite row does not stop it.
    """
    from loopmodel.backend.isam2 import _Landmark

    backend = Isam2Backend(_calibration(), BackendConfig())
    for i in range(40):  # landmark i in the graph with i + 1 factors
        backend._landmarks[i] = _Landmark(i, 0, set(range(i + 1)))
        backend._lm_current[i] = i
    rng = np.random.default_rng(0)
    crowded = np.column_stack([np.arange(30), rng.uniform(1, 79, 30), rng.uniform(1, 119, 30)])  # 80 x 120 px cell
    others = np.array([[30 + k, 80 * (k % 7 + 1) + 40, 60 + 120 * (k // 7)] for k in range(10)], float)
    rows = np.vstack([crowded, others, [[np.nan, 5.0, 5.0]]])[rng.permutation(41)]
    order = rows[backend._spread_order(rows, backend._row_lkeys(rows))]
    assert sorted(order[:, 0].tolist(), key=lambda x: (np.isnan(x), x))[:40] == list(range(40))  # all kept
    first = order[:11, 0].astype(int).tolist()
    assert sorted(first) == [29, *range(30, 40)], first
    assert int(order[11, 0]) == 28

def _feed_live(loop_prior: bool) -> tuple[list[float], list[float], float]:
    """4 rounds without revisits, a loop every 6 keyframes, ``loop_policy: local``.

    Per keyframe the error (m) of its own pose right after its update and loops (the live end of
    the trajectory, against the truth); the CPU ms of each loop's call; the final estimate's ATE (m).
    """
    from loopmodel.config import RefineConfig

    n = 100
    prob = rounds_problem(n, features_per_kf=100, local_map_kf=2, loop_every_kf=6)
    loops = _loops_by_query(prob)
    # without local_rebuild_kf: the loop prior alone (with rebuilds every 20 keyframes, measured: the third
    # round's live error 8.8 / 6.7 mm, final ATE 4.36 / 4.95 mm)
    config = BackendConfig(loop_policy="local", local_loop_prior=loop_prior, local_rebuild_kf=0)
    backend = Isam2Backend(_calibration(), config)
    truth = np.array([T[:3, 3] for T in prob.true_world_from_kf])
    live, loop_ms = [], []
    for kf in prob.keyframes:
        backend.add_keyframe(kf)
        for old, rel in loops.get(kf.id, []):
            t0 = time.process_time()
            backend.add_loop_constraint(kf.id, old, rel)
            loop_ms.append((time.process_time() - t0) * 1e3)
        est = backend.estimate(landmarks=False).world_from_kf
        live.append(float(np.linalg.norm(est[kf.id][:3, 3] - truth[kf.id])))
    final = backend.final_estimate(RefineConfig(batch_ba=False, distribute_loops=False))
    return live, loop_ms, _ate_m(final.world_from_kf, truth)


def test_local_loop_prior_corrects_the_live_end_at_a_bounded_cost() -> None:
    """``local_loop_prior`` (issue 33 item 5, window9): under ``local`` a loop moves the live end at once.

    Without it the loops wait for the final estimate and the third round's live poses keep the drift.
    """
    live_off, _, final_off = _feed_live(False)
    live_on, loop_ms, final_on = _feed_live(True)
    rms = lambda e: float(np.sqrt(np.mean(np.square(e[50:75]))))  # noqa: E731 - the third round (m)
    # measured (m): the third round's live error 11.9 mm without, 7.8 mm with the priors (the default
    # loop_policy isam2: 7.8 mm); final ATE 4.97 / 5.14 mm (5.32 mm with local_defer_keyframe)
    assert rms(live_on) < 0.8 * rms(live_off), (rms(live_off), rms(live_on))
    assert final_on < 1.1 * final_off, (final_off, final_on)
    # one small update whatever the loop's span: the last loops cost what the first ones did
    assert np.max(loop_ms[-3:]) < 3.0 * np.median(loop_ms[:4]) + 2.0, loop_ms


class _CountingIsam2:
    """An ``ISAM2`` whose ``update`` calls are counted (what each one costs: the window's top re-eliminated)."""

    def __init__(self, inner: object) -> None:
        self._inner, self.updates = inner, 0

    def __getattr__(self, name: str) -> object:
        return getattr(self._inner, name)

    def update(self, *args: object, **kwargs: object) -> object:
        self.updates += 1
        return self._inner.update(*args, **kwargs)  # type: ignore[attr-defined]


def _feed_late(defer: bool, defer_keyframe: bool = False) -> tuple[list[int], list[int], int, float, float]:
    """3 rounds with revisits; each keyframe's monocular observations half in ``add_keyframe``, half late.

    As the loop stage hands them over (``add_observations``, then the loop constraint for a loop
    keyframe). Per keyframe the iSAM2 updates it cost and whether it had a loop; the live factors; the
    live error (m, RMS over the third round) of each loop keyframe right after its loop; the final ATE (m).
    """
    import dataclasses

    from loopmodel.config import RefineConfig

    prob = rounds_problem(45, per_round=15, features_per_kf=60, local_map_kf=1, loop_every_kf=5, revisit_points=40)
    loops = _loops_by_query(prob)
    config = BackendConfig(
        loop_policy="local", local_defer_late=defer, local_defer_keyframe=defer_keyframe, local_rebuild_kf=0
    )
    backend = Isam2Backend(_calibration(), config)
    counter = _CountingIsam2(backend._isam)
    backend._isam = counter
    truth = np.array([T[:3, 3] for T in prob.true_world_from_kf])
    updates, looped, live = [], [], []
    for kf in prob.keyframes:
        mono = np.asarray(kf.mono_obs, float).reshape(-1, 3)
        half = mono.shape[0] // 2
        n0 = counter.updates
        backend.add_keyframe(dataclasses.replace(kf, mono_obs=mono[:half]))
        backend.add_observations(kf.id, mono[half:])
        for old, rel in loops.get(kf.id, []):
            backend.add_loop_constraint(kf.id, old, rel)
        est = backend.estimate(landmarks=False).world_from_kf
        updates.append(counter.updates - n0)
        looped.append(int(kf.id in loops))
        if kf.id in loops and kf.id >= 30:
            live.append(float(np.linalg.norm(est[kf.id][:3, 3] - truth[kf.id])))
    final = backend.final_estimate(RefineConfig(batch_ba=False, distribute_loops=False))
    rms = float(np.sqrt(np.mean(np.square(live))))
    return updates, looped, backend.num_factors, rms, _ate_m(final.world_from_kf, truth)


def test_late_observations_join_the_next_update() -> None:
    """``local_defer_late`` (issue 33 item 5, isam10): a loop keyframe costs two iSAM2 updates, not three.

    The rounds scan's loop keyframes brought three updates each (the keyframe's, its loop's late
    observations', the loop's prior's), each re-eliminating the window's top: the late observations
    now wait for the next update (the prior's; the next keyframe's without a loop). Same factors, the
    loop's correction of the live end and the final accuracy unchanged.
    """
    upd_on, looped, factors_on, live_on, final_on = _feed_late(True)
    upd_off, _, factors_off, live_off, final_off = _feed_late(False)
    assert sum(looped[15:]) == 6
    # deterministic counts: without deferral 2 a keyframe, 3 with a loop; with it 1 and 2
    assert upd_off[15:] == [2 + lp for lp in looped[15:]], upd_off
    assert upd_on[15:] == [1 + lp for lp in looped[15:]], upd_on
    # the same observations; landmark creation gates them at the pose estimates of the moment, which
    # the deferred observations reach one update later (measured 6217 / 6188 factors)
    assert abs(factors_on - factors_off) < 0.01 * factors_off, (factors_off, factors_on)
    # measured: the third round's loop keyframes right after their loops 4.02 mm without, 4.08 mm with;
    # final ATE 1.82 / 1.75 mm
    assert live_on < 1.1 * live_off + 1e-4, (live_off, live_on)
    assert final_on < 1.05 * final_off + 1e-5, (final_off, final_on)


def test_deferred_observations_are_removable_and_join_the_final_estimate() -> None:
    """Late observations waiting for an update can be removed (their slots come first) or kept to the end."""
    import dataclasses

    from loopmodel.config import RefineConfig

    prob = rounds_problem(12, per_round=12, features_per_kf=60, local_map_kf=2)
    backend = Isam2Backend(_calibration(), BackendConfig(loop_policy="local"))
    for kf in prob.keyframes:
        mono = np.asarray(kf.mono_obs, float).reshape(-1, 3)
        backend.add_keyframe(dataclasses.replace(kf, mono_obs=mono[:0]))
        backend.add_observations(kf.id, mono)
    last = prob.keyframes[-1]
    late = [(last.id, int(lm)) for lm in np.asarray(last.mono_obs)[:, 0]]
    assert backend.observation_factor_index(late[0]) is None  # waiting: not in iSAM2 yet
    assert backend.remove_observations(late[:5]) == 5  # flushed first, then removed from iSAM2
    assert all(backend.observation_factor_index(o) is None for o in late[:5])
    assert all(backend.observation_factor_index(o) is not None for o in late[5:])
    n = backend.num_factors
    final = backend.final_estimate(RefineConfig(batch_ba=False, distribute_loops=False))
    assert backend.num_factors == n
    truth = np.array([T[:3, 3] for T in prob.true_world_from_kf])
    assert _ate_m(final.world_from_kf, truth) < 0.005


_BEHIND_WORKER = """
import functools, time
import numpy as np
from loopmodel.backend.worker import BackgroundBackend
backend = BackgroundBackend(functools.partial(time.sleep, 600), "process")  # a worker that never reads
for _ in range(5):
    backend.add_observations(1, np.zeros((20000, 3)))  # more than a pipe holds
time.sleep(0.5)
"""


def test_process_exits_while_its_backend_worker_is_behind() -> None:
    """A run whose back-end worker is far behind still exits (the full scale bench hung at exit).

    At exit the daemon worker is terminated, then multiprocessing joined the inbox's feeder thread,
    which was blocked writing into the full pipe for ever.
    """
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", _BEHIND_WORKER], timeout=120, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]


def test_keyframe_update_waits_for_its_loop() -> None:
    """``local_defer_keyframe`` (issue 33 item 5, isam12): one iSAM2 update a keyframe, a loop keyframe's too.

    The keyframe's own update waits for the calls after it (the loop's late observations and prior)
    and runs with them at the next estimate; the loop keyframes' live error and the final accuracy
    as with two updates.
    """
    upd_kf, looped, factors_kf, live_kf, final_kf = _feed_late(True, defer_keyframe=True)
    upd, _, factors, live, final = _feed_late(True)
    assert sum(looped[15:]) == 6
    assert upd_kf == [1] * len(upd_kf), upd_kf  # counted, not timed: 1 + loop without
    # measured: the third round's loop keyframes right after their loops 4.08 / 4.21 mm, final ATE 1.75 / 1.83 mm
    assert upd[15:] == [1 + lp for lp in looped[15:]], upd
    assert abs(factors_kf - factors) < 0.01 * factors, (factors, factors_kf)
    assert live_kf < 1.1 * live + 1e-4, (live, live_kf)
    assert final_kf < 1.05 * final + 1e-5, (final, final_kf)


def _feed_rebuild(rebuild_kf: int) -> tuple[Isam2Backend, list[int], list[float], int]:
    """4 rounds with revisits and loops under ``local``, iSAM2 rebuilt every ``rebuild_kf`` keyframes (0: never).

    The variables in iSAM2 after each keyframe, the live error (m) of each keyframe right after its
    update, the landmarks of ``estimate(landmarks=True)`` at the end; the back end before its final estimate.
    """
    prob = rounds_problem(60, per_round=15, features_per_kf=60, local_map_kf=1, loop_every_kf=5, revisit_points=40)
    loops = _loops_by_query(prob)
    config = BackendConfig(loop_policy="local", local_rebuild_kf=rebuild_kf, local_rebuild_keep_kf=10)
    backend = Isam2Backend(_calibration(), config)
    sizes, live = [], []
    for kf in prob.keyframes:
        backend.add_keyframe(kf)
        for old, rel in loops.get(kf.id, []):
            backend.add_loop_constraint(kf.id, old, rel)
        est = backend.estimate(landmarks=False).world_from_kf
        sizes.append(backend._isam.getLinearizationPoint().size())
        live.append(float(np.linalg.norm(est[kf.id][:3, 3] - prob.true_world_from_kf[kf.id][:3, 3])))
    return backend, sizes, live, int(backend.estimate(landmarks=True).landmark_ids.size)


def test_window_rebuild_bounds_isam2_and_everything_joins_at_the_end() -> None:
    """``local_rebuild_kf`` (issue 33 item 5, isam12): iSAM2 holds a bounded window; the final estimate all.

    Rebuilt every 10 keyframes on the newest 10, iSAM2's variables stay at what the second round
    held while without they grow with the map; the landmarks, the factors of the final estimate and
    its accuracy as without; a late observation by a keyframe the rebuild left out brings it back.
    """
    from gtsam.symbol_shorthand import X

    from loopmodel.config import RefineConfig

    off, sizes_off, live_off, lms_off = _feed_rebuild(0)
    on, sizes_on, live_on, lms_on = _feed_rebuild(10)
    assert on.window_rebuilds == 4 and off.window_rebuilds == 0
    assert sizes_off[-1] > 1.8 * sizes_off[29], sizes_off  # the map grows
    assert max(sizes_on[-15:]) < 1.2 * max(sizes_on[15:30]), sizes_on  # iSAM2's window does not
    assert sizes_on[-1] < 0.6 * sizes_off[-1]
    # estimate(landmarks=True) still gives the left-out landmarks (landmark creation gates at the pose
    # estimates of the moment: measured 3253 / 3246 landmarks)
    assert lms_on == on.num_landmarks and lms_off == off.num_landmarks
    assert abs(lms_on - lms_off) < 0.01 * lms_off, (lms_off, lms_on)
    # the live error of the last round's keyframes (measured 8.2 mm without, 7.8 mm with; iSAM2 4931 / 1783 variables)
    rms_off, rms_on = (float(np.sqrt(np.mean(np.square(v[45:])))) for v in (live_off, live_on))
    assert rms_on < 1.25 * rms_off + 1e-4, (rms_off, rms_on)
    # a late observation by keyframe 5 (left out since the first rebuild) of keyframe 6's points
    prob = rounds_problem(60, per_round=15, features_per_kf=60, local_map_kf=1, loop_every_kf=5, revisit_points=40)
    kf6 = prob.keyframes[6]
    T5, T6 = prob.true_world_from_kf[5], prob.true_world_from_kf[6]
    p = np.asarray(kf6.points_in_kf, float) @ T6[:3, :3].T + T6[:3, 3]
    q = (p - T5[:3, 3]) @ T5[:3, :3]
    uv = q[:, :2] / q[:, 2:3] * 500.0 + np.array([319.5, 239.5])
    inside = (q[:, 2] > 0) & (uv[:, 0] > 0) & (uv[:, 0] < 640) & (uv[:, 1] > 0) & (uv[:, 1] < 480)
    rows = np.column_stack([np.asarray(kf6.landmark_ids)[inside], uv[inside]])[:10]
    assert rows.shape[0] >= 5
    assert not on._isam.valueExists(X(5))
    assert on.add_observations(5, rows).new_factors == rows.shape[0]
    on.estimate(landmarks=True)  # runs the update the late observations wait for (local_defer_late)
    assert on._isam.valueExists(X(5))
    off.add_observations(5, rows)
    truth = np.array([T[:3, 3] for T in prob.true_world_from_kf])
    finals = [b.final_estimate(RefineConfig(batch_ba=False, distribute_loops=False)) for b in (off, on)]
    # the holds dropped, every observation and loop joined (as many as in the back end without rebuilds)
    assert abs(on.num_factors - off.num_factors) < 0.01 * off.num_factors, (off.num_factors, on.num_factors)
    assert not [r for r in on._factors.values() if r.kind == "proxy"]
    ate_off, ate_on = (_ate_m(f.world_from_kf, truth) for f in finals)
    assert ate_on < 1.05 * ate_off + 1e-5, (ate_off, ate_on)


def _feed_loop_after(defer_loop: bool) -> tuple[list[int], list[int], list[int], float, float]:
    """3 rounds with revisits; each loop found after its keyframe's estimate, as the loop worker finds them.

    Per keyframe: ``add_keyframe`` and an estimate, then (a loop keyframe) the loop's late observations,
    its constraint and an estimate. Returns the iSAM2 updates each keyframe's estimate and each loop's
    estimate ran, the loop flags, the live error (m, RMS over the third round) of each keyframe after a
    loop keyframe right after its own estimate (the live end the loop corrected), the final ATE (m).
    """
    import dataclasses

    from loopmodel.config import RefineConfig

    prob = rounds_problem(45, per_round=15, features_per_kf=60, local_map_kf=1, loop_every_kf=5, revisit_points=40)
    loops = _loops_by_query(prob)
    config = BackendConfig(loop_policy="local", local_defer_loop=defer_loop, local_rebuild_kf=0)
    backend = Isam2Backend(_calibration(), config)
    counter = _CountingIsam2(backend._isam)
    backend._isam = counter
    truth = np.array([T[:3, 3] for T in prob.true_world_from_kf])
    kf_updates, loop_updates, looped, live = [], [], [], []
    for kf in prob.keyframes:
        mono = np.asarray(kf.mono_obs, float).reshape(-1, 3)
        half = mono.shape[0] // 2
        n0 = counter.updates
        backend.add_keyframe(dataclasses.replace(kf, mono_obs=mono[:half]))
        est = backend.estimate(landmarks=False).world_from_kf
        kf_updates.append(counter.updates - n0)
        if kf.id - 1 in loops and kf.id >= 30:
            live.append(float(np.linalg.norm(est[kf.id][:3, 3] - truth[kf.id])))
        n0 = counter.updates
        backend.add_observations(kf.id, mono[half:])
        for old, rel in loops.get(kf.id, []):
            backend.add_loop_constraint(kf.id, old, rel)
        backend.estimate(landmarks=False)
        loop_updates.append(counter.updates - n0)
        looped.append(int(kf.id in loops))
    final = backend.final_estimate(RefineConfig(batch_ba=False, distribute_loops=False))
    rms = float(np.sqrt(np.mean(np.square(live))))
    return kf_updates, loop_updates, looped, rms, _ate_m(final.world_from_kf, truth)


def test_loop_found_after_its_keyframe_joins_the_next_keyframes_update() -> None:
    """``local_defer_loop`` (issue 33 item 5, be15): one iSAM2 update a keyframe, a loop found late too.

    The loop worker's loops arrive after their keyframe's estimate: without the option each brought
    a second update (its late observations and prior); with it they wait for the next keyframe's
    update, which corrects the live end one keyframe later. Counted, not timed.
    """
    kf_on, loop_on, looped, live_on, final_on = _feed_loop_after(True)
    kf_off, loop_off, _, live_off, final_off = _feed_loop_after(False)
    assert sum(looped[15:]) == 6
    assert kf_off == [1] * len(kf_off) and kf_on == [1] * len(kf_on), (kf_off, kf_on)
    assert loop_off[1:] == [1] * (len(loop_off) - 1), loop_off  # late observations (and a loop): one more update
    assert loop_on == [0] * len(loop_on), loop_on  # nothing runs until the next keyframe
    # measured: the keyframes after the third round's loop keyframes 5.30 mm without, 5.14 mm with;
    # final ATE 1.86 / 1.80 mm
    assert live_on < 1.2 * live_off + 1e-4, (live_off, live_on)
    assert final_on < 1.05 * final_off + 1e-5, (final_off, final_on)


def test_estimate_reads_a_keyframe_the_rebuild_left_out_once() -> None:
    """be18: a keyframe a window rebuild left out of iSAM2 does not move until the final estimate.

    ``estimate(landmarks=False)`` reads it once after it left, never in turn; the poses it returns
    are the left-out values (what reading every pose, ``estimate_window_kf: 0``, returns).
    """
    from gtsam.symbol_shorthand import X

    prob = rounds_problem(60, per_round=15, features_per_kf=60, local_map_kf=1, loop_every_kf=5, revisit_points=40)
    loops = _loops_by_query(prob)
    backends = [
        Isam2Backend(_calibration(), BackendConfig(loop_policy="local", local_rebuild_kf=10, estimate_window_kf=n))
        for n in (5, 0)
    ]
    reads: dict[int, int] = {}
    part = backends[0]
    keys_of = part._estimate_keys

    def counted() -> list[int]:
        ids = keys_of()
        for k in ids:
            if X(k) in part._frozen_keys:
                reads[k] = reads.get(k, 0) + 1
        return ids

    part._estimate_keys = counted  # type: ignore[method-assign]
    for kf in prob.keyframes:
        ests = []
        for b in backends:
            b.add_keyframe(kf)
            for old, rel in loops.get(kf.id, []):
                b.add_loop_constraint(kf.id, old, rel)
            ests.append(b.estimate(landmarks=False).world_from_kf)
        got, ref = ests
        for k in got:
            if X(k) in part._frozen_keys:
                np.testing.assert_array_equal(got[k], part._frozen.atPose3(X(k)).matrix())
                np.testing.assert_allclose(got[k], ref[k], atol=1e-12)
    assert part.window_rebuilds == 4
    frozen = [k for k in got if X(k) in part._frozen_keys]
    assert len(frozen) >= 30, len(frozen)
    assert reads and max(reads.values()) == 1, reads  # once each, not in turn


def _relinearised_poses(fraction: float) -> tuple[list[tuple[float, set[int], set[int]]], float]:
    """Each iSAM2 update of 4 revisiting rounds with ``relinearize_group_fraction`` ``fraction``.

    Per update: the largest pose step before it over the thresholds, the poses above ``fraction`` of them,
    and the poses whose linearisation point the update moved (iSAM2's own record); the online ATE (m).
    """
    n = 60
    prob = rounds_problem(n, features_per_kf=100, local_map_kf=2, loop_every_kf=6, revisit_points=150)
    loops = _loops_by_query(prob)
    cfg = BackendConfig(relinearize_group_fraction=fraction)
    backend = Isam2Backend(_calibration(), cfg)
    seen: list[tuple[float, set[int], set[int]]] = []
    update = backend._isam_update

    def spy(*args: object, **kwargs: object) -> object:
        isam = backend._isam
        delta, lin = isam.getDelta(), gtsam.Values(isam.getLinearizationPoint())  # copies: iSAM2 updates them
        keys = [k for k in (backend._xkey[kf] for kf in backend._kf_order) if delta.exists(k)]
        ratio = {
            k: max(np.abs(delta.at(k)[:3]).max() / cfg.relinearize_threshold_rad,
                   np.abs(delta.at(k)[3:]).max() / cfg.relinearize_threshold_m)
            for k in keys
        }
        result = update(*args, **kwargs)
        after = backend._isam.getLinearizationPoint()
        if backend._isam is isam and keys:
            moved = {k for k in keys if not lin.atPose3(k).equals(after.atPose3(k), 1e-12)}
            seen.append((max(ratio.values()), {k for k, r in ratio.items() if r > fraction}, moved))
        return result

    backend._isam_update = spy  # type: ignore[method-assign]
    for kf in prob.keyframes:
        backend.add_keyframe(kf)
        for old, rel in loops.get(kf.id, []):
            backend.add_loop_constraint(kf.id, old, rel)
        backend.estimate(landmarks=False)
    truth = np.array([T[:3, 3] for T in prob.true_world_from_kf])
    return seen, _ate_m(backend.estimate(landmarks=False).world_from_kf, truth)


def test_relinearize_group_fraction_relinearises_the_near_threshold_poses_together() -> None:
    """be20 (issue 33): once one pose's step crosses the thresholds, every pose above the fraction follows it.

    While none crosses, none relinearises (as without grouping); then more of them at once; the online
    estimate stays as accurate.
    """
    grouped, ate_grouped = _relinearised_poses(0.7)
    single, ate_single = _relinearised_poses(1.0)
    for top, above, moved in grouped:
        assert not moved or top > 1.0  # nothing relinearises before one pose crosses the full thresholds
        assert not moved or moved == above  # then every pose above the fraction at once
    crossings = [moved for _, _, moved in grouped if moved]
    alone = [moved for _, _, moved in single if moved]
    assert all(top > 1.0 and moved == above for top, above, moved in single if moved)  # without: those over 1
    # measured (seed 0): 17 relinearising updates, 3.5 poses each, against 16 with 2.25 (the synthetic steps
    # cross every few updates); online ATE 3.33 against 3.52 mm
    assert max(len(m) for m in crossings) >= 4
    assert sum(map(len, crossings)) / len(crossings) > 1.3 * sum(map(len, alone)) / len(alone)
    assert ate_grouped < ate_single * 1.05


def _relinearising_updates(rebuild_skip: int) -> tuple[Isam2Backend, list[tuple[int, int, int]], float]:
    """4 revisiting rounds under ``local`` rebuilt every 10 keyframes, ``local_rebuild_relinearize_skip`` given.

    Per iSAM2 update: the window rebuilds before it, its number in its iSAM2, the variables it
    relinearised; the live error (RMS, m) of the last two rounds' keyframes right after their updates.
    """
    prob = rounds_problem(60, per_round=15, features_per_kf=60, local_map_kf=1, loop_every_kf=5, revisit_points=40)
    loops = _loops_by_query(prob)
    config = BackendConfig(
        loop_policy="local", local_rebuild_kf=10, local_rebuild_keep_kf=10, local_rebuild_relinearize_skip=rebuild_skip
    )
    backend = Isam2Backend(_calibration(), config)
    seen: list[tuple[int, int, int]] = []
    update = backend._isam_update

    def spy(*args: object, **kwargs: object) -> object:
        result = update(*args, **kwargs)
        seen.append((backend.window_rebuilds, backend._isam_updates, result.getVariablesRelinearized()))
        return result

    backend._isam_update = spy  # type: ignore[method-assign]
    live = []
    for kf in prob.keyframes:
        backend.add_keyframe(kf)
        for old, rel in loops.get(kf.id, []):
            backend.add_loop_constraint(kf.id, old, rel)
        est = backend.estimate(landmarks=False).world_from_kf
        live.append(float(np.linalg.norm(est[kf.id][:3, 3] - prob.true_world_from_kf[kf.id][:3, 3])))
    return backend, seen, float(np.sqrt(np.mean(np.square(live[30:]))))


def test_rebuilt_window_checks_relinearisation_at_its_own_cadence() -> None:
    """be21 (issue 33): a window rebuild's iSAM2 relinearises every ``local_rebuild_relinearize_skip``-th update.

    Before the first rebuild every ``relinearize_skip``-th (2) as without; after it only every 4th (0: every
    2nd throughout); the live error of the last two rounds as without.
    """
    at4, seen4, live4 = _relinearising_updates(4)
    at2, seen2, live2 = _relinearising_updates(0)
    assert at4.window_rebuilds == at2.window_rebuilds == 4
    for seen in (seen4, seen2):  # before the first rebuild: at updates 2, 4, 6, ... of the first iSAM2
        first = [n for rebuilds, n, relin in seen if rebuilds == 0 and relin]
        assert first and all(n % 2 == 0 for n in first) and any(n % 4 == 2 for n in first), first
    later4 = [n for rebuilds, n, relin in seen4 if rebuilds > 0 and relin]
    later2 = [n for rebuilds, n, relin in seen2 if rebuilds > 0 and relin]
    assert later4 and all(n % 4 == 0 for n in later4), later4
    assert any(n % 4 == 2 for n in later2), later2  # with 0 the rebuilt iSAM2s keep relinearize_skip's cadence
    assert len(later4) < len(later2)
    assert live4 < 1.1 * live2 + 1e-4, (live2, live4)


def test_rebuilt_window_relinearises_only_at_rebuilds_by_default() -> None:
    """be23b (issue 33): with ``local_rebuild_relinearize_skip`` -1 (the default) a rebuilt iSAM2 never relinearises.

    Before the first rebuild every ``relinearize_skip``-th update does, as with 4; after it no update
    relinearises until the next rebuild takes the window at its estimate; the live error of the last
    two rounds as with 4; a forced relinearisation (:meth:`Isam2Backend.refine`) still relinearises.
    """
    assert BackendConfig().local_rebuild_relinearize_skip == -1
    never, seen, live = _relinearising_updates(-1)
    _, seen4, live4 = _relinearising_updates(4)
    assert never.window_rebuilds == 4
    first = [n for rebuilds, n, relin in seen if rebuilds == 0 and relin]
    assert first == [n for rebuilds, n, relin in seen4 if rebuilds == 0 and relin], first
    assert [n for rebuilds, n, relin in seen if rebuilds > 0 and relin] == []
    assert [n for rebuilds, n, relin in seen4 if rebuilds > 0 and relin]  # 4 relinearised there
    assert live < 1.1 * live4 + 1e-4, (live4, live)
    never.refine(max_iterations=1)
    assert seen[-1][2] > 0, seen[-1]
