"""``python -m services.recorder``: record the map, the robot and the relaxer's progress into a Rerun file.

Flags (besides the bus flags ``--config --mode --connect --listen --robot`` and ``-v``):

``--out DIR``
    write ``DIR/recording.rrd`` (default: the current directory); the directory is created.
``--rrd PATH``
    write the recording to ``PATH`` instead (excludes ``--out``).
``--viewer``
    also stream to a Rerun viewer spawned on ``--viewer-port`` (default 9876); the file is written
    either way, and a viewer that cannot start is only a warning.
``--recording-id ID``
    Rerun recording id (default: a fresh random one), so that several files can be merged.
``--duration-s S``
    stop after ``S`` wall seconds.
``--max-sim-time S``
    stop at the first message stamped later than ``S`` simulated seconds (it is not recorded).
``--params FILE``
    JSON object of ``RecorderParams`` fields (services/recorder/core.py); ``--param NAME=VALUE``
    (repeatable) overrides single fields after it.

SIGINT and SIGTERM stop the recorder; the recording is flushed and closed on every way out (also at the
end of ``--duration-s`` and on an exception), so ``rerun rrd verify`` accepts it. Exit codes: 0 after a
clean stop, 2 for bad flags, parameters or bus configuration.
"""

from __future__ import annotations

import argparse
import sys
import threading
from pathlib import Path

import msgspec
import zenoh

from services.recorder.core import RecorderParams
from services.recorder.node import run
from services.runtime import service_main

RECORDING_NAME = "recording.rrd"
DESCRIPTION = "Record the map, the robot and the relaxer's progress into a Rerun file (recording.rrd)."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    out = parser.add_mutually_exclusive_group()
    out.add_argument("--out", type=Path, default=None, metavar="DIR",
                     help=f"write DIR/{RECORDING_NAME} (default: the current directory)")
    out.add_argument("--rrd", type=Path, default=None, metavar="PATH", help="write the recording to PATH")
    parser.add_argument("--viewer", action="store_true", help="also stream to a spawned Rerun viewer")
    parser.add_argument("--viewer-port", type=int, default=9876, help="port of the spawned viewer (default 9876)")
    parser.add_argument("--recording-id", default=None, help="Rerun recording id (default: random)")
    parser.add_argument("--duration-s", type=float, default=None, help="stop after this many wall seconds")
    parser.add_argument("--max-sim-time", type=float, default=None, metavar="S",
                        help="stop at the first message stamped later than S simulated seconds")
    parser.add_argument("--params", type=Path, default=None, metavar="FILE",
                        help="JSON object of RecorderParams fields")
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                        help="override one RecorderParams field (repeatable)")


def params_from_args(args: argparse.Namespace) -> RecorderParams:
    """RecorderParams from ``--params`` and ``--param``; ValueError says what is wrong."""
    fields: dict[str, object] = {}
    if args.params is not None:
        try:
            loaded = msgspec.json.decode(args.params.read_bytes())
        except OSError as e:
            raise ValueError(f"{args.params}: {e.strerror}") from e
        except msgspec.DecodeError as e:
            raise ValueError(f"{args.params}: {e}") from e
        if not isinstance(loaded, dict):
            raise ValueError(f"{args.params}: expected a JSON object of RecorderParams fields")
        fields.update(loaded)
    for item in args.param:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ValueError(f"--param {item!r} is not of the form NAME=VALUE")
        fields[name] = value
    try:
        return msgspec.convert(fields, RecorderParams, strict=False)
    except msgspec.ValidationError as e:
        raise ValueError(f"recorder parameters: {e}") from e


def rrd_path_from_args(args: argparse.Namespace) -> Path:
    if args.rrd is not None:
        return args.rrd
    return (args.out if args.out is not None else Path.cwd()) / RECORDING_NAME


def _run(session: zenoh.Session, args: argparse.Namespace, stop: threading.Event) -> None:
    run(session, args.recorder_params, rrd_path=rrd_path_from_args(args), robot=args.robot, stop=stop,
        viewer=args.viewer, viewer_port=args.viewer_port, recording_id=args.recording_id,
        duration_s=args.duration_s, max_sim_time_s=args.max_sim_time)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(add_help=False)
    add_arguments(parser)
    known, _ = parser.parse_known_args(argv)
    try:
        params = params_from_args(known)
    except ValueError as e:
        print(f"recorder: {e}", file=sys.stderr)
        return 2

    def run_with_params(session: zenoh.Session, args: argparse.Namespace, stop: threading.Event) -> None:
        args.recorder_params = params
        _run(session, args, stop)

    return service_main("recorder", run_with_params, description=DESCRIPTION,
                        add_arguments=add_arguments, argv=argv)


if __name__ == "__main__":
    sys.exit(main())
