"""The physics stages: the inverse-physics Lightning module driven by a strategy.

>>> from toolkit.physics import InversePhysicsModule, PhysicsInput
"""

from toolkit.physics.inputs import PhysicsInput
from toolkit.physics.module import InversePhysicsModule

__all__ = ["InversePhysicsModule", "PhysicsInput"]
