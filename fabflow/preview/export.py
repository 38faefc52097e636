"""One self-contained HTML file that plays the construction sequence offline.

The scene is built on a private viser server bound to 127.0.0.1 on a free
port; viser's scene serializer records the initial scene, then one update per
build step with a pause between them. The recording (zstd-compressed, base64)
is embedded in viser's single-file client build, so the file needs no server
and no network: open it in a browser and it plays, with a time slider to scrub
through the steps.
"""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import viser

from fabflow.errors import InputError
from fabflow.preview.model import PreviewModel
from fabflow.preview.scene import PreviewScene
from fabflow.project import Project

MAX_EXPORT_BYTES = 20 * 1024 * 1024
"""Size budget of an exported file (the cabin must stay under it)."""


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_html` wrote.

    Attributes
    ----------
    path
        The HTML file.
    size_bytes
        Its size.
    n_steps
        Build steps recorded.
    duration_s
        Playback length at 1x speed (seconds).
    seconds_per_step
        Playback time per build step (seconds).
    """

    path: Path
    size_bytes: int
    n_steps: int
    duration_s: float
    seconds_per_step: float


def check_export_target(path: str | Path) -> Path:
    """Check that ``path`` can be written as the export file (an existing folder, not a dir).

    Raises
    ------
    InputError
        If ``path`` is a folder or its folder does not exist.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError("export target is a folder; expected an .html file name", source=path)
    if not path.parent.is_dir():
        raise InputError("the folder of the export file does not exist", source=path)
    return path


def default_seconds_per_step(n_steps: int, target_s: float = 45.0) -> float:
    """Playback time per step so the whole sequence lasts about ``target_s`` seconds."""
    return min(0.5, max(0.02, target_s / max(n_steps, 1)))


@contextlib.contextmanager
def quiet_server() -> Iterator[viser.ViserServer]:
    """A viser server on 127.0.0.1 at a free port, its banner suppressed, stopped on exit."""
    sink = io.StringIO()
    with contextlib.redirect_stdout(sink):
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        yield server
    finally:
        with contextlib.redirect_stdout(sink):
            server.stop()


def record_html(
    server: viser.ViserServer,
    model: PreviewModel,
    project: Project | None = None,
    colour_mode: str = "state",
    seconds_per_step: float | None = None,
    ghost: bool = True,
) -> str:
    """Build the scene on ``server``, record every step and return the HTML text.

    Parameters
    ----------
    server
        A fresh server (nothing drawn on it yet).
    model, project, colour_mode, ghost
        As for :class:`~fabflow.preview.scene.PreviewScene`.
    seconds_per_step
        Playback time per build step; :func:`default_seconds_per_step` if ``None``.
    """
    dt = default_seconds_per_step(model.n_steps) if seconds_per_step is None else seconds_per_step
    if dt <= 0:
        raise InputError(f"seconds per step must be positive, got {dt}")
    # One atomic block around the whole recording: no browser is connected, so
    # nothing needs to be delivered until the end, and the server thread is not
    # woken for every message.
    with server.atomic():
        scene = PreviewScene(server, model, project, colour_mode=colour_mode, ghost=ghost, step=0)
        top = float(model.block_positions[:, 2].max(initial=0.0)) + 0.8
        centre = model.block_positions[:, :2].mean(axis=0) if len(model.block_positions) else (0, 0)
        server.scene.add_label(
            "/legend",
            text=f"{model.name}\n{model.legend_text(colour_mode)}",
            position=(float(centre[0]), float(centre[1]), top),
        )
        serializer = server.get_scene_serializer()
        serializer.insert_sleep(1.0)
        for k in range(1, model.n_steps + 1):
            scene.set_step(k)
            serializer.insert_sleep(dt)
        serializer.insert_sleep(2.0)
    return serializer.as_html()


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary name beside ``path`` and rename it into place."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def export_html(
    model: PreviewModel,
    path: str | Path,
    project: Project | None = None,
    colour_mode: str = "state",
    seconds_per_step: float | None = None,
    ghost: bool = True,
) -> ExportResult:
    """Write the construction sequence as one self-contained HTML file.

    The file is written to a temporary name beside ``path`` and renamed into
    place, so an existing file is never left half-written.

    Parameters
    ----------
    model
        The preview model.
    path
        Target ``.html`` file.
    project
        The project (site and localization setup), if any.
    colour_mode
        Block colours in the recording.
    seconds_per_step
        Playback time per build step (seconds); about 45 s in total if ``None``.
    ghost
        Show the elements not built yet as a faint ghost.
    """
    path = check_export_target(path)
    dt = default_seconds_per_step(model.n_steps) if seconds_per_step is None else seconds_per_step
    with quiet_server() as server:
        text = record_html(server, model, project, colour_mode, dt, ghost)
    data = text.encode("utf-8")
    write_atomic(path, data)
    return ExportResult(
        path=path,
        size_bytes=len(data),
        n_steps=model.n_steps,
        duration_s=1.0 + dt * model.n_steps + 2.0,
        seconds_per_step=dt,
    )
