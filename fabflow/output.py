"""Atomic output folders.

A run writes into a fresh staging folder beside the destination; only when the
whole run has completed is the staging folder swapped into place. A run that
fails leaves the destination exactly as it was before (absent, or holding the
previous complete result) and removes its staging folder.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np


@contextlib.contextmanager
def atomic_output_dir(out: str | Path) -> Iterator[Path]:
    """Yield a staging folder that replaces ``out`` when the block completes.

    Parameters
    ----------
    out
        The destination folder. Its parent is created if needed. An existing
        ``out`` is replaced only after the block has finished without error.

    Yields
    ------
    Path
        An empty folder on the same file system as ``out``; write everything there.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists() and not out.is_dir():
        from fabflow.errors import InputError

        raise InputError("output path exists and is not a folder", source=out)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    try:
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    previous = None
    if out.exists():
        previous = Path(tempfile.mkdtemp(prefix=f".{out.name}.previous-", dir=out.parent))
        previous.rmdir()
        out.rename(previous)
    staging.rename(out)
    if previous is not None:
        shutil.rmtree(previous, ignore_errors=True)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot serialise {type(obj).__name__} to JSON")


def write_json(path: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON, converting numpy arrays and scalars.

    Parameters
    ----------
    path
        Target file; its parent folder must exist.
    data
        JSON-compatible data, possibly holding numpy arrays.
    """
    path = Path(path)
    path.write_text(json.dumps(data, indent=2, default=_json_default) + "\n", encoding="utf-8")
    return path
