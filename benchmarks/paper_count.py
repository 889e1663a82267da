"""How many of the paper's PAC-NeRF table entries a benchmark table reaches.

Reads a ``tables.json`` written by ``projo4d benchmark`` (or ``benchmarks/combine_rounds.py``) and
compares each strategy's mean per family with its row in the ProJo4D paper's PAC-NeRF table
(TMLR 2026, Table "Evaluation on PAC-NeRF dataset"): ``progressive`` with *ProJo4D*, ``joint``
with *Full Joint*, ``sequential`` with *GIC*. An entry counts when our mean is at or below the
paper's (every compared column is an error: CD ×1e3, EMD in m, v0 MAE in m/s, log10 MAEs of the
material parameters, the friction angle's MAE in degrees). The paper's table has 27 entries
per row: CD, EMD and v0 for all five families plus 12 material errors.

Usage::

    python benchmarks/paper_count.py docs/results/paper_size/round18_refine_stage0/combined/tables.json
    python benchmarks/paper_count.py T/tables.json --md count.md

Prints one JSON line per strategy (``{"strategy", "paper_row", "at_or_below", "of", "entries"}``);
``--md`` also writes a table of every entry.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional

#: The paper's PAC-NeRF table, per row name, family (our material name) and our column key.
PAPER_ROWS: dict[str, dict[str, dict[str, float]]] = {
    "ProJo4D": {
        "neo_hookean": {"cd": 0.913, "emd": 0.042, "mae:v0": 0.007, "mae:E": 0.124, "mae:nu": 0.048},
        "newtonian": {"cd": 0.339, "emd": 0.039, "mae:v0": 0.008, "mae:mu": 0.134, "mae:kappa": 1.425},
        "non_newtonian": {"cd": 0.473, "emd": 0.038, "mae:v0": 0.005, "mae:mu": 0.491, "mae:kappa": 0.462,
                          "mae:yield_stress": 0.144, "mae:plastic_viscosity": 0.463},
        "plasticine": {"cd": 1.103, "emd": 0.053, "mae:v0": 0.024, "mae:E": 0.742, "mae:nu": 0.084,
                       "mae:yield_stress": 0.144},
        "sand": {"cd": 0.264, "emd": 0.045, "mae:v0": 0.005, "mae:friction_angle": 4.998},
    },
    "Full Joint": {
        "neo_hookean": {"cd": 1.318, "emd": 0.049, "mae:v0": 0.020, "mae:E": 0.216, "mae:nu": 0.061},
        "newtonian": {"cd": 0.346, "emd": 0.040, "mae:v0": 0.008, "mae:mu": 0.294, "mae:kappa": 3.312},
        "non_newtonian": {"cd": 8.104, "emd": 0.099, "mae:v0": 0.080, "mae:mu": 2.315, "mae:kappa": 1.673,
                          "mae:yield_stress": 1.839, "mae:plastic_viscosity": 1.455},
        "plasticine": {"cd": 17.678, "emd": 0.124, "mae:v0": 0.092, "mae:E": 2.856, "mae:nu": 0.075,
                       "mae:yield_stress": 6.612},
        "sand": {"cd": 53.564, "emd": 0.223, "mae:v0": 0.046, "mae:friction_angle": 67.893},
    },
    "GIC": {
        "neo_hookean": {"cd": 5.512, "emd": 0.126, "mae:v0": 0.008, "mae:E": 0.189, "mae:nu": 0.123},
        "newtonian": {"cd": 0.537, "emd": 0.103, "mae:v0": 0.009, "mae:mu": 0.103, "mae:kappa": 3.180},
        "non_newtonian": {"cd": 0.689, "emd": 0.040, "mae:v0": 0.015, "mae:mu": 0.869, "mae:kappa": 0.725,
                          "mae:yield_stress": 0.069, "mae:plastic_viscosity": 0.519},
        "plasticine": {"cd": 2.012, "emd": 0.062, "mae:v0": 0.010, "mae:E": 1.597, "mae:nu": 0.134,
                       "mae:yield_stress": 0.327},
        "sand": {"cd": 20.262, "emd": 0.122, "mae:v0": 0.007, "mae:friction_angle": 6.785},
    },
}

#: Which paper row each of our strategies is compared with.
COMPARED_WITH = {"progressive": "ProJo4D", "joint": "Full Joint", "sequential": "GIC"}


def count(tables: dict, strategy: str, paper_row: Optional[str] = None) -> dict:
    """Entries of ``strategy``'s rows in ``tables`` (a benchmark ``tables.json``, 3 views) at or below
    the paper's ``paper_row`` (default: :data:`COMPARED_WITH`). A family or column missing from
    ``tables`` counts as not reached, so ``of`` is always the paper row's 27 entries.

    Returns ``{"strategy", "paper_row", "at_or_below", "of", "entries": [{"family", "column",
    "ours", "paper", "n", "reached"}]}`` (``ours`` ``None`` where the table has no value)."""
    row_name = paper_row or COMPARED_WITH[strategy]
    paper = PAPER_ROWS[row_name]
    ours: dict[str, dict] = {}
    for table in tables.get("tables", []):
        if int(table.get("cameras", 3)) != 3:
            continue
        for row in table.get("rows", []):
            if row.get("strategy") == strategy:
                ours[table["material"]] = row
    entries = []
    for family, columns in paper.items():
        row = ours.get(family, {})
        for column, value in columns.items():
            cell = (row.get("values") or {}).get(column) or {}
            mean = cell.get("mean")
            entries.append({"family": family, "column": column, "ours": mean, "paper": value,
                            "n": cell.get("n"), "reached": mean is not None and mean <= value})
    return {"strategy": strategy, "paper_row": row_name, "at_or_below": sum(e["reached"] for e in entries),
            "of": len(entries), "entries": entries}


def markdown(results: list[dict]) -> str:
    """One table: every entry with each strategy's mean and the paper's value (reached in bold)."""
    head = "| family | column | " + " | ".join(f"{r['strategy']} ({r['paper_row']})" for r in results) + " |"
    lines = [head, "|---|---|" + "---:|" * len(results)]
    for i, e in enumerate(results[0]["entries"]):
        cells = []
        for r in results:
            x = r["entries"][i]
            ours = "-" if x["ours"] is None else f"{x['ours']:.3g}"
            cells.append((f"**{ours}**" if x["reached"] else ours) + f" ({x['paper']:g})")
        lines.append(f"| {e['family']} | {e['column']} | " + " | ".join(cells) + " |")
    lines.append("| **at or below** | | " + " | ".join(f"**{r['at_or_below']} of {r['of']}**" for r in results) + " |")
    return "\n".join(lines) + "\n"


def main(argv: Optional[list[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("tables", type=Path, help="a tables.json of projo4d benchmark or combine_rounds.py")
    p.add_argument("--strategies", nargs="+", default=list(COMPARED_WITH), choices=list(COMPARED_WITH))
    p.add_argument("--md", type=Path, default=None, help="also write the per-entry table here")
    args = p.parse_args(argv)
    if not args.tables.is_file():
        raise SystemExit(f"{args.tables}: no such file (expected a tables.json of projo4d benchmark)")
    try:
        tables = json.loads(args.tables.read_text())
    except json.JSONDecodeError as err:
        raise SystemExit(f"{args.tables}: not JSON ({err}); expected a tables.json of projo4d benchmark") from None
    if not isinstance(tables, dict) or not isinstance(tables.get("tables"), list):
        raise SystemExit(f"{args.tables}: no 'tables' list; expected a tables.json of projo4d benchmark "
                         "or benchmarks/combine_rounds.py")
    results = [count(tables, s) for s in args.strategies]
    for r in results:
        print(json.dumps(r), flush=True)
    if args.md:
        from toolkit.atomic import write_text

        write_text(args.md, markdown(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
