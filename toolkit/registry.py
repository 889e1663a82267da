"""A small generic name -> class registry with lazily loaded third-party plugins.

Each of projo4d's registries (materials, renderers, strategies) is one :class:`Registry`
filled by a decorator in the module that defines the entry::

    MATERIALS = Registry("material", entry_point_group="projo4d.materials")

    @MATERIALS.register("neo_hookean")
    class NeoHookean(Material): ...

Third-party packages add entries without editing projo4d by declaring an entry point in
their own ``pyproject.toml``::

    [project.entry-points."projo4d.materials"]
    my_foam = "my_pkg.foam:Foam"

Entry points are only imported when a name is looked up that is not registered yet (or when
the full list is asked for), so ``import toolkit`` stays light.
"""

from __future__ import annotations

import difflib
import importlib.metadata
from typing import Callable, Generic, Iterator, TypeVar

T = TypeVar("T")

__all__ = ["Registry", "UnknownNameError"]


class UnknownNameError(KeyError):
    """Raised by :meth:`Registry.get` for a name that no entry (built-in or plugin) has."""

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message

    def __str__(self) -> str:  # KeyError would otherwise print the repr of the message
        return self.message


class Registry(Generic[T]):
    """Maps short names to classes (or factories).

    Args:
        kind: what the entries are, used in error messages ("material", "renderer", ...).
        entry_point_group: the ``importlib.metadata`` entry-point group scanned for plugins.
        builtin_modules: modules that register the built-in entries when imported; they are
            imported on the first lookup, so importing the registry itself stays cheap.
    """

    def __init__(self, kind: str, entry_point_group: str | None = None, builtin_modules: tuple[str, ...] = (),
                 plural: str | None = None):
        self.kind = kind
        self.plural = plural or (kind[:-1] + "ies" if kind.endswith("y") else kind + "s")
        self.entry_point_group = entry_point_group
        self.builtin_modules = tuple(builtin_modules)
        self._entries: dict[str, T] = {}
        self._plugins_loaded = False
        self._builtins_loaded = not self.builtin_modules

    def _load_builtins(self) -> None:
        if self._builtins_loaded:
            return
        self._builtins_loaded = True
        import importlib

        for mod in self.builtin_modules:
            importlib.import_module(mod)

    def register(self, name: str, *, overwrite: bool = False) -> Callable[[T], T]:
        """Decorator that registers ``obj`` under ``name`` and returns it unchanged."""
        if not isinstance(name, str) or not name:
            raise ValueError(f"a {self.kind} name must be a non-empty string, got {name!r}")

        def decorator(obj: T) -> T:
            if name in self._entries and not overwrite and self._entries[name] is not obj:
                raise ValueError(
                    f"{self.kind} {name!r} is already registered to {self._entries[name]!r}; "
                    "pass overwrite=True to replace it"
                )
            self._entries[name] = obj
            if isinstance(obj, type) and not obj.__dict__.get("registry_name"):
                try:
                    obj.registry_name = name  # type: ignore[attr-defined]
                except (AttributeError, TypeError):
                    pass
            return obj

        return decorator

    def _load_plugins(self, force: bool = False) -> None:
        if (self._plugins_loaded and not force) or self.entry_point_group is None:
            self._plugins_loaded = True
            return
        self._plugins_loaded = True
        for ep in importlib.metadata.entry_points(group=self.entry_point_group):
            if ep.name in self._entries:
                continue
            try:
                obj = ep.load()
            except Exception as exc:  # a broken plugin must not break the built-ins
                import warnings

                warnings.warn(
                    f"could not load {self.kind} plugin {ep.name!r} from entry point "
                    f"{ep.value!r} (group {self.entry_point_group!r}): {exc}",
                    stacklevel=2,
                )
                continue
            if isinstance(obj, type) and not obj.__dict__.get("registry_name"):
                try:  # a plugin class (possibly a subclass of a built-in) is known by its entry-point name
                    obj.registry_name = ep.name  # type: ignore[attr-defined]
                except (AttributeError, TypeError):
                    pass
            self._entries.setdefault(ep.name, obj)

    def get(self, name: str) -> T:
        """Return the entry called ``name``.

        Raises:
            UnknownNameError: listing the known names and the closest matches.
        """
        if name in self._entries:
            return self._entries[name]
        self._load_builtins()
        if name in self._entries:
            return self._entries[name]
        # plugins installed after the first scan are found on a miss
        self._load_plugins(force=True)
        if name in self._entries:
            return self._entries[name]
        known = sorted(self._entries)
        close = difflib.get_close_matches(str(name), known, n=3, cutoff=0.5)
        hint = f" Did you mean {', '.join(repr(c) for c in close)}?" if close else ""
        raise UnknownNameError(
            f"unknown {self.kind} {name!r}.{hint} Known {self.plural}: {', '.join(known) or '(none)'}."
        )

    def names(self) -> list[str]:
        """All registered names, plugins included, sorted."""
        self._load_builtins()
        self._load_plugins()
        return sorted(self._entries)

    def __contains__(self, name: object) -> bool:
        if name in self._entries:
            return True
        self._load_builtins()
        self._load_plugins()
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def __len__(self) -> int:
        return len(self.names())

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, entries={sorted(self._entries)})"
