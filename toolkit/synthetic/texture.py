"""A procedural colour texture on the object's material (rest-pose) coordinates.

The colour of a material point depends only on where it was at rest, so the pattern moves and
deforms with the object. It combines three layers so that a photometric loss has structure at
several scales to hold on to:

* a smooth gradient between two colours along a random direction (period ~ the object size),
* soft stripes of a third colour along another random direction (period ~ size / 3),
* a 3D checker that modulates brightness by +-12 % (cell ~ size / 5).

Everything is drawn from ``numpy.random.default_rng(seed)``: same seed, same texture.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["ProceduralTexture", "ConstantTexture", "ground_checker"]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _smoothstep(lo: float, hi: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


@dataclass(frozen=True)
class ProceduralTexture:
    """Colour as a function of rest-pose position (see the module docstring).

    Attributes:
        colors: three RGB colours in [0, 1]: gradient start, gradient end, stripes.
        origin: rest-pose point the pattern is centred on (metres).
        gradient_dir, stripe_dir: unit directions of the gradient and the stripes.
        gradient_period, stripe_period, checker_period: lengths in metres.
        gradient_phase, stripe_phase: radians.
    """

    colors: tuple[tuple[float, float, float], ...]
    origin: tuple[float, float, float]
    gradient_dir: tuple[float, float, float]
    stripe_dir: tuple[float, float, float]
    gradient_period: float
    stripe_period: float
    checker_period: float
    gradient_phase: float
    stripe_phase: float

    @classmethod
    def from_seed(cls, seed: int, size: float = 0.2, origin=(0.0, 0.0, 0.0)) -> "ProceduralTexture":
        """A random texture for an object of about ``size`` metres centred at ``origin``."""
        if not (math.isfinite(size) and size > 0):
            raise ValueError(f"texture size must be a positive length in metres, got {size!r}")
        rng = np.random.default_rng(seed)
        hue = rng.uniform()
        hues = (hue, (hue + rng.uniform(0.25, 0.45)) % 1.0, (hue + rng.uniform(0.55, 0.75)) % 1.0)
        colors = tuple(
            tuple(float(c) for c in colorsys.hsv_to_rgb(h, rng.uniform(0.45, 0.85), rng.uniform(0.7, 0.95))) for h in hues
        )
        g = _unit(rng.normal(size=3))
        s = rng.normal(size=3)
        s = _unit(s - 0.5 * np.dot(s, g) * g)  # not parallel to the gradient
        return cls(
            colors=colors,
            origin=tuple(float(o) for o in origin),
            gradient_dir=tuple(float(x) for x in g),
            stripe_dir=tuple(float(x) for x in s),
            gradient_period=float(size * rng.uniform(1.5, 2.5)),
            stripe_period=float(size * rng.uniform(0.25, 0.4)),
            checker_period=float(size * rng.uniform(0.15, 0.25)),
            gradient_phase=float(rng.uniform(0, 2 * math.pi)),
            stripe_phase=float(rng.uniform(0, 2 * math.pi)),
        )

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) rest-pose points (metres) -> (N, 3) float32 RGB albedo in [0, 1]."""
        q = np.asarray(points, dtype=np.float64).reshape(-1, 3) - np.asarray(self.origin)
        c0, c1, c2 = (np.asarray(c) for c in self.colors)
        g = 0.5 + 0.5 * np.sin(2 * math.pi * (q @ np.asarray(self.gradient_dir)) / self.gradient_period + self.gradient_phase)
        base = (1.0 - g)[:, None] * c0 + g[:, None] * c1
        s = 0.5 + 0.5 * np.sin(2 * math.pi * (q @ np.asarray(self.stripe_dir)) / self.stripe_period + self.stripe_phase)
        stripe = _smoothstep(0.35, 0.65, s)
        col = (1.0 - 0.7 * stripe)[:, None] * base + (0.7 * stripe)[:, None] * c2
        cells = np.floor(q / self.checker_period).astype(np.int64).sum(axis=1) & 1
        col = col * np.where(cells == 1, 0.88, 1.12)[:, None]
        return np.clip(col, 0.0, 1.0).astype(np.float32)

    def to_dict(self) -> dict:
        """JSON-ready description (for the ground-truth file)."""
        return {"kind": "procedural", **{k: (list(map(list, v)) if k == "colors" else v) for k, v in asdict(self).items()}}


@dataclass(frozen=True)
class ConstantTexture:
    """One colour everywhere (tests, shading checks)."""

    color: tuple[float, float, float] = (0.8, 0.8, 0.8)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        n = np.asarray(points).reshape(-1, 3).shape[0]
        return np.tile(np.asarray(self.color, np.float32), (n, 1))

    def to_dict(self) -> dict:
        return {"kind": "constant", "color": list(self.color)}


def ground_checker(points: np.ndarray, period: float = 0.2, colors=(0.42, 0.58)) -> np.ndarray:
    """(N, 3) points on the ground plane -> (N, 3) grey checker albedo (x-z cells of ``period`` m)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cells = (np.floor(p[:, 0] / period).astype(np.int64) + np.floor(p[:, 2] / period).astype(np.int64)) & 1
    grey = np.where(cells == 1, colors[1], colors[0]).astype(np.float32)
    return np.repeat(grey[:, None], 3, axis=1)
