"""What a benchmark runs: scenes x camera counts x strategies, as jobs with dependencies.

Three kinds of job:

* ``generate``: write one synthetic scene of a suite (only when the benchmark generates its
  suite, see :func:`toolkit.benchmark.scenes.scenes_to_generate`);
* ``prepare``: stage 0 + particle continuum (or the oracle geometry) for one scene and one camera
  set, written **once** as ``BENCH/scenes/<scene>/cams<k>/physics_input.pt``;
* ``fit``: one strategy's physics fit, prediction, metrics and report in
  ``BENCH/runs/<scene>/cams<k>/<strategy>/``, starting from that shared ``physics_input.pt``
  (linked into the run folder), so every strategy is compared on the identical 4D representation
  (as the paper does).

Folder layout::

    BENCH/
      benchmark.json                      the plan's settings (strategies, cameras, overrides)
      progress.jsonl                      every event the runner printed
      scenes/<scene>/cams<k>/             a pipeline run folder up to physics_input.pt (+ job.json)
      runs/<scene>/cams<k>/<strategy>/    a pipeline run folder (physics/, evaluation/, report/,
                                          summary.json) + job.json
      logs/<job>.log                      each job's output
      tables/                             tables.md, tables.json and the comparison figures

Each job folder gets a ``job.json`` marker (status, fingerprint of its settings, wall time of
every attempt). A rerun skips jobs whose marker says ``done`` with the same fingerprint; other
jobs resume from their checkpoints.

Settings of a scene come from the config ``configs/<dataset>_*.yaml`` of its material
(:func:`config_for`; ``dataset`` is ``synthetic`` for suites), then the size preset
(:data:`BENCH_SIZES`), then the command line's overrides. Iteration overrides (``stage1_iterations``, ``stage2_iterations``,
``appearance_iterations``) go to every strategy that has that option; ``joint`` and ``cyclic``
take their total (stage 1 + stage 2).
"""

from __future__ import annotations

import copy
import hashlib
import json
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional, Union

__all__ = [
    "BENCH_SIZES",
    "BenchmarkError",
    "BenchmarkSpec",
    "Job",
    "SceneEntry",
    "StrategyEntry",
    "camera_subset",
    "parse_strategy",
    "plan_benchmark",
    "scaled_stage0",
    "config_for",
]

#: Benchmark size presets: RunSettings overrides and strategy iteration counts.
#: ``full`` keeps the configs as they are (GIC's 40k-iteration stage 0, the paper's iteration counts,
#: sequential's 40k-iteration appearance stage unless ``appearance_iterations`` is given);
#: ``small`` is CPU-sized (tutorials, smoke tests): tiny stage 0, a 0.04 m grid with the config's
#: substeps scaled to keep their time step per cell (e.g. 100 at 0.02 m -> 50), shorter stages.
BENCH_SIZES: dict[str, dict[str, dict]] = {
    "full": {"settings": {}, "iterations": {}},
    "small": {
        # substeps: the config's, scaled by its dx / 0.04 (the same Courant number), see scene_settings
        "settings": {"stage0": "tiny", "sim": {"dx": 0.04}},
        "iterations": {"stage1_iterations": 30, "stage2_iterations": 60, "appearance_iterations": 300},
    },
}

#: the RunSettings fields that decide ``physics_input.pt`` (shared by every strategy)
PREPARE_FIELDS = ("scene", "cameras", "n_train", "downscale", "stage0", "geometry", "continuum", "renderer", "seed")

ITERATION_KEYS = ("stage1_iterations", "stage2_iterations", "appearance_iterations")

#: the benchmark's periodic evaluation: 5 points per stage, EMD on 1024 points (the final
#: evaluation uses the evaluator's 2048; an exact 2048-point EMD costs ~0.35 s a frame on a CPU)
DEFAULT_PERIODIC_EVAL = {"per_stage": 5, "emd_points": 1024}


class BenchmarkError(ValueError):
    """A benchmark that cannot be planned or resumed as asked (the message says what to change)."""


@dataclass
class SceneEntry:
    """One scene of a benchmark.

    Attributes:
        name: unique name, also its folder under ``scenes/`` and ``runs/`` (``family/000``).
        path: the scene folder (absolute).
        material: registered material name of the fit.
        generate: a :class:`~toolkit.synthetic.SceneSpec` as a dict when the benchmark writes the
            scene itself (a ``generate`` job), else ``None``.
        config: YAML config of this scene (default: the dataset's config of its material).
        variant: for a variant of another scene (:mod:`toolkit.benchmark.variant_jobs`), its
            ``name``, ``spec``, ``source`` folder and ``base`` entry; else ``None``.
    """

    name: str
    path: str
    material: str
    generate: Optional[dict] = None
    config: Optional[str] = None
    variant: Optional[dict] = None


@dataclass
class StrategyEntry:
    """A strategy of the comparison: ``label`` (its folder and table row), ``spec`` (registered
    name, schedule string or ``package.module.Class``) and its ``options``."""

    label: str
    spec: str
    options: dict = field(default_factory=dict)


@dataclass
class BenchmarkSpec:
    """Everything that defines a benchmark's jobs.

    Attributes:
        scenes: the scenes.
        strategies: the strategies compared (:func:`parse_strategy` turns strings into entries).
        cameras: camera counts; one table per count, and a Table-8 style ablation when several.
        size: ``"full"`` or ``"small"`` (:data:`BENCH_SIZES`).
        dataset: config prefix: the scene's material picks ``configs/<dataset>_*.yaml``.
        config: one YAML config for every scene instead (RunSettings fields or the
            ``run:``/``model:`` layout of ``configs/``).
        overrides: RunSettings fields applied last (``sim`` and ``model_options`` are merged key by key).
        iterations: ``stage1_iterations``, ``stage2_iterations``, ``appearance_iterations``.
        periodic_eval: :class:`~toolkit.physics.periodic_eval.PeriodicEvaluation` arguments, or
            ``None`` to switch it off.
        checkpoint_every: physics iterations between checkpoints (a stopped job also saves
            where it stopped).
        variants: ``{name: VariantSpec fields}``: every scene also runs as each variant
            (:mod:`toolkit.benchmark.variant_jobs`); empty: none.
    """

    scenes: list[SceneEntry]
    strategies: list[StrategyEntry]
    cameras: list[int] = field(default_factory=lambda: [3])
    size: str = "full"
    dataset: str = "synthetic"
    config: Optional[str] = None
    overrides: dict = field(default_factory=dict)
    iterations: dict = field(default_factory=dict)
    periodic_eval: Optional[dict] = field(default_factory=lambda: dict(DEFAULT_PERIODIC_EVAL))
    checkpoint_every: int = 200
    variants: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.strategies = [s if isinstance(s, StrategyEntry) else parse_strategy(s) for s in self.strategies]
        if self.size not in BENCH_SIZES:
            raise BenchmarkError(f"size must be one of {sorted(BENCH_SIZES)}, got {self.size!r}")
        if not self.scenes:
            raise BenchmarkError("a benchmark needs at least one scene")
        if not self.strategies:
            raise BenchmarkError("a benchmark needs at least one strategy")
        labels = [s.label for s in self.strategies]
        if len(set(labels)) != len(labels):
            raise BenchmarkError(f"strategy labels must be unique, got {labels}; write LABEL=SPEC to tell them apart")
        names = [s.name for s in self.scenes]
        if len(set(names)) != len(names):
            raise BenchmarkError(f"scene names must be unique, got {names}")
        if not self.cameras or any(not isinstance(c, int) or c < 1 for c in self.cameras):
            raise BenchmarkError(f"camera counts must be integers >= 1, got {self.cameras}")
        unknown = set(self.iterations) - set(ITERATION_KEYS)
        if unknown:
            raise BenchmarkError(f"unknown iteration keys {sorted(unknown)}; known: {list(ITERATION_KEYS)}")
        if self.variants:
            from toolkit.benchmark.variant_jobs import check_variants

            self.variants = check_variants(self.variants)

    def to_dict(self) -> dict:
        return json.loads(json.dumps(asdict(self)))

    @classmethod
    def from_dict(cls, d: dict) -> "BenchmarkSpec":
        d = dict(d)
        d["scenes"] = [SceneEntry(**s) for s in d["scenes"]]
        d["strategies"] = [StrategyEntry(**s) for s in d["strategies"]]
        return cls(**d)


@dataclass
class Job:
    """One unit of work (see the module docstring).

    Attributes:
        id: ``generate:<scene>``, ``variant:<scene>``, ``prepare:<scene>:cams<k>`` or
            ``fit:<scene>:cams<k>:<strategy>``.
        kind: ``generate``, ``variant``, ``prepare`` or ``fit``.
        folder: where the job writes (absolute).
        scene, material, cameras, strategy, variant: what it is about (``None`` where not applicable).
        depends: ids of the jobs that must be done first.
        settings: :class:`~toolkit.run_settings.RunSettings` fields (``prepare``, ``fit``) or
            ``{"spec": ...}`` (``generate``).
        fingerprint: hash of what decides the job's result (its marker must match to be skipped).
        extra: ``physics_input`` (the shared file, ``fit``), ``periodic_eval``,
            ``checkpoint_every``, ``log`` (the log file).
    """

    id: str
    kind: str
    folder: str
    scene: str
    material: str
    cameras: Optional[int] = None
    strategy: Optional[str] = None
    depends: list[str] = field(default_factory=list)
    settings: dict = field(default_factory=dict)
    fingerprint: str = ""
    extra: dict = field(default_factory=dict)
    variant: Optional[str] = None

    def to_dict(self) -> dict:
        return json.loads(json.dumps(asdict(self)))


# ------------------------------------------------------------------------------------ strategies
_LABEL_OK = re.compile(r"[^A-Za-z0-9_.+-]+")


def _safe_label(text: str) -> str:
    return _LABEL_OK.sub("_", text).strip("_") or "strategy"


def parse_strategy(text: str, options: Optional[dict] = None) -> StrategyEntry:
    """``"progressive"``, ``"LABEL=SPEC"`` (e.g. ``"xas=XAS:100@3,XASM:150"``) or a schedule string.

    A schedule string without a label is labelled by a folder-safe form of itself.
    """
    label, spec = None, text.strip()
    m = re.match(r"^([A-Za-z0-9_.+-]+)=(.+)$", spec)
    if m and ":" not in m.group(1):
        label, spec = m.group(1), m.group(2).strip()
    if not spec:
        raise BenchmarkError(f"empty strategy in {text!r}")
    return StrategyEntry(label=label or _safe_label(spec), spec=spec, options=dict(options or {}))


def _strategy_class(spec: str):
    """The Strategy class of a registered name or class path (``None`` for a schedule string)."""
    if ":" in spec:
        return None
    if "." in spec:
        import importlib

        module_name, _, cls_name = spec.rpartition(".")
        try:
            return getattr(importlib.import_module(module_name), cls_name)
        except (ImportError, AttributeError) as err:
            raise BenchmarkError(f"cannot import strategy class {spec!r}: {err}") from None
    from strategies import STRATEGIES
    from toolkit.registry import UnknownNameError

    try:
        return STRATEGIES.get(spec)
    except UnknownNameError as err:
        raise BenchmarkError(str(err)) from None


def strategy_options(entry: StrategyEntry, iterations: dict, material: str) -> dict:
    """The options of one strategy for one material: the iteration overrides it accepts, then its
    own options, checked by building the strategy's stages for ``material``."""
    cls = _strategy_class(entry.spec)
    if cls is None:
        if entry.options:
            raise BenchmarkError(f"strategy {entry.label}: a schedule string takes no options")
        return {}
    from strategies.defaults import STAGE1_ITERATIONS, stage2_iterations

    known = set(cls.option_defaults)
    opts: dict[str, Any] = {k: iterations[k] for k in ITERATION_KEYS if k in known and iterations.get(k) is not None}
    if "iterations" in known and (iterations.get("stage1_iterations") or iterations.get("stage2_iterations")):
        opts["iterations"] = int(iterations.get("stage1_iterations") or STAGE1_ITERATIONS) + int(
            iterations.get("stage2_iterations") or stage2_iterations(material))
    unknown = set(entry.options) - known
    if unknown:
        raise BenchmarkError(f"strategy {entry.label} ({entry.spec}) has no option(s) {sorted(unknown)}; known: {sorted(known)}")
    opts.update(entry.options)
    try:  # a bad option value stops the plan, not the fit after its scene and stage 0
        cls(**opts).stages(material)
    except (ValueError, TypeError) as err:
        raise BenchmarkError(f"strategy {entry.label} ({entry.spec}) with options {entry.options}: {err}") from None
    return opts


def scaled_stage0(iterations: int) -> dict:
    """GIC's full stage-0 schedule shortened to ``iterations``, as a ``RunSettings.stage0``
    mapping (:func:`toolkit.scene.stage0_schedule.compressed_settings`): the same phases in the same order,
    a cheaper, less converged stage 0 (state it when reporting).

    Raises:
        BenchmarkError: ``iterations`` is not an integer >= 100.
    """
    from toolkit.scene.stage0 import compressed_settings

    try:
        return compressed_settings(iterations)
    except ValueError as err:
        raise BenchmarkError(f"stage-0 {err}") from None


# ------------------------------------------------------------------------------------ cameras
def camera_subset(count: int, n_cameras: int) -> Union[str, list[int]]:
    """The fitting cameras for ``count`` views of a scene with ``n_cameras`` cameras.

    3 views are the sparse protocol (0-based 1, 5, 9: ``"sparse"``); ``count >= n_cameras`` is
    ``"all"``; other counts are nested around it: 1 -> [1], 2 -> [1, 5], more than 3 -> 1, 5, 9 and
    then the cameras farthest (around the ring) from those already chosen.
    """
    if count >= n_cameras:
        return "all"
    if count == 3 and n_cameras > 9:
        return "sparse"
    base = [c for c in (1, 5, 9) if c < n_cameras]
    chosen = base[:count]
    while len(chosen) < count:
        rest = [c for c in range(n_cameras) if c not in chosen]

        def ring(a: int, b: int) -> int:
            d = abs(a - b) % n_cameras
            return min(d, n_cameras - d)

        chosen.append(max(rest, key=lambda c: (min(ring(c, x) for x in chosen), -c)))
    return sorted(chosen)


# ------------------------------------------------------------------------------------ settings
def configs_dir() -> Path:
    """The shipped ``configs/`` folder (a checkout's, or the wheel's ``toolkit/configs``)."""
    from toolkit.resources import configs_dir as _configs_dir

    return _configs_dir()


def _load_config(path: Path) -> dict:
    import yaml

    from toolkit.commands.run import settings_from_sections

    cfg = yaml.safe_load(path.read_text()) or {}
    if not isinstance(cfg, dict):
        raise BenchmarkError(f"{path} must hold a mapping")
    if "run" in cfg or "model" in cfg:
        cfg = settings_from_sections(cfg, path)
    return cfg


def config_for(dataset: str, material: str) -> Optional[Path]:
    """The config ``configs/<dataset>_*.yaml`` whose model material is ``material`` (the files are
    named by family, e.g. ``synthetic_elastic.yaml`` for ``neo_hookean``), or ``None``."""
    import yaml

    for path in sorted(configs_dir().glob(f"{dataset}_*.yaml")):
        try:
            cfg = yaml.safe_load(path.read_text()) or {}
        except (OSError, yaml.YAMLError):
            continue
        model = cfg.get("model") if isinstance(cfg.get("model"), dict) else cfg
        if isinstance(model, dict) and model.get("material") == material:
            return path
    return None


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if k in ("sim", "continuum", "model_options") and isinstance(v, dict):
            out[k] = {**(out.get(k) or {}), **v}
        else:
            out[k] = copy.deepcopy(v)
    return out


def scene_settings(scene: SceneEntry, spec: BenchmarkSpec) -> tuple[dict, Optional[str]]:
    """RunSettings fields of a scene (config, then size preset, then overrides) and the config used."""
    from toolkit.pipeline import RunSettings

    cfg_path = scene.config or spec.config
    if cfg_path is None:
        found = config_for(spec.dataset, scene.material)
        cfg_path = str(found) if found else None
    base = _load_config(Path(cfg_path)) if cfg_path else {}
    if base.get("material") not in (None, scene.material):
        raise BenchmarkError(f"{cfg_path} is for material {base['material']!r} but scene {scene.name} is {scene.material!r}")
    preset = BENCH_SIZES[spec.size]["settings"]
    settings = _merge(_merge(base, preset), spec.overrides)
    given_sim = {**(preset.get("sim") or {}), **(spec.overrides.get("sim") or {})}
    if "dx" in given_sim and "substeps" not in given_sim:
        # a grid other than the config's keeps the config's Courant number: substeps scale with
        # config dx / final dx (the final dx is the overrides' when they give one, else the preset's)
        base_sim = base.get("sim") or {}
        scale = float(base_sim.get("dx", 0.02)) / float(settings["sim"]["dx"])
        settings["sim"]["substeps"] = max(10, int(round(float(base_sim.get("substeps", 100)) * scale)))
    settings["material"] = scene.material
    settings["scene"] = scene.path
    unknown = set(settings) - set(RunSettings.__dataclass_fields__)
    if unknown:
        raise BenchmarkError(f"unknown RunSettings field(s) {sorted(unknown)} (from {cfg_path or 'the overrides'})")
    return settings, cfg_path


def _fingerprint(data: Any) -> str:
    return hashlib.sha1(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _scene_cameras(scene: SceneEntry) -> int:
    if scene.variant is not None:
        return _scene_cameras(SceneEntry(**scene.variant["base"]))
    if scene.generate is not None:
        return int(scene.generate["spec"]["n_cameras"])
    from toolkit.data import load_scene

    return load_scene(scene.path).n_cameras


# ------------------------------------------------------------------------------------ the plan
def plan_benchmark(spec: BenchmarkSpec, out: str | Path) -> list[Job]:
    """The jobs of a benchmark in ``out`` (nothing runs; nothing is written).

    One ``prepare`` job per scene and camera count, shared by every strategy's ``fit`` job of
    that scene and camera count; a ``generate`` job first for scenes the benchmark writes; with
    ``spec.variants``, a ``variant`` job and the same jobs for each variant of each scene.
    """
    from toolkit.benchmark.variant_jobs import variant_job, variant_scenes

    out = Path(out).resolve()
    jobs: list[Job] = []
    for scene in list(spec.scenes) + variant_scenes(spec.scenes, spec.variants, out):
        gen_id, var = None, (scene.variant or {}).get("name")
        if var is not None:
            job = variant_job(scene, out, str(out / "logs" / _log_name(f"variant:{scene.name}")),
                              _fingerprint({"kind": "variant", "source": scene.variant["source"], "spec": scene.variant["spec"]}))
            gen_id = job.id
            jobs.append(job)
        elif scene.generate is not None:
            gen_id = f"generate:{scene.name}"
            jobs.append(Job(id=gen_id, kind="generate", folder=scene.path, scene=scene.name, material=scene.material,
                            settings=copy.deepcopy(scene.generate), fingerprint=_fingerprint(scene.generate["spec"]),
                            extra={"log": str(out / "logs" / _log_name(gen_id))}))
        base, cfg_path = scene_settings(scene, spec)
        n_cams = _scene_cameras(scene)
        for count in spec.cameras:
            cams = camera_subset(count, n_cams)
            prep_dir = out / "scenes" / scene.name / f"cams{count}"
            prep_settings = {**base, "cameras": cams, "out": str(prep_dir)}
            prep_key = {k: prep_settings.get(k) for k in PREPARE_FIELDS}
            prep_key["sim_dx"] = (prep_settings.get("sim") or {}).get("dx", 0.02)
            if var is not None:
                prep_key["variant"] = scene.variant["spec"]
            prep_id = f"prepare:{scene.name}:cams{count}"
            prep_fp = _fingerprint({"kind": "prepare", **prep_key, "scene": scene.name})
            jobs.append(Job(id=prep_id, kind="prepare", folder=str(prep_dir), scene=scene.name, material=scene.material,
                            cameras=count, depends=[gen_id] if gen_id else [], settings=prep_settings, fingerprint=prep_fp, variant=var,
                            extra={"config": cfg_path, "log": str(out / "logs" / _log_name(prep_id))}))
            for strat in spec.strategies:
                run_dir = out / "runs" / scene.name / f"cams{count}" / strat.label
                fit_settings = {**base, "cameras": cams, "out": str(run_dir), "curriculum": strat.spec,
                                "curriculum_options": strategy_options(strat, _iterations(spec), scene.material),
                                "checkpoint_every": spec.checkpoint_every}
                fit_id = f"fit:{scene.name}:cams{count}:{strat.label}"
                fp_settings = {k: v for k, v in fit_settings.items() if k not in ("out", "device", "checkpoint_every",
                                                                                   "report_cameras", "threads")}
                fp_settings["scene"] = scene.name
                jobs.append(Job(id=fit_id, kind="fit", folder=str(run_dir), scene=scene.name, material=scene.material,
                                cameras=count, strategy=strat.label, depends=[prep_id], settings=fit_settings, variant=var,
                                fingerprint=_fingerprint({"kind": "fit", "prepare": prep_fp, **fp_settings}),
                                extra={"physics_input": str(prep_dir / "physics_input.pt"), "periodic_eval": spec.periodic_eval,
                                       "checkpoint_every": spec.checkpoint_every, "config": cfg_path,
                                       "log": str(out / "logs" / _log_name(fit_id))}))
    return jobs


def _iterations(spec: BenchmarkSpec) -> dict:
    return {**BENCH_SIZES[spec.size]["iterations"], **{k: v for k, v in spec.iterations.items() if v is not None}}


def _log_name(job_id: str) -> str:
    return _safe_label(job_id.replace(":", "__").replace("/", "-")) + ".log"
