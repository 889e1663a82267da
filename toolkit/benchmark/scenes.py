"""Where a benchmark's scenes come from: a generated suite on disk, a suite the benchmark generates
itself (one ``generate`` job per scene), or scene folders of any supported layout."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional, Sequence

from toolkit.benchmark.plan import BenchmarkError, SceneEntry, _safe_label

__all__ = ["only_scenes", "scenes_from_dirs", "scenes_from_suite", "scenes_to_generate"]


def scenes_from_suite(suite_dir: str | Path, families: Optional[Sequence[str]] = None,
                      max_per_family: Optional[int] = None) -> list[SceneEntry]:
    """The complete scenes of a generated suite (``projo4d generate suite``), material = family."""
    root = Path(suite_dir).resolve()
    index_path = root / "suite.json"
    if not index_path.is_file():
        raise BenchmarkError(f"{index_path} does not exist: write the suite with `projo4d generate suite --out {suite_dir}` "
                             "(or let the benchmark generate it)")
    index = json.loads(index_path.read_text())
    out, counts = [], {}
    for entry in index.get("scenes", []):
        fam = entry["family"]
        if families and fam not in families:
            continue
        if not entry.get("complete", True) or entry.get("error"):
            continue
        if max_per_family is not None and counts.get(fam, 0) >= max_per_family:
            continue
        counts[fam] = counts.get(fam, 0) + 1
        out.append(SceneEntry(name=entry["name"], path=str(root / entry["path"]), material=fam))
    if not out:
        raise BenchmarkError(f"{index_path} lists no complete scene" + (f" of families {list(families)}" if families else ""))
    return out


def scenes_to_generate(suite_dir: str | Path, families: Sequence[str], per_family: int, seed: int = 0, size: str = "full",
                       device: str = "cpu", spec_overrides: Optional[dict] = None, *,
                       shape_set: str = "pac_nerf") -> list[SceneEntry]:
    """Scenes of a suite that the benchmark generates itself (one ``generate`` job each, in
    parallel); the same draws as :func:`toolkit.synthetic.generate_suite` with these arguments.

    ``device`` is the Warp device *inside a worker* (``"cuda:0"`` on GPU workers: each worker sees
    its own GPU as device 0).
    """
    from toolkit.synthetic.spec import spec_to_dict
    from toolkit.synthetic.suite import FAMILY_RANGES, sample_scene_spec

    unknown = [f for f in families if f not in FAMILY_RANGES]
    if unknown:
        raise BenchmarkError(f"unknown material families {unknown}; choose from {', '.join(FAMILY_RANGES)}")
    root = Path(suite_dir).resolve()
    out = []
    for fam in families:
        for i in range(per_family):
            spec = sample_scene_spec(fam, i, seed, size, device, shape_set=shape_set, **(spec_overrides or {}))
            out.append(SceneEntry(name=f"{fam}/{i:03d}", path=str(root / fam / f"{i:03d}"), material=fam,
                                  generate={"spec": spec_to_dict(spec), "suite": {"root": str(root), "families": list(families),
                                                                                  "per_family": per_family, "seed": seed,
                                                                                  "size": size, "device": device,
                                                                                  "spec_overrides": dict(spec_overrides or {}),
                                                                                  "shape_set": shape_set}}))
    return out


def only_scenes(scenes: Sequence[SceneEntry], names: Sequence[str]) -> list[SceneEntry]:
    """The entries of ``scenes`` named in ``names`` (``family/index``, e.g. ``sand/002``), in the
    order of ``scenes``; a name that matches none raises :class:`BenchmarkError` listing the names."""
    known = {s.name for s in scenes}
    missing = [n for n in names if n not in known]
    if missing:
        raise BenchmarkError(f"--only names {missing}, which are not among this benchmark's scenes: "
                             f"{', '.join(sorted(known))}")
    wanted = set(names)
    return [s for s in scenes if s.name in wanted]


def scenes_from_dirs(dirs: Sequence[str | Path], material: Optional[str] = None) -> list[SceneEntry]:
    """Scene folders of any supported layout (PAC-NeRF, Spring-Gaus, GSO, generated); the material
    is ``material`` or the scene's recorded ground truth."""
    out, seen = [], {}
    for d in dirs:
        path = Path(d).resolve()
        if not path.is_dir():
            raise BenchmarkError(f"scene folder {d} does not exist")
        mat = material
        if mat is None:
            gt_path = path / "ground_truth.json"
            if gt_path.is_file():
                mat = json.loads(gt_path.read_text()).get("material")
        if not mat:
            raise BenchmarkError(f"{d}: give --material (the scene records none)")
        base = _safe_label(path.name)
        name = base if base not in seen else f"{base}-{seen[base] + 1}"
        seen[base] = seen.get(base, 0) + 1
        out.append(SceneEntry(name=name, path=str(path), material=str(mat)))
    return out
