"""Where the shipped YAML configs are: ``configs/`` of a checkout, ``toolkit/configs`` of a wheel.

The repository keeps its configs in the top-level ``configs/`` folder (one per dataset x material,
plus ``demo.yaml``). ``pyproject.toml`` maps that folder to the package ``toolkit.configs``, so a
wheel (``pip install projo4d``) carries them inside ``toolkit/``. An editable install
(``pip install -e .``: setuptools' editable finder does not import the mapped folder, which has no
``__init__.py``) and a plain checkout on ``sys.path`` find them next to the packages instead.
Code that needs a config asks :func:`configs_dir` or :func:`find_config`, never a path relative
to the source file.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

__all__ = ["configs_dir", "find_config", "list_configs"]

_PACKAGE = "toolkit.configs"


def _checkout_configs() -> Path | None:
    """``configs/`` beside the ``toolkit`` package when that is a source checkout (it has a
    ``pyproject.toml``), else ``None`` (a ``configs`` folder in site-packages is somebody else's)."""
    root = Path(__file__).resolve().parents[1]
    folder = root / "configs"
    if folder.is_dir() and (root / "pyproject.toml").is_file():
        return folder
    return None


def configs_dir() -> Path:
    """The folder holding the shipped ``*.yaml`` configs.

    Returns:
        The installed package data folder ``toolkit/configs`` when it is importable (wheel, or an
        editable install that maps it), else the checkout's top-level ``configs/``.

    Raises:
        FileNotFoundError: neither exists (a broken install), naming both places looked at.
    """
    try:
        spec = importlib.util.find_spec(_PACKAGE)
    except (ImportError, ValueError):
        spec = None
    if spec is not None:
        for location in spec.submodule_search_locations or []:
            folder = Path(location)
            if folder.is_dir() and any(folder.glob("*.yaml")):
                return folder
    folder = _checkout_configs()
    if folder is not None:
        return folder
    raise FileNotFoundError(
        f"projo4d's configs were not found: no package data {_PACKAGE!r} (toolkit/configs/*.yaml in the "
        f"installed package) and no checkout folder {Path(__file__).resolve().parents[1] / 'configs'}; "
        "reinstall projo4d (pip install projo4d, or pip install -e . in a clone)")


def list_configs() -> list[str]:
    """File names (``demo.yaml``, ``pacnerf_sand.yaml``, ...) of the shipped configs, sorted."""
    return sorted(p.name for p in configs_dir().glob("*.yaml"))


def find_config(name: str) -> Path:
    """The path of a shipped config by file name, with or without ``.yaml``.

    Args:
        name: e.g. ``"pacnerf_sand"`` or ``"pacnerf_sand.yaml"``.

    Raises:
        FileNotFoundError: no such config; the message lists the shipped ones.
    """
    file = name if name.endswith((".yaml", ".yml")) else f"{name}.yaml"
    path = configs_dir() / file
    if not path.is_file():
        raise FileNotFoundError(
            f"no shipped config {file!r} in {configs_dir()}; the shipped configs are: {', '.join(list_configs())}")
    return path
