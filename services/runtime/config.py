"""Zenoh sessions from the JSON5 files in ``deploy/``, with the bus flags every process shares."""

from __future__ import annotations

import argparse
import json
from importlib import resources
from pathlib import Path

import zenoh

from messages.topics import DEFAULT_ROBOT

DEFAULT_CONFIG = "local-peer.json5"
HUB_PORT = 7447  # where `relaxmap run` listens and every local peer connects


def deploy_file(name: str) -> Path:
    """Path of a file shipped in ``deploy/``."""
    return Path(str(resources.files("deploy").joinpath(name)))


def load_config(
    path: str | Path | None = None,
    *,
    mode: str | None = None,
    connect: list[str] | None = None,
    listen: list[str] | None = None,
) -> zenoh.Config:
    """A zenoh config from ``path`` (default: deploy/local-peer.json5) with flag overrides.

    Raises
    ------
    ValueError
        When the file is missing or zenoh rejects it; the message names the file.
    """
    path = Path(path) if path else deploy_file(DEFAULT_CONFIG)
    if not path.is_file():
        raise ValueError(f"zenoh config {path}: no such file")
    try:
        conf = zenoh.Config.from_file(str(path))
        if mode:
            conf.insert_json5("mode", json.dumps(mode))
        if connect is not None:
            conf.insert_json5("connect/endpoints", json.dumps(connect))
        if listen is not None:
            conf.insert_json5("listen/endpoints", json.dumps(listen))
    except zenoh.ZError as e:
        raise ValueError(f"zenoh config {path}: {e}") from e
    return conf


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """The bus flags of every relaxmap process."""
    g = parser.add_argument_group("bus")
    g.add_argument("--config", help="zenoh JSON5 configuration (default: deploy/local-peer.json5)")
    g.add_argument("--mode", choices=("peer", "client", "router"), help="override the zenoh mode")
    g.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable; replaces the file's)")
    g.add_argument("--listen", action="append", metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable; replaces the file's)")
    g.add_argument("--robot", default=DEFAULT_ROBOT, help="robot name in every key expression")


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    return load_config(args.config, mode=args.mode, connect=args.connect, listen=args.listen)


def loopback_config(*, listen: list[str] | None = None, connect: list[str] | None = None) -> zenoh.Config:
    """A peer config on loopback with explicit endpoints (tests, benchmarks, the launcher's hub)."""
    return load_config(listen=listen or ["tcp/127.0.0.1:0"], connect=connect or [])
