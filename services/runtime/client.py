"""The asking side of the bus: typed queries and liveliness of services."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, TypeVar

import msgspec
import zenoh

from messages import topics
from messages.codec import DecodeError, codec
from messages.types import ErrorReply
from services.runtime.errors import QueryFailed

T = TypeVar("T")


def _error_text(err: zenoh.ReplyError) -> str:
    data = err.payload.to_bytes()
    try:
        return msgspec.json.decode(data, type=ErrorReply).error
    except DecodeError:
        return data.decode("utf-8", "replace")


def query(session: zenoh.Session, key: str, params: str | dict[str, Any] | None = None, *,
          type_: type[T] | None = None, fmt: str = "msgpack", timeout_s: float = 5.0) -> T | Any:
    """Ask ``key`` and return the first reply, decoded as ``type_`` (or as plain data).

    Raises
    ------
    QueryFailed
        On an error reply (with its text), an undecodable reply, or no reply within ``timeout_s``.
    """
    if isinstance(params, dict):
        params = ";".join(f"{k}={v}" for k, v in params.items())
    sel = key if not params else f"{key}?{params}"
    if fmt != "msgpack":
        sel += (";" if "?" in sel else "?") + f"format={fmt}"
    # A session that has just opened may not know the queryable yet (declarations take a moment to
    # propagate): then the query ends at once with no reply, and it is asked again until the timeout.
    deadline = time.monotonic() + timeout_s
    while True:
        # No consolidation: the first reply is handed over at once, not after the query's end.
        left = max(deadline - time.monotonic(), 0.001)
        for reply in session.get(sel, timeout=left, consolidation=zenoh.ConsolidationMode.NONE):
            if reply.err is not None:
                raise QueryFailed(f"{key}: {_error_text(reply.err)}")
            data = reply.ok.payload.to_bytes()
            try:
                if type_ is not None:
                    return codec(type_).decode(data) if fmt == "msgpack" else codec(type_).decode_json(data)
                return msgspec.msgpack.decode(data) if fmt == "msgpack" else msgspec.json.decode(data)
            except DecodeError as e:
                raise QueryFailed(f"{key}: undecodable reply: {e}") from e
        if time.monotonic() + 0.05 >= deadline:
            break
        time.sleep(0.05)
    raise QueryFailed(f"{key}: no reply within {timeout_s:g} s (is the service running?)")


def alive_services(session: zenoh.Session, robot: str = topics.DEFAULT_ROBOT, *,
                   timeout_s: float = 1.0) -> set[str]:
    """Names of the services whose liveliness token is on the bus now."""
    names = set()
    for reply in session.liveliness().get(topics.alive(robot), timeout=timeout_s):
        if reply.ok is not None:
            names.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
    return names


class AliveWatcher:
    """Tracks which services are alive, from liveliness tokens (history included).

    zenoh reports a token's end within milliseconds when its process is killed (the connection
    closes) and after the lease when a process hangs.
    """

    def __init__(self, session: zenoh.Session, robot: str = topics.DEFAULT_ROBOT,
                 on_change: Callable[[str, bool], None] | None = None) -> None:
        self._alive: set[str] = set()
        self._cond = threading.Condition()
        self._on_change = on_change
        self._sub = session.liveliness().declare_subscriber(topics.alive(robot), self._on_sample, history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        up = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            (self._alive.add if up else self._alive.discard)(name)
            self._cond.notify_all()
        if self._on_change is not None:
            self._on_change(name, up)

    @property
    def alive(self) -> set[str]:
        with self._cond:
            return set(self._alive)

    def wait(self, predicate: Callable[[set[str]], bool], timeout_s: float) -> bool:
        """Wait until ``predicate(alive set)`` holds; False on timeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not predicate(self._alive):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def wait_alive(self, services: Iterable[str], timeout_s: float) -> bool:
        wanted = set(services)
        return self.wait(lambda alive: wanted <= alive, timeout_s)

    def wait_gone(self, service: str, timeout_s: float) -> bool:
        return self.wait(lambda alive: service not in alive, timeout_s)

    def close(self) -> None:
        self._sub.undeclare()
