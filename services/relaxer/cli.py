"""``relaxmap relax INPUT --out OUTPUT``: optimise a stored map (g2o pose graph or compass ``map.json``)."""

from __future__ import annotations

import argparse
import sys

METHODS = ("relax", "exact", "gn", "lm", "auto")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", metavar="INPUT", help="a g2o file (poses, no compass) or a map.json (compass mode)")
    parser.add_argument("--out", required=True, metavar="OUTPUT", help="where to write the result (INPUT's format)")
    parser.add_argument("--method", choices=METHODS, default="auto",
                        help="relax: the paper's relaxation (Figure 3 / Appendix B); exact: one sparse solve "
                             "(compass); gn, lm: Gauss-Newton, Levenberg-Marquardt; auto (default): lm for g2o, "
                             "sweeps with the exact-solve fallback for map.json")
    parser.add_argument("--max-iters", type=int, default=None, metavar="N",
                        help="iterations (GN/LM) or sweeps (relax) at most")
    parser.add_argument("--tol", type=float, default=None, metavar="X",
                        help="stop when an iteration lowers the objective by less than this fraction of it")


def _kind(path: str) -> str:
    low = path.lower()
    if low.endswith(".g2o"):
        return "g2o"
    if low.endswith(".json"):
        return "json"
    with open(path, "rb") as f:
        head = f.read(4096).lstrip()
    return "json" if head.startswith(b"{") else "g2o"


def main(args: argparse.Namespace) -> int:
    import time

    from services.relaxer.g2o import G2oError
    from services.relaxer.graph import GraphError
    from services.relaxer.mapjson import MapFileError
    from services.relaxer.sparse import SolveError

    if args.max_iters is not None and args.max_iters < 1:
        print("error: --max-iters must be at least 1", file=sys.stderr)
        return 2
    if args.tol is not None and not args.tol >= 0:
        print("error: --tol must be >= 0", file=sys.stderr)
        return 2
    try:
        kind = _kind(args.input)
        t0 = time.perf_counter()
        if kind == "g2o":
            return _relax_g2o(args, t0)
        return _relax_map(args, t0)
    except (G2oError, MapFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (GraphError, SolveError, ValueError) as exc:
        print(f"error: {args.input}: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


def _report(kind: str, counts: str, f0: float, f1: float, iterations: int, converged: bool, method: str,
            seconds: float, what: str) -> None:
    print(f"{kind}: {counts}")
    print(f"method: {method}")
    print(f"initial {what}: {f0:.10g}")
    print(f"final {what}: {f1:.10g}")
    print(f"iterations: {iterations} ({'converged' if converged else 'not converged'})")
    print(f"time: {seconds:.3f} s")


def _relax_g2o(args: argparse.Namespace, t0: float) -> int:
    import time

    from services.relaxer.g2o import read_g2o, write_g2o
    from services.relaxer.pose import PoseParams, optimize

    data = read_g2o(args.input)
    t_load = time.perf_counter() - t0
    if args.method == "exact":
        print("error: --method exact needs a compass map (the pose objective is not quadratic); "
              "use gn, lm or relax", file=sys.stderr)
        return 2
    kw = {}
    if args.max_iters is not None:
        kw["max_iters"] = args.max_iters
    elif args.method == "relax":
        kw["max_iters"] = 10_000
    if args.tol is not None:
        kw["tol_rel"] = args.tol
    parts = data.graph.components()[0]
    if parts > 1:
        print(f"note: the graph has {parts} parts; the first pose of each is held fixed")
    t1 = time.perf_counter()
    res = optimize(data.graph, data.poses, method=args.method, params=PoseParams(**kw))
    t_solve = time.perf_counter() - t1
    write_g2o(args.out, data.graph, res.poses)
    _report("g2o", f"{data.graph.n_poses} poses, {data.graph.n_edges} edges (loaded in {t_load:.3f} s)",
            res.initial_objective, res.objective, res.iterations, res.converged, res.method, t_solve,
            "objective (0.5 sum e^T Info e)")
    return 0


def _relax_map(args: argparse.Namespace, t0: float) -> int:
    import time

    from services.relaxer.compass import CompassParams, energy, relax
    from services.relaxer.mapjson import read_map_json, write_map_json

    data = read_map_json(args.input)
    g = data.graph
    t_load = time.perf_counter() - t0
    method = "exact" if args.method in ("gn", "lm") else args.method
    kw = {}
    if args.max_iters is not None:
        kw["max_sweeps"] = args.max_iters
    if args.tol is not None:
        kw["tol_energy_rel"] = args.tol
    parts = g.components()[0]
    if parts > 1:
        print(f"note: the map has {parts} parts; the pinned place and the first place of each other part "
              f"are held fixed")
    pinned = g.index_of(data.pinned_id)
    e0 = energy(g, data.xy, data.noise)
    t1 = time.perf_counter()
    res = relax(g, data.xy, noise=data.noise, pinned=pinned, method=method, params=CompassParams(**kw))
    t_solve = time.perf_counter() - t1
    write_map_json(args.out, g, res.xy, res.noise, data.pinned_id)
    n = res.noise
    _report("map.json", f"{g.n_places} places, {g.n_links} links (loaded in {t_load:.3f} s)", e0, res.energy,
            res.iterations, res.converged, method + (" (the energy is quadratic: one Gauss-Newton step is exact)"
                                                     if args.method in ("gn", "lm") else ""),
            t_solve, "energy (Eq. 7)")
    print(f"noise: s_dd={n.s_dd_m2:.6g} s_aa={n.s_aa_rad2:.6g} s_da={n.s_da_m_rad:.6g}"
          + (f" (exact solves: {res.exact_solves})" if res.exact_solves else ""))
    return 0
