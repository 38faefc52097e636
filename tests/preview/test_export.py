"""The offline HTML export: self-contained, every step recorded as updates, small."""

from __future__ import annotations

import base64
import re
from pathlib import Path

import msgspec
import pytest
import zstandard

from fabflow.errors import InputError
from fabflow.preview.arm import RobotArm
from fabflow.preview.export import MAX_EXPORT_BYTES, export_html
from fabflow.preview.model import build_model
from fabflow.preview.synthetic import PointArm, translation, wall_design
from fabflow.robots import get_robot

T_FLANGE_TOOL = translation(0.0, 0.0, 0.2)
UPDATE_KINDS = {
    "SceneNodeUpdateMessage",
    "SetPositionMessage",
    "SetOrientationMessage",
    "SetSceneNodeVisibilityMessage",
}


@pytest.fixture(scope="module")
def model():
    elements, plan = wall_design()
    return build_model(elements, plan, arm=PointArm(), T_flange_tool=T_FLANGE_TOOL)


def decode_embedded(html: str) -> dict:
    b64 = re.search(r'__VISER_EMBED_DATA__="([^"]+)"', html).group(1)
    raw = base64.b64decode(b64)
    inner = zstandard.ZstdDecompressor().decompress(raw[8:], max_output_size=1 << 30)
    n = int.from_bytes(inner[:8], "little")
    return msgspec.msgpack.decode(inner[8 : 8 + n])


def test_export_is_one_small_offline_file_that_plays_every_step(model, tmp_path: Path) -> None:
    out = tmp_path / "wall.html"
    result = export_html(model, out, seconds_per_step=0.25)
    html = out.read_text(encoding="utf-8")
    assert result.size_bytes == out.stat().st_size < MAX_EXPORT_BYTES
    urls = set(re.findall(r"(?:https?:)?//[a-zA-Z0-9.-]+\.[a-z]{2,}[^\s\"')]*", html))
    assert urls <= {"//www.w3.org/2000/svg", "http://www.w3.org/2000/svg"}, urls
    data = decode_embedded(html)
    assert data["durationSeconds"] == pytest.approx(1.0 + 0.25 * model.n_steps + 2.0)
    times = sorted({t for t, _ in data["messages"]})
    assert len(times) == model.n_steps + 1
    later = [msg for t, msg in data["messages"] if t > 0]
    assert later and {m["type"] for m in later} <= UPDATE_KINDS
    assert not list(tmp_path.glob(".*tmp"))


def test_export_rejects_a_missing_folder(model, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="does not exist"):
        export_html(model, tmp_path / "nope" / "x.html")


def test_cabin_sized_export_stays_far_under_the_size_budget(tmp_path: Path) -> None:
    elements, plan = wall_design(n_rows=30, n_per_row=25, n_stations=3, n_prebuilt=200)
    m = build_model(elements, plan, arm=RobotArm(get_robot("kuka_kr60_3"), T_FLANGE_TOOL))
    assert len(m.block_index) >= 737 and m.n_steps >= 536
    result = export_html(m, tmp_path / "big.html", colour_mode="state")
    assert result.size_bytes < MAX_EXPORT_BYTES / 4
