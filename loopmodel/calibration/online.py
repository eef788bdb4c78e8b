"""Self-calibration during the run (``calibration.refine: online``, issue 31 item 1).

Every ``online_every_kf`` keyframes the last ``online_window_kf`` go through the calibrating bundle
adjustment (:func:`loopmodel.calibration.selfcal.refine_final`, no laser, no combination held) off
the tracking thread (a worker process by default; the tracker only hands over the keyframes and
looks for the answer between frames). Each window's information about the calibration (its
posterior against the prior, in prior-whitened units) is added to the earlier windows'
(:class:`WindowFusion`; the windows share no keyframe, so their data are nearly independent), and
the fused estimate, with the combinations the windows together leave weak
(``observable_direction_ratio``) held at the recorded values, is the run's current calibration.

When it has moved more than ``online_switch_sigma`` prior sigmas from the one in force, the front
end's rectifier is rebuilt from it between frames (:meth:`RectifyingModel.following`, the left lens
kept as recorded and the right camera carrying the pair's refined relative geometry, :func:`left_kept`): the same
rectified pair (rectified camera matrices, baseline, the left rectifying rotation), so poses,
landmarks, the back end and the loop stage keep their meaning; the raw images are mapped through
the refined lenses and stereo rotation from then on. Measurements made after a switch are taken
back to the recorded rectification (:meth:`OnlineCalibration.keyframes_as_recorded`,
:meth:`OnlineCalibration.observations_as_recorded`: through the raw pixel they were measured at)
for the final refinement, which starts from the online estimate (``start_values``).
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing as mp
import time
from collections.abc import Mapping
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.calibration.refine_rig import N_PARAMS, RigParameters, prior_sigmas, raw_from_rectified_px
from loopmodel.calibration.selfcal import rays_from_raw_px, rectifying_rotations, refine_final
from loopmodel.config import SelfCalibrationConfig
from loopmodel.errors import LoopmodelError
from loopmodel.types import Keyframe, StereoCalibration

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class RectifyingModel:
    """A raw calibration and the rectification it was used with.

    ``rot_rect_from_cam`` (left, right: 3x3 rotations, rectified from each raw camera) and
    ``K_rect`` (left, right: the rectified camera matrices, pixels).
    """

    raw: StereoCalibration
    rot_rect_from_cam: tuple[F64, F64]
    K_rect: tuple[F64, F64]

    @classmethod
    def of(cls, calibration: StereoCalibration) -> RectifyingModel:
        """The recorded calibration's own rectification (OpenCV's, as the front end's :class:`Rectifier`)."""
        R1, R2, K1, K2 = rectifying_rotations(calibration)
        return cls(calibration, (R1, R2), (K1, K2))

    def following(self, refined: StereoCalibration) -> RectifyingModel:
        """``refined``'s lenses into this rectified pair: left rotation kept, right one ``R_left R_rl^T``.

        The rectified cameras keep their orientation, so a right point rectified with it lies on the
        left row up to the refined baseline direction's tilt in the rectified frame (a 0.02 deg
        rotation change: 3.5e-4 of the disparity).
        """
        R_left = self.rot_rect_from_cam[0]
        R_rl = refined.right_from_left[:3, :3]
        return RectifyingModel(refined, (R_left, R_left @ R_rl.T), self.K_rect)

    def rectified_px_in(self, uv_rect_px: F64, side: int, other: RectifyingModel) -> F64:
        """Rectified pixels of camera ``side`` (0 left, 1 right) measured with this model, in ``other``'s (N x 2).

        Each goes back to the raw pixel it was measured at (this model) and out through ``other``.
        """
        uv = np.asarray(uv_rect_px, float).reshape(-1, 2)
        if uv.shape[0] == 0:
            return uv.copy()
        cal, oth = self.raw, other.raw
        K, d = (cal.K_left, cal.dist_left) if side == 0 else (cal.K_right, cal.dist_right)
        raw = raw_from_rectified_px(uv, self.K_rect[side], self.rot_rect_from_cam[side], K, d)
        Ko, do = (oth.K_left, oth.dist_left) if side == 0 else (oth.K_right, oth.dist_right)
        p = rays_from_raw_px(raw, Ko, do) @ other.rot_rect_from_cam[side].T @ other.K_rect[side].T
        return p[:, :2] / p[:, 2:3]


def left_kept(refined: StereoCalibration, recorded: StereoCalibration) -> StereoCalibration:
    """``refined`` with the recorded left lens, the right camera moved so the pair's relative geometry stays refined.

    The right camera matrix ``K_r K_l^-1 K_l,recorded`` (refined ``K_r``, ``K_l``): the disparity offset
    and the focal-length ratio stay the refined ones while the left image is rectified as recorded, so
    the tracked left features do not jump at a switch. Measured on the rendered rig of
    tests/test_online_calib.py (final 0.41 mm): both lenses re-rectified 1.32 mm, the left kept
    0.66 mm; KITTI clip ATE (final 0.0495 m) 0.0585 / 0.0612 -> 0.0525 m.
    """
    K_right = refined.K_right @ np.linalg.inv(refined.K_left) @ recorded.K_left
    return StereoCalibration(
        recorded.K_left, K_right, refined.right_from_left, recorded.image_size, recorded.dist_left,
        refined.dist_right, False, refined.camera_model,
    )


def keyframe_in(kf: Keyframe, measured: RectifyingModel, other: RectifyingModel) -> Keyframe:
    """``kf`` with its pixels (stereo, right rows, monocular) moved from ``measured``'s rectification to ``other``'s.

    A keyframe without measured right rows has its right matches read at the left row.
    """
    st = np.asarray(kf.stereo_px, float).reshape(-1, 3)
    rows = np.asarray(kf.right_rows_px, float).ravel()
    has_rows = rows.size == st.shape[0]
    left = measured.rectified_px_in(st[:, [0, 2]], 0, other)
    right = measured.rectified_px_in(np.column_stack([st[:, 1], rows if has_rows else st[:, 2]]), 1, other)
    mono = np.asarray(kf.mono_obs, float).reshape(-1, 3).copy()
    if mono.shape[0]:
        mono[:, 1:3] = measured.rectified_px_in(mono[:, 1:3], 0, other)
    return dataclasses.replace(
        kf,
        stereo_px=np.column_stack([left[:, 0], right[:, 0], left[:, 1]]),
        right_rows_px=right[:, 1].copy() if has_rows else kf.right_rows_px,
        mono_obs=mono,
    )


@dataclass
class WindowInformation:
    """What one window told about the calibration, in prior-whitened units (``(theta - recorded) / sigma``).

    ``information`` (16 x 16, zero on parameters it did not estimate) and ``vector`` (``C^-1 x``,
    the posterior's information times its mean), the window's keyframes and its time (s).
    """

    information: F64
    vector: F64
    keyframes: int
    seconds: float


def window_information(
    keyframes: list[Keyframe],
    world_from_kf: dict[int, F64],
    recorded: StereoCalibration,
    config: SelfCalibrationConfig,
    measured_with: list[RectifyingModel | None] | None = None,
) -> WindowInformation | None:
    """The calibrating bundle adjustment of one window (poses, landmarks from the keyframes); None when it cannot run.

    ``measured_with``: per keyframe the model its pixels were measured with (None: the recorded
    one); they are taken back to the recorded rectification first.
    """
    t0 = time.perf_counter()
    base = RectifyingModel.of(recorded)
    kfs = [
        kf if m is None else keyframe_in(kf, m, base)
        for kf, m in zip(keyframes, measured_with or [None] * len(keyframes), strict=True)
    ]
    cfg = config.model_copy(update={"observable_direction_ratio": 1.0})  # held in the fusion, not per window
    try:
        sc = refine_final(kfs, world_from_kf, np.zeros(0, np.int64), np.zeros((0, 3)), recorded, cfg,
                          np.array([0.0, 0.0, 1.0]), 1.0)
    except (LoopmodelError, np.linalg.LinAlgError, ValueError) as exc:
        logger.info("online self-calibration: window not refined (%s)", exc)
        return None
    r = sc.rig
    act = np.flatnonzero(r.estimated)
    info = np.zeros((N_PARAMS, N_PARAMS))
    vec = np.zeros(N_PARAMS)
    if act.size and r.whitened_posterior.shape == (act.size, act.size):
        C_inv = np.linalg.inv(r.whitened_posterior)
        x = (r.values[act] - r.recorded_values[act]) / r.prior_sigma[act]
        info[np.ix_(act, act)] = C_inv - np.eye(act.size)  # the data's part (the prior's is the identity)
        vec[act] = C_inv @ x
    return WindowInformation(info, vec, len(kfs), time.perf_counter() - t0)


@dataclass
class WindowFusion:
    """The windows' information summed over the prior (identity, whitened units); the fused estimate."""

    information: F64 = field(default_factory=lambda: np.zeros((N_PARAMS, N_PARAMS)))
    vector: F64 = field(default_factory=lambda: np.zeros(N_PARAMS))
    windows: int = 0

    def add(self, w: WindowInformation) -> None:
        """One more window's information."""
        self.information += w.information
        self.vector += w.vector
        self.windows += 1

    def estimate(self, hold_ratio: float) -> tuple[F64, F64]:
        """The fused move (whitened, 16) with the combinations above ``hold_ratio`` posterior/prior held at 0.

        Returns the move and the posterior sigma over prior sigma per parameter (1 where not informed).
        """
        H = np.eye(N_PARAMS) + 0.5 * (self.information + self.information.T)
        C = np.linalg.inv(H)
        x = C @ self.vector
        ev, U = np.linalg.eigh(C)
        keep = np.sqrt(np.maximum(ev, 0.0)) <= hold_ratio
        x = U[:, keep] @ (U[:, keep].T @ x)
        return x, np.sqrt(np.maximum(np.diag(C), 0.0))


def _executor(kind: str) -> Executor | None:
    if kind == "inline":
        return None
    if kind == "thread" or mp.current_process().daemon:
        return ThreadPoolExecutor(1, thread_name_prefix="loopmodel-online-calib")
    return ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"))


class OnlineCalibration:
    """The run's online self-calibration: windows submitted, their answers fused, switches decided.

    Feed keyframes (without images) with :meth:`add_keyframe`; between frames :meth:`poll` returns
    the model the front end should rectify with when it changes (else None).
    """

    def __init__(self, recorded: StereoCalibration, config: SelfCalibrationConfig) -> None:
        self.recorded = recorded
        self.config = config
        self.base = RectifyingModel.of(recorded)
        self.current = self.base
        self.rig = RigParameters.of(recorded)
        self.sigma = prior_sigmas(
            config.sigma_focal_px, config.sigma_principal_px, config.sigma_k1, config.sigma_k2,
            config.sigma_rotation_deg, config.sigma_baseline_m,
        )
        self.fusion = WindowFusion()
        self.applied = np.zeros(N_PARAMS)  # the move (whitened) in force
        self.moved = np.zeros(N_PARAMS)  # the latest fused move
        #: (first timestamp, model) of each switch, in order
        self.switches: list[tuple[int, RectifyingModel]] = []
        self._keyframes: list[tuple[Keyframe, RectifyingModel | None]] = []
        self._since = 0
        self._pending: list[Future[WindowInformation | None]] = []
        self._executor = _executor(config.online_worker)
        self.window_seconds: list[float] = []
        self.submit_ms: list[float] = []

    # ------------------------------------------------------------------ during the run
    def add_keyframe(self, kf: Keyframe, world_from_kf: Mapping[int, F64]) -> None:
        """A new keyframe (measured with the model in force); every ``online_every_kf`` a window is submitted.

        ``world_from_kf``: the current keyframe poses (the back end's, as corrected so far).
        """
        t0 = time.perf_counter()
        self._keyframes.append((kf, None if self.current is self.base else self.current))
        self._since += 1
        n = self.config.online_window_kf
        if self._since < self.config.online_every_kf or len(self._keyframes) < n:
            return
        self._since = 0
        window = [(k, m) for k, m in self._keyframes[-n:] if int(k.id) in world_from_kf]
        poses = {int(k.id): np.asarray(world_from_kf[int(k.id)], float) for k, _m in window}
        args = ([k for k, _m in window], poses, self.recorded, self.config, [m for _k, m in window])
        if self._executor is None:
            w = window_information(*args)
            if w is not None:
                self._take(w)
        else:
            self._pending.append(self._executor.submit(window_information, *args))
        self.submit_ms.append(1e3 * (time.perf_counter() - t0))

    def _take(self, w: WindowInformation) -> None:
        self.fusion.add(w)
        self.window_seconds.append(w.seconds)
        self.moved, _ratio = self.fusion.estimate(self.config.observable_direction_ratio)

    def poll(self, timestamp_ns: int) -> RectifyingModel | None:
        """Finished windows fused; the new model when the fused calibration moved past ``online_switch_sigma``.

        ``timestamp_ns``: the frame about to be tracked (the first the new model rectifies).
        """
        self.collect()
        if float(np.max(np.abs(self.moved - self.applied))) <= self.config.online_switch_sigma:
            return None
        self.applied = self.moved.copy()
        self.current = self.base.following(left_kept(self.rig.calibration(self.values), self.recorded))
        self.switches.append((int(timestamp_ns), self.current))
        logger.info(
            "online self-calibration: re-rectified (window %d, largest move %.2f prior sigma)",
            self.fusion.windows, float(np.max(np.abs(self.applied))),
        )
        return self.current

    def collect(self) -> None:
        """The finished windows fused (none waited for)."""
        done = [f for f in self._pending if f.done()]
        for f in done:
            self._pending.remove(f)
            try:
                w = f.result()
            except Exception as exc:  # noqa: BLE001 - a failed window is logged, the run goes on
                logger.warning("online self-calibration: window failed (%s)", exc)
                continue
            if w is not None:
                self._take(w)

    @property
    def values(self) -> F64:
        """The calibration in force (:data:`~loopmodel.calibration.refine_rig.PARAM_NAMES` order)."""
        return self.rig.values + self.applied * self.sigma

    @property
    def latest_values(self) -> F64:
        """The latest fused calibration (the final refinement's start), in force or not."""
        return self.rig.values + self.moved * self.sigma

    def close(self) -> None:
        """Stop the worker: finished windows fused, pending ones dropped."""
        self.collect()
        self._pending.clear()
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None

    # ------------------------------------------------------------------ at the end
    def model_at(self, timestamp_ns: int) -> RectifyingModel | None:
        """The model a frame at ``timestamp_ns`` was rectified with (None: the recorded one)."""
        out = None
        for t, m in self.switches:
            if timestamp_ns >= t:
                out = m
        return out

    def keyframes_as_recorded(self, keyframes: list[Keyframe]) -> list[Keyframe]:
        """The keyframes with their pixels in the recorded rectification."""
        out = []
        for kf in keyframes:
            m = self.model_at(int(kf.timestamp_ns))
            out.append(kf if m is None else keyframe_in(kf, m, self.base))
        return out

    def observations_as_recorded(self, frames: list[Any]) -> list[Any]:
        """Frame results (``observed``: left rectified pixels) with their pixels in the recorded rectification."""
        out = []
        for fr in frames:
            m = self.model_at(int(fr.timestamp_ns))
            obs = getattr(fr, "observed", None)
            if m is None or obs is None:
                out.append(fr)
                continue
            uv = m.rectified_px_in(np.asarray(obs.uv_px, float), 0, self.base).astype(np.float32)
            out.append(dataclasses.replace(fr, observed=dataclasses.replace(obs, uv_px=uv)))
        return out

    def metrics(self) -> dict[str, Any]:
        """``metrics.json`` keys (``calibration_online_*``)."""
        return {
            "calibration_refine": "online",
            "calibration_online_windows": self.fusion.windows,
            "calibration_online_switches": len(self.switches),
            "calibration_online_moved_max_sigma": float(np.max(np.abs(self.applied))),
            "calibration_online_window_s_median": (
                float(np.median(self.window_seconds)) if self.window_seconds else None
            ),
            "calibration_online_submit_ms_max": float(np.max(self.submit_ms)) if self.submit_ms else None,
        }
