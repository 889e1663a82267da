"""Repository-wide pytest set-up: Warp's kernel cache lives in a repo-local ignored folder
(``.warp_cache/<warp version>``, via ``WARP_CACHE_PATH``, read when Warp initializes)."""

from __future__ import annotations

import os
import pathlib

_ROOT = pathlib.Path(__file__).resolve().parent
os.environ.setdefault("WARP_CACHE_PATH", str(_ROOT / ".warp_cache"))


def pytest_configure(config):  # noqa: D103
    import warp as wp

    wp.config.quiet = True
    wp.init()
