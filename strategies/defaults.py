"""Iteration counts and batches of the paper (ProJo4D appendix, GIC's schedule)."""

from __future__ import annotations

__all__ = ["STAGE1_ITERATIONS", "STAGE2_ITERATIONS", "stage2_iterations", "EARLY_FRAMES", "STAGE1_BATCH", "STAGE2_BATCH",
           "APPEARANCE_ITERATIONS"]

#: Stage 1 (XAS for ProJo4D, S for GIC): 100 iterations on the first frames.
STAGE1_ITERATIONS = 100
#: Stage 2 (XASM for ProJo4D, M for GIC) per material family, PAC-NeRF schedule (paper appendix).
STAGE2_ITERATIONS = {
    "neo_hookean": 150,
    "neo_hookean_simplicits": 150,
    "sand": 150,
    "newtonian": 250,
    "non_newtonian": 350,
    "plasticine": 300,
}
#: the first frames used by velocity stages ("first frames" in GIC / ProJo4D Stage 1).
EARLY_FRAMES = 3
#: cameras x frames per iteration (paper Table 10): Stage 1 3x3, Stage 2 3x20.
STAGE1_BATCH = (3, 3)
STAGE2_BATCH = (3, 20)
#: GIC's appearance refinement ("Stage 3"), 1 camera x 1 frame per iteration.
APPEARANCE_ITERATIONS = 40_000


def stage2_iterations(material: str | None, default: int = 150) -> int:
    """Stage-2 iterations for a material (150 for unknown or third-party materials)."""
    return STAGE2_ITERATIONS.get(material or "", default)
