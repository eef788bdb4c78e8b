"""Inputs of the evaluation: results folders, trajectory files and bag topics, ground truth.

A results folder (DESIGN.md) holds ``trajectory_online.tum`` (poses as estimated live),
``trajectory_final.tum`` (after every loop closure), ``keyframes.tum`` and ``metrics.json``
whose optional ``loop_closures`` list holds one object per closure. The time of a closure
is read from ``timestamp_ns``/``time_ns``/``t_ns``/``stamp_ns`` (or ``*_s`` in seconds,
``frame`` as an index into the online trajectory, ``keyframe``/``kf`` as an index into
``keyframes.tum``), optionally prefixed with ``query_``/``current_``; the matched old place
likewise with a ``match_``/``matched_``/``candidate_``/``old_`` prefix. Other numbers of an
event (inliers, correction size, optimisation time) are carried into the report.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from loopmodel.config import SequenceConfig
from loopmodel.errors import FormatError, InputError
from loopmodel.io.text import require_existing_file
from loopmodel.io.trajectory_io import guess_format, read_trajectory
from loopmodel.types import Trajectory

ONLINE_FILE = "trajectory_online.tum"

FINAL_FILE = "trajectory_final.tum"

KEYFRAMES_FILE = "keyframes.tum"

RUN_METRICS_FILE = "metrics.json"


@dataclass
class TimedTrajectory:
    """A trajectory with where it came from and whether its times are real.

    KITTI files carry none; their poses are numbered at a fixed rate.
    """

    traj: Trajectory
    source: str
    has_times: bool


def _bag_trajectory(spec: str | Path) -> TimedTrajectory | None:
    """A ``BAG:TOPIC`` trajectory (pose topics or ``/tf:PARENT.CHILD``), or None for other specs."""
    from loopmodel.io.bag_trajectory import parse_bag_spec, read_bag_trajectory

    parsed = parse_bag_spec(spec)
    if parsed is None:
        return None
    return TimedTrajectory(read_bag_trajectory(*parsed), str(spec), True)


def load_trajectory_file(path: str | Path, rate_hz: float = 10.0) -> TimedTrajectory:
    """Read a TUM, KITTI or EuRoC trajectory for evaluation.

    Repeated timestamps are kept (some estimators write them), times going backwards are an error.
    """
    bag = _bag_trajectory(path)
    if bag is not None:
        return bag
    p = Path(path)
    require_existing_file(p, "trajectory file")  # a device or FIFO was "does not exist" (issue 34)
    fmt = guess_format(p)
    traj = read_trajectory(p, fmt, rate_hz=rate_hz)  # repeated times allowed, no going back
    if len(traj) < 2:
        raise InputError(p, f"trajectory has {len(traj)} pose(s); at least 2 are needed")
    return TimedTrajectory(traj, str(p), fmt != "kitti")


def load_ground_truth(spec: str | Path, sequence_config: SequenceConfig | None = None) -> TimedTrajectory:
    """Ground truth from a trajectory file (TUM, KITTI, EuRoC) or from a sequence.

    A sequence (MCAP file, EuRoC or KITTI folder) is read with :func:`loopmodel.io.open_sequence`.
    """
    bag = _bag_trajectory(spec)
    if bag is not None:
        return bag
    p = Path(spec)
    if not p.exists():
        raise InputError(p, "ground truth path does not exist")
    if p.is_dir() or p.suffix.lower() in (".mcap", ".bag", ".db3"):
        from loopmodel.io.sequence import open_sequence

        seq = open_sequence(p, sequence_config)
        gt = seq.ground_truth
        if gt is None:
            raise InputError(p, f"the {seq.format_name} sequence has no ground truth")
        if len(gt) < 2:
            raise InputError(p, f"ground truth has {len(gt)} pose(s); at least 2 are needed")
        return TimedTrajectory(gt, str(p), True)
    rate = sequence_config.kitti_rate_hz if sequence_config else 10.0
    return load_trajectory_file(p, rate)


def check_comparable(ref: TimedTrajectory, est: TimedTrajectory) -> None:
    """Raise :class:`FormatError` when the two cannot be associated.

    A KITTI file (no times) against a timed one, or two KITTI files of different lengths.
    """
    if ref.has_times != est.has_times:
        untimed, timed = (ref, est) if not ref.has_times else (est, ref)
        raise FormatError(
            untimed.source,
            f"unequal formats: a KITTI pose file has no timestamps and cannot be associated with "
            f"the timed trajectory {timed.source} (give the sequence folder or a TUM/EuRoC file)",
        )
    if not ref.has_times and len(ref.traj) != len(est.traj):
        raise FormatError(
            est.source,
            f"KITTI pose files are matched by index and need equal lengths: {len(est.traj)} poses "
            f"vs {len(ref.traj)} in {ref.source}",
        )


@dataclass
class LoopClosureEvent:
    """One recorded loop closure: query (current) time, matched old time, other numbers."""

    index: int
    time_ns: int | None
    match_time_ns: int | None
    fields: dict[str, Any]


@dataclass
class RunData:
    """A results folder (or a plain estimate, as a run with only a final trajectory)."""

    name: str
    path: Path | None
    final: TimedTrajectory | None
    online: TimedTrajectory | None = None
    keyframes: TimedTrajectory | None = None
    run_metrics: dict[str, Any] = field(default_factory=dict)
    loop_closures: list[LoopClosureEvent] = field(default_factory=list)
    loop_closures_recorded: bool = False


_QUERY_PREFIXES = ("", "query_", "current_", "cur_", "new_")

_MATCH_PREFIXES = ("match_", "matched_", "candidate_", "old_", "loop_", "ref_")

_NS_KEYS = ("timestamp_ns", "time_ns", "t_ns", "stamp_ns")

_S_KEYS = ("timestamp_s", "time_s", "t_s", "stamp_s")

_FRAME_KEYS = ("frame", "frame_index", "frame_idx")

_KF_KEYS = ("keyframe", "kf", "keyframe_index", "kf_index", "keyframe_id", "kf_id")


def _event_time_ns(ev: dict[str, Any], prefixes: tuple[str, ...], run: RunData) -> int | None:
    for pre in prefixes:
        for k in _NS_KEYS:
            v = ev.get(pre + k)
            if isinstance(v, int | float) and not isinstance(v, bool):
                return int(v)
        for k in _S_KEYS:
            v = ev.get(pre + k)
            if isinstance(v, int | float) and not isinstance(v, bool):
                return int(round(float(v) * 1e9))
        for keys, tt in ((_FRAME_KEYS, run.online or run.final), (_KF_KEYS, run.keyframes)):
            for k in keys:
                v = ev.get(pre + k)
                if isinstance(v, int) and not isinstance(v, bool) and tt is not None:
                    if 0 <= v < len(tt.traj):
                        return int(tt.traj.timestamps_ns[v])
    return None


def parse_loop_closures(events: Any, run: RunData, source: str) -> list[LoopClosureEvent]:
    """Loop-closure events of a run's ``metrics.json`` (see the module docstring)."""
    if events is None:
        return []
    if not isinstance(events, list):
        raise FormatError(source, "'loop_closures' must be a list of objects")
    out: list[LoopClosureEvent] = []
    for k, ev in enumerate(events):
        if not isinstance(ev, dict):
            raise FormatError(source, f"loop_closures[{k}] must be an object, got {type(ev).__name__}")
        out.append(
            LoopClosureEvent(
                k,
                _event_time_ns(ev, _QUERY_PREFIXES, run),
                _event_time_ns(ev, _MATCH_PREFIXES, run),
                ev,
            )
        )
    return out


def load_run(path: str | Path, rate_hz: float = 10.0) -> RunData:
    """Read a results folder.

    The online, final and keyframe trajectories (those present; one of online/final is required),
    ``metrics.json`` and its loop-closure events.
    """
    p = Path(path)
    if not p.is_dir():
        raise InputError(p, "results folder does not exist (or is not a folder)")
    tt: dict[str, TimedTrajectory | None] = {}
    for key, name in (
        ("online", ONLINE_FILE),
        ("final", FINAL_FILE),
        ("keyframes", KEYFRAMES_FILE),
    ):
        f = p / name
        tt[key] = load_trajectory_file(f, rate_hz) if f.is_file() else None
    if tt["final"] is None and tt["online"] is None:
        raise InputError(p, f"results folder has neither {FINAL_FILE} nor {ONLINE_FILE}")
    run = RunData(p.resolve().name, p, tt["final"] or tt["online"], tt["online"], tt["keyframes"])
    mpath = p / RUN_METRICS_FILE
    if mpath.is_file():
        from loopmodel.io.text import read_text_file

        try:
            data = json.loads(read_text_file(mpath, "metrics file"))
        except json.JSONDecodeError as exc:
            raise FormatError(mpath, f"not valid JSON ({exc.msg} at line {exc.lineno})") from None
        except RecursionError:
            raise FormatError(mpath, "not valid JSON (nested too deeply)") from None
        if not isinstance(data, dict):
            raise FormatError(mpath, "expected a JSON object")
        run.run_metrics = data
        # the pipeline records every loop-closing event in ``loop_events`` (type "loop" or
        # "relocalization"); a plain ``loop_closures`` list is read too
        events = data.get("loop_closures")
        if events is None and isinstance(data.get("loop_events"), list):
            events = [e for e in data["loop_events"] if isinstance(e, dict) and e.get("type", "loop") == "loop"]
        run.loop_closures_recorded = events is not None
        run.loop_closures = parse_loop_closures(events, run, str(mpath))
    return run


def ground_truth_hint(run: RunData) -> Path | None:
    """The sequence a run was made from, when its ``metrics.json`` names an existing path."""
    for key in ("sequence_path", "sequence", "input", "source"):
        v = run.run_metrics.get(key)
        if isinstance(v, str) and v and Path(v).exists():
            return Path(v)
    return None


def plain_run(est: TimedTrajectory) -> RunData:
    """A single estimate (``--ref/--est``) as a run with only a final trajectory."""
    return RunData(Path(est.source).stem, None, est)
