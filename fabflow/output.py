"""Atomic output folders.

A run writes into a fresh staging folder beside the destination; only when the
whole run has completed is the staging folder swapped into place. A run that
fails leaves the destination exactly as it was before (absent, or holding the
previous complete result) and removes its staging folder.

fabflow only ever replaces a folder it wrote itself (it carries the marker file
:data:`MARKER`) or an empty one: pointing ``-o`` at a project folder or a home
directory is refused, never wiped.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from fabflow.errors import InputError

MARKER = ".fabflow-output"
"""File in every output folder fabflow writes; only such folders are replaced."""


def _check_destination(out: Path) -> None:
    if out.name in ("", ".", "..") or out.resolve() == Path(out.resolve().anchor):
        raise InputError("choose a named output folder, not the current or root folder", out)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", out)
    if out.is_dir() and any(out.iterdir()) and not (out / MARKER).exists():
        raise InputError(
            "output folder exists, is not empty and was not written by fabflow; "
            "choose another folder or remove it first (fabflow only replaces its own outputs)",
            out,
        )


@contextlib.contextmanager
def atomic_output_dir(out: str | Path) -> Iterator[Path]:
    """Yield a staging folder that replaces ``out`` when the block completes.

    Parameters
    ----------
    out
        The destination folder. Its parent is created if needed. An existing
        ``out`` is replaced only after the block has finished without error, and
        only if it is empty or an earlier fabflow output.

    Yields
    ------
    Path
        An empty folder on the same file system as ``out``; write everything there.

    Raises
    ------
    InputError
        When ``out`` cannot be used (a file, a foreign non-empty folder, not
        writable).
    """
    out = Path(out)
    _check_destination(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    except OSError as exc:
        raise InputError(f"cannot create the output folder: {exc.strerror or exc}", out) from None
    # mkdtemp makes a private folder; give the result the usual permissions.
    umask = os.umask(0)
    os.umask(umask)
    staging.chmod(0o777 & ~umask)
    (staging / MARKER).write_text("written by fabflow; replaced by the next run\n")
    try:
        yield staging
        previous = None
        if out.exists():
            previous = Path(tempfile.mkdtemp(prefix=f".{out.name}.previous-", dir=out.parent))
            previous.rmdir()
            out.rename(previous)
        try:
            staging.rename(out)
        except OSError as exc:
            if previous is not None:
                previous.rename(out)
            raise InputError(
                f"cannot move the results into place: {exc.strerror or exc}", out
            ) from None
        if previous is not None:
            shutil.rmtree(previous, ignore_errors=True)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot serialise {type(obj).__name__} to JSON")


def json_safe(data: Any) -> Any:
    """``data`` with numpy arrays and scalars as lists and numbers, NaN and infinity as None.

    JSON has no NaN or infinity (Python's ``json`` would write the invalid
    tokens ``NaN`` and ``Infinity``); a number that is not available or not
    bounded is written as ``null``.
    """
    if isinstance(data, dict):
        return {k: json_safe(v) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [json_safe(v) for v in data]
    if isinstance(data, np.ndarray):
        return json_safe(data.tolist())
    if isinstance(data, np.generic):
        data = data.item()
    if isinstance(data, float) and not math.isfinite(data):
        return None
    return data


def json_text(data: Any) -> str:
    """Indented JSON text of ``data`` (see :func:`json_safe`), with a final newline."""
    return json.dumps(json_safe(data), indent=2, default=_json_default, allow_nan=False) + "\n"


def write_json(path: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON (numpy converted, NaN and infinity as null).

    Parameters
    ----------
    path
        Target file; its parent folder must exist.
    data
        JSON-compatible data, possibly holding numpy arrays.
    """
    path = Path(path)
    path.write_text(json_text(data), encoding="utf-8")
    return path
