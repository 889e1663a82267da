"""``projo4d materials``: list the registered materials, effects and renderers with their parameters."""

from __future__ import annotations

import argparse

__all__ = ["configure", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print machine-readable JSON instead of tables")


def describe() -> dict:
    """Everything registered, as plain data."""
    from materials import MATERIALS, get_material
    from renderers import RENDERERS
    from toolkit.mpm.effects import EFFECTS, get_effect

    info: dict = {"materials": {}, "effects": {}, "renderers": RENDERERS.names()}
    for name in MATERIALS.names():
        m = get_material(name)
        info["materials"][name] = [
            {"name": p.name, "default": p.default, "transform": p.transform, "range": [p.low, p.high],
             "fit_range": list(p.fit_bounds), "optimized": p.optimize, "units": p.units, "description": p.description}
            for p in m.params
        ]
    for name in EFFECTS.names():
        e = get_effect(name)
        info["effects"][name] = [
            {"name": p.name, "default": p.default, "range": [p.low, p.high], "optimized": p.optimize, "units": p.units,
             "description": p.description}
            for p in e.params
        ]
    try:
        from strategies import STRATEGIES

        info["strategies"] = STRATEGIES.names()
    except ImportError:
        pass
    return info


def run(args: argparse.Namespace) -> int:
    import json

    info = describe()
    if args.json:
        print(json.dumps(info, indent=2, default=str))
        return 0
    from rich.console import Console
    from rich.table import Table

    console = Console()
    for kind in ("materials", "effects"):
        table = Table(title=kind, show_lines=False)
        for col in ("name", "parameter", "default", "optimized as", "range", "units", "description"):
            table.add_column(col)
        for name, params in info[kind].items():
            for i, p in enumerate(params):
                rng = f"[{p['range'][0]:g}, {p['range'][1]:g}]"
                if p.get("fit_range", p["range"]) != p["range"]:
                    rng += f", fitted in [{p['fit_range'][0]:g}, {p['fit_range'][1]:g}]"
                table.add_row(name if i == 0 else "", p["name"], f"{p['default']:g}", p.get("transform", "linear"),
                              rng, p["units"], p["description"])
        console.print(table)
    console.print("renderers: " + ", ".join(info["renderers"]))
    if "strategies" in info:
        console.print("strategies: " + ", ".join(info["strategies"]))
    return 0
