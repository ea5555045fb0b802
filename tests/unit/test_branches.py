"""Paired branches of an in-process run (services.launch.branches)."""

from __future__ import annotations

import json
import math

import pytest

from services.launch import branches as br
from services.launch.inprocess import InProcessParams, InProcessRun, LinkRecord, PlaceRecord, RunRecord
from services.place_recognizer import PlaceRecognizerParams
from sim.world import load_world


def _link(tick, a, b, dx, dy):
    return LinkRecord(tick=tick, from_id=a, to_id=b, d_m=math.hypot(dx, dy), theta_rad=math.atan2(dy, dx),
                      steps=20, mean_step_m=0.05, traversals=1)


def test_wrong_links_counts_each_pair_measured_wrong_in_the_window_once():
    rec = RunRecord(world="w", seed=0, dt_s=0.1)
    rec.places = {i: PlaceRecord(i, 0, (float(i), 0.0), (float(i), 0.0)) for i in range(4)}
    rec.links = [
        _link(10, 0, 1, 1.02, 0.03),  # right
        _link(12, 1, 2, 1.0, 0.8),  # 0.8 m off
        _link(15, 2, 1, -1.0, -0.7),  # the same pair, backwards, 0.7 m off: counted once
        _link(17, 1, 0, -1.0, 0.0),  # right, backwards
        _link(18, 0, 1, 1.0, 0.0),  # ... and forwards
        _link(30, 2, 3, 2.0, 0.0),  # 1 m off, after the first window
        _link(35, 1, 2, 1.0, 0.0),  # pair 1-2 measured right later
        _link(14, 3, 9, 1.0, 0.0),  # a place no longer mapped
    ]
    assert br.wrong_links(rec, 0, 20) == 1
    assert br.wrong_links(rec, 0, 40) == 2
    assert br.wrong_links(rec, 0, 40, threshold_m=0.9) == 1
    assert br.wrong_links(rec, 16, 40) == 1  # from tick 16 pair 1-2 is measured right only
    assert br.wrong_links(rec, 0, 14) == 1


def test_a_copy_with_the_same_parameters_continues_exactly_as_the_run():
    """The copy owns its simulator, random generator and cores: stepping it does not move the run,
    and the run stepped as far gives the same scans, places and links."""
    run = InProcessRun(load_world("orebro-office"), InProcessParams(seed=2, max_sim_time_s=400.0))
    while run.record.ticks < 1500:
        run.tick()
    same = br.continued(run, run.recognizer.params, 3000)
    blind = br.continued(run, PlaceRecognizerParams(match_sharpness=0.5), 3000)
    assert run.record.ticks == 1500
    while run.record.ticks < 3000:
        run.tick()
    assert same.record.scans == run.record.scans and same.record.links == run.record.links
    assert same.record.places == run.record.places and len(run.record.places) > 3
    # a recognizer that hardly believes its matches localises otherwise from the same state
    assert [s.place_id for s in blind.record.scans] != [s.place_id for s in run.record.scans]


def test_branches_yield_every_window_and_an_empty_variant_is_the_run():
    w = load_world("orebro-office")
    out = list(br.branches(w, InProcessParams(seed=1, max_sim_time_s=500.0), [{}, {"match_sharpness": 0.5}],
                           every_s=200.0, window_s=150.0))
    # the second window is cut at the run's end
    assert [t for o in out for t in (o.start_s, o.end_s)] == pytest.approx([200.0, 350.0, 400.0, 500.0])
    for o in out:
        assert o.variant_wrong[0] == o.base_wrong and o.variant_links[0] == o.base_links
    assert sum(o.base_links for o in out) > 0


def test_a_variant_names_recognizer_parameters_only():
    base = PlaceRecognizerParams()
    with pytest.raises(ValueError, match="not a place recognizer parameter: sharpness"):
        br.recognizer_variant(base, {"sharpness": 3})
    with pytest.raises(ValueError, match=r"Expected `int`, got `str` - at `\$.none_components`"):
        br.recognizer_variant(base, {"none_components": "x"})
    with pytest.raises(ValueError, match="not a place recognizer parameter: deviation.no_such"):
        br.recognizer_variant(base, {"deviation": {"no_such": 1}})
    v = br.recognizer_variant(base, {"match_sharpness": 12, "match_weights": [1, 0.1, 0.1],
                                     "deviation": {"enabled": False}})
    assert v.match_sharpness == 12 and v.match_weights == (1, 0.1, 0.1) and not v.deviation.enabled
    assert v.cell_m == base.cell_m and v.deviation.prior_std_rad == base.deviation.prior_std_rad


@pytest.mark.parametrize("argv", [["--variant", "{not json"], ["--variant", "[1, 2]"],
                                  ["--variant", '{"cell": 1}'], ["--variant", '{"cell_m": true}'],
                                  ["--base", '{"cell": 1}', "--variant", "{}"], ["--base", "[]", "--variant", "{}"], ["--variant", "{}", "--every", "0"]])
def test_bad_arguments_exit_with_a_message(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        br.main(argv)
    assert exc.value.code == 2
    assert "error:" in capsys.readouterr().err


def test_the_command_prints_each_window_and_the_totals_against_its_base(capsys):
    assert br.main(["--max-sim-time", "300", "--every", "150", "--window", "100", "--base",
                    '{"none_components": 1}', "--variant", '{"none_components": 1}', "--variant", "{}"]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    windows, total = lines[:-1], lines[-1]
    assert [w["start_s"] for w in windows] == [150.0]  # the copy from 300 s has no time left and is not made
    assert total["base"] == {"none_components": 1}
    # the first variant is the base itself: the same links, window by window
    assert all(w["variant_links"][0] == w["base_links"] for w in windows)
    assert total["variants"][0]["links"] == total["base_links"] > 0
