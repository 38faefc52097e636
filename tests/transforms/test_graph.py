"""Tests of the frame graph: tree walking, named errors, covariance propagation."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from fabflow.errors import InputError
from fabflow.transforms import (
    DisconnectedFramesError,
    FrameCycleError,
    FrameError,
    FrameGraph,
    Pose,
    UnknownFrameError,
    apply_T,
    perturb,
    point_covariance,
    pose_error,
)


def _cov(rng: np.random.Generator, sig_t: float, sig_r: float) -> np.ndarray:
    """A random full-rank 6x6 covariance with the given scales (m, rad)."""
    L = rng.normal(size=(6, 6)) * 0.3 + np.eye(6)
    L = L * np.r_[[sig_t] * 3, [sig_r] * 3][:, None]
    return L @ L.T


def _site(rng: np.random.Generator) -> tuple[FrameGraph, dict[str, Pose], dict[str, np.ndarray]]:
    poses = {
        "world>total_station": Pose.from_rotvec([0.0, 0.0, 1.2], [12.0, -4.0, 1.5]),
        "total_station>base": Pose.from_rotvec([0.02, -0.01, -2.3], [-6.0, 9.0, -1.2]),
        "base>flange": Pose.from_rotvec([0.4, 1.1, -0.3], [0.8, 0.2, 1.4]),
        "flange>tool": Pose.from_rotvec([0.0, 0.0, 0.0], [0.0, 0.0, 0.25]),
        "world>element_1": Pose.from_rotvec([0.0, 0.0, 0.7], [3.0, 2.0, 0.0]),
    }
    covs = {
        "world>total_station": _cov(rng, 0.002, 0.0005),
        "total_station>base": _cov(rng, 0.005, 0.002),
    }
    g = FrameGraph()
    for key, T in poses.items():
        parent, child = key.split(">")
        g.add(parent, child, T, covs.get(key))
    return g, poses, covs


def test_get_walks_the_tree_both_ways() -> None:
    g, P, _ = _site(np.random.default_rng(0))
    T_world_tool = (
        P["world>total_station"] @ P["total_station>base"] @ P["base>flange"] @ P["flange>tool"]
    )
    assert g.get("world", "tool").allclose(T_world_tool, 1e-12)
    assert g.get("tool", "world").allclose(T_world_tool.inverse(), 1e-12)
    T_el_tool = P["world>element_1"].inverse() @ T_world_tool
    assert g.get("element_1", "tool").allclose(T_el_tool, 1e-12)
    assert g.get("base", "base").allclose(Pose.identity(), 0.0)
    assert g.path("element_1", "base") == ["element_1", "world", "total_station", "base"]
    assert set(g.frames) == {"world", "total_station", "base", "flange", "tool", "element_1"}


def test_exact_path_has_zero_covariance() -> None:
    g, _, _ = _site(np.random.default_rng(0))
    _, C = g.get_with_covariance("base", "tool")
    assert np.all(C == 0.0)


@pytest.mark.parametrize(("a", "b"), [("world", "tool"), ("tool", "element_1")])
def test_covariance_matches_monte_carlo(a: str, b: str) -> None:
    rng = np.random.default_rng(42)
    g, P, covs = _site(rng)
    T_ab, C = g.get_with_covariance(a, b)
    n = 10_000
    sampled = {
        key: perturb(P[key].matrix, rng.multivariate_normal(np.zeros(6), covs[key], size=n))
        for key in covs
    }
    # compose the sampled edge poses along the same path
    names = g.path(a, b)
    T = np.broadcast_to(np.eye(4), (n, 4, 4))
    for u, v in itertools.pairwise(names):
        if f"{u}>{v}" in P:
            step = sampled.get(f"{u}>{v}", P[f"{u}>{v}"].matrix)
        else:
            fwd = sampled.get(f"{v}>{u}", P[f"{v}>{u}"].matrix)
            step = np.linalg.inv(fwd)
        T = T @ step
    err = pose_error(T_ab.matrix, T)
    C_mc = np.cov(err.T)
    sd = np.sqrt(np.diag(C))
    assert np.all(sd > 0)
    # every entry within 5 % of the scale sqrt(C_ii C_jj) (diagonal: 5 % relative)
    rel = np.abs(C_mc - C) / np.outer(sd, sd)
    assert rel.max() < 0.05, rel.round(3)
    # the propagated covariance is not trivially the edge covariance
    assert not np.allclose(C, covs["total_station>base"], rtol=0.2)


def test_named_errors() -> None:
    g, _P, _ = _site(np.random.default_rng(1))
    with pytest.raises(UnknownFrameError, match=r"'robot'.*known frames: base"):
        g.get("world", "robot")
    with pytest.raises(FrameCycleError, match="cycle"):
        g.add("tool", "world", Pose.identity())
    with pytest.raises(FrameCycleError):
        g.add("element_1", "base", Pose.identity())
    g.add_frame("uwb")
    with pytest.raises(DisconnectedFramesError, match="not connected"):
        g.get("uwb", "world")
    with pytest.raises(FrameError, match="itself"):
        g.add("world", "world", Pose.identity())
    with pytest.raises(FrameError, match="single Pose"):
        g.add("world", "x", Pose.identity(3))
    with pytest.raises(FrameError, match="non-empty"):
        g.add("", "x", Pose.identity())
    with pytest.raises(InputError, match="positive semi-definite"):
        g.add("world", "uwb", Pose.identity(), -np.eye(6))
    with pytest.raises(InputError, match="6x6"):
        g.add("world", "uwb", Pose.identity(), np.eye(3))
    asym = np.eye(6)
    asym[0, 1] = 0.5
    with pytest.raises(InputError, match="symmetric"):
        g.add("world", "uwb", Pose.identity(), asym)
    assert issubclass(FrameError, InputError)


def test_set_and_remove_edges() -> None:
    g, P, _ = _site(np.random.default_rng(2))
    new = Pose.from_rotvec([0.0, 0.0, 0.1], [1.0, 1.0, 0.0])
    g.set("base", "total_station", new.inverse(), np.eye(6) * 1e-6)
    assert g.get("total_station", "base").allclose(new, 1e-12)
    _, C = g.get_with_covariance("world", "base")
    assert np.all(np.linalg.eigvalsh(C) > 0)
    with pytest.raises(FrameError, match="no edge"):
        g.set("world", "tool", new)
    g.remove("flange", "tool")
    with pytest.raises(DisconnectedFramesError):
        g.get("world", "tool")
    g.add("tool", "flange", P["flange>tool"].inverse())
    assert g.get("flange", "tool").allclose(P["flange>tool"], 1e-12)


def test_target_point_covariance_matches_monte_carlo() -> None:
    rng = np.random.default_rng(5)
    g, _, _ = _site(rng)
    T_wt, C = g.get_with_covariance("total_station", "tool")
    p_tool = np.array([0.05, -0.02, 0.1])
    C_p = point_covariance(T_wt.matrix, C, p_tool)
    deltas = rng.multivariate_normal(np.zeros(6), C, size=10_000)
    samples = apply_T(perturb(T_wt.matrix, deltas), p_tool)
    C_mc = np.cov(samples.T)
    sd = np.sqrt(np.diag(C_p))
    assert (np.abs(C_mc - C_p) / np.outer(sd, sd)).max() < 0.05
