"""Shortest paths and reachability over the explorer's place graph (Dijkstra with a heap)."""

from __future__ import annotations

import heapq
from collections.abc import Mapping

# A heap over dicts, not scipy.sparse.csgraph: the graph has at most a few hundred places, changes on
# every confirmation, and is keyed by place ids, so building a sparse matrix per query costs more
# than the search.

Graph = Mapping[int, Mapping[int, float]]  # place -> neighbour -> non-negative edge weight


def dijkstra(graph: Graph, source: int) -> tuple[dict[int, float], dict[int, int]]:
    """Distances from ``source`` and the predecessor of each reached place.

    Examples
    --------
    >>> g = {0: {1: 1.0, 2: 5.0}, 1: {0: 1.0, 2: 1.5}, 2: {0: 5.0, 1: 1.5}}
    >>> dist, prev = dijkstra(g, 0)
    >>> dist[2], prev[2]
    (2.5, 1)
    """
    dist = {source: 0.0}
    prev: dict[int, int] = {}
    heap = [(0.0, source)]
    done: set[int] = set()
    while heap:
        d, u = heapq.heappop(heap)
        if u in done:
            continue
        done.add(u)
        for v, w in graph.get(u, {}).items():
            nd = d + w
            if nd < dist.get(v, float("inf")):
                dist[v] = nd
                prev[v] = u
                heapq.heappush(heap, (nd, v))
    return dist, prev


def path_to(prev: Mapping[int, int], source: int, target: int) -> list[int]:
    """The place sequence ``source .. target`` from Dijkstra's predecessors; empty if unreached."""
    if target == source:
        return [source]
    if target not in prev:
        return []
    path = [target]
    while path[-1] != source:
        path.append(prev[path[-1]])
    return path[::-1]


def reachable(graph: Graph, source: int) -> set[int]:
    """Every place some path reaches from ``source`` (``source`` included)."""
    seen = {source}
    stack = [source]
    while stack:
        u = stack.pop()
        for v in graph.get(u, {}):
            if v not in seen:
                seen.add(v)
                stack.append(v)
    return seen
