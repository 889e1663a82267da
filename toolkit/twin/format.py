"""The digital-twin file: everything needed to re-simulate and re-render a fitted object.

A twin is one ``.npz`` file (numpy's zip of ``.npy`` arrays; read with ``allow_pickle=False``, so
loading it never runs code) holding

* ``twin.json``: a 0-d unicode array with the metadata below (JSON, schema :data:`TWIN_SCHEMA`);
* the arrays of :data:`ARRAYS`: particles, the material parameter vector, the refined Gaussians and
  their embedding in the particles, and the dataset's cameras.

Conventions: SI units (:data:`UNITS`); every position, velocity and camera is in the simulator's
**canonical world** (``+y`` up, ground plane ``y = 0``, see :mod:`toolkit.data.world`); ``world``
records the dataset's own frame and the rigid map ``x_canonical = R x_dataset + t``, so results can be
moved back. ``format`` is ``"projo4d-twin"``; ``version`` is :data:`TWIN_VERSION` and a file of a
newer version is refused with a clear error.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["DigitalTwin", "TwinFormatError", "TWIN_FORMAT", "TWIN_VERSION", "TWIN_SCHEMA", "UNITS", "ARRAYS"]

TWIN_FORMAT = "projo4d-twin"
TWIN_VERSION = 1

#: units of every quantity in a twin
UNITS = {"length": "m", "time": "s", "velocity": "m/s", "acceleration": "m/s^2", "density": "kg/m^3",
         "stress": "Pa", "volume": "m^3", "angle": "deg"}

#: array name -> (dtype, shape with symbolic sizes, meaning); ``colors`` or ``sh`` is present, not both
ARRAYS = {
    "particles": ("float32", "(N, 3)", "simulation particles at frame 0, m (refined by the fit's X group)"),
    "material_params": ("float32", "(P,)", "material parameters in physical units, in material.param_names order"),
    "effect_params": ("float32", "(E,)", "effect parameters, flat, in effect order (MPMSimulator.pack_effects)"),
    "gaussian_means": ("float32", "(G, 3)", "Gaussian centres at frame 0, m"),
    "gaussian_log_scales": ("float32", "(G, 1|3)", "natural log of the standard deviations, m"),
    "gaussian_quats": ("float32", "(G, 4)", "rotations (w, x, y, z)"),
    "gaussian_opacity_logits": ("float32", "(G,)", "pre-sigmoid opacities"),
    "gaussian_colors": ("float32", "(G, 3)", "RGB in [0, 1] (when the Gaussians have no SH)"),
    "gaussian_sh": ("float32", "(G, K, 3)", "SH coefficients (when present)"),
    "embed_index": ("int64", "(G, k)", "particles each Gaussian follows (toolkit.physics.embedding)"),
    "embed_weight": ("float32", "(G, k)", "their weights, summing to 1 per Gaussian"),
    "deform_index": ("int64", "(G, k)", "particles whose motion shapes each Gaussian (only when the Gaussians deform)"),
    "deform_gradient": ("float32", "(G, k, 3)", "their deformation-gradient coefficients "
                        "(toolkit.physics.embedding.local_deformation; only when the Gaussians deform)"),
    "times": ("float32", "(T,)", "frame times of the fitted video, s"),
    "camera_K": ("float32", "(C, 3, 3)", "intrinsics of the dataset's cameras, px"),
    "camera_w2c": ("float32", "(C, 4, 4)", "world-to-camera extrinsics (OpenCV), m"),
}

#: JSON schema of ``twin.json`` (draft 2020-12)
TWIN_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "projo4d digital twin metadata",
    "type": "object",
    "required": ["format", "version", "units", "material", "params", "v0", "gravity", "effects", "sim", "n_train"],
    "properties": {
        "format": {"const": TWIN_FORMAT},
        "version": {"type": "integer", "minimum": 1},
        "units": {"type": "object"},
        "material": {"type": "object", "required": ["name", "options", "param_names"],
                     "properties": {"name": {"type": "string"}, "options": {"type": "object"},
                                    "param_names": {"type": "array", "items": {"type": "string"}}}},
        "params": {"type": "object", "additionalProperties": {"type": "number"}},
        "v0": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
        "gravity": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
        "effects": {"type": "object", "additionalProperties": {"type": "object"}},
        "sim": {"type": "object", "description": "toolkit.mpm.SimConfig fields (frame_dt and particle_volume set)"},
        "grid": {"type": ["object", "null"], "description": "the fit's grid: origin (m), dims, dx (m)"},
        "substeps_floor": {"type": "integer", "minimum": 0},
        "n_train": {"type": "integer", "minimum": 1},
        "renderer": {"type": "string"},
        "cameras": {"type": ["object", "null"], "description": "width, height, near, far, train (0-based indices)"},
        "world": {"type": ["object", "null"], "description": "toolkit.physics.world_checks.world_meta"},
        "source": {"type": "object", "description": "run folder, toolkit version, creation time"},
    },
}


class TwinFormatError(ValueError):
    """A twin file that is not a readable projo4d twin (names the file and what is wrong)."""


@dataclass
class DigitalTwin:
    """A fitted object, ready to re-simulate (see the module docstring for units and frames).

    Attributes:
        meta: the ``twin.json`` dict (material, params, v0, gravity, effects, sim, grid, ...).
        arrays: the arrays of :data:`ARRAYS` (numpy).
    """

    meta: dict
    arrays: dict = field(default_factory=dict)

    # ------------------------------------------------------------------ convenience
    @property
    def material(self) -> str:
        return self.meta["material"]["name"]

    @property
    def params(self) -> dict[str, float]:
        """Material parameters, physical units (E in Pa, nu, viscosities in Pa s, ...)."""
        return dict(self.meta["params"])

    @property
    def v0(self) -> list[float]:
        """Fitted initial velocity, m/s, canonical world."""
        return list(self.meta["v0"])

    @property
    def n_frames(self) -> int:
        return int(len(self.arrays["times"]))

    @property
    def frame_dt(self) -> float:
        return float(self.meta["sim"]["frame_dt"])

    # ------------------------------------------------------------------ I/O
    def validate(self, where: str = "twin") -> None:
        """Raise :class:`TwinFormatError` naming ``where``, the field and what is expected."""
        m = self.meta
        if m.get("format") != TWIN_FORMAT:
            raise TwinFormatError(f"{where}: format is {m.get('format')!r}, expected {TWIN_FORMAT!r}")
        v = m.get("version")
        if not isinstance(v, int) or v < 1:
            raise TwinFormatError(f"{where}: version must be an integer >= 1, got {v!r}")
        if v > TWIN_VERSION:
            raise TwinFormatError(f"{where}: version {v} is newer than this projo4d reads ({TWIN_VERSION}); upgrade projo4d")
        for key in TWIN_SCHEMA["required"]:
            if key not in m:
                raise TwinFormatError(f"{where}: twin.json lacks the field {key!r}")
        for key in ("v0", "gravity"):
            if len(m[key]) != 3:
                raise TwinFormatError(f"{where}: {key} must have 3 components, got {m[key]!r}")
        a = self.arrays
        for name in ("particles", "material_params", "effect_params", "gaussian_means", "gaussian_log_scales",
                     "gaussian_quats", "gaussian_opacity_logits", "embed_index", "embed_weight", "times"):
            if name not in a:
                raise TwinFormatError(f"{where}: the array {name!r} is missing ({ARRAYS[name][2]})")
        n, g = a["particles"].shape[0], a["gaussian_means"].shape[0]
        if a["particles"].ndim != 2 or a["particles"].shape[1] != 3 or n == 0:
            raise TwinFormatError(f"{where}: particles must have shape (N, 3) with N >= 1, got {a['particles'].shape}")
        if ("gaussian_colors" in a) == ("gaussian_sh" in a):
            raise TwinFormatError(f"{where}: exactly one of gaussian_colors and gaussian_sh must be present")
        if a["embed_index"].shape[0] != g or a["embed_weight"].shape != a["embed_index"].shape:
            raise TwinFormatError(f"{where}: embed_index/embed_weight must have shape (G={g}, k), got "
                                  f"{a['embed_index'].shape} and {a['embed_weight'].shape}")
        if a["embed_index"].size and (a["embed_index"].min() < 0 or a["embed_index"].max() >= n):
            raise TwinFormatError(f"{where}: embed_index must index the {n} particles")
        if ("deform_index" in a) != ("deform_gradient" in a):
            raise TwinFormatError(f"{where}: deform_index and deform_gradient come together (deformed Gaussians) or not at all")
        if "deform_index" in a:
            di, dg = a["deform_index"], a["deform_gradient"]
            if di.ndim != 2 or di.shape[0] != g or dg.shape != di.shape + (3,):
                raise TwinFormatError(f"{where}: deform_index/deform_gradient must have shapes (G={g}, k) and (G, k, 3), "
                                      f"got {di.shape} and {dg.shape}")
            if di.size and (di.min() < 0 or di.max() >= n):
                raise TwinFormatError(f"{where}: deform_index must index the {n} particles")
        names = m["material"]["param_names"]
        if a["material_params"].shape != (len(names),):
            raise TwinFormatError(f"{where}: material_params must have shape ({len(names)},) for {names}, "
                                  f"got {a['material_params'].shape}")

    def save(self, path: str | Path) -> Path:
        """Write the twin to ``path`` (``.npz``), atomically; returns the path."""
        from toolkit.atomic import write_with

        self.validate(str(path))
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        payload = {k: np.ascontiguousarray(v) for k, v in self.arrays.items()}
        payload["twin.json"] = np.array(json.dumps(self.meta, indent=1, sort_keys=True))

        def write(tmp):
            with open(tmp, "wb") as f:
                np.savez_compressed(f, **payload)

        write_with(path, write)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "DigitalTwin":
        """Read a twin written by :meth:`save` (or ``projo4d export``); validates it."""
        path = Path(path)
        if path.is_dir() and (path / "twin.npz").is_file():
            path = path / "twin.npz"
        if not path.is_file():
            raise TwinFormatError(f"{path}: no such twin file (write one with `projo4d export RUN`)")
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except Exception as err:  # noqa: BLE001 - any unreadable zip/npy
            raise TwinFormatError(f"{path}: not a readable .npz twin file ({err})") from None
        if "twin.json" not in arrays:
            raise TwinFormatError(f"{path}: no twin.json entry: not a projo4d twin")
        try:
            meta = json.loads(str(arrays.pop("twin.json")))
        except json.JSONDecodeError as err:
            raise TwinFormatError(f"{path}: twin.json is not valid JSON ({err})") from None
        twin = cls(meta=meta, arrays=arrays)
        twin.validate(str(path))
        return twin

    def summary(self) -> str:
        """A few lines for humans: material, parameters, v0, sizes."""
        p = ", ".join(f"{k} = {v:.4g}" for k, v in self.params.items())
        eff = "; ".join(f"{e}: {vals}" for e, vals in self.meta["effects"].items()) or "none"
        return (f"{self.material} ({p}); v0 = {np.round(self.v0, 4).tolist()} m/s; gravity = "
                f"{np.round(self.meta['gravity'], 4).tolist()} m/s^2; effects: {eff}\n"
                f"{len(self.arrays['particles'])} particles, {len(self.arrays['gaussian_means'])} Gaussians, "
                f"{self.n_frames} frames of {self.frame_dt:.4g} s ({self.meta['n_train']} fitted)")
