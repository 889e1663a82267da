"""benchmarks/combine_rounds.py: rounds of a benchmark joined into one table (later rounds win)."""

from __future__ import annotations

import json

import pytest

from tests.bench_helpers import load_benchmark_script


def _script():
    return load_benchmark_script("combine_rounds")


def _rec(scene, e_err, cd):
    return {"scene": scene, "material": "neo_hookean", "strategy": "progressive", "cameras": 3, "curriculum": "X",
            "metrics": {"cd": cd, "emd": 0.01}, "errors": {"E": e_err, "v0": 0.01}, "optimized": ["E"]}


def test_rounds_are_joined_and_a_later_round_replaces_a_fit(tmp_path, capsys):
    one, two = tmp_path / "one.json", tmp_path / "two.json"
    one.write_text(json.dumps({"settings": {"size": "full"}, "records": [_rec("neo_hookean/000", 0.6, 1.0),
                                                                        _rec("neo_hookean/001", 0.2, 2.0)]}))
    two.write_text(json.dumps({"settings": {}, "records": [_rec("neo_hookean/001", 0.1, 3.0)]}))  # a redo of /001
    summary = tmp_path / "run" / "summary.json"
    summary.parent.mkdir()
    summary.write_text(json.dumps({"material": "neo_hookean", "future": {"cd": 5.0, "emd": 0.02},
                                   "errors": {"error/E": 0.3, "error/v0": 0.02}}))
    mod = _script()
    assert mod.main([str(one), str(two), "--summary", f"neo_hookean/002={summary}", "--out", str(tmp_path / "out")]) == 0
    tables = json.loads((tmp_path / "out" / "tables.json").read_text())
    by_scene = {r["scene"]: r for r in tables["records"]}
    assert sorted(by_scene) == ["neo_hookean/000", "neo_hookean/001", "neo_hookean/002"]
    assert by_scene["neo_hookean/001"]["errors"]["E"] == 0.1 and by_scene["neo_hookean/002"]["metrics"]["cd"] == 5.0
    (row,) = tables["tables"][0]["rows"]
    assert row["n"] == 3 and row["values"]["mae:E"]["mean"] == pytest.approx((0.6 + 0.1 + 0.3) / 3)
    assert row["values"]["cd"]["mean"] == pytest.approx((1.0 + 3.0 + 5.0) / 3)
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["fits"] == {"neo_hookean": 3}


def test_bad_inputs_are_named(tmp_path, capsys):
    mod = _script()
    with pytest.raises(SystemExit) as stop:
        mod.main([str(tmp_path / "missing.json"), "--out", str(tmp_path / "out")])
    assert stop.value.code == 2 and "missing.json does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        mod.main([str(tmp_path), "--summary", "sand/001=nowhere.json", "--out", str(tmp_path / "out")])
    assert stop.value.code == 2 and "SCENE=PATH" in capsys.readouterr().err
    no_records = tmp_path / "t.json"
    no_records.write_text("{}")
    with pytest.raises(SystemExit, match="has no 'records'"):
        mod.main([str(no_records), "--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()


def test_a_combined_table_lists_its_rounds_flat(tmp_path):
    """Combining a combined table again names every original round once, oldest first (they used to nest one
    level deeper with each combination), and keeps each round's own settings in the JSON."""
    mod = _script()
    a, b, c = (tmp_path / f"{n}.json" for n in "abc")
    a.write_text(json.dumps({"settings": {"size": "full", "sim": {"dx": 0.02}}, "records": [_rec("neo_hookean/000", 0.6, 1.0)]}))
    b.write_text(json.dumps({"settings": {"size": "full", "sim": {"dx": 0.01}}, "records": [_rec("neo_hookean/001", 0.2, 2.0)]}))
    c.write_text(json.dumps({"settings": {"size": "small"}, "records": [_rec("neo_hookean/000", 0.1, 3.0)]}))
    assert mod.main([str(a), str(b), "--out", str(tmp_path / "ab")]) == 0
    assert mod.main([str(tmp_path / "ab" / "tables.json"), str(c), "--out", str(tmp_path / "abc")]) == 0
    tables = json.loads((tmp_path / "abc" / "tables.json").read_text())
    assert list(tables["settings"]["rounds"]) == [str(a), str(b), str(c)]
    assert tables["settings"]["rounds"][str(b)]["sim"] == {"dx": 0.01}
    md = (tmp_path / "abc" / "tables.md").read_text()
    assert f"- **rounds**: {a}, {b}, {c}\n" in md
    assert {r["scene"]: r["errors"]["E"] for r in tables["records"]} == {"neo_hookean/000": 0.1, "neo_hookean/001": 0.2}


def test_an_arm_stands_in_for_a_strategy(tmp_path, capsys):
    """``--stand-in held=progressive``: the round's held fits are counted as progressive's, its own progressive
    fits of those scenes are dropped, and a scene without a held fit keeps its progressive one."""
    mod = _script()
    old, new = tmp_path / "old.json", tmp_path / "new.json"
    old.write_text(json.dumps({"settings": {}, "records": [_rec("neo_hookean/000", 0.6, 1.0), _rec("neo_hookean/001", 0.5, 1.5)]}))
    new.write_text(json.dumps({"settings": {}, "records": [
        _rec("neo_hookean/000", 0.4, 2.0),
        {**_rec("neo_hookean/000", 0.1, 4.0), "strategy": "held"},
        _rec("neo_hookean/001", 0.3, 3.0)]}))
    assert mod.main([str(old), str(new), "--out", str(tmp_path / "plain")]) == 0
    assert mod.main([str(old), str(new), "--stand-in", "held=progressive", "--out", str(tmp_path / "whatif")]) == 0
    plain = json.loads((tmp_path / "plain" / "tables.json").read_text())
    whatif = json.loads((tmp_path / "whatif" / "tables.json").read_text())
    assert sorted((r["scene"], r["strategy"]) for r in plain["records"]) == [
        ("neo_hookean/000", "held"), ("neo_hookean/000", "progressive"), ("neo_hookean/001", "progressive")]
    by_scene = {r["scene"]: r for r in whatif["records"]}
    assert [r["strategy"] for r in whatif["records"]] == ["progressive", "progressive"]
    assert by_scene["neo_hookean/000"]["errors"]["E"] == 0.1 and by_scene["neo_hookean/000"]["stands_in_for"] == "held"
    assert by_scene["neo_hookean/001"]["errors"]["E"] == 0.3 and "stands_in_for" not in by_scene["neo_hookean/001"]
    (row,) = whatif["tables"][0]["rows"]
    assert row["values"]["mae:E"]["mean"] == pytest.approx((0.1 + 0.3) / 2)
    assert whatif["settings"]["stand-ins"] == {"held": "progressive"}
    for bad in ("held", "held=held", "=progressive"):
        with pytest.raises(SystemExit) as stop:
            mod.main([str(new), "--stand-in", bad, "--out", str(tmp_path / "bad")])
        assert stop.value.code == 2 and "ARM=STRATEGY" in capsys.readouterr().err
