"""A mixin for settings dataclasses: build from a dict (with a clear error) and back."""

from __future__ import annotations

from dataclasses import asdict, fields
from typing import Any, ClassVar, Mapping, TypeVar

__all__ = ["DictSettings"]

S = TypeVar("S", bound="DictSettings")


class DictSettings:
    """Mixin for ``@dataclass`` settings: :meth:`from_dict` (None -> defaults, an instance -> itself,
    a mapping -> validated fields) and :meth:`to_dict`. Subclasses set :attr:`settings_name`."""

    settings_name: ClassVar[str] = "settings"

    @classmethod
    def defaults(cls: type[S]) -> S:
        """The settings used when none are given."""
        return cls()

    @classmethod
    def from_dict(cls: type[S], d: "S | Mapping[str, Any] | None") -> S:
        if d is None:
            return cls.defaults()
        if isinstance(d, cls):
            return d
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown {cls.settings_name} {sorted(unknown)}; known: {sorted(names)}")
        return cls(**d)

    def to_dict(self) -> dict:
        return asdict(self)
