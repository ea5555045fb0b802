"""g2o and map.json files, and the ``relaxmap relax`` command."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.cli import main as cli_main
from services.relaxer.compass import CompassNoise, solve_exact
from services.relaxer.g2o import G2oError, format_g2o, parse_g2o, read_g2o, write_g2o
from services.relaxer.mapjson import MapFileError, format_map_json, parse_map_json, read_map_json, write_map_json
from services.relaxer.pose import objective
from services.relaxer.synthetic import office_map

from tests.conftest import DATASETS  # noqa: E402 (after the gtsam check where there is one)

INFO = "1 0 0 1 0 1"
GOOD_G2O = f"""VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1 0 0
EDGE_SE2 0 1 1 0 0 {INFO}
EDGE_SE2 1 2 1 0 0.5 {INFO}
EDGE_SE2 2 0 -1 -1 0 {INFO}
"""


# ------------------------------------------------------------------------------------------ g2o
def test_g2o_round_trip(tmp_path):
    data = parse_g2o(GOOD_G2O)
    assert data.graph.ids.tolist() == [0, 1, 2]
    np.testing.assert_allclose(data.poses[2], [2.0, 0.0, 0.5])  # composed from 1 by edge 1 -> 2
    assert data.given.tolist() == [True, True, False]
    path = tmp_path / "x.g2o"
    write_g2o(path, data.graph, data.poses)
    again = read_g2o(path)
    np.testing.assert_array_equal(again.poses, data.poses)
    np.testing.assert_array_equal(again.graph.info, data.graph.info)
    np.testing.assert_array_equal(again.graph.z, data.graph.z)
    assert format_g2o(again.graph, again.poses) == path.read_text()
    assert [p.name for p in tmp_path.iterdir()] == ["x.g2o"]


def test_g2o_odometry_initialisation_matches_the_published_objective():
    path = DATASETS / "CSAIL.g2o"
    if not path.exists():
        pytest.skip(f"{path} not found (set RELAXMAP_DATASETS)")
    data = read_g2o(path)
    assert not data.given.any()
    assert objective(data.graph, data.poses) == pytest.approx(1.07215e6, rel=1e-5)  # datasets/README.md


@pytest.mark.parametrize("text, line, problem", [
    (f"VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0\n", 2, "needs 11 fields"),
    ("VERTEX_SE2 0 0 0\n", 1, "needs 4 fields"),
    (f"VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 zero 0 {INFO}\n", 2, "field 4 ('zero') is not a number"),
    (f"VERTEX_SE2 x 0 0 0\n", 1, "not an integer id"),
    (f"VERTEX_SE2 0 0 nan 0\n", 1, "not finite"),
    (f"VERTEX_SE2 0 0 0 0\nVERTEX_XY 1 0 0\n", 2, "unknown record 'VERTEX_XY'"),
    (f"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nVERTEX_SE2 0 1 1 1\n", 3, "duplicate vertex id 0 (first on line 1)"),
    (f"EDGE_SE2 0 0 1 0 0 {INFO}\n", 1, "to itself"),
    (f"EDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1\n", 1, "not positive definite"),
])
def test_g2o_errors_name_the_line(text, line, problem):
    with pytest.raises(G2oError) as err:
        parse_g2o(text, source="bad.g2o")
    assert err.value.line == line
    assert problem in str(err.value)
    assert str(err.value).startswith(f"bad.g2o:{line}: ")


def test_g2o_edge_to_a_vertex_without_initial_value_is_composed_and_parts_start_at_the_origin():
    data = parse_g2o(f"VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 {INFO}\nEDGE_SE2 5 6 0 1 0 {INFO}\n")
    np.testing.assert_allclose(data.poses, [[0, 0, 0], [1, 0, 0], [0, 0, 0], [0, 1, 0]])
    assert data.graph.components()[0] == 2


# ------------------------------------------------------------------------------------- map.json
def _small_map():
    om = office_map(40, rng=np.random.default_rng(0))
    om.graph.add_place(1000)
    om.graph.add_link(0, 1000, d_m=0.7, theta_rad=2.0, variance_m2=0.05)
    xy = np.r_[om.xy_dead_reckoning, [[0.1, 0.2]]]
    return om.graph, xy


def test_map_json_round_trip(tmp_path):
    g, xy = _small_map()
    path = tmp_path / "map.json"
    write_map_json(path, g, xy, CompassNoise(1e-3, 2e-3, 1e-4), pinned_id=3)
    m = read_map_json(path)
    assert m.pinned_id == 3 and m.noise == CompassNoise(1e-3, 2e-3, 1e-4)
    np.testing.assert_array_equal(m.xy, xy)
    np.testing.assert_array_equal(m.graph.ids, g.ids)
    for name in ("src", "dst", "d_m", "theta_rad", "steps", "mean_step_m"):
        np.testing.assert_array_equal(getattr(m.graph, name), getattr(g, name))
    np.testing.assert_array_equal(np.isnan(m.graph.variance_m2), np.isnan(g.variance_m2))
    assert json.loads(path.read_text())["links"][-1]["variance"] == 0.05
    assert format_map_json(m.graph, m.xy, m.noise, m.pinned_id) == path.read_text()


def _doc(places=None, links=None, **extra):
    places = places if places is not None else [
        '{"id": 1, "x": 0.0, "y": 0.0}', '{"id": 2, "x": 1.0, "y": 0.0}', '{"id": 3, "x": 1.0, "y": 1.0}']
    links = links if links is not None else [
        '{"from": 1, "to": 2, "d": 1.0, "theta": 0.0, "steps": 10, "mean_step": 0.1, "variance": null}',
        '{"from": 2, "to": 3, "d": 1.0, "theta": 1.57, "steps": 10, "mean_step": 0.1, "variance": null}']
    tail = "".join(f',\n"{k}": {v}' for k, v in extra.items())
    return '{\n"places": [\n' + ",\n".join(places) + '\n],\n"links": [\n' + ",\n".join(links) + "\n]" + tail + "\n}\n"


def test_map_json_template_is_valid():
    m = parse_map_json(_doc(pinned=2))
    assert m.graph.n_places == 3 and m.graph.n_links == 2 and m.pinned_id == 2


@pytest.mark.parametrize("text, line, problem", [
    ('{"places": [\n{"id": 1, "x": 0.0, "y": 0.0}\n', 3, "not valid JSON"),
    (_doc(places=['{"id": 1, "x": 0.0, "y": 0.0}', '{"id": 2, "x": "one", "y": 0.0}']), 4, "x = 'one'"),
    (_doc(places=['{"id": 1, "x": 0.0, "y": 0.0}', '{"id": 2, "x": 1.0}']), 4, "missing field(s) ['y']"),
    (_doc(places=['{"id": 1, "x": 0.0, "y": 0.0}', '{"id": 1, "x": 1.0, "y": 0.0}']), 4,
     "duplicate place id 1 (first on line 3)"),
    (_doc(links=['{"from": 1, "to": 9, "d": 1.0, "theta": 0.0}']), 8, "no place with id 9"),
    (_doc(links=['{"from": 1, "to": 2, "d": 1.0, "theta": 0.0}', '{"from": 2, "to": 1, "d": 1.0, "theta": 3.1}']),
     9, "duplicate link between places 2 and 1"),
    (_doc(links=['{"from": 1, "to": 2, "d": 1.0, "theta": 0.0, "colour": "red"}']), 8, "unknown field(s) ['colour']"),
    (_doc(links=['{"from": 1, "to": 2, "d": 1.0, "theta": 0.0, "steps": 0}']), 8, "steps = 0"),
    (_doc(links=['{"from": 1, "to": 2, "d": 1.0, "theta": 0.0, "variance": -1}']), 8, "variance = -1"),
    (_doc(pinned=7), 0, "pinned = 7"),
    (_doc(extra_field=1), 0, "unknown field(s) ['extra_field']"),
])
def test_map_json_errors_name_the_line(text, line, problem):
    with pytest.raises(MapFileError) as err:
        parse_map_json(text, source="map.json")
    assert err.value.line == line, str(err.value)
    assert problem in str(err.value)


# ------------------------------------------------------------------------------------------ CLI
def _run(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", "relax", *argv], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parents[2], timeout=120)


def test_cli_relaxes_a_g2o_file(tmp_path):
    src = tmp_path / "in.g2o"
    src.write_text(GOOD_G2O)
    out = tmp_path / "out.g2o"
    proc = _run(str(src), "--out", str(out), "--method", "gn")
    assert proc.returncode == 0, proc.stderr
    assert "initial objective" in proc.stdout and "final objective" in proc.stdout and "iterations" in proc.stdout
    res = read_g2o(out)
    final = float(proc.stdout.split("final objective (0.5 sum e^T Info e): ")[1].split()[0])
    assert objective(res.graph, res.poses) == pytest.approx(final, rel=1e-9)
    assert final < objective(res.graph, parse_g2o(GOOD_G2O).poses)


def test_cli_relaxes_a_map_json_to_the_exact_minimum(tmp_path):
    g, xy = _small_map()
    src, out = tmp_path / "map.json", tmp_path / "out.json"
    noise = CompassNoise(1e-3, 2e-3, 1e-4)
    write_map_json(src, g, xy, noise, pinned_id=0)
    assert cli_main(["relax", str(src), "--out", str(out), "--method", "exact"]) == 0
    m = read_map_json(out)
    ref = solve_exact(g, xy, noise=noise)
    np.testing.assert_allclose(m.xy, ref.xy, atol=1e-9)
    assert m.noise == ref.noise


@pytest.mark.parametrize("text, suffix", [(f"VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0\n", ".g2o"),
                                          ('{"places": [{"id": 1, "x": 0, "y": 0}], "links": [{"from": 1}]}',
                                           ".json")])
def test_cli_bad_input_fails_with_the_line_and_writes_nothing(tmp_path, text, suffix):
    src, out = tmp_path / f"in{suffix}", tmp_path / f"out{suffix}"
    src.write_text(text)
    proc = _run(str(src), "--out", str(out))
    assert proc.returncode == 2
    assert f"{src}:" in proc.stderr and "error" in proc.stderr
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [src.name]


def test_cli_reaches_gtsam_objective_on_a_public_data_set(tmp_path):
    path = DATASETS / "intel.g2o"
    if not path.exists():
        pytest.skip(f"{path} not found (set RELAXMAP_DATASETS)")
    proc = _run(str(path), "--out", str(tmp_path / "intel.g2o"), "--method", "lm")
    assert proc.returncode == 0, proc.stderr
    assert "final objective (0.5 sum e^T Info e): 22.5021165" in proc.stdout  # datasets/README.md
