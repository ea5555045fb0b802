"""``relaxmap worlds`` and the registration of ``relaxmap bench sim``."""

from __future__ import annotations

import json

from services import cli
from services.bench import BENCHES


def test_worlds_lists_the_builtin_worlds_with_sizes(capsys):
    assert cli.main(["worlds"]) == 0
    out = capsys.readouterr().out
    sizes = (("orebro-office", "45.5 x 11.5"), ("manchester-corridors", "33.5 x 32.5"), ("campus", "109.5 x 63.5"))
    for name, size in sizes:
        line = next(ln for ln in out.splitlines() if ln.startswith(name))
        assert size in line


def test_worlds_json_and_a_bad_file(capsys, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"walls": [[0, 0, 1, "x"]], "start": [0, 0, 0]}')
    assert cli.main(["worlds", "--json", str(bad)]) == 1
    captured = capsys.readouterr()
    rows = json.loads(captured.out)
    assert {r["name"] for r in rows} >= {"orebro-office", "manchester-corridors", "campus"}
    assert "walls[0][3] must be a number" in captured.err


def test_bench_sim_is_registered():
    assert BENCHES["sim"][0] == "services.bench.sim"
    args = cli.build_parser().parse_args(["bench", "sim", "--steps", "10", "--no-bus"])
    assert args.steps == 10 and args.no_bus


def test_bench_sim_runs_without_the_bus(capsys):
    assert cli.main(["bench", "sim", "--steps", "50", "--no-bus"]) == 0
    out = capsys.readouterr().out
    assert "steps/s" in out and "rays/s" in out
