"""Trajectories from bag topics for ``loopmodel eval``.

``BAG:TOPIC`` for ``PoseStamped``, ``PoseWithCovarianceStamped``, ``Odometry``,
``TransformStamped``, and ``BAG:/tf:PARENT.CHILD`` for a chain of ``/tf`` (and ``/tf_static``)
transforms (the spelling of ``evo``'s bag tools).

Poses are ``parent_from_child`` (metres) at the messages' header stamps (ns). A TF chain is
evaluated at the stamps of its dynamic edge with the fewest messages; the other dynamic
edges are interpolated (linear translation, slerp rotation) and stamps outside their span
are left out.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from loopmodel.errors import FormatError, InputError
from loopmodel.io.rosbag_io import BAG_SUFFIXES, BagReader, header_stamp_ns, open_bag, pose_from_msg_fields
from loopmodel.types import Trajectory

POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/TransformStamped",
)
TF_TYPE = "tf2_msgs/msg/TFMessage"


def parse_bag_spec(spec: str | Path) -> tuple[Path, str] | None:
    """``(bag, topic)`` of a ``BAG:TOPIC`` argument whose bag part exists, else None."""
    s = str(spec)
    i = s.find(":")
    while i > 0:
        p = Path(s[:i])
        if p.exists() and (p.is_dir() or p.suffix.lower() in BAG_SUFFIXES):
            return p, s[i + 1 :]
        i = s.find(":", i + 1)
    return None


def _pose_of(msg: object, msgtype: str) -> np.ndarray:
    if msgtype.endswith("TransformStamped"):
        tr = msg.transform  # type: ignore[attr-defined]
        return pose_from_msg_fields(tr.translation, tr.rotation)
    pose = msg.pose  # type: ignore[attr-defined]
    if msgtype.endswith(("PoseWithCovarianceStamped", "Odometry")):
        pose = pose.pose
    return pose_from_msg_fields(pose.position, pose.orientation)


def trajectory_from_messages(bag: BagReader, topic: str, source: str) -> Trajectory:
    """Poses of a pose-type topic at its header stamps."""
    msgtype = bag.msgtype(topic)
    if msgtype not in POSE_TYPES:
        raise InputError(source, f"topic of type '{msgtype}' is not one of {', '.join(POSE_TYPES)}")
    times, poses = [], []
    for _t, mt, _l, msg in bag.messages([topic]):
        times.append(header_stamp_ns(msg))
        poses.append(_pose_of(msg, mt))
    return _checked(times, poses, source)


def _checked(times: list[int], poses: list[np.ndarray], source: str) -> Trajectory:
    if len(times) < 2:
        raise InputError(source, f"{len(times)} pose(s) found; at least 2 are needed")
    t = np.asarray(times, dtype=np.int64)
    order = np.argsort(t, kind="stable")
    if np.any(np.diff(t) < 0):  # receive order may differ from stamp order
        t = t[order]
        poses = [poses[k] for k in order]
    return Trajectory(t, np.asarray(poses))


def _tf_edges(bag: BagReader) -> tuple[dict[tuple[str, str], list[tuple[int, np.ndarray]]], set[tuple[str, str]]]:
    edges: dict[tuple[str, str], list[tuple[int, np.ndarray]]] = {}
    static: set[tuple[str, str]] = set()
    for topic in ("/tf_static", "/tf", "tf_static", "tf"):
        if bag.msgtype(topic) != TF_TYPE:
            continue
        for _t, _m, _l, msg in bag.messages([topic]):
            for tr in msg.transforms:
                key = (str(tr.header.frame_id).lstrip("/"), str(tr.child_frame_id).lstrip("/"))
                T = pose_from_msg_fields(tr.transform.translation, tr.transform.rotation)
                edges.setdefault(key, []).append((header_stamp_ns(tr), T))
                if "static" in topic:
                    static.add(key)
    return edges, static


def _chain(edges: set[tuple[str, str]], parent: str, child: str) -> list[tuple[str, str, bool]] | None:
    """Edges from ``parent`` to ``child`` (breadth first over the undirected tree).

    The flag says the edge is used forward (parent -> child as stored).
    """
    nbr: dict[str, list[tuple[str, tuple[str, str, bool]]]] = {}
    for a, b in edges:
        nbr.setdefault(a, []).append((b, (a, b, True)))
        nbr.setdefault(b, []).append((a, (a, b, False)))
    prev: dict[str, tuple[str, tuple[str, str, bool]] | None] = {parent: None}
    queue = deque([parent])
    while queue:
        f = queue.popleft()
        if f == child:
            break
        for g, e in nbr.get(f, []):
            if g not in prev:
                prev[g] = (f, e)
                queue.append(g)
    if child not in prev:
        return None
    out: list[tuple[str, str, bool]] = []
    f = child
    while prev[f] is not None:
        step = prev[f]
        assert step is not None
        out.append(step[1])
        f = step[0]
    return out[::-1]


def _interpolator(samples: list[tuple[int, np.ndarray]]):  # noqa: ANN202 - a closure
    t = np.array([s[0] for s in samples], dtype=np.int64)
    order = np.argsort(t, kind="stable")
    t = t[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t = t[keep]
    Ts = np.asarray([samples[k][1] for k in order])[keep]
    if len(t) == 1:
        return lambda q: (np.repeat(Ts[:1], len(q), 0), np.abs(q - t[0]) == 0)
    slerp = Slerp(t.astype(float), Rotation.from_matrix(Ts[:, :3, :3]))

    def at(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ok = (q >= t[0]) & (q <= t[-1])
        qq = np.clip(q, t[0], t[-1]).astype(float)
        out = np.repeat(np.eye(4)[None], len(q), 0)
        out[:, :3, :3] = slerp(qq).as_matrix()
        for k in range(3):
            out[:, k, 3] = np.interp(qq, t.astype(float), Ts[:, k, 3])
        return out, ok

    return at


def tf_chain_trajectory(bag: BagReader, parent: str, child: str, source: str) -> Trajectory:
    """``parent_from_child`` over time from ``/tf`` and ``/tf_static``."""
    edges, static = _tf_edges(bag)
    if not edges:
        raise InputError(source, "the bag has no /tf or /tf_static (tf2_msgs/TFMessage) topic")
    chain = _chain(set(edges), parent.lstrip("/"), child.lstrip("/"))
    if chain is None:
        frames = sorted({f for e in edges for f in e})
        raise InputError(source, f"no TF chain from '{parent}' to '{child}'; frames: {', '.join(frames)}")
    dynamic = [(a, b) for a, b, _f in chain if (a, b) not in static]
    if not dynamic:
        raise InputError(source, f"the chain {parent} -> {child} is static (one pose, not a trajectory)")
    base = min(dynamic, key=lambda e: len(edges[e]))
    times = np.array(sorted({s[0] for s in edges[base]}), dtype=np.int64)
    total = np.repeat(np.eye(4)[None], len(times), 0)
    valid = np.ones(len(times), bool)
    for a, b, forward in chain:
        if (a, b) in static:
            T = np.repeat(edges[(a, b)][-1][1][None], len(times), 0)
        else:
            T, ok = _interpolator(edges[(a, b)])(times)
            valid &= ok
        if not forward:
            T = np.linalg.inv(T)
        total = total @ T
    return _checked(list(times[valid]), list(total[valid]), source)


def read_bag_trajectory(bag_path: Path, topic: str) -> Trajectory:
    """Trajectory of ``topic`` in a bag: a pose-type topic, or ``/tf:PARENT.CHILD``."""
    source = f"{bag_path}:{topic}"
    with open_bag(bag_path) as bag:
        name, sep, frames = topic.partition(":")
        if sep and bag.msgtype(name) == TF_TYPE:
            parent, dot, child = frames.partition(".")
            if not dot or not parent or not child:
                raise InputError(source, "a TF trajectory is TOPIC:PARENT.CHILD, e.g. /tf:odom.base_link")
            return tf_chain_trajectory(bag, parent, child, source)
        if topic not in bag.connections:
            listing = ", ".join(f"{k} ({v['type']})" for k, v in bag.topic_table().items())
            raise InputError(source, f"no such topic; topics found: {listing}")
        if bag.msgtype(topic) == TF_TYPE:
            raise FormatError(source, f"a TF topic needs the frames: {topic}:PARENT.CHILD")
        return trajectory_from_messages(bag, topic, source)
