"""The preview in a real browser: Debian's chromium driven by playwright, headless.

Opens the live page and the exported HTML file (with every network request
blocked), waits for the scene, moves the step slider and checks that the
screenshots are not blank and differ between steps. Screenshots are kept in
``test-artifacts/preview/``.
"""

from __future__ import annotations

import io
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT
from PIL import Image

from fabflow.preview.app import serve
from fabflow.preview.export import export_html
from fabflow.preview.model import PreviewModel, build_model
from fabflow.preview.synthetic import PointArm, wall_design

pytestmark = pytest.mark.browser

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
ARTIFACTS = ROOT / "test-artifacts" / "preview"
VIEWPORT = {"width": 1500, "height": 760}
TIMEOUT_MS = 180_000
"""Software rendering on a loaded machine is slow; be patient before failing."""
PANEL_WIDTH = 420
"""Pixels at the right of the live page covered by viser's control panel."""


@pytest.fixture(scope="module")
def model() -> PreviewModel:
    elements, plan = wall_design(n_rows=6, n_per_row=6, n_stations=3)
    return build_model(elements, plan, name="wall", arm=PointArm())


@pytest.fixture(scope="module")
def browser() -> Iterator:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        yield b
        b.close()


def wait_until(cond: Callable[[], bool], timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise AssertionError("timed out waiting for the page")
        time.sleep(0.1)


def canvas_shot(page, name: str, panel: bool = False) -> np.ndarray:
    """Screenshot of the 3D canvas, saved as an artifact, as an (H, W, 3) array.

    With ``panel`` the part of the canvas under the control panel is cut off, so
    only the 3D scene is compared.
    """
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.wait_for_timeout(1500)
    box = page.evaluate(
        """() => {
            let best = null;
            for (const c of document.querySelectorAll("canvas")) {
                const r = c.getBoundingClientRect();
                if (!best || r.width * r.height > best.width * best.height)
                    best = {x: r.x, y: r.y, width: r.width, height: r.height};
            }
            return best;
        }"""
    )
    assert box is not None and box["width"] > 100 and box["height"] > 100, box
    if panel:
        box["width"] -= PANEL_WIDTH
    png = page.screenshot(clip=box, timeout=180_000)
    (ARTIFACTS / f"{name}.png").write_bytes(png)
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def assert_not_blank(img: np.ndarray) -> None:
    flat = img.reshape(-1, 3)
    colours, counts = np.unique(flat, axis=0, return_counts=True)
    background = colours[np.argmax(counts)]
    share = np.mean(np.any(np.abs(flat - background) > 12, axis=1))
    assert share > 0.03, f"only {share:.1%} of the canvas differs from the background"
    assert len(colours) > 50


def assert_differ(a: np.ndarray, b: np.ndarray) -> None:
    changed = np.mean(np.any(np.abs(a - b) > 12, axis=2))
    assert changed > 0.003, f"only {changed:.2%} of the pixels changed between steps"


def test_live_page_moves_through_the_steps(browser, model: PreviewModel) -> None:
    preview = serve(model, port=0)
    try:
        page = browser.new_page(viewport=VIEWPORT)
        page.set_default_timeout(TIMEOUT_MS)
        page.goto(preview.url)
        page.wait_for_selector("canvas", timeout=60_000)
        page.get_by_text("Build sequence").first.wait_for(timeout=60_000)
        slider = page.get_by_role("slider").first
        slider.wait_for(timeout=30_000)
        full = canvas_shot(page, "live_full", panel=True)
        assert_not_blank(full)

        slider.focus()
        page.keyboard.press("Home")
        wait_until(lambda: preview.scene.step == 0)
        start = canvas_shot(page, "live_step0", panel=True)
        assert_not_blank(start)
        for _ in range(5):
            page.keyboard.press("ArrowRight")
        wait_until(lambda: preview.scene.step == 5)
        five = canvas_shot(page, "live_step5", panel=True)
        assert_not_blank(five)
        assert_differ(start, five)
        assert_differ(five, full)
        page.close()
    finally:
        preview.stop()


def scene_changes(page, seek, name: str, early: float, late: float) -> None:  # type: ignore[no-untyped-def]
    """The canvas at two points of the playback: neither blank, and different."""
    seek(early)
    first = canvas_shot(page, f"{name}_early")
    seek(late)
    second = canvas_shot(page, f"{name}_late")
    assert_not_blank(first)
    assert_not_blank(second)
    assert_differ(first, second)


def open_offline(browser, path: Path):  # type: ignore[no-untyped-def]
    """Open an exported file with the network blocked; pause it at its first frame.

    Returns the context, the page, a ``seek(fraction)`` on its time slider and the
    list of blocked requests (to stay empty).
    """
    context = browser.new_context(viewport=VIEWPORT)
    external: list[str] = []

    def block(route) -> None:
        url = route.request.url
        if url.startswith(("file:", "data:", "blob:")):
            route.continue_()
        else:
            external.append(url)
            route.abort()

    context.route("**/*", block)
    page = context.new_page()
    page.set_default_timeout(TIMEOUT_MS)
    loaded: list[str] = []
    page.on(
        "console", lambda m: loaded.append(m.text) if "Embedded data loaded" in m.text else None
    )
    page.goto(path.as_uri())
    page.wait_for_selector("canvas", timeout=60_000)
    wait_until(lambda: bool(loaded), timeout=60.0)
    page.keyboard.press("Space")  # pause playback
    track = page.locator(".mantine-Slider-track").first
    track.wait_for(timeout=60_000)
    box = track.bounding_box()
    assert box is not None

    def seek(fraction: float) -> None:
        page.mouse.click(box["x"] + fraction * box["width"], box["y"] + box["height"] / 2)

    return context, page, seek, external


def test_exported_file_plays_offline(browser, model: PreviewModel, tmp_path: Path) -> None:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    out = ARTIFACTS / "wall.html"
    export_html(model, out, colour_mode="station", seconds_per_step=0.5)
    context, page, seek, external = open_offline(browser, out)
    scene_changes(page, seek, "export", 0.08, 0.9)
    assert external == []
    context.close()


def test_stone_wall_preview_plays_offline(browser, tmp_path: Path) -> None:
    from helpers import small_stone_wall

    from fabflow.preview.stones import export_stone_html
    from fabflow.project import load_project
    from fabflow.stones.run import run_stone_wall

    project = load_project(small_stone_wall(tmp_path))
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    out = ARTIFACTS / "stone_wall.html"
    result = export_stone_html(run_stone_wall(project, seed=4), out, project, 1.0)
    assert result.n_steps == 4
    context, page, seek, external = open_offline(browser, out)
    scene_changes(page, seek, "stones", 0.05, 0.95)
    assert external == []
    context.close()
