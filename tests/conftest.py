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


def pytest_configure(config):  # noqa: D103
    # An xdist worker takes its share of the cores for torch's intra-op pool: by default each of
    # N workers would start one thread per core, N times more than there are cores (measured 10 %
    # slower on CI's 2 cores with 2 workers). Subprocesses set their own (toolkit.threads).
    import os

    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if os.environ.get("PYTEST_XDIST_WORKER") and workers > 1:
        import torch

        from toolkit.threads import available_cores

        torch.set_num_threads(max(1, available_cores() // workers))


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    """Every test that takes ``device`` runs once per device present (cpu, and cuda:0 if any)."""
    return request.param


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch thread for a module's tests (tiny tensors run faster so on shared cores); the
    previous count is restored when the module ends. Use with ``pytest.mark.usefixtures``."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
