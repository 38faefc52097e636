"""Choosing the prism points for a total station localization (paper 001, eqs 9-11).

The points should be spread as far as the robot's workspace allows: eq 10
maximises ``sum |P_i|^2 + sum_{i<j} |P_i - P_j|^2`` subject to eq 11, every point
inside the reach sphere ``|P_i - c| <= r`` (``c = (0, 0, h)`` in the paper), in
front of the robot (``x > 0``) and above the ground (``z > 0``).

Near a structure under construction a chosen point may be unusable. The
obstacle-avoiding search of the paper grows spheres around the desired point
in 10 cm steps, puts an equally spaced grid of candidates on each sphere and
takes the first candidate for which the tool's bounding box is clear of the
structure, the segment from the arm's shoulder to the point is clear (the arm
passes there), the point lies in the workspace and, beyond the paper, the line
of sight from the instrument is clear and the point keeps a minimum distance
from the points already chosen.

All coordinates are in the robot base frame, metres.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import optimize

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.boxes import Boxes, boxes_overlap, segments_hit


@dataclass(frozen=True)
class Workspace:
    """Where the prism may be placed (eq 11), in the base frame.

    Attributes
    ----------
    center
        Centre of the reach sphere (the shoulder; ``(0, 0, h)`` in the paper), metres.
    reach
        Reach sphere radius ``r`` (metres).
    x_min
        Points must lie more than ``x_min`` in front of the robot: ``x > x_min``
        in the paper, along ``front`` in general.
    front
        Unit vector ``(x, y)`` in the base frame pointing to the robot's front:
        the paper's ``(1, 0)``; where the arm is mounted turned on its platform,
        the platform's front, away from the platform and its magazine.
    z_min
        Points must have ``z > z_min`` (above the ground or deck).
    z_max
        Points must have ``z < z_max`` (not in the paper: where the arm cannot
        hold the tool above a height, e.g. with the tool pointing down).
    margin
        Fraction of the reach kept free so the arm is never fully stretched.
    min_radius
        Points must be at least this far from ``center`` (metres).
    reachable
        Optional exact reach test ``(m, 3) -> (m,)`` bool (inverse kinematics),
        applied on top of the sphere.
    """

    center: tuple[float, float, float] = (0.0, 0.0, 1.0)
    reach: float = 2.55
    x_min: float = 0.0
    front: tuple[float, float] = (1.0, 0.0)
    z_min: float = 0.0
    z_max: float = float("inf")
    margin: float = 0.1
    min_radius: float = 0.3
    reachable: Callable[[np.ndarray], np.ndarray] | None = field(default=None, compare=False)

    @property
    def radius(self) -> float:
        """Usable radius ``reach * (1 - margin)`` (metres)."""
        return self.reach * (1.0 - self.margin)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Boolean mask of the ``(..., 3)`` points that satisfy eq 11 (with margin)."""
        p = np.asarray(points, dtype=float)
        r = np.linalg.norm(p - np.asarray(self.center), axis=-1)
        ok = (
            (r <= self.radius + 1e-6)
            & (r >= self.min_radius)
            & (p[..., :2] @ np.asarray(self.front) > self.x_min)
            & (p[..., 2] > self.z_min)
            & (p[..., 2] < self.z_max)
        )
        if self.reachable is not None and ok.any():
            flat = ok.reshape(-1)
            flat[flat] = self.reachable(p.reshape(-1, 3)[flat])
        return ok

    def contains_geometry(self, points: np.ndarray) -> np.ndarray:
        """Like :meth:`contains` without the (expensive) ``reachable`` test."""
        return replace(self, reachable=None).contains(points)


# ------------------------------------------------------------ eqs 9-11


def spread_objective(points: np.ndarray) -> float:
    """Eq 10: ``sum |P_i|^2 + sum_{i<j} |P_i - P_j|^2`` (m^2) of ``(n, 3)`` points."""
    P = np.asarray(points, dtype=float)
    n = P.shape[0]
    s = P.sum(axis=0)
    return float((n + 1) * np.sum(P * P) - s @ s)


def optimal_points(
    n: int,
    workspace: Workspace,
    rng: np.random.Generator,
    n_starts: int = 4,
) -> np.ndarray:
    """Solve eqs 9-11: ``n`` localization points of maximal spread in the workspace.

    SLSQP from ``n_starts`` random feasible starts (analytic gradients); the
    best local optimum is returned.

    Parameters
    ----------
    n
        Number of points (>= 3).
    workspace
        Reach sphere and half-space constraints (base frame).
    rng
        Source of the random starts.

    Returns
    -------
    numpy.ndarray
        ``(n, 3)`` points in the base frame (metres).
    """
    if n < 3:
        raise InputError(f"need at least 3 localization points, got {n}")
    c = np.asarray(workspace.center, dtype=float)
    front = np.asarray(workspace.front, dtype=float)
    rad = workspace.radius - 1e-6
    eps = 1e-3

    def fun(x: np.ndarray) -> float:
        return -spread_objective(x.reshape(n, 3))

    def jac(x: np.ndarray) -> np.ndarray:
        P = x.reshape(n, 3)
        return -(2.0 * (n + 1) * P - 2.0 * P.sum(axis=0)).ravel()

    def ineq(x: np.ndarray) -> np.ndarray:
        P = x.reshape(n, 3)
        d = P - c
        return np.concatenate(
            [
                rad**2 - np.einsum("ni,ni->n", d, d),
                P[:, :2] @ front - workspace.x_min - eps,
                P[:, 2] - workspace.z_min - eps,
                np.minimum(workspace.z_max - eps - P[:, 2], 1e6),
            ]
        )

    def ineq_jac(x: np.ndarray) -> np.ndarray:
        P = x.reshape(n, 3)
        Jc = np.zeros((4 * n, n, 3))
        rows = np.arange(n)
        Jc[rows, rows] = -2.0 * (P - c)
        Jc[n + rows, rows, :2] = front
        Jc[2 * n + rows, rows, 2] = 1.0
        Jc[3 * n + rows, rows, 2] = -1.0
        return Jc.reshape(4 * n, 3 * n)

    best: np.ndarray | None = None
    best_f = np.inf
    for _ in range(n_starts):
        x0 = sample_workspace(workspace, n, rng).ravel()
        res = optimize.minimize(
            fun,
            x0,
            jac=jac,
            method="SLSQP",
            constraints=[{"type": "ineq", "fun": ineq, "jac": ineq_jac}],
            options={"maxiter": 200, "ftol": 1e-8},
        )
        if res.fun < best_f and np.all(ineq(res.x) >= -1e-6):
            best_f, best = float(res.fun), res.x.reshape(n, 3)
    if best is None:
        raise LocalizationError(
            "the point selection found no feasible configuration; check the workspace "
            f"(reach {workspace.reach} m, z_min {workspace.z_min} m)"
        )
    return best


def sample_workspace(workspace: Workspace, n: int, rng: np.random.Generator) -> np.ndarray:
    """``(n, 3)`` points drawn uniformly from the workspace (rejection sampling)."""
    c = np.asarray(workspace.center, dtype=float)
    out = np.zeros((0, 3))
    for _ in range(100):
        cand = c + rng.uniform(-workspace.radius, workspace.radius, (max(4 * n, 64), 3))
        out = np.concatenate([out, cand[workspace.contains(cand)]])
        if len(out) >= n:
            return out[:n]
    raise LocalizationError(
        f"the workspace (reach {workspace.reach} m about {workspace.center}, "
        f"z > {workspace.z_min}, {workspace.x_min} m in front along {workspace.front}) is empty"
    )


# ------------------------------------------------------------ obstacle avoidance


def sphere_grid(n: int) -> np.ndarray:
    """``(n, 3)`` nearly equally spaced unit vectors (Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


@dataclass(frozen=True)
class ClearanceRules:
    """The criteria a localization point must meet (step 2c of the paper's search).

    Attributes
    ----------
    tool_half_extents
        Half side lengths of the tool's bounding box centred on the prism (metres).
    sight_from
        Instrument position in the base frame; the line of sight to it must be clear.
    min_separation
        Smallest distance between two chosen points (metres).
    """

    tool_half_extents: tuple[float, float, float] = (0.15, 0.15, 0.2)
    sight_from: tuple[float, float, float] | None = None
    min_separation: float = 0.25


CRITERIA = ("workspace", "structure", "arm path", "line of sight", "separation", "reach")
"""The criteria of :func:`check_candidates`, in the order they are tested."""


def _boxes_near(boxes: Boxes, lo: np.ndarray, hi: np.ndarray) -> Boxes:
    """The boxes whose bounding spheres touch the axis-aligned region ``[lo, hi]``."""
    if len(boxes) == 0:
        return boxes
    c = boxes.T_base_box[:, :3, 3]
    radius = 0.5 * np.linalg.norm(boxes.extents, axis=1)
    gap = np.maximum(lo - c, 0.0) + np.maximum(c - hi, 0.0)
    near = np.linalg.norm(gap, axis=1) <= radius
    return Boxes(boxes.T_base_box[near], boxes.extents[near])


def check_candidates(
    candidates: np.ndarray,
    workspace: Workspace,
    boxes: Boxes,
    rules: ClearanceRules,
    chosen: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Test candidate points against every criterion, cheapest first.

    Each test only sees the candidates that passed the ones before, and only
    the boxes near them, so large structures stay cheap.

    Returns
    -------
    ok, rejected
        ``(m,)`` mask of the clear candidates and ``(6,)`` how many were
        rejected first by each criterion of :data:`CRITERIA`.
    """
    cand = np.asarray(candidates, dtype=float)
    ok = np.ones(cand.shape[0], dtype=bool)
    rejected = np.zeros(len(CRITERIA), dtype=int)
    half = np.asarray(rules.tool_half_extents, dtype=float)
    center = np.asarray(workspace.center, dtype=float)

    def apply(k: int, test: Callable[[np.ndarray], np.ndarray]) -> None:
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            return
        passed = test(cand[idx])
        rejected[k] += int((~passed).sum())
        ok[idx[~passed]] = False

    def overlap(p: np.ndarray) -> np.ndarray:
        near = _boxes_near(boxes, p.min(axis=0) - half, p.max(axis=0) + half)
        return ~boxes_overlap(p, half, near)

    def segments_from(start: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        def test(p: np.ndarray) -> np.ndarray:
            lo = np.minimum(p.min(axis=0), start)
            hi = np.maximum(p.max(axis=0), start)
            return ~segments_hit(start, p, _boxes_near(boxes, lo, hi))

        return test

    apply(0, workspace.contains_geometry)
    apply(1, overlap)
    apply(2, segments_from(center))
    if rules.sight_from is not None:
        apply(3, segments_from(np.asarray(rules.sight_from, dtype=float)))
    if chosen is not None and len(chosen):
        apply(
            4,
            lambda p: (
                np.linalg.norm(p[:, None, :] - chosen[None], axis=-1).min(axis=1)
                >= rules.min_separation
            ),
        )
    if workspace.reachable is not None:
        apply(5, workspace.reachable)
    return ok, rejected


def clear_mask(
    candidates: np.ndarray,
    workspace: Workspace,
    boxes: Boxes,
    rules: ClearanceRules,
    chosen: np.ndarray | None = None,
) -> np.ndarray:
    """``(m,)`` mask of candidate points meeting every criterion (see :func:`check_candidates`)."""
    return check_candidates(candidates, workspace, boxes, rules, chosen)[0]


@dataclass(frozen=True, eq=False)
class ClearPoints:
    """Result of :func:`avoid_obstacles`.

    Attributes
    ----------
    points
        ``(k, 3)`` clear points (base frame, metres).
    moved
        ``(k,)`` how far each was moved from its desired point (metres).
    index
        ``(k,)`` which desired point each one replaces.
    dropped
        Desired points for which no clear point was found, with the reason.
    """

    points: np.ndarray
    moved: np.ndarray
    index: np.ndarray
    dropped: tuple[tuple[int, str], ...] = ()


def _workspace_grid(workspace: Workspace, spacing: float) -> np.ndarray:
    """Regular grid points (``spacing`` metres) inside the workspace geometry."""
    c = np.asarray(workspace.center, dtype=float)
    r = workspace.radius
    axes = [np.arange(c[k] - r, c[k] + r + 1e-9, spacing) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return grid[workspace.contains_geometry(grid)]


def clear_workspace_points(
    workspace: Workspace,
    boxes: Boxes,
    rules: ClearanceRules,
    spacing: float = 0.2,
    reachable_grid: np.ndarray | None = None,
) -> np.ndarray:
    """``(m, 3)`` points of a ``spacing`` grid over the workspace that meet every criterion
    (the pool :func:`avoid_obstacles` refills dropped points from).

    ``reachable_grid``: the grid points that pass the workspace's reach test, when
    already known (the reach does not change from station to station).
    """
    if reachable_grid is not None:
        free = replace(workspace, reachable=None)
        return reachable_grid[check_candidates(reachable_grid, free, boxes, rules)[0]]
    grid = _workspace_grid(workspace, spacing)
    return grid[check_candidates(grid, workspace, boxes, rules)[0]]


def reachable_workspace_grid(workspace: Workspace, spacing: float = 0.2) -> np.ndarray:
    """``(m, 3)`` points of a ``spacing`` grid over the workspace that pass its reach test."""
    grid = _workspace_grid(workspace, spacing)
    return grid[workspace.contains(grid)]


def farthest_points(points: np.ndarray, k: int) -> np.ndarray:
    """``min(k, m)`` of the ``(m, 3)`` points, each the farthest from those taken before
    (the first: the farthest from their centroid); a spread subset."""
    P = np.asarray(points, dtype=float)
    if len(P) <= k:
        return P
    taken = [int(np.argmax(np.linalg.norm(P - P.mean(axis=0), axis=1)))]
    gap = np.linalg.norm(P - P[taken[0]], axis=1)
    for _ in range(k - 1):
        taken.append(int(np.argmax(gap)))
        gap = np.minimum(gap, np.linalg.norm(P - P[taken[-1]], axis=1))
    return P[taken]


def _most_spread(candidates: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """The candidate that, added to ``chosen``, gives the largest eq 10 objective."""
    n = len(chosen) + 1
    s = chosen.sum(axis=0) + candidates
    sq = np.sum(chosen * chosen) + np.einsum("mi,mi->m", candidates, candidates)
    return candidates[int(np.argmax((n + 1) * sq - np.einsum("mi,mi->m", s, s)))]


def avoid_obstacles(
    points: np.ndarray,
    workspace: Workspace,
    boxes: Boxes,
    rules: ClearanceRules | None = None,
    step: float = 0.10,
    max_radius: float = 1.5,
    spacing: float = 0.10,
    min_points: int | None = None,
) -> ClearPoints:
    """Move each desired point to the nearest clear one (the paper's growing-sphere search).

    For a point that fails a criterion, spheres of radius ``step``,
    ``2 step``, ... around it are tried; each carries an equally spaced grid
    of about one candidate per ``spacing^2`` of area (at least 12). On the
    smallest sphere with clear candidates, the paper takes the first one; here
    the one that keeps the points most spread (eq 10 with the points chosen so
    far) is taken, so a blocked point does not end up next to another one. A
    desired point with no
    clear candidate within ``max_radius`` is replaced by the clear point of a
    20 cm grid over the whole workspace that keeps the points most spread; if
    there is none it is dropped, as long as at least ``min_points`` remain.

    Parameters
    ----------
    points
        ``(n, 3)`` desired points (base frame, metres).
    workspace, boxes, rules
        The criteria (see :func:`check_candidates`).
    step, max_radius, spacing
        Search sphere growth, largest radius, grid spacing (metres).
    min_points
        Fewest points that must be found (default: all of them).

    Raises
    ------
    LocalizationError
        When fewer than ``min_points`` clear points are found; the message
        names the blocked point and how many candidates each criterion rejected.
    """
    rules = rules or ClearanceRules()
    P = np.asarray(points, dtype=float)
    need = P.shape[0] if min_points is None else min_points
    found: list[np.ndarray] = []
    moved: list[float] = []
    index: list[int] = []
    dropped: list[tuple[int, str]] = []
    for i, p in enumerate(P):
        chosen = np.asarray(found).reshape(-1, 3)
        if clear_mask(p[None], workspace, boxes, rules, chosen)[0]:
            found.append(p)
            moved.append(0.0)
            index.append(i)
            continue
        r = step
        fails = np.zeros(len(CRITERIA), dtype=int)
        while r <= max_radius + 1e-9:
            k = max(12, int(np.ceil(4 * np.pi * r * r / spacing**2)))
            cand = p + r * sphere_grid(k)
            ok, rejected = check_candidates(cand, workspace, boxes, rules, chosen)
            if ok.any():
                found.append(_most_spread(cand[ok], chosen))
                moved.append(r)
                index.append(i)
                break
            fails += rejected
            r += step
        else:
            reason = ", ".join(
                f"{name} {count}" for name, count in zip(CRITERIA, fails, strict=True) if count
            )
            dropped.append((i, f"({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}): rejected by {reason}"))
    if dropped:
        # refill the dropped points from anywhere in the workspace, most spread first
        pool = clear_workspace_points(workspace, boxes, rules)
        for i, _why in dropped:
            chosen = np.asarray(found).reshape(-1, 3)
            if len(chosen):
                gap = np.linalg.norm(pool[:, None, :] - chosen[None], axis=-1).min(axis=1)
                pool = pool[gap >= rules.min_separation]
            if len(pool) == 0:
                break
            best = _most_spread(pool, chosen)
            found.append(best)
            moved.append(float(np.linalg.norm(best - P[i])))
            index.append(i)
        refilled = {index[k] for k in range(len(index))}
        dropped = [(i, why) for i, why in dropped if i not in refilled]
    if len(found) < need:
        i, why = dropped[0]
        raise LocalizationError(
            f"found only {len(found)} of the {need} localization points needed: no clear "
            f"point within {max_radius} m of desired point {i + 1} {why} (candidates "
            "rejected first by each criterion; a blocked line of sight needs a higher or "
            "different instrument position)"
        )
    return ClearPoints(
        points=np.asarray(found).reshape(-1, 3),
        moved=np.asarray(moved),
        index=np.asarray(index, dtype=int),
        dropped=tuple(dropped),
    )
