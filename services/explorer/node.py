"""explorer on the bus: poses, sonar, localizations and the map in; velocity commands and the place graph out."""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from dataclasses import asdict, dataclass, field

import msgspec
import zenoh

from messages import topics
from messages.types import (
    DeadReckonedPose,
    ExplorationStatus,
    LinkConfidence,
    LinkDeleted,
    LinkInferred,
    LocalizationBelief,
    MapUpdate,
    OdometryStep,
    PlaceConfirmed,
    PlaceDeleted,
    PlacePredicted,
    PlaceScan,
    Pose2,
    RecognizerProgress,
    SonarScan,
    VelocityCommand,
)
from services.explorer.core import (
    Explorer,
    ExplorerOutput,
    ExplorerParams,
    ExplorerState,
    LinkConfidenceEvent,
    LinkDeletedEvent,
    LinkInferredEvent,
    PlaceConfirmedEvent,
    PlaceDeletedEvent,
    PlaceFix,
    PlacePredictedEvent,
)
from services.runtime import Node, nonnegative_int, positive_float
from services.runtime.saved_map import (
    RobotAt,
    SavedMap,
    add_resume_arguments,
    fetch_saved_map,
    robot_at_from_args,
    sonar_scan,
)
from services.runtime.checkpoint import Checkpoint, EventLog

SERVICE = "explorer"
log = logging.getLogger("relaxmap.explorer")

_EVENT_TYPES = {
    PlacePredictedEvent: (PlacePredicted, "places_predicted"),
    PlaceConfirmedEvent: (PlaceConfirmed, "places_confirmed"),
    PlaceDeletedEvent: (PlaceDeleted, "places_deleted"),
    LinkInferredEvent: (LinkInferred, "links_inferred"),
    LinkConfidenceEvent: (LinkConfidence, "links_confidence"),
    LinkDeletedEvent: (LinkDeleted, "links_deleted"),
}


@dataclass(frozen=True)
class ExplorerNodeParams:
    dt_s: float = 0.1  # sensor_sim's tick: a pose stamped t answers tick round(t / dt_s)
    wait_localization: bool = True  # answer a tick only once the localizations of earlier scans are in
    localization_timeout_s: float = 2.0  # wall time to wait for one before answering without it
    follow_map: bool = True  # move places to the relaxed coordinates of map/update
    wait_map: bool = True  # following the map, answer a tick once the updates of the links and places before it are in
    map_timeout_s: float = 0.5  # wall time to wait for those updates before answering without them
    status_period_s: float = 1.0  # simulated time between status messages (and on every change)
    max_sim_time_s: float | None = None  # stop after answering the tick at or past this simulated time
    duration_s: float | None = None  # stop after this wall time
    resume: bool = False  # continue the map the relaxer holds (asked over the bus before the start)
    first_place_id: int = 0  # with resume: new places get ids from here on (above every id used before)
    resume_near_m: float = 1.0  # places are predicted from their scans taken this close to the centre
    resume_at: RobotAt | None = None  # with resume: where the robot was (None: by the latest stored scan)
    state_path: str | None = None  # checkpoint: saved with every answered tick, resumed from after a restart
    core: ExplorerParams = field(default_factory=ExplorerParams)  # the explorer itself


class ExplorerCheckpoint(msgspec.Struct, frozen=True):
    """The explorer and the shell's bookkeeping, as of the last tick answered."""

    core: ExplorerState
    last_tick: int
    sensor_tick: int
    last_cmd: tuple[float, float]
    seq: dict[str, int]
    status: tuple[bool, int, int, int] | None
    status_stamp: float
    scans: dict[int, SonarScan]
    beliefs: dict[int, LocalizationBelief]
    counts: dict[str, int]
    scan_heard: int = -1
    scan_due: int = -1
    placed_tick: int = -1


class ExplorerShell:
    """Answers every tick of the simulator's lockstep clock exactly once, reproducibly.

    The command for tick ``k`` is computed from the dead-reckoned pose of tick ``k`` with the sonar
    scan of an earlier tick and the recognizer's localization of that scan (normally tick ``k - 1``),
    as :mod:`services.launch.inprocess` does. The scans of earlier ticks are in once the odometry step
    of tick ``k`` is and the scan it names (``sonar_seq``) has been heard: zenoh keeps the order of
    one key's messages, not across keys, so a scan can come after a later odometry step. The
    localization comes later still, so the answer waits for all of them, at most
    ``localization_timeout_s`` (counted in health; the tick is then answered without). A pose of a
    tick already answered (the simulator repeats tick 0 until its first command arrives) is answered
    again with the same command. Once exploration is complete every tick is answered with zero velocity.

    Following the relaxed map (``follow_map`` and ``wait_map``), once a map update has been heard, the
    answer also waits for the map as the in-process loop has it at the explorer's step of tick ``k``:
    when the recognizer has work at tick ``k`` (the tick's scan, or the place events of tick ``k - 1``),
    for its ``RecognizerProgress`` of tick ``k``; then for the update that holds the latest link it
    names (or the latest link a localization of an earlier scan names) and the latest place
    confirmation and place and link deletion this shell published (``MapUpdate.link_seq``,
    ``confirmed_seq``, ``deleted_seq``, ``links_deleted_seq``); at most ``map_timeout_s`` (counted in
    ``map_timeouts``). No later update can come before the answer: the recognizer's next work waits
    for this tick's command. So the answer is a function of the seed, as in the loop.
    """

    def __init__(self, params: ExplorerNodeParams, publish, clock=time.monotonic, save=None,
                 log_events=None) -> None:
        self.params = params
        self._save = save  # save(checkpoint), called with every answer before anything is published
        self._log_events = log_events  # log_events([(topic name, message)]): map events, before they go out
        self.core = Explorer(params.core)
        self._publish = publish  # publish(topic_name, message)
        self._clock = clock
        self._pose: DeadReckonedPose | None = None  # the pose awaiting its answer
        self._pose_wall = 0.0
        self._scans: dict[int, SonarScan] = {}  # tick -> scan not yet given to the core
        self._beliefs: dict[int, LocalizationBelief] = {}  # tick -> localization of that scan
        self.last_tick = -1
        self._sensor_tick = -1  # the latest tick of an odometry step
        self._scan_heard = -1  # the highest seq of a scan heard
        self._scan_due = -1  # the highest seq of a scan an odometry step said was published
        self._last_cmd = (0.0, 0.0)
        self._seq: dict[str, int] = {}
        self._status: tuple | None = None
        self._status_stamp = -math.inf
        self.output: ExplorerOutput | None = None
        self._map_seen = False  # a relaxer publishes
        self._map_heard = [-1, -1, -1, -1]  # the highest link, place confirmation, place deletion and link
        # deletion seqs a map update named
        self._progress_tick = -1  # the latest tick the recognizer said its work of was done
        self._progress_link = -1  # ... and the latest link then
        self._placed_tick = -1  # the latest tick this shell confirmed or deleted a place at
        self.counts = {"ticks": 0, "repeats": 0, "skipped_poses": 0, "scans": 0, "fixes": 0,
                       "localization_timeouts": 0, "map_updates": 0, "events": 0, "complete": 0,
                       "late_scans": 0, "scan_timeouts": 0, "relocalisations": 0, "map_timeouts": 0}

    def _tick_of(self, stamp: float) -> int:
        return round(stamp / self.params.dt_s)

    def checkpoint(self) -> ExplorerCheckpoint:
        return ExplorerCheckpoint(
            core=self.core.snapshot(), last_tick=self.last_tick, sensor_tick=self._sensor_tick,
            last_cmd=self._last_cmd, seq=dict(self._seq), status=self._status, status_stamp=self._status_stamp,
            scans=dict(self._scans), beliefs=dict(self._beliefs), counts=dict(self.counts),
            scan_heard=self._scan_heard, scan_due=self._scan_due, placed_tick=self._placed_tick)

    def resume(self, ckpt: ExplorerCheckpoint) -> None:
        """Go on from a checkpoint: the ticks it answered are answered, its events published."""
        self.core.restore_snapshot(ckpt.core)
        self.last_tick, self._sensor_tick, self._last_cmd = ckpt.last_tick, ckpt.sensor_tick, tuple(ckpt.last_cmd)
        self._seq, self._status_stamp = dict(ckpt.seq), ckpt.status_stamp
        self._status = tuple(ckpt.status) if ckpt.status is not None else None
        self._scans, self._beliefs = dict(ckpt.scans), dict(ckpt.beliefs)
        self._scan_heard, self._scan_due = ckpt.scan_heard, ckpt.scan_due
        self._placed_tick = ckpt.placed_tick
        self.counts.update(ckpt.counts)

    def _next_seq(self, name: str) -> int:
        n = self._seq.get(name, 0)
        self._seq[name] = n + 1
        return n

    def restore(self, saved: SavedMap) -> None:
        """Continue the saved map: its places and links, fresh predictions, the robot where it was."""
        places = {p.place_id: (p.x_m, p.y_m) for p in saved.graph.places}
        nearest: dict[int, PlaceScan] = {}
        for s in saved.near:
            best = nearest.get(s.place_id)
            if best is None or math.hypot(s.offset_x_m, s.offset_y_m) < math.hypot(best.offset_x_m, best.offset_y_m):
                nearest[s.place_id] = s
        last, at = saved.latest, saved.robot
        cx, cy = places[at.place_id]
        events = self.core.restore(
            places, [(lk.from_id, lk.to_id, lk.traversals) for lk in saved.graph.links],
            {pid: (s.heading_rad, sonar_scan(s)) for pid, s in nearest.items()}, at_place=at.place_id,
            robot_xy=(cx + at.offset_xy[0], cy + at.offset_xy[1]),
            pose=Pose2(x_m=at.dr_xy[0], y_m=at.dr_xy[1], heading_rad=last.heading_rad), scan=sonar_scan(last),
            next_place_id=max(self.params.first_place_id, max(saved.graph.deleted, default=-1) + 1))
        for ev in events:
            msg_type, name = _EVENT_TYPES[type(ev)]
            self._publish(name, msg_type(stamp=last.stamp, seq=self._next_seq(name), **asdict(ev)))
            self.counts["events"] += 1
        log.info("%s: continuing %d places, %d links from place %d; %d places predicted", SERVICE, len(places),
                 len(saved.graph.links), at.place_id, len(events))

    # -- inputs ---------------------------------------------------------------------------------
    def on_dr_pose(self, msg: DeadReckonedPose) -> None:
        tick = self._tick_of(msg.stamp)
        if tick <= self.last_tick:
            if tick == self.last_tick:  # the simulator repeats a tick it has no command for
                self.counts["repeats"] += 1
                self._command(msg.stamp, tick, *self._last_cmd)
            return
        if self._pose is not None and self._tick_of(self._pose.stamp) == tick:
            self._pose = msg  # the same tick again (the simulator's start): keep waiting from the first
        else:
            if self._pose is not None:
                self.counts["skipped_poses"] += 1  # real-time clock: only the newest pose is answered
            self._pose, self._pose_wall = msg, self._clock()
        self.try_answer()

    def on_sonar(self, msg: SonarScan) -> None:
        self._scan_heard = max(self._scan_heard, msg.seq)
        tick = self._tick_of(msg.stamp)
        if tick >= self.last_tick:  # a scan of the tick just answered serves the next one
            self._scans[tick] = msg
        else:
            self.counts["late_scans"] += 1  # a later tick was answered without it
            log.info("%s: scan of tick %d heard after tick %d was answered", SERVICE, tick, self.last_tick)
        self.try_answer()

    def on_odometry(self, msg: OdometryStep) -> None:
        self._sensor_tick = max(self._sensor_tick, self._tick_of(msg.stamp))
        self._scan_due = max(self._scan_due, msg.sonar_seq)
        self.try_answer()

    def on_localization(self, msg: LocalizationBelief) -> None:
        tick = self._tick_of(msg.stamp)
        if tick >= self.last_tick:
            self._beliefs[tick] = msg
        self.try_answer()

    def on_map_update(self, msg: MapUpdate) -> None:
        self.counts["map_updates"] += 1
        if self.params.follow_map and msg.changed:
            self.core.move_places({p.place_id: (p.x_m, p.y_m) for p in msg.changed})
        self._map_seen = True
        named = (msg.link_seq, msg.confirmed_seq, msg.deleted_seq, msg.links_deleted_seq)
        self._map_heard = [max(h, n) for h, n in zip(self._map_heard, named)]
        self.try_answer()

    def on_progress(self, msg: RecognizerProgress) -> None:
        if msg.tick >= self._progress_tick:
            self._progress_tick, self._progress_link = msg.tick, max(self._progress_link, msg.link_seq)
        self.try_answer()

    def _following(self) -> bool:
        p = self.params
        return p.follow_map and p.wait_map and self._map_seen

    def _recognizer_due(self, tick: int) -> bool:
        """Whether the recognizer has work at ``tick`` whose progress the answer has not heard."""
        work = tick in self._scans or (self._placed_tick >= 0 and self._placed_tick == tick - 1)
        return self._following() and work and self._progress_tick < tick

    def _map_due(self, earlier: list[int]) -> list[int] | None:
        """The link, place confirmation, place deletion and link deletion seqs whose map updates the
        answer after the scans of ``earlier`` ticks waits for; None when it waits for none."""
        if not self._following():
            return None
        links = max([self._progress_link] + [self._beliefs[t].link_seq for t in earlier if t in self._beliefs])
        return [links, self._seq.get("places_confirmed", 0) - 1, self._seq.get("places_deleted", 0) - 1,
                self._seq.get("links_deleted", 0) - 1]

    def check_timeout(self) -> None:
        """Called periodically: answer a pose whose localization is overdue."""
        self.try_answer()

    # -- answering ------------------------------------------------------------------------------
    def try_answer(self) -> None:
        pose = self._pose
        if pose is None:
            return
        tick = self._tick_of(pose.stamp)
        waited = self._clock() - self._pose_wall
        if self.last_tick >= 0 and (self._sensor_tick < tick or self._scan_heard < self._scan_due):
            # the odometry of this tick names the scans before it: wait for both (the first tick, 0 or
            # the one a continued run starts at, comes without odometry)
            if waited < self.params.localization_timeout_s:
                return
            if self._scan_heard < self._scan_due:  # lost for good (a restart): wait for it no more
                self.counts["scan_timeouts"] += 1
                log.warning("%s: scans up to seq %d not heard within %.1f s: answering tick %d without them",
                            SERVICE, self._scan_due, self.params.localization_timeout_s, tick)
                self._scan_heard = self._scan_due
        earlier = sorted(t for t in self._scans if t < tick)
        missing = [t for t in earlier if t not in self._beliefs]
        if missing and self.params.wait_localization:
            if waited < self.params.localization_timeout_s:
                return
            self.counts["localization_timeouts"] += len(missing)
            log.warning("%s: no localization for the scan of tick %d within %.1f s: answering tick %d without it",
                        SERVICE, missing[-1], self.params.localization_timeout_s, tick)
        recognizer_due = self._recognizer_due(tick)
        due = self._map_due(earlier)
        if recognizer_due or (due is not None and any(h < d for h, d in zip(self._map_heard, due))):
            if waited < self.params.map_timeout_s:
                return
            self.counts["map_timeouts"] += 1  # the recognizer or the relaxer is slow or gone: answer without
            log.warning("%s: %s within %.1f s: answering tick %d without it", SERVICE,
                        "the recognizer's work of the tick not done" if recognizer_due else
                        "no map update for link %d and place events %d, %d, %d" % tuple(due),
                        self.params.map_timeout_s, tick)
            self._progress_tick = max(self._progress_tick, tick)
            if due is not None:
                self._map_heard = [max(h, d) for h, d in zip(self._map_heard, due)]
        scan = self._scans[earlier[-1]] if earlier else None
        with_fix = [t for t in earlier if t in self._beliefs]
        fix = PlaceFix.from_message(self._beliefs[with_fix[-1]]) if with_fix else None
        for t in earlier:
            self._scans.pop(t)
        self._beliefs = {t: b for t, b in self._beliefs.items() if t >= tick}
        self._pose = None
        self.counts["scans"] += scan is not None
        self.counts["fixes"] += fix is not None
        requests = self.core.relocalisations
        out = self.core.step(pose.stamp, pose.compass, scan, fix)
        self.output = out
        if self.core.relocalisations > requests:
            self.counts["relocalisations"] = self.core.relocalisations
            log.info("%s: legs keep failing from place %d, where the belief puts the robot: asking the "
                     "recognizer to relocalise (request %d)", SERVICE, self.core.last_place, self.core.relocalisations)
        events = []
        for ev in out.events:
            msg_type, name = _EVENT_TYPES[type(ev)]
            events.append((name, msg_type(stamp=pose.stamp, seq=self._next_seq(name), **asdict(ev))))
            if name in ("places_confirmed", "places_deleted"):
                self._placed_tick = tick  # the recognizer applies it at the next tick
        cmd = (0.0, 0.0) if out.status.complete else (out.command.v_mps, out.command.omega_radps)
        self.counts["ticks"] += 1
        self.counts["events"] += len(events)
        self.counts["complete"] = int(out.status.complete)
        self.last_tick, self._last_cmd = tick, cmd
        st = out.status
        key = (st.complete, st.confirmed, st.predicted, st.target_id)
        status = None
        if key != self._status or pose.stamp - self._status_stamp >= self.params.status_period_s - 1e-9:
            self._status, self._status_stamp = key, pose.stamp
            status = ExplorationStatus(
                stamp=pose.stamp, seq=self._next_seq("exploration_status"), complete=st.complete,
                confirmed=st.confirmed, predicted=st.predicted, target_id=st.target_id)
        command = self._velocity(pose.stamp, tick, *cmd)
        map_events = [(name, msg) for name, msg in events if name in _EVENT_TOPIC.values()]
        if self._log_events is not None and map_events:
            self._log_events(map_events)
        if self._save is not None:  # a place id published is a place id the checkpoint knows
            self._save(self.checkpoint())
        for name, msg in events:
            self._publish(name, msg)
        self._publish("cmd_velocity", command)
        if status is not None:
            self._publish("exploration_status", status)

    def _command(self, stamp: float, tick: int, v: float, w: float) -> None:
        self._publish("cmd_velocity", self._velocity(stamp, tick, v, w))

    def _velocity(self, stamp: float, tick: int, v: float, w: float) -> VelocityCommand:
        """The command of ``tick``, naming the latest place events published before it; final once
        exploration is complete (the status of the tick is kept before its command is made)."""
        return VelocityCommand(stamp=stamp, seq=self._next_seq("cmd_velocity"), v_mps=v, omega_radps=w, tick=tick,
                               confirmed_seq=self._seq.get("places_confirmed", 0) - 1,
                               deleted_seq=self._seq.get("places_deleted", 0) - 1,
                               links_deleted_seq=self._seq.get("links_deleted", 0) - 1,
                               relocalisations=self.core.relocalisations,
                               final=self._status is not None and self._status[0])


# The map events, logged before they go out and published again after a restart. A repeat is harmless:
# place ids are never reused (a known place stays known, a deleted one deleted), and receivers ignore
# a link deletion older than the link's latest measurement.
_MapEvent = PlaceConfirmed | PlaceDeleted | LinkDeleted
_EVENT_TOPIC = {PlaceConfirmed: "places_confirmed", PlaceDeleted: "places_deleted", LinkDeleted: "links_deleted"}
_TYPES = {"cmd_velocity": VelocityCommand, "places_predicted": PlacePredicted, "places_confirmed": PlaceConfirmed,
          "places_deleted": PlaceDeleted, "links_inferred": LinkInferred, "links_confidence": LinkConfidence,
          "links_deleted": LinkDeleted, "exploration_status": ExplorationStatus}


def run(session: zenoh.Session, params: ExplorerNodeParams = ExplorerNodeParams(), *,
        robot: str = topics.DEFAULT_ROBOT, stop: threading.Event | None = None) -> ExplorerShell:
    """Explore until ``stop`` or a limit; return the shell (its core and counters)."""
    stop = stop or threading.Event()
    with Node(session, SERVICE, robot=robot) as node:
        pubs = {name: node.publisher(getattr(topics, name)(robot), type_,
                                     history=topics.MAP_EVENT_HISTORY if name in topics.MAP_EVENT_TOPICS else 0)
                for name, type_ in _TYPES.items()}
        ckpt = Checkpoint(params.state_path, ExplorerCheckpoint) if params.state_path else None
        events = EventLog(f"{params.state_path}.events", _MapEvent) if params.state_path else None
        shell = ExplorerShell(params, lambda name, msg: pubs[name].put(msg), save=ckpt.save if ckpt else None,
                              log_events=(lambda evs: events.append([m for _, m in evs])) if events else None)
        saved = ckpt.load() if ckpt else None
        if saved is not None:  # a restart within the run: the checkpoint wins over --resume
            shell.resume(saved)
            log.info("%s: resumed at tick %d with %d places from %s", SERVICE, shell.last_tick,
                     len(shell.core.places), params.state_path)
        elif params.resume:
            shell.restore(fetch_saved_map(session, robot, near_m=params.resume_near_m, at=params.resume_at))
        if events is not None:
            # the killed process may have logged map events that never left it: all of them again,
            # in their order
            resent = events.read()
            for msg in resent:
                pubs[_EVENT_TOPIC[type(msg)]].put(msg)
            if resent:
                log.info("%s: %d map events of %s published again", SERVICE, len(resent), events.path)

        def update_detail() -> None:
            node.detail.update(shell.counts)
            node.detail["last_tick"] = float(shell.last_tick)
            node.detail["confirmed"] = float(sum(q.confirmed for q in shell.core.places.values()))
            node.detail["predicted"] = float(sum(not q.confirmed for q in shell.core.places.values()))
            node.detail["stalls"] = float(shell.core.stalls)

        def on_dr_pose(msg: DeadReckonedPose) -> None:
            shell.on_dr_pose(msg)
            if params.max_sim_time_s is not None and shell.last_tick * params.dt_s >= params.max_sim_time_s - 1e-9:
                log.info("%s: simulated time %.1f s reached", SERVICE, shell.last_tick * params.dt_s)
                stop.set()

        node.subscribe(topics.dr_pose(robot), DeadReckonedPose, on_dr_pose)
        node.subscribe(topics.sonar(robot), SonarScan, shell.on_sonar)
        node.subscribe(topics.recognizer_progress(robot), RecognizerProgress, shell.on_progress)
        node.subscribe(topics.odometry(robot), OdometryStep, shell.on_odometry)
        node.subscribe(topics.localization(robot), LocalizationBelief, shell.on_localization)
        node.subscribe(topics.map_update(robot), MapUpdate, shell.on_map_update)
        update_detail()
        wall_end = time.monotonic() + params.duration_s if params.duration_s else math.inf

        def on_tick() -> None:
            shell.check_timeout()
            update_detail()
            if time.monotonic() >= wall_end:
                stop.set()

        node.spin(stop, tick=on_tick, period_s=0.05)
        update_detail()
        log.info("%s: %d ticks, %d confirmed places, complete=%s; %d localization timeouts, %d scan timeouts, "
                 "%d map timeouts, %d late scans, %d skipped poses", SERVICE, shell.counts["ticks"],
                 int(node.detail["confirmed"]), bool(shell.counts["complete"]), shell.counts["localization_timeouts"],
                 shell.counts["scan_timeouts"], shell.counts["map_timeouts"], shell.counts["late_scans"],
                 shell.counts["skipped_poses"])
    return shell



def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=0,
                        help="accepted for a uniform command line; the explorer draws no random numbers")
    parser.add_argument("--dt-s", type=positive_float, default=0.1, help="sensor_sim's tick (default 0.1)")
    parser.add_argument("--no-wait-localization", action="store_true",
                        help="answer each tick at once, without waiting for the localization of the last scan")
    parser.add_argument("--localization-timeout-s", type=positive_float, default=2.0,
                        help="wall time to wait for a localization before answering without it (default 2)")
    parser.add_argument("--no-follow-map", action="store_true",
                        help="keep places in dead-reckoning coordinates (ignore map/update)")
    parser.add_argument("--no-wait-map", action="store_true",
                        help="answer a tick without waiting for the map updates of the links and places before it")
    parser.add_argument("--max-sim-time", type=positive_float, default=None, metavar="S",
                        help="stop after answering the tick that reaches this simulated time")
    parser.add_argument("--duration-s", type=positive_float, default=None, help="stop after this wall time")
    add_resume_arguments(parser)
    parser.add_argument("--first-place-id", type=nonnegative_int, default=0, metavar="N",
                        help="with --resume: new places get ids from N on (above every id used before)")
    parser.add_argument("--state", metavar="PATH", default=None,
                        help="checkpoint file: saved with every answered tick; a restarted process resumes from it")


def main_run(session: zenoh.Session, args: argparse.Namespace, stop: threading.Event) -> None:
    """What ``python -m services.explorer`` runs once the session is open."""
    run(session, ExplorerNodeParams(dt_s=args.dt_s, wait_localization=not args.no_wait_localization,
                                    localization_timeout_s=args.localization_timeout_s,
                                    follow_map=not args.no_follow_map, wait_map=not args.no_wait_map,
                                    max_sim_time_s=args.max_sim_time, duration_s=args.duration_s, resume=args.resume,
                                    first_place_id=args.first_place_id, resume_at=robot_at_from_args(args),
                                    state_path=args.state),
        robot=args.robot, stop=stop)
