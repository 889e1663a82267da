"""benchmarks/paper_count.py: a benchmark table's means against the paper's PAC-NeRF rows."""

from __future__ import annotations

import json

import pytest

from tests.bench_helpers import load_benchmark_script


def _script():
    return load_benchmark_script("paper_count")


def _table(material, strategy, values, cameras=3):
    return {"material": material, "cameras": cameras,
            "rows": [{"strategy": strategy, "values": {k: {"mean": v, "n": 5} for k, v in values.items()}}]}


def test_every_paper_row_has_the_27_entries_of_the_table():
    mod = _script()
    for row in mod.PAPER_ROWS.values():
        assert sum(len(cols) for cols in row.values()) == 27
        assert sorted(row) == ["neo_hookean", "newtonian", "non_newtonian", "plasticine", "sand"]


def test_counts_entries_at_or_below_the_paper_and_missing_ones_as_not_reached(tmp_path, capsys):
    mod = _script()
    tables = {"tables": [
        # sand: CD equal to the paper's (counts), EMD above, v0 below, friction angle above
        _table("sand", "progressive", {"cd": 0.264, "emd": 0.05, "mae:v0": 0.004, "mae:friction_angle": 6.0}),
        # elastic: log E below ProJo4D's 0.124; the 6-view table is not compared
        _table("neo_hookean", "progressive", {"mae:E": 0.1}),
        _table("neo_hookean", "progressive", {"cd": 0.0, "emd": 0.0}, cameras=6),
        _table("sand", "joint", {"mae:friction_angle": 60.0}),
    ]}
    res = mod.count(tables, "progressive")
    assert res["paper_row"] == "ProJo4D" and res["of"] == 27
    reached = {(e["family"], e["column"]) for e in res["entries"] if e["reached"]}
    assert reached == {("sand", "cd"), ("sand", "mae:v0"), ("neo_hookean", "mae:E")}
    assert res["at_or_below"] == 3
    assert mod.count(tables, "joint")["at_or_below"] == 1  # 60° against Full Joint's 67.9°
    path = tmp_path / "tables.json"
    path.write_text(json.dumps(tables))
    assert mod.main([str(path), "--strategies", "progressive", "--md", str(tmp_path / "c.md")]) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["at_or_below"] == 3
    assert "**3 of 27**" in (tmp_path / "c.md").read_text()


def test_a_missing_or_wrong_file_is_named(tmp_path):
    with pytest.raises(SystemExit, match="nope.json"):
        _script().main([str(tmp_path / "nope.json")])
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(SystemExit, match="bad.json: not JSON"):
        _script().main([str(bad)])
    bad.write_text(json.dumps({"records": []}))  # a summary, not a tables.json
    with pytest.raises(SystemExit, match="bad.json: no 'tables' list"):
        _script().main([str(bad)])
