"""Simulated runs of the whole loop in process, measured against ground truth (issue 5's criteria).

The measures are those of :mod:`services.launch.place_metrics`; ``python -m services.launch.inprocess
--world orebro-office --seed 0 --no-relax`` prints them for one run. Each whole-exploration test states
the figure measured; other seeds' are in docs/places.md.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest

from services.launch.inprocess import InProcessParams, InProcessRun, PlaceRecord, RunRecord
from services.launch.place_metrics import CHI2_2DOF_95, map_errors, measure
from sim.geometry import wrap_angle
from sim.sensors import CompassModel
from sim.world import load_world


def _run(world: str, sim_s: float, *, seed: int = 0, relax: bool = False, until_complete: bool = True):
    w = load_world(world)
    rec = InProcessRun(w, InProcessParams(seed=seed, max_sim_time_s=sim_s, relax=relax,
                                          stop_when_complete=until_complete)).run()
    return rec, measure(rec, w)


def test_a_run_is_a_function_of_the_seed():
    a, _ = _run("orebro-office", 60.0, seed=3, relax=True)
    b, _ = _run("orebro-office", 60.0, seed=3, relax=True)
    c, _ = _run("orebro-office", 60.0, seed=4, relax=True)
    assert a.places and a.places == b.places and a.links == b.links and a.scans == b.scans
    assert a.trajectory == b.trajectory and a.relaxed == b.relaxed
    assert a.trajectory != c.trajectory


def test_map_errors_after_rigid_alignment():
    rng = np.random.default_rng(1)
    true = rng.uniform(0, 10, size=(12, 2))
    c, s = np.cos(0.3), np.sin(0.3)
    moved = true @ np.array([[c, s], [-s, c]]) + [4.0, -2.0]  # the same map, rotated and shifted
    noisy = moved + rng.normal(scale=0.1, size=moved.shape)
    rec = RunRecord(world="w", seed=0, dt_s=0.1)
    rec.places = {i: PlaceRecord(i, 0, tuple(true[i]), tuple(moved[i])) for i in range(12)}
    rec.relaxed = {i: tuple(noisy[i]) for i in range(12)}
    m = map_errors(rec)
    assert m["map_error_explorer_rms_m"] == pytest.approx(0.0, abs=1e-9)
    assert 0.05 < m["map_error_relaxed_rms_m"] < 0.15


@pytest.fixture(scope="module")
def short_run():
    """Ten simulated minutes of orebro-office: the corridor and the first rooms."""
    return _run("orebro-office", 600.0)


def test_short_run_places_offsets_and_links(short_run):
    rec, m = short_run
    assert m["places"] >= 30 and m["collisions"] < 0.2 * rec.ticks
    assert m["revisits"] >= 10 and m["recognition_rate"] >= 0.7
    assert m["misrecognised_scans"] <= 0.02 * m["localised_scans"]
    assert m["offset_error_median_m"] < 0.1
    # measured links (about a metre) close to the true displacements between the places' true centres
    assert m["link_error_median_m"] < 0.1
    assert m["nees_within_95"] >= 0.85
    assert m["map_error_explorer_rms_m"] < 0.6



def test_compass_deviation_learned_and_taken_out_of_the_links():
    """50 simulated minutes of orebro-office pass the disturbances at (11, 6) and (38, 2) (12 and -18
    degrees). On the links whose places the truth deviates by more than 4 degrees, what is left of the
    true deviation after the recognizer's correction is 0.21-0.37 of it (seeds 0-7; 0.46 for seed 0
    with the pairs of visits compared at the places' centres, ``DeviationParams.visit_baseline`` off),
    and the published angles are off by 0.58-0.94 of the same links' uncorrected angles (seed 0: 5.7
    against 8.9 degrees). The second ratio carries every other error of the links too, so it moves
    with the run (on the CI machine seed 0 once took another path and came to 0.85), and is held only
    to be below 1; the first measures the learning itself (1 with no correction)."""
    w = load_world("orebro-office")
    run = InProcessRun(w, InProcessParams(seed=0, max_sim_time_s=3000.0, relax=False))
    rec = run.run()
    compass, recognizer = CompassModel(w), run.recognizer
    dev = recognizer.deviations
    truth = {i: p.true_xy for i, p in rec.places.items()}
    true_dev = {i: compass.deviation_rad(*xy) for i, xy in truth.items()}
    rows = []
    for lk in rec.latest_links().values():
        a, b = lk.from_id, lk.to_id
        true_theta = math.atan2(truth[b][1] - truth[a][1], truth[b][0] - truth[a][0])
        correction = recognizer._correction(a, b)  # what the recognizer took out of the published angle
        rows.append((0.5 * (true_dev[a] + true_dev[b]), correction, wrap_angle(lk.theta_rad - true_theta),
                     wrap_angle(lk.theta_rad + correction - true_theta)))
    true_corr, corrections, corrected, uncorrected = np.array(rows).T
    disturbed = np.abs(true_corr) > math.radians(4.0)
    assert disturbed.sum() >= 15
    left = np.abs(true_corr - corrections)[disturbed].mean() / np.abs(true_corr)[disturbed].mean()
    assert left < 0.42
    assert np.abs(corrected)[disturbed].mean() < np.abs(uncorrected)[disturbed].mean()
    # the places well inside a disturbance are found turned its way
    strong = [i for i, d in true_dev.items() if abs(d) > math.radians(8.0)]
    assert len(strong) >= 5
    assert all(np.sign(dev.deviation(i)) == np.sign(true_dev[i]) for i in strong)
    # a link whose correction moved is published again with the same traversals
    published = Counter((lk.from_id, lk.to_id, lk.traversals) for lk in rec.links)
    assert max(published.values()) >= 2


@pytest.fixture(scope="module")
def orebro():
    """A whole exploration of orebro-office (seed 0), relaxed coordinates fed back as in ``relaxmap run``:
    complete at 6512 simulated seconds with 419 places."""
    rec, m = _run("orebro-office", 9000.0, relax=True)
    print({k: m[k] for k in ("sim_time_s", "wall_time_s", "places", "revisits", "recognition_rate",
                             "offset_error_median_m", "link_error_rms_m", "nees_within_95", "coverage",
                             "largest_unvisited_m2")})
    return rec, m


@pytest.mark.slow
def test_orebro_exploration_ends_with_no_predicted_place(orebro):
    rec, m = orebro
    assert m["complete"] and m["predicted_left"] == 0
    assert m["places"] >= 150


@pytest.mark.slow
def test_orebro_offset_error(orebro):
    _, m = orebro
    assert m["offset_error_median_m"] < 0.15  # issue 5: median offset error under 0.15 m


@pytest.mark.slow
def test_orebro_link_errors_consistent_with_the_covariance_model(orebro):
    _, m = orebro
    # normalised squared errors under Eq. 5 (noise by maximum likelihood from the true errors): a
    # chi-square with 2 degrees of freedom puts 95% below 5.991
    assert m["nees_within_95"] >= 0.9, CHI2_2DOF_95


@pytest.mark.slow
def test_orebro_link_errors_grow_with_the_steps_as_eq5_says(orebro):
    """The longer half of the links has 0.22-0.42 of the shorter half's mean NEES (seeds 0-2 and the
    same seed with relaxed coordinates that differ in the last digits: the statistic moves with the
    run). On seed 0's links, a variance growing with the square of the steps gives 0.07, and one that
    does not grow 0.61: the link errors grow with the steps more slowly than Eq. 5 says, because the
    sonar offsets at both ends add a part that does not grow."""
    _, m = orebro
    assert 0.15 <= m["nees_long_over_short"] <= 4.0


@pytest.mark.slow
def test_orebro_relaxed_map_within_half_a_metre(orebro):
    """Measured (seed 0): the relaxed places 0.15 m RMS from the true centres after rigid alignment, the
    explorer's dead-reckoned coordinates at confirmation 0.22 m (0.13 and 0.16 m before "no known place"
    became three tracks; 0.17 and 0.24 m in an earlier run)."""
    _, m = orebro
    assert m["map_error_relaxed_rms_m"] < 0.5
    assert m["map_error_relaxed_rms_m"] <= m["map_error_explorer_rms_m"] + 0.05


@pytest.mark.slow
def test_orebro_revisits_recognised(orebro):
    """Measured (seed 0): 99.7% of 584 revisits (99.8% of 542 before "no known place" became three
    tracks; 99.5% of 635 in an earlier run; 99.8% of 585 before
    the compass's deviation map; 98.9% before links waited for 5 observations and flat matches kept the
    predicted offset; 89% before the walls-first match, docs/places.md)."""
    _, m = orebro
    assert m["recognition_rate"] >= 0.95  # issue 5: at least 95% of revisits recognised


@pytest.mark.slow
def test_orebro_every_reachable_region_visited(orebro):
    """Measured (seed 0): 99.0% of the reachable free space within 1 m of the true path, no region left
    (98.3% before "no known place" became three tracks; 98.8% in an earlier run; 98.6% and 2.6 m^2 before the compass's deviation map; before links waited
    for 5 observations and flat matches kept the predicted offset: 93% and a room of 22 m^2 never
    entered; before predictions in 16 directions: 70%, rooms of up to 105 m^2)."""
    _, m = orebro
    assert m["coverage"] >= 0.95 and m["largest_unvisited_m2"] < 10.0


@pytest.fixture(scope="module")
def manchester():
    """A whole exploration of manchester-corridors (seed 0), relaxed coordinates fed back: complete at 7397
    simulated seconds with 532 places."""
    return _run("manchester-corridors", 9000.0, relax=True)


@pytest.mark.slow
def test_manchester_exploration_ends_with_no_place_left_to_explore(manchester):
    """Measured (seed 0): no predicted place left at 7397 s, 97.9% of the reachable free space within 1 m of
    the true path, the largest region left 2.8 m^2 (95.2% and 21 m^2 before "no known place" became
    three tracks; 68.5% and 90 m^2 before a robot that does not move on weighed its scans less,
    docs/places.md, "A robot that does not move on"; seeds 0-29 now range over 78-99%, mean 89%,
    against 69-99%, mean 90%, before the three tracks and 53-99%, mean 87%, before that). Part of the building can be left unseen
    when an exploration ends (docs/places.md, "What still limits the map"); the bounds hold that part
    to one region of the size of those runs' largest."""
    _, m = manchester
    assert m["complete"] and m["predicted_left"] == 0
    assert m["coverage"] >= 0.65 and m["largest_unvisited_m2"] < 100.0
    assert m["offset_error_median_m"] < 0.15
