"""The live preview: a viser server with the scene and its control panel."""

from __future__ import annotations

from dataclasses import dataclass

import viser

from fabflow.preview.gui import PreviewGui, ProgramSource
from fabflow.preview.model import PreviewModel
from fabflow.preview.scene import PreviewScene
from fabflow.project import Project


@dataclass
class LivePreview:
    """A running live preview.

    Attributes
    ----------
    server
        The viser server (``server.get_port()`` is the port actually bound).
    scene
        The scene, shared by every connected browser.
    gui
        The control panel.
    """

    server: viser.ViserServer
    scene: PreviewScene
    gui: PreviewGui

    @property
    def url(self) -> str:
        """The address to open in a browser."""
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def stop(self) -> None:
        """Stop playing and shut the server down."""
        self.gui.stop()
        self.server.stop()


def serve(
    model: PreviewModel,
    project: Project | None = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    colour_mode: str = "station",
    program_source: ProgramSource | None = None,
    verbose: bool = False,
) -> LivePreview:
    """Start a viser server showing the model, with the control panel.

    Parameters
    ----------
    model
        The preview model.
    project
        The project (site, localization setup), if any.
    host
        Interface to bind; the default serves this machine only.
    port
        Port to try first (the next free one is taken if busy; 0 for any).
    colour_mode
        Initial colour mode.
    program_source
        The download button's program generator (see :class:`PreviewGui`).
    verbose
        Let viser print its banner.
    """
    server = viser.ViserServer(host=host, port=port, verbose=verbose)
    try:
        scene = PreviewScene(server, model, project, colour_mode=colour_mode)
        gui = PreviewGui(server, scene, program_source)
    except BaseException:
        server.stop()
        raise
    return LivePreview(server=server, scene=scene, gui=gui)
