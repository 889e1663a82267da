"""Small particle bodies for the simulator tests (a few hundred particles)."""

from __future__ import annotations

import numpy as np
import torch


def block(n: tuple[int, int, int], spacing: float, corner: tuple[float, float, float]) -> torch.Tensor:
    """(N, 3) float32 particles on a regular lattice: n[i] per axis, lower corner ``corner``."""
    idx = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    pts = np.asarray(corner) + (idx + 0.5) * spacing
    return torch.tensor(pts, dtype=torch.float32).contiguous()


def extent(x: torch.Tensor, axis: int) -> float:
    return float(x[:, axis].max() - x[:, axis].min())
