"""Incremental keyframe/landmark estimation with GTSAM iSAM2.

Variables: ``X(kf_id)`` keyframe poses (``world_from_kf`` of the left camera, metres) and
``L(j)`` landmarks (world frame, metres; ``j`` is an internal index, see
``max_landmark_span_kf``). Stereo observations become ``GenericStereoFactor3D`` with
``Cal3_S2Stereo``, monocular ones ``GenericProjectionFactorCal3_S2``; both with a Huber
M-estimator. The first keyframe carries a tight prior that fixes the gauge.

Each update hands iSAM2 only the new factors and values. What keeps updates cheap:

* a landmark enters the graph only once it was observed ``min_observations`` times (a
  landmark seen once adds no information on the poses); it is initialised from its
  stereo triangulation with the largest disparity, and its observations are gated
  against that initial point;
* stereo observations with a disparity under ``min_disparity_px`` are dropped (these
  near-infinite points make the linear system indeterminate, see below);
* elimination groups put the newest poses last in chronological order (landmarks and
  older poses first), so COLAMD ties cannot drag old poses and landmarks into the root
  clique after a relinearisation;
* optionally (``max_landmark_span_kf``) a long track continues in a fresh landmark
  variable, bounding the band of the pose graph and thereby the root clique;
* per-type relinearisation thresholds (poses vs landmarks);
* optionally (``loop_policy: local``) a local problem: an observation of a landmark older than
  ``local_window_kf`` keyframes goes to a proxy variable ``P(i)`` fixed by a prior at the
  landmark's estimate, and the real observation and the loop constraints join only for the final
  estimate (:meth:`Isam2Backend._merge_outside`), so no update reaches into the old map.

An ``IndeterminateSystemException`` (GTSAM raises it as ``RuntimeError`` naming the
variable) leaves iSAM2's Bayes tree half-updated, so the back end rebuilds iSAM2 from its
own record of live factors, without the offending landmark, and continues.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Literal

import gtsam
import numpy as np
import numpy.ma  # noqa: F401 - see below
from gtsam.symbol_shorthand import L, P, X
from numpy.typing import NDArray

from loopmodel.backend.base import F64, BackendEstimate, BackendUpdate, Observation

# fin19 (issue 32): the final estimate's modules loaded with this one (in the back-end worker, at its start),
# not in the final estimate the run waits for: the loop distribution, its pose graph, and numpy.ma, which
# np.unique imports at its first call (numpy 2.4: np.ma.is_masked). They took 0.05 s CPU there, 0.15 s at
# load 7, without bytecode (PYTHONDONTWRITEBYTECODE, as this machine's shells)
from loopmodel.backend.loop_distribution import distribute_loop_errors
from loopmodel.config import BackendConfig, RefineConfig
from loopmodel.errors import EstimationError, InputError
from loopmodel.geometry.se3 import invert_pose
from loopmodel.types import Keyframe, StereoCalibration

logger = logging.getLogger(__name__)

_SYMBOL_RE = re.compile(r"Symbol:\s*([A-Za-z])(\d+)")
_INDEX_MASK = np.uint64((1 << 56) - 1)
_EYE4 = np.eye(4)
_X_CHAR = ord("x")
_L_KEY = ord("l") << 56  # gtsam's L(j) is _L_KEY | j (a Symbol's character in the top 8 bits)
#: keyframe_obs_budget: the grid (columns, rows) over the image its observations are spread on
_BUDGET_GRID = (8, 4)


@dataclass(slots=True)
class _Obs:
    """One buffered or live observation of a landmark."""

    kf_id: int
    stereo: bool
    px: tuple[float, ...]  # (u_l, u_r, v) or (u, v), rectified pixels
    point_in_kf: F64 | None  # stereo triangulation in the keyframe's left camera (m)


FactorKind = Literal["stereo", "mono", "prior", "loop", "proxy"]


@dataclass(slots=True)
class _FactorRecord:
    made: gtsam.NonlinearFactor | None  # the factor, or None until :attr:`factor` is first read
    kind: FactorKind
    lkey: int = -1  # internal landmark index, or -1
    obs: Observation | None = None
    build: Callable[[], gtsam.NonlinearFactor] | None = None  # makes ``made`` on first use
    key_tuple: tuple[int, ...] | None = None  # the factor's gtsam keys, once known

    @property
    def factor(self) -> gtsam.NonlinearFactor:
        """The factor; one waiting outside iSAM2 is made when first needed (its final estimate, be16)."""
        if self.made is None:
            assert self.build is not None
            self.made, self.build = self.build(), None
        return self.made

    def keys(self) -> tuple[int, ...]:
        """The factor's gtsam keys (an observation's are known when it is recorded: no call into GTSAM, be17)."""
        if self.key_tuple is None:
            self.key_tuple = tuple(self.factor.keys())
        return self.key_tuple


@dataclass
class _Landmark:
    landmark_id: int
    first_seq: int  # keyframe sequence number of the first observation in the graph
    fids: set[int] = field(default_factory=set)
    in_isam: int = 0  # its observations that went into iSAM2 (keyframe_obs_redundant_kf)


def _is_pose_key(key: int) -> bool:
    """Whether gtsam key ``key`` is a keyframe pose ``X(i)``."""
    return key >> 56 == _X_CHAR


def _is_identity(T: F64) -> bool:
    return bool(np.allclose(T, np.eye(4), atol=1e-12))


class Isam2Backend:
    """The iSAM2 back end (implements :class:`loopmodel.backend.Backend`).

    ``calibration`` is the rectified stereo calibration in which the keyframes' pixel
    observations are expressed (``FrontEnd.calibration``); ``K_left`` and ``baseline_m``
    are used.
    """

    def __init__(self, calibration: StereoCalibration, config: BackendConfig | None = None) -> None:
        self.config = config or BackendConfig()
        cfg = self.config
        K = calibration.K_left
        fx, fy, skew, cx, cy = (
            float(K[0, 0]),
            float(K[1, 1]),
            float(K[0, 1]),
            float(K[0, 2]),
            float(K[1, 2]),
        )
        self._K = np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        self._baseline_m = calibration.baseline_m
        self._image_size = calibration.image_size  # (width, height) px
        self._cal_stereo = gtsam.Cal3_S2Stereo(fx, fy, skew, cx, cy, self._baseline_m)
        self._cal_mono = gtsam.Cal3_S2(fx, fy, skew, cx, cy)
        self._stereo_noise = self._robust(gtsam.noiseModel.Isotropic.Sigma(3, cfg.pixel_sigma_px))
        self._mono_noise = self._robust(gtsam.noiseModel.Isotropic.Sigma(2, cfg.pixel_sigma_px))
        self._isam = gtsam.ISAM2(self.isam2_params(cfg))
        self._isam_updates = 0  # iSAM2's own count: it checks relinearisation every _relinearize_skip-th
        self._relinearize_skip = cfg.relinearize_skip  # this iSAM2's (local_rebuild_relinearize_skip after a rebuild)
        self._factors: dict[int, _FactorRecord] = {}
        self._slot: dict[int, int] = {}  # factor id -> iSAM2 factor index
        self._next_fid = 0
        self._batch: list[int] = []  # factor ids recorded since the last iSAM2 update
        self._obs_fid: dict[Observation, int] = {}
        self._landmarks: dict[int, _Landmark] = {}  # internal index -> landmark
        self._lm_current: dict[int, int] = {}  # landmark id -> internal index in the graph
        # internal index -> its landmark's first_seq (_Landmark.first_seq as an array: a keyframe's rows are
        # told revisits by one array lookup, be21)
        self._lm_first_seq = np.zeros(1024, dtype=np.int64)
        self._next_lkey = 0
        self._pending: dict[int, list[_Obs]] = {}
        self._pending_buckets: dict[int, list[int]] = {}  # keyframe seq -> pending landmark ids
        self._kf_seq: dict[int, int] = {}
        self._xkey: dict[int, int] = {}  # kf id -> X(kf id)
        self._kf_order: list[int] = []
        self._pose_guess: dict[int, F64] = {}
        self._body: dict[int, F64] = {}  # kf id -> rect_from_cam
        self._body_pose: dict[int, tuple[gtsam.Pose3, ...]] = {}  # kf id -> (body_P_sensor,) for factors
        self._last_poses: dict[int, F64] = {}
        # estimate(landmarks=False) reads the newest poses and older ones in turn (_estimate_keys)
        self._estimate_all = True
        self._estimated_kfs = 0
        self._estimate_turn = 0
        self._theta0 = gtsam.Values()  # every variable's initial value
        self.rebuilds = 0
        self.last_result: gtsam.ISAM2Result | None = None
        #: noise and outcome of the last :meth:`batch_refine` (for metrics.json)
        self.refine_info: dict[str, Any] = {}
        self._links: list[tuple[int, int]] = []  # (previous keyframe, keyframe) tracked links
        # the front end's robust pose-residual scale per keyframe interval (px)
        self._frontend_sigma_px: list[float] = []
        self.dropped_landmarks = 0
        # issue 36: the disparity offset the front end took out of each keyframe's right columns
        # (px, kf id -> offset) and its latest estimate (frontend.disparity_offset: estimate)
        self._kf_offset_px: dict[int, float] = {}
        self._offset_estimate_px: float | None = None
        # issue 33 item 5, loop_policy local: factor ids kept out of iSAM2 (observations of
        # landmarks older than the local window, loop constraints) until the final estimate
        self._windowed = cfg.loop_policy == "local"
        self._outside: set[int] = set()
        # a revisited landmark is seen in iSAM2 through a proxy P(i) held by a prior at its estimate
        # (internal landmark index -> (proxy index, keyframe seq it was made at)); real fid -> proxy fids
        self._proxy: dict[int, tuple[int, int]] = {}
        self._proxy_fids: dict[int, list[int]] = {}
        self._next_pkey = 0
        self._new_proxies = gtsam.Values()
        self._proxy_noise = gtsam.noiseModel.Isotropic.Sigma(3, cfg.loop_sigma_m)  # every proxy's prior
        # keyframe_obs_budget: observations of known landmarks each keyframe's updates took so far
        self._budget_used: dict[int, int] = {}
        # a keyframe whose tracker resumed an older keyframe's features (``ba_info["resumed_from_keyframe"]``)
        # -> that keyframe's seq: its landmarks' observations tie the keyframe to the old map (never over the budget)
        self._resumed_seq: dict[int, int] = {}
        self.budget_dropped = 0  # observations over the budget left out (keyframe_obs_overflow drop)
        # local_proxies_per_kf: old landmarks each keyframe sees through proxies so far; those left out
        self._proxies_used: dict[int, int] = {}
        self.proxies_skipped = 0
        # local_defer_late: late observations (a loop's) wait for the next update (the loop prior's)
        self._defer_late = self._windowed and cfg.local_defer_late and cfg.blunder_sigma <= 0
        self._deferred_graph = gtsam.NonlinearFactorGraph()
        self._deferred_values = gtsam.Values()
        self._deferred_fids: list[int] = []
        self._deferred_all = False  # a deferred update may move more than the window
        # local_defer_keyframe: a keyframe's own update waits for the next one (its loop's) or an estimate
        self._defer_kf = self._defer_late and cfg.local_defer_keyframe
        self._kf_waiting = False  # a keyframe's update waits (at most one: the next keyframe runs it first)
        # local_defer_loop: a loop's prior (and its late observations) wait for the next keyframe's update
        self._defer_loop = self._defer_kf and cfg.local_defer_loop
        self._updated = True  # an iSAM2 update ran since the last estimate()
        # local_rebuild_kf: the variables a rebuild left out of iSAM2, at their estimate (keys disjoint
        # from iSAM2's); the gauge-tight priors holding the older keyframes a rebuild kept (factor ids)
        self._frozen = gtsam.Values()
        self._frozen_keys: set[int] = set()
        self._frozen_kfs: set[int] = set()  # the keyframes whose poses are in _frozen_keys (be21)
        self._fixed_fids: list[int] = []
        self._rebuilt_at = 0  # keyframes in the graph at the last rebuild
        self._frozen_unread: list[int] = []  # keyframes a rebuild left out, not read by estimate() since
        self.window_rebuilds = 0

    # ------------------------------------------------------------------ set-up
    @staticmethod
    def isam2_params(cfg: BackendConfig, relinearize_skip: int = 0) -> gtsam.ISAM2Params:
        """``gtsam.ISAM2Params`` from the configuration; ``relinearize_skip`` > 0 instead of the configured one.

        ``relinearize_skip`` < 0: no relinearisation but a forced one (a window rebuild's iSAM2 waits for the next).
        """
        params = gtsam.ISAM2Params()
        thresholds = gtsam.ISAM2ThresholdMap()
        # relinearize_group_fraction < 1: iSAM2 checks poses at that fraction of the thresholds and
        # _isam_update holds them there until one crosses the full ones (_poses_held)
        f = cfg.relinearize_group_fraction
        thresholds.insert(("x", f * np.array([cfg.relinearize_threshold_rad] * 3 + [cfg.relinearize_threshold_m] * 3)))
        thresholds.insert(("l", np.full(3, cfg.relinearize_threshold_landmark_m)))
        thresholds.insert(("p", np.full(3, cfg.relinearize_threshold_landmark_m)))  # proxies of old landmarks
        params.setRelinearizeThreshold(thresholds)
        params.relinearizeSkip = max(relinearize_skip or cfg.relinearize_skip, 1)
        params.enableRelinearization = relinearize_skip >= 0
        params.enablePartialRelinearizationCheck = cfg.partial_relinearization_check
        params.setFactorization(cfg.factorization)
        gn = gtsam.ISAM2GaussNewtonParams()
        gn.setWildfireThreshold(cfg.wildfire_threshold)
        params.setOptimizationParams(gn)
        return params

    def _robust(self, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
        if self.config.huber_k <= 0:
            return base
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(self.config.huber_k), base)

    # ------------------------------------------------------------------ queries
    @property
    def keyframe_ids(self) -> list[int]:
        """Ids of the keyframes in the graph, in insertion order."""
        return list(self._kf_seq)

    @property
    def num_factors(self) -> int:
        """Live factors in the graph."""
        return len(self._factors)

    def factor_graph(self) -> gtsam.NonlinearFactorGraph:
        """A copy of every live factor (for batch comparison)."""
        graph = gtsam.NonlinearFactorGraph()
        for fid in sorted(self._factors):
            graph.add(self._factors[fid].factor)
        return graph

    @property
    def num_observations(self) -> int:
        """Observation factors in the graph."""
        return len(self._obs_fid)

    @property
    def num_landmarks(self) -> int:
        """Landmark variables in the graph."""
        return len(self._landmarks)

    def initial_values(self) -> gtsam.Values:
        """Initial values of the variables still in the graph (for a batch solution)."""
        keys: set[int] = set()
        for rec in self._factors.values():
            keys.update(rec.keys())
        out = gtsam.Values()
        for key in keys:
            if gtsam.Symbol(key).chr() == ord("x"):
                out.insert(key, self._theta0.atPose3(key))
            else:
                out.insert(key, self._theta0.atPoint3(key))
        return out

    def values(self) -> gtsam.Values:
        """The current iSAM2 estimate of every variable (``gtsam.Values``)."""
        self._flush_deferred()
        return self._current_values()

    def observation_factor_index(self, observation: Observation) -> int | None:
        """iSAM2 factor index of an observation ``(keyframe_id, landmark_id)`` in the graph."""
        fid = self._obs_fid.get(observation)
        return None if fid is None else self._slot.get(fid)

    # ------------------------------------------------------------------ factors
    def _new_fid(self, rec: _FactorRecord, outside: bool = False) -> int:
        """Record a factor for the next iSAM2 update, or ``outside`` it until :meth:`_merge_outside`."""
        fid = self._next_fid
        self._next_fid += 1
        self._factors[fid] = rec
        (self._outside.add if outside else self._batch.append)(fid)
        return fid

    def _obs_factor(self, obs: _Obs, landmark_key: int) -> gtsam.NonlinearFactor:
        """The factor of observation ``obs`` of the landmark variable ``landmark_key`` (a gtsam key)."""
        extra = self._body_pose.get(obs.kf_id, ())
        px = obs.px
        pose_key = self._xkey[obs.kf_id]  # X(kf_id), made once a keyframe (be17)
        if obs.stereo:
            sp = gtsam.StereoPoint2(px[0], px[1], px[2])
            return gtsam.GenericStereoFactor3D(sp, self._stereo_noise, pose_key, landmark_key, self._cal_stereo, *extra)
        return gtsam.GenericProjectionFactorCal3_S2(
            np.array(px[:2]), self._mono_noise, pose_key, landmark_key, self._cal_mono, *extra
        )

    def _add_obs(
        self, obs: _Obs, lkey: int, lm_id: int, graph: gtsam.NonlinearFactorGraph, outside: bool = False
    ) -> None:
        key = (obs.kf_id, lm_id)
        obs_fid = self._obs_fid
        if key in obs_fid:  # the same observation twice: keep the first
            return
        lm = self._landmarks[lkey]
        kind: FactorKind = "stereo" if obs.stereo else "mono"
        # a revisit: it sees the landmark after the local window (loop_policy local: through a proxy). Such
        # observations (a revisit, a loop's resumed features) tie the keyframe to the old map: the keyframe's
        # budget does not leave them out (be15)
        revisit = not outside and lm.first_seq < self._window_start_seq(obs.kf_id)
        landmark_key = _L_KEY | lkey  # L(lkey), without a gtsam call a row (be23c)
        keys = (self._xkey[obs.kf_id], landmark_key)  # as the factor names them
        if outside or revisit:  # over the keyframe's budget, or a revisit: joins at the final estimate
            # its factor is made then (what waits outside iSAM2 costs the keyframe little, be16)
            build = partial(self._obs_factor, obs, landmark_key)
            fid = self._new_fid(_FactorRecord(None, kind, lkey, key, build, keys), outside=True)
            if revisit and self._proxy_room(obs.kf_id):  # through a proxy: ties the keyframe to the old map
                self._proxy_fids[fid] = self._proxy_observation(obs, lkey, graph)
        else:
            factor = self._obs_factor(obs, landmark_key)
            fid = self._new_fid(_FactorRecord(factor, kind, lkey, key, None, keys))
            graph.add(factor)
            lm.in_isam += 1
        obs_fid[key] = fid
        lm.fids.add(fid)

    def _isam_update(self, *args: Any, **kwargs: Any) -> Any:
        """``self._isam.update(...)``; what :meth:`estimate` reads has changed (``_updated``).

        With ``relinearize_group_fraction`` < 1, at an update that checks relinearisation the poses
        :meth:`_poses_held` names stay at their linearisation point (iSAM2's ``noRelinKeys``).
        """
        self._isam_updates += 1
        skip = self._relinearize_skip
        checks = kwargs.get("force_relinearize", False) or skip > 0 and self._isam_updates % skip == 0
        if checks and self.config.relinearize_group_fraction < 1.0:
            held = self._poses_held()
            if held is not None:
                kwargs["noRelinKeys"] = held
        result = self._isam.update(*args, **kwargs)
        self._updated = True
        return result

    def _poses_held(self) -> gtsam.KeyList | None:
        """The poses iSAM2 must not relinearise at this update (``relinearize_group_fraction``), or None.

        iSAM2 checks poses at the fraction f of ``relinearize_threshold_rad`` / ``_m``. While no pose's
        linear step (iSAM2's delta: rotation rad, translation m, per axis) exceeds the full thresholds,
        every pose above f of them is held: nothing relinearises, as without grouping. Once one does,
        none is held: every pose above f relinearises in this one update, where one at a time each
        would re-eliminate all its landmarks in an update of its own (issue 33, be20).
        """
        delta = self._isam.getDelta()  # iSAM2 brings it up to date before a relinearisation check anyway
        keys = [key for kf in self._kf_order if delta.exists(key := self._xkey[kf])]
        if not keys:
            return None
        cfg = self.config
        step = np.abs(delta.vector(keys)).reshape(-1, 2, 3).max(axis=2)  # per pose: (rotation rad, translation m)
        ratio = np.maximum(step[:, 0] / cfg.relinearize_threshold_rad, step[:, 1] / cfg.relinearize_threshold_m)
        if ratio.max() > 1.0:
            return None
        held = gtsam.KeyList()
        for j in np.flatnonzero(ratio > cfg.relinearize_group_fraction).tolist():
            held.push_back(keys[j])
        return held

    def _new_isam(self, relinearize_skip: int = 0) -> None:
        """An empty iSAM2 with this back end's parameters (a rebuild); :meth:`estimate` reads it anew.

        ``relinearize_skip`` > 0: it checks relinearisation every that many updates (a window rebuild's);
        < 0: never (only when forced: :meth:`refine`).
        """
        self._isam = gtsam.ISAM2(self.isam2_params(self.config, relinearize_skip))
        self._isam_updates = 0  # iSAM2's own count: it checks relinearisation every _relinearize_skip-th
        self._relinearize_skip = relinearize_skip or self.config.relinearize_skip
        self._updated = True

    def _old_map_seq(self, kf_id: int) -> int:
        """Observations of ``kf_id`` of landmarks first seen before this keyframe sequence number tie it to the old map.

        ``keyframe_obs_budget`` never leaves those out: a revisit (:meth:`_add_obs`), or an observation of a
        landmark first seen no later than the keyframe whose features the tracker resumed after a loop (be19: a
        short loop's old features are landmarks of the local window, which the budget would otherwise hold
        back). One number a keyframe (be23c: was a test of two calls a row that waits).
        """
        cut = self._window_start_seq(kf_id)
        resumed = self._resumed_seq.get(kf_id)
        return cut if resumed is None else max(cut, resumed + 1)

    def _window_start_seq(self, kf_id: int) -> int:
        """Landmarks first seen before this keyframe sequence number are older than ``kf_id``'s local window.

        An observation of one is a revisit (``loop_policy`` local: through a proxy); 0 without the window (a
        landmark's ``first_seq`` is >= 0, so none is).
        """
        return self._kf_seq[kf_id] - self.config.local_window_kf if self._windowed else 0

    def _proxy_room(self, kf_id: int) -> bool:
        """Whether keyframe ``kf_id`` may see one more old landmark through a proxy (``local_proxies_per_kf``).

        Counts it if so. Over the bound a revisit's observation only joins at the final estimate.
        """
        bound = self.config.local_proxies_per_kf
        if bound <= 0:
            return True
        used = self._proxies_used.get(kf_id, 0)
        if used >= bound:
            self.proxies_skipped += 1
            return False
        self._proxies_used[kf_id] = used + 1
        return True

    def _revisit_rows(self, kf_id: int, lkeys: NDArray[np.int64]) -> int:
        """How many of the landmarks ``lkeys`` (internal indices, -1: none) ``kf_id`` would see through proxies."""
        if not self._windowed:
            return 0
        cut = self._window_start_seq(kf_id)
        return int(np.count_nonzero(self._lm_first_seq[lkeys[lkeys >= 0]] < cut))

    def _row_lkeys(self, rows: F64) -> NDArray[np.int64]:
        """The internal index of each row's (landmark id, u, v px) landmark in the graph; -1 if none or not finite.

        One dict look-up a row, shared by :meth:`_budget_binds`, :meth:`_proxies_bind` and
        :meth:`_spread_order` (be21: each looked every row up again; the bind test alone took 0.24-0.28 ms a
        keyframe of the rounds scan's last round, 0.05 ms with these).
        """
        finite = np.isfinite(rows[:, 0])
        ids = np.where(finite, rows[:, 0], -1.0).astype(np.int64).tolist()
        current = self._lm_current
        return np.array(
            [current.get(i, -1) if ok else -1 for i, ok in zip(ids, finite.tolist(), strict=True)], dtype=np.int64
        ).reshape(-1)

    def _proxy_observation(self, obs: _Obs, lkey: int, graph: gtsam.NonlinearFactorGraph) -> list[int]:
        """``obs`` of old landmark ``lkey`` as an observation of its proxy in iSAM2; returns the factor ids.

        The proxy is a landmark variable held by a prior of ``loop_sigma_m`` at the landmark's current
        estimate, renewed once older than ``local_window_kf`` keyframes: the old poses and landmarks
        stay out of the update (ORB-SLAM's local BA with the old map fixed).
        """
        seq = self._kf_seq[obs.kf_id]
        fids = []
        entry = self._proxy.get(lkey)
        if entry is None or seq - entry[1] > self.config.local_window_kf:
            entry = (self._next_pkey, seq)
            self._next_pkey += 1
            self._proxy[lkey] = entry
            # a landmark made by a deferred update (local_defer_late) is not in iSAM2 yet: its initial point
            p = self._point_estimate(L(lkey))
            self._new_proxies.insertPoint3(P(entry[0]), p)  # no overload resolution (be17)
            prior = gtsam.PriorFactorPoint3(P(entry[0]), p, self._proxy_noise)
            fids.append(self._new_fid(_FactorRecord(prior, "proxy")))
            graph.add(prior)
        proxy = self._obs_factor(obs, P(entry[0]))
        fids.append(self._new_fid(_FactorRecord(proxy, "proxy")))
        graph.add(proxy)
        return fids

    def _drop_proxy_observation(self, fid: int) -> list[int]:
        """Forget the proxy observation factor of factor ``fid`` (not the proxy's prior); its iSAM2 slots."""
        slots = []
        for pf in self._proxy_fids.pop(fid, []):
            rec = self._factors.get(pf)
            if rec is not None and rec.factor.size() == 2:
                del self._factors[pf]
                slot = self._slot.pop(pf, None)
                if slot is not None:
                    slots.append(slot)
        return slots

    def _project(self, kf_ids: list[int], p_world: F64, poses: dict[int, F64] | None = None) -> F64:
        """Predicted (u_left, u_right, v) rectified pixels of world points ``p_world`` (N, 3).

        In keyframes ``kf_ids`` (N) at ``poses`` (default: the current pose guesses); NaN rows
        behind the camera.
        """
        src = self._pose_guess if poses is None else poses
        # one pose (and body transform) per keyframe, indexed per point
        uniq, inv = np.unique(np.asarray(kf_ids, dtype=np.int64), return_inverse=True)
        T = np.stack([src[k] for k in uniq.tolist()])[inv] if kf_ids else np.zeros((0, 4, 4))
        p = np.einsum("nji,nj->ni", T[:, :3, :3], p_world - T[:, :3, 3])
        if self._body and kf_ids:
            B = np.stack([self._body.get(k, _EYE4) for k in uniq.tolist()])[inv]
            p = np.einsum("nij,nj->ni", B[:, :3, :3], p) + B[:, :3, 3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            zi = np.where(z > 1e-9, 1.0 / z, np.nan)
            K = self._K
            u = (K[0, 0] * p[:, 0] + K[0, 1] * p[:, 1]) * zi + K[0, 2]
            v = K[1, 1] * p[:, 1] * zi + K[1, 2]
            ur = u - K[0, 0] * self._baseline_m * zi
        return np.column_stack([u, ur, v])

    def _triangulate(self, owner: NDArray[np.int64], kf_ids: list[int], meas: F64, p0: F64, iterations: int) -> F64:
        """Gauss-Newton refinement of world points ``p0`` (M, 3) on observations ``meas``.

        Observations are (N, 3: u_left, u_right or NaN for monocular, v) in keyframes ``kf_ids`` at
        their pose guesses; observation ``j`` belongs to point ``owner[j]`` (every point observed).
        A point whose update fails keeps its start value.
        """
        if owner.size and np.any(np.diff(owner) < 0):  # group the observations by point
            order = np.argsort(owner, kind="stable")
            owner, meas = owner[order], meas[order]
            kf_ids = [kf_ids[i] for i in order.tolist()]
        starts = np.flatnonzero(np.r_[True, np.diff(owner) != 0])
        uniq, inv = np.unique(np.asarray(kf_ids), return_inverse=True)
        T = np.stack([self._pose_guess[int(k)] for k in uniq])[inv]
        Rt = np.transpose(T[:, :3, :3], (0, 2, 1))  # cam_from_world rotation
        t = T[:, :3, 3]
        if self._body:
            B = np.stack([self._body.get(int(k), _EYE4) for k in uniq])[inv]
            Rt = B[:, :3, :3] @ Rt
            t_b = B[:, :3, 3]
        else:
            t_b = np.zeros_like(t)
        K = self._K
        fx, skew, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
        fb = fx * self._baseline_m
        mono = ~np.isfinite(meas[:, 1])
        m = p0.shape[0]
        p = p0.copy()
        good = np.ones(m, dtype=bool)
        for _ in range(iterations):
            pc = np.einsum("nij,nj->ni", Rt, p[owner] - t) + t_b
            x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
            front = z > 1e-6
            good &= np.bincount(owner, weights=~front, minlength=m) == 0
            iz = np.where(front, 1.0 / np.where(front, z, 1.0), 0.0)
            u = (fx * x + skew * y) * iz + cx
            v = fy * y * iz + cy
            r = np.column_stack([u - meas[:, 0], u - fb * iz - meas[:, 1], v - meas[:, 2]])
            Jc = np.zeros((len(owner), 3, 3))
            Jc[:, 0] = np.column_stack([fx * iz, skew * iz, -(fx * x + skew * y) * iz * iz])
            Jc[:, 1] = Jc[:, 0]
            Jc[:, 1, 2] += fb * iz * iz
            Jc[:, 2] = np.column_stack([np.zeros_like(z), fy * iz, -fy * y * iz * iz])
            r[mono, 1] = 0.0
            Jc[mono, 1] = 0.0
            J = Jc @ Rt
            # observations of a point are contiguous: sum them per point with reduceat
            H = np.add.reduceat(np.einsum("nki,nkj->nij", J, J), starts, axis=0)
            g = np.add.reduceat(np.einsum("nji,nj->ni", J, r), starts, axis=0)
            H += np.eye(3) * 1e-9
            ok = good & (np.linalg.det(H) > 1e-12)
            dp = np.zeros((m, 3))
            if ok.any():
                dp[ok] = -np.linalg.solve(H[ok], g[ok][:, :, None])[:, :, 0]
            p = p + dp
            good &= np.isfinite(p).all(axis=1)
            p[~good] = p0[~good]
        return p

    @staticmethod
    def _meas_rows(obs: list[_Obs]) -> F64:
        """(u_left, u_right or NaN for monocular, v) rows of observations ``obs`` (N, 3 px)."""
        return np.array([o.px if o.stereo else (o.px[0], np.nan, o.px[1]) for o in obs], dtype=float)

    def _creation_candidates(self, candidates: list[int]) -> list[tuple[int, list[_Obs], _Obs]]:
        """Pending landmarks of ``candidates`` ready to enter: (id, observations, stereo one of largest disparity)."""
        todo = []
        for lm in candidates:
            obs = self._pending.get(lm)
            if obs is None or len(obs) < self.config.min_observations:
                continue
            best = None
            for o in obs:
                if o.stereo and (best is None or o.px[0] - o.px[1] > best.px[0] - best.px[1]):
                    best = o
            if best is not None:
                todo.append((lm, obs, best))
        return todo

    def _gate_initial(self, todo: list[tuple[int, list[_Obs], _Obs]], p_world: F64) -> list[bool]:
        """Which candidates pass the ``init_gate_px`` gate whole at their initial points ``p_world`` (world, m).

        The pending buffer of one that does not keeps only its observations within the gate.
        """
        keep_all = [True] * len(todo)
        gate = self.config.init_gate_px
        if gate <= 0:
            return keep_all
        owner = np.array([i for i, (_, obs, _) in enumerate(todo) for _ in obs])
        flat = [o for _, obs, _ in todo for o in obs]
        pred = self._project([o.kf_id for o in flat], p_world[owner])
        meas = self._meas_rows(flat)
        err = np.abs(pred - meas)
        err[~np.isfinite(meas)] = 0.0
        bad = ~np.isfinite(pred[:, [0, 2]]).all(axis=1) | (err.max(axis=1) > gate)
        if not bad.any():
            return keep_all
        for j in np.flatnonzero(bad).tolist():
            keep_all[int(owner[j])] = False
        start = 0
        for i, (lm, obs, _) in enumerate(todo):
            n = len(obs)
            if not keep_all[i]:
                self._pending[lm] = [o for o, b in zip(obs, bad[start : start + n].tolist(), strict=True) if not b]
            start += n
        return keep_all

    def _regated(self, lm: int) -> tuple[list[_Obs], F64] | None:
        """A gated candidate's surviving observations and its new initial point (world, m), if it still qualifies.

        Its best triangulation may have changed; every survivor must lie within the gate of it.
        """
        cfg = self.config
        kept = self._pending[lm]
        if len(kept) < cfg.min_observations or not any(o.stereo for o in kept):
            return None
        b = max((o for o in kept if o.stereo), key=lambda o: o.px[0] - o.px[1])
        Tb = self._pose_guess[b.kf_id]
        assert b.point_in_kf is not None
        pw = Tb[:3, :3] @ b.point_in_kf + Tb[:3, 3]
        pr = self._project([o.kf_id for o in kept], np.tile(pw, (len(kept), 1)))
        ok = all(
            np.isfinite(pr[j, 0])
            and max(
                abs(pr[j, 0] - o.px[0]),
                abs(pr[j, 2] - o.px[-1]),
                abs(pr[j, 1] - o.px[1]) if o.stereo else 0.0,
            )
            <= cfg.init_gate_px
            for j, o in enumerate(kept)
        )
        return (kept, pw) if ok else None

    def _insert_landmark(
        self, lm: int, obs: list[_Obs], point: F64, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values
    ) -> None:
        """Landmark ``lm`` enters the graph at ``point`` (world, m) with its observations ``obs``."""
        lkey = self._next_lkey
        self._next_lkey += 1
        first_seq = min(self._kf_seq[o.kf_id] for o in obs)
        self._landmarks[lkey] = _Landmark(lm, first_seq)
        if lkey >= self._lm_first_seq.size:
            self._lm_first_seq = np.concatenate([self._lm_first_seq, np.zeros_like(self._lm_first_seq)])
        self._lm_first_seq[lkey] = first_seq
        self._lm_current[lm] = lkey
        values.insertPoint3(L(lkey), np.asarray(point, dtype=float))  # no overload resolution (be17)
        for o in obs:
            self._add_obs(o, lkey, lm, graph)
        del self._pending[lm]

    def _create_landmarks(self, candidates: list[int], graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> int:
        """Move pending landmarks with enough observations into the graph.

        Each is initialised from its stereo triangulation of largest disparity; observations farther
        than ``init_gate_px`` from that point are dropped first. Returns how many were created.
        """
        todo = self._creation_candidates(candidates)
        if not todo:
            return 0
        T = np.stack([self._pose_guess[b.kf_id] for _, _, b in todo])
        pts = np.array([b.point_in_kf for _, _, b in todo])
        p_world = np.einsum("nij,nj->ni", T[:, :3, :3], pts) + T[:, :3, 3]
        keep_all = self._gate_initial(todo, p_world)
        ok_idx = [i for i, k in enumerate(keep_all) if k]
        if ok_idx and self.config.init_iterations > 0:
            # refine the points on all their observations (poses at their current guesses)
            owner = np.array([j for j, i in enumerate(ok_idx) for _ in todo[i][1]])
            flat = [o for i in ok_idx for o in todo[i][1]]
            p_world[ok_idx] = self._triangulate(
                owner, [o.kf_id for o in flat], self._meas_rows(flat), p_world[ok_idx], self.config.init_iterations
            )
        created = 0
        for i, (lm, obs, _) in enumerate(todo):
            entry = (obs, p_world[i]) if keep_all[i] else self._regated(lm)
            if entry is not None:
                self._insert_landmark(lm, entry[0], entry[1], graph, values)
                created += 1
        return created

    def _observe(
        self,
        lm_id: int,
        o: _Obs,
        graph: gtsam.NonlinearFactorGraph,
        candidates: list[int],
        budget: int | None = None,
        redundant: int = 0,
    ) -> None:
        """Route one observation to its landmark in the graph or to the pending buffer.

        Landmarks whose buffer is full enough are appended to ``candidates``. With a ``budget`` an
        observation of a landmark in the graph waits outside iSAM2 (until the final estimate) once
        the update being built holds ``budget`` factors; ``redundant`` > 0 (``keyframe_obs_redundant_kf``):
        then only an observation of a landmark that many observations fix in iSAM2.
        """
        lkey = self._lm_current.get(lm_id)
        if lkey is not None:
            span = self.config.max_landmark_span_kf
            if span > 0 and o.stereo and self._kf_seq[o.kf_id] - self._landmarks[lkey].first_seq >= span:
                del self._lm_current[lm_id]  # the track continues as a new landmark variable
            else:
                self._observe_known(lm_id, lkey, o, graph, budget, redundant)
                return
        pend = self._pending.get(lm_id)
        if pend is None:
            self._pending[lm_id] = [o]
            pend = self._pending[lm_id]
            self._pending_buckets.setdefault(self._kf_seq[o.kf_id], []).append(lm_id)
        else:
            pend.append(o)
        if len(pend) >= self.config.min_observations:
            candidates.append(lm_id)

    def _observe_known(
        self, lm_id: int, lkey: int, o: _Obs, graph: gtsam.NonlinearFactorGraph, budget: int | None, redundant: int
    ) -> None:
        """Route observation ``o`` of landmark ``lm_id`` in the graph (internal index ``lkey``): see :meth:`_observe`.

        It waits outside iSAM2 for the final estimate once the update being built holds ``budget`` factors;
        with ``redundant`` > 0 only if that many observations of the landmark are in iSAM2 already (be22:
        ORB-SLAM's redundancy rule, a point seen by 3 keyframes, for observations; without a budget nothing
        waits: the rule alone, every redundant observation held back, cost the KITTI clip).
        """
        lm = self._landmarks[lkey]
        over = (
            budget is not None
            and budget <= len(self._batch)
            and (redundant <= 0 or lm.in_isam >= redundant)
            and lm.first_seq >= self._old_map_seq(o.kf_id)  # not one that ties the keyframe to the old map
        )
        if over and self.config.keyframe_obs_overflow == "drop":
            self.budget_dropped += 1  # never in the graph: what one keyframe adds stays bounded
            return
        self._add_obs(o, lkey, lm_id, graph, outside=over)

    # ------------------------------------------------------------------ updates
    def add_keyframe(self, keyframe: Keyframe) -> BackendUpdate:
        """Add keyframe ``keyframe.id`` with its stereo and monocular observations and update."""
        t0 = time.perf_counter()
        kf_id = int(keyframe.id)
        if kf_id in self._kf_seq:
            raise EstimationError(f"keyframe {kf_id} was already added to the back end")
        T = np.asarray(keyframe.world_from_kf, dtype=float).reshape(4, 4)
        if not np.all(np.isfinite(T)):
            raise InputError(f"keyframe {kf_id}", "world_from_kf has non-finite values")
        cfg = self.config
        self._note_frontend_info(kf_id, keyframe.ba_info)
        resumed = keyframe.ba_info.get("resumed_from_keyframe")
        if resumed is not None and int(resumed) in self._kf_seq:
            self._resumed_seq[kf_id] = self._kf_seq[int(resumed)]
        self._before_keyframe()
        self._kf_seq[kf_id] = len(self._kf_seq)
        self._xkey[kf_id] = X(kf_id)
        self._kf_order.append(kf_id)
        prev = keyframe.prev_keyframe_id
        if keyframe.connected and prev is not None and int(prev) in self._kf_seq:
            self._links.append((int(prev), kf_id))
        self._pose_guess[kf_id] = T
        rect_from_cam = keyframe.rect_from_cam
        if not _is_identity(np.asarray(rect_from_cam, float)):
            self._body[kf_id] = np.asarray(rect_from_cam, float).reshape(4, 4)
            self._body_pose[kf_id] = (gtsam.Pose3(invert_pose(self._body[kf_id])),)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        values.insert(X(kf_id), gtsam.Pose3(T))
        report = BackendUpdate(kf_id)
        first = len(self._kf_seq) == 1
        if first or not keyframe.connected:
            self._add_prior(kf_id, T, first, graph)

        ids = np.asarray(keyframe.landmark_ids, dtype=np.int64).ravel()
        px = np.asarray(keyframe.stereo_px, dtype=float).reshape(-1, 3)
        pts = np.asarray(keyframe.points_in_kf, dtype=float).reshape(-1, 3)
        if not (ids.shape[0] == px.shape[0] == pts.shape[0]):
            raise InputError(
                f"keyframe {kf_id}",
                f"landmark_ids ({ids.shape[0]}), stereo_px ({px.shape[0]}) and points_in_kf "
                f"({pts.shape[0]}) must have the same length",
            )
        ok = (
            np.isfinite(px).all(axis=1)
            & np.isfinite(pts).all(axis=1)
            & (pts[:, 2] > 0)
            & (px[:, 0] - px[:, 1] >= max(cfg.min_disparity_px, 1e-6))
        )
        report.rejected_observations += int((~ok).sum())
        candidates: list[int] = []
        sel = np.flatnonzero(ok)
        # every observation is routed by _observe. An earlier inlined copy of it ("fast path")
        # for stereo observations of known landmarks saved nothing measurable: add_keyframe CPU
        # time over the first 40 frames of gtsam's KITTI 00 VO data, 6 runs x 2 alternations,
        # min 0.753 / 0.614 s inlined vs 0.694 / 0.625 s merged (machine load 20-27).
        for lm, p, q in zip(ids[sel].tolist(), px[sel].tolist(), pts[sel], strict=True):
            self._observe(lm, _Obs(kf_id, True, tuple(p), q), graph, candidates)
        seq = self._kf_seq[kf_id]
        report.rejected_observations += self._observe_mono(kf_id, keyframe.mono_obs, graph, candidates)
        report.new_landmarks = self._create_landmarks(candidates, graph, values)
        self._prune_pending(seq)
        if not (first or not keyframe.connected) and not self._linked(kf_id, 3):
            # too few observations determine this pose: a loose prior keeps the system solvable
            self._add_prior(kf_id, T, False, graph)
        report.new_factors = graph.size()
        new_fids = list(self._batch)
        self._theta0.insert(values)
        self._run_update(graph, values, [], X(kf_id), defer=self._defer_kf)
        self._kf_waiting = self._defer_kf and bool(self._deferred_fids)
        if cfg.blunder_sigma > 0:
            report.removed_blunders = self._screen_new([f for f in new_fids if f in self._factors])
        report.pending_landmarks = len(self._pending)
        report.update_ms = (time.perf_counter() - t0) * 1e3
        return report

    def _linked(self, kf_id: int, n: int) -> bool:
        """Whether the factors recorded for the next update hold ``n`` observations of keyframe ``kf_id``.

        Proxy factors count (they tie it to the old map); stops at the ``n``-th (be17: not the whole batch).
        """
        factors, found = self._factors, 0
        for f in self._batch:
            r = factors[f]
            if r.obs is not None and r.obs[0] == kf_id or r.kind == "proxy":
                found += 1
                if found >= n:
                    return True
        return False

    def _note_frontend_info(self, kf_id: int, ba_info: dict[str, float]) -> None:
        """Keep the front end's pose residual sigma (px) and the disparity offset (px) it applied to ``kf_id``."""
        sig = ba_info.get("pose_residual_sigma_px")
        if sig is not None and np.isfinite(sig) and sig > 0:
            self._frontend_sigma_px.append(float(sig))
        applied = ba_info.get("disparity_offset_applied_px")
        estimate = ba_info.get("disparity_offset_estimate_px")
        if applied is not None and estimate is not None and np.isfinite(applied) and np.isfinite(estimate):
            self._kf_offset_px[kf_id] = float(applied)
            self._offset_estimate_px = float(estimate)

    def _before_keyframe(self) -> None:
        """Run the waiting keyframe's deferred update; rebuild iSAM2 on its window when it is due."""
        cfg = self.config
        if self._kf_waiting:  # the previous keyframe's update (no estimate came between) runs on its own
            self._flush_deferred()
        if self._windowed and cfg.local_rebuild_kf > 0:
            n_kf = len(self._kf_order)
            keep = max(cfg.local_rebuild_keep_kf, cfg.local_window_kf)
            if n_kf >= keep + cfg.local_rebuild_kf and n_kf - self._rebuilt_at >= cfg.local_rebuild_kf:
                self._rebuild_window(keep)

    def _observe_mono(
        self, kf_id: int, mono_obs: F64, graph: gtsam.NonlinearFactorGraph, candidates: list[int], budgeted: bool = True
    ) -> int:
        """Route monocular observations (landmark id, u, v px) of ``kf_id``; returns how many were rejected.

        Rejected: non-finite, or of a landmark that was dropped or never seen. ``budgeted``: under
        ``keyframe_obs_budget`` (a keyframe's own rows; not a loop's late observations, be19).
        """
        rejected = 0
        rows = np.asarray(mono_obs, dtype=float).reshape(-1, 3)
        budget: int | None = None
        used = self._budget_used.get(kf_id, 0)
        if budgeted and self.config.keyframe_obs_budget > 0:  # the keyframe's budget over all its updates
            budget = max(self.config.keyframe_obs_budget - used, len(self._batch))
        redundant = self.config.keyframe_obs_redundant_kf if budgeted else 0
        # which ones wait (budget) and which old landmarks get proxies (local_proxies_per_kf): by the spread order
        if budget is not None or self._windowed and self.config.local_proxies_per_kf > 0:
            lkeys = self._row_lkeys(rows)
            if self._budget_binds(kf_id, budget, rows, lkeys) or self._proxies_bind(kf_id, lkeys):
                rows = rows[self._spread_order(rows, lkeys, redundant)]
        finite = np.isfinite(rows).all(axis=1).tolist()  # one array operation, not one per row
        current, pending = self._lm_current, self._pending
        for row, ok in zip(rows.tolist(), finite, strict=True):
            lm_id = int(row[0]) if ok else -1
            lkey = current.get(lm_id) if ok else None
            if lkey is not None:  # straight to its landmark (be23c: the span rule is for stereo observations only)
                self._observe_known(lm_id, lkey, _Obs(kf_id, False, (row[1], row[2]), None), graph, budget, redundant)
            elif ok and lm_id in pending:
                self._observe(lm_id, _Obs(kf_id, False, (row[1], row[2]), None), graph, candidates, budget, redundant)
            else:
                rejected += 1
        if budget is not None:
            self._budget_used[kf_id] = used + len(self._batch)
        return rejected

    def _budget_binds(self, kf_id: int, budget: int | None, rows: F64, lkeys: NDArray[np.int64]) -> bool:
        """Whether ``budget`` may leave some of ``rows`` (landmark id, u, v px) of ``kf_id`` out of the update.

        Counted as the budget counts: the update's factors so far, a row of a landmark in the graph one, a
        revisit's two (its proxy's prior); rows of pending landmarks none. Only then are the rows put in the
        spread order (be19: sorting every keyframe's rows cost the first round, which the budget never bound).
        ``lkeys``: the rows' landmarks (:meth:`_row_lkeys`).
        """
        if budget is None or len(self._batch) + 2 * rows.shape[0] <= budget:
            return False
        in_graph = int(np.count_nonzero(lkeys >= 0))
        return len(self._batch) + in_graph + self._revisit_rows(kf_id, lkeys) > budget

    def _proxies_bind(self, kf_id: int, lkeys: NDArray[np.int64]) -> bool:
        """Whether ``local_proxies_per_kf`` leaves some of the rows' old landmarks ``lkeys`` without a proxy."""
        bound = self.config.local_proxies_per_kf
        if bound <= 0 or not self._windowed:
            return False
        left = bound - self._proxies_used.get(kf_id, 0)
        return self._revisit_rows(kf_id, lkeys) > left

    def _spread_order(self, rows: F64, lkeys: NDArray[np.int64], redundant: int = 0) -> NDArray[np.intp]:
        """The order (row indices) in which a budget takes monocular observations ``rows`` (landmark id, u, v px).

        Round robin over a grid of the image (``_BUDGET_GRID`` cells), in each cell the observations of
        the landmarks with the most factors first (a point many keyframes fix constrains the pose
        most): what :attr:`BackendConfig.keyframe_obs_budget` keeps is spread over the image and well
        determined (issue 33, be13). Ties keep their order: deterministic. ``lkeys``: the rows' landmarks
        (:meth:`_row_lkeys`). ``redundant`` > 0: the rows of landmarks that many observations fix in iSAM2
        last (those the budget may hold back, :meth:`_observe`).
        """
        n = rows.shape[0]
        if n == 0:
            return np.arange(0)
        finite = np.asarray(np.isfinite(rows).all(axis=1), dtype=bool)
        uv = np.where(finite[:, None], rows[:, 1:3], 0.0)
        (cols, grid_rows), (w, h) = _BUDGET_GRID, self._image_size
        cell = np.clip((uv[:, 0] * cols / w).astype(np.int64), 0, cols - 1) + cols * np.clip(
            (uv[:, 1] * grid_rows / h).astype(np.int64), 0, grid_rows - 1
        )
        landmarks = self._landmarks
        keys = np.where(finite, lkeys, -1).tolist()
        support = np.array([len(landmarks[k].fids) if k >= 0 else 0 for k in keys])
        by_cell = np.lexsort((-support, cell))  # by cell, the best supported first
        sorted_cell = cell[by_cell]
        first = np.r_[0, np.flatnonzero(np.diff(sorted_cell)) + 1]
        rank = np.arange(n) - np.repeat(first, np.diff(np.r_[first, n]))  # place within its cell
        if redundant <= 0:
            return by_cell[np.lexsort((sorted_cell, rank))]
        late = np.array([k >= 0 and landmarks[k].in_isam >= redundant for k in keys], dtype=bool)
        return by_cell[np.lexsort((sorted_cell, rank, late[by_cell]))]

    def add_observations(self, keyframe_id: int, mono_obs: F64) -> BackendUpdate:
        """Add monocular observations (landmark id, u, v rectified px) to keyframe ``keyframe_id``; update.

        Those the keyframe has already are kept as they are (:meth:`_add_obs`). For a loop found
        after its keyframe was added (the loop worker's last detections, drained at the end of a run).
        """
        t0 = time.perf_counter()
        kf_id = int(keyframe_id)
        if kf_id not in self._kf_seq:
            raise EstimationError(f"observations of keyframe {kf_id}, which is not in the back end")
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        report = BackendUpdate(kf_id)
        candidates: list[int] = []
        # a loop's observations of its old keyframe's landmarks tie the keyframe to the old map: never over
        # keyframe_obs_budget (be19; a revisit's never were, a short loop's old landmarks are in the window)
        report.rejected_observations = self._observe_mono(kf_id, mono_obs, graph, candidates, budgeted=False)
        report.new_landmarks = self._create_landmarks(candidates, graph, values)
        report.new_factors = graph.size()
        new_fids = list(self._batch)
        self._theta0.insert(values)
        # under local the update stays in the window (older landmarks through proxies): the old map does
        # not move, so estimate() need not read every pose again (a keyframe's update, as for add_keyframe)
        recent = self._windowed and self._kf_seq[kf_id] >= len(self._kf_order) - 1 - self.config.local_window_kf
        self._run_update(graph, values, [], X(kf_id) if recent else None, defer=True)
        if self.config.blunder_sigma > 0:
            report.removed_blunders = self._screen_new([f for f in new_fids if f in self._factors])
        report.pending_landmarks = len(self._pending)
        report.update_ms = (time.perf_counter() - t0) * 1e3
        return report

    def _prune_pending(self, seq: int) -> None:
        """Forget pending landmarks not observed in the last ``pending_max_age_kf`` keyframes.

        They would never reach the graph; keeps memory bounded.
        """
        cut = seq - self.config.pending_max_age_kf
        for old in [k for k in self._pending_buckets if k <= cut]:
            for lm in self._pending_buckets.pop(old):
                obs = self._pending.get(lm)
                if not obs:
                    continue
                last = self._kf_seq.get(obs[-1].kf_id, -1)
                if last <= cut:
                    del self._pending[lm]
                else:
                    self._pending_buckets.setdefault(last, []).append(lm)

    def _add_prior(self, kf_id: int, T: F64, gauge: bool, graph: gtsam.NonlinearFactorGraph | None) -> None:
        cfg = self.config
        rad, m = (
            (cfg.prior_sigma_rad, cfg.prior_sigma_m)
            if gauge
            else (cfg.segment_prior_sigma_rad, cfg.segment_prior_sigma_m)
        )
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([rad] * 3 + [m] * 3))
        prior = gtsam.PriorFactorPose3(X(kf_id), gtsam.Pose3(T), noise)
        self._new_fid(_FactorRecord(prior, "prior"))
        if graph is not None:
            graph.add(prior)

    def _run_update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        remove_slots: list[int],
        newest: int | None,
        defer: bool = False,
    ) -> None:
        """One iSAM2 update with the factors just recorded (the last ``graph.size()`` fids).

        With ``defer`` (late observations) under ``local_defer_late`` the factors wait and join the next
        update: the loop's prior that follows them, the next keyframe's, or :meth:`_flush_deferred`'s
        before a removal or a read of the whole map.
        """
        new_fids, self._batch = self._batch, []
        if self._new_proxies.size():
            values.insert(self._new_proxies)
            self._theta0.insert(self._new_proxies)
            self._new_proxies = gtsam.Values()
        if len(new_fids) != graph.size():
            raise EstimationError(f"internal: {len(new_fids)} recorded factors but {graph.size()} in the update")
        if self._deferred_fids or defer and self._defer_late:
            self._deferred_all |= newest is None
            self._deferred_graph.push_back(graph)
            self._deferred_values.insert(values)
            self._deferred_fids.extend(new_fids)
            if defer and self._defer_late and not remove_slots:
                return
            graph, values, new_fids = self._deferred_graph, self._deferred_values, self._deferred_fids
            newest = None if self._deferred_all else newest
            self._clear_deferred()
        if self._frozen_keys:
            self._thaw(graph, values, new_fids)
        self._estimate_all |= newest is None  # not a keyframe's update: it may move the whole map
        # removal-only updates keep GTSAM's default ordering: their affected set may be tiny
        groups = None if newest is None else self._ordering_groups(len(graph.keyVector()))
        try:
            result = self._isam_update(graph, values, remove_slots, constrainedKeys=groups)
        except RuntimeError as exc:
            self._recover(exc)
            return
        self.last_result = result
        for fid, slot in zip(new_fids, result.getNewFactorsIndices(), strict=True):
            self._slot[fid] = slot

    def _clear_deferred(self) -> None:
        self._deferred_graph = gtsam.NonlinearFactorGraph()
        self._deferred_values = gtsam.Values()
        self._deferred_fids = []
        self._deferred_all = False
        self._kf_waiting = False

    def _flush_deferred(self) -> None:
        """Run the update the deferred factors wait for (``local_defer_late``), if any.

        A waiting keyframe's (``local_defer_keyframe``) runs as that keyframe's update would have.
        """
        if self._deferred_fids:
            newest = X(self._kf_order[-1]) if self._kf_waiting else None
            self._run_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], newest)

    def _ordering_groups(self, n_keys: int) -> gtsam.KeyGroupMap | None:
        """Elimination groups for an update whose affected set has at least ``n_keys`` variables.

        The newest ``ordering_window_kf`` poses last, oldest to newest, the rest (landmarks, older
        poses) first. CCOLAMD needs every group below the number of variables it orders, hence the
        window and the bound.
        """
        window = min(self.config.ordering_window_kf, n_keys - 1, len(self._kf_order))
        if window <= 0:
            return None
        groups = gtsam.KeyGroupMap()
        for g, kf in enumerate(self._kf_order[-window:], start=1):
            groups.insert2(X(kf), g)
        return groups

    def _recover(self, exc: RuntimeError) -> None:
        """Rebuild iSAM2 after an indeterminate system.

        Without the offending landmark, or with a loose prior on an undetermined keyframe pose.
        """
        message = str(exc)
        for _attempt in range(20):
            match = _SYMBOL_RE.search(message)
            if "ndeterminant" not in message and "ndeterminate" not in message or match is None:
                raise EstimationError(f"iSAM2 update failed: {message.strip().splitlines()[0]}") from exc
            symbol, index = match.group(1), int(match.group(2))
            theta = self._current_values(self._isam.getLinearizationPoint())  # with what a rebuild left out
            if symbol == "l":
                self._drop_landmark(index)
            elif symbol == "x" and index in self._kf_seq:
                src = theta if theta.exists(X(index)) else self._theta0
                self._add_prior(index, src.atPose3(X(index)).matrix(), False, None)
            else:
                raise EstimationError(f"iSAM2: variable {symbol}{index} is not determined by its factors") from exc
            logger.warning("iSAM2 indeterminate near %s%d; rebuilding", symbol, index)
            self.rebuilds += 1
            self._estimate_all = True
            self._clear_deferred()  # their factors are in the record: the rebuild takes them
            self._new_isam(self._relinearize_skip)  # the cadence it had (a window rebuild's, if one made it)
            self._slot.clear()
            keys: set[int] = set()
            for fid, rec in self._factors.items():
                if fid not in self._outside:
                    keys.update(rec.keys())
            for kf in self._kf_seq:  # a keyframe left without factors keeps a loose prior
                if X(kf) not in keys:
                    src = theta if theta.exists(X(kf)) else self._theta0
                    self._add_prior(kf, src.atPose3(X(kf)).matrix(), False, None)
                    keys.add(X(kf))
            self._batch.clear()
            graph = gtsam.NonlinearFactorGraph()
            fids = sorted(set(self._factors) - self._outside)
            for fid in fids:
                graph.add(self._factors[fid].factor)
            values = gtsam.Values()
            for key in keys:
                src = theta if theta.exists(key) else self._theta0
                if gtsam.Symbol(key).chr() == ord("x"):
                    values.insert(key, src.atPose3(key))
                else:
                    values.insertPoint3(key, src.atPoint3(key))  # a Point3 as new landmarks are (be18)
            # every variable goes back to iSAM2 (a failed attempt's linearization point has them all: be18,
            # a second attempt read the rebuild's left-out values over them)
            self._frozen, self._frozen_keys, self._frozen_kfs = gtsam.Values(), set(), set()
            groups = self._ordering_groups(len(keys))
            try:
                result = self._isam_update(graph, values, [], constrainedKeys=groups)
            except RuntimeError as again:
                message = str(again)
                continue
            for fid, slot in zip(fids, result.getNewFactorsIndices(), strict=True):
                self._slot[fid] = slot
            return
        raise EstimationError("iSAM2 stayed indeterminate after dropping 20 landmarks") from exc

    def _drop_landmark(self, lkey: int) -> list[int]:
        """Forget every factor of internal landmark ``lkey``; returns their iSAM2 slots."""
        lm = self._landmarks.pop(lkey, None)
        if lm is None:
            return []
        self.dropped_landmarks += 1
        slots = []
        for fid in lm.fids:
            rec = self._factors.pop(fid)
            self._outside.discard(fid)
            slots.extend(self._drop_proxy_observation(fid))
            if rec.obs is not None:
                self._obs_fid.pop(rec.obs, None)
            slot = self._slot.pop(fid, None)
            if slot is not None:
                slots.append(slot)
        if self._lm_current.get(lm.landmark_id) == lkey:
            del self._lm_current[lm.landmark_id]
        return slots

    def _remove_fids(self, fids: Iterable[int]) -> list[int]:
        """Forget observation factors; a landmark left without support is dropped whole."""
        slots: list[int] = []
        touched: set[int] = set()
        for fid in fids:
            rec = self._factors.pop(fid, None)
            if rec is None:
                continue
            self._outside.discard(fid)
            if rec.obs is not None:
                self._obs_fid.pop(rec.obs, None)
            slot = self._slot.pop(fid, None)
            if slot is not None:
                slots.append(slot)
            slots.extend(self._drop_proxy_observation(fid))
            if rec.lkey >= 0 and rec.lkey in self._landmarks:
                self._landmarks[rec.lkey].fids.discard(fid)
                touched.add(rec.lkey)
        for lkey in touched:
            kinds = [self._factors[f].kind for f in self._landmarks[lkey].fids]
            if "stereo" not in kinds and len(kinds) < 2 or not kinds:
                slots.extend(self._drop_landmark(lkey))
        return slots

    def remove_observations(self, observations: Iterable[Observation]) -> int:
        """Remove observations ``(keyframe_id, landmark_id)`` (blunders) with ``removeFactorIndices``.

        Pending ones are just forgotten. Returns the count removed.
        """
        self._flush_deferred()  # their slots first
        fids = []
        n = 0
        for kf_id, lm_id in observations:
            key = (int(kf_id), int(lm_id))
            fid = self._obs_fid.get(key)
            if fid is not None:
                fids.append(fid)
                n += 1
            elif lm_id in self._pending:
                before = len(self._pending[lm_id])
                self._pending[lm_id] = [o for o in self._pending[lm_id] if o.kf_id != key[0]]
                n += before - len(self._pending[lm_id])
        slots = self._remove_fids(fids)
        if slots:
            self._run_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), slots, None)
        return n

    def _screen_new(self, new_fids: list[int]) -> int:
        """Remove new observations whose whitened residual exceeds ``blunder_sigma`` at the updated estimate.

        Robust weights aside.
        """
        recs = [(f, self._factors[f]) for f in new_fids if self._factors[f].obs is not None]
        if not recs:
            return 0
        poses = {}
        for _, rec in recs:
            k = rec.obs[0]  # type: ignore[index]
            if k not in poses:
                poses[k] = self._isam.calculateEstimatePose3(X(k)).matrix()
        pts = np.array([self._isam.calculateEstimatePoint3(L(rec.lkey)) for _, rec in recs], dtype=float)
        pred = self._project([rec.obs[0] for _, rec in recs], pts, poses)  # type: ignore[index]
        meas = np.array([self._measured(rec) for _, rec in recs])
        stereo = np.array([rec.kind == "stereo" for _, rec in recs])
        diff = pred - meas
        diff[~stereo, 1] = 0.0
        norm = np.sqrt(np.nansum(diff**2, axis=1)) / self.config.pixel_sigma_px
        bad = [
            f
            for (f, _), n, fin in zip(recs, norm, np.isfinite(pred[:, 0]), strict=True)
            if not fin or n > self.config.blunder_sigma
        ]
        if bad:
            slots = self._remove_fids(bad)
            self._run_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), slots, None)
        return len(bad)

    @staticmethod
    def _measured(rec: _FactorRecord) -> F64:
        f: Any = rec.factor
        if rec.kind == "stereo":
            m = f.measured()
            return np.array([m.uL(), m.uR(), m.v()])
        uv = np.asarray(f.measured(), dtype=np.float64).ravel()
        return np.array([uv[0], np.nan, uv[1]])

    def refine(self, max_iterations: int = 10) -> int:
        """Extra iSAM2 iterations without new factors (e.g. at the end of a run) until no variable needs relinearising.

        Returns the iterations run.
        """
        self._estimate_all = True
        for it in range(max_iterations):
            result = self._isam_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], force_relinearize=True)
            if result.getVariablesRelinearized() == 0:
                return it + 1
        return max_iterations

    def reprojection_residuals_px(self, values: gtsam.Values | None = None) -> F64:
        """Image residuals (measured minus predicted, pixels) of every live observation factor.

        u_left, u_right, v of stereo and u, v of monocular observations, concatenated, at ``values``
        (default: the current iSAM2 estimate).
        """
        vals = values if values is not None else self._isam.calculateEstimate()
        out: list[F64] = []
        for rec in self._factors.values():
            if rec.kind in ("stereo", "mono"):
                f: Any = rec.factor
                out.append(np.asarray(f.unwhitenedError(vals), dtype=np.float64).ravel())
        return np.concatenate(out) if out else np.zeros(0)

    @staticmethod
    def robust_error_px(residuals_px: F64, sigma_px: float, huber_k: float) -> float:
        """Huber-robust RMS of image residuals (pixels).

        ``sigma * sqrt(mean(2 rho(r / sigma)))`` with ``rho`` Huber's loss at ``huber_k`` (the plain
        RMS when every residual is within ``huber_k`` sigmas; Gaussian when ``huber_k`` <= 0).
        """
        r = np.abs(np.asarray(residuals_px, float)) / sigma_px
        r = r[np.isfinite(r)]
        if r.size == 0:
            return float("nan")
        rho = 0.5 * r**2 if huber_k <= 0 else np.where(r <= huber_k, 0.5 * r**2, huber_k * r - 0.5 * huber_k**2)
        return float(sigma_px * np.sqrt(2.0 * rho.mean()))

    def batch_refine(
        self,
        pixel_sigma_px: float | None = None,
        huber_k: float = 1.345,
        max_iterations: int = 30,
        min_gain_sd: float = 3.0,
        stop_gain_sd: float = 0.0,
    ) -> BackendEstimate:
        """Final batch bundle adjustment of every keyframe and landmark on all live factors.

        By gtsam Levenberg-Marquardt from the current estimate, with the stereo and monocular
        observations re-weighted to ``pixel_sigma_px`` under a Huber loss of ``huber_k`` sigmas
        (priors and loop constraints as they are). ``pixel_sigma_px`` None: the run's own noise, the
        robust scale (1.4826 x median absolute value) of the image residuals (KLT and stereo
        observations) at the incremental solution, corrected for the redundancy
        ``sqrt(n / (n - u))`` (n residuals, u pose and landmark unknowns: a landmark seen by two
        keyframes leaves little redundancy, so the raw scale is far too small); without redundancy,
        the median over keyframe intervals of the front end's robust pose-residual scale
        (``ba_info`` ``pose_residual_sigma_px``). The result is kept only when it lowers the robust
        reprojection error (:meth:`robust_error_px` at that scale) significantly: the robust
        chi-square drops by more than ``min_gain_sd`` standard deviations sqrt(2 n) of a chi-square
        of n residuals; otherwise the incremental solution is returned. :attr:`refine_info` says
        which, with the noise. With ``stop_gain_sd`` > 0 Levenberg-Marquardt stops when an iteration
        lowers the robust chi-square by less than that many of those standard deviations (else at
        gtsam's relative and absolute tolerances, 1e-5). The incremental solution keeps its own
        weights; this one is not fed back to iSAM2. With the front end's disparity offset estimated (``ba_info``
        ``disparity_offset_applied_px`` / ``_estimate_px``), every keyframe's right columns are first
        re-expressed with the latest estimate instead of the one taken out when it was matched, so that
        all keyframes share one offset (the robust errors before and after are both of those).
        """
        if not self._kf_seq:
            raise EstimationError("batch refinement of an empty back end")
        start = self._isam.calculateEstimate()
        r0 = self.reprojection_residuals_px(start)
        mad_px = float(1.4826 * np.median(np.abs(r0))) if r0.size else float("nan")
        keys = np.asarray(start.keys(), dtype=np.uint64)
        chars = (keys >> np.uint64(56)).astype(np.int64)
        unknowns = 6 * int((chars == ord("x")).sum()) + 3 * int((chars == ord("l")).sum())
        redundancy = r0.size - unknowns
        backend_px = mad_px * np.sqrt(r0.size / redundancy) if redundancy > 0 else float("nan")
        frontend_px = float(np.median(self._frontend_sigma_px)) if self._frontend_sigma_px else float("nan")
        source = "configured"
        if pixel_sigma_px is not None:
            sigma = float(pixel_sigma_px)
        elif np.isfinite(backend_px) and backend_px > 0:
            sigma, source = max(backend_px, 1e-3), "back-end residual MAD, redundancy-corrected"
        elif np.isfinite(frontend_px):
            sigma, source = max(frontend_px, 1e-3), "front-end pose residuals"
        else:
            raise EstimationError("no image residuals to estimate the noise from")
        base3: gtsam.noiseModel.Base = gtsam.noiseModel.Isotropic.Sigma(3, sigma)
        base2: gtsam.noiseModel.Base = gtsam.noiseModel.Isotropic.Sigma(2, sigma)
        if huber_k > 0:
            huber = gtsam.noiseModel.mEstimator.Huber.Create(huber_k)
            base3 = gtsam.noiseModel.Robust.Create(huber, base3)
            base2 = gtsam.noiseModel.Robust.Create(huber, base2)
        graph = gtsam.NonlinearFactorGraph()
        shift = self._offset_shifts_px()
        observed: list[Any] = []  # the observation factors as refined (re-expressed right columns)
        for fid in sorted(self._factors):
            rec = self._factors[fid]
            f: Any = rec.factor
            if rec.kind in ("stereo", "mono") and rec.obs is not None:
                # the keyframe's body_P_sensor as its factors got it (issue 32: with an inversion per
                # observation the refinement took 0.83 instead of 0.68 s CPU, 150-frame realistic orbit)
                extra = self._body_pose.get(rec.obs[0], ())
                keys = f.keys()
                if rec.kind == "stereo":
                    m, d = f.measured(), shift.get(rec.obs[0], 0.0)
                    m = gtsam.StereoPoint2(m.uL(), m.uR() + d, m.v()) if d else m
                    f = gtsam.GenericStereoFactor3D(m, base3, keys[0], keys[1], self._cal_stereo, *extra)
                else:
                    f = gtsam.GenericProjectionFactorCal3_S2(
                        np.asarray(f.measured(), float).ravel(), base2, keys[0], keys[1], self._cal_mono, *extra
                    )
                observed.append(f)
            graph.add(f)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        n_res = int(np.isfinite(r0).sum())
        if stop_gain_sd > 0:  # gtsam's error: about half the robust chi-square (Huber on each factor's norm)
            params.setAbsoluteErrorTol(0.5 * stop_gain_sd * np.sqrt(2.0 * n_res))
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, start, params)
        values = optimizer.optimize()

        def residuals(vals: gtsam.Values) -> F64:
            if not shift:
                return self.reprojection_residuals_px(vals)
            out = [np.asarray(f.unwhitenedError(vals), dtype=np.float64).ravel() for f in observed]
            return np.concatenate(out) if out else np.zeros(0)

        # at the start without re-expressed columns: the residuals r0 already computed
        before = self.robust_error_px(residuals(start) if shift else r0, sigma, huber_k)
        after = self.robust_error_px(residuals(values), sigma, huber_k)
        # the robust chi-square (sum of 2 rho(r / sigma)) must drop by more than min_gain_sd
        # of its standard deviations sqrt(2 n): a smaller drop is not told apart from noise
        drop = n_res * ((before / sigma) ** 2 - (after / sigma) ** 2)
        applied = bool(drop > min_gain_sd * np.sqrt(2.0 * n_res))
        self.refine_info = {
            "pixel_sigma_px": sigma,
            "pixel_sigma_source": source,
            "frontend_residual_sigma_px": frontend_px,
            "backend_residual_mad_px": mad_px,
            "backend_residual_sigma_px": backend_px,
            "refine_residuals": int(r0.size),
            "refine_unknowns": unknowns,
            "refine_robust_px_before": before,
            "refine_robust_px_after": after,
            "refine_chi2_drop": float(drop),
            "refine_chi2_sd": float(np.sqrt(2.0 * n_res)),
            "refine_applied": applied,
            "refine_iterations": int(optimizer.iterations()),
        }
        if not applied:
            logger.info("batch refinement not applied: robust error %.4f px -> %.4f px", before, after)
            values = start
        world_from_kf = {k: values.atPose3(X(k)).matrix() for k in self._kf_seq}
        lkeys = sorted(k for k in self._landmarks if values.exists(L(k)))
        pts = np.array([values.atPoint3(L(k)) for k in lkeys], dtype=float).reshape(-1, 3)
        ids = np.array([self._landmarks[k].landmark_id for k in lkeys], dtype=np.int64)
        return BackendEstimate(world_from_kf, ids, pts, set(world_from_kf))

    def _offset_shifts_px(self) -> dict[int, float]:
        """Per keyframe, what re-expresses its right columns with the latest disparity offset estimate (px).

        The front end took ``applied`` out of a keyframe's right columns (measured - applied); with
        the latest estimate it is measured - estimate, so the shift is applied - estimate. Empty
        without an estimate or when nothing moves.
        """
        est = self._offset_estimate_px
        if est is None:
            return {}
        out = {k: a - est for k, a in self._kf_offset_px.items() if abs(a - est) > 1e-9}
        return out

    def final_estimate(self, refine: RefineConfig | None) -> BackendEstimate:
        """Extra iSAM2 iterations, then the batch bundle adjustment when ``refine.batch_ba``.

        Extra iterations by :meth:`refine` (at most ``refine.extra_iterations``), the batch bundle
        adjustment by :meth:`batch_refine`; the plain estimate when ``refine`` is None.
        """
        if self._windowed or self._outside:
            self._merge_outside()
        if refine is None:
            return self.estimate()
        if refine.extra_iterations > 0:
            self.refine(refine.extra_iterations)
        if not refine.batch_ba:
            est = self.estimate()
        else:
            est = self.batch_refine(
                refine.pixel_sigma_px, refine.huber_k, refine.max_iterations, refine.min_gain_sd, refine.stop_gain_sd
            )
        return self._distribute_loops(est, refine) if refine.distribute_loops else est

    def loop_constraints(self) -> list[tuple[int, int, F64]]:
        """The live loop constraints as ``(kf_a, kf_b, kf_a_from_kf_b)`` (4x4, metres)."""
        out = []
        for rec in self._factors.values():
            if rec.kind == "loop":
                f: Any = rec.factor
                a, b = (int(gtsam.symbolIndex(k)) for k in f.keys())
                out.append((a, b, np.asarray(f.measured().matrix(), dtype=np.float64)))
        return out

    def _distribute_loops(self, est: BackendEstimate, refine: RefineConfig) -> BackendEstimate:
        """``est`` with each loop's discrepancy spread along its keyframe cycle.

        :func:`~loopmodel.backend.loop_distribution.distribute_loop_errors`; each landmark moves
        with its first keyframe. :attr:`refine_info` gets the largest keyframe move.
        """
        loops = self.loop_constraints()
        if not loops:
            return est
        cfg = self.config
        moved = distribute_loop_errors(
            est.world_from_kf,
            self._links,
            loops,
            refine.loop_odometry_sigma_deg,
            refine.loop_odometry_sigma_m,
            float(np.degrees(cfg.loop_sigma_rad)),
            cfg.loop_sigma_m,
        )
        fix = {k: moved[k] @ invert_pose(np.asarray(est.world_from_kf[k], float)) for k in moved}
        first_kf = {lm.landmark_id: self._kf_order[lm.first_seq] for lm in self._landmarks.values()}
        pts = np.asarray(est.landmarks_in_world, float).reshape(-1, 3).copy()
        for i, lid in enumerate(np.asarray(est.landmark_ids).tolist()):
            F = fix.get(first_kf.get(int(lid), -1))
            if F is not None:
                pts[i] = F[:3, :3] @ pts[i] + F[:3, 3]
        shift = [float(np.linalg.norm(F[:3, 3])) for F in fix.values()]
        self.refine_info["loops_distributed"] = len(loops)
        self.refine_info["loop_distribution_max_move_m"] = max(shift, default=0.0)
        return BackendEstimate(moved, est.landmark_ids, pts, set(moved))

    def metrics(self) -> dict[str, Any]:
        """Factor and landmark counts of the graph.

        The noise and outcome of the final batch refinement (:attr:`refine_info`: ``pixel_sigma_px``
        and where it came from).
        """
        return {
            "isam2_factors": self.num_factors,
            "isam2_landmarks": self.num_landmarks,
            "isam2_budget_dropped": self.budget_dropped,  # keyframe_obs_budget's rest left out (drop)
            "isam2_proxies_skipped": self.proxies_skipped,  # revisits over local_proxies_per_kf (final only)
            **self.refine_info,
        }

    def add_loop_constraint(self, kf_a: int, kf_b: int, a_from_b: F64, sigmas: F64 | None = None) -> int:
        """Add ``kf_a_from_kf_b`` (4x4) as a robust between-factor.

        ``sigmas`` (rad x3, m x3) default to the configured loop sigmas. Returns the constraint's
        factor id.
        """
        for k in (kf_a, kf_b):
            if k not in self._kf_seq:
                raise EstimationError(f"loop constraint names keyframe {k}, which is not in the back end")
        cfg = self.config
        s = (
            np.asarray(sigmas, float)
            if sigmas is not None
            else np.array([cfg.loop_sigma_rad] * 3 + [cfg.loop_sigma_m] * 3)
        )
        noise = self._robust(gtsam.noiseModel.Diagonal.Sigmas(s))
        factor = gtsam.BetweenFactorPose3(X(int(kf_a)), X(int(kf_b)), gtsam.Pose3(np.asarray(a_from_b, float)), noise)
        if self._windowed:
            fid = self._new_fid(_FactorRecord(factor, "loop"), outside=True)  # it joins at the final estimate
            if cfg.local_loop_prior:
                self._loop_prior(fid, int(kf_a), int(kf_b), np.asarray(a_from_b, float), noise)
            return fid
        fid = self._new_fid(_FactorRecord(factor, "loop"))
        graph = gtsam.NonlinearFactorGraph()
        graph.add(factor)
        self._run_update(graph, gtsam.Values(), [], None)
        # a loop moves much of the trajectory: relinearise right away
        self._isam_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], force_relinearize=True)
        return fid

    def _loop_prior(self, fid: int, kf_a: int, kf_b: int, a_from_b: F64, noise: gtsam.noiseModel.Base) -> None:
        """``loop_policy`` local: loop ``fid`` as a prior on its newer keyframe at the older one's estimate.

        ``world_from_new = world_from_old (estimate) * old_from_new`` with the loop's noise: the update
        involves only the newer keyframe (in the local window), so a loop corrects the live end of
        the trajectory at the cost of one small update, however old its other keyframe (issue 33
        item 5); the old map stays where it is until the final estimate, where this prior is dropped
        and the loop constraint itself joins (:meth:`_merge_outside`).
        """
        new, old = (kf_a, kf_b) if self._kf_seq[kf_a] >= self._kf_seq[kf_b] else (kf_b, kf_a)
        old_from_new = a_from_b if new == kf_b else invert_pose(a_from_b)
        world_from_old = self._pose_estimate(old).matrix()
        prior = gtsam.PriorFactorPose3(X(new), gtsam.Pose3(world_from_old @ old_from_new), noise)
        self._proxy_fids[fid] = [self._new_fid(_FactorRecord(prior, "proxy"))]
        graph = gtsam.NonlinearFactorGraph()
        graph.add(prior)
        # with the loop's late observations (local_defer_late), and with local_defer_loop in the next keyframe's update
        self._run_update(graph, gtsam.Values(), [], X(new), defer=self._defer_loop)

    def remove_loop_constraint(self, constraint_id: int) -> None:
        """Remove a loop constraint returned by :meth:`add_loop_constraint`."""
        rec = self._factors.get(constraint_id)
        if rec is None or rec.kind != "loop":
            raise EstimationError(f"no loop constraint with id {constraint_id}")
        self._flush_deferred()  # its prior's slot first
        del self._factors[constraint_id]
        if constraint_id in self._outside:
            self._outside.discard(constraint_id)
            slots = [s for pf in self._proxy_fids.pop(constraint_id, []) if self._factors.pop(pf, None) is not None
                     and (s := self._slot.pop(pf, None)) is not None]
            if slots:
                self._run_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), slots, None)
            return
        slot = self._slot.pop(constraint_id, None)
        if slot is not None:
            self._run_update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [slot], None)

    # ------------------------------------------------------------------ estimate
    def estimate(self, landmarks: bool = True) -> BackendEstimate:
        """Current keyframe poses, landmarks, and the keyframes whose pose moved since the previous call.

        Landmarks are left out when ``landmarks`` is False: cost then grows with the keyframes only.
        Moved: more than ``change_tolerance_m`` (position, or rotation x 1 m).
        """
        lm_ids = np.zeros(0, dtype=np.int64)
        pts = np.zeros((0, 3))
        # a keyframe's update waits at most until here (local_defer_keyframe); a loop's for the next keyframe's
        if landmarks or self._kf_waiting or (self._defer_kf and not self._defer_loop):
            self._flush_deferred()
        if not (landmarks or self._updated or len(self._kf_order) > self._estimated_kfs):
            return BackendEstimate(dict(self._last_poses), lm_ids, pts, set())  # nothing moved since the last call
        self._updated = False
        if landmarks:
            vals = self._current_values()
            keys = np.asarray(vals.keys(), dtype=np.uint64)
            chars = (keys >> np.uint64(56)).astype(np.int64)
            idx = (keys & _INDEX_MASK).astype(np.int64)
            ids = np.sort(idx[chars == ord("x")]).tolist()
            rows = gtsam.utilities.extractPose3(vals).reshape(-1, 12)
            lkeys = np.sort(idx[chars == ord("l")])
            # every Point3 in key order: the landmarks (l) before their proxies (p, loop_policy local)
            all_pts = gtsam.utilities.extractPoint3(vals).reshape(-1, 3)[: lkeys.size]
            known = self._landmarks
            live = np.array([k in known for k in lkeys.tolist()], dtype=bool)
            lm_ids = np.array([known[k].landmark_id for k in lkeys[live].tolist()], dtype=np.int64)
            pts = all_pts[live]
        else:
            ids = self._estimate_keys()
            mats = np.array([self._pose_estimate(k).matrix() for k in ids]).reshape(-1, 4, 4)
            rows = np.concatenate([mats[:, :3, :3].reshape(-1, 9), mats[:, :3, 3]], axis=1)
        poses = np.zeros((rows.shape[0], 4, 4))
        poses[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
        poses[:, :3, 3] = rows[:, 9:]
        poses[:, 3, 3] = 1.0
        fresh: dict[int, F64] = dict(zip(ids, poses, strict=True))
        world_from_kf = fresh if landmarks else {**self._last_poses, **fresh}
        # changed keyframes: position moved, or rotation moved (angle x 1 m), beyond tolerance
        tol = self.config.change_tolerance_m
        known_kf = [k in self._last_poses for k in ids]
        changed = {k for k, kn in zip(ids, known_kf, strict=True) if not kn}
        if any(known_kf):
            sel = np.flatnonzero(known_kf)
            prev = np.stack([self._last_poses[ids[j]] for j in sel])
            cur = poses[sel]
            dt = np.linalg.norm(cur[:, :3, 3] - prev[:, :3, 3], axis=1)
            cos = (np.einsum("nij,nij->n", prev[:, :3, :3], cur[:, :3, :3]) - 1.0) / 2.0
            dr = np.arccos(np.clip(cos, -1.0, 1.0))
            changed.update(ids[j] for j in sel[(dt > tol) | (dr > tol)].tolist())
        self._last_poses = world_from_kf
        self._pose_guess.update(fresh)
        return BackendEstimate(world_from_kf, lm_ids, pts, changed)

    def _estimate_keys(self) -> list[int]:
        """The keyframes whose poses :meth:`estimate` reads from iSAM2 this call (issue 33).

        With ``estimate_window_kf`` N > 0: the keyframes added since the last call, the newest N, and
        N older ones in turn (each older pose is read again every (keyframes - N) / N calls); every
        keyframe after an update that was not a keyframe's (a loop, observations, a removal, a
        rebuild), which may move the whole map. Reading one pose costs about 0.1 ms: reading all of
        them grew the back end's cost per keyframe by 12 ms at 116 keyframes of the rounds scan.
        A keyframe a window rebuild left out of iSAM2 (``local_rebuild_kf``) does not move until the
        final estimate: it is read once after it left, then no more (be18).
        """
        n = self.config.estimate_window_kf
        order = self._kf_order
        new = len(order) - self._estimated_kfs
        self._estimated_kfs = len(order)
        left, self._frozen_unread = self._frozen_unread, []
        if n == 0 or self._estimate_all or len(order) <= 2 * n + new:
            self._estimate_all = False
            return list(order)
        recent = max(n, new)
        # be21: the keyframes out of iSAM2 by their own small set, not each pose key in _frozen_keys (the
        # whole map's left-out variables; 0.25 ms an estimate by 349 keyframes of the full rounds scan)
        frozen = self._frozen_kfs
        live = [k for k in order if k not in frozen] if frozen else order
        old = live[:-recent]
        newest = left + live[-recent:]
        if not old:
            return newest
        start = self._estimate_turn % len(old)
        self._estimate_turn = start + n
        return old[start : start + n] + old[: max(start + n - len(old), 0)] + newest

    # ------------------------------------------------------------------ loop policy local (issue 33)
    def _current_values(self, base: gtsam.Values | None = None) -> gtsam.Values:
        """iSAM2's estimate (or a copy of ``base``) with the variables a window rebuild left out."""
        vals = self._isam.calculateEstimate() if base is None else gtsam.Values(base)
        if self._frozen_keys:
            vals.insert_or_assign(self._frozen)
        return vals

    def _pose_estimate(self, kf_id: int) -> gtsam.Pose3:
        """The current estimate of keyframe ``kf_id``'s pose: iSAM2's, a deferred update's, or a rebuild's."""
        key = self._xkey[kf_id]  # X(kf_id)
        if key in self._frozen_keys:
            return self._frozen.atPose3(key)
        if self._deferred_values.exists(key):
            return self._deferred_values.atPose3(key)
        return self._isam.calculateEstimatePose3(key)

    def _point_estimate(self, key: int) -> F64:
        """The current estimate of landmark variable ``key``, wherever it is (see :meth:`_pose_estimate`)."""
        if key in self._frozen_keys:
            return self._frozen.atPoint3(key)
        if self._deferred_values.exists(key):
            return self._deferred_values.atPoint3(key)
        return self._isam.calculateEstimatePoint3(key)

    def _hold(self, key: int, value: Any, graph: gtsam.NonlinearFactorGraph) -> int:
        """A prior that holds variable ``key`` at ``value`` in iSAM2 only (kind proxy: dropped at the merge).

        Keyframes by the gauge prior's sigmas (fixed, as the old map under ``local``), landmarks by
        ``loop_sigma_m`` (as a proxy). Returns its factor id (recorded for the next update).
        """
        cfg = self.config
        if _is_pose_key(key):
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([cfg.prior_sigma_rad] * 3 + [cfg.prior_sigma_m] * 3))
            prior: gtsam.NonlinearFactor = gtsam.PriorFactorPose3(key, value, noise)
        else:
            prior = gtsam.PriorFactorPoint3(key, value, gtsam.noiseModel.Isotropic.Sigma(3, cfg.loop_sigma_m))
        graph.add(prior)
        fid = self._next_fid
        self._next_fid += 1
        self._factors[fid] = _FactorRecord(prior, "proxy")
        self._fixed_fids.append(fid)
        return fid

    def _thaw(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, new_fids: list[int]) -> None:
        """Variables of ``graph`` a rebuild left out return to iSAM2, held at their estimate by :meth:`_hold`.

        E.g. a new landmark first seen by a keyframe older than the rebuild's window; appends the
        priors' factor ids to ``new_fids``.
        """
        back = self._frozen_keys.intersection(graph.keyVector())
        if not back:
            return
        for key in sorted(back):
            if _is_pose_key(key):
                value: Any = self._frozen.atPose3(key)
                values.insert(key, value)
            else:
                value = self._frozen.atPoint3(key)
                values.insertPoint3(key, value)
            new_fids.append(self._hold(key, value, graph))
            self._frozen.erase(key)
            self._frozen_keys.discard(key)
            if _is_pose_key(key):
                self._frozen_kfs.discard(int(gtsam.Symbol(key).index()))

    def _rebuild_window(self, keep: int) -> None:
        """A fresh iSAM2 on the factors of the newest ``keep`` keyframes (``local_rebuild_kf``).

        Kept: every factor in iSAM2 whose landmarks (and proxies) the newest ``keep`` keyframes observe
        and whose keyframes are among them, or are older ones those factors name, each held by
        :meth:`_hold` at its estimate (the fixed old map of ``local``). Every other variable leaves
        iSAM2 at its estimate (:attr:`_frozen`); its factors stay recorded and join for the final
        estimate (:meth:`_merge_outside`). Only what is in iSAM2 is visited: the cost is bounded by
        the window, not the map.
        """
        self._flush_deferred()
        theta = self._isam.calculateEstimate()
        free = {X(k) for k in self._kf_order[-keep:]}
        is_pose = _is_pose_key
        keys_of = {fid: self._factors[fid].keys() for fid in self._slot}
        kept_vars = set(free)
        for keys in keys_of.values():
            if not free.isdisjoint(keys):
                kept_vars.update(keys)
        old_fixed = set(self._fixed_fids)
        self._fixed_fids = []
        fids: list[int] = []
        for fid, keys in keys_of.items():
            others = [k for k in keys if not is_pose(k)]
            # a landmark's or proxy's factor if the window keeps them; a pose-only one (a prior) if its
            # keyframes are free: an older keyframe's hold is made anew below
            if all(k in kept_vars for k in others) if others else free.issuperset(keys):
                fids.append(fid)
                if fid in old_fixed:
                    self._fixed_fids.append(fid)
        for fid in old_fixed.difference(fids):
            self._factors.pop(fid, None)
        graph = gtsam.NonlinearFactorGraph()
        for fid in fids:
            graph.add(self._factors[fid].factor)
        in_graph = set(graph.keyVector())
        for key in sorted(in_graph - free):
            if is_pose(key):
                fids.append(self._hold(key, theta.atPose3(key), graph))
        # theta split by copies and erasures (no value through Python, be17): iSAM2's part, the rest frozen
        values, out = gtsam.Values(theta), gtsam.Values(theta)
        for key in theta.keys():
            if key in in_graph:
                out.erase(key)
            else:
                values.erase(key)
                self._frozen_keys.add(key)
                if is_pose(key):
                    self._frozen_unread.append(int(gtsam.Symbol(key).index()))
                    self._frozen_kfs.add(self._frozen_unread[-1])
        self._frozen.insert(out)
        # be21: the rebuilt window checks relinearisation at its own cadence (local_rebuild_relinearize_skip;
        # be23b: by default never, the next rebuild relinearising it at its estimate)
        self._new_isam(self.config.local_rebuild_relinearize_skip)
        self._slot.clear()
        self._rebuilt_at = len(self._kf_order)
        self.window_rebuilds += 1
        try:
            result = self._isam_update(graph, values, [], constrainedKeys=self._ordering_groups(len(in_graph)))
        except RuntimeError as exc:
            self._recover(exc)
            return
        for fid, slot in zip(fids, result.getNewFactorsIndices(), strict=True):
            self._slot[fid] = slot

    def _merge_outside(self) -> None:
        """Every factor in one iSAM2 (``loop_policy`` local, before the final estimate).

        A fresh iSAM2 on all live factors (the proxies' left out) from the current estimate; from then
        on the back end is a plain one.
        """
        self._flush_deferred()
        theta = self._current_values()
        self._frozen, self._frozen_keys, self._frozen_kfs, self._fixed_fids = gtsam.Values(), set(), set(), []
        for fid in [f for f, rec in self._factors.items() if rec.kind == "proxy"]:
            del self._factors[fid]
        self._proxy.clear()
        self._proxy_fids.clear()
        keys: set[int] = set()
        for rec in self._factors.values():
            keys.update(rec.keys())
        values = gtsam.Values(theta)  # the variables the factors name, at the estimate (be17: erasures)
        for key in theta.keys():
            if key not in keys:
                values.erase(key)
        self._windowed = False
        self._outside.clear()
        self._estimate_all = True
        self._new_isam()
        self._slot.clear()
        self._batch.clear()
        fids = sorted(self._factors)
        graph = gtsam.NonlinearFactorGraph()
        for fid in fids:
            graph.add(self._factors[fid].factor)
        try:
            result = self._isam_update(graph, values, [], constrainedKeys=self._ordering_groups(len(keys)))
        except RuntimeError as exc:
            self._recover(exc)
            return
        for fid, slot in zip(fids, result.getNewFactorsIndices(), strict=True):
            self._slot[fid] = slot
