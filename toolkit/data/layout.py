"""Picking the reader for a scene folder from the files present."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from toolkit.data.errors import DatasetError
from toolkit.data.pac_nerf import read_pac_nerf
from toolkit.data.scene import MultiViewScene
from toolkit.data.spring_gaus import read_spring_gaus, read_spring_gaus_real
from toolkit.data.vid2sim import read_vid2sim_gso

__all__ = ["READERS", "detect_layout", "load_scene"]

READERS: dict[str, Callable[..., MultiViewScene]] = {
    "pac_nerf": read_pac_nerf,
    "spring_gaus": read_spring_gaus,
    "spring_gaus_real": read_spring_gaus_real,
    "vid2sim_gso": read_vid2sim_gso,
}

# Checked in this order: GIC's PAC-NeRF preprocessing also writes transforms_train.json.
_MARKERS = (
    ("all_data.json", "pac_nerf", "PAC-NeRF"),
    ("camera.json", "spring_gaus", "Spring-Gaus synthetic"),
    ("transforms_train.json", "vid2sim_gso", "Vid2Sim GSO"),
    ("dynamic/cameras_calib.json", "spring_gaus_real", "Spring-Gaus real capture"),
)


def detect_layout(root: str | Path) -> str:
    """Name of the layout of ``root`` (a key of :data:`READERS`).

    Raises:
        DatasetError: No known marker file, listing every file looked for.
    """
    root = Path(root)
    for marker, layout, _ in _MARKERS:
        if (root / marker).is_file():
            return layout
    if (root.parent / "dynamic" / "cameras_calib.json").is_file():
        return "spring_gaus_real"  # <real_capture>/<object>, as ProJo4D passes it
    looked = ", ".join(f"{m} ({label})" for m, _, label in _MARKERS)
    where = root if root.exists() else f"{root} (which does not exist)"
    raise DatasetError(f"unknown dataset layout in {where}: looked for {looked}")


def load_scene(root: str | Path, layout: str = "auto", **kwargs) -> MultiViewScene:
    """Read the scene at ``root`` with the reader of ``layout`` (``"auto"``: detected).

    Args:
        root: Scene folder.
        layout: ``"auto"`` or one of :data:`READERS`.
        **kwargs: Passed to the reader (e.g. ``include_nvs`` for Vid2Sim, ``obj_name`` for
            Spring-Gaus real capture).
    """
    name = detect_layout(root) if layout == "auto" else layout
    if name not in READERS:
        raise DatasetError(f"unknown layout {layout!r}: choose 'auto' or one of {sorted(READERS)}")
    return READERS[name](root, **kwargs)
