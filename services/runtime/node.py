"""What every service node shares: typed pub/sub and queryables, liveliness, health, one event loop."""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, Generic, TypeVar

import msgspec
import zenoh
import zenoh.ext as ze

from messages import topics
from messages.codec import DecodeError, codec, encode
from messages.types import ErrorReply, Health
from services.runtime.errors import QueryError
from services.runtime.params import QueryParams

T = TypeVar("T")
log = logging.getLogger("relaxmap.runtime")

_MSGPACK = zenoh.Encoding("application/msgpack")
HEARTBEAT_S = 0.5  # period of the miss-detection heartbeat of publishers with history
QueryHandler = Callable[[str, QueryParams], Any]


class TypedPublisher(Generic[T]):
    """Publishes messages of one type on one key, msgpack-encoded, counting them."""

    def __init__(self, node: Node, key: str, type_: type[T], *, lossless: bool = True, history: int = 0) -> None:
        self.key = key
        self.type = type_
        self._node = node
        # lossless: zenoh's congestion control "block" (a slow subscriber slows the publisher down
        # rather than losing messages); otherwise "drop" (for streams where only the latest matters)
        cc = zenoh.CongestionControl.BLOCK if lossless else zenoh.CongestionControl.DROP
        if history > 0:
            # zenoh's advanced publisher: keeps the last ``history`` samples for subscribers that join
            # late or restart, announces itself, and sends heartbeats so subscribers detect misses
            self._pub = ze.declare_advanced_publisher(
                node.session, key, encoding=_MSGPACK, congestion_control=cc,
                cache=ze.CacheConfig(history, replies_config=ze.RepliesConfig(congestion_control=cc)),
                sample_miss_detection=ze.MissDetectionConfig(heartbeat=HEARTBEAT_S, sporadic_heartbeat=None),
                publisher_detection=True)
        else:
            self._pub = node.session.declare_publisher(key, encoding=_MSGPACK, congestion_control=cc)

    def put(self, msg: T) -> None:
        if not isinstance(msg, self.type):
            raise TypeError(f"{self.key} carries {self.type.__name__}, not {type(msg).__name__}")
        self._pub.put(codec(self.type).encode(msg))
        self._node._count("messages_out")

    @property
    def matching_status(self) -> bool:
        """True when at least one subscriber matches this key."""
        return self._pub.matching_status if hasattr(self._pub, "matching_status") else True

    def undeclare(self) -> None:
        self._pub.undeclare()


class Node:
    """A service's presence on the bus.

    Subscribers decode in zenoh's threads (a message that fails to decode is counted and logged,
    never raised) and hand the decoded message to one event queue; queries go through the same queue.
    ``spin`` runs the callbacks one at a time in the caller's thread, so a service's state is only
    ever touched by one thread. The health queryable is declared at construction; the liveliness
    token when ``spin`` starts (or at ``announce``), once every subscriber and queryable is declared,
    so that "alive" means "serving".
    """

    def __init__(self, session: zenoh.Session, service: str, *, robot: str = topics.DEFAULT_ROBOT,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.session = session
        self.service = service
        self.robot = robot
        self._clock = clock
        self._started = clock()
        self._lock = threading.Lock()
        self._counts = {"messages_in": 0, "messages_out": 0, "decode_errors": 0, "query_errors": 0,
                        "handler_errors": 0}
        self.detail: dict[str, float] = {}  # service-specific counters, shown in health
        # queue.Queue, not SimpleQueue: on Python 3.11 a signal that interrupts SimpleQueue.get(timeout)
        # near the end of its timeout leaves it waiting with a negative timeout, i.e. for ever, so a
        # SIGTERM could leave a service blocked in spin_once once its inputs had stopped
        self._events: queue.Queue[tuple[Callable[..., None], tuple]] = queue.Queue()
        self._entities: list[Any] = []
        self._entities.append(session.declare_queryable(topics.health(robot, service), self._on_health_query))
        self._token: zenoh.LivelinessToken | None = None

    # -- counters ---------------------------------------------------------------------------------
    def _count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._counts[name] += n

    def count(self, name: str) -> int:
        with self._lock:
            return self._counts[name]

    def health(self) -> Health:
        with self._lock:
            counts = dict(self._counts)
            detail = {k: float(v) for k, v in self.detail.items()}
        detail["handler_errors"] = float(counts["handler_errors"])
        detail["queued"] = float(self._events.qsize())  # received, not handled yet: a service that lags
        return Health(stamp=time.time(), seq=0, service=self.service, pid=os.getpid(),
                      uptime_s=self._clock() - self._started, messages_in=counts["messages_in"],
                      messages_out=counts["messages_out"], decode_errors=counts["decode_errors"],
                      query_errors=counts["query_errors"], detail=detail)

    def _on_health_query(self, query: zenoh.Query) -> None:
        try:
            fmt = QueryParams(query.parameters, ("format",)).str("format", "msgpack", choices=("msgpack", "json"))
            query.reply(query.key_expr, encode(self.health(), fmt))
        except QueryError as e:
            self._reply_error(query, str(e))

    # -- declarations -----------------------------------------------------------------------------
    def publisher(self, key: str, type_: type[T], *, lossless: bool = True, history: int = 0) -> TypedPublisher[T]:
        """A typed publisher on ``key``.

        ``lossless=False`` lets zenoh drop under congestion. ``history=N`` keeps the last N messages
        for subscribers declared with ``history=True`` that join late or restart (zenoh's advanced
        publisher, with miss detection).
        """
        pub = TypedPublisher(self, key, type_, lossless=lossless, history=history)
        self._entities.append(pub)
        return pub

    def subscribe(self, key: str, type_: type[T], callback: Callable[[T], None], *, history: bool = False) -> None:
        """Call ``callback(msg)`` from ``spin`` for every message on ``key`` that decodes as ``type_``.

        With ``history``, the subscriber is zenoh's advanced subscriber: it first receives what the
        publishers declared with ``history`` still hold (also from publishers that appear later), and
        recovers missed messages from their heartbeats; misses it cannot recover are counted in
        ``detail["missed"]``. The callback must then accept a message it has seen before.
        """
        dec = codec(type_)

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                msg = dec.decode(sample.payload.to_bytes())
            except DecodeError as e:
                self._count("decode_errors")
                log.warning("%s: undecodable message on %s (%d bytes): %s", self.service, sample.key_expr,
                            len(sample.payload), e)
                return
            self._count("messages_in")
            self._events.put((callback, (msg,)))

        if not history:
            self._entities.append(self.session.declare_subscriber(key, on_sample))
            return
        sub = ze.declare_advanced_subscriber(
            self.session, key, on_sample, history=ze.HistoryConfig(detect_late_publishers=True),
            recovery=ze.RecoveryConfig(heartbeat=True, periodic_queries=None), subscriber_detection=True)

        def on_miss(miss: ze.Miss) -> None:
            with self._lock:
                self.detail["missed"] = self.detail.get("missed", 0) + miss.nb
            log.warning("%s: %d messages on %s missed for good", self.service, miss.nb, key)

        self._entities.append(sub.sample_miss_listener(on_miss))
        self._entities.append(sub)

    def queryable(self, key: str, handler: QueryHandler, *, params: Iterable[str] = ()) -> None:
        """Serve ``key`` from ``spin``: ``handler(key, params)`` returns a msgspec-serialisable reply.

        The reply is msgpack unless the query says ``format=json``. A ``QueryError`` raised by the
        handler (or by parameter validation) becomes an error reply that says what is wrong.
        """
        allowed = (*params, "format")

        def on_query(query: zenoh.Query) -> None:
            self._events.put((self._serve_query, (query, handler, allowed)))

        self._entities.append(self.session.declare_queryable(key, on_query))

    def _serve_query(self, query: zenoh.Query, handler: QueryHandler, allowed: tuple[str, ...]) -> None:
        key = str(query.key_expr)
        try:
            params = QueryParams(query.parameters, allowed)
            fmt = params.str("format", "msgpack", choices=("msgpack", "json"))
            reply = handler(key, params)
            query.reply(query.key_expr, encode(reply, fmt))
        except QueryError as e:
            self._reply_error(query, str(e))
        except Exception as e:  # a handler bug must not kill the service; the client learns of it
            log.exception("%s: query %s failed", self.service, key)
            self._reply_error(query, f"internal error: {type(e).__name__}: {e}")

    def _reply_error(self, query: zenoh.Query, error: str) -> None:
        self._count("query_errors")
        log.info("%s: error reply to %s: %s", self.service, query.selector, error)
        query.reply_err(msgspec.json.encode(ErrorReply(error=error, key=str(query.key_expr))))

    # -- the event loop ---------------------------------------------------------------------------
    def announce(self) -> None:
        """Declare the liveliness token ``relaxmap/<robot>/alive/<service>`` (once)."""
        if self._token is None:
            self._token = self.session.liveliness().declare_token(topics.alive(self.robot, self.service))

    def call_soon(self, fn: Callable[..., None], *args: Any) -> None:
        """Run ``fn(*args)`` from ``spin`` (thread-safe)."""
        self._events.put((fn, args))

    def spin_once(self, timeout_s: float | None) -> bool:
        """Run at most one queued callback, waiting up to ``timeout_s``; False if none came."""
        try:
            fn, args = self._events.get(timeout=timeout_s)
        except queue.Empty:
            return False
        try:
            fn(*args)
        except Exception:  # one bad message must not stop the service
            self._count("handler_errors")
            log.exception("%s: callback %s failed", self.service, getattr(fn, "__name__", fn))
        return True

    def spin(self, stop: threading.Event, *, tick: Callable[[], None] | None = None,
             period_s: float = 0.1, drain_s: float = 1.0) -> None:
        """Run callbacks until ``stop`` is set; ``tick()`` runs at least every ``period_s``.

        After the stop, what is already queued is still handled, for up to ``drain_s``: a message
        that arrived is not thrown away because a signal came just after it.
        """
        self.announce()
        next_tick = time.monotonic() + period_s
        while not stop.is_set():
            self.spin_once(min(max(next_tick - time.monotonic(), 0.0), period_s))
            if time.monotonic() < next_tick:
                continue
            next_tick = time.monotonic() + period_s
            if tick is not None:
                try:
                    tick()
                except Exception:
                    self._count("handler_errors")
                    log.exception("%s: tick failed", self.service)
        drain_end = time.monotonic() + drain_s
        while time.monotonic() < drain_end and self.spin_once(0.0):
            pass

    def close(self) -> None:
        """Undeclare everything (the liveliness token last, so others see the service leave)."""
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        self._entities.clear()
        if self._token is not None:
            try:
                self._token.undeclare()
            except zenoh.ZError:
                pass
            self._token = None

    def __enter__(self) -> Node:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
