"""Material registry: one module per constitutive model.

>>> from materials import get_material, MATERIALS
>>> m = get_material("plasticine", yield_rule="pacnerf")
>>> MATERIALS.names()
['kelvin_voigt', 'neo_hookean', 'neo_hookean_simplicits', 'newtonian', 'non_newtonian', 'plasticine', 'sand']

Third-party models register through the ``projo4d.materials`` entry-point group.
"""

from __future__ import annotations

from typing import Any

from materials.base import Material, MaterialError, MaterialParam, lame_parameters
from toolkit.registry import Registry

MATERIALS: Registry[type[Material]] = Registry(
    "material",
    entry_point_group="projo4d.materials",
    builtin_modules=(
        "materials.neo_hookean",
        "materials.neo_hookean_simplicits",
        "materials.newtonian",
        "materials.non_newtonian",
        "materials.plasticine",
        "materials.sand",
        "materials.kelvin_voigt",
    ),
)
register_material = MATERIALS.register

__all__ = ["MATERIALS", "register_material", "get_material", "Material", "MaterialParam", "MaterialError", "lame_parameters"]


def get_material(name: str | Material, **options: Any) -> Material:
    """A material instance from its registered name (or the instance itself, returned as is)."""
    if isinstance(name, Material):
        if options:
            raise MaterialError("options can only be given with a material name, not with an instance")
        return name
    return MATERIALS.get(name)(**options)
