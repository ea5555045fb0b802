"""The mapping loop in one process, without the bus: simulator, dead reckoning, recognizer, explorer, relaxer.

Every component is a pure core, stepped at the simulator's period in the order the bus nodes keep
(see ``docs/places.md``): at tick ``k`` the recognizer takes the explorer's events of tick ``k - 1``
and then the scan of tick ``k`` (with the dead-reckoned pose of the same tick); the explorer takes the
pose of tick ``k`` with the scan and the localization of tick ``k - 1``, and its command answers
tick ``k``. A run is a function of the world, the parameters and the seed. Ground truth is recorded
alongside (the true pose at every tick, at every scan and at every place confirmation) for the
measures of :mod:`services.launch.place_metrics`.

``python -m services.launch.inprocess --world orebro-office --seed 0`` runs one exploration and
prints its measures as JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from messages.types import (
    CompassReading,
    DeadReckonedPose,
    LinkDeleted,
    LinkMeasured,
    OdometryStep,
    PlaceConfirmed,
    PlaceDeleted,
    SonarScan,
)
from services.dead_reckoning import core as dr_core
from services.explorer import (
    Explorer,
    ExplorerParams,
    LinkDeletedEvent,
    PlaceConfirmedEvent,
    PlaceDeletedEvent,
    PlaceFix,
)
from services.place_recognizer import PlaceRecognizer, PlaceRecognizerParams, RecognizerOutput
from services.place_recognizer.history import POSE_HISTORY, PoseHistory
from services.relaxer.online import OnlineMap, OnlineParams
from services.sensor_sim import core as sim_core
from sim.world import World, load_world


def _default_sim() -> sim_core.SensorSimParams:
    return sim_core.SensorSimParams(sonar_every_m=0.2, sonar_period_s=1.0)


@dataclass(frozen=True)
class InProcessParams:
    """Parameters of an in-process run."""

    seed: int = 0  # seed of the simulator's random generator and of the relaxer's (a separate one)
    max_sim_time_s: float = 3600.0  # end the run at this simulated time
    stop_when_complete: bool = True  # end the run once exploration is complete
    relax: bool = True  # run the relaxer's on-line map and feed relaxed coordinates back
    sim: sim_core.SensorSimParams = field(default_factory=_default_sim)  # robot, sensors, scan spacing
    recognizer: PlaceRecognizerParams = field(default_factory=PlaceRecognizerParams)
    explorer: ExplorerParams = field(default_factory=ExplorerParams)
    online: OnlineParams = field(default_factory=OnlineParams)  # the relaxer's on-line map


@dataclass(frozen=True)
class ScanRecord:
    """One scan: where the robot truly was, where dead reckoning put it, what the recognizer said."""

    tick: int
    true_xy: tuple[float, float]
    dr_xy: tuple[float, float]
    place_id: int  # localization: the place the robot is at, -1 between places
    probability: float
    offset_xy: tuple[float, float]  # filtered offset from the most probable place's centre


@dataclass(frozen=True)
class PlaceRecord:
    """A confirmed place: the true robot position at its confirmation is its true centre."""

    place_id: int
    tick: int
    true_xy: tuple[float, float]
    map_xy: tuple[float, float]  # the explorer's coordinates at confirmation


@dataclass(frozen=True)
class LinkRecord:
    """A link measurement as published (fused over traversals)."""

    tick: int
    from_id: int
    to_id: int
    d_m: float
    theta_rad: float
    steps: int
    mean_step_m: float
    traversals: int


@dataclass
class RunRecord:
    """Everything an in-process run recorded."""

    world: str
    seed: int
    dt_s: float
    ticks: int = 0
    complete: bool = False
    complete_tick: int = -1  # first tick at which exploration was complete, -1 if never
    wall_time_s: float = 0.0
    trajectory: list[tuple[float, float]] = field(default_factory=list)  # true position at every tick
    scans: list[ScanRecord] = field(default_factory=list)
    places: dict[int, PlaceRecord] = field(default_factory=dict)  # confirmed places still in the map
    deleted_confirmed: list[int] = field(default_factory=list)  # confirmed places deleted later
    links: list[LinkRecord] = field(default_factory=list)
    predicted_left: int = 0  # predicted places at the end
    collisions: int = 0
    relocalisations: int = 0  # the explorer's requests to the recognizer to relocalise
    timings_s: dict[str, float] = field(default_factory=dict)  # wall time per component
    relaxed: dict[int, tuple[float, float]] = field(default_factory=dict)  # final relaxed coordinates
    noise: tuple[float, float, float] | None = None  # final S_dd, S_aa, S_da of the relaxer

    @property
    def sim_time_s(self) -> float:
        return self.ticks * self.dt_s

    def latest_links(self) -> dict[frozenset[int], LinkRecord]:
        """The last measurement of every link (the fused one), for links between places still mapped."""
        out: dict[frozenset[int], LinkRecord] = {}
        for lk in self.links:
            if lk.from_id in self.places and lk.to_id in self.places:
                out[frozenset((lk.from_id, lk.to_id))] = lk
        return out


class InProcessRun:
    """One exploration, stepped tick by tick (:meth:`tick`) or to the end (:meth:`run`)."""

    def __init__(self, world: World, params: InProcessParams = InProcessParams()) -> None:
        self.world = world
        self.params = params
        self.model = sim_core.SimModel(world, params.sim)
        self.rng = np.random.default_rng(params.seed)
        self.recognizer = PlaceRecognizer(params.recognizer)
        self.explorer = Explorer(params.explorer)
        # the relaxer's own generator from the same seed, as `relaxmap run` gives the relaxer node (--seed)
        self.online = OnlineMap(params.online, rng=np.random.default_rng(params.seed)) if params.relax else None
        self.record = RunRecord(world=world.name, seed=params.seed, dt_s=params.sim.dt_s)
        self._dr = dr_core.DrState()
        self._timings = dict.fromkeys(("sim", "dead_reckoning", "recognizer", "explorer", "relaxer"), 0.0)
        self._prev_events: tuple = ()
        self._prev_dr: DeadReckonedPose | None = None
        self._prev_scan: SonarScan | None = None
        self._prev_fix: PlaceFix | None = None
        self._relocalised = 0  # the explorer's relocalisation requests the recognizer has acted on
        self._history = PoseHistory(POSE_HISTORY)  # as the recognizer's node keeps them
        self._stepped_stamp: float | None = None  # the pose stamp of the last scan stepped
        self._state, frame = sim_core.start(self.model, self.rng)
        self._command = self._handle(frame)

    @property
    def done(self) -> bool:
        p, r = self.params, self.record
        return (r.ticks * p.sim.dt_s >= p.max_sim_time_s - 1e-9) or (p.stop_when_complete and r.complete)

    def run(self) -> RunRecord:
        """Step until exploration is complete or the simulated time limit; return the record."""
        t0 = time.perf_counter()
        while not self.done:
            self.tick()
        self.record.wall_time_s += time.perf_counter() - t0
        return self.finish()

    def tick(self) -> None:
        """One simulator period: the robot executes the last command, every core takes its inputs."""
        t0 = time.perf_counter()
        self._state, frame = sim_core.step(self._state, self._command, self.model, self.rng)
        self._timings["sim"] += time.perf_counter() - t0
        self._command = self._handle(frame)

    def finish(self) -> RunRecord:
        r = self.record
        r.timings_s = dict(self._timings)
        r.collisions = self._state.collisions
        r.relocalisations = self.explorer.relocalisations
        r.predicted_left = sum(1 for q in self.explorer.places.values() if not q.confirmed)
        if self.online is not None:
            self.online.settle()  # as the relaxer service does once the events stop: the map at its minimum
            r.relaxed = self.online.coordinates()
            n = self.online.relaxer.noise
            r.noise = (n.s_dd_m2, n.s_aa_rad2, n.s_da_m_rad)
        return r

    # -- one tick ---------------------------------------------------------------------------------
    def _handle(self, frame: sim_core.Frame) -> tuple[float, float]:
        r = self.record
        r.ticks = frame.tick
        truth = (frame.truth.pose.x_m, frame.truth.pose.y_m)
        r.trajectory.append(truth)
        dr = self._dead_reckon(frame.compass, frame.odometry)
        t0 = time.perf_counter()
        if self._prev_dr is not None:
            for ev in self._prev_events:
                if isinstance(ev, PlaceConfirmedEvent):
                    self._links(self.recognizer.add_place(ev.place_id, ev.x_m, ev.y_m, self._prev_dr), frame.tick)
                elif isinstance(ev, PlaceDeletedEvent):
                    self.recognizer.remove_place(ev.place_id)
        fix = None
        if frame.sonar is not None:
            if self.explorer.relocalisations > self._relocalised:  # asked for by tick k - 1's step
                self._relocalised = self.explorer.relocalisations
                self.recognizer.relocalise()
            out = self.recognizer.step(dr, frame.sonar, self._history.between(self._stepped_stamp, dr.stamp))
            self._stepped_stamp = dr.stamp
            self._links(out, frame.tick)
            loc = out.localization
            r.scans.append(ScanRecord(frame.tick, truth, (dr.compass.x_m, dr.compass.y_m), loc.place_id,
                                      loc.probability, (loc.offset_x_m, loc.offset_y_m)))
            fix = PlaceFix(loc.place_id, loc.offset_x_m, loc.offset_y_m, frame.sonar.stamp)
        self._timings["recognizer"] += time.perf_counter() - t0

        t0 = time.perf_counter()
        out = self.explorer.step(frame.truth.stamp, dr.compass, self._prev_scan, self._prev_fix)
        self._timings["explorer"] += time.perf_counter() - t0
        for ev in out.events:
            if isinstance(ev, PlaceConfirmedEvent):
                r.places[ev.place_id] = PlaceRecord(ev.place_id, frame.tick, truth, (ev.x_m, ev.y_m))
            elif isinstance(ev, PlaceDeletedEvent) and ev.place_id in r.places:
                del r.places[ev.place_id]
                r.deleted_confirmed.append(ev.place_id)
        self._relax_events(out.events, frame.truth.stamp)
        if out.status.complete and not r.complete:
            r.complete, r.complete_tick = True, frame.tick
        self._prev_events, self._prev_dr = out.events, dr
        self._prev_scan, self._prev_fix = frame.sonar, fix
        if out.status.complete:
            return 0.0, 0.0
        return out.command.v_mps, out.command.omega_radps

    def _dead_reckon(self, compass: CompassReading, odometry: OdometryStep | None) -> DeadReckonedPose:
        t0 = time.perf_counter()
        poses: list[DeadReckonedPose] = []
        self._dr, out = dr_core.step(self._dr, compass)
        poses += out
        if odometry is not None:
            self._dr, out = dr_core.step(self._dr, odometry)
            poses += out
        self._timings["dead_reckoning"] += time.perf_counter() - t0
        for pose in poses:
            self._history.add(pose)
        if not poses:
            raise RuntimeError(f"dead reckoning gave no pose at {compass.stamp:.1f} s")
        return poses[-1]

    def _links(self, out: RecognizerOutput, tick: int) -> None:
        for lk in out.links:
            self.record.links.append(LinkRecord(tick, lk.from_id, lk.to_id, lk.d_m, lk.theta_rad, lk.steps,
                                                lk.mean_step_m, lk.traversals))
            if self.online is not None:
                t0 = time.perf_counter()
                msg = LinkMeasured(stamp=tick * self.params.sim.dt_s, seq=len(self.record.links),
                                   from_id=lk.from_id, to_id=lk.to_id, d_m=lk.d_m, theta_rad=lk.theta_rad,
                                   steps=lk.steps, mean_step_m=lk.mean_step_m, traversals=lk.traversals)
                self._apply(self.online.on_link_measured(msg).update)
                self._timings["relaxer"] += time.perf_counter() - t0

    def _relax_events(self, events: tuple, stamp: float) -> None:
        """The explorer's map events of this step, to the relaxer together (as the relaxer node applies
        the events one velocity command names)."""
        if self.online is None:
            return
        t0 = time.perf_counter()
        batch = []
        for i, ev in enumerate(events):
            if isinstance(ev, PlaceConfirmedEvent):
                batch.append(PlaceConfirmed(stamp=stamp, seq=i, place_id=ev.place_id, x_m=ev.x_m, y_m=ev.y_m))
            elif isinstance(ev, PlaceDeletedEvent):
                batch.append(PlaceDeleted(stamp=stamp, seq=i, place_id=ev.place_id, reason=ev.reason))
            elif isinstance(ev, LinkDeletedEvent):
                batch.append(LinkDeleted(stamp=stamp, seq=i, from_id=ev.from_id, to_id=ev.to_id, reason=ev.reason))
        if batch:
            self._apply(self.online.on_explorer_events(batch, stamp).update)
        self._timings["relaxer"] += time.perf_counter() - t0

    def _apply(self, update) -> None:
        if update is None or not update.changed:
            return
        centres = {p.place_id: (p.x_m, p.y_m) for p in update.changed}
        self.explorer.move_places(centres)
        self.recognizer.move_places(centres)


def run_world(world: str | World, params: InProcessParams = InProcessParams()) -> RunRecord:
    """Explore ``world`` (a name, a file or a :class:`sim.world.World`) in process; return the record."""
    w = world if isinstance(world, World) else load_world(world)
    return InProcessRun(w, params).run()


def main(argv: list[str] | None = None) -> int:
    from services.launch.place_metrics import measure

    parser = argparse.ArgumentParser(prog="python -m services.launch.inprocess",
                                     description="Explore a world in process and print the place measures.")
    parser.add_argument("--world", default="orebro-office", help="built-in world name or world file")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulator")
    parser.add_argument("--max-sim-time", type=float, default=3600.0, metavar="S", help="simulated time limit")
    parser.add_argument("--no-relax", action="store_true", help="do not feed relaxed coordinates back")
    args = parser.parse_args(argv)
    world = load_world(args.world)
    rec = run_world(world, InProcessParams(seed=args.seed, max_sim_time_s=args.max_sim_time,
                                           relax=not args.no_relax))
    m = measure(rec, world)
    json.dump({k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in m.items()},
              sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
