"""Shared fixtures: the devices to run on (CPU always, CUDA where present)."""

from __future__ import annotations

import pytest


def available_devices() -> list[str]:
    import warp as wp

    devices = ["cpu"]
    if wp.is_cuda_available():
        devices.append("cuda:0")
    return devices


DEVICES = available_devices()


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    """Every test that takes ``device`` runs once per device present (cpu, and cuda:0 if any)."""
    return request.param
