"""Merging two session maps (``loopmodel map merge``, ``run --mode extend``; issue 20).

Every keyframe of map B is relocalized against map A's keyframe database (descriptors and the
P3P bank on A's 3-D features, then seed 004's KLT stage on A's keyframe image). Each success
gives a candidate ``worldA_from_worldB``; the candidate most others agree with (within
``agree_m`` / ``agree_deg``) wins and its supporters become links between the maps. The joint
pose graph holds both maps' own edges (odometry and loops, at the relative poses of the maps'
current keyframe poses: their own optimisation is kept as their measurement) and the links
(``kfA_from_kfB`` measured by relocalization), A's first keyframe fixed; Levenberg-Marquardt
(:func:`loopmodel.backend.robust_posegraph.optimize_lm`) spreads the links' disagreement.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import LoopConfig
from loopmodel.errors import InputError
from loopmodel.geometry.se3 import invert_pose, so3_log
from loopmodel.loop.closer import LoopCloser
from loopmodel.loop.closure import relocalize_in_database
from loopmodel.loop.database import PlaceParams
from loopmodel.loop.reloc import RelocParams
from loopmodel.loop.session_map import EDGE_SESSIONS, PackedFeatures, SessionMap, _concat_packed, _offsets

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]


@dataclass
class MapLink:
    """Keyframe ``kf_b`` of map B relocalized at keyframe ``kf_a`` of map A: ``a_from_b`` (4x4, metres)."""

    kf_a: int
    kf_b: int
    a_from_b: F64
    inliers: int
    world_a_from_world_b: F64


@dataclass
class MergeReport:
    """How two maps were joined: candidates, agreeing links, ``world_a_from_world_b`` (before and after)."""

    candidates: int
    links: int
    world_a_from_world_b: F64
    offset_m: float
    offset_deg: float
    optimise_s: float
    link_list: list[MapLink] = field(default_factory=list)


def _motion(T: F64) -> tuple[float, float]:
    return float(np.linalg.norm(T[:3, 3])), float(np.degrees(np.linalg.norm(so3_log(T[:3, :3]))))


def find_links(a: SessionMap, b: SessionMap, config: LoopConfig) -> list[MapLink]:
    """Relocalize every keyframe of B in A; one candidate link per success."""
    db = a.database(PlaceParams.from_config(config))
    closer = LoopCloser(a.calibration, config)
    params = RelocParams.from_config(config)
    row_a = a.row_of()
    remembered: set[int] = set()
    links: list[MapLink] = []
    for i in range(len(b)):
        kf_a, res = relocalize_in_database(b.features.feature_set(i), db, closer.camera, params)
        if kf_a is None or res.cam_from_map is None:
            continue
        j = row_a[kf_a]
        b_rect_from_a_rect = np.asarray(res.cam_from_map)
        inliers = res.n_inliers
        image = b.image(i)
        if image.size:
            if kf_a not in remembered:
                closer.remember(a.keyframe(j))
                remembered.add(kf_a)
            tr = closer.track_old_features(kf_a, image, b_rect_from_a_rect)
            if tr is not None and tr[1].size >= max(config.min_inliers, inliers):
                b_rect_from_a_rect, inliers = tr[0], int(tr[1].size)
        b_from_a = invert_pose(b.rect_from_cam[i]) @ b_rect_from_a_rect @ a.rect_from_cam[j]
        a_from_b = invert_pose(b_from_a)
        wa_from_wb = a.world_from_kf[j] @ a_from_b @ invert_pose(b.world_from_kf[i])
        links.append(MapLink(int(kf_a), int(b.keyframe_ids[i]), a_from_b, inliers, wa_from_wb))
    return links


def consensus(links: list[MapLink], agree_m: float, agree_deg: float) -> list[MapLink]:
    """The links whose ``worldA_from_worldB`` agrees with the most others (the largest consistent set)."""
    best: list[MapLink] = []
    for c in links:
        inv_c = invert_pose(c.world_a_from_world_b)
        group = []
        for o in links:
            m, d = _motion(inv_c @ o.world_a_from_world_b)
            if m <= agree_m and d <= agree_deg:
                group.append(o)
        if len(group) > len(best):
            best = group
    return best


def _information(sigma_deg: float, sigma_m: float) -> F64:
    return np.diag([1 / np.radians(sigma_deg) ** 2] * 3 + [1 / sigma_m**2] * 3)


def merge_maps(
    a: SessionMap,
    b: SessionMap,
    config: LoopConfig | None = None,
    agree_m: float = 0.02,
    agree_deg: float = 2.0,
    min_links: int = 1,
) -> tuple[SessionMap, MergeReport]:
    """Map B joined to map A in A's world (see the module docstring).

    Raises :class:`InputError` when fewer than ``min_links`` keyframes of B agree on where B lies in A.
    """
    from loopmodel.backend.robust_posegraph import PoseGraph, optimize_lm

    cfg = config if config is not None else LoopConfig()
    cand = find_links(a, b, cfg)
    links = consensus(cand, agree_m, agree_deg)
    if len(links) < min_links:
        raise InputError("map merge", f"no shared view found: {len(cand)} relocalizations, none agreeing")
    best = max(links, key=lambda x: x.inliers)
    T0 = best.world_a_from_world_b
    off = int(max(a.keyframe_ids.max(), b.keyframe_ids.max())) + 1 if len(a) else 0
    init = {int(k): np.asarray(T) for k, T in a.pose_of().items()}
    init.update({int(k) + off: T0 @ np.asarray(T) for k, T in b.pose_of().items()})
    edges: list[tuple[int, int]] = []
    rel: list[F64] = []
    info: list[F64] = []
    odo: list[bool] = []
    own = _information(cfg.robust_odometry_sigma_deg, cfg.robust_odometry_sigma_m)
    for m, shift in ((a, 0), (b, off)):
        for i, j in m.edges.tolist():
            p, q = i + shift, j + shift
            edges.append((p, q))
            rel.append(invert_pose(init[p]) @ init[q])
            info.append(own)
            odo.append(True)
    link_info = _information(cfg.robust_loop_sigma_deg, cfg.robust_loop_sigma_m)
    for lk in links:
        edges.append((lk.kf_a, lk.kf_b + off))
        rel.append(lk.a_from_b)
        info.append(link_info)
        odo.append(False)
    graph = PoseGraph(3, init, np.array(edges, np.int64).reshape(-1, 2), rel, info, np.array(odo, bool))
    t0 = time.perf_counter()
    res = optimize_lm(graph)
    solved = {k: res.world_from_pose.get(k, init[k]) for k in init}
    opt_s = time.perf_counter() - t0
    # where B's first keyframe ended up: B's world in A's after the optimisation
    b0 = int(b.keyframe_ids[0])
    T = solved[b0 + off] @ invert_pose(b.world_from_kf[0])
    merged = _joined(a, b, solved, off, links, T)
    dm, dd = _motion(T)
    report = MergeReport(len(cand), len(links), T, dm, dd, opt_s, links)
    logger.info("maps merged: %d links of %d candidates; B moved %.3f m / %.2f deg", len(links), len(cand), dm, dd)
    return merged, report


def _rebag(b: PackedFeatures, like: PackedFeatures) -> PackedFeatures:
    """B's features with words and bags of ``like``'s vocabulary (when theirs differs)."""
    va, vb = like.vocabulary, b.vocabulary
    if va.centers.shape == vb.centers.shape and np.array_equal(va.centers, vb.centers):
        return b
    n = b.offsets.size - 1
    sets = [b.feature_set(i) for i in range(n)]
    return PackedFeatures.pack(b.kind, sets, va)


def _joined(
    a: SessionMap, b: SessionMap, world_from_kf: dict[int, F64], off: int, links: list[MapLink], T: F64
) -> SessionMap:
    """One map of A's and B's keyframes (B's ids shifted by ``off``), poses from ``world_from_kf``."""
    if a.features.kind != b.features.kind:
        raise InputError("map merge", f"descriptor kinds differ: {a.features.kind} and {b.features.kind}")
    lm_off = int(max(a.lm_ids.max(initial=-1), a.landmark_ids.max(initial=-1), b.lm_ids.max(initial=-1))) + 1
    bf = _rebag(b.features, a.features)
    bf = dataclasses.replace(bf, ids=np.where(bf.ids >= 0, bf.ids + lm_off, -1))
    feats = _concat_packed([a.features, bf], [np.arange(len(a)), np.arange(len(b))])
    ids = np.concatenate([a.keyframe_ids, b.keyframe_ids + off])
    link_edges = np.array([(lk.kf_a, lk.kf_b + off) for lk in links], np.int64).reshape(-1, 2)
    sess_b = b.session + int(a.session.max(initial=-1)) + 1
    lm_b = b.landmarks_in_world @ T[:3, :3].T + T[:3, 3]
    return dataclasses.replace(
        a,
        keyframe_ids=ids,
        timestamps_ns=np.concatenate([a.timestamps_ns, b.timestamps_ns]),
        world_from_kf=np.stack([world_from_kf[int(k)] for k in ids]),
        rect_from_cam=np.concatenate([a.rect_from_cam, b.rect_from_cam]),
        frame_index=np.concatenate([a.frame_index, b.frame_index]),
        session=np.concatenate([a.session, sess_b]),
        lm_offsets=_offsets(np.concatenate([np.diff(a.lm_offsets), np.diff(b.lm_offsets)]).tolist()),
        lm_ids=np.concatenate([a.lm_ids, b.lm_ids + lm_off]),
        lm_points_in_kf=np.concatenate([a.lm_points_in_kf, b.lm_points_in_kf]),
        lm_stereo_px=np.concatenate([a.lm_stereo_px, b.lm_stereo_px]),
        features=feats,
        image_offsets=_offsets(np.concatenate([np.diff(a.image_offsets), np.diff(b.image_offsets)]).tolist()),
        images_png=np.concatenate([a.images_png, b.images_png]),
        landmark_ids=np.concatenate([a.landmark_ids, b.landmark_ids + lm_off]),
        landmarks_in_world=np.concatenate([a.landmarks_in_world, lm_b]),
        edges=np.concatenate([a.edges, b.edges + off, link_edges]),
        edge_a_from_b=np.concatenate([a.edge_a_from_b, b.edge_a_from_b, _stack([lk.a_from_b for lk in links])]),
        edge_kind=np.concatenate([a.edge_kind, b.edge_kind, np.full(len(links), EDGE_SESSIONS, np.int8)]),
        stripe_timestamps_ns=np.concatenate([a.stripe_timestamps_ns, b.stripe_timestamps_ns]),
        stripe_offsets=_offsets(np.concatenate([np.diff(a.stripe_offsets), np.diff(b.stripe_offsets)]).tolist()),
        stripe_points_in_cam=np.concatenate([a.stripe_points_in_cam, b.stripe_points_in_cam]),
        stripe_kf=np.concatenate([a.stripe_kf, b.stripe_kf + off]),
        stripe_kf_from_cam=np.concatenate([a.stripe_kf_from_cam, b.stripe_kf_from_cam]),
        info={**a.info, "merged_from": [a.info.get("sequence"), b.info.get("sequence")]},
        # the newer session's refined calibration (it started from A's when the rig is the same)
        refined_calibration=b.refined_calibration if b.refined_calibration is not None else a.refined_calibration,
    )


def _stack(mats: list[F64]) -> F64:
    return np.stack(mats) if mats else np.zeros((0, 4, 4))


def append_session(old: SessionMap, new: SessionMap) -> SessionMap:
    """A resumed run's map: ``old`` without its last keyframe, then ``new`` (whose first keyframe re-made it).

    One edge joins the two at their poses; the keyframes keep their poses and the session number.
    """
    from loopmodel.loop.session_map import select_rows

    kept = select_rows(old, np.arange(len(old) - 1)) if len(old) > 1 else None
    if kept is None or len(new) == 0:
        return new if kept is None else kept
    off = int(old.keyframe_ids.max()) + 1
    poses = {int(k): np.asarray(T) for k, T in kept.pose_of().items()}
    poses.update({int(k) + off: np.asarray(T) for k, T in new.pose_of().items()})
    a_last, b_first = int(kept.keyframe_ids[-1]), int(new.keyframe_ids[0])
    rel = invert_pose(poses[a_last]) @ poses[b_first + off]
    link = MapLink(a_last, b_first, rel, 0, np.eye(4))
    joined = _joined(kept, new, poses, off, [link], np.eye(4))
    return dataclasses.replace(joined, session=np.full(len(joined), int(old.session[0]), np.int64), info=old.info)
