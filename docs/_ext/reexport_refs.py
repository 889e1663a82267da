"""Resolve Python cross-references to re-exported and unqualified names.

The API reference documents each object once, where it is defined
(``toolkit.mpm.simulator.MPMSimulator``), but docstrings refer to objects the way users import
them (``toolkit.mpm.MPMSimulator``, ``materials.Material``) or by their bare name inside their
own package (``DatasetError``). When Sphinx's Python domain finds no target, this handler looks
for exactly one documented object that

1. ends with ``.<target>`` (bare or partly qualified names, ``MPMSimulator.stable_substeps``), or
2. lives under the target's package prefix and has the target's last name component
   (``toolkit.mpm.MPMSimulator`` -> ``toolkit.mpm.simulator.MPMSimulator``),

and links to it. Ambiguous or unknown names (``torch.Tensor``: there is no intersphinx, the build
uses no network) stay unresolved, which is not a warning unless Sphinx runs in nitpicky mode.
"""

from __future__ import annotations

from typing import Any

from sphinx.util.nodes import make_refnode


def _unique(names: list[str]) -> str | None:
    return names[0] if len(names) == 1 else None


def resolve(app: Any, env: Any, node: Any, contnode: Any):
    if node.get("refdomain") != "py":
        return None
    target = str(node.get("reftarget", "")).lstrip("~.")
    if not target:
        return None
    objects = env.get_domain("py").objects
    name = _unique([n for n in objects if n.endswith("." + target)])
    if name is None and "." in target:
        package, last = target.rsplit(".", 1)
        name = _unique([n for n in objects if n.startswith(package + ".") and n.endswith("." + last)])
    if name is None:
        return None
    entry = objects[name]
    return make_refnode(app.builder, node["refdoc"], entry.docname, entry.node_id, contnode, name)


def setup(app: Any) -> dict:
    app.connect("missing-reference", resolve)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
