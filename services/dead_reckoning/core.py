"""Compass-based and raw odometry, integrated side by side from the sensor streams (pure)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from messages.types import CompassReading, DeadReckonedPose, OdometryStep, Pose2
from sim.geometry import circular_mean, wrap_angle


@dataclass(frozen=True)
class DeadReckoningParams:
    max_pending: int = 32  # odometry steps held while their compass reading is awaited
    compass_memory: int = 64  # recent compass readings kept to pair with odometry arriving late
    missing_memory: int = 256  # skipped seqs remembered per stream, to tell a late message from a duplicate


@dataclass(frozen=True)
class StreamSeq:
    """Sequence bookkeeping of one input stream."""

    expected: int = -1  # the next seq expected; -1 before the first message
    missing: frozenset[int] = frozenset()  # skipped seqs that have not arrived (the most recent few)
    gaps: int = 0  # messages skipped and never arrived
    reordered: int = 0  # messages that arrived after a later one
    duplicates: int = 0  # messages seen twice (or older than anything remembered)


NEW, LATE, DUPLICATE = "new", "late", "duplicate"


def track(s: StreamSeq, seq: int, memory: int) -> tuple[StreamSeq, str]:
    """Account for message ``seq`` on a stream: ``new`` (in order, possibly after a gap), ``late``
    (a skipped one arriving now) or ``duplicate``."""
    if s.expected < 0 or seq == s.expected:
        return replace(s, expected=seq + 1), NEW
    if seq > s.expected:
        skipped = range(max(s.expected, seq - memory), seq)
        missing = s.missing.union(skipped)
        if len(missing) > memory:
            missing = frozenset(sorted(missing)[-memory:])
        return replace(s, expected=seq + 1, missing=missing, gaps=s.gaps + (seq - s.expected)), NEW
    if seq in s.missing:
        return replace(s, missing=s.missing - {seq}, gaps=s.gaps - 1, reordered=s.reordered + 1), LATE
    return replace(s, duplicates=s.duplicates + 1), DUPLICATE


Pose = tuple[float, float, float]


@dataclass(frozen=True)
class DrState:
    initialised: bool = False  # a first compass reading fixed the frame
    compass_pose: Pose = (0.0, 0.0, 0.0)  # heading from the compass, distance from the wheels
    raw_pose: Pose = (0.0, 0.0, 0.0)  # wheels only
    last_heading: float = 0.0  # compass heading at the end of the last integrated step
    last_stamp: float = 0.0  # stamp of the last integrated step (or of the first compass reading)
    steps: int = 0  # odometry steps integrated
    path_length_m: float = 0.0  # sum of |distance| of the integrated steps
    out_seq: int = 0  # seq of the next published pose
    odometry: StreamSeq = StreamSeq()
    compass: StreamSeq = StreamSeq()
    pending: tuple[OdometryStep, ...] = ()  # odometry awaiting its compass reading, oldest first
    headings: tuple[tuple[int, float], ...] = ()  # recent (stamp in microseconds, compass heading)
    dropped: int = 0  # odometry steps that ended before the first compass reading
    continued: bool = False  # the frame continues a saved run's (see ``continued_state``)
    continued_raw: bool = False  # ... and so does the raw odometry pose
    start_steps: int = 0  # steps when this run started (the start phase lasts until the next one)

    @property
    def gaps(self) -> int:
        return self.odometry.gaps + self.compass.gaps


def continued_state(compass_xy: tuple[float, float], raw_pose: Pose | None = None, *, steps: int = 0,
                    path_length_m: float = 0.0) -> DrState:
    """The state of a run that continues a saved one: its last compass-based position, raw pose and
    step record, so that poses, step counts and path lengths go on from where they were.

    The compass heading is taken from the first reading, as at any start; without ``raw_pose`` the
    raw odometry restarts at the compass-based position with that heading.

    >>> s, poses = step(continued_state((2.0, 1.0), steps=40, path_length_m=3.5),
    ...                 CompassReading(stamp=4.0, seq=40, heading_rad=0.5))
    >>> p = poses[0]
    >>> (p.compass.x_m, p.compass.y_m, p.compass.heading_rad, p.raw.x_m, p.steps, p.path_length_m)
    (2.0, 1.0, 0.5, 2.0, 40, 3.5)
    """
    raw = (0.0, 0.0, 0.0) if raw_pose is None else (float(raw_pose[0]), float(raw_pose[1]), float(raw_pose[2]))
    return DrState(compass_pose=(float(compass_xy[0]), float(compass_xy[1]), 0.0), raw_pose=raw, steps=steps,
                   path_length_m=path_length_m, continued=True, continued_raw=raw_pose is not None,
                   start_steps=steps)


def _us(stamp: float) -> int:
    return round(stamp * 1e6)


def step(state: DrState, msg: OdometryStep | CompassReading,
         params: DeadReckoningParams = DeadReckoningParams()) -> tuple[DrState, list[DeadReckonedPose]]:
    """Take one sensor message; return the new state and the poses to publish (zero or more).

    Notes
    -----
    Compass-based dead reckoning (Section 4.1, Figure 6): a step of wheel distance ``d`` ending at
    compass heading ``h_k`` moves the robot by ``d (cos a, sin a)`` with ``a`` the circular mean of
    ``h_{k-1}`` and ``h_k``; the heading is the compass's own. Raw odometry integrates the wheels'
    rotation instead. An odometry step is paired with the compass reading of the same stamp; when
    that reading never comes, the heading is predicted as ``h_{k-1}`` plus the wheels' rotation.
    The frame starts at the origin (or where a saved run left it, ``continued_state``) with the first
    compass heading. Until the first odometry step,
    every repeat of the first compass reading repeats the initial pose (the start of a lockstep run).
    """
    if isinstance(msg, CompassReading):
        return _on_compass(state, msg, params)
    if isinstance(msg, OdometryStep):
        return _on_odometry(state, msg, params)
    raise TypeError(f"dead reckoning takes OdometryStep or CompassReading, not {type(msg).__name__}")


def _on_compass(state: DrState, msg: CompassReading,
                params: DeadReckoningParams) -> tuple[DrState, list[DeadReckonedPose]]:
    stream, verdict = track(state.compass, msg.seq, params.missing_memory)
    if verdict == DUPLICATE:
        state = replace(state, compass=stream)
        if state.initialised and state.steps == state.start_steps:
            # start phase: sensor_sim repeats tick 0 until a command comes; so does the first pose,
            # for a commander that keys on dead-reckoned poses
            state, pose = _emit(state, state.last_stamp)
            return state, [pose]
        return state, []
    headings = tuple(sorted(state.headings + ((_us(msg.stamp), msg.heading_rad),)))[-params.compass_memory:]
    state = replace(state, compass=stream, headings=headings)
    out: list[DeadReckonedPose] = []
    if not state.initialised:
        h = msg.heading_rad
        kept = tuple(o for o in state.pending if _us(o.stamp) > _us(msg.stamp))
        x, y = state.compass_pose[:2] if state.continued else (0.0, 0.0)
        raw = state.raw_pose if state.continued_raw else (x, y, h)
        state = replace(state, initialised=True, compass_pose=(x, y, h), raw_pose=raw,
                        last_heading=h, last_stamp=msg.stamp, pending=kept,
                        dropped=state.dropped + len(state.pending) - len(kept))
        state, pose = _emit(state, msg.stamp)
        out.append(pose)
    # integrate, oldest first, every pending step that ended at or before this reading
    while state.pending and _us(state.pending[0].stamp) <= _us(msg.stamp):
        first, rest = state.pending[0], state.pending[1:]
        state = replace(state, pending=rest)
        state, poses = _integrate(state, first)
        out += poses
    return state, out


def _on_odometry(state: DrState, msg: OdometryStep,
                 params: DeadReckoningParams) -> tuple[DrState, list[DeadReckonedPose]]:
    stream, verdict = track(state.odometry, msg.seq, params.missing_memory)
    state = replace(state, odometry=stream)
    if verdict == DUPLICATE:
        return state, []
    if not state.initialised:
        pending = (*state.pending, msg)[-params.max_pending:]
        return replace(state, pending=pending,
                       dropped=state.dropped + len(state.pending) + 1 - len(pending)), []
    if _us(msg.stamp) <= _us(state.last_stamp):  # late: its neighbours are integrated already
        return _integrate_late(state, msg)
    known = dict(state.headings)
    newest = state.headings[-1][0] if state.headings else -1
    pending = tuple(sorted((*state.pending, msg), key=lambda o: o.stamp))
    state = replace(state, pending=pending)
    out: list[DeadReckonedPose] = []
    # integrate in order while the head of the queue can be: its compass reading is here, or a
    # newer reading came (so its own is lost), or the queue is full
    while state.pending:
        head = state.pending[0]
        key = _us(head.stamp)
        if key in known or newest > key or len(state.pending) > params.max_pending:
            state = replace(state, pending=state.pending[1:])
            state, poses = _integrate(state, head)
            out += poses
        else:
            break
    return state, out


def _integrate(state: DrState, odo: OdometryStep) -> tuple[DrState, list[DeadReckonedPose]]:
    known = dict(state.headings)
    prev = state.last_heading
    end = known.get(_us(odo.stamp))
    if end is None:
        end = wrap_angle(prev + odo.rotation_rad)  # the reading is lost: predict it from the wheels
    mid = circular_mean(prev, end)
    d = odo.distance_m
    x, y, _ = state.compass_pose
    rx, ry, rh = state.raw_pose
    rmid = rh + 0.5 * odo.rotation_rad
    state = replace(state, compass_pose=(x + d * math.cos(mid), y + d * math.sin(mid), end),
                    raw_pose=(rx + d * math.cos(rmid), ry + d * math.sin(rmid), wrap_angle(rh + odo.rotation_rad)),
                    last_heading=end, last_stamp=odo.stamp, steps=state.steps + 1,
                    path_length_m=state.path_length_m + abs(d))
    state, pose = _emit(state, odo.stamp)
    return state, [pose]


def _integrate_late(state: DrState, odo: OdometryStep) -> tuple[DrState, list[DeadReckonedPose]]:
    """A step older than the last integrated one: displacements add up in any order."""
    known = dict(state.headings)
    end = known.get(_us(odo.stamp), state.last_heading)
    earlier = [h for s, h in state.headings if s < _us(odo.stamp)]
    heading = circular_mean(earlier[-1], end) if earlier else end
    d = odo.distance_m
    x, y, h = state.compass_pose
    rx, ry, rh = state.raw_pose
    state = replace(state, compass_pose=(x + d * math.cos(heading), y + d * math.sin(heading), h),
                    raw_pose=(rx + d * math.cos(rh), ry + d * math.sin(rh), wrap_angle(rh + odo.rotation_rad)),
                    steps=state.steps + 1, path_length_m=state.path_length_m + abs(d))
    state, pose = _emit(state, state.last_stamp)
    return state, [pose]


def _emit(state: DrState, stamp: float) -> tuple[DrState, DeadReckonedPose]:
    cx, cy, ch = state.compass_pose
    rx, ry, rh = state.raw_pose
    pose = DeadReckonedPose(stamp=stamp, seq=state.out_seq, compass=Pose2(x_m=cx, y_m=cy, heading_rad=ch),
                            raw=Pose2(x_m=rx, y_m=ry, heading_rad=rh), steps=state.steps,
                            path_length_m=state.path_length_m, gaps=state.gaps)
    return replace(state, out_seq=state.out_seq + 1), pose
