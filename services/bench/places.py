"""``relaxmap bench places``: recognition time per scan against the map size; exploration wall time."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--places", type=int, nargs="+", default=[100, 1000], help="map sizes for recognition")
    parser.add_argument("--world", default="orebro-office", help="world of the scans and of the exploration")
    parser.add_argument("--sim-s", type=float, default=300.0, help="simulated seconds of the exploration run")
    parser.add_argument("--seed", type=int, default=0, help="seed of the place positions and the simulator")


def main(args: argparse.Namespace) -> int:
    import numpy as np

    from messages.types import DeadReckonedPose, Pose2, SonarScan
    from services.bench.table import print_table, time_call
    from services.launch.inprocess import InProcessParams, InProcessRun
    from services.place_recognizer import PlaceRecognizer, PlaceRecognizerParams
    from services.place_recognizer.histogram import match_axis
    from services.sensor_sim.core import SimModel
    from sim.world import load_world

    world = load_world(args.world)
    rng = np.random.default_rng(args.seed)
    model = SimModel(world)
    xmin, ymin, xmax, ymax = world.bounds

    def free_points(n: int) -> np.ndarray:
        out = []
        while len(out) < n:
            p = rng.uniform((xmin, ymin), (xmax, ymax), size=(4 * n, 2))
            out += [q for q, bad in zip(p, world.occupied(p, margin_m=0.3), strict=True) if not bad]
        return np.array(out[:n])

    def scan_at(x: float, y: float, k: int):
        ranges = model.sonar.measure((x, y, 0.0), world, rng)
        sp = model.params.sonar
        return SonarScan(stamp=float(k), seq=k, angles_rad=model.sonar_angles, ranges_m=ranges.tolist(),
                         beam_width_rad=sp.beam_width_rad, min_range_m=sp.min_range_m, max_range_m=sp.max_range_m)

    def dr_at(x: float, y: float, k: int) -> DeadReckonedPose:
        pose = Pose2(x_m=x, y_m=y, heading_rad=0.0)
        return DeadReckonedPose(stamp=float(k), seq=k, compass=pose, raw=pose, steps=10 * k, path_length_m=0.5 * k)

    # -- recognition: one scan against maps of N places (signatures from scans at random free points) ------
    rows = []
    probe = free_points(1)[0]
    for n in args.places:
        timings = {}
        for label, min_prior in (("all", 0.0), ("gated", PlaceRecognizerParams().match_min_prior)):
            rec = PlaceRecognizer(PlaceRecognizerParams(match_min_prior=min_prior))
            for i, (x, y) in enumerate(free_points(n)):
                dr = dr_at(x, y, i)
                rec.step(dr, scan_at(x, y, i))
                rec.add_place(i, x, y, dr)
            dr, scan = dr_at(*probe, n + 1), scan_at(*probe, n + 1)
            timings[label] = time_call(lambda rec=rec, dr=dr, scan=scan: rec.step(dr, scan), repeat=3)
        sig = rec.signature(0)
        one = time_call(lambda sig=sig: (match_axis(sig.x, sig.x, 10), match_axis(sig.y, sig.y, 10)), repeat=3)
        rows.append((n, timings["all"] * 1e3, timings["gated"] * 1e3, one * 1e6, timings["all"] / one))
    print_table("Recognition: one sonar scan against the map", ["places", "ms / scan (all matched)",
                "ms / scan (gated by prior)", "one match (us)", "all / one match"], rows,
                note="Reference: the x and y histogram match of one place (Eq. 19, all shifts), same run. Gated: "
                     f"match_min_prior={PlaceRecognizerParams().match_min_prior:g} (the default), only places "
                     "at least that probable before the scan are matched.")

    # -- exploration: the in-process loop, wall time per simulated minute -------------------------------
    run = InProcessRun(world, InProcessParams(seed=args.seed, max_sim_time_s=args.sim_s, stop_when_complete=False))
    rec = run.run()
    minutes = rec.sim_time_s / 60.0
    t = rec.timings_s
    total = rec.wall_time_s
    rows = [(name, t[name] / minutes, t[name] / t["sim"]) for name in ("sim", "dead_reckoning", "recognizer",
                                                                         "explorer", "relaxer")]
    rows.append(("whole loop", total / minutes, total / t["sim"]))
    print_table(f"Exploration of {world.name}: {rec.sim_time_s:.0f} s simulated, {len(rec.places)} places, "
                f"{len(rec.scans)} scans", ["component", "wall s / simulated min", "x simulator"], rows,
                note="Reference: the simulator's own step (robot, odometry, compass, sonar), same run.")
    return 0
