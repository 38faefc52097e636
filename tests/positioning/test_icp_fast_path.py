"""ICP's fast path: kept correspondences, coarse levels, one-thread small searches,
and the map's normals in closed form.

None of it may change the results: the correspondences at every pose are those
of a fresh KD-tree search, the coarse levels end on the full problem's minimum,
and the normals are those of an eigen-decomposition.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from helpers import icp_room as room
from scipy.spatial import cKDTree

import fabflow.positioning.icp_search as search_module
import fabflow.positioning.pointcloud as pointcloud_module
from fabflow.positioning.icp import IcpTarget, icp, prepare_target
from fabflow.positioning.icp_search import Matches, levels
from fabflow.positioning.pointcloud import estimate_normals
from fabflow.transforms.se3 import apply_T, inv_T, perturb, pose_error


@pytest.fixture(scope="module")
def target() -> IcpTarget:
    return prepare_target(room(np.random.default_rng(0), 3000))


def fresh(target: IcpTarget, p: np.ndarray, dmax: float) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``p`` with a target point within ``dmax``, and that point (a new search)."""
    d, idx = cKDTree(target.points).query(p, k=1, distance_upper_bound=dmax)
    ok = np.flatnonzero(np.isfinite(d))
    return ok, idx[ok]


def test_kept_correspondences_are_those_of_a_fresh_search(target: IcpTarget) -> None:
    """Along a walk of large and small moves, and when the distance changes."""
    rng = np.random.default_rng(1)
    src = room(rng, 400) + rng.normal(0, 0.01, (2800, 3))
    matches = Matches(target.tree, target.points, len(src), workers=1)
    T = perturb(np.eye(4), [0.2, -0.1, 0.05, 0.01, 0.0, 0.1])
    rows = np.sort(rng.choice(len(src), 700, replace=False))
    for k in range(40):
        size = 0.05 if k % 10 == 0 else 0.002 if k % 3 else 0.0002
        T = perturb(T, rng.normal(0, size, 6) * [1, 1, 1, 0.2, 0.2, 0.2])
        dmax = 0.3 if k < 20 else 0.1
        sub = rows if k % 4 == 1 else None
        p = apply_T(T, src if sub is None else src[sub])
        at, nearest, offset, dist = matches.find(p, dmax, sub)
        ok, idx = fresh(target, p, dmax)
        np.testing.assert_array_equal(at, ok)
        np.testing.assert_array_equal(nearest, idx)
        np.testing.assert_allclose(offset, p[ok] - target.points[idx], atol=1e-12)
        np.testing.assert_allclose(dist, np.linalg.norm(offset, axis=1), atol=1e-12)
    # most small moves keep most correspondences: far fewer searches than points
    assert matches.searched < 0.5 * 40 * len(src)


def test_final_correspondences_are_those_of_a_fresh_search(target: IcpTarget) -> None:
    rng = np.random.default_rng(2)
    T_true = perturb(np.eye(4), [0.1, -0.05, 0.02, 0.01, -0.01, 0.05])
    src = apply_T(inv_T(T_true), room(rng, 1000)) + rng.normal(0, 0.003, (7000, 3))
    res = icp(src, target, max_correspondence_distance=(0.3, 0.1))
    p = apply_T(res.T, src)
    ok, idx = fresh(target, p, 0.1)
    assert res.n_inliers == len(ok)
    assert target.normals is not None
    r = np.einsum("ij,ij->i", p[ok] - target.points[idx], target.normals[idx])
    np.testing.assert_allclose(res.residuals, r, atol=1e-12)


def test_levels_are_nested_and_spread_over_any_order() -> None:
    assert levels(search_module.THIN_FACTOR * search_module.THIN_POINTS - 1) == [None]
    n = 64 * 300  # a scan stored column by column: the channel is the row modulo 64
    parts = levels(n)
    assert parts[-1] is None
    subsets = [rows for rows in parts if rows is not None]
    assert [round(len(rows), -1) for rows in subsets] == [1200, 4800]
    assert set(subsets[0]) <= set(subsets[1])
    for rows in subsets:
        assert np.all(np.diff(rows) > 0)
        per_channel = np.bincount(rows % 64, minlength=64)
        assert per_channel.min() >= 0.8 * len(rows) / 64
        assert per_channel.max() <= 1.2 * len(rows) / 64


@pytest.mark.parametrize("method", ["point_to_plane", "point_to_point"])
def test_levels_end_on_the_full_problems_minimum(
    target: IcpTarget, method: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """From the initial errors of the accuracy tests, with and without coarse levels."""
    rng = np.random.default_rng(3)
    T_true = perturb(np.eye(4), [0.25, -0.2, 0.05, 0.0, 0.0, 0.15])
    src = apply_T(inv_T(T_true), room(rng, 1200)) + rng.normal(0, 0.003, (8400, 3))
    assert len(levels(len(src))) == 3
    # run to a standstill: the relative criteria also stop a slow crawl
    kw: dict[str, Any] = {"method": method, "max_iterations": 100, "min_step": 1e-7}
    kw |= {"relative_fitness": 0.0, "relative_rmse": 0.0}
    with_levels = icp(src, target, **kw)
    monkeypatch.setattr(search_module, "THIN_POINTS", 10**9)
    plain = icp(src, target, **kw)
    # point-to-point creeps along the surfaces: it stops where its steps get small
    same = 1e-6 if method == "point_to_plane" else 1e-4
    np.testing.assert_allclose(pose_error(with_levels.T, plain.T), 0.0, atol=same)
    tol = 3e-3 if method == "point_to_plane" else 1e-2  # the target's 9 cm spacing
    assert np.linalg.norm(pose_error(with_levels.T, T_true)[:3]) < tol
    assert with_levels.n_inliers == plain.n_inliers
    assert with_levels.converged and plain.converged


def test_small_searches_run_on_one_thread(target: IcpTarget) -> None:
    calls: list[tuple[int, int]] = []

    class Spy:
        def query(self, x: np.ndarray, **kw: Any) -> Any:
            calls.append((len(x), kw["workers"]))
            return target.tree.query(x, **kw)

    spied = IcpTarget(points=target.points, normals=target.normals, tree=Spy())  # type: ignore[arg-type]
    src = room(np.random.default_rng(4), 300)
    icp(src, spied, init=perturb(np.eye(4), [0.05, 0.0, 0.0, 0.0, 0.0, 0.02]), workers=-1)
    assert calls and all(w == 1 for n, w in calls if n < search_module.PARALLEL_QUERY_MIN)


def test_normals_in_chunks_equal_normals_at_once(monkeypatch: pytest.MonkeyPatch) -> None:
    pts = room(np.random.default_rng(5), 500)
    whole, var_whole = estimate_normals(pts, k=12, return_planarity=True)
    monkeypatch.setattr(pointcloud_module, "NORMALS_CHUNK", 97)
    chunked, var_chunked = estimate_normals(pts, k=12, return_planarity=True)
    np.testing.assert_allclose(chunked, whole, atol=1e-9)
    np.testing.assert_allclose(var_chunked, var_whole, atol=1e-12)


def test_normals_in_closed_form_equal_an_eigen_decomposition() -> None:
    """On noisy surfaces, at edges and corners, and along a line (where either
    normal across it will do)."""
    rng = np.random.default_rng(6)
    pts = room(rng, 800) + rng.normal(0, 0.002, (5600, 3))
    k = 15
    normals, variation = estimate_normals(pts, k=k, return_planarity=True)
    _, idx = cKDTree(pts).query(pts, k=k)
    nb = pts[idx] - pts[idx].mean(axis=1, keepdims=True)
    evals, evecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb) / k)
    cos = np.abs(np.einsum("ij,ij->i", normals, evecs[:, :, 0]))
    np.testing.assert_allclose(cos, 1.0, atol=1e-9)
    np.testing.assert_allclose(variation, evals[:, 0] / evals.sum(axis=1), atol=1e-12)
    line = np.c_[np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)]
    across = estimate_normals(line, k=5)
    np.testing.assert_allclose(across[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(across, axis=1), 1.0)
