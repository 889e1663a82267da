"""GPU out-of-memory errors say who holds the card (toolkit.device_memory): detection of the
errors Warp and torch raise, the arithmetic of the note, and the error boundary's second line."""

from __future__ import annotations

import pytest

from toolkit.device_memory import format_memory_note, oom_device, oom_note
from toolkit.errors import EXIT_FAILURE, describe_error

GB = 10**9


@pytest.mark.parametrize("err, device", [
    (RuntimeError("Failed to allocate 173081600 bytes on device 'cuda:0'"), "cuda:0"),
    (RuntimeError("Warp CUDA error 2: out of memory (in function wp_alloc_device_async, warp.cu:812)"), "cuda:0"),
    (RuntimeError("Failed to allocate 10518552 bytes on device 'cuda:3'"), "cuda:3"),
    (RuntimeError("the grid left the domain"), None),
    (ValueError("out of range"), None),
])
def test_out_of_memory_errors_are_recognised(err, device):
    assert oom_device(err) == device


def test_the_note_splits_the_card_between_this_run_and_the_others():
    usage = {"total": 80 * GB, "free": 1 * GB, "warp": 30 * GB, "warp_peak": 34 * GB,
             "torch_allocated": 3 * GB, "torch_reserved": 4 * GB}
    note = format_memory_note("cuda:0", usage)
    assert note.startswith("cuda:0: 80.0 GB in all, 1.0 GB free; this run holds 34.0 GB (Warp 30.0 GB, peak 34.0 GB;")
    assert "other processes about 45.0 GB" in note  # 80 - 1 - (30 + 4)
    assert "--jobs-per-gpu" in note and "keep_tapes" in note


def test_the_error_boundary_adds_the_note_to_an_out_of_memory_failure():
    code, message = describe_error(RuntimeError("Failed to allocate 173081600 bytes on device 'cuda:0'"))
    assert code == EXIT_FAILURE
    first, second = message.split("\n")
    assert first.startswith("RuntimeError: Failed to allocate 173081600 bytes") and "--debug" in first
    assert second.strip() == oom_note(RuntimeError("Failed to allocate 1 bytes on device 'cuda:0'"))
    assert "cuda:0" in second and "fewer runs on this GPU" in second
    # any other failure keeps its one line
    assert "\n" not in describe_error(RuntimeError("the simulation diverged"))[1]
