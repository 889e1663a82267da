"""Evaluate a material's Warp update on given F (test helper)."""

from __future__ import annotations

import numpy as np
import torch
import warp as wp

_CACHE: dict = {}


def _kernel(material):
    key = material.cache_key()
    if key not in _CACHE:
        update = material.warp_update()

        @wp.kernel(module="unique")
        def probe(
            F: wp.array(dtype=wp.mat33),
            C: wp.array(dtype=wp.mat33),
            J: wp.array(dtype=float),
            p: wp.array2d(dtype=float),
            dt: float,
            F_out: wp.array(dtype=wp.mat33),
            J_out: wp.array(dtype=float),
            tau_out: wp.array(dtype=wp.mat33),
        ):
            i = wp.tid()
            Fn, Jn, tau = update(F[i], C[i], J[i], dt, p, 0)
            F_out[i] = Fn
            J_out[i] = Jn
            tau_out[i] = tau

        _CACHE[key] = probe
    return _CACHE[key]


def evaluate_update(material, F: np.ndarray, C: np.ndarray, J: np.ndarray, params: torch.Tensor, device: str, dt: float = 1e-4):
    """Run ``update(F, C, J, dt, params)`` for a batch; returns numpy (F_new, J_new, tau)."""
    n = F.shape[0]
    Fa = wp.array(F.astype(np.float32), dtype=wp.mat33, device=device)
    Ca = wp.array(C.astype(np.float32), dtype=wp.mat33, device=device)
    Ja = wp.array(J.astype(np.float32), dtype=float, device=device)
    pa = wp.array(params.detach().cpu().numpy().reshape(1, -1).astype(np.float32), dtype=float, device=device)
    Fo = wp.zeros(n, dtype=wp.mat33, device=device)
    Jo = wp.zeros(n, dtype=float, device=device)
    To = wp.zeros(n, dtype=wp.mat33, device=device)
    wp.launch(_kernel(material), dim=n, inputs=[Fa, Ca, Ja, pa, dt, Fo, Jo, To], device=device)
    return Fo.numpy(), Jo.numpy(), To.numpy()
