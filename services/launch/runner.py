"""The body of ``relaxmap run``: hub session, supervisor, progress, end of the run, outputs."""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import zenoh
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from messages import topics
from messages.types import MapStats
from services.launch.graph import GraphError, ProcessGraph, load_graph
from services.launch.monitor import RunMonitor
from services.launch.resume import (
    RUN_FILE,
    RUN_FORMAT,
    STORE_FILE,
    ResumeError,
    RunRecord,
    read_run_record,
    recording_name,
    write_run_record,
)
from services.launch.run_cli import DEFAULT_OUT, DEFAULT_WORLD, RESUME_START_TIMEOUT_S, START_TIMEOUT_S
from services.launch.supervisor import Supervisor
from services.runtime import (
    AliveWatcher,
    QueryFailed,
    deploy_file,
    load_config,
    loopback_config,
    query,
    shutdown_event,
)
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
    from sim.world import builtin_worlds

    if world_ref not in builtin_worlds() and not Path(world_ref).is_file():
        raise RunError(f"cannot resume: the saved run's world file {world_ref} is gone")
    return RunPlan(out=out, world=saved.world, world_ref=world_ref, seed=saved.seed, saved=saved)


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


REMOTE_CONFIG = "client.json5"  # default zenoh config of a run that reaches the other hosts through a router


def open_bus(args: argparse.Namespace, robot: str) -> tuple[zenoh.Session, list[str], str]:
    """The launcher's session, the bus flags of the services it starts, and where the bus is (in words).

    Without ``--connect`` and ``--config`` the launcher is the loopback hub every local peer connects to;
    with them, the launcher and its services reach the other hosts through a router.
    """
    if not args.connect and not args.config:
        endpoint = f"tcp/127.0.0.1:{args.port or free_port()}"
        try:
            session = zenoh.open(loopback_config(listen=[endpoint]))
        except zenoh.ZError as e:
            raise RunError(f"cannot listen on {endpoint} ({e}); is another run using it? Try --port 0") from e
        return session, ["--connect", endpoint, "--listen", "tcp/127.0.0.1:0", "--robot", robot], endpoint
    path = Path(args.config).resolve() if args.config else deploy_file(REMOTE_CONFIG)
    try:
        conf = load_config(path, connect=args.connect or None)
    except ValueError as e:
        raise RunError(str(e)) from e
    where = ", ".join(args.connect) or f"the endpoints of {path}"
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as e:
        raise RunError(f"cannot reach {where} with {path} ({e}); is the router up?") from e
    flags = ["--config", str(path), *(a for e in args.connect for a in ("--connect", e)), "--robot", robot]
    return session, flags, where


def local_part(graph: ProcessGraph, *, only: list[str], skip: list[str], remote: bool) -> ProcessGraph:
    """The services of ``graph`` that this host starts (``--only`` / ``--skip``)."""
    if not (only or skip):
        return graph
    if not remote:
        raise RunError("--only and --skip split the graph across hosts: name the router with --connect "
                       "(or a zenoh config with --config)")
    unknown = sorted((set(only) | set(skip)) - set(graph.names()))
    if unknown:
        raise RunError(f"no service {', '.join(unknown)} in the graph ({', '.join(graph.names())})")
    keep = [s for s in graph.services if (s.name in only if only else s.name not in skip)]
    if not keep:
        raise RunError("--skip leaves no service to start on this host")
    return ProcessGraph(services=keep)


def run(args: argparse.Namespace) -> int:
    console = Console(stderr=True, log_path=False)
    plan = plan_run(args)
    out = plan.out
    held = [name for name in (RUN_FILE, STORE_FILE, "state") if (out / name).exists()]
    if plan.saved is None and held:
        raise RunError(f"{out} holds a run ({', '.join(held)}): continue it with --resume {out}, or give the "
                       "new run another --out")
    out.mkdir(parents=True, exist_ok=True)
    # the services' checkpoints are for restarts within one part: a continued run starts from run.json
    # and the relaxer's map (below), not from where a killed process of the last part was
    shutil.rmtree(out / "state", ignore_errors=True)
    try:
        graph = load_graph(args.graph or deploy_file("graph.json"))
    except GraphError as e:
        raise RunError(str(e)) from e
    local = local_part(graph, only=args.only, skip=args.skip, remote=bool(args.connect or args.config))
    world = plan.world_ref
    saved = plan.saved
    recording_id = saved.recording_id if saved is not None else str(uuid.uuid4())
    recordings = [*(saved.recordings if saved is not None else []), recording_name(plan.part)]
    if saved is not None:
        console.log(f"continuing the run in {out} (part {plan.part}) at {saved.sim_time_s:.1f} simulated s: "
                    f"world {saved.world}, seed {saved.seed}, {saved.places} places")
    robot = topics.DEFAULT_ROBOT
    session, common, where = open_bus(args, robot)
    stop = shutdown_event()
    values = {"world": world, "seed": str(plan.seed), "out": str(out), "max_sim_time": f"{args.max_sim_time:g}",
              "viewer": "--viewer" if args.viewer else "", "recording": str(out / recordings[-1]),
              "recording_id": recording_id, **resume_values(plan)}
    supervisor = Supervisor(local, common_args=common, values=values, log_dir=out / "logs", on_event=console.log)
    start_timeout_s = args.start_timeout_s
    if start_timeout_s is None:
        start_timeout_s = START_TIMEOUT_S if saved is None else RESUME_START_TIMEOUT_S
    watcher = AliveWatcher(session, robot, on_change=lambda name, up: None if up else log.info("%s left", name))
    if args.only:
        try:
            supervisor.start()
            _wait_alive(start_timeout_s, local.names(), local.names(), supervisor, watcher, stop, out)
            console.log(f"serving {', '.join(local.names())} on {where} (Ctrl-C stops)")
            console.log(f"serving ends: {_serve(supervisor, stop)}")
        finally:
            codes = supervisor.stop()
            watcher.close()
            session.close()
        _report_codes(codes, console)
        return 0
    monitor = RunMonitor(session, robot)
    if saved is not None:
        monitor.restore(saved.monitor)
    wall0 = time.monotonic()
    try:
        supervisor.start()
        _wait_alive(start_timeout_s, graph.names(), local.names(), supervisor, watcher, stop, out)
        console.log(f"all {len(graph.services)} services alive on {where}")
        reason = _watch(args, supervisor, monitor, stop, console)
        console.log(f"run ends: {reason}")
        # the robot stops first, so that the map, the robot's state and run.json tell of the same moment
        if "sensor_sim" in supervisor.services:
            supervisor.halt("sensor_sim")
        if not _wait_for_relaxer(session, robot, monitor, timeout_s=args.settle_timeout_s):
            console.log(f"the relaxer's map still lacks places or links after {args.settle_timeout_s:g} s: "
                        "written as it is (see links_lost)")
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
    _report_codes(codes, console)
    console.print_json(json.dumps(summary))
    return 0


def _report_codes(codes: dict[str, int], console: Console) -> None:
    bad = {k: v for k, v in codes.items() if v not in (0, -15)}
    if bad:
        console.log(f"services that did not stop cleanly: {bad}")


def _wait_alive(timeout_s: float, names: list[str], local: list[str], supervisor: Supervisor,
                watcher: AliveWatcher, stop, out: Path) -> None:
    """Wait until every one of ``names`` is alive (those not in ``local`` run on other hosts)."""
    deadline = time.monotonic() + timeout_s
    while not watcher.wait_alive(names, 0.2):
        supervisor.poll()
        if supervisor.failure:
            raise RunError(supervisor.failure)
        missing = sorted(set(names) - watcher.alive)
        here = [n for n in missing if n in local]
        text = "; ".join(part for part in (
            ", ".join(here) + (f" (logs in {out / 'logs'})" if here else ""),
            ", ".join(n for n in missing if n not in local) + " from other hosts (is their run up?)"
            if len(here) < len(missing) else "") if part)
        if stop.is_set():
            raise RunError(f"stopped by signal before every service was alive (missing: {text})")
        if time.monotonic() > deadline:
            raise RunError(f"not alive after {timeout_s:g} s: {text}")


def _wait_for_relaxer(session: zenoh.Session, robot: str, monitor: RunMonitor, *, timeout_s: float,
                      quiet_s: float = 1.0) -> bool:
    """Wait until the map events have stopped coming (``quiet_s``) and the relaxer holds every place and
    link they named: when the simulation stops, the last events are still on their way, and the relaxer
    takes them in one at a time. Then the written map is the same whatever the timing. False on timeout.

    Raises
    ------
    RunError
        When the relaxer never answered ``map/stats`` (gone, or not allowed to serve the map).
    """
    deadline = time.monotonic() + timeout_s
    answered = False
    while True:
        places, links = monitor.map_counts()
        try:
            stats = query(session, topics.map_stats(robot), type_=MapStats,
                          timeout_s=min(max(deadline - time.monotonic(), 1.0), 10.0))
            answered = True
        except QueryFailed as e:
            if time.monotonic() > deadline and not answered:
                raise RunError(f"the relaxer does not answer {topics.map_stats(robot)}: {e}") from e
            stats = None
        if stats is not None and stats.places >= places and stats.links >= links and monitor.quiet_s() >= quiet_s:
            return True
        if time.monotonic() > deadline and answered:
            return False
        time.sleep(0.1)


def _serve(supervisor: Supervisor, stop) -> str:
    """Keep this host's services running (restarts by policy) until Ctrl-C or until they all ended."""
    while not stop.is_set():
        supervisor.poll()
        if supervisor.failure:
            raise RunError(supervisor.failure)
        if not supervisor.pids() and all(sv.restart_at is None for sv in supervisor.services.values()):
            return "every service of this host ended"
        time.sleep(0.2)
    return "stopped by signal"


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
