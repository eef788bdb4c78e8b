"""A session's map: what a later session needs to localize in it, extend it or merge with it (issue 20).

Per keyframe: id, time, pose ``world_from_kf`` (left camera, metres), ``rect_from_cam``, the
session it came from, its stereo landmarks (ids, points in the keyframe frame, rectified stereo
pixels), its rectified left image (PNG, decoded only when a stage needs it: re-detection, KLT)
and its loop-closing feature set (keypoints, descriptors, 3-D points in the rectified keyframe
frame, landmark ids) of the configured descriptor kind, with the vocabulary and every keyframe's
bag of words (the rows of the inverted file). The map also holds the landmarks in the world, the
pose graph (odometry and loop constraints ``kf_a_from_kf_b``), the laser stripes anchored to
keyframes (``kf_from_cam`` of the stripe's sensor pose), the stereo calibration of the keyframes'
pixels, and the configuration of the run that made it.

Arrays are stored columnar (offsets per keyframe), so a 1,000-keyframe map loads in a second or
two; the file is :mod:`loopmodel.io.map_file`'s.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.config import LoopConfig
from loopmodel.errors import InputError
from loopmodel.imaging.codec import declared_image_size, decode_quietly
from loopmodel.loop.database import KeyframeDatabase, PlaceParams
from loopmodel.loop.descriptors import descriptor
from loopmodel.loop.features import FeatureSet, empty_features
from loopmodel.loop.vocabulary import Vocabulary
from loopmodel.types import Keyframe, MapFileData, StereoCalibration, StripeAnchors, StripeProfile, Trajectory

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Pose-graph edge kinds.
EDGE_ODOMETRY, EDGE_LOOP, EDGE_SESSIONS = 0, 1, 2


@dataclass
class PackedFeatures:
    """The loop-closing feature sets of every keyframe of one descriptor kind, concatenated.

    ``offsets`` (N+1,) into the feature rows; ``words`` (F,) each feature's vocabulary word;
    ``bow_offsets`` (N+1,), ``bow_words``, ``bow_weights``: each keyframe's TF-IDF bag of words (the
    inverted file's rows)."""

    kind: str
    offsets: I64
    keypoints_px: F64
    descriptors: NDArray[Any]
    points_in_kf: F64
    ids: I64
    laplacian: NDArray[np.int8]
    words: I64
    bow_offsets: I64
    bow_words: I64
    bow_weights: F64
    vocabulary: Vocabulary

    def __post_init__(self) -> None:
        # the values the map file keeps (see ``_STORED``), so a saved map loads back equal
        for name in ("keypoints_px", "points_in_kf", "bow_weights"):
            setattr(self, name, _as_stored(getattr(self, name), np.float32))
        stored = descriptor(self.kind).stored_dtype
        if stored is not None and not descriptor(self.kind).binary:  # rounded as the map file keeps them
            self.descriptors = _as_stored(self.descriptors, stored, np.float32)

    def feature_set(self, i: int) -> FeatureSet:
        """Keyframe ``i``'s (row index) feature set (views of the arrays)."""
        a, b = int(self.offsets[i]), int(self.offsets[i + 1])
        return FeatureSet(
            self.keypoints_px[a:b],
            self.descriptors[a:b],
            self.kind,
            self.points_in_kf[a:b],
            self.ids[a:b],
            self.laplacian[a:b],
        )

    @staticmethod
    def pack(kind: str, sets: Sequence[FeatureSet], vocabulary: Vocabulary) -> PackedFeatures:
        """Concatenate feature sets (one per keyframe, in row order) with their words and bags."""
        dim = sets[0].descriptors.shape[1] if sets else descriptor(kind).dim
        dtype = sets[0].descriptors.dtype if sets else descriptor(kind).dtype
        words = [vocabulary.transform(s.descriptors) for s in sets]
        bows = [vocabulary.bow(words=w) for w in words]

        def cat(parts: list[NDArray[Any]], shape: tuple[int, ...], dt: Any) -> NDArray[Any]:
            return np.concatenate(parts) if parts else np.zeros(shape, dt)

        return PackedFeatures(
            kind,
            _offsets([len(s) for s in sets]),
            cat([s.keypoints_px for s in sets], (0, 2), float),
            cat([s.descriptors for s in sets], (0, dim), dtype),
            cat([s.points_in_kf for s in sets], (0, 3), float),
            cat([s.ids for s in sets], (0,), np.int64),
            cat([s.laplacian for s in sets], (0,), np.int8),
            cat(words, (0,), np.int64),
            _offsets([b[0].size for b in bows]),
            cat([b[0] for b in bows], (0,), np.int64),
            cat([b[1] for b in bows], (0,), float),
            vocabulary,
        )

    def subset(self, rows: I64) -> PackedFeatures:
        """The feature sets of keyframe rows ``rows`` (in that order)."""
        return _concat_packed([self], [rows])


def _calibration_arrays(prefix: str, cal: StereoCalibration) -> dict[str, NDArray[Any]]:
    """A raw calibration's arrays in the map file (``<prefix>_K_left`` ...)."""
    return {
        f"{prefix}_K_left": cal.K_left,
        f"{prefix}_K_right": cal.K_right,
        f"{prefix}_right_from_left": cal.right_from_left,
        f"{prefix}_dist_left": np.asarray(cal.dist_left, float),
        f"{prefix}_dist_right": np.asarray(cal.dist_right, float),
    }


def _map_calibration(arrays: dict[str, NDArray[Any]], meta: Any) -> MapCalibration | None:
    """The map file's refined calibration (None when the map has none: written before issue 31 item 4)."""
    if not isinstance(meta, dict) or "refined_K_left" not in arrays:
        return None

    def cal(prefix: str) -> StereoCalibration:
        return StereoCalibration(
            arrays[f"{prefix}_K_left"],
            arrays[f"{prefix}_K_right"],
            arrays[f"{prefix}_right_from_left"],
            tuple(int(v) for v in meta["image_size"]),  # type: ignore[arg-type]
            arrays[f"{prefix}_dist_left"],
            arrays[f"{prefix}_dist_right"],
            False,
            str(meta.get("camera_model", "pinhole")),
        )

    sigma = {str(k): float(v) for k, v in dict(meta.get("sigma", {})).items()}
    prior = {str(k): float(v) for k, v in dict(meta.get("sigma_prior", {})).items()}
    return MapCalibration(cal("refined"), cal("recorded"), sigma, prior)


def _offsets(counts: Sequence[int]) -> I64:
    return np.concatenate([[0], np.cumsum(np.asarray(counts, dtype=np.int64))]).astype(np.int64)


def _ranges(offsets: I64, rows: I64) -> I64:
    """Indices of the items of ``rows`` (each row's ``offsets[r]:offsets[r+1]``), in order."""
    parts = [np.arange(offsets[r], offsets[r + 1]) for r in rows]
    return np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, np.int64)


def _concat_packed(packs: Sequence[PackedFeatures], rows: Sequence[I64]) -> PackedFeatures:
    """The chosen keyframe rows of several packs (same kind and vocabulary), one after the other."""
    f_idx = [_ranges(p.offsets, r) for p, r in zip(packs, rows, strict=True)]
    b_idx = [_ranges(p.bow_offsets, r) for p, r in zip(packs, rows, strict=True)]

    def cat(name: str, idx: list[I64]) -> NDArray[Any]:
        return np.concatenate([getattr(p, name)[i] for p, i in zip(packs, idx, strict=True)])

    counts = np.concatenate([np.diff(p.offsets)[r] for p, r in zip(packs, rows, strict=True)])
    bcounts = np.concatenate([np.diff(p.bow_offsets)[r] for p, r in zip(packs, rows, strict=True)])
    return PackedFeatures(
        packs[0].kind,
        _offsets(counts.tolist()),
        cat("keypoints_px", f_idx),
        cat("descriptors", f_idx),
        cat("points_in_kf", f_idx),
        cat("ids", f_idx),
        cat("laplacian", f_idx),
        cat("words", f_idx),
        _offsets(bcounts.tolist()),
        cat("bow_words", b_idx),
        cat("bow_weights", b_idx),
        packs[0].vocabulary,
    )


@dataclass
class MapCalibration:
    """The rig's calibration as the session that made the map refined it (issue 31, ``calibration.refine``).

    ``refined``: the raw (unrectified) calibration after the refinement; ``recorded``: the raw one
    that session started from; ``sigma`` / ``sigma_prior``: each parameter's posterior and prior
    standard deviation by :data:`~loopmodel.calibration.refine_rig.PARAM_NAMES` (pixels, radial terms,
    degrees, metres). A later session of the same rig starts from ``refined`` (:mod:`loopmodel.sessions`).
    """

    refined: StereoCalibration
    recorded: StereoCalibration
    sigma: dict[str, float]
    sigma_prior: dict[str, float]

    @staticmethod
    def from_report(refined: StereoCalibration, recorded: StereoCalibration, report: dict[str, Any]) -> MapCalibration:
        """From a run's refined calibration and its report (``SelfCalibration.report()``)."""
        params = dict(report.get("parameters", {}))
        return MapCalibration(
            refined,
            recorded,
            {str(n): float(p["sigma"]) for n, p in params.items()},
            {str(n): float(p["sigma_prior"]) for n, p in params.items()},
        )


@dataclass
class SessionMap:
    """A saved map (see the module docstring); row ``i`` of every per-keyframe array is one keyframe.

    Poses ``world_from_kf`` (N, 4, 4) of the left camera, metres, in the map's world (the first
    session's first keyframe). ``stripe_kf`` / ``stripe_kf_from_cam`` anchor stripe ``s`` to a
    keyframe id; ``edges`` (E, 2) keyframe ids ``(a, b)`` with ``edge_a_from_b`` (E, 4, 4) and
    ``edge_kind`` (odometry, loop, between sessions)."""

    calibration: StereoCalibration
    keyframe_ids: I64
    timestamps_ns: I64
    world_from_kf: F64
    rect_from_cam: F64
    frame_index: I64
    session: I64
    lm_offsets: I64
    lm_ids: I64
    lm_points_in_kf: F64
    lm_stereo_px: F64
    features: PackedFeatures
    image_offsets: I64
    images_png: NDArray[np.uint8]
    landmark_ids: I64
    landmarks_in_world: F64
    edges: I64
    edge_a_from_b: F64
    edge_kind: NDArray[np.int8]
    stripe_timestamps_ns: I64
    stripe_offsets: I64
    stripe_points_in_cam: F64
    stripe_kf: I64
    stripe_kf_from_cam: F64
    config_yaml: str = ""
    info: dict[str, Any] = field(default_factory=dict)
    # issue 31 item 4: the calibration the map's session refined (None: not refined, or an older map)
    refined_calibration: MapCalibration | None = None

    def __post_init__(self) -> None:
        for name in ("lm_points_in_kf", "lm_stereo_px", "stripe_points_in_cam"):
            setattr(self, name, _as_stored(getattr(self, name), np.float32))

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return int(self.keyframe_ids.size)

    def row_of(self) -> dict[int, int]:
        """Keyframe id -> row."""
        return {int(k): i for i, k in enumerate(self.keyframe_ids.tolist())}

    def pose_of(self) -> dict[int, F64]:
        """Keyframe id -> ``world_from_kf``."""
        return {int(k): self.world_from_kf[i] for i, k in enumerate(self.keyframe_ids.tolist())}

    def image(self, i: int) -> NDArray[np.uint8]:
        """Row ``i``'s rectified left grey image (empty when the map has none)."""
        a, b = int(self.image_offsets[i]), int(self.image_offsets[i + 1])
        if b <= a:
            return np.zeros((0, 0), np.uint8)
        img = decode_quietly(self.images_png[a:b])
        if img is None or img.dtype != np.uint8 or img.ndim != 2:  # damaged after its header: no image
            return np.zeros((0, 0), np.uint8)
        return np.asarray(img)

    def keyframe(self, i: int, with_image: bool = True) -> Keyframe:
        """Row ``i`` as a :class:`~loopmodel.types.Keyframe` (stereo landmarks, pose, image)."""
        a, b = int(self.lm_offsets[i]), int(self.lm_offsets[i + 1])
        return Keyframe(
            int(self.keyframe_ids[i]),
            int(self.timestamps_ns[i]),
            self.world_from_kf[i].copy(),
            self.lm_ids[a:b],
            self.lm_points_in_kf[a:b],
            self.lm_stereo_px[a:b],
            image=self.image(i) if with_image else np.zeros((0, 0), np.uint8),
            frame_index=int(self.frame_index[i]),
            rect_from_cam=self.rect_from_cam[i].copy(),
            segment=int(self.session[i]),
        )

    def database(self, params: PlaceParams | None = None) -> KeyframeDatabase:
        """A place-recognition database of the map's keyframes (its vocabulary and bags of words)."""
        db = KeyframeDatabase(self.features.vocabulary, params)
        f = self.features
        for i, k in enumerate(self.keyframe_ids.tolist()):
            a, b = int(f.bow_offsets[i]), int(f.bow_offsets[i + 1])
            lo, hi = int(f.offsets[i]), int(f.offsets[i + 1])
            db.add_precomputed(int(k), f.feature_set(i), f.words[lo:hi], f.bow_words[a:b], f.bow_weights[a:b])
        return db

    def stripes_with_poses(self) -> tuple[list[StripeProfile], F64]:
        """The stripes and their sensor poses ``world_from_cam`` (S, 4, 4) from their anchors."""
        pose = self.pose_of()
        out: list[StripeProfile] = []
        poses = np.empty((self.stripe_kf.size, 4, 4))
        for s, k in enumerate(self.stripe_kf.tolist()):
            a, b = int(self.stripe_offsets[s]), int(self.stripe_offsets[s + 1])
            out.append(StripeProfile(int(self.stripe_timestamps_ns[s]), self.stripe_points_in_cam[a:b]))
            poses[s] = pose[int(k)] @ self.stripe_kf_from_cam[s]
        return out, poses

    def summary(self) -> dict[str, Any]:
        """Plain numbers for ``loopmodel map info``."""
        sessions, counts = np.unique(self.session, return_counts=True)
        pos = self.world_from_kf[:, :3, 3]
        extent = (pos.max(axis=0) - pos.min(axis=0)).tolist() if len(self) else [0.0, 0.0, 0.0]
        return {
            "keyframes": len(self),
            "sessions": {int(s): int(c) for s, c in zip(sessions, counts, strict=True)},
            "descriptor": self.features.kind,
            "features": int(self.features.keypoints_px.shape[0]),
            "vocabulary_words": self.features.vocabulary.n_words,
            "keyframe_landmarks": int(self.lm_ids.size),
            "landmarks": int(self.landmark_ids.size),
            "pose_graph_edges": {
                "odometry": int(np.sum(self.edge_kind == EDGE_ODOMETRY)),
                "loop": int(np.sum(self.edge_kind == EDGE_LOOP)),
                "between_sessions": int(np.sum(self.edge_kind == EDGE_SESSIONS)),
            },
            "stripes": int(self.stripe_kf.size),
            "stripe_points": int(self.stripe_points_in_cam.shape[0]),
            "images": int(np.sum(np.diff(self.image_offsets) > 0)),
            "keyframe_extent_m": extent,
            "calibration": self.calibration.summary(),
            "calibration_refined": self.refined_calibration is not None,
            **{k: v for k, v in self.info.items() if k in ("loopmodel_version", "version", "sequence")},
        }

    # ------------------------------------------------------------------ file
    def to_file_data(self) -> MapFileData:
        """The arrays and the JSON description of the map file."""
        c = self.calibration
        f = self.features
        v = f.vocabulary
        arrays: dict[str, NDArray[Any]] = {
            "calib_K_left": c.K_left,
            "calib_K_right": c.K_right,
            "calib_right_from_left": c.right_from_left,
            "calib_dist_left": c.dist_left,
            "calib_dist_right": c.dist_right,
            "vocabulary_centers": v.centers,
            "vocabulary_children": v.children,
            "vocabulary_word": v.word,
            "vocabulary_idf": v.idf,
        }
        for name in _KF_ARRAYS + _OTHER_ARRAYS:
            arrays[name] = getattr(self, name)
        rc = self.refined_calibration
        if rc is not None:  # optional arrays: a map without them loads as before
            for prefix, cal in (("refined", rc.refined), ("recorded", rc.recorded)):
                arrays.update(_calibration_arrays(prefix, cal))
        for name in _FEATURE_ARRAYS:
            arrays[f"features_{name}"] = getattr(f, name)
        for name, dtype in _stored_dtypes(f).items():
            arrays[name] = _to_storage(arrays[name], dtype, name)
        meta = {
            "calibration": {
                "image_size": list(c.image_size),
                "rectified": c.rectified,
                "camera_model": c.camera_model,
            },
            "descriptor": f.kind,
            "vocabulary_binary": v.binary,
            "vocabulary_info": v.info,
            "config_yaml": self.config_yaml,
            "info": self.info,
            "keyframes": len(self),
        }
        if rc is not None:
            meta["calibration_refined"] = {
                "image_size": list(rc.refined.image_size),
                "camera_model": rc.refined.camera_model,
                "sigma": dict(rc.sigma),
                "sigma_prior": dict(rc.sigma_prior),
            }
        return MapFileData(meta, arrays)

    @classmethod
    def from_file_data(cls, data: MapFileData) -> SessionMap:
        """The map of a map file's content (:func:`loopmodel.io.map_file.load_session_map` reads it)."""
        a, m = data.arrays, data.meta
        cal = m["calibration"]
        calibration = StereoCalibration(
            a["calib_K_left"],
            a["calib_K_right"],
            a["calib_right_from_left"],
            tuple(cal["image_size"]),
            a.get("calib_dist_left", np.zeros(5)),
            a.get("calib_dist_right", np.zeros(5)),
            bool(cal["rectified"]),
            str(cal["camera_model"]),
        )
        voc = Vocabulary(
            a["vocabulary_centers"],
            a["vocabulary_children"],
            a["vocabulary_word"],
            a["vocabulary_idf"],
            bool(m["vocabulary_binary"]),
            dict(m.get("vocabulary_info", {})),
        )
        a = {k: _from_storage(k, v, str(m["descriptor"])) for k, v in a.items()}
        fa = {n: a[f"features_{n}"] for n in _FEATURE_ARRAYS}
        feats = PackedFeatures(kind=str(m["descriptor"]), vocabulary=voc, **fa)
        kw = {n: a[n] for n in _KF_ARRAYS + _OTHER_ARRAYS}
        smap = cls(
            calibration=calibration,
            refined_calibration=_map_calibration(a, m.get("calibration_refined")),
            features=feats,
            config_yaml=str(m.get("config_yaml", "")),
            info={
                **dict(m.get("info", {})),
                "loopmodel_version": m.get("loopmodel_version"),
                "version": m.get("version"),
            },
            **kw,
        )
        smap.check()
        return smap

    def check(self) -> None:
        """Raise ValueError unless the per-keyframe arrays and offsets agree."""
        n = len(self)
        for name in ("timestamps_ns", "frame_index", "session"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"{name} has {getattr(self, name).shape[0]} rows, not {n}")
        for name in ("world_from_kf", "rect_from_cam"):
            if getattr(self, name).shape != (n, 4, 4):
                raise ValueError(f"{name} is not ({n}, 4, 4)")
        for name, off, rows in (
            ("lm_offsets", self.lm_offsets, self.lm_ids.shape[0]),
            ("image_offsets", self.image_offsets, self.images_png.shape[0]),
            ("features_offsets", self.features.offsets, self.features.keypoints_px.shape[0]),
            ("features_bow_offsets", self.features.bow_offsets, self.features.bow_words.shape[0]),
            ("stripe_offsets", self.stripe_offsets, self.stripe_points_in_cam.shape[0]),
        ):
            size = n + 1 if name != "stripe_offsets" else self.stripe_kf.size + 1
            if off.shape != (size,) or off[0] != 0 or off[-1] != rows or np.any(np.diff(off) < 0):
                raise ValueError(f"{name} do not match their rows")
        known = set(self.keyframe_ids.tolist())
        if len(known) != n:
            raise ValueError("keyframe ids are not unique")
        self._check_values()
        if not set(self.stripe_kf.tolist()) <= known or not set(self.edges.ravel().tolist()) <= known:
            raise ValueError("a stripe or pose-graph edge names an unknown keyframe")


    def _check_values(self) -> None:
        """Raise ValueError on non-finite poses and points, or an image that is no PNG of the camera's size.

        Checked when a map is loaded (issue 34): a damaged image would otherwise reach the KLT of a
        relocalization as an empty image.
        """
        for name in ("world_from_kf", "rect_from_cam", "edge_a_from_b", "stripe_kf_from_cam", "landmarks_in_world"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise ValueError(f"{name} has non-finite values")
        for name in ("lm_points_in_kf", "lm_stereo_px"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise ValueError(f"{name} has non-finite values")
        size = tuple(int(v) for v in self.calibration.image_size)
        for i in range(len(self)):
            a, b = int(self.image_offsets[i]), int(self.image_offsets[i + 1])
            if b <= a:
                continue  # a keyframe stored without its image
            found = declared_image_size(self.images_png[a : min(b, a + 64)].tobytes())
            if self.images_png[a : a + 8].tobytes() != b"\x89PNG\r\n\x1a\n" or found != size:
                raise ValueError(
                    f"image of keyframe {int(self.keyframe_ids[i])} is not a {size[0]}x{size[1]} PNG"
                    + (f" (it declares {found[0]}x{found[1]})" if found else "")
                )


_KF_ARRAYS = (
    "keyframe_ids",
    "timestamps_ns",
    "world_from_kf",
    "rect_from_cam",
    "frame_index",
    "session",
    "lm_offsets",
    "lm_ids",
    "lm_points_in_kf",
    "lm_stereo_px",
    "image_offsets",
    "images_png",
)
_OTHER_ARRAYS = (
    "landmark_ids",
    "landmarks_in_world",
    "edges",
    "edge_a_from_b",
    "edge_kind",
    "stripe_timestamps_ns",
    "stripe_offsets",
    "stripe_points_in_cam",
    "stripe_kf",
    "stripe_kf_from_cam",
)
_FEATURE_ARRAYS = (
    "offsets",
    "keypoints_px",
    "descriptors",
    "points_in_kf",
    "ids",
    "laplacian",
    "words",
    "bow_offsets",
    "bow_words",
    "bow_weights",
)
#: The arrays a map file must hold (checked when it is read).
REQUIRED_ARRAYS = (
    *_KF_ARRAYS,
    *_OTHER_ARRAYS,
    *(f"features_{n}" for n in _FEATURE_ARRAYS),
    "calib_K_left",
    "calib_K_right",
    "calib_right_from_left",
    "vocabulary_centers",
    "vocabulary_children",
    "vocabulary_word",
    "vocabulary_idf",
)


#: How the map file stores arrays that are held wider in memory (issue 20: map size).
#: float32 (24-bit mantissa, relative 6e-8): keypoints and stereo pixels (under 1e-4 px at 1,280 px),
#: 3-D points in their keyframe's frame and stripe points (under 0.1 um at 1 m, 3 um at 50 m),
#: bag-of-words weights. The in-memory arrays are rounded to these values when a map is made
#: (``__post_init__``), so a saved map loads back equal. Ids and words: int32 (checked). Poses,
#: calibration and the vocabulary stay float64. Descriptors: ORB as computed (uint8), SIFT as uint8
#: (OpenCV's SIFT values are whole numbers 0..255; checked, else float32), SURF as float16 (its unit
#: vectors' components to 5e-4 relative).
_STORED: dict[str, Any] = {
    "lm_points_in_kf": np.float32,
    "lm_stereo_px": np.float32,
    "stripe_points_in_cam": np.float32,
    "features_keypoints_px": np.float32,
    "features_points_in_kf": np.float32,
    "features_bow_weights": np.float32,
    "lm_ids": np.int32,
    "landmark_ids": np.int32,
    "features_ids": np.int32,
    "features_words": np.int32,
    "features_bow_words": np.int32,
}
#: the in-memory dtype of each stored array (descriptors: by kind)
_MEMORY: dict[str, Any] = {k: (np.float64 if np.dtype(v).kind == "f" else np.int64) for k, v in _STORED.items()}


def _as_stored(a: NDArray[Any], stored: Any, memory: Any = np.float64) -> NDArray[Any]:
    """``a`` rounded to the ``stored`` dtype, held as ``memory``."""
    return np.asarray(a).astype(stored).astype(memory)


def _stored_dtypes(f: PackedFeatures) -> dict[str, Any]:
    out = dict(_STORED)
    d = f.descriptors
    stored = descriptor(f.kind).stored_dtype
    if stored is not None:
        out["features_descriptors"] = stored
    elif d.dtype != np.uint8 and (d.size == 0 or (np.all(d == np.round(d)) and d.min() >= 0 and d.max() <= 255)):
        out["features_descriptors"] = np.uint8
    return out


def _to_storage(a: NDArray[Any], dtype: Any, name: str) -> NDArray[Any]:
    out = np.asarray(a).astype(dtype)
    if np.dtype(dtype).kind == "i" and not np.array_equal(out, a):
        raise ValueError(f"{name} does not fit {np.dtype(dtype).name}")
    return out


def _from_storage(name: str, a: NDArray[Any], kind: str) -> NDArray[Any]:
    if name in _MEMORY:
        return a.astype(_MEMORY[name])
    if name == "features_descriptors":
        return a.astype(descriptor(kind).dtype)
    return a


# ---------------------------------------------------------------------- building
#: a keyframe image's PNG: the "sub" row filter, then deflate with Huffman codes only (fe8). Lossless as
#: before and smaller, at less than half the CPU of level 1 with the adaptive filters: KITTI clip image
#: (1226x370) 5.7 ms / 294 kB against 12.8 ms / 301 kB; realistic orbit and sample scan images (640x480)
#: 3.5 ms / 168 kB against 8.0 ms / 181 kB (load 4)
_PNG_PARAMS = [
    cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
    cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB,
]


def _png(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    if image.size == 0:
        return np.zeros(0, np.uint8)
    ok, buf = cv2.imencode(".png", image, _PNG_PARAMS)
    return np.asarray(buf, np.uint8).ravel() if ok else np.zeros(0, np.uint8)


def map_vocabulary(config: LoopConfig, sets: Sequence[FeatureSet], vocabulary: Vocabulary | None = None) -> Vocabulary:
    """``vocabulary`` (the run's, by :mod:`loopmodel.io.vocabulary_file`), else one trained on ``sets``."""
    if vocabulary is not None:
        return vocabulary
    docs = [s.descriptors for s in sets if len(s)]
    if not docs:
        raise InputError("loop.descriptor", "no features to train a map vocabulary on")
    allx = np.concatenate(docs)
    rng = np.random.default_rng(0)
    if allx.shape[0] > 60000:
        allx = allx[rng.choice(allx.shape[0], 60000, replace=False)]
    return Vocabulary.train(allx, config.vocabulary_branching, config.vocabulary_levels, rng=rng, documents=docs)


@dataclass
class MapInputs:
    """What a run hands to :func:`build_session_map`.

    ``keyframes`` with their images, in id order; ``world_from_kf`` the final keyframe poses;
    ``loop_constraints`` as ``(kf_a, kf_b, kf_a_from_kf_b)``."""

    calibration: StereoCalibration
    keyframes: list[Keyframe]
    world_from_kf: dict[int, F64]
    landmark_ids: I64
    landmarks_in_world: F64
    loop_constraints: list[tuple[int, int, F64]]
    stripes: StripeAnchors
    config_yaml: str = ""
    info: dict[str, Any] = field(default_factory=dict)


@dataclass
class KeyframeContent:
    """What the map keeps of a keyframe's image: its loop features (configured kind) and its PNG bytes."""

    features: FeatureSet
    png: NDArray[np.uint8]


class KeyframeArchiver:
    """Each keyframe's map content (:class:`KeyframeContent`): features as keyframes arrive, images at the end.

    The loop features are taken from the loop stage's detection (or detected) in a worker thread
    during the run, so the session map at the end of a run (:func:`build_session_map`) does not
    prepare every keyframe after the last frame (onepass, issue 32: on the KITTI clip that was 1.4 s
    of the 1.6 s of the map step). The images are PNG-encoded after the frames on two threads
    (:meth:`encode_images`, beside the final refinement; OpenCV releases the GIL): encoding during the
    run took 10-14 ms of CPU per KITTI keyframe from the tracking thread's two cores (fe8).
    """

    def __init__(self, calibration: StereoCalibration, config: LoopConfig) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self._calibration = calibration
        self._config = config
        self._closer: Any = None
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="map-keyframes")
        self._jobs: dict[int, Future[FeatureSet]] = {}
        self._images: dict[int, NDArray[np.uint8]] = {}
        self._encoding: dict[int, Future[NDArray[np.uint8]]] | None = None  # encode_images(): each image's PNG
        self._taking = threading.Event()  # set by take(): detections are no longer waited for

    def add(self, kf: Keyframe, detection: Future[Any] | None = None) -> None:
        """Prepare this keyframe's features in the worker; its image is kept for :meth:`take`.

        ``detection``: the loop stage's detection of the keyframe (a future of
        :class:`~loopmodel.loop.stage.Detection`): its ``features``, when there, are the same loop
        features, not detected a second time (issue 33: 5-6 ms of CPU per KITTI frame).
        """
        self._jobs[int(kf.id)] = self._pool.submit(self._prepare, kf, detection)
        self._images[int(kf.id)] = np.asarray(kf.image)

    def _prepare(self, kf: Keyframe, detection: Future[Any] | None = None) -> FeatureSet:
        features = None
        # a detection still running when the map is taken (abandoned at the loop stage's drain) is not
        # waited for: its features are detected here
        while detection is not None and not detection.done() and not self._taking.is_set():
            self._taking.wait(0.05)
        if detection is not None and detection.done():
            try:
                features = detection.result().features
            except Exception:  # noqa: BLE001 - a failed detection: the features are detected here
                logger.debug("keyframe %d: no features from its detection", kf.id, exc_info=True)
        if features is not None and np.asarray(kf.image).size:
            return features
        if not np.asarray(kf.image).size:
            return empty_features(self._config.descriptor)
        if self._closer is None:
            from loopmodel.loop.closer import LoopCloser

            self._closer = LoopCloser(self._calibration, self._config)
        return self._closer.keyframe_features(kf)

    def encode_images(self) -> None:
        """Start the keyframe images' PNG encoding on two threads (after the last frame: beside the final refinement).

        :meth:`take` waits for them (and starts them when not started). Keyframes added later are not encoded.
        """
        from concurrent.futures import ThreadPoolExecutor

        if self._encoding is None:
            pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="map-png")
            self._encoding = {k: pool.submit(_png, image) for k, image in self._images.items()}
            pool.shutdown(wait=False)

    def take(self) -> dict[int, KeyframeContent]:
        """Every finished keyframe's content with its PNG image (waits for the pending features and images).

        A failed one is left out, logged (the map step prepares it again).
        """
        features: dict[int, FeatureSet] = {}
        self._taking.set()
        for k, job in self._jobs.items():
            try:
                features[k] = job.result()
            except Exception as exc:  # the map step prepares it again
                logger.warning("map content of keyframe %d: %s", k, exc)
        self.encode_images()
        encoding, self._encoding = self._encoding or {}, None
        self.close()
        out: dict[int, KeyframeContent] = {}
        for k, f in features.items():
            try:
                out[k] = KeyframeContent(f, encoding[k].result())
            except Exception as exc:  # the map step prepares it again
                logger.warning("map image of keyframe %d: %s", k, exc)
        return out

    def close(self) -> None:
        """Stop the worker (pending work is dropped)."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._jobs = {}
        self._images = {}


def keyframe_content(closer: Any, kf: Keyframe, kind: str) -> KeyframeContent:
    """A keyframe's loop features (by ``closer``, a :class:`~loopmodel.loop.closer.LoopCloser`) and PNG image."""
    image = np.asarray(kf.image)
    features = closer.keyframe_features(kf) if image.size else empty_features(kind)
    return KeyframeContent(features, _png(image))


def build_session_map(
    inputs: MapInputs,
    config: LoopConfig,
    prepared: dict[int, KeyframeContent] | None = None,
    vocabulary: Vocabulary | None = None,
) -> SessionMap:
    """The map of a run: keyframes re-described with the configured descriptor kind, the pose graph, stripes.

    ``prepared``: keyframes' content made during the run (:class:`KeyframeArchiver`); the others are
    prepared here. ``vocabulary``: the run's (its kind); None: one trained on the map's keyframes.
    """
    from loopmodel.loop.closer import LoopCloser

    kfs = inputs.keyframes
    content = dict(prepared or {})
    missing = [k for k in kfs if int(k.id) not in content]
    if missing:
        closer = LoopCloser(inputs.calibration, config)
        content.update({int(k.id): keyframe_content(closer, k, config.descriptor) for k in missing})
    sets = [content[int(k.id)].features for k in kfs]
    voc = map_vocabulary(config, sets, vocabulary)
    edges: list[tuple[int, int]] = []
    rel: list[F64] = []
    kinds: list[int] = []
    for k in kfs:
        if k.connected and k.prev_keyframe_id is not None and k.kf_prev_from_kf is not None:
            edges.append((int(k.prev_keyframe_id), int(k.id)))
            rel.append(np.asarray(k.kf_prev_from_kf, float))
            kinds.append(EDGE_ODOMETRY)
    for a, b, a_from_b in inputs.loop_constraints:
        edges.append((int(a), int(b)))
        rel.append(np.asarray(a_from_b, float))
        kinds.append(EDGE_LOOP)
    pngs = [content[int(k.id)].png for k in kfs]
    st = inputs.stripes
    smap = SessionMap(
        calibration=inputs.calibration,
        keyframe_ids=np.array([k.id for k in kfs], np.int64),
        timestamps_ns=np.array([k.timestamp_ns for k in kfs], np.int64),
        world_from_kf=_stack([inputs.world_from_kf.get(int(k.id), k.world_from_kf) for k in kfs]),
        rect_from_cam=_stack([k.rect_from_cam for k in kfs]),
        frame_index=np.array([k.frame_index for k in kfs], np.int64),
        session=np.zeros(len(kfs), np.int64),
        lm_offsets=_offsets([len(k.landmark_ids) for k in kfs]),
        lm_ids=_cat([np.asarray(k.landmark_ids, np.int64) for k in kfs], (0,)).astype(np.int64),
        lm_points_in_kf=_cat([np.asarray(k.points_in_kf, float).reshape(-1, 3) for k in kfs], (0, 3)),
        lm_stereo_px=_cat([np.asarray(k.stereo_px, float).reshape(-1, 3) for k in kfs], (0, 3)),
        features=PackedFeatures.pack(config.descriptor, sets, voc),
        image_offsets=_offsets([p.size for p in pngs]),
        images_png=_cat(pngs, (0,)).astype(np.uint8),
        landmark_ids=np.asarray(inputs.landmark_ids, np.int64),
        landmarks_in_world=np.asarray(inputs.landmarks_in_world, float).reshape(-1, 3),
        edges=np.array(edges, np.int64).reshape(-1, 2),
        edge_a_from_b=_stack(rel),
        edge_kind=np.array(kinds, np.int8),
        stripe_timestamps_ns=np.array([s.timestamp_ns for s in st.stripes], np.int64),
        stripe_offsets=_offsets([len(s.points_in_cam) for s in st.stripes]),
        stripe_points_in_cam=_cat([np.asarray(s.points_in_cam, float).reshape(-1, 3) for s in st.stripes], (0, 3)),
        stripe_kf=np.asarray(st.kf_ids, np.int64),
        stripe_kf_from_cam=np.asarray(st.kf_from_cam, float).reshape(-1, 4, 4),
        config_yaml=inputs.config_yaml,
        info=dict(inputs.info),
    )
    smap.check()
    return smap





def _stack(mats: Sequence[Any]) -> F64:
    return np.stack([np.asarray(m, float) for m in mats]) if len(mats) else np.zeros((0, 4, 4))


def _cat(parts: Sequence[NDArray[Any]], shape: tuple[int, ...]) -> NDArray[Any]:
    return np.concatenate(parts) if len(parts) else np.zeros(shape)


def replicate(smap: SessionMap, copies: int) -> SessionMap:
    """``smap``'s keyframes repeated ``copies`` times under new ids (a large map to time loading)."""
    n = len(smap)
    rows = np.tile(np.arange(n), copies)
    step = int(smap.keyframe_ids.max()) + 1 if n else 1
    ids = np.concatenate([smap.keyframe_ids + c * step for c in range(copies)])
    lm, im = _ranges(smap.lm_offsets, rows), _ranges(smap.image_offsets, rows)
    base = dataclasses.replace(smap, **_rows_only(smap, rows, lm, im))
    return dataclasses.replace(
        base,
        keyframe_ids=ids,
        edges=np.concatenate([smap.edges + c * step for c in range(copies)]),
        edge_a_from_b=np.concatenate([smap.edge_a_from_b] * copies),
        edge_kind=np.concatenate([smap.edge_kind] * copies),
        stripe_kf=np.concatenate([smap.stripe_kf + c * step for c in range(copies)]),
        stripe_timestamps_ns=np.concatenate([smap.stripe_timestamps_ns] * copies),
        stripe_offsets=_offsets(np.tile(np.diff(smap.stripe_offsets), copies).tolist()),
        stripe_points_in_cam=np.concatenate([smap.stripe_points_in_cam] * copies),
        stripe_kf_from_cam=np.concatenate([smap.stripe_kf_from_cam] * copies),
    )


def select_rows(smap: SessionMap, rows: I64) -> SessionMap:
    """The keyframes of ``rows`` (in that order) with the edges and stripes among them."""
    lm = _ranges(smap.lm_offsets, rows)
    im = _ranges(smap.image_offsets, rows)
    ids = smap.keyframe_ids[rows]
    e = np.isin(smap.edges, ids).all(axis=1) if smap.edges.size else np.zeros(0, bool)
    st = np.flatnonzero(np.isin(smap.stripe_kf, ids))
    pts = _ranges(smap.stripe_offsets, st)
    return dataclasses.replace(
        smap,
        edges=smap.edges[e],
        edge_a_from_b=smap.edge_a_from_b[e],
        edge_kind=smap.edge_kind[e],
        stripe_timestamps_ns=smap.stripe_timestamps_ns[st],
        stripe_offsets=_offsets(np.diff(smap.stripe_offsets)[st].tolist()),
        stripe_points_in_cam=smap.stripe_points_in_cam[pts],
        stripe_kf=smap.stripe_kf[st],
        stripe_kf_from_cam=smap.stripe_kf_from_cam[st],
        **_rows_only(smap, rows, lm, im),
    )


def _rows_only(smap: SessionMap, rows: I64, lm: I64, im: I64) -> dict[str, Any]:
    return dict(
        keyframe_ids=smap.keyframe_ids[rows],
        timestamps_ns=smap.timestamps_ns[rows],
        world_from_kf=smap.world_from_kf[rows],
        rect_from_cam=smap.rect_from_cam[rows],
        frame_index=smap.frame_index[rows],
        session=smap.session[rows],
        lm_offsets=_offsets(np.diff(smap.lm_offsets)[rows].tolist()),
        lm_ids=smap.lm_ids[lm],
        lm_points_in_kf=smap.lm_points_in_kf[lm],
        lm_stereo_px=smap.lm_stereo_px[lm],
        features=smap.features.subset(rows),
        image_offsets=_offsets(np.diff(smap.image_offsets)[rows].tolist()),
        images_png=smap.images_png[im],
    )


# ---------------------------------------------------------------------- resuming a run
@dataclass
class ResumePoint:
    """What an interrupted run left for ``loopmodel run --resume``: its map and trajectories.

    The resumed run starts again at the frame of the map's last keyframe (``frame_index``) with that
    keyframe's pose; the frames before it keep the interrupted run's poses."""

    map: SessionMap
    online: Trajectory
    final: Trajectory
    keyframes: Trajectory

    @property
    def frame_index(self) -> int:
        """Frame of the last keyframe (the resumed run starts there)."""
        return int(self.map.frame_index[-1])

    @property
    def timestamp_ns(self) -> int:
        """Time of the last keyframe."""
        return int(self.map.timestamps_ns[-1])

    @property
    def world_from_kf(self) -> F64:
        """Pose of the last keyframe (left camera, metres)."""
        return np.asarray(self.map.world_from_kf[-1])
