"""Atomic artifact writes and setting aside corrupt files.

Every artifact of a run is written to a temporary file in the same folder and renamed over its
final name (``os.replace``, atomic on POSIX), so a kill at any moment leaves either the previous
file or the complete new one, never a truncated one. A file that is still found unreadable (a
copy interrupted by hand, a full disk) is renamed to ``<name>.corrupt`` by :func:`set_aside` so
that the run can fall back to an earlier one or recompute it, and the user can still inspect it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator

__all__ = ["atomic_path", "write_text", "write_json", "torch_save", "write_with", "set_aside", "CorruptArtifactError", "load_error_reason"]

log = logging.getLogger(__name__)


class CorruptArtifactError(ValueError):
    """An artifact file exists but cannot be read (the message names the file)."""


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it is renamed to ``path``.

    On an exception the temporary file is removed and ``path`` is left as it was. The temporary
    name keeps the final suffix (``.x.tmp1234.npz``), so writers that add a suffix do not.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) atomically to ``path``."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_json(path: str | Path, data: Any, indent: int | None = 2) -> Path:
    """Write ``data`` as JSON atomically to ``path``."""
    return write_text(path, json.dumps(data, indent=indent))


def torch_save(obj: Any, path: str | Path) -> Path:
    """``torch.save`` to ``path`` atomically."""
    import torch

    with atomic_path(path) as tmp:
        torch.save(obj, tmp)
    return Path(path)


def write_with(path: str | Path, writer: Callable[[Path], Any]) -> Path:
    """Call ``writer(tmp_path)`` and rename the result to ``path`` (for writers with their own API)."""
    with atomic_path(path) as tmp:
        writer(tmp)
    return Path(path)


def load_error_reason(err: BaseException) -> str:
    """A one-line reason for a failed ``torch.load`` (torch's own advice to pass
    ``weights_only=False`` would load arbitrary code, so it is not repeated)."""
    text = str(err).strip()
    if "weights only load failed" in text.lower() or "weights_only" in text:
        return "not a complete torch file"
    if "failed finding central directory" in text or "PytorchStreamReader" in text:
        return "truncated or not a torch file"
    return (text.splitlines()[0][:160] if text else type(err).__name__)


def set_aside(path: str | Path, reason: str) -> Path:
    """Rename an unreadable artifact to ``<name>.corrupt`` (numbered if taken) and log why."""
    path = Path(path)
    target = path.with_name(path.name + ".corrupt")
    k = 1
    while target.exists():
        k += 1
        target = path.with_name(f"{path.name}.corrupt{k}")
    os.replace(path, target)
    log.warning("%s is unreadable (%s); set aside as %s", path, reason, target.name)
    return target

