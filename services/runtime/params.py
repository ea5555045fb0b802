"""Validated query parameters: typed getters whose errors say what is wrong."""

from __future__ import annotations

import math
from collections.abc import Iterable

import zenoh

from services.runtime.errors import QueryError

MAX_PARAM_CHARS = 256  # longer values are refused, never parsed


def parse_parameters(text: str) -> list[tuple[str, str]]:
    """``k=v`` pairs separated by ``;`` (zenoh's own separator) or ``&`` (as in a URL).

    zenoh.Parameters splits on ``;`` only; the query API of relaxmap documents ``from=1&to=2``, so
    both are accepted here.
    """
    items = []
    for part in text.replace("&", ";").split(";"):
        if part:
            name, _, value = part.partition("=")
            items.append((name, value))
    return items


class QueryParams:
    """The parameters of one query, checked against the names a queryable accepts."""

    def __init__(self, params: zenoh.Parameters | str | dict[str, str], allowed: Iterable[str]) -> None:
        if isinstance(params, dict):
            items = [(str(k), str(v)) for k, v in params.items()]
        else:
            items = parse_parameters(str(params))
        allowed = frozenset(allowed)
        self._values: dict[str, str] = {}
        for name, value in items:
            if name not in allowed:
                accepted = ", ".join(sorted(allowed)) or "none"
                raise QueryError(f"unknown parameter {name[:40]!r} (accepted: {accepted})")
            if name in self._values:
                raise QueryError(f"parameter {name!r} given twice")
            if len(value) > MAX_PARAM_CHARS:
                raise QueryError(f"parameter {name!r} is {len(value)} characters long (at most {MAX_PARAM_CHARS})")
            self._values[name] = value

    def __contains__(self, name: str) -> bool:
        return name in self._values

    def str(self, name: str, default: str | None = None, *, choices: Iterable[str] | None = None) -> str:
        value = self._values.get(name, default)
        if value is None:
            raise QueryError(f"missing parameter {name!r}")
        if choices is not None and value not in (choices := tuple(choices)):
            raise QueryError(f"parameter {name!r} must be one of {', '.join(choices)}, got {value[:40]!r}")
        return value

    def int(self, name: str, default: int | None = None, *, min_value: int | None = None) -> int:
        raw = self._values.get(name)
        if raw is None:
            if default is None:
                raise QueryError(f"missing parameter {name!r}")
            return default
        try:
            value = int(raw)
        except ValueError:
            raise QueryError(f"parameter {name!r} must be an integer, got {raw[:40]!r}") from None
        if min_value is not None and value < min_value:
            raise QueryError(f"parameter {name!r} must be at least {min_value}, got {value}")
        return value

    def float(self, name: str, default: float | None = None, *, min_value: float | None = None,
              max_value: float | None = None) -> float:
        raw = self._values.get(name)
        if raw is None:
            if default is None:
                raise QueryError(f"missing parameter {name!r}")
            return default
        try:
            value = float(raw)
        except ValueError:
            raise QueryError(f"parameter {name!r} must be a number, got {raw[:40]!r}") from None
        if not math.isfinite(value):
            raise QueryError(f"parameter {name!r} must be finite, got {raw[:40]!r}")
        if min_value is not None and value < min_value:
            raise QueryError(f"parameter {name!r} must be at least {min_value}, got {value}")
        if max_value is not None and value > max_value:
            raise QueryError(f"parameter {name!r} must be at most {max_value}, got {value}")
        return value
