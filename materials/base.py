"""The material interface: parameters with their optimization transforms, and the Warp update.

A material is one class with its parameters and its kernels. The simulator calls one Warp
function per particle and substep, built by :meth:`Material.warp_update`::

    F_new, J_new, tau = update(F_tmp, C, J, dt, params, row)

* ``F_tmp = (I + dt C) F`` (3x3, the trial deformation gradient),
* ``C`` the APIC affine velocity matrix (1/s), ``J`` the tracked volume ratio (used by fluids),
* ``params`` a ``wp.array2d(dtype=float)`` of *physical* parameter values, shape (R, P) with
  R = 1 (one value for the whole body) or R = N (one row per particle); ``row`` picks the row,
* returns the new (elastic) deformation gradient, the new J, and the Kirchhoff stress tau (Pa).

Parameters are optimized in a transformed ("raw") space: ``log10`` (E, viscosities, yield
stress), ``tanh`` (Poisson's ratio, bounded to [lo, hi]) or ``linear`` (friction angle in
degrees). :meth:`Material.to_physical` maps raw torch tensors to physical values differentiably.

A parameter's **fit range** (:attr:`MaterialParam.fit_range`) is where a fit keeps it, which may be
narrower than where it is valid: Poisson's ratio is valid down to -0.99 (auxetic foams), but a fit
keeps it in [0, 0.49] unless told otherwise (``model: {fit_ranges: {nu: [-0.99, 0.49]}}``;
:meth:`Material.fit_ranges`). The range is enforced by projection after each optimizer step,
so a fit that never leaves it takes exactly the steps it would take without one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, Mapping

import numpy as np
import torch

__all__ = ["MaterialParam", "Material", "MaterialError", "lame_parameters", "default_lr", "LOG10_LR", "RANGE_FRACTION_LR"]

Transform = Literal["log10", "tanh", "linear"]


class MaterialError(ValueError):
    """An invalid material parameter value, name or option."""


@dataclass(frozen=True)
class MaterialParam:
    """One physical parameter of a material.

    Attributes:
        name: key used in dicts, configs and reports (``E``, ``nu``, ``mu``, ...).
        default: default starting guess, physical units.
        transform: how it is optimized: ``log10``, ``tanh`` (bounded) or ``linear``.
        low, high: valid physical range. For ``log10`` parameters ``low`` is exclusive (the
            value must be > low, normally 0); otherwise both ends are inclusive. For ``tanh``
            parameters the range is also the tanh bound.
        optimize: whether the parameter is optimized by default.
        lr: Adam learning rate in the raw (transformed) space. ``None`` (the default) applies the
            scale-free rule :func:`default_lr`: 0.1 decade for ``log10`` parameters, 1 % of the
            valid range for bounded (``tanh``, finite ``linear``) ones, so no scene needs hand-set rates.
        units: physical units, for reports.
        description: one line for docs and ``projo4d materials``.
        search: physical ``(low, high)`` range of the coarse global search run before gradient
            descent (:mod:`toolkit.physics.coarse_search`); ``None``: not searched (the fit
            starts at the guess).
        fit_range: physical ``(low, high)`` range a fit keeps the parameter in (inside the valid
            range; ``None``: the valid range). See :meth:`Material.fit_ranges`.
    """

    name: str
    default: float
    transform: Transform = "log10"
    low: float = 0.0
    high: float = math.inf
    optimize: bool = True
    lr: float | None = None
    units: str = ""
    description: str = ""
    search: tuple[float, float] | None = None
    fit_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.lr is None:
            object.__setattr__(self, "lr", default_lr(self.transform, self.low, self.high))
        if self.search is not None:
            lo, hi = (float(v) for v in self.search)
            if not lo < hi:
                raise MaterialError(f"{self.name}: search range {self.search!r} must be (low, high) with low < high")
            self.check(lo)
            self.check(hi)
        if self.fit_range is not None:
            self.check_fit_range(self.fit_range)

    @property
    def fit_bounds(self) -> tuple[float, float]:
        """The physical ``(low, high)`` a fit keeps the parameter in (the valid range by default)."""
        return (float(self.fit_range[0]), float(self.fit_range[1])) if self.fit_range is not None else (self.low, self.high)

    def check_fit_range(self, bounds: Any, material: str = "") -> tuple[float, float]:
        """``bounds`` as a float pair after checking it is ``[low, high]`` with ``low < high``,
        both inside the valid range; raises :class:`MaterialError` naming the parameter."""
        where = f"{material}." if material else ""
        ok = (isinstance(bounds, (list, tuple)) and len(bounds) == 2
              and all(isinstance(b, (int, float)) and not isinstance(b, bool) and math.isfinite(b) for b in bounds))
        if not ok or not float(bounds[0]) < float(bounds[1]):
            raise MaterialError(f"{where}{self.name}: fit range {bounds!r} must be [low, high] with finite low < high")
        lo, hi = float(bounds[0]), float(bounds[1])
        inside = (lo >= self.low if self.transform != "log10" else lo > self.low) and hi <= self.high
        if not inside:
            raise MaterialError(f"{where}{self.name}: fit range [{lo:g}, {hi:g}] must lie inside the valid range "
                                f"{'(' if self.transform == 'log10' else '['}{self.low:g}, {self.high:g}]")
        return lo, hi

    def raw_fit_bounds(self, bounds: tuple[float, float]) -> tuple[float, float]:
        """``bounds`` (physical) as the interval of raw values a fit may take. ``linear``: the
        bounds within the valid range; ``log10``/``tanh``: an end at the valid range's edge
        (which the transform cannot pass anyway) is left open (``-inf`` / ``inf``)."""
        lo, hi = bounds
        if self.transform == "linear":
            return max(float(lo), self.low), min(float(hi), self.high)
        at_low = lo <= self.low or (self.transform == "log10" and lo <= 0)
        at_high = hi >= self.high
        rlo = -math.inf if at_low else float(self.to_raw(lo))
        rhi = math.inf if at_high else float(self.to_raw(hi))
        return rlo, rhi

    def check(self, value: float, material: str = "") -> None:
        """Raise :class:`MaterialError` if ``value`` is outside the valid range."""
        where = f"{material}." if material else ""
        if not isinstance(value, (int, float)) or not math.isfinite(float(value)):
            raise MaterialError(f"{where}{self.name} must be a finite number, got {value!r}")
        v = float(value)
        if self.transform == "log10":
            if not (v > self.low and v <= self.high):
                raise MaterialError(
                    f"{where}{self.name} = {v:g} is out of range: expected {self.low:g} < {self.name} <= {self.high:g}"
                    + (f" {self.units}" if self.units else "")
                )
        elif not (float(np.float32(self.low)) <= v <= float(np.float32(self.high))):  # parameters travel as float32
            raise MaterialError(
                f"{where}{self.name} = {v:g} is out of range: expected {self.low:g} <= {self.name} <= {self.high:g}"
                + (f" {self.units}" if self.units else "")
            )

    def to_raw(self, value: torch.Tensor | float) -> torch.Tensor:
        """Physical value -> optimized (raw) value."""
        v = torch.as_tensor(value, dtype=torch.float32)
        if self.transform == "log10":
            return torch.log10(v)
        if self.transform == "tanh":
            r = self.high - self.low
            z = (v - self.low - r / 2) / (r / 2)
            return (r / 2) * torch.atanh(z.clamp(-1 + 1e-6, 1 - 1e-6))
        return v.clone()

    def to_physical(self, raw: torch.Tensor) -> torch.Tensor:
        """Optimized (raw) value -> physical value, differentiable."""
        if self.transform == "log10":
            return torch.pow(10.0, raw)
        if self.transform == "tanh":
            r = self.high - self.low
            # a saturated tanh can round past an end in float32 (0.49 -> 0.49000001)
            return ((r / 2) * torch.tanh(2 * raw / r) + self.low + r / 2).clamp(self.low, self.high)
        return raw


#: Adam step of ``log10`` parameters, decades per iteration (the scale-free rule of :func:`default_lr`)
LOG10_LR = 0.1
#: Adam step of bounded parameters as a fraction of their valid range (:func:`default_lr`)
RANGE_FRACTION_LR = 0.01


def default_lr(transform: str, low: float, high: float) -> float:
    """The scale-free learning rate of a parameter in its raw (optimized) space.

    ``log10``: :data:`LOG10_LR` decades per step whatever the parameter's magnitude (a soft
    jelly and a stiff rubber take the same relative steps); ``tanh`` and bounded ``linear``:
    :data:`RANGE_FRACTION_LR` of the valid range ``high - low`` (the tanh raw space has the
    physical units near the middle of the range); an unbounded ``linear`` parameter: 0.01.
    """
    if transform == "log10":
        return LOG10_LR
    if math.isfinite(high - low):
        return RANGE_FRACTION_LR * (high - low)
    return 0.01


def lame_parameters(E: float, nu: float) -> tuple[float, float]:
    """Lame parameters (mu, lambda) in Pa from Young's modulus E (Pa) and Poisson's ratio nu."""
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


class Material:
    """Base class of the constitutive models.

    Subclasses set :attr:`params` and implement :meth:`build_update`, which returns a
    ``@wp.func`` with the signature described in the module docstring. Options (e.g. the
    plasticine yield rule) are constructor keyword arguments stored in :attr:`options`; they
    are compile-time constants of the generated kernel.

    Args:
        **options: model options (see each subclass).
    """

    registry_name: ClassVar[str] = ""
    params: ClassVar[tuple[MaterialParam, ...]] = ()
    uses_svd: ClassVar[bool] = False
    #: True for models whose state is the scalar J (fluids) rather than F.
    tracks_volume_only: ClassVar[bool] = False
    option_defaults: ClassVar[Mapping[str, Any]] = {}

    def __init__(self, **options: Any):
        unknown = set(options) - set(self.option_defaults)
        if unknown:
            raise MaterialError(
                f"{type(self).__name__} has no option(s) {sorted(unknown)}; "
                f"known options: {sorted(self.option_defaults) or 'none'}"
            )
        self.options: dict[str, Any] = {**self.option_defaults, **options}
        self._update = None

    # ----------------------------------------------------------------- parameters
    @property
    def name(self) -> str:
        return self.registry_name or type(self).__name__

    @property
    def param_names(self) -> list[str]:
        return [p.name for p in self.params]

    def param(self, name: str) -> MaterialParam:
        for p in self.params:
            if p.name == name:
                return p
        raise MaterialError(f"material {self.name!r} has no parameter {name!r}; its parameters are {self.param_names}")

    def fit_ranges(self, overrides: Mapping[str, Any] | str | None = None) -> dict[str, tuple[float, float]]:
        """Physical ``(low, high)`` per parameter that a fit keeps it in.

        Args:
            overrides: ``None``: each parameter's :attr:`MaterialParam.fit_bounds`; ``"valid"``: the
                valid ranges (no narrower range, as fits did before fit ranges existed); a mapping
                ``{name: [low, high]}`` replaces the named parameters' ranges (inside the valid range).

        Raises:
            MaterialError: an unknown parameter name or a range outside the valid one.
        """
        if overrides == "valid":
            return {p.name: (p.low, p.high) for p in self.params}
        out = {p.name: p.fit_bounds for p in self.params}
        if overrides is None:
            return out
        if not isinstance(overrides, Mapping):
            raise MaterialError(f"{self.name}: fit ranges must be 'valid' or a mapping {{parameter: [low, high]}}, "
                                f"got {overrides!r}")
        unknown = set(overrides) - set(self.param_names)
        if unknown:
            raise MaterialError(f"material {self.name!r} has no parameter(s) {sorted(unknown)} to give a fit range; "
                                f"its parameters are {self.param_names}")
        for name, bounds in overrides.items():
            out[name] = self.param(name).check_fit_range(bounds, self.name)
        return out

    def defaults(self) -> dict[str, float]:
        """Default starting guesses, physical units."""
        return {p.name: p.default for p in self.params}

    def complete(self, values: Mapping[str, float] | None) -> dict[str, float]:
        """``values`` with missing parameters filled from the defaults; unknown keys raise."""
        values = dict(values or {})
        unknown = set(values) - set(self.param_names)
        if unknown:
            raise MaterialError(
                f"material {self.name!r} has no parameter(s) {sorted(unknown)}; its parameters are {self.param_names}"
            )
        return {p.name: float(values.get(p.name, p.default)) for p in self.params}

    def validate(self, values: Mapping[str, float]) -> None:
        """Raise :class:`MaterialError` naming the parameter, value and valid range."""
        for p in self.params:
            if p.name in values:
                p.check(values[p.name], self.name)

    def pack(self, values: Mapping[str, float] | None = None, device: str | torch.device = "cpu") -> torch.Tensor:
        """Physical values -> (P,) float32 tensor in :attr:`params` order (validated)."""
        full = self.complete(values)
        self.validate(full)
        return torch.tensor([full[n] for n in self.param_names], dtype=torch.float32, device=device)

    def unpack(self, packed: torch.Tensor) -> dict[str, float]:
        """(P,) tensor of physical values -> dict of floats."""
        flat = packed.detach().reshape(-1, len(self.params))[0].cpu().tolist()
        return dict(zip(self.param_names, flat))

    def to_raw(self, values: Mapping[str, float] | None = None) -> torch.Tensor:
        """Physical values -> (P,) raw (optimized-space) tensor."""
        full = self.complete(values)
        self.validate(full)
        return torch.stack([p.to_raw(full[p.name]) for p in self.params])

    def to_physical(self, raw: torch.Tensor) -> torch.Tensor:
        """(..., P) raw tensor -> (..., P) physical tensor, differentiable."""
        if raw.shape[-1] != len(self.params):
            raise MaterialError(f"material {self.name!r} expects {len(self.params)} raw parameters, got shape {tuple(raw.shape)}")
        return torch.stack([p.to_physical(raw[..., i]) for i, p in enumerate(self.params)], dim=-1)

    def check_tensor(self, physical: torch.Tensor) -> None:
        """Validate a (P,) or (N, P) tensor of physical values (reports the first bad entry)."""
        if physical.ndim not in (1, 2) or physical.shape[-1] != len(self.params):
            raise MaterialError(
                f"material {self.name!r} expects parameters of shape (P,) or (N, P) with P = {len(self.params)} "
                f"({', '.join(self.param_names)}), got {tuple(physical.shape)}"
            )
        rows = physical.detach().reshape(-1, len(self.params)).cpu()
        if not torch.isfinite(rows).all():
            bad = (~torch.isfinite(rows)).nonzero()[0].tolist()
            raise MaterialError(f"material {self.name!r}: parameter {self.param_names[bad[1]]} is NaN or inf (row {bad[0]})")
        for i, p in enumerate(self.params):
            # ranges are intervals: the extremes being valid means every row is
            p.check(float(rows[:, i].min()), self.name)
            p.check(float(rows[:, i].max()), self.name)

    # ----------------------------------------------------------------- time step
    def wave_speed(self, values: Mapping[str, Any], density: float) -> np.ndarray:
        """Speed of the fastest small-strain wave, m/s (the explicit time step's limit).

        The default is the elastic P-wave ``sqrt((lambda + 2 mu) / rho)`` from ``E`` and ``nu``
        (``(lambda + 2 mu) = E (1 - nu) / ((1 + nu)(1 - 2 nu))``) when the material has both, else 0
        (no known limit). Materials with other parameters override it.

        Args:
            values: physical parameters; each a float or an array (one entry per particle).
            density: kg/m^3.

        Returns:
            array of wave speeds (shape of the broadcast values), m/s.
        """
        if "E" in values and "nu" in values:
            E = np.asarray(values["E"], np.float64)
            nu = np.asarray(values["nu"], np.float64)
            modulus = E * (1 - nu) / ((1 + nu) * (1 - 2 * nu))
            return np.sqrt(np.maximum(modulus, 0.0) / density)
        return np.zeros(())

    def viscous_dt(self, values: Mapping[str, Any], density: float, dx: float) -> np.ndarray:
        """Largest stable substep of the explicit viscous term, seconds (``inf`` without one).

        Args:
            values: physical parameters (floats or per-particle arrays).
            density: kg/m^3.
            dx: grid spacing, metres.
        """
        return np.full((), np.inf)

    # ----------------------------------------------------------------- kernels
    def build_update(self):  # pragma: no cover - abstract
        """Return the ``@wp.func`` update (see module docstring)."""
        raise NotImplementedError

    def warp_update(self):
        """The cached Warp update function for this material and its options."""
        if self._update is None:
            self._update = self.build_update()
        return self._update

    def cache_key(self) -> tuple:
        """Identifies the generated kernels: class and options."""
        return (type(self).__qualname__, tuple(sorted((k, repr(v)) for k, v in self.options.items())))

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={v!r}" for k, v in self.options.items())
        return f"{type(self).__name__}({opts})"
