"""3-D recordings of a run with rerun (``pip install loopmodel[viz]``).

:class:`RerunRecorder` writes one recording on two timelines, ``frame`` (the frame index) and
``time`` (the sequence's time, seconds). Entity paths (world frame of the run, metres):

* ``world/camera`` — the current left camera (transform + pinhole) and ``world/camera/image``
  with ``world/camera/image/features`` (tracked corners coloured by track age; outliers red);
* ``world/path/online`` — the path as estimated live; ``world/path/final`` — the path after
  the latest correction (re-logged at every correction);
* ``world/keyframes`` — keyframe positions; ``world/landmarks`` — landmark points;
* ``world/stripes`` — laser points in the world; ``world/mesh`` — the (live) mesh;
* ``world/events`` — a line between the two keyframes of each loop or relocalization, and
  ``events`` (text log), also for loops found after the last keyframe (logged at the end);
* ``world/ground_truth`` — the sequence's ground-truth path when it has one, placed in the run's
  world by its pose at the first frame (origin alignment);
* ``metrics/<name>`` — per-frame scalars (track ms, inliers, keyframes, back-end ms).

Images are logged at most every ``image_every`` frames and downscaled by ``image_scale``;
point clouds are capped at ``max_points`` (every k-th point), so logging stays cheap. A blueprint
(:func:`blueprint`) lays the viewer out: the 3-D view large, the camera image and three plots beside it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import InputError
from loopmodel.listener import RunListener

if TYPE_CHECKING:
    from loopmodel.frontend import FrameResult, Keyframe, TrackedFeatures
    from loopmodel.result import RunResult
    from loopmodel.types import StereoFrame, Trajectory

F64 = NDArray[np.float64]

#: The entity paths a recording of a run holds (the test reads them back).
ENTITY_PATHS = (
    "world/camera",
    "world/camera/image",
    "world/camera/image/features",
    "world/path/online",
    "world/path/final",
    "world/keyframes",
    "world/landmarks",
    "world/stripes",
    "world/mesh",
    "world/events",
    "world/ground_truth",
    "events",
)

#: The plots of the blueprint (the other metrics stay in the recording, one click away).
BLUEPRINT_PLOTS = ("track_ms", "inliers", "keyframes")


def blueprint() -> Any:
    """The viewer layout: the 3-D world large on the left; the camera image and three plots on the right."""
    import rerun.blueprint as rrb

    plots = [rrb.TimeSeriesView(origin=f"metrics/{name}", name=name) for name in BLUEPRINT_PLOTS]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="3-D: paths, keyframes, stripes, mesh"),
            rrb.Vertical(rrb.Spatial2DView(origin="world/camera/image", name="left camera"), *plots),
            column_shares=[3, 1],
        ),
        rrb.TimePanel(timeline="frame", play_state="following", state="collapsed"),  # opens at the end of the run
        collapse_panels=True,
    )


@dataclass(frozen=True)
class RerunSink:
    """Where a recording goes: a ``.rrd`` file, a spawned viewer, or a viewer at an address."""

    path: Path | None = None
    spawn: bool = False
    connect: str | None = None

    @property
    def enabled(self) -> bool:
        """True when any sink is set."""
        return self.path is not None or self.spawn or self.connect is not None


def _import_rerun() -> Any:
    try:
        import rerun as rr
    except ImportError:
        raise InputError("--rerun", "rerun-sdk is not installed: pip install 'loopmodel[viz]'") from None
    return rr


def _age_colours(age: NDArray[np.int64], inlier: NDArray[np.bool_]) -> NDArray[np.uint8]:
    """Track age to colour: young blue → old green (saturating at 30 frames); outliers red."""
    a = np.clip(np.asarray(age, float) / 30.0, 0.0, 1.0)
    rgb = np.stack([np.zeros_like(a), 80 + 175 * a, 255 * (1 - a)], axis=1)
    rgb[~np.asarray(inlier, bool)] = (255, 40, 40)
    return rgb.astype(np.uint8)


def _subsample(points: F64, max_points: int) -> F64:
    p = np.asarray(points, float).reshape(-1, 3)
    if p.shape[0] <= max_points:
        return p
    return p[:: int(np.ceil(p.shape[0] / max_points))]


class RerunRecorder:
    """Logs a run to rerun. Every method is cheap when nothing is to be logged."""

    def __init__(
        self,
        sink: RerunSink,
        application_id: str = "loopmodel",
        image_every: int = 1,
        image_scale: float = 0.5,
        max_points: int = 50_000,
    ) -> None:
        rr = _import_rerun()
        self._rr = rr
        self.rec = rr.RecordingStream(application_id)
        layout = blueprint()
        if sink.path is not None:
            sink.path.parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(sink.path), default_blueprint=layout)
        elif sink.spawn:
            self.rec.spawn(default_blueprint=layout)
        elif sink.connect is not None:
            addr = sink.connect if "://" in sink.connect else f"rerun+http://{sink.connect}/proxy"
            self.rec.connect_grpc(addr, default_blueprint=layout)
        self.image_every = max(1, int(image_every))
        self.image_scale = float(image_scale)
        self.max_points = int(max_points)
        self._online: list[F64] = []
        self._K: F64 | None = None
        self._size: tuple[int, int] = (0, 0)
        # the run's world is its first left camera: x right, y down, z forward (issue 35: not z up)
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)

    # -- time ---------------------------------------------------------------------------------
    def set_frame(self, index: int, timestamp_ns: int) -> None:
        """Place what follows at frame ``index`` (sequence time ``timestamp_ns``)."""
        self._rr.set_time("frame", sequence=int(index), recording=self.rec)
        self._rr.set_time("time", duration=float(timestamp_ns) * 1e-9, recording=self.rec)

    # -- static -------------------------------------------------------------------------------
    def camera_model(self, K: F64, width_px: int, height_px: int) -> None:
        """The rectified left camera's intrinsics (pixels), logged once."""
        s = self.image_scale
        self._K = np.asarray(K, float)
        self._size = (int(width_px), int(height_px))
        Ks = self._K.copy()
        Ks[:2] *= s
        self.rec.log(
            "world/camera",
            self._rr.Pinhole(
                image_from_camera=Ks, resolution=[round(width_px * s), round(height_px * s)], image_plane_distance=0.05
            ),
            static=True,
        )

    # -- per frame ----------------------------------------------------------------------------
    def frame(
        self,
        index: int,
        timestamp_ns: int,
        world_from_cam: F64 | None,
        image: NDArray[np.uint8] | None = None,
        features_uv: F64 | None = None,
        track_age: NDArray[np.int64] | None = None,
        inlier: NDArray[np.bool_] | None = None,
        scalars: Mapping[str, float] | None = None,
    ) -> None:
        """One processed frame.

        Camera pose, image with tracked features (pixels of the rectified left image), path so far
        and scalars.
        """
        rr = self._rr
        self.set_frame(index, timestamp_ns)
        if world_from_cam is not None and np.all(np.isfinite(world_from_cam)):
            T = np.asarray(world_from_cam, float)
            self.rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            self._online.append(T[:3, 3].copy())
            if len(self._online) % 5 == 1 or len(self._online) < 5:
                self.rec.log("world/path/online", rr.LineStrips3D([np.array(self._online)], colors=[(255, 170, 0)]))
        if image is not None and index % self.image_every == 0:
            import cv2

            s = self.image_scale
            small = image if s == 1.0 else cv2.resize(image, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
            encoded, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 80])  # 2x faster than rerun
            if encoded:
                self.rec.log("world/camera/image", rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"))
            if features_uv is not None and len(features_uv):
                uv = np.asarray(features_uv, float).reshape(-1, 2) * s
                n = uv.shape[0]
                age = np.zeros(n, np.int64) if track_age is None else np.asarray(track_age)
                ok = np.ones(n, bool) if inlier is None else np.asarray(inlier, bool)
                self.rec.log("world/camera/image/features", rr.Points2D(uv, colors=_age_colours(age, ok), radii=1.5))
        for name, value in (scalars or {}).items():
            if value is not None and np.isfinite(value):
                self.rec.log(f"metrics/{name}", rr.Scalars(float(value)))

    # -- map ----------------------------------------------------------------------------------
    def keyframes(self, world_from_kf: F64) -> None:
        """All keyframe positions (N x 4 x 4 poses)."""
        T = np.asarray(world_from_kf, float).reshape(-1, 4, 4)
        self.rec.log("world/keyframes", self._rr.Points3D(T[:, :3, 3], colors=[(80, 200, 255)], radii=0.004))

    def landmarks(self, points_world: F64) -> None:
        """Landmark points (P x 3, metres)."""
        p = _subsample(points_world, self.max_points)
        self.rec.log("world/landmarks", self._rr.Points3D(p, colors=[(200, 200, 200)], radii=0.0015))

    def stripes(self, points_world: F64) -> None:
        """Laser points placed in the world (P x 3, metres)."""
        p = _subsample(points_world, self.max_points)
        self.rec.log("world/stripes", self._rr.Points3D(p, colors=[(40, 255, 40)], radii=0.0008))

    def mesh(self, vertices: F64, triangles: NDArray[np.int64], normals: F64 | None = None) -> None:
        """The (live) mesh in the world frame."""
        kw: dict[str, Any] = {}
        if normals is not None and len(normals) == len(vertices):
            kw["vertex_normals"] = np.asarray(normals, np.float32)
        self.rec.log(
            "world/mesh",
            self._rr.Mesh3D(
                vertex_positions=np.asarray(vertices, np.float32),
                triangle_indices=np.asarray(triangles, np.uint32),
                albedo_factor=(0.75, 0.72, 0.65, 1.0),
                **kw,
            ),
        )

    def final_path(self, world_from_cam: F64) -> None:
        """The whole path after the latest correction (N x 4 x 4)."""
        T = np.asarray(world_from_cam, float).reshape(-1, 4, 4)
        if len(T):
            self.rec.log("world/path/final", self._rr.LineStrips3D([T[:, :3, 3]], colors=[(60, 140, 255)]))

    def ground_truth(self, positions_world: F64) -> None:
        """The ground-truth path (N x 3, metres, the run's world), logged once."""
        p = np.asarray(positions_world, float).reshape(-1, 3)
        if len(p) >= 2:
            self.rec.log(
                "world/ground_truth", self._rr.LineStrips3D([p], colors=[(230, 230, 230)], radii=0.001), static=True
            )

    def event(self, text: str, a_world: F64 | None = None, b_world: F64 | None = None) -> None:
        """A loop or relocalization: a text line and a line between the matched positions."""
        self.rec.log("events", self._rr.TextLog(text, level="INFO"))
        if a_world is not None and b_world is not None:
            seg = np.stack([np.asarray(a_world, float)[:3], np.asarray(b_world, float)[:3]])
            self.rec.log("world/events", self._rr.LineStrips3D([seg], colors=[(255, 0, 255)], radii=0.002))

    def close(self) -> None:
        """Flush and close the recording."""
        self.rec.flush()
        self.rec.disconnect()


def ground_truth_in_run_world(gt: Trajectory, first_ns: int) -> F64:
    """Ground-truth positions (N x 3, metres) in a run's world.

    Its pose at the run's first frame (time ``first_ns``) becomes the origin, as the run's world is
    its first camera (origin alignment).
    """
    k = int(np.argmin(np.abs(gt.timestamps_ns.astype(np.int64) - int(first_ns))))
    cam0_from_gtworld = np.linalg.inv(gt.world_from_cam[k])
    return np.asarray(gt.world_from_cam[:, :3, 3] @ cam0_from_gtworld[:3, :3].T + cam0_from_gtworld[:3, 3])


class RerunListener(RunListener):
    """Records a run as it happens (:class:`~loopmodel.listener.RunListener` for the pipeline).

    Per frame: camera pose, rectified left image with its tracked features (coloured by the
    frames since their keyframe; pose outliers red), the online path and scalars. Per
    keyframe: keyframe positions. On a correction: the corrected path (every frame recomposed
    from its keyframe's pose, as the run's anchored trajectory does), at most every
    ``path_every`` corrections and always after a loop event. Loop events as text and lines;
    the live mesh when it changes; at the end the final path, landmarks, stripes and mesh.
    """

    def __init__(
        self,
        recorder: RerunRecorder,
        K_rect: F64,
        image_size: tuple[int, int],
        path_every: int = 10,
        ground_truth: Trajectory | None = None,
    ) -> None:
        self.rec = recorder
        self.ground_truth = ground_truth
        self._events_logged = 0
        self.rec.camera_model(K_rect, image_size[0], image_size[1])
        self.path_every = max(1, int(path_every))
        self._world_from_kf: dict[int, F64] = {}
        self._kf_frame: dict[int, int] = {}
        self._anchor: list[tuple[int, F64]] = []  # per OK frame: keyframe id, kf_from_cam
        self._corrections = 0
        self._n = 0
        self._t_ns = 0

    def on_frame(self, frame: StereoFrame, result: FrameResult, tracks: TrackedFeatures) -> None:
        """Pose, image, features and scalars of one frame."""
        self._n, self._t_ns = int(frame.index), int(result.timestamp_ns)
        if self.ground_truth is not None and len(self.ground_truth):
            self._log_ground_truth(self.ground_truth, self._t_ns)
            self.ground_truth = None  # once
        if result.is_keyframe:
            self._kf_frame[result.keyframe_id] = self._n
        if result.ok:
            self._anchor.append((result.keyframe_id, np.asarray(result.kf_from_cam, float)))
        uv = np.vstack([tracks.inlier_px.reshape(-1, 2), tracks.outlier_px.reshape(-1, 2)])
        age = np.full(len(uv), self._n - self._kf_frame.get(tracks.keyframe_id, self._n), np.int64)
        inlier = np.arange(len(uv)) < len(tracks.inlier_px)
        self.rec.frame(
            self._n,
            self._t_ns,
            result.world_from_cam if result.ok else None,
            image=tracks.left_rect,
            features_uv=uv,
            track_age=age,
            inlier=inlier,
            scalars={
                "track_ms": result.track_ms,
                "keyframe_ms": result.keyframe_ms,
                "inliers": float(result.inliers),
                "tracked": float(result.tracked),
                "keyframes": float(len(self._world_from_kf)),
            },
        )

    def on_keyframe(self, keyframe: Keyframe, result: FrameResult) -> None:
        """Keyframe positions after the keyframe joined the map."""
        self._world_from_kf[keyframe.id] = np.asarray(keyframe.world_from_kf, float)
        self.rec.keyframes(np.stack(list(self._world_from_kf.values())))

    def on_correction(self, world_from_kf: Mapping[int, F64]) -> None:
        """Corrected keyframes; the corrected path every ``path_every`` corrections."""
        for k, T in world_from_kf.items():
            self._world_from_kf[int(k)] = np.asarray(T, float)
        self._corrections += 1
        if self._corrections % self.path_every == 0:
            self._log_corrected_path()

    def _log_corrected_path(self) -> None:
        poses = [self._world_from_kf[k] @ T for k, T in self._anchor if k in self._world_from_kf]
        if poses:
            self.rec.final_path(np.stack(poses))
        if self._world_from_kf:
            self.rec.keyframes(np.stack(list(self._world_from_kf.values())))

    def on_live_mesh(self, mesh: Any) -> None:
        """The live mesh as it grows and moves with corrections."""
        if mesh is not None and len(mesh.triangles):
            self.rec.mesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles))

    def _log_ground_truth(self, gt: Trajectory, first_ns: int) -> None:
        self.rec.ground_truth(ground_truth_in_run_world(gt, first_ns))

    def on_loop_events(self, events: list[dict[str, Any]]) -> None:
        """Each loop closure or relocalization as text and a line between its keyframes."""
        self._log_events(events)
        self._log_corrected_path()

    def _log_events(self, events: list[dict[str, Any]]) -> None:
        for ev in events:
            self._events_logged += 1
            a = self._world_from_kf.get(int(ev.get("keyframe", -1)))
            b = self._world_from_kf.get(int(ev.get("match_keyframe", -1)))
            text = (
                f"{ev.get('type', 'event')}: keyframe {ev.get('keyframe')} ↔ {ev.get('match_keyframe')}, "
                f"{ev.get('inliers', '?')} inliers, correction {1e3 * float(ev.get('correction_m') or 0.0):.2f} mm"
            )
            self.rec.event(text, None if a is None else a[:3, 3], None if b is None else b[:3, 3])

    def on_finish(self, result: RunResult) -> None:
        """The final path, landmarks, stripes and mesh; then the recording is closed."""
        try:
            self.rec.set_frame(self._n, self._t_ns)
            self.rec.final_path(result.final.world_from_cam)
            if len(result.keyframes):
                self.rec.keyframes(result.keyframes.world_from_cam)
                for kid, T in zip(result.keyframe_ids.tolist(), result.keyframes.world_from_cam, strict=True):
                    self._world_from_kf[int(kid)] = np.asarray(T, float)
            events = [e for e in result.metrics.get("loop_events") or [] if isinstance(e, dict)]
            self._log_events(events[self._events_logged :])  # loops found after the last keyframe
            if result.landmarks_in_world is not None and len(result.landmarks_in_world):
                self.rec.landmarks(result.landmarks_in_world)
            if result.stripes:
                from loopmodel.mapping.stripe_map import StripeMap

                placed = StripeMap.from_trajectory(result.final, result.stripes).world_points()
                if len(placed):
                    self.rec.stripes(placed)
            if result.mesh is not None and len(result.mesh.triangles):
                m = result.mesh
                self.rec.mesh(np.asarray(m.vertices), np.asarray(m.triangles))
        finally:
            self.rec.close()
