"""Who holds the GPU's memory when an allocation fails.

A CUDA out-of-memory error says how many bytes did not fit, not why: this run's grids and kept
tapes (:mod:`toolkit.mpm.tapes`), its renderer and torch tensors, or other processes on the same
card (several runs per GPU, issue #25). :func:`oom_note` turns such an error into one more line
with the card's total and free memory, what this process holds through Warp's memory pool and
torch's caching allocator, the rest (other processes), and what lowers it. The error boundary
(:mod:`toolkit.errors`) and the benchmark's failed-job records add it to the error.

On the paper-size benchmark one scene failed twice with "Failed to allocate 173081600 bytes on
device 'cuda:0'" while sharing its card with two or three other runs
(``docs/results/paper_size.md``); the note is what tells those causes apart.
"""

from __future__ import annotations

import re
from typing import Optional

__all__ = ["oom_device", "memory_usage", "format_memory_note", "oom_note"]

_DEVICE = re.compile(r"on device '?(cuda(?::\d+)?)'?")


def oom_device(err: BaseException) -> Optional[str]:
    """The CUDA device of an out-of-memory error (Warp's "Failed to allocate N bytes on device
    'cuda:0'", Warp's "out of memory", torch's ``OutOfMemoryError``), or None for any other error."""
    text = str(err)
    name = type(err).__name__
    if not ("out of memory" in text.lower() or "failed to allocate" in text.lower() or name == "OutOfMemoryError"):
        return None
    match = _DEVICE.search(text)
    if match:
        return match.group(1)
    return "cuda:0" if ("cuda" in text.lower() or name == "OutOfMemoryError") else None


def memory_usage(device: str) -> Optional[dict]:
    """Bytes on ``device``: ``total``, ``free`` (the driver's view, every process), ``warp`` and
    ``warp_peak`` (this process's Warp memory pool now and at its highest), ``torch_allocated``
    and ``torch_reserved`` (this process's torch caching allocator). None when the device cannot
    be queried (no CUDA here)."""
    try:
        import warp as wp

        dev = wp.get_device(device)
        if not dev.is_cuda:
            return None
        out = {"total": int(dev.total_memory), "free": int(dev.free_memory), "warp": 0, "warp_peak": 0,
               "torch_allocated": 0, "torch_reserved": 0}
        if wp.is_mempool_enabled(dev):
            out["warp"] = int(wp.get_mempool_used_mem_current(dev))
            out["warp_peak"] = int(wp.get_mempool_used_mem_high(dev))
    except Exception:  # noqa: BLE001 - no CUDA, no Warp: nothing to report
        return None
    try:
        import torch

        if torch.cuda.is_available():
            out["torch_allocated"] = int(torch.cuda.memory_allocated(device))
            out["torch_reserved"] = int(torch.cuda.memory_reserved(device))
    except Exception:  # noqa: BLE001
        pass
    return out


def _gb(b: float) -> str:
    return f"{b / 1e9:.1f} GB"


def format_memory_note(device: str, usage: Optional[dict]) -> str:
    """One line: the card's memory and who holds it (``usage`` from :func:`memory_usage`), and
    what lowers it."""
    hint = ("fewer runs on this GPU (benchmark --jobs-per-gpu), SimConfig.keep_tapes false, or a coarser dx "
            "lower what a run needs")
    if usage is None:
        return f"{device} ran out of memory (its usage could not be read); {hint}"
    mine = usage["warp"] + usage["torch_reserved"]
    others = max(usage["total"] - usage["free"] - mine, 0)
    return (f"{device}: {_gb(usage['total'])} in all, {_gb(usage['free'])} free; this run holds {_gb(mine)} "
            f"(Warp {_gb(usage['warp'])}, peak {_gb(usage['warp_peak'])}; torch {_gb(usage['torch_allocated'])} "
            f"allocated, {_gb(usage['torch_reserved'])} reserved); other processes about {_gb(others)}; {hint}")


def oom_note(err: BaseException) -> str:
    """:func:`format_memory_note` for a CUDA out-of-memory error, else ""."""
    device = oom_device(err)
    if device is None:
        return ""
    return format_memory_note(device, memory_usage(device))
