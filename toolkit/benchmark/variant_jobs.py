"""Scene variants in a benchmark: every scene also runs as each named variant (issue #20).

``projo4d benchmark ... --variants NAME=JSON ...`` (:attr:`BenchmarkSpec.variants
<toolkit.benchmark.plan.BenchmarkSpec.variants>`: name -> :class:`~toolkit.synthetic.variants.VariantSpec`
fields) adds, per scene and variant:

* a ``variant`` job ``variant:<scene>@<name>`` writing ``BENCH/variants/<scene>/<name>/``
  (:func:`~toolkit.synthetic.variants.make_variant`), after the scene's ``generate`` job when the
  benchmark generates the scene;
* the scene's ``prepare`` and ``fit`` jobs again for the variant, as scene ``<scene>@<name>``
  (folders ``scenes/<scene>@<name>/`` and ``runs/<scene>@<name>/``), the ``prepare`` job after the
  ``variant`` job. The variant's spec is part of their fingerprints.

The tables show each variant as its own rows (column ``variant``) under the same material and
camera count; records, markers and ``job.json`` carry ``variant``. Without variants nothing of
the plan, the fingerprints or the tables changes.
"""

from __future__ import annotations

import copy
import re
from dataclasses import asdict
from pathlib import Path
from typing import Optional, Sequence

__all__ = ["VARIANT_SEP", "check_variants", "variant_scenes", "variant_job", "base_scene", "run_variant_job", "variant_job_done"]

#: separates a scene's name from its variant's in benchmark scene names (``neo_hookean/000@noisy``)
VARIANT_SEP = "@"
_NAME_OK = re.compile(r"^[A-Za-z0-9_.+-]+$")


def check_variants(variants: dict) -> dict:
    """Validate ``{name: VariantSpec fields}``; returns it with every spec complete (defaults filled in).

    Raises:
        BenchmarkError: a name that is not folder-safe (letters, digits, ``_.+-``) or a spec with
            an unknown field or a value out of range (the message names it).
    """
    from toolkit.benchmark.plan import BenchmarkError
    from toolkit.synthetic.variants import VariantError, VariantSpec

    out = {}
    for name, fields in (variants or {}).items():
        if not isinstance(name, str) or not _NAME_OK.match(name):
            raise BenchmarkError(f"variant name {name!r} must be letters, digits and _.+- only")
        try:
            out[name] = VariantSpec.from_dict(dict(fields) if isinstance(fields, dict) else fields).to_dict()
        except (VariantError, TypeError) as err:
            raise BenchmarkError(f"variant {name}: {err}") from None
    return out


def variant_scenes(scenes: Sequence, variants: dict, out: str | Path) -> list:
    """The variant :class:`~toolkit.benchmark.plan.SceneEntry` of every scene and variant, scene-major.

    Each has ``name = <scene>@<variant>``, ``path = out/variants/<scene>/<variant>`` and
    ``variant = {"name", "spec", "source", "base"}`` (``base``: the source scene entry as a dict).
    """
    from toolkit.benchmark.plan import SceneEntry

    root = Path(out).resolve() / "variants"
    entries = []
    for scene in scenes:
        for name, spec in variants.items():
            entries.append(SceneEntry(name=f"{scene.name}{VARIANT_SEP}{name}", path=str(root / scene.name / name),
                                      material=scene.material, config=scene.config,
                                      variant={"name": name, "spec": dict(spec), "source": scene.path, "base": asdict(scene)}))
    return entries


def base_scene(scene):
    """The scene a variant entry was made from (the entry itself when it is no variant)."""
    from toolkit.benchmark.plan import SceneEntry

    return SceneEntry(**scene.variant["base"]) if getattr(scene, "variant", None) else scene


def variant_job(scene, out: Path, log_file: str, fingerprint: str):
    """The ``variant`` :class:`~toolkit.benchmark.plan.Job` of a variant scene entry."""
    from toolkit.benchmark.plan import Job

    base = base_scene(scene)
    jid = f"variant:{scene.name}"
    return Job(id=jid, kind="variant", folder=scene.path, scene=scene.name, material=scene.material,
               depends=[f"generate:{base.name}"] if base.generate is not None else [], variant=scene.variant["name"],
               settings=copy.deepcopy({"source": scene.variant["source"], "spec": scene.variant["spec"]}),
               fingerprint=fingerprint, extra={"log": log_file})


def variant_job_done(job: dict) -> bool:
    """Whether a ``variant`` job's folder holds the variant of its source made with its spec."""
    from toolkit.synthetic.variants import VariantSpec, variant_is_complete

    s = job["settings"]
    return variant_is_complete(job["folder"], VariantSpec.from_dict(s["spec"]), s["source"])


def run_variant_job(job: dict) -> dict:
    """Write the variant (skipped when it is already complete); returns what was applied."""
    import json

    from toolkit.synthetic.variants import VARIANT_FILE, VariantSpec, make_variant

    if not variant_job_done(job):
        make_variant(job["settings"]["source"], job["folder"], VariantSpec.from_dict(job["settings"]["spec"]))
    applied = json.loads((Path(job["folder"]) / VARIANT_FILE).read_text())["applied"]
    return {"variant": job.get("variant"), "flipped_fraction": applied["masks"]["flipped_fraction"],
            "frames": applied["frames"]}


def variant_of(record: dict) -> Optional[str]:
    """The variant name of a table record or job marker (``None``: the scene as generated)."""
    return record.get("variant") or None
