"""The control panel of the live preview: step slider, play, dropdowns, info, downloads."""

from __future__ import annotations

import html
import threading
import time
from collections.abc import Callable

import numpy as np
import viser

from fabflow.errors import FabflowError
from fabflow.json_format import json_text
from fabflow.positioning.result import BasePose
from fabflow.preview.model import PreviewModel
from fabflow.preview.scene import PreviewScene

ProgramSource = Callable[[int], tuple[str, bytes]]
"""Given a work-package index, the file name and bytes of that station's program."""

METHOD_NAMES = {"uwb": "UWB", "total_station": "total station", "icp": "LiDAR ICP"}


def work_package_json(model: PreviewModel, package: int) -> tuple[str, bytes]:
    """A work package as a JSON program: station, base pose and targets in the base frame.

    The targets are ``T_base_tool = inv(T_world_base) @ T_world_target`` (metres),
    the form a controller takes them in; the base pose is the planned one, or the
    localized one when the model holds a localization result for the visit.
    """
    m = model
    sid = m.station_ids[int(m.package_station[package])]
    result = m.localization_at(package)
    T_world_base = (
        np.asarray(result.T_world_base, dtype=float)
        if result is not None
        else m.T_world_base[package]
    )
    steps = np.flatnonzero(m.step_package == package)
    T_base_targets = np.linalg.inv(T_world_base) @ m.T_world_targets[steps]
    data = {
        "project": m.name,
        "work_package": int(package),
        "station": sid,
        "T_world_platform": m.T_world_platform[package].tolist(),
        "lift": float(m.lift[package]),
        "T_world_base": T_world_base.tolist(),
        "base_pose_source": "localized" if result is not None else "planned",
        "elements": [m.elements[int(i)].id for i in m.sequence[steps]],
        "T_base_targets": T_base_targets.tolist(),
    }
    name = f"{m.name}_wp{package:02d}_{sid}.json".replace(" ", "_")
    return name, json_text(data, indent=1).encode()


def legend_html(model: PreviewModel, mode: str) -> str:
    """The colour legend of a mode as a small HTML table of swatches."""
    rows = "".join(
        f'<div style="display:flex;align-items:center;gap:6px;margin:1px 0">'
        f'<span style="display:inline-block;width:14px;height:14px;border-radius:3px;'
        f'background:rgb{rgb}"></span><span>{html.escape(label)}</span></div>'
        for label, rgb in model.legend(mode)
    )
    return f'<div style="font-size:0.8em;padding:2px 4px">{rows}</div>'


def integrity_line(result: BasePose) -> str:
    """One markdown line on a localization's integrity; failed and degraded ones in red."""
    integ = result.integrity
    if integ is None:
        return '<span style="color:#c00000">**Integrity: untested**</span>'
    if integ.failed:
        return (
            f'<span style="color:#c00000">**Integrity FAILED**: {html.escape(integ.reason)}</span>'
        )
    degraded = integ.checks.get("degraded")
    pl = integ.protection_level.get("horizontal")
    level = f", protection level {1000 * pl:.1f} mm" if pl is not None else ""
    if degraded:
        return f'<span style="color:#c00000">**Integrity degraded**: {html.escape(degraded)}</span>'
    if integ.status == "excluded":
        return f"Integrity: passed after leaving out {html.escape(integ.reason[9:])}{level}"
    return f"Integrity: ok{level}"


def _red(text: str) -> str:
    return f'<span style="color:#c00000">{text}</span>'


def step_info(model: PreviewModel, step: int) -> str:
    """Markdown describing a step: element, station, localization, arm, deviation."""
    m = model
    step = m.check_step(step)
    lines = [f"**Step {step} / {m.n_steps}**", ""]
    e = m.element_at(step)
    if e is None:
        lines.append("Nothing placed yet.")
    else:
        where = f"layer {e.layer}" + (f", part {e.part}" if e.part else "")
        lines.append(f"Element **{e.id}** ({e.type.replace('_', ' ')}, {where})")
    p = m.package_at(step)
    if p >= 0:
        sid = m.station_ids[int(m.package_station[p])]
        lines.append(
            f"Station **{sid}**: visit {p + 1} of {len(m.T_world_platform)}, "
            f"lift {m.lift[p]:.2f} m, travel {m.travel[p]:.2f} m"
        )
        result = m.localization_at(p)
        method = METHOD_NAMES.get(m.method, m.method)
        if result is None:
            lines.append(f"Localization: {method}, planned pose (no result loaded)")
        else:
            res = np.asarray(result.residuals, dtype=float)
            norms = np.linalg.norm(res.reshape(res.shape[0], -1), axis=1) if res.size else res
            shown = ", ".join(f"{1000 * r:.1f}" for r in norms[:8])
            more = " ..." if norms.size > 8 else ""
            sigma = np.sqrt(np.clip(np.diag(result.covariance)[:3], 0.0, None)) * 1000
            lines.append(
                f"Localization: {METHOD_NAMES.get(result.method, result.method)}, "
                f"RMSE {1000 * result.rmse:.1f} mm, "
                f"σ xyz {sigma[0]:.1f}/{sigma[1]:.1f}/{sigma[2]:.1f} mm"
            )
            if norms.size:
                lines.append(f"Residuals (mm): {shown}{more}")
            lines.append(integrity_line(result))
    if m.arm is not None and not m.arm_reached[step]:
        lines.append("**Arm: target not reachable**")
    if e is not None and m.deviation is not None:
        d = m.deviation[m.elements.index(e)]
        if np.isfinite(d):
            ok = "within" if d <= m.tolerance else "**outside**"
            lines.append(
                f"Simulated deviation {1000 * d:.1f} mm ({ok} {1000 * m.tolerance:.0f} mm)"
            )
    return "  \n".join(lines)


class PreviewGui:
    """The control panel of a live preview.

    Parameters
    ----------
    server
        The viser server the scene is drawn on.
    scene
        The scene the controls drive.
    program_source
        Gives a work package's program for the download button; defaults to
        :func:`work_package_json`.
    """

    def __init__(
        self,
        server: viser.ViserServer,
        scene: PreviewScene,
        program_source: ProgramSource | None = None,
    ) -> None:
        self.server = server
        self.scene = scene
        self.model = m = scene.model
        self.program_source = program_source or (lambda p: work_package_json(m, p))
        self._playing = threading.Event()
        self._thread: threading.Thread | None = None
        self._syncing = False
        gui = server.gui
        gui.configure_theme(control_width="large", dark_mode=False, show_logo=False)
        gui.set_panel_label(f"fabflow · {m.name}")
        with gui.add_folder("Build sequence"):
            self.slider = gui.add_slider(
                "Step", min=0, max=max(m.n_steps, 1), step=1, initial_value=scene.step
            )
            self.play = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
            self.speed = gui.add_slider(
                "Steps / s", min=1, max=60, step=1, initial_value=min(20, max(1, m.n_steps // 20))
            )
            self.station = gui.add_dropdown(
                "Station",
                options=m.station_ids or ("-",),
                initial_value=m.station_at(scene.step) or "-",
            )
        with gui.add_folder("Display"):
            self.colour = gui.add_dropdown(
                "Colour by", options=m.colour_modes(), initial_value=scene.colour_mode
            )
            self.ghost = gui.add_checkbox("Ghost of unbuilt", initial_value=scene.ghost_enabled)
            self.legend = gui.add_html(legend_html(m, scene.colour_mode))
        with gui.add_folder("Current step"):
            self.info = gui.add_markdown(step_info(m, scene.step))
            self.download = gui.add_button("Download station program", icon=viser.Icon.DOWNLOAD)

        self.slider.on_update(lambda _: self._on_step())
        self.play.on_click(lambda _: self.toggle_play())
        self.station.on_update(lambda _: self._on_station())
        self.colour.on_update(lambda _: self._on_colour())
        self.ghost.on_update(lambda _: self.scene.set_ghost(self.ghost.value))
        self.download.on_click(self._on_download)

    def _on_step(self) -> None:
        step = int(self.slider.value)
        self.scene.set_step(step)
        self.info.content = step_info(self.model, step)
        sid = self.model.station_at(step)
        if sid is not None and sid != self.station.value:
            self._syncing = True
            try:
                self.station.value = sid
            finally:
                self._syncing = False

    def _on_station(self) -> None:
        if self._syncing or self.station.value not in self.model.station_ids:
            return
        self.slider.value = self.model.first_step_of_station(self.station.value)

    def _on_colour(self) -> None:
        self.scene.set_colour_mode(self.colour.value)
        self.legend.content = legend_html(self.model, self.colour.value)

    def _on_download(self, event: viser.GuiEvent) -> None:
        p = self.model.package_at(self.scene.step)
        if p < 0 or event.client is None:
            return
        try:
            name, content = self.program_source(p)
        except FabflowError as exc:
            event.client.add_notification(
                title="No program for this station", body=str(exc), color="red"
            )
            return
        event.client.send_file_download(name, content)

    @property
    def playing(self) -> bool:
        """Whether the sequence is playing."""
        return self._playing.is_set()

    def toggle_play(self) -> None:
        """Start playing from the current step (from 0 at the end), or pause."""
        if self._playing.is_set():
            self._playing.clear()
            return
        if int(self.slider.value) >= self.model.n_steps:
            self.slider.value = 0
        self._playing.set()
        self.play.label = "Pause"
        self.play.icon = viser.Icon.PLAYER_PAUSE
        self._thread = threading.Thread(target=self._play_loop, daemon=True)
        self._thread.start()

    def _play_loop(self) -> None:
        try:
            while self._playing.is_set() and int(self.slider.value) < self.model.n_steps:
                self.slider.value = int(self.slider.value) + 1
                time.sleep(1.0 / float(self.speed.value))
        finally:
            self._playing.clear()
            self.play.label = "Play"
            self.play.icon = viser.Icon.PLAYER_PLAY

    def stop(self) -> None:
        """Stop playing and wait for the play thread to end."""
        self._playing.clear()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
