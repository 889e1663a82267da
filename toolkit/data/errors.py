"""The one error type of the dataset readers, and checked file access that raises it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["DatasetError", "require_file", "load_json", "field"]


class DatasetError(ValueError):
    """A dataset on disk is missing, incomplete or malformed; the message names the file."""


def require_file(path: Path, what: str) -> Path:
    """Return ``path`` if it is a file, else raise :class:`DatasetError` saying what was expected."""
    if not path.is_file():
        raise DatasetError(f"missing file {path}: expected {what}")
    return path


def load_json(path: Path, what: str) -> Any:
    """Parse a JSON file; a missing file or a syntax error raises :class:`DatasetError`."""
    require_file(path, what)
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DatasetError(
            f"malformed JSON in {path} at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path} is not UTF-8 text ({exc})") from None


def field(mapping: Any, key: str, path: Path, where: str) -> Any:
    """``mapping[key]``, or a :class:`DatasetError` naming the file, the entry and the field."""
    if not isinstance(mapping, dict):
        raise DatasetError(f"{path}: {where} must be a JSON object, got {type(mapping).__name__}")
    if key not in mapping:
        raise DatasetError(f"{path}: {where} has no field {key!r} (fields: {sorted(mapping)})")
    return mapping[key]
