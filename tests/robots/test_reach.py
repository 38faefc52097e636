"""Reachability maps and the mobile platform."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fabflow.errors import InputError, UnsupportedError
from fabflow.project import Platform, Tool
from fabflow.robots import MobilePlatform, get_robot, reach_map
from fabflow.robots import reach as reach_module
from fabflow.tasks.plan import Station

TOOL = np.eye(4)
TOOL[2, 3] = 0.2


@pytest.fixture(autouse=True)
def _isolated_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FABFLOW_CACHE_DIR", str(tmp_path))


def tool_down_poses(p: np.ndarray, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.tile(np.eye(4), (len(p), 1, 1))
    T[:, :3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.diag([1.0, -1.0, -1.0])
    T[:, :3, 3] = p
    return T


def ik_reachable(name: str, p: np.ndarray, n_yaw: int = 12) -> np.ndarray:
    """Ground truth: some sampled yaw has an IK solution within limits."""
    r = get_robot(name)
    out = np.zeros(len(p), dtype=bool)
    for yaw in np.arange(n_yaw) * 2 * np.pi / n_yaw:
        T = tool_down_poses(p, yaw) @ np.linalg.inv(TOOL)
        _, valid = r.ik_batch(T)
        out |= valid.any(axis=1)
    return out


@pytest.mark.parametrize("name", ["kuka_kr60_3", "ur10e"])
def test_reach_map_agrees_with_ik(name: str) -> None:
    rm = reach_map(name, TOOL, step=0.08, disk_cache=False)
    r = get_robot(name)
    rng = np.random.default_rng(0)
    ext = r.reach + 0.3
    p = rng.uniform([-ext, -ext, r.dh[0, 2] - ext], [ext, ext, r.dh[0, 2] + ext], (1500, 3))
    pred = rm.reachable(p)
    truth = ik_reachable(name, p)
    assert pred.sum() > 150
    # Conservative lookup: (almost) no false positives; most reachable points recognised.
    assert (pred & ~truth).sum() <= 0.01 * pred.sum()
    assert (pred & truth).sum() >= 0.8 * truth.sum()


def test_reach_map_extent_and_symmetry() -> None:
    rm = reach_map("kuka_kr60_3", TOOL, step=0.08, disk_cache=False)
    r = get_robot("kuka_kr60_3")
    assert rm.r_max <= r.reach + 0.2 + 1e-9
    assert rm.z_min < 0.0 < rm.z_max
    assert not rm.reachable([r.reach + 0.5, 0.0, 0.8])[0]
    p = np.array([[1.4, 0.0, 0.5], [1.2, 0.3, 0.2], [0.9, -0.5, 1.0]])
    ok = rm.reachable(p)
    for a in np.linspace(0, 2 * np.pi, 7):
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        np.testing.assert_array_equal(rm.reachable(p @ R.T), ok)
    assert ok.any()
    d = rm.to_dict()
    assert d["robot"] == "kuka_kr60_3" and 0 < d["reachable_fraction"] < 1


def test_reach_map_memory_and_disk_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(reach_module, "_MEMORY", {})
    a = reach_map("abb_irb4600_60_205", TOOL, step=0.08, n_yaw=4)
    assert reach_map("abb_irb4600_60_205", TOOL, step=0.08, n_yaw=4) is a
    files = list((tmp_path / "reach").glob("*.npz"))
    assert len(files) == 1
    reach_module._MEMORY.clear()
    b = reach_map("abb_irb4600_60_205", TOOL, step=0.08, n_yaw=4)
    assert b is not a
    np.testing.assert_array_equal(a.grid, b.grid)
    assert (a.r_min, a.r_max, a.z_min, a.z_max) == (b.r_min, b.r_max, b.z_min, b.z_max)
    # A different tool is a different map.
    other = TOOL.copy()
    other[2, 3] = 0.4
    c = reach_map("abb_irb4600_60_205", other, step=0.08, n_yaw=4)
    assert c is not a and len(list((tmp_path / "reach").glob("*.npz"))) == 2


def test_brokk_reach_map() -> None:
    rm = reach_map("brokk_170", TOOL, step=0.1, disk_cache=False)
    r = get_robot("brokk_170")
    q = r.q_nominal.copy()
    q[4] = -np.pi / 2 - q[1:4].sum()  # chisel pointing straight down
    assert r.within_limits(q)
    p = (r.fk(q) @ TOOL)[:3, 3]
    assert rm.reachable(p)[0]
    assert 2.0 < rm.r_max <= r.reach + 0.2 + 1e-9


def test_reach_map_bad_input() -> None:
    with pytest.raises(UnsupportedError):
        reach_map("kuka_kr60_3", TOOL, tool_axis="sideways")
    with pytest.raises(InputError):
        reach_map("kuka_kr60_3", np.eye(3))
    with pytest.raises(UnsupportedError):
        reach_map("kuka_kr7", TOOL)
    rm = reach_map("kuka_kr60_3", TOOL, step=0.1, n_yaw=2, disk_cache=False)
    with pytest.raises(InputError):
        rm.reachable(np.zeros((4, 2)))
    # The project's tool pose, as a matrix, keys the same map.
    assert (
        reach_map("kuka_kr60_3", Tool().T_flange_tool.matrix(), step=0.1, n_yaw=2, disk_cache=False)
        is rm
    )


def test_platform_from_project_and_lift() -> None:
    spec = Platform()
    plat = MobilePlatform(
        robot=get_robot("kuka_kr60_3"),
        footprint=spec.footprint,
        lift_range=spec.lift,
        T_platform_base=spec.T_platform_base.matrix(),
        safety_margin=spec.safety_margin,
    )
    T_wp = np.eye(4)
    T_wp[:3, 3] = [5.0, 2.0, 0.0]
    station = Station("S1", T_wp, lift=0.4)
    np.testing.assert_allclose(
        plat.T_world_base(T_wp, 0.4), station.T_world_base(plat.T_platform_base)
    )
    rm = reach_map("kuka_kr60_3", TOOL, step=0.08, disk_cache=False)
    p_base = np.array([[1.3, 0.2, 0.3], [1.0, -0.4, -0.2], [0.5, 0.5, 1.2]])
    # The lift only shifts the base frame: a point lifted with the platform stays reachable.
    for h in (0.0, 0.4, 1.2):
        p_world = p_base @ np.eye(3) + plat.T_world_base(T_wp, h)[:3, 3]
        np.testing.assert_array_equal(plat.reachable(rm, p_world, T_wp, h), rm.reachable(p_base))
    with pytest.raises(InputError):
        plat.T_world_base(T_wp, 2.0)
    corners = plat.footprint_corners(T_wp, with_margin=False)
    np.testing.assert_allclose(corners.mean(axis=0), [5.0, 2.0])
    np.testing.assert_allclose(np.ptp(corners, axis=0), [2.2, 1.6])
    high = np.array([[6.0, 2.0, 2.6]])
    lift, n = plat.best_lift(rm, high, T_wp)
    assert n == 1 and lift > 0.0
    # The vectorized lift sweep agrees with querying each lift separately.
    pts = np.array([[6.0, 2.0, 2.6], [6.2, 2.5, 0.4], [5.5, 1.0, 1.5]])
    T_rot = T_wp.copy()
    T_rot[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    lifts, ok = plat.reachable_lifts(rm, pts, T_rot, n=7)
    for j, h in enumerate(lifts):
        np.testing.assert_array_equal(ok[:, j], plat.reachable(rm, pts, T_rot, h))
    assert ok.any() and not ok.all()


def test_yaw_invariance_only_for_axial_tools() -> None:
    kuka = get_robot("kuka_kr60_3")
    assert reach_module._yaw_invariant(kuka, TOOL)
    offset = TOOL.copy()
    offset[0, 3] = 0.15  # TCP beside the flange axis: yaw moves the wrist
    assert not reach_module._yaw_invariant(kuka, offset)
    assert not reach_module._yaw_invariant(get_robot("brokk_170"), TOOL)
    rm = reach_map("kuka_kr60_3", offset, step=0.1, n_yaw=6, disk_cache=False)
    assert 0.0 < rm.yaw_fraction[rm.grid].min() <= 1.0
    assert (rm.yaw_fraction[rm.grid] < 1.0).any()  # some nodes only at some yaws


@pytest.mark.parametrize("margin", [0.02, 0.05, 0.08, 0.15, 0.3])
def test_shrunk_reach_is_the_disk_erosion(margin: float) -> None:
    from scipy import ndimage

    from fabflow.robots.reach_model import reach_model

    model = reach_model("kuka_kr60_3", np.eye(4))
    cells = int(np.ceil(margin / min(model.r_step, model.z_step) - 1e-9))
    ii, jj = np.mgrid[-cells : cells + 1, -cells : cells + 1]
    disk = (ii * model.r_step) ** 2 + (jj * model.z_step) ** 2 <= margin**2 + 1e-12
    expected = ndimage.binary_erosion(model.table, structure=disk, border_value=0)
    assert np.array_equal(model.shrunk(margin).table, expected)


def test_a_margin_beyond_the_reach_is_quick_and_empty() -> None:
    import time

    from fabflow.robots.reach_model import reach_model

    model = reach_model("kuka_kr60_3", np.eye(4))
    t0 = time.perf_counter()
    assert not model.shrunk(5.0).table.any()
    assert time.perf_counter() - t0 < 1
