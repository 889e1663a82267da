"""Motion-factorized deformation network (GIC style): ``x_t = x_0 + Δ(x_0, t)``.

Architecture (facts from GIC ``utils/time_utils.py::DeformNetwork`` and ProJo4D's version):

* **Encodings.** Positions and times pass through a NeRF frequency encoding
  ``[x, sin(2^0 x), cos(2^0 x), ..., sin(2^(L-1) x), cos(2^(L-1) x)]`` (GIC: L = 10 for
  positions, 6 for time). With ``time_net`` the time encoding is followed by a small MLP
  (``Linear(., 256) - ReLU - Linear(256, time_out = 30)``, GIC's ``timenet``).
* **Motion basis** (time only): an MLP of ``basis_depth`` layers of width ``basis_width`` with a
  skip connection re-injecting the time code after layer ``basis_depth // 2``; its head outputs
  ``num_basis`` basis vectors of the output attributes, ``B(t)`` (num_attr, num_basis).
* **Coefficients** (space-time): an MLP on ``[enc(x_0), enc(t)]`` with ``coeff_depth`` hidden
  layers of width ``coeff_width``, giving ``c(x_0, t)`` (num_attr, num_basis) per point.
* **Output**: ``Δ = mean_b c_b * B_b`` per attribute: position offsets (3), optionally a
  log-scale offset (1 for isotropic, 3 otherwise) and a quaternion offset (4).

Differences from GIC, on purpose:

* The basis head is zero-initialized (ProJo4D's ``init_zero_mb`` option), so ``Δ ≡ 0`` at the
  start: after the static warm-up the dynamic phase starts from the warm-up's Gaussians.
* Inputs are normalized: ``x`` is mapped by ``(x - x_center) / x_half`` (the canonical bounding
  box to [-1, 1], set with :meth:`DeformationNetwork.set_normalization`) and time by
  ``(t - t_offset) / t_scale`` (the training time span to [0, 1]). GIC feeds raw world
  coordinates and dataset times; normalizing makes the frequencies independent of the scene's
  units and of the frame rate. With the identity normalization the network is GIC's.
* A scale offset is added to the *log*-scale (GIC adds it to the activated scale), so scales stay
  positive.

Shapes: positions (N, 3) metres; times are scalars in seconds (0-dim or (1,) tensors, or floats)
or (T,) for a batch of times (outputs then get a leading T dimension).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional, Sequence

import torch
import torch.nn.functional as F
from torch import nn
from toolkit.settings import DictSettings

__all__ = [
    "FrequencyEncoding",
    "TimeEncoding",
    "MotionBasis",
    "CoefficientNet",
    "DeformationConfig",
    "DeformationNetwork",
    "Deformation",
]


class FrequencyEncoding(nn.Module):
    """NeRF positional encoding with log-spaced frequencies ``2^0 .. 2^(n_freqs - 1)``.

    Args:
        in_dim: Input width D.
        n_freqs: Number of frequencies L (0: identity).
        include_input: Prepend the raw input.

    Output width: ``D * (include_input + 2 L)``; order ``[x, sin(f0 x), cos(f0 x), sin(f1 x), ...]``.
    """

    def __init__(self, in_dim: int, n_freqs: int, include_input: bool = True):
        super().__init__()
        self.in_dim, self.n_freqs, self.include_input = int(in_dim), int(n_freqs), bool(include_input)
        self.register_buffer("freqs", 2.0 ** torch.arange(self.n_freqs, dtype=torch.float32), persistent=False)
        self.out_dim = self.in_dim * (int(self.include_input) + 2 * self.n_freqs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.n_freqs == 0:
            return x
        xf = x[..., None, :] * self.freqs[:, None].to(x)  # (..., L, D)
        enc = torch.stack([torch.sin(xf), torch.cos(xf)], dim=-2).flatten(-3)  # (..., L*2*D)
        return torch.cat([x, enc], dim=-1) if self.include_input else enc


class TimeEncoding(nn.Module):
    """Frequency encoding of a scalar time, optionally followed by GIC's ``timenet`` MLP."""

    def __init__(self, n_freqs: int = 6, time_net: bool = True, time_out: int = 30, hidden: int = 256):
        super().__init__()
        self.enc = FrequencyEncoding(1, n_freqs)
        if time_net:
            self.net: Optional[nn.Module] = nn.Sequential(
                nn.Linear(self.enc.out_dim, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, time_out)
            )
            self.out_dim = int(time_out)
        else:
            self.net = None
            self.out_dim = self.enc.out_dim

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        """(T, 1) normalized times -> (T, out_dim)."""
        e = self.enc(t)
        return self.net(e) if self.net is not None else e


class MotionBasis(nn.Module):
    """Time-only MLP producing ``num_basis`` basis vectors of ``num_attr`` attributes."""

    def __init__(self, in_dim: int, num_attr: int, num_basis: int = 10, width: int = 256, depth: int = 8, zero_init: bool = True):
        super().__init__()
        self.num_attr, self.num_basis = int(num_attr), int(num_basis)
        self.skip = depth // 2
        layers = [nn.Linear(in_dim, width)]
        for i in range(depth - 1):
            layers.append(nn.Linear(width + (in_dim if i == self.skip else 0), width))
        self.layers = nn.ModuleList(layers)
        self.head = nn.Linear(width, self.num_attr * self.num_basis)
        if zero_init:
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)

    def forward(self, t_emb: torch.Tensor) -> torch.Tensor:
        """(T, in_dim) -> (T, num_attr, num_basis)."""
        h = t_emb
        for i, layer in enumerate(self.layers):
            if i == self.skip + 1:
                h = torch.cat([t_emb, h], dim=-1)
            h = F.relu(layer(h))
        return self.head(h).reshape(-1, self.num_attr, self.num_basis)


class CoefficientNet(nn.Module):
    """Space-time MLP producing per-point coefficients (num_attr, num_basis)."""

    def __init__(self, x_dim: int, t_dim: int, num_attr: int, num_basis: int = 10, width: int = 256, depth: int = 2):
        super().__init__()
        self.num_attr, self.num_basis = int(num_attr), int(num_basis)
        layers = [nn.Linear(x_dim + t_dim, width)] + [nn.Linear(width, width) for _ in range(depth)]
        self.layers = nn.ModuleList(layers)
        self.head = nn.Linear(width, self.num_attr * self.num_basis)

    def forward(self, x_emb: torch.Tensor, t_emb: torch.Tensor) -> torch.Tensor:
        """x_emb (N, x_dim), t_emb (T, t_dim) -> (T, N, num_attr, num_basis)."""
        T, N = t_emb.shape[0], x_emb.shape[0]
        h = torch.cat([x_emb[None].expand(T, N, -1), t_emb[:, None].expand(T, N, -1)], dim=-1)
        for layer in self.layers:
            h = F.relu(layer(h))
        return self.head(h).reshape(T, N, self.num_attr, self.num_basis)


@dataclass
class DeformationConfig(DictSettings):
    settings_name = "deformation settings"

    """Hyper-parameters of :class:`DeformationNetwork`. Defaults are GIC's
    (``arguments/__init__.py::ModelParams`` with the PAC-NeRF / Spring-Gaus configs' ``timenet``).

    Attributes:
        x_multires: Frequencies of the position encoding (GIC 10).
        t_multires: Frequencies of the time encoding (GIC 6).
        time_net: Follow the time encoding with an MLP (GIC configs: true).
        time_out: Output width of that MLP (GIC 30).
        num_basis: Number of motion bases (GIC 10).
        basis_width, basis_depth: Motion-basis MLP (GIC 256, 8).
        coeff_width, coeff_depth: Coefficient MLP hidden width and extra layers (GIC 256, 2).
        deform_scale: Also output a log-scale offset (GIC isotropic: yes; ProJo4D: no).
        deform_rotation: Also output a quaternion offset (anisotropic Gaussians only).
        zero_init: Zero-initialize the basis head, so ``Δ = 0`` at the start.
        detach_input: Feed ``x_0.detach()`` to the network (GIC does), so canonical positions
            get gradients only through the additive path ``x_0 + Δ``.
        dxyz_scale: Gain on the position offsets (GIC ``dxyz_scale``, 1). With Adam the
            time-only basis moves ``Δ`` by about ``dxyz_scale * mean|c| * lr`` metres per step;
            a gain of 10 sped up short runs but made some diverge (Gaussians thrown out of view),
            so the presets keep 1.
    """

    x_multires: int = 10
    t_multires: int = 6
    time_net: bool = True
    time_out: int = 30
    num_basis: int = 10
    basis_width: int = 256
    basis_depth: int = 8
    coeff_width: int = 256
    coeff_depth: int = 2
    deform_scale: bool = False
    deform_rotation: bool = False
    zero_init: bool = True
    detach_input: bool = True
    dxyz_scale: float = 1.0

    @classmethod
    def tiny(cls) -> "DeformationConfig":
        """A small network for CPU tests and the demo (same structure, narrower and shallower)."""
        return cls(
            x_multires=6, t_multires=4, time_out=16, num_basis=8, basis_width=64, basis_depth=4,
            coeff_width=64, coeff_depth=1,
        )



class Deformation(NamedTuple):
    """Offsets predicted for N points (a leading T dimension for a batch of times).

    Attributes:
        xyz: (N, 3) position offsets, metres.
        log_scales: (N, S) log-scale offsets (S = 1 isotropic, 3 otherwise) or None.
        quats: (N, 4) quaternion offsets or None.
    """

    xyz: torch.Tensor
    log_scales: Optional[torch.Tensor] = None
    quats: Optional[torch.Tensor] = None


class DeformationNetwork(nn.Module):
    """``Δ(x_0, t)`` as a motion-factorized network (module docstring).

    Args:
        config: Network hyper-parameters.
        scale_dim: Width of the log-scale offset (1 for isotropic Gaussians, 3 otherwise).

    Buffers: ``x_center`` (3,), ``x_half`` (3,), ``t_offset`` (), ``t_scale`` () for the input
    normalization (identity until :meth:`set_normalization`).
    """

    def __init__(self, config: DeformationConfig | dict | None = None, scale_dim: int = 1):
        super().__init__()
        self.config = cfg = DeformationConfig.from_dict(config)
        self.scale_dim = int(scale_dim)
        self.split_sizes = [3, self.scale_dim if cfg.deform_scale else 0, 4 if cfg.deform_rotation else 0]
        num_attr = sum(self.split_sizes)
        self.pos_enc = FrequencyEncoding(3, cfg.x_multires)
        self.time_enc = TimeEncoding(cfg.t_multires, cfg.time_net, cfg.time_out)
        self.basis = MotionBasis(self.time_enc.out_dim, num_attr, cfg.num_basis, cfg.basis_width, cfg.basis_depth, cfg.zero_init)
        self.coeffs = CoefficientNet(self.pos_enc.out_dim, self.time_enc.out_dim, num_attr, cfg.num_basis, cfg.coeff_width, cfg.coeff_depth)
        self.register_buffer("x_center", torch.zeros(3))
        self.register_buffer("x_half", torch.ones(3))
        self.register_buffer("t_offset", torch.zeros(()))
        self.register_buffer("t_scale", torch.ones(()))

    @torch.no_grad()
    def set_normalization(
        self,
        bbox_min: Sequence[float] | torch.Tensor,
        bbox_max: Sequence[float] | torch.Tensor,
        t_min: float = 0.0,
        t_max: float = 1.0,
    ) -> None:
        """Map the box ``[bbox_min, bbox_max]`` (metres) to [-1, 1]^3 (one common half-size, so
        the mapping is a similarity) and ``[t_min, t_max]`` (seconds) to [0, 1]."""
        lo = torch.as_tensor(bbox_min, dtype=torch.float32).reshape(3)
        hi = torch.as_tensor(bbox_max, dtype=torch.float32).reshape(3)
        self.x_center.copy_((lo + hi) / 2)
        self.x_half.fill_(float(((hi - lo) / 2).max().clamp_min(1e-6)))
        self.t_offset.fill_(float(t_min))
        self.t_scale.fill_(float(max(t_max - t_min, 1e-6)))

    def forward(self, x: torch.Tensor, t: torch.Tensor | float) -> Deformation:
        """Offsets for points ``x`` (N, 3) at time ``t``.

        Args:
            x: (N, 3) canonical positions, metres (detached internally when ``detach_input``).
            t: A time in seconds (float, 0-dim or (1,) tensor) -> outputs (N, ...); or (T,) times
               (T > 1) -> outputs (T, N, ...).
        """
        if self.config.detach_input:
            x = x.detach()
        tt = torch.as_tensor(t, dtype=x.dtype, device=x.device)
        batched = tt.ndim == 1 and tt.shape[0] > 1
        tt = tt.reshape(-1, 1)
        xn = (x - self.x_center) / self.x_half
        tn = (tt - self.t_offset) / self.t_scale
        x_emb = self.pos_enc(xn)
        t_emb = self.time_enc(tn)
        basis = self.basis(t_emb)  # (T, A, B)
        coeff = self.coeffs(x_emb, t_emb)  # (T, N, A, B)
        attrs = (coeff * basis[:, None]).mean(dim=-1)  # (T, N, A)
        if not batched:
            attrs = attrs[0]
        xyz, ls, q = torch.split(attrs, self.split_sizes, dim=-1)
        return Deformation(
            xyz=xyz * self.config.dxyz_scale if self.config.dxyz_scale != 1.0 else xyz,
            log_scales=ls if self.split_sizes[1] else None,
            quats=q if self.split_sizes[2] else None,
        )
