"""Errors of the synthetic scene generator (all are ``ValueError`` subclasses with a message saying what to fix)."""

from __future__ import annotations

__all__ = ["SyntheticError", "SpecError", "MeshFileError", "FramingError"]


class SyntheticError(ValueError):
    """Base class of the generator's errors."""


class SpecError(SyntheticError):
    """A scene specification is invalid: unknown shape/material/effect, a value out of range,
    an object below the ground, ..."""


class MeshFileError(SpecError):
    """A user-given mesh file is missing, unreadable, empty, non-finite or not closed."""


class FramingError(SpecError):
    """Part of the object's trajectory leaves the image of some camera."""
