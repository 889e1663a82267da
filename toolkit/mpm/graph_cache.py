"""Captured Warp graphs of a simulator, by key, captured once a key has been used often enough.

A capture records every launch of a chain (on the CPU, Warp's API capture builds a record per
launch, which costs more than launching it), and a replay then skips the Python cost of every
launch. A chain that runs once (a probe, the last iteration before the substeps change) only
pays the capture. :class:`GraphCache` therefore runs a key launch by launch until its
``min_uses``-th use, and captures it then: 2 on the CPU, 1 (the first use) on CUDA.
"""

from __future__ import annotations

from typing import Hashable

__all__ = ["GraphCache"]


class GraphCache(dict):
    """``key -> captured graph`` (with whatever the caller keeps beside it).

    Args:
        min_uses: the use of a key at which it is captured (1: the first).
    """

    def __init__(self, min_uses: int = 1):
        super().__init__()
        if min_uses < 1:
            raise ValueError(f"min_uses must be >= 1, got {min_uses}")
        self.min_uses = int(min_uses)
        self._uses: dict[Hashable, int] = {}

    def should_capture(self, key: Hashable) -> bool:
        """Whether this use of ``key`` replays its graph (captured now if it is not yet); False:
        run the chain launch by launch (the use is counted)."""
        if key in self:
            return True
        uses = self._uses.get(key, 0) + 1
        if uses >= self.min_uses:
            self._uses.pop(key, None)
            return True
        self._uses[key] = uses
        return False
