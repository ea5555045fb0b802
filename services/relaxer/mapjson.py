"""Reading and writing relaxmap's compass-mode ``map.json`` (architecture.md)."""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.relaxer.compass import CompassNoise
from services.common.files import atomic_write
from services.relaxer.graph import GraphError, MapGraph

__all__ = ["MapFile", "MapFileError", "format_map_json", "parse_map_json", "read_map_json", "write_map_json"]


class MapFileError(ValueError):
    """A malformed ``map.json``; ``line`` is the 1-based line of the offending item (0 if none)."""

    def __init__(self, source: str, line: int, problem: str) -> None:
        self.source, self.line, self.problem = source, line, problem
        where = f"{source}:{line}" if line else source
        super().__init__(f"{where}: {problem}")


@dataclass(frozen=True)
class MapFile:
    """A compass-mode map: graph, coordinates, noise parameters and the pinned place."""

    graph: MapGraph
    xy: np.ndarray  # (N, 2) place coordinates by dense index (m)
    noise: CompassNoise
    pinned_id: int


_PLACE = {"id", "x", "y"}
_LINK_REQ = {"from", "to", "d", "theta"}
_LINK_OPT = {"steps", "mean_step", "variance"}
_TOP = {"places", "links", "noise", "pinned"}


def _array_lines(text: str, key: str) -> list[int]:
    """Line numbers of the elements of the top-level array ``key`` (best effort)."""
    m = re.search(r'"%s"\s*:\s*\[' % re.escape(key), text)
    if not m:
        return []
    dec = json.JSONDecoder()
    idx = m.end()
    out = []
    n = len(text)
    while idx < n:
        while idx < n and text[idx] in " \t\r\n,":
            idx += 1
        if idx >= n or text[idx] == "]":
            break
        out.append(text.count("\n", 0, idx) + 1)
        try:
            _, idx = dec.raw_decode(text, idx)
        except json.JSONDecodeError:
            break
    return out


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def parse_map_json(text: str, *, source: str = "<map.json>") -> MapFile:
    """Parse ``map.json`` text; see :func:`read_map_json`."""
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise MapFileError(source, exc.lineno, f"not valid JSON: {exc.msg} (column {exc.colno})") from None
    if not isinstance(doc, dict):
        raise MapFileError(source, 1, "the top level must be an object with 'places' and 'links'")
    extra = set(doc) - _TOP
    if extra:
        raise MapFileError(source, 0, f"unknown field(s) {sorted(extra)} at the top level")
    for key in ("places", "links"):
        if not isinstance(doc.get(key), list):
            raise MapFileError(source, 0, f"'{key}' must be a list")
    pl_lines = _array_lines(text, "places")
    ln_lines = _array_lines(text, "links")

    def line(lines: list[int], k: int) -> int:
        return lines[k] if k < len(lines) else 0

    ids, xy = [], []
    first_line: dict[int, int] = {}
    for k, p in enumerate(doc["places"]):
        where = line(pl_lines, k)
        if not isinstance(p, dict):
            raise MapFileError(source, where, f"place {k} is not an object")
        missing, extra = _PLACE - set(p), set(p) - _PLACE
        if missing:
            raise MapFileError(source, where, f"place {k}: missing field(s) {sorted(missing)}")
        if extra:
            raise MapFileError(source, where, f"place {k}: unknown field(s) {sorted(extra)}")
        if not _is_int(p["id"]):
            raise MapFileError(source, where, f"place {k}: id {p['id']!r} is not an integer")
        for f in ("x", "y"):
            if not _is_num(p[f]):
                raise MapFileError(source, where, f"place {p['id']}: {f} = {p[f]!r} is not a finite number")
        if p["id"] in first_line:
            raise MapFileError(source, where, f"duplicate place id {p['id']} (first on line {first_line[p['id']]})")
        first_line[p["id"]] = where
        ids.append(p["id"])
        xy.append((float(p["x"]), float(p["y"])))
    g = MapGraph(capacity=max(len(ids), 1))
    g.add_places(ids)
    cols: dict[str, list] = {k: [] for k in ("from", "to", "d", "theta", "steps", "mean_step", "variance")}
    seen: dict[tuple[int, int], int] = {}
    for k, lk in enumerate(doc["links"]):
        where = line(ln_lines, k)
        if not isinstance(lk, dict):
            raise MapFileError(source, where, f"link {k} is not an object")
        missing, extra = _LINK_REQ - set(lk), set(lk) - _LINK_REQ - _LINK_OPT
        if missing:
            raise MapFileError(source, where, f"link {k}: missing field(s) {sorted(missing)}")
        if extra:
            raise MapFileError(source, where, f"link {k}: unknown field(s) {sorted(extra)}")
        for f in ("from", "to"):
            if not _is_int(lk[f]):
                raise MapFileError(source, where, f"link {k}: '{f}' = {lk[f]!r} is not an integer place id")
            if lk[f] not in first_line:
                raise MapFileError(source, where, f"link {k}: no place with id {lk[f]}")
        a, b = lk["from"], lk["to"]
        if a == b:
            raise MapFileError(source, where, f"link {k}: from place {a} to itself")
        key = (min(a, b), max(a, b))
        if key in seen:
            raise MapFileError(source, where, f"duplicate link between places {a} and {b} (first on line {seen[key]})")
        seen[key] = where
        for f in ("d", "theta"):
            if not _is_num(lk[f]):
                raise MapFileError(source, where, f"link {a} -> {b}: {f} = {lk[f]!r} is not a finite number")
        var = lk.get("variance")
        if var is not None and not (_is_num(var) and var > 0):
            raise MapFileError(source, where, f"link {a} -> {b}: variance = {var!r} must be null or > 0")
        steps, ms = lk.get("steps", 1), lk.get("mean_step", 1.0)
        if var is None:
            if not (_is_int(steps) and steps >= 1):
                raise MapFileError(source, where, f"link {a} -> {b}: steps = {steps!r} must be an integer >= 1")
            if not (_is_num(ms) and ms > 0):
                raise MapFileError(source, where, f"link {a} -> {b}: mean_step = {ms!r} must be > 0")
        if lk["d"] < 0:
            raise MapFileError(source, where, f"link {a} -> {b}: d = {lk['d']!r} is negative")
        for f, v in (("from", a), ("to", b), ("d", lk["d"]), ("theta", lk["theta"]),
                     ("steps", steps if _is_num(steps) else 1), ("mean_step", ms if _is_num(ms) else 1.0),
                     ("variance", math.nan if var is None else var)):
            cols[f].append(v)
    try:
        g.add_links(cols["from"], cols["to"], d_m=cols["d"], theta_rad=cols["theta"], steps=cols["steps"],
                    mean_step_m=cols["mean_step"], variance_m2=cols["variance"])
    except GraphError as exc:
        raise MapFileError(source, 0, str(exc)) from None
    noise = CompassNoise()
    if "noise" in doc:
        nz = doc["noise"]
        if not isinstance(nz, dict) or set(nz) != {"s_dd", "s_aa", "s_da"} or not all(_is_num(v) for v in nz.values()):
            raise MapFileError(source, 0, "'noise' must be {\"s_dd\": number, \"s_aa\": number, \"s_da\": number}")
        if not (nz["s_dd"] > 0 and nz["s_aa"] > 0 and nz["s_dd"] * nz["s_aa"] > nz["s_da"] ** 2):
            raise MapFileError(source, 0, f"noise {nz} is not a covariance (need s_dd, s_aa > 0, s_da^2 < s_dd s_aa)")
        noise = CompassNoise(float(nz["s_dd"]), float(nz["s_aa"]), float(nz["s_da"]))
    if not ids:
        raise MapFileError(source, 0, "the map has no place")
    pinned = doc.get("pinned", ids[0])
    if not _is_int(pinned) or pinned not in first_line:
        raise MapFileError(source, 0, f"pinned = {pinned!r} is not the id of a place")
    return MapFile(graph=g, xy=np.array(xy, dtype=float).reshape(-1, 2), noise=noise, pinned_id=int(pinned))


def read_map_json(path: str | os.PathLike) -> MapFile:
    """Read a ``map.json``: places, traversed links, noise parameters and the pinned place.

    Raises :class:`MapFileError` naming the line of the offending place or link for invalid JSON,
    missing, unknown or non-numeric fields, duplicate place ids or links, links to a missing place
    and a pinned id that is not a place. A map in several parts is accepted: the solvers hold the
    pinned place and the first place of every other part (a per-part gauge).
    """
    p = Path(path)
    try:
        text = p.read_text()
    except UnicodeDecodeError:
        raise MapFileError(str(p), 0, "not a text file") from None
    return parse_map_json(text, source=str(p))


def format_map_json(graph: MapGraph, xy: np.ndarray, noise: CompassNoise, pinned_id: int) -> str:
    """``map.json`` text, one place or link per line."""
    xy = np.asarray(xy, dtype=float)
    ids = graph.ids.tolist()
    places = [json.dumps({"id": i, "x": x, "y": y}) for i, (x, y) in zip(ids, xy.tolist())]
    links = []
    for a, b, d, th, st, ms, var in zip(graph.src.tolist(), graph.dst.tolist(), graph.d_m.tolist(),
                                        graph.theta_rad.tolist(), graph.steps.tolist(),
                                        graph.mean_step_m.tolist(), graph.variance_m2.tolist()):
        links.append(json.dumps({"from": ids[a], "to": ids[b], "d": d, "theta": th, "steps": int(st),
                                 "mean_step": ms, "variance": None if math.isnan(var) else var}))
    noise_s = json.dumps({"s_dd": noise.s_dd_m2, "s_aa": noise.s_aa_rad2, "s_da": noise.s_da_m_rad})
    return ('{\n"places": [\n' + ",\n".join(places) + '\n],\n"links": [\n' + ",\n".join(links)
            + f'\n],\n"noise": {noise_s},\n"pinned": {int(pinned_id)}\n}}\n')


def write_map_json(path: str | os.PathLike, graph: MapGraph, xy: np.ndarray, noise: CompassNoise,
                   pinned_id: int) -> None:
    """Write ``map.json`` atomically (temporary file, then rename)."""
    atomic_write(path, format_map_json(graph, xy, noise, pinned_id))
