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
from services.launch.graph import GraphError, load_graph
from services.launch.monitor import RunMonitor
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


def run(args: argparse.Namespace) -> int:
    console = Console(stderr=True, log_path=False)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    try:
        graph = load_graph(args.graph or deploy_file("graph.json"))
    except GraphError as e:
        raise RunError(str(e)) from e
    world = resolve_world(args.world)
    robot = topics.DEFAULT_ROBOT
    port = args.port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    try:
        session = zenoh.open(loopback_config(listen=[endpoint]))
    except zenoh.ZError as e:
        raise RunError(f"cannot listen on {endpoint} ({e}); is another run using it? Try --port 0") from e
    stop = shutdown_event()
    values = {"world": world, "seed": str(args.seed), "out": str(out), "max_sim_time": f"{args.max_sim_time:g}",
              "viewer": "--viewer" if args.viewer else ""}
    common = ["--connect", endpoint, "--listen", "tcp/127.0.0.1:0", "--robot", robot]
    supervisor = Supervisor(graph, common_args=common, values=values, log_dir=out / "logs", on_event=console.log)
    monitor = RunMonitor(session, robot)
    watcher = AliveWatcher(session, robot, on_change=lambda name, up: None if up else log.info("%s left", name))
    wall0 = time.monotonic()
    try:
        supervisor.start()
        deadline = time.monotonic() + args.start_timeout_s
        while not watcher.wait_alive(graph.names(), 0.2):
            supervisor.poll()
            if supervisor.failure:
                raise RunError(supervisor.failure)
            missing = ", ".join(sorted(set(graph.names()) - watcher.alive))
            if stop.is_set():
                raise RunError(f"stopped by signal before every service was alive (missing: {missing})")
            if time.monotonic() > deadline:
                raise RunError(f"not alive after {args.start_timeout_s:g} s: {missing} (logs in {out / 'logs'})")
        console.log(f"all {len(graph.services)} services alive on {endpoint}")
        reason = _watch(args, supervisor, monitor, stop, console)
        console.log(f"run ends: {reason}")
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
    bad = {k: v for k, v in codes.items() if v not in (0, -15)}
    if bad:
        console.log(f"services that did not stop cleanly: {bad}")
    console.print_json(json.dumps(summary))
    return 0


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
