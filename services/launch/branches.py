"""Paired branches of one in-process run: copies continued with other recognizer parameters, wrong links counted."""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import math
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import msgspec
import numpy as np

from services.launch.inprocess import InProcessParams, InProcessRun, RunRecord
from services.place_recognizer import PlaceRecognizerParams
from sim.world import World, load_world


@dataclass(frozen=True)
class BranchWindow:
    """One window: the run itself and each variant's copy, from the same state at ``start_s``.

    Attributes
    ----------
    start_s, end_s : float
        The window's simulated time.
    base_wrong, variant_wrong : int, tuple of int
        Pairs of places whose link was measured wrong in the window (:func:`wrong_links`): by the run,
        by each variant.
    base_links, variant_links : int, tuple of int
        Pairs of places whose link was measured in the window.
    """

    start_s: float
    end_s: float
    base_wrong: int
    variant_wrong: tuple[int, ...]
    base_links: int
    variant_links: tuple[int, ...]


def recognizer_variant(params: PlaceRecognizerParams, overrides: Mapping[str, object]) -> PlaceRecognizerParams:
    """``params`` with ``overrides`` (a nested object for the deviation's parameters), converted and
    checked by msgspec; ``ValueError`` naming a field the recognizer does not have or a wrong value."""
    fields = msgspec.to_builtins(params)
    _merge(fields, overrides, params, "")
    try:
        return msgspec.convert(fields, PlaceRecognizerParams)
    except msgspec.ValidationError as exc:
        raise ValueError(f"place recognizer parameters: {exc}") from None


def _merge(into: dict, overrides: Mapping[str, object], like: object, path: str) -> None:
    """``overrides`` into ``into`` (the builtins of ``like``, a dataclass), by name; msgspec ignores
    names a dataclass does not have, so they are refused here."""
    unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(like)})
    if unknown:
        raise ValueError(f"not a place recognizer parameter: {', '.join(path + n for n in unknown)}")
    for name, value in overrides.items():
        now = getattr(like, name)
        if dataclasses.is_dataclass(now) and isinstance(value, Mapping):  # e.g. {"deviation": {"enabled": false}}
            _merge(into[name], value, now, f"{path}{name}.")
        else:
            into[name] = value


def _window_links(record: RunRecord, since_tick: int, until_tick: int) -> dict[frozenset[int], list]:
    """Every measurement in ``[since_tick, until_tick)``, by pair of places."""
    out: dict[frozenset[int], list] = {}
    for lk in record.links:
        if since_tick <= lk.tick < until_tick:
            out.setdefault(frozenset((lk.from_id, lk.to_id)), []).append(lk)
    return out


def wrong_links(record: RunRecord, since_tick: int, until_tick: int, *, threshold_m: float = 0.5) -> int:
    """Pairs of places still mapped whose link was measured in ``[since_tick, until_tick)`` further
    than ``threshold_m`` from the places' true displacement at least once (a link measured from or to
    a place the robot was not at: a place is about 1 m from its neighbours)."""
    places = record.places
    n = 0
    for pair in _window_links(record, since_tick, until_tick).values():
        a, b = pair[0].from_id, pair[0].to_id
        if a not in places or b not in places:
            continue
        true = np.subtract(places[b].true_xy, places[a].true_xy)
        for lk in pair:
            sign = 1.0 if lk.from_id == a else -1.0
            measured = sign * np.array((lk.d_m * math.cos(lk.theta_rad), lk.d_m * math.sin(lk.theta_rad)))
            if np.hypot(*(measured - true)) > threshold_m:
                n += 1
                break
    return n


def continued(run: InProcessRun, recognizer: PlaceRecognizerParams, until_tick: int) -> InProcessRun:
    """A copy of ``run`` (simulator, random generator, every core) with the recognizer's parameters
    set to ``recognizer``, stepped to ``until_tick`` or its end; ``run`` itself is not touched."""
    b = copy.deepcopy(run)
    b.recognizer.params = recognizer
    while b.record.ticks < until_tick and not b.done:
        b.tick()
    return b


def branches(world: World, params: InProcessParams, variants: Sequence[Mapping[str, object]], *,
             every_s: float, window_s: float, threshold_m: float = 0.5) -> Iterator[BranchWindow]:
    """Run ``world`` in process; every ``every_s`` of simulated time copy the whole run (simulator,
    its random generator, every core) once per variant, set the variant's recognizer parameters on
    the copy and continue it ``window_s``; yield each window once the run has passed it.

    Notes
    -----
    A whole run is chaotic: one sum rounded differently in its last bit sends the robot elsewhere,
    and thirty seeds hardly tell a change of a few centimetres. A window compares the same robot in
    the same building with the same map, for ``window_s``: the difference is the variant's. A variant
    ``{}`` continues exactly as the run.
    """
    runs = [recognizer_variant(params.recognizer, v) for v in variants]
    run = InProcessRun(world, params)
    dt = params.sim.dt_s
    width = int(round(window_s / dt))
    pending: list[tuple[int, int, list[InProcessRun]]] = []
    next_s = every_s
    while True:
        finished = run.done
        if not finished:
            run.tick()
            if run.record.ticks * dt >= next_s - 1e-9 and not run.done:  # no copy at the run's end
                next_s += every_s
                start = run.record.ticks
                copies = [continued(run, rp, start + width) for rp in runs]
                pending.append((start, start + width, copies))
        while pending and (finished or run.record.ticks >= pending[0][1]):
            start, end, copies = pending.pop(0)
            yield BranchWindow(
                start_s=start * dt, end_s=min(end, run.record.ticks) * dt,
                base_wrong=wrong_links(run.record, start, end, threshold_m=threshold_m),
                variant_wrong=tuple(wrong_links(b.record, start, end, threshold_m=threshold_m) for b in copies),
                base_links=len(_window_links(run.record, start, end)),
                variant_links=tuple(len(_window_links(b.record, start, end)) for b in copies))
        if finished:
            return


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m services.launch.branches",
        description="Copy an in-process run at intervals, continue each copy with other place recognizer "
                    "parameters, and count the wrong links each measures (one JSON line a window, then totals).")
    parser.add_argument("--world", default="orebro-office", help="built-in world name or world file")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulator")
    parser.add_argument("--max-sim-time", type=float, default=9000.0, metavar="S", help="simulated time limit")
    parser.add_argument("--every", type=float, default=400.0, metavar="S", help="simulated time between copies")
    parser.add_argument("--window", type=float, default=300.0, metavar="S", help="simulated time a copy runs on")
    parser.add_argument("--base", default="{}", metavar="JSON",
                        help="recognizer parameters of the run itself (default: the defaults)")
    parser.add_argument("--variant", action="append", required=True, metavar="JSON",
                        help='recognizer parameters of a copy, e.g. \'{"match_sharpness": 12}\' (repeatable)')
    args = parser.parse_args(argv)
    try:
        base_ov = json.loads(args.base)
        variants = [json.loads(v) for v in args.variant]
        if not all(isinstance(v, dict) for v in [base_ov, *variants]):
            raise ValueError("the base and a variant are JSON objects of parameter names and values")
        recognizer = recognizer_variant(PlaceRecognizerParams(), base_ov)
        for v in variants:
            recognizer_variant(recognizer, v)
        if args.every <= 0 or args.window <= 0:
            raise ValueError("--every and --window must be positive")
        world = load_world(args.world)
    except (ValueError, TypeError, OSError) as exc:  # json.JSONDecodeError is a ValueError
        parser.error(str(exc))
    params = InProcessParams(seed=args.seed, max_sim_time_s=args.max_sim_time, recognizer=recognizer)
    base, wrong, links = 0, np.zeros(len(variants), dtype=int), np.zeros(len(variants), dtype=int)
    fewer, more = np.zeros(len(variants), dtype=int), np.zeros(len(variants), dtype=int)
    base_links = 0
    for w in branches(world, params, variants, every_s=args.every, window_s=args.window):
        print(json.dumps(dataclasses.asdict(w)), flush=True)
        v = np.array(w.variant_wrong)
        base += w.base_wrong
        base_links += w.base_links
        wrong += v
        links += np.array(w.variant_links)
        fewer += v < w.base_wrong
        more += v > w.base_wrong
    print(json.dumps({"world": world.name, "seed": args.seed, "base": base_ov, "base_wrong": base, "base_links": base_links,
                      "variants": [{"variant": variants[k], "wrong": int(wrong[k]), "links": int(links[k]),
                                    "windows_fewer": int(fewer[k]), "windows_more": int(more[k])}
                                   for k in range(len(variants))]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
