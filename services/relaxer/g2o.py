"""Reading and writing 2-D pose graphs in g2o format (``VERTEX_SE2``, ``EDGE_SE2``)."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.common.files import atomic_write
from services.relaxer.graph import GraphError
from services.relaxer.pose import PoseGraph, odometry_initialisation

__all__ = ["G2oError", "G2oFile", "parse_g2o", "read_g2o", "write_g2o", "format_g2o"]


class G2oError(ValueError):
    """A malformed g2o file; ``line`` is the 1-based line number (0 when no single line is to blame)."""

    def __init__(self, source: str, line: int, problem: str) -> None:
        self.source, self.line, self.problem = source, line, problem
        where = f"{source}:{line}" if line else source
        super().__init__(f"{where}: {problem}")


@dataclass(frozen=True)
class G2oFile:
    """A pose graph read from g2o, with its initial poses."""

    graph: PoseGraph
    poses: np.ndarray  # (N, 3) initial poses by dense index (ids sorted ascending)
    given: np.ndarray  # (N,) True where the file had a VERTEX_SE2 for the pose


_FIELDS = {"VERTEX_SE2": 4, "EDGE_SE2": 11}


def _number(tok: str, source: str, lineno: int, field: int, integer: bool = False) -> float | int:
    try:
        if integer:
            return int(tok)
        val = float(tok)
    except ValueError:
        kind = "an integer id" if integer else "a number"
        raise G2oError(source, lineno, f"field {field} ({tok!r}) is not {kind}") from None
    if not math.isfinite(val):
        raise G2oError(source, lineno, f"field {field} ({tok!r}) is not finite")
    return val


def parse_g2o(text: str, *, source: str = "<g2o>") -> G2oFile:
    """Parse g2o text; see :func:`read_g2o`."""
    vertices: dict[int, tuple[float, float, float]] = {}
    vertex_line: dict[int, int] = {}
    e_ij: list[tuple[int, int]] = []
    e_val: list[list[float]] = []
    e_line: list[int] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        toks = raw.split()
        if not toks or toks[0].startswith("#"):
            continue
        tag = toks[0]
        if tag not in _FIELDS:
            raise G2oError(source, lineno, f"unknown record {tag!r} (expected VERTEX_SE2 or EDGE_SE2)")
        want = _FIELDS[tag]
        if len(toks) - 1 != want:
            raise G2oError(source, lineno, f"{tag} needs {want} fields after the tag, got {len(toks) - 1}")
        if tag == "VERTEX_SE2":
            vid = _number(toks[1], source, lineno, 1, integer=True)
            vals = [_number(t, source, lineno, f) for f, t in enumerate(toks[2:], start=2)]
            if vid in vertices:
                raise G2oError(source, lineno, f"duplicate vertex id {vid} (first on line {vertex_line[vid]})")
            vertices[vid] = (vals[0], vals[1], vals[2])
            vertex_line[vid] = lineno
        else:
            a = _number(toks[1], source, lineno, 1, integer=True)
            b = _number(toks[2], source, lineno, 2, integer=True)
            if a == b:
                raise G2oError(source, lineno, f"edge from vertex {a} to itself")
            vals = [_number(t, source, lineno, f) for f, t in enumerate(toks[3:], start=3)]
            e_ij.append((a, b))
            e_val.append(vals)
            e_line.append(lineno)
    if not e_ij and not vertices:
        raise G2oError(source, 0, "no VERTEX_SE2 or EDGE_SE2 record")
    ij = np.array(e_ij, dtype=np.int64).reshape(-1, 2)
    val = np.array(e_val, dtype=float).reshape(-1, 9)
    ids = np.array(sorted(set(vertices) | set(ij.reshape(-1).tolist())), dtype=np.int64)
    index = {int(v): k for k, v in enumerate(ids.tolist())}
    info = np.empty((len(val), 3, 3))
    up = val[:, 3:]
    info[:, 0, 0], info[:, 0, 1], info[:, 0, 2] = up[:, 0], up[:, 1], up[:, 2]
    info[:, 1, 1], info[:, 1, 2], info[:, 2, 2] = up[:, 3], up[:, 4], up[:, 5]
    info[:, 1, 0], info[:, 2, 0], info[:, 2, 1] = up[:, 1], up[:, 2], up[:, 4]
    if len(info):
        eig_min = np.linalg.eigvalsh(info)[:, 0]
        bad = np.flatnonzero(~(eig_min > 0))
        if len(bad):
            k = int(bad[0])
            raise G2oError(source, e_line[k], f"information matrix is not positive definite "
                                              f"(smallest eigenvalue {eig_min[k]:.3g})")
    gi = np.array([index[a] for a in ij[:, 0].tolist()], dtype=np.int64)
    gj = np.array([index[b] for b in ij[:, 1].tolist()], dtype=np.int64)
    graph = PoseGraph(ids=ids, i=gi, j=gj, z=val[:, :3].copy(), info=info)
    given = np.array([int(v) in vertices for v in ids.tolist()], dtype=bool)
    poses = np.zeros((len(ids), 3))
    for v, p in vertices.items():
        poses[index[v]] = p
    if not given.all():
        try:
            poses = odometry_initialisation(graph, given, poses)
        except GraphError as exc:
            raise G2oError(source, 0, str(exc)) from None
    return G2oFile(graph=graph, poses=poses, given=given)


def read_g2o(path: str | os.PathLike) -> G2oFile:
    """Read a g2o file of ``VERTEX_SE2`` and ``EDGE_SE2`` records.

    Poses without ``VERTEX_SE2`` are initialised by composing edges from poses that have one,
    sequential edges ``id -> id + 1`` first (odometry initialisation; a part of the graph with no
    vertex at all starts from its smallest id at the origin). Blank lines and ``#`` comments are
    skipped. Raises :class:`G2oError` naming the line for truncated lines, non-numeric or non-finite
    fields, unknown records, duplicate vertex ids, self-edges and information matrices that are not
    positive definite.
    """
    p = Path(path)
    try:
        text = p.read_text()
    except UnicodeDecodeError:
        raise G2oError(str(p), 0, "not a text file") from None
    return parse_g2o(text, source=str(p))


def format_g2o(graph: PoseGraph, poses: np.ndarray) -> str:
    """g2o text: one ``VERTEX_SE2`` per pose, then one ``EDGE_SE2`` per edge (upper triangle of Info)."""
    out = []
    for vid, (x, y, t) in zip(graph.ids.tolist(), np.asarray(poses, dtype=float).tolist()):
        out.append(f"VERTEX_SE2 {vid} {x!r} {y!r} {t!r}")
    ids = graph.ids
    iu = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    up = np.stack([graph.info[:, a, b] for a, b in iu], axis=1) if graph.n_edges else np.zeros((0, 6))
    for a, b, z, m in zip(ids[graph.i].tolist(), ids[graph.j].tolist(), graph.z.tolist(), up.tolist()):
        out.append("EDGE_SE2 " + " ".join([str(a), str(b)] + [repr(v) for v in z + m]))
    return "\n".join(out) + "\n"


def write_g2o(path: str | os.PathLike, graph: PoseGraph, poses: np.ndarray) -> None:
    """Write a g2o file atomically (temporary file, then rename)."""
    atomic_write(path, format_g2o(graph, poses))
