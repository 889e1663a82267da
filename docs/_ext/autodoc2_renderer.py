"""sphinx-autodoc2's reStructuredText renderer with two presentation fixes.

* Values of module and class attributes are shown as their **source text**, read from the file
  at the line range autodoc2 records. autodoc2's own value extraction goes to ``None`` when
  there is no value (a bare annotation such as a dataclass field, which would read ``= None``)
  or when it does not understand the expression, shows a call as the quoted string
  ``'name(...)'``, and truncates a tuple at its first non-constant element (a tuple of
  ``MaterialParam(...)`` calls would read ``= ()``). Attributes without a value show none; long
  values are shortened with an ellipsis.
* A class whose ``__init__`` has no docstring of its own would get an empty "Initialization"
  heading: it is left out.
"""

from __future__ import annotations

import ast
import functools
import typing as t
from pathlib import Path

from autodoc2.render.rst_ import RstRenderer

__all__ = ["Renderer", "MAX_VALUE_CHARS"]

MAX_VALUE_CHARS = 100


@functools.lru_cache(maxsize=256)
def _source_lines(path: str) -> tuple[str, ...]:
    return tuple(Path(path).read_text(encoding="utf-8").splitlines())


def _assigned_value(lines: t.Sequence[str], first: int, last: int) -> str | None:
    """Source text of the value assigned on lines ``first..last`` (1-based), or None."""
    text = "\n".join(lines[first - 1 : last])
    try:
        tree = ast.parse(text.strip())  # class attributes are indented
    except SyntaxError:
        return None
    if len(tree.body) != 1 or not isinstance(tree.body[0], (ast.Assign, ast.AnnAssign)):
        return None
    node = tree.body[0].value
    if node is None:
        return None  # a bare annotation: no value
    segment = ast.get_source_segment(text.strip(), node)
    if segment is None:
        return None
    segment = " ".join(segment.split())
    if len(segment) > MAX_VALUE_CHARS:
        segment = segment[: MAX_VALUE_CHARS - 3].rstrip() + "..."
    return segment


class Renderer(RstRenderer):
    """See the module docstring."""

    def _value_text(self, item: t.Any) -> str | None:
        rng = item.get("range")
        if not rng:
            return None
        for ancestor in self._db.get_ancestors(item["full_name"], include_self=False):
            if ancestor is not None and "file_path" in ancestor:
                try:
                    return _assigned_value(_source_lines(ancestor["file_path"]), *rng)
                except (OSError, UnicodeDecodeError):
                    return None
        return None

    def render_data(self, item: t.Any) -> t.Iterable[str]:
        value = self._value_text(item)
        for line in super().render_data(item):
            if line.startswith("   :value: "):
                if value is None:
                    continue
                line = f"   :value: {value}"
            yield line

    def render_class(self, item: t.Any) -> t.Iterable[str]:
        lines = list(super().render_class(item))
        init = self.get_item(f"{item['full_name']}.__init__")
        if init is None or (init.get("doc") or "").strip():
            return lines
        try:
            i = lines.index("   .. rubric:: Initialization")
        except ValueError:
            return lines
        # the rubric, a blank line, the docstring directive, its options, a blank line
        j = i + 1
        while j < len(lines) and lines[j] == "":
            j += 1
        if j < len(lines) and lines[j].startswith("   .. autodoc2-docstring::"):
            j += 1
            while j < len(lines) and lines[j].startswith("      :"):
                j += 1
        while j < len(lines) and lines[j] == "":
            j += 1
        return lines[:i] + lines[j:]
