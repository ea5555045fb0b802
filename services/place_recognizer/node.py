"""place_recognizer on the bus: dead-reckoned poses, sonar and the explorer's places in; beliefs and links out."""

from __future__ import annotations

import argparse
import bisect
import logging
import math
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import msgspec
import numpy as np
import zenoh

from messages import topics
from messages.types import (
    DeadReckonedPose,
    Hypothesis,
    LinkMeasured,
    LocalizationBelief,
    MapUpdate,
    OdometryStep,
    PlaceConfirmed,
    PlaceDeleted,
    RecognizerProgress,
    SonarScan,
    VelocityCommand,
)
from services.place_recognizer.core import (
    LinkEstimate,
    PlaceRecognizer,
    PlaceRecognizerParams,
    PlaceSignature,
    RecognizerOutput,
    RecognizerState,
)
from services.place_recognizer.deviation import DeviationParams
from services.place_recognizer.grid import PlacedScan
from services.place_recognizer.history import POSE_HISTORY, PoseHistory
from services.runtime import Node, positive_float
from services.runtime.checkpoint import Checkpoint, EventLog
from services.runtime.saved_map import (
    RobotAt,
    SavedMap,
    add_resume_arguments,
    fetch_saved_map,
    robot_at_from_args,
)

SERVICE = "place_recognizer"
log = logging.getLogger("relaxmap.place_recognizer")


@dataclass(frozen=True)
class PlaceRecognizerNodeParams:
    follow_map: bool = True  # move place centres to the relaxed coordinates of map/update
    wait_map: bool = True  # following the map, the next input waits for the update that holds the last link
    pose_history: int = POSE_HISTORY  # dead-reckoned poses kept to pair with scans and confirmations
    max_pending_scans: int = 64  # scans held while their pose is awaited (the oldest are dropped)
    dt_s: float = 0.1  # sensor_sim's tick: a message stamped t belongs to tick round(t / dt_s)
    order_timeout_s: float = 0.5  # wall time an input waits for the inputs that must come first
    max_sim_time_s: float | None = None  # stop after the pose stamped at or past this simulated time
    duration_s: float | None = None  # stop after this wall time
    resume: bool = False  # continue the map the relaxer holds (asked over the bus before the start)
    resume_near_m: float = 1.0  # signatures are rebuilt from the scans taken this close to a centre
    resume_at: RobotAt | None = None  # with resume: where the robot was (None: by the latest stored scan)
    state_path: str | None = None  # checkpoint: saved with every scan and event applied, resumed after a restart
    links_log: str | None = None  # every link measured, one JSON line each, appended before it is published
    checkpoint_poses: int = 16  # the latest dead-reckoned poses kept in the checkpoint
    core: PlaceRecognizerParams = field(default_factory=PlaceRecognizerParams)  # the recognizer itself


class RecognizerCheckpoint(msgspec.Struct, frozen=True):
    """The recognizer (signatures aside) and the shell's bookkeeping after an input was applied."""

    core: RecognizerState
    poses: list[DeadReckonedPose]  # the latest ones
    applied: list[int]  # places whose confirmation (and deletion) has been applied, negated for deletions
    cmd_tick: int
    sensor_tick: int
    done_tick: int
    belief_seq: int
    link_seq: int
    last_scan_seq: int
    latest_stamp: float
    counts: dict[str, int]
    event_seqs: tuple[int, int] = (-1, -1)  # the highest seqs of places confirmed and deleted applied
    relocalisations: int = 0  # the explorer's count of relocalisation requests, as last acted on


class RecognizerFiles:
    """The recognizer's checkpoint on disk: the state in one file, each place's signature in its own
    (``<state>.signatures/<id>``, written when it is new or has grown), so that a save costs the size
    of what changed rather than of the whole map. The links log is appended before a link is published."""

    def __init__(self, state_path: str | None, links_log: str | None) -> None:
        self.state = Checkpoint(state_path, RecognizerCheckpoint) if state_path else None
        self._sig_dir = Path(f"{state_path}.signatures") if state_path else None
        self._saved: dict[int, object] = {}  # place id -> the logodds array saved last
        self._links_log = EventLog(links_log, LinkMeasured) if links_log else None

    def _signature(self, place_id: int) -> Checkpoint[PlaceSignature]:
        assert self._sig_dir is not None
        return Checkpoint(self._sig_dir / str(place_id), PlaceSignature)

    def load(self) -> tuple[RecognizerCheckpoint, dict[int, PlaceSignature]] | None:
        saved = self.state.load() if self.state else None
        if saved is None:
            return None
        sigs = {}
        for pid in saved.core.signature_ids:
            sig = self._signature(pid).load()
            if sig is not None:
                sigs[pid] = sig
                self._saved[pid] = sig.logodds
        return saved, sigs

    def save(self, shell: RecognizerShell) -> None:
        if self.state is None:
            return
        sigs = shell.core.signatures()
        for pid, sig in sigs.items():  # first the signatures, then the state that names them
            if self._saved.get(pid) is not sig.logodds:
                ckpt = self._signature(pid)
                ckpt.save(sig)
                ckpt.close()
                self._saved[pid] = sig.logodds
        self.state.save(shell.checkpoint())
        for pid in set(self._saved) - set(sigs):
            self._signature(pid).remove()
            del self._saved[pid]

    def record(self, links: list[LinkMeasured]) -> None:
        """Append ``links`` to the links log (one write: a killed process leaves whole lines)."""
        if self._links_log is not None:
            self._links_log.append(links)

    def recorded(self) -> list[LinkMeasured]:
        """The latest measurement of each link in the log (a line cut short by a kill is skipped)."""
        return [] if self._links_log is None else _latest_links(self._links_log.read())


def read_links_log(path: str | Path) -> list[LinkMeasured]:
    """The latest measurement of each link (pair of places) in a recognizer's links log."""
    return _latest_links(EventLog(path, LinkMeasured).read())


def _latest_links(links: list[LinkMeasured]) -> list[LinkMeasured]:
    latest = {(min(lk.from_id, lk.to_id), max(lk.from_id, lk.to_id)): lk for lk in links}
    return list(latest.values())


class RecognizerShell:
    """Orders the inputs the way the in-process loop does, so that a lockstep run is reproducible.

    The order is, tick by tick: the explorer's events of tick ``j - 1`` (places confirmed or
    deleted), then the scan of tick ``j`` with the dead-reckoned pose of the same stamp. zenoh keeps
    the order of one key's messages, not across keys, so the messages that follow an input name it:

    - the velocity command of tick ``j - 1`` names the latest place events the explorer published
      before it (``confirmed_seq``, ``deleted_seq``), so the scan of tick ``j`` waits for that command
      and for those events;
    - the odometry step of tick ``j + 1`` names the latest scan published before it (``sonar_seq``),
      so the events of tick ``j`` wait for that step and that scan: once both are in, every scan of
      tick ``j`` or earlier is.

    - following the relaxed map (``follow_map`` and ``wait_map``), once a map update has been heard:
      after a link is published, the next scan or event waits for the update that names it
      (``MapUpdate.link_seq``), and the work of tick ``j`` waits for the update that holds the
      explorer's place and link events named by the command of tick ``j - 1`` (``confirmed_seq``,
      ``deleted_seq``, ``links_deleted_seq``), as the in-process loop moves the places before its next
      step.

    Once the work of a tick is done (the events of the tick before, the tick's scan), a
    ``RecognizerProgress`` names the tick and the latest link: the explorer answers the tick after it.

    Without commands (nobody drives in lockstep) or sensors, an input waits at most
    ``order_timeout_s`` of wall time. Inputs that miss their turn are applied at once (counted).
    """

    def __init__(self, params: PlaceRecognizerNodeParams,
                 publish_belief, publish_link, clock=time.monotonic, files: RecognizerFiles | None = None,
                 publish_progress=None) -> None:
        self.params = params  # publish_belief, publish_link, publish_progress: one message each
        self._publish_progress = publish_progress
        self._progress_seq = 0
        self._files = files or RecognizerFiles(None, None)
        self._applied: set[int] = set()  # places confirmed (id) or deleted (-1 - id) already applied
        self.core = PlaceRecognizer(params.core)
        self._publish_belief = publish_belief
        self._publish_link = publish_link
        self._clock = clock
        self._history = PoseHistory(params.pose_history)
        self._stepped_stamp: float | None = None  # the pose stamp of the last scan stepped
        self._scans: list[tuple[SonarScan, float]] = []  # (scan, wall time of arrival), in stamp order
        self._events: list[tuple[PlaceConfirmed | PlaceDeleted, float]] = []  # in arrival order
        self._cmd_tick = -1  # the latest tick a velocity command answered
        self._sensor_tick = -1  # the latest tick of an odometry step
        self._done_tick = -1  # the tick of the latest scan or events applied
        self._scan_heard = self._scan_due = -1  # the highest seq of a scan heard / named by an odometry step
        self._event_heard = [-1, -1]  # the highest seqs of places confirmed and deleted heard
        self._event_due = [-1, -1]  # ... named by a velocity command
        self._links_deleted_due = -1  # the highest seq of a link deletion named by a velocity command
        self._map_events = [-1, -1, -1]  # the explorer's confirmations, deletions, link deletions a map update
        # named as applied
        self._event_applied = [-1, -1]  # ... applied
        self._relocalise: list[tuple[int, int]] = []  # (tick, count) of each rise of the explorer's requests
        self._relocalised = 0  # the count acted on
        self._belief_seq = 0
        self._link_seq = 0
        self._map_heard = -1  # the highest link seq a map update named (-1: no update heard yet)
        self._map_seen = False  # a relaxer publishes: links wait for their update
        self._linked = -math.inf  # wall time of the last link published
        self.counts = {"scans": 0, "localised": 0, "links": 0, "places": 0, "deleted": 0, "map_updates": 0,
                       "dropped_scans": 0, "unpaired_scans": 0, "late_events": 0, "repeated_scans": 0,
                       "order_timeouts": 0, "repeated_events": 0, "resent_links": 0, "relocalisations": 0,
                       "map_timeouts": 0}
        self._last_scan_seq = -1
        self._last_belief: LocalizationBelief | None = None  # published for the scan of _last_scan_seq
        self.latest_stamp = -math.inf

    def _tick(self, stamp: float) -> int:
        return round(stamp / self.params.dt_s)

    def restore(self, saved: SavedMap) -> None:
        """Continue the saved map: places, fused links, signatures from the stored scans, the robot's place."""
        places = {p.place_id: (p.x_m, p.y_m) for p in saved.graph.places}
        links = [LinkEstimate(from_id=lk.from_id, to_id=lk.to_id, d_m=lk.d_m, theta_rad=lk.theta_rad, steps=lk.steps,
                              mean_step_m=lk.mean_step_m, traversals=lk.traversals) for lk in saved.graph.links]
        scans: dict[int, list[PlacedScan]] = {}
        for s in saved.near:  # placed at their offset from the place's centre
            scans.setdefault(s.place_id, []).append(PlacedScan(
                x_m=s.offset_x_m, y_m=s.offset_y_m, heading_rad=s.heading_rad, angles_rad=np.asarray(s.angles_rad),
                ranges_m=np.asarray(s.ranges_m), beam_width_rad=s.beam_width_rad, min_range_m=0.0,
                max_range_m=s.max_range_m))
        at = saved.robot
        self.core.restore(places, links, scans, at_place=at.place_id, offset_xy=at.offset_xy, dr_xy=at.dr_xy)
        log.info("%s: continuing %d places (%d signatures), %d links; robot last at place %d", SERVICE,
                 len(places), len(scans), len(links), at.place_id)

    def checkpoint(self) -> RecognizerCheckpoint:
        n = self.params.checkpoint_poses
        return RecognizerCheckpoint(
            core=self.core.snapshot(), poses=self._history.poses[-n:], applied=sorted(self._applied),
            cmd_tick=self._cmd_tick, sensor_tick=self._sensor_tick, done_tick=self._done_tick,
            belief_seq=self._belief_seq, link_seq=self._link_seq, last_scan_seq=self._last_scan_seq,
            latest_stamp=self.latest_stamp, counts=dict(self.counts), event_seqs=tuple(self._event_applied),
            relocalisations=self._relocalised)

    def resume(self, ckpt: RecognizerCheckpoint, signatures: dict[int, PlaceSignature]) -> None:
        """Go on from a checkpoint: its places, signatures, belief and links in progress."""
        self.core.restore_snapshot(ckpt.core, signatures)
        self._history = PoseHistory(self.params.pose_history, ckpt.poses)
        self._applied = set(ckpt.applied)
        self._cmd_tick, self._sensor_tick, self._done_tick = ckpt.cmd_tick, ckpt.sensor_tick, ckpt.done_tick
        self._belief_seq, self._link_seq, self._last_scan_seq = ckpt.belief_seq, ckpt.link_seq, ckpt.last_scan_seq
        self._map_heard = self._link_seq - 1  # what the relaxer took before the restart is not waited for
        self.latest_stamp = ckpt.latest_stamp
        self.counts.update(ckpt.counts)
        # what was heard and not applied is gone with the killed process: only what was applied counts
        # as heard (the explorer's history brings the rest)
        self._scan_heard = self._scan_due = self._last_scan_seq
        self._event_applied = list(ckpt.event_seqs)
        self._event_heard, self._event_due = list(ckpt.event_seqs), list(ckpt.event_seqs)
        self._map_events = [*ckpt.event_seqs, -1]  # as for the links: not waited for after a restart
        self._relocalised, self._relocalise = ckpt.relocalisations, []

    def _commit(self, links: list[LinkMeasured]) -> None:
        """Before anything of an applied input is published: the links into the log, then the state."""
        self._files.record(links)
        self._files.save(self)

    # -- inputs ---------------------------------------------------------------------------------
    def on_dr_pose(self, msg: DeadReckonedPose) -> None:
        if not self._history.add(msg):
            return  # older than one already kept: dead reckoning repeats only its first pose
        self.latest_stamp = msg.stamp
        self.drain()

    def on_sonar(self, msg: SonarScan) -> None:
        self._scan_heard = max(self._scan_heard, msg.seq)
        if msg.seq <= self._last_scan_seq or any(s.seq == msg.seq for s, _ in self._scans):
            self.counts["repeated_scans"] += 1  # the simulator repeats tick 0 until it starts
            last = self._last_belief
            if last is not None and msg.seq == self._last_scan_seq and last.stamp == msg.stamp:
                self._publish_belief(last)  # so does its localization, for a subscriber that came late
            return
        bisect.insort(self._scans, (msg, self._clock()), key=lambda e: e[0].stamp)
        if len(self._scans) > self.params.max_pending_scans:
            self._scans.pop(0)
            self.counts["dropped_scans"] += 1
        self.drain()

    def on_odometry(self, msg: OdometryStep) -> None:
        self._sensor_tick = max(self._sensor_tick, self._tick(msg.stamp))
        self._scan_due = max(self._scan_due, msg.sonar_seq)
        self.drain()

    def on_command(self, msg: VelocityCommand) -> None:
        self._cmd_tick = max(self._cmd_tick, msg.tick)
        self._event_due = [max(self._event_due[0], msg.confirmed_seq), max(self._event_due[1], msg.deleted_seq)]
        self._links_deleted_due = max(self._links_deleted_due, msg.links_deleted_seq)
        if msg.relocalisations > max(self._relocalised, self._relocalise[-1][1] if self._relocalise else 0):
            self._relocalise.append((msg.tick, msg.relocalisations))
        self.drain()

    def on_explorer_event(self, msg: PlaceConfirmed | PlaceDeleted) -> None:
        kind = isinstance(msg, PlaceDeleted)
        self._event_heard[kind] = max(self._event_heard[kind], msg.seq)
        key = self._event_key(msg)
        if key in self._applied or any(self._event_key(e) == key for e, _ in self._events):
            self.counts["repeated_events"] += 1  # history heard again after a restart
            return
        if self._tick(msg.stamp) < self._done_tick:
            self.counts["late_events"] += 1  # a scan after it was processed already: apply it now
            log.info("%s: %s of tick %d heard after tick %d was processed; applied now", SERVICE,
                     type(msg).__name__, self._tick(msg.stamp), self._done_tick)
            self._apply_event(msg)
            return
        self._events.append((msg, self._clock()))
        self.drain()

    @staticmethod
    def _event_key(msg: PlaceConfirmed | PlaceDeleted) -> int:
        return msg.place_id if isinstance(msg, PlaceConfirmed) else -1 - msg.place_id

    def on_map_update(self, msg: MapUpdate) -> None:
        self.counts["map_updates"] += 1
        if self.params.follow_map and msg.changed:
            self.core.move_places({p.place_id: (p.x_m, p.y_m) for p in msg.changed})
        self._map_seen = True
        self._map_heard = max(self._map_heard, msg.link_seq)
        self._map_events = [max(h, n) for h, n in
                            zip(self._map_events, (msg.confirmed_seq, msg.deleted_seq, msg.links_deleted_seq))]
        self.drain()

    def _events_named(self) -> list[int]:
        return [*self._event_due, self._links_deleted_due]

    def _map_in(self) -> bool:
        """Whether the map updates of the links published so far, and of the explorer's events the
        commands named, are in (or not waited for)."""
        p = self.params
        return not (p.follow_map and p.wait_map and self._map_seen) or (
            self._map_heard >= self._link_seq - 1
            and all(h >= n for h, n in zip(self._map_events, self._events_named())))

    def drain(self) -> None:
        """Apply every input whose turn has come (also called periodically, for the timeouts)."""
        timeout = self.params.order_timeout_s
        while True:
            now = self._clock()
            if self._events:
                ev, since = self._events[0]
                j = self._tick(ev.stamp)
                scan_first = bool(self._scans) and self._tick(self._scans[0][0].stamp) <= j
                if not scan_first:
                    ready = (self._sensor_tick >= j + 1 and self._scan_heard >= self._scan_due
                             and self._history.reaches(ev.stamp) and (self._cmd_tick >= j or self._cmd_tick < 0))
                    if (ready and self._map_in()) or now - max(since, self._linked) >= timeout:
                        self.counts["order_timeouts"] += not ready
                        self._give_up_waiting()
                        self._events.pop(0)
                        self._done_tick = max(self._done_tick, j)
                        self._apply_event(ev)
                        if not (self._events and self._tick(self._events[0][0].stamp) == j) and not any(
                                self._tick(sc.stamp) == j + 1 for sc, _ in self._scans):
                            self._progress(j + 1)  # the tick after the events has no scan: its work is done
                        continue
            if self._scans:
                scan, since = self._scans[0]
                t = self._tick(scan.stamp)
                events_first = bool(self._events) and self._tick(self._events[0][0].stamp) < t
                has_pose = self._history.reaches(scan.stamp)
                events_in = all(h >= d for h, d in zip(self._event_heard, self._event_due))
                ready = has_pose and (t == 0 or (self._cmd_tick >= t - 1 and events_in))
                if not events_first and ((ready and self._map_in()) or (now - max(since, self._linked) >= timeout
                                                                and len(self._history) > 0)):
                    self.counts["order_timeouts"] += not ready
                    self._give_up_waiting()
                    self._scans.pop(0)
                    self._done_tick = max(self._done_tick, t)
                    self._relocalise_before(t)
                    self._step(scan)
                    self._progress(t)
                    continue
            return

    def _progress(self, tick: int) -> None:
        if self._publish_progress is not None:
            self._publish_progress(RecognizerProgress(stamp=tick * self.params.dt_s, seq=self._progress_seq, tick=tick,
                                                      link_seq=self._link_seq - 1))
            self._progress_seq += 1

    def _give_up_waiting(self) -> None:
        """After an order timeout: what was named and not heard is lost (a restart), not late."""
        if self._scan_heard < self._scan_due or any(h < d for h, d in zip(self._event_heard, self._event_due)):
            log.warning("%s: scans up to seq %d and place events up to seqs %s not heard within %.1f s; going on "
                        "without them", SERVICE, self._scan_due, self._event_due, self.params.order_timeout_s)
        if not self._map_in():
            self.counts["map_timeouts"] += 1
            log.warning("%s: no map update for link %d and the explorer's events %s within %.1f s; going on without "
                        "it", SERVICE, self._link_seq - 1, self._events_named(), self.params.order_timeout_s)
        self._scan_heard = max(self._scan_heard, self._scan_due)
        self._event_heard = [max(h, d) for h, d in zip(self._event_heard, self._event_due)]
        self._map_heard = max(self._map_heard, self._link_seq - 1)
        self._map_events = [max(h, n) for h, n in zip(self._map_events, self._events_named())]

    def _relocalise_before(self, tick: int) -> None:
        """Act on the explorer's requests to relocalise named by the commands of ticks before ``tick``
        (in process: after the explorer's step of tick ``j - 1``, before the scan of tick ``j``)."""
        due = [n for t, n in self._relocalise if t < tick]
        if not due:
            return
        self._relocalise = [(t, n) for t, n in self._relocalise if t >= tick]
        if due[-1] > self._relocalised:
            self._relocalised = due[-1]
            self.core.relocalise()
            self.counts["relocalisations"] += 1
            log.info("%s: relocalising at the explorer's request %d (tick %d): the belief's mass spread near the "
                     "robot, no link from the place it was at", SERVICE, due[-1], tick)

    # -- processing -----------------------------------------------------------------------------
    def _step(self, scan: SonarScan) -> None:
        self._last_scan_seq = max(self._last_scan_seq, scan.seq)
        dr = self._history.at(scan.stamp)
        if dr is None:
            self.counts["unpaired_scans"] += 1
            return
        out = self.core.step(dr, scan, self._history.between(self._stepped_stamp, dr.stamp))
        self._stepped_stamp = dr.stamp
        self.counts["scans"] += 1
        loc = out.localization
        self.counts["localised"] += loc.place_id >= 0
        links = self._links(out, scan.stamp)
        belief = LocalizationBelief(
            stamp=scan.stamp, seq=self._belief_seq, place_id=loc.place_id, probability=loc.probability,
            offset_x_m=loc.offset_x_m, offset_y_m=loc.offset_y_m, offset_var_m2=loc.offset_var_m2,
            hypotheses=[Hypothesis(place_id=i, probability=p) for i, p in loc.hypotheses], pose=dr.compass,
            link_seq=self._link_seq - 1)
        self._belief_seq += 1
        self._last_belief = belief
        self._commit(links)
        self._publish_belief(belief)
        for link in links:
            self._publish_link(link)

    def _apply_event(self, ev: PlaceConfirmed | PlaceDeleted) -> None:
        kind = isinstance(ev, PlaceDeleted)
        self._event_applied[kind] = max(self._event_applied[kind], ev.seq)
        if isinstance(ev, PlaceDeleted):
            self.core.remove_place(ev.place_id)
            self.counts["deleted"] += 1
            self._applied.add(self._event_key(ev))
            self._commit([])
            return
        dr = self._history.at(ev.stamp)
        if dr is None:
            dr = self._history.first
        if dr is None:
            return
        self.counts["places"] += 1
        self._applied.add(self._event_key(ev))
        links = self._links(self.core.add_place(ev.place_id, ev.x_m, ev.y_m, dr), ev.stamp)
        self._commit(links)
        for link in links:
            self._publish_link(link)

    def _links(self, out: RecognizerOutput, stamp: float) -> list[LinkMeasured]:
        links = []
        for link in out.links:
            links.append(LinkMeasured(stamp=stamp, seq=self._link_seq, **asdict(link)))
            self._link_seq += 1
            self.counts["links"] += 1
        if links:
            self._linked = self._clock()  # the wait for their map update starts now
        return links

    def resend_recorded(self) -> int:
        """Publish again the latest measurement of every link in the links log; returns how many.

        After a restart: a link the killed process logged may not have left it. Receivers take a
        measurement they hold already as a repeat (the relaxer compares it with the one it holds).
        """
        links = self._files.recorded()
        for link in links:
            self._publish_link(link)
        self.counts["resent_links"] += len(links)
        return len(links)


def run(session: zenoh.Session, params: PlaceRecognizerNodeParams = PlaceRecognizerNodeParams(), *,
        robot: str = topics.DEFAULT_ROBOT, stop: threading.Event | None = None) -> RecognizerShell:
    """Recognise places until ``stop`` or a limit; return the shell (its core and counters)."""
    stop = stop or threading.Event()
    with Node(session, SERVICE, robot=robot) as node:
        pub_belief = node.publisher(topics.localization(robot), LocalizationBelief)
        pub_link = node.publisher(topics.links_measured(robot), LinkMeasured, history=topics.MAP_EVENT_HISTORY)
        pub_progress = node.publisher(topics.recognizer_progress(robot), RecognizerProgress)
        files = RecognizerFiles(params.state_path, params.links_log)
        shell = RecognizerShell(params, pub_belief.put, pub_link.put, files=files, publish_progress=pub_progress.put)
        saved = files.load()
        if saved is not None:  # a restart within the run: the checkpoint wins over --resume
            shell.resume(*saved)
            log.info("%s: resumed with %d places from %s", SERVICE, shell.core.belief.ids.size, params.state_path)
        elif params.resume:
            shell.restore(fetch_saved_map(session, robot, near_m=params.resume_near_m, at=params.resume_at))
        if shell.resend_recorded():
            log.info("%s: %d links of the links log published again", SERVICE, shell.counts["resent_links"])

        def update_detail() -> None:
            node.detail.update(shell.counts)
            node.detail["known_places"] = float(shell.core.belief.ids.size)
            node.detail["rejected_traversals"] = float(shell.core.rejected_traversals)
            node.detail["rejected_arrivals"] = float(shell.core.rejected_arrivals)
            node.detail["pending_scans"] = float(len(shell._scans))
            node.detail["pending_events"] = float(len(shell._events))
            node.detail["last_stamp_s"] = shell.latest_stamp if math.isfinite(shell.latest_stamp) else 0.0

        def on_dr_pose(msg: DeadReckonedPose) -> None:
            shell.on_dr_pose(msg)
            if params.max_sim_time_s is not None and msg.stamp >= params.max_sim_time_s - 1e-9:
                log.info("%s: simulated time %.1f s reached", SERVICE, msg.stamp)
                stop.set()

        node.subscribe(topics.dr_pose(robot), DeadReckonedPose, on_dr_pose)
        node.subscribe(topics.sonar(robot), SonarScan, shell.on_sonar)
        node.subscribe(topics.odometry(robot), OdometryStep, shell.on_odometry)
        node.subscribe(topics.cmd_velocity(robot), VelocityCommand, shell.on_command)
        node.subscribe(topics.places_confirmed(robot), PlaceConfirmed, shell.on_explorer_event)
        node.subscribe(topics.places_deleted(robot), PlaceDeleted, shell.on_explorer_event)
        if saved is not None:
            # resumed: the explorer's history brings the place events sent while this process was away
            # (an event heard on both subscribers is applied once). Only then: a history subscriber may
            # hand over an event after the velocity command the explorer sent after it, and the order
            # of events and scans (above) would no longer be the explorer's.
            node.subscribe(topics.places_confirmed(robot), PlaceConfirmed, shell.on_explorer_event, history=True)
            node.subscribe(topics.places_deleted(robot), PlaceDeleted, shell.on_explorer_event, history=True)
        node.subscribe(topics.map_update(robot), MapUpdate, shell.on_map_update)
        update_detail()
        wall_end = time.monotonic() + params.duration_s if params.duration_s else math.inf

        def on_tick() -> None:
            shell.drain()
            update_detail()
            if time.monotonic() >= wall_end:
                stop.set()

        node.spin(stop, tick=on_tick, period_s=0.1)
        update_detail()
        log.info("%s: %d scans, %d localised, %d places, %d links; %d order timeouts, %d map timeouts, %d late "
                 "events, %d unpaired scans, %d dropped scans", SERVICE, shell.counts["scans"],
                 shell.counts["localised"], shell.counts["places"], shell.counts["links"],
                 shell.counts["order_timeouts"], shell.counts["map_timeouts"], shell.counts["late_events"],
                 shell.counts["unpaired_scans"], shell.counts["dropped_scans"])
    return shell



def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=0,
                        help="accepted for a uniform command line; the recognizer draws no random numbers")
    parser.add_argument("--no-follow-map", action="store_true",
                        help="keep place centres in dead-reckoning coordinates (ignore map/update)")
    parser.add_argument("--no-wait-map", action="store_true",
                        help="after a link, go on without waiting for the map update that holds it")
    parser.add_argument("--no-compass-deviation", action="store_true",
                        help="do not learn the compass's deviation per place nor correct the links' angles by it")
    parser.add_argument("--max-sim-time", type=positive_float, default=None, metavar="S",
                        help="stop after the pose that reaches this simulated time")
    parser.add_argument("--duration-s", type=positive_float, default=None, help="stop after this wall time")
    add_resume_arguments(parser)
    parser.add_argument("--order-timeout-s", type=positive_float, default=0.5,
                        help="wall time an input waits for the inputs that must come first (default 0.5)")
    parser.add_argument("--state", metavar="PATH", default=None,
                        help="checkpoint file (and PATH.signatures/): a restarted process resumes from it")
    parser.add_argument("--links-log", metavar="PATH", default=None,
                        help="append every link measured to this file (JSON lines) before publishing it; "
                             "a restarted process publishes the latest of each again")


def main_run(session: zenoh.Session, args: argparse.Namespace, stop: threading.Event) -> None:
    """What ``python -m services.place_recognizer`` runs once the session is open."""
    run(session, PlaceRecognizerNodeParams(follow_map=not args.no_follow_map, wait_map=not args.no_wait_map,
                                           max_sim_time_s=args.max_sim_time,
                                           duration_s=args.duration_s, order_timeout_s=args.order_timeout_s,
                                           state_path=args.state, links_log=args.links_log, resume=args.resume,
                                           resume_at=robot_at_from_args(args),
                                           core=PlaceRecognizerParams(deviation=DeviationParams(
                                               enabled=not args.no_compass_deviation))),
        robot=args.robot, stop=stop)
