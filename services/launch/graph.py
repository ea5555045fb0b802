"""The process graph of ``relaxmap run``: which services, their inputs, outputs and restart policy."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import msgspec

from messages import topics


class RestartPolicy(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """What the supervisor does when a service process exits on its own."""

    policy: str = "on-failure"  # "never", "on-failure" (non-zero exit or signal) or "always"
    max_restarts: int = 5  # restarts allowed over the whole run before the run fails
    backoff_s: float = 0.5  # wait before the first restart; doubles after each one
    backoff_max_s: float = 8.0  # ceiling of the doubling wait


class ServiceSpec(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One service of the graph."""

    name: str  # liveliness name, relaxmap/<robot>/alive/<name>
    module: str  # run as `python -m <module>`
    inputs: list[str] = []  # names of messages.topics functions the service subscribes to
    outputs: list[str] = []  # names of messages.topics functions it publishes or serves
    args: list[str] = []  # extra arguments; {world} {seed} {out} {max_sim_time} {viewer} {recording} and the
    # {resume_<service>} lists expand (relaxmap run's values)
    restart: RestartPolicy = RestartPolicy()
    required: bool = True  # the run fails when a required service dies and cannot be restarted


class ProcessGraph(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    services: list[ServiceSpec]

    def names(self) -> list[str]:
        return [s.name for s in self.services]


class GraphError(ValueError):
    """The process graph file is malformed or inconsistent."""


def load_graph(path: str | Path) -> ProcessGraph:
    """Read and check a process graph file (JSON).

    Raises
    ------
    GraphError
        Naming the file and what is wrong: bad JSON, unknown fields, an input nobody produces, a
        topic that ``messages/topics.py`` does not define, a duplicate service, a bad policy.
    """
    path = Path(path)
    try:
        graph = msgspec.json.decode(path.read_bytes(), type=ProcessGraph)
    except OSError as e:
        raise GraphError(f"{path}: {e.strerror}") from e
    except msgspec.DecodeError as e:
        raise GraphError(f"{path}: {e}") from e
    problems = check_graph(graph)
    if problems:
        raise GraphError(f"{path}: " + "; ".join(problems))
    return graph


def check_graph(graph: ProcessGraph) -> list[str]:
    """Every problem of the graph, in words (empty when it is sound)."""
    known = set(topics.all_topics())
    problems = []
    names = graph.names()
    for name in sorted({n for n in names if names.count(n) > 1}):
        problems.append(f"service {name!r} appears twice")
    produced = {o for s in graph.services for o in s.outputs}
    for s in graph.services:
        for t in (*s.inputs, *s.outputs):
            if t not in known:
                problems.append(f"{s.name}: {t!r} is not a key expression of messages/topics.py")
        for t in s.inputs:
            if t in known and t not in produced:
                problems.append(f"{s.name}: input {t!r} has no producer")
        if s.restart.policy not in ("never", "on-failure", "always"):
            problems.append(f"{s.name}: restart policy {s.restart.policy!r} (never, on-failure, always)")
        if s.restart.max_restarts < 0 or s.restart.backoff_s < 0:
            problems.append(f"{s.name}: negative restart limits")
    return problems


def expand_args(spec: ServiceSpec, values: Mapping[str, str | Sequence[str]]) -> list[str]:
    """The service's extra arguments with their ``{name}`` fields filled in (empty results dropped).

    An argument that is one field alone, whose value is a list, becomes the list's items (none when
    it is empty): ``"{resume}"`` with ``["--resume", "--first-place-id", "7"]``.
    """
    text = {k: v for k, v in values.items() if isinstance(v, str)}
    out: list[str] = []
    for a in spec.args:
        alone = re.fullmatch(r"\{(\w+)\}", a)
        if alone and alone.group(1) in values and not isinstance(values[alone.group(1)], str):
            out += [str(v) for v in values[alone.group(1)]]
            continue
        try:
            arg = a.format(**text)
        except KeyError as e:
            raise GraphError(f"{spec.name}: unknown field {e} in args") from None
        if arg:
            out.append(arg)
    return out
