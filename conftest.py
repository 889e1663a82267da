"""Repository-wide pytest set-up: Warp's kernel cache lives in a repo-local ignored folder."""

from __future__ import annotations

import os
import pathlib

_ROOT = pathlib.Path(__file__).resolve().parent
os.environ.setdefault("WARP_CACHE_PATH", str(_ROOT / ".warp_cache"))


def pytest_configure(config):  # noqa: D103
    import warp as wp

    wp.config.kernel_cache_dir = os.environ["WARP_CACHE_PATH"]
    wp.config.quiet = True
    wp.init()
