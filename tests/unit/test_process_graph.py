"""The shipped process graph is sound, and the checks catch what is wrong with a graph."""

from __future__ import annotations

import importlib.util
import json

import pytest

from messages import topics
from services.launch.graph import GraphError, ProcessGraph, check_graph, expand_args, load_graph
from services.runtime import deploy_file


def test_shipped_graph_is_sound():
    graph = load_graph(deploy_file("graph.json"))
    assert set(graph.names()) == {"sensor_sim", "dead_reckoning", "place_recognizer", "explorer", "relaxer",
                                  "recorder"}
    known = topics.all_topics()
    for s in graph.services:
        assert importlib.util.find_spec(s.module) is not None, s.module
        assert importlib.util.find_spec(s.module + ".__main__") is not None, s.module
        for t in (*s.inputs, *s.outputs):
            assert t in known
    values = {"world": "w", "seed": "3", "out": "/o", "max_sim_time": "10", "viewer": "", "recording": "/o/r.rrd",
              "recording_id": "id",
              **{f"resume_{s.name}": [] for s in graph.services}}
    args = {s.name: expand_args(s, values) for s in graph.services}
    assert args["relaxer"] == ["--store", "/o/map.sqlite", "--seed", "3"]
    assert args["recorder"] == ["--rrd", "/o/r.rrd", "--recording-id", "id"]
    assert args["explorer"] == ["--seed", "3", "--state", "/o/state/explorer"]
    values["resume_explorer"] = ["--resume", "--first-place-id", "7"]
    assert expand_args(next(s for s in graph.services if s.name == "explorer"), values) == [
        "--seed", "3", "--state", "/o/state/explorer", "--resume", "--first-place-id", "7"]


def _graph(services) -> ProcessGraph:
    import msgspec

    return msgspec.convert({"services": services}, ProcessGraph)


def test_checks_find_problems():
    g = _graph([
        {"name": "a", "module": "m", "inputs": ["odometry"], "outputs": ["nonsense"]},
        {"name": "a", "module": "m", "restart": {"policy": "sometimes"}},
    ])
    problems = " | ".join(check_graph(g))
    assert "service 'a' appears twice" in problems
    assert "'nonsense' is not a key expression" in problems
    assert "input 'odometry' has no producer" in problems
    assert "restart policy 'sometimes'" in problems


def test_bad_files(tmp_path):
    bad = tmp_path / "g.json"
    bad.write_text("{not json")
    with pytest.raises(GraphError, match="g.json"):
        load_graph(bad)
    bad.write_text(json.dumps({"services": [{"name": "a", "module": "m", "colour": "red"}]}))
    with pytest.raises(GraphError, match="colour"):
        load_graph(bad)
    with pytest.raises(GraphError, match="No such file"):
        load_graph(tmp_path / "missing.json")
