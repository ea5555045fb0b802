"""The body of ``relaxmap run``: hub session, supervisor, progress, end of the run, outputs."""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import zenoh
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from messages import topics
from messages.types import MapStats
from services.launch.graph import GraphError, ProcessGraph, load_graph
from services.launch.monitor import RunMonitor
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
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    try:
        graph = load_graph(args.graph or deploy_file("graph.json"))
    except GraphError as e:
        raise RunError(str(e)) from e
    local = local_part(graph, only=args.only, skip=args.skip, remote=bool(args.connect or args.config))
    world = resolve_world(args.world)
    robot = topics.DEFAULT_ROBOT
    session, common, where = open_bus(args, robot)
    stop = shutdown_event()
    values = {"world": world, "seed": str(args.seed), "out": str(out), "max_sim_time": f"{args.max_sim_time:g}",
              "viewer": "--viewer" if args.viewer else ""}
    supervisor = Supervisor(local, common_args=common, values=values, log_dir=out / "logs", on_event=console.log)
    watcher = AliveWatcher(session, robot, on_change=lambda name, up: None if up else log.info("%s left", name))
    if args.only:
        try:
            supervisor.start()
            _wait_alive(args, local.names(), local.names(), supervisor, watcher, stop, out)
            console.log(f"serving {', '.join(local.names())} on {where} (Ctrl-C stops)")
            console.log(f"serving ends: {_serve(supervisor, stop)}")
        finally:
            codes = supervisor.stop()
            watcher.close()
            session.close()
        _report_codes(codes, console)
        return 0
    monitor = RunMonitor(session, robot)
    wall0 = time.monotonic()
    try:
        supervisor.start()
        _wait_alive(args, graph.names(), local.names(), supervisor, watcher, stop, out)
        console.log(f"all {len(graph.services)} services alive on {where}")
        reason = _watch(args, supervisor, monitor, stop, console)
        console.log(f"run ends: {reason}")
        if not _wait_for_relaxer(session, robot, monitor, timeout_s=args.settle_timeout_s):
            console.log(f"the relaxer's map still lacks places or links after {args.settle_timeout_s:g} s: "
                        "written as it is (see links_lost)")
        from services.launch.outputs import write_outputs

        try:
            summary = write_outputs(session, robot, out, monitor, world=args.world, seed=args.seed,
                                    wall_time_s=time.monotonic() - wall0,
                                    restarts={n: sv.restarts for n, sv in supervisor.services.items()})
        except QueryFailed as e:
            raise RunError(f"could not get the final map from the relaxer: {e} (logs in {out / 'logs'})") from e
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


def _wait_alive(args: argparse.Namespace, names: list[str], local: list[str], supervisor: Supervisor,
                watcher: AliveWatcher, stop, out: Path) -> None:
    """Wait until every one of ``names`` is alive (those not in ``local`` run on other hosts)."""
    deadline = time.monotonic() + args.start_timeout_s
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
            raise RunError(f"not alive after {args.start_timeout_s:g} s: {text}")


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
