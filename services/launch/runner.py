"""The body of ``relaxmap run``: hub session, supervisor, progress, end of the run, outputs."""

from __future__ import annotations

import argparse
import json
import logging
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import zenoh
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from messages import topics
from services.launch.graph import GraphError, load_graph
from services.launch.monitor import RunMonitor
from services.launch.resume import (
    RUN_FORMAT,
    ResumeError,
    RunRecord,
    read_run_record,
    recording_name,
    write_run_record,
)
from services.launch.run_cli import DEFAULT_OUT, DEFAULT_WORLD, RESUME_START_TIMEOUT_S, START_TIMEOUT_S
from services.launch.supervisor import Supervisor
from services.runtime import AliveWatcher, QueryFailed, deploy_file, loopback_config, shutdown_event
from services.runtime.procs import free_port

log = logging.getLogger("relaxmap.run")


class RunError(RuntimeError):
    """The run could not start or could not go on; the message says why."""


def resolve_world(world: str) -> str:
    """A built-in world's name, or the absolute path of a world file."""
    from sim.world import WorldError, builtin_worlds, load_world

    if world in builtin_worlds():
        return world
    path = Path(world)
    if not path.is_file():
        raise RunError(f"world {world!r} is neither a built-in world ({', '.join(builtin_worlds())}) nor a file")
    try:
        load_world(path)  # a bad world file is reported here, before any process starts
    except WorldError as e:
        raise RunError(str(e)) from e
    return str(path.resolve())


@dataclass(frozen=True)
class RunPlan:
    """What this run is: where it writes, its world and seed, and the saved run it continues (if any)."""

    out: Path
    world: str  # as given (or as the saved run gave it)
    world_ref: str  # built-in name or absolute file path
    seed: int
    saved: RunRecord | None  # the run continued, None for a new one

    @property
    def part(self) -> int:
        return 1 if self.saved is None else self.saved.parts + 1


def plan_run(args: argparse.Namespace) -> RunPlan:
    """Check the command line against the saved run (with ``--resume``); ``RunError`` says what is wrong."""
    if args.resume is None:
        world = args.world or DEFAULT_WORLD
        out = Path(args.out or DEFAULT_OUT).resolve()
        return RunPlan(out=out, world=world, world_ref=resolve_world(world),
                       seed=0 if args.seed is None else args.seed, saved=None)
    out = Path(args.resume).resolve()
    if args.out is not None and Path(args.out).resolve() != out:
        raise RunError(f"--out {args.out} and --resume {args.resume} differ: a continued run writes into the "
                       "directory of the run it continues")
    try:
        saved = read_run_record(out)
    except ResumeError as e:
        raise RunError(f"cannot resume: {e}") from e
    if args.world is not None and resolve_world(args.world) != saved.world_ref:
        raise RunError(f"cannot resume: --world {args.world} contradicts the saved run's world {saved.world!r} "
                       "(leave --world out to continue it)")
    if args.seed is not None and args.seed != saved.seed:
        raise RunError(f"cannot resume: --seed {args.seed} contradicts the saved run's seed {saved.seed} "
                       "(leave --seed out to continue it)")
    if args.max_sim_time <= saved.sim_time_s:
        raise RunError(f"cannot resume: the saved run is at {saved.sim_time_s:.1f} simulated seconds already; "
                       f"--max-sim-time ({args.max_sim_time:g}) must go beyond it")
    world_ref = saved.world_ref
    if world_ref not in builtin_world_names() and not Path(world_ref).is_file():
        raise RunError(f"cannot resume: the saved run's world file {world_ref} is gone")
    return RunPlan(out=out, world=saved.world, world_ref=world_ref, seed=saved.seed, saved=saved)


def builtin_world_names() -> list[str]:
    from sim.world import builtin_worlds

    return list(builtin_worlds())


def _number(value: float) -> str:
    """A number as an argument: fixed-point, so that argparse takes a negative one as a value (it would
    take ``-1e-05`` for an option), to 1e-12."""
    return f"{float(value):.12f}"


def resume_values(plan: RunPlan) -> dict[str, list[str]]:
    """The ``{resume_<service>}`` arguments of the process graph: empty for a new run."""
    values: dict[str, list[str]] = {f"resume_{n}": [] for n in
                                    ("sensor_sim", "dead_reckoning", "place_recognizer", "explorer")}
    if plan.saved is None:
        return values
    m = plan.saved.monitor
    r = m.robot
    assert r is not None  # read_run_record refuses a run without it
    values["resume_sensor_sim"] = ["--start-pose", *map(_number, r.truth), "--start-tick", str(r.tick)]
    values["resume_dead_reckoning"] = ["--start-xy", *map(_number, r.dr_xy), "--start-raw", *map(_number, r.dr_raw),
                                       "--start-steps", str(r.steps), "--start-path-m", _number(r.path_length_m)]
    at: list[str] = []
    if r.fix is not None:  # where the recognizer last localised the robot (else the services ask the map)
        at = ["--resume-place", str(r.fix.place_id), "--resume-offset", *map(_number, r.fix.offset_xy),
              "--resume-dr", *map(_number, r.fix.dr_xy)]
    values["resume_place_recognizer"] = ["--resume", *at]
    values["resume_explorer"] = ["--resume", *at, "--first-place-id", str(m.max_place_id + 1)]
    return values


def run(args: argparse.Namespace) -> int:
    console = Console(stderr=True, log_path=False)
    plan = plan_run(args)
    out = plan.out
    out.mkdir(parents=True, exist_ok=True)
    try:
        graph = load_graph(args.graph or deploy_file("graph.json"))
    except GraphError as e:
        raise RunError(str(e)) from e
    world = plan.world_ref
    saved = plan.saved
    recording_id = saved.recording_id if saved is not None else str(uuid.uuid4())
    recordings = [*(saved.recordings if saved is not None else []), recording_name(plan.part)]
    if saved is not None:
        console.log(f"continuing the run in {out} (part {plan.part}) at {saved.sim_time_s:.1f} simulated s: "
                    f"world {saved.world}, seed {saved.seed}, {saved.places} places")
    robot = topics.DEFAULT_ROBOT
    port = args.port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    try:
        session = zenoh.open(loopback_config(listen=[endpoint]))
    except zenoh.ZError as e:
        raise RunError(f"cannot listen on {endpoint} ({e}); is another run using it? Try --port 0") from e
    stop = shutdown_event()
    values = {"world": world, "seed": str(plan.seed), "out": str(out), "max_sim_time": f"{args.max_sim_time:g}",
              "viewer": "--viewer" if args.viewer else "", "recording": str(out / recordings[-1]),
              "recording_id": recording_id, **resume_values(plan)}
    common = ["--connect", endpoint, "--listen", "tcp/127.0.0.1:0", "--robot", robot]
    supervisor = Supervisor(graph, common_args=common, values=values, log_dir=out / "logs", on_event=console.log)
    monitor = RunMonitor(session, robot)
    if saved is not None:
        monitor.restore(saved.monitor)
    watcher = AliveWatcher(session, robot, on_change=lambda name, up: None if up else log.info("%s left", name))
    wall0 = time.monotonic()
    try:
        supervisor.start()
        start_timeout_s = args.start_timeout_s
        if start_timeout_s is None:
            start_timeout_s = START_TIMEOUT_S if saved is None else RESUME_START_TIMEOUT_S
        deadline = time.monotonic() + start_timeout_s
        while not watcher.wait_alive(graph.names(), 0.2):
            supervisor.poll()
            if supervisor.failure:
                raise RunError(supervisor.failure)
            missing = ", ".join(sorted(set(graph.names()) - watcher.alive))
            if stop.is_set():
                raise RunError(f"stopped by signal before every service was alive (missing: {missing})")
            if time.monotonic() > deadline:
                raise RunError(f"not alive after {start_timeout_s:g} s: {missing} (logs in {out / 'logs'})")
        console.log(f"all {len(graph.services)} services alive on {endpoint}")
        reason = _watch(args, supervisor, monitor, stop, console)
        console.log(f"run ends: {reason}")
        # the robot stops first, so that the map, the robot's state and run.json tell of the same moment
        if "sensor_sim" in supervisor.services:
            supervisor.halt("sensor_sim")
        _settle(monitor)
        from services.launch.outputs import write_outputs

        wall_before = saved.wall_time_s if saved is not None else 0.0
        try:
            summary = write_outputs(session, robot, out, monitor, world=plan.world, seed=plan.seed,
                                    wall_time_s=wall_before + time.monotonic() - wall0, parts=plan.part,
                                    restarts={n: sv.restarts for n, sv in supervisor.services.items()})
        except QueryFailed as e:
            raise RunError(f"could not get the final map from the relaxer: {e} (logs in {out / 'logs'})") from e
        write_run_record(out, RunRecord(
            format=RUN_FORMAT, world=plan.world, world_ref=plan.world_ref, seed=plan.seed, parts=plan.part,
            sim_time_s=monitor.sim_time_s, wall_time_s=summary["wall_time_s"],
            exploration_complete=summary["exploration_complete"], places=summary["places"],
            recording_id=recording_id, recordings=recordings, monitor=monitor.saved_state()))
    finally:
        codes = supervisor.stop()
        watcher.close()
        monitor.close()
        session.close()
    bad = {k: v for k, v in codes.items() if v not in (0, -15)}
    if bad:
        console.log(f"services that did not stop cleanly: {bad}")
    console.print_json(json.dumps(summary))
    return 0


def _settle(monitor: RunMonitor, *, quiet_s: float = 0.5, max_s: float = 5.0) -> None:
    """Wait until no map update came for ``quiet_s`` (at most ``max_s``): the last events are in."""
    end = time.monotonic() + max_s
    last = monitor.progress()
    quiet_since = time.monotonic()
    while (now := time.monotonic()) < end and now - quiet_since < quiet_s:
        time.sleep(0.05)
        p = monitor.progress()
        if p["version"] != last["version"]:
            last, quiet_since = p, time.monotonic()


def _watch(args: argparse.Namespace, supervisor: Supervisor, monitor: RunMonitor, stop, console: Console) -> str:
    """Poll until exploration ends, the simulated-time limit, Ctrl-C, or a failure; returns why."""
    columns = [TextColumn("[bold]sim {task.completed:7.1f} s"), BarColumn(),
               TextColumn("places {task.fields[places]:>4}  links {task.fields[links]:>4}  "
                          "E {task.fields[energy]:9.3g}  {task.fields[rtf]:5.1f}x real time"),
               TimeElapsedColumn()]
    last_log = 0.0
    with Progress(*columns, console=console, disable=args.headless, transient=False) as bar:
        task = bar.add_task("run", total=args.max_sim_time, places=0, links=0, energy=float("nan"), rtf=0.0)
        while True:
            supervisor.poll()
            p = monitor.progress()
            bar.update(task, completed=min(p["sim_time_s"], args.max_sim_time), places=p["places"],
                       links=p["links"], energy=p["energy"], rtf=p["rtf"])
            if args.headless and time.monotonic() - last_log > 10:
                last_log = time.monotonic()
                console.log(f"sim {p['sim_time_s']:.1f} s, {p['places']} places, {p['links']} links, "
                            f"energy {p['energy']:.4g}, {p['rtf']:.1f}x real time")
            if supervisor.failure:
                raise RunError(supervisor.failure)
            if p["complete"]:
                return "exploration complete"
            if p["sim_time_s"] >= args.max_sim_time:
                return f"simulated-time limit ({args.max_sim_time:g} s)"
            if stop.is_set():
                return "stopped by signal"
            time.sleep(0.1)
