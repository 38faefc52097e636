"""Iterative Closest Point registration (point-to-point and point-to-plane).

:func:`icp` aligns a source cloud to a target cloud: it returns the 4x4 transform
``T`` mapping source points into the target frame (for scan-to-map
localization: ``T_world_lidar``), with the quality figures fitness and inlier
RMSE and a 6x6 covariance of the pose in fabflow's convention (see
:mod:`fabflow.positioning.result`: errors ``[dx, dy, dz, rx, ry, rz]`` expressed in
the target frame, ``T_true = [Exp(r) R, t + d]``).

The algorithm: nearest-neighbour correspondences from a KD-tree over the target
(:class:`scipy.spatial.cKDTree`); a coarse-to-fine schedule of maximum
correspondence distances; a robust kernel (iteratively reweighted least squares);
each step is the closed-form weighted Kabsch solution (point-to-point) or one
Gauss-Newton step of the linearized point-to-plane problem. A stage ends when the
relative changes of fitness and inlier RMSE both drop below their tolerances, or
the step becomes negligible, or after ``max_iterations``.

The searches are cut without changing what ICP converges to
(:mod:`fabflow.positioning.icp_search`): a point's correspondence is kept while
it cannot have changed, and a stage on a source of at least ``THIN_FACTOR *
THIN_POINTS`` points first iterates on nested subsets of it, ``THIN_FACTOR`` times
smaller each (down to ``THIN_POINTS``), each handing over to the next once an
update moves no point by more than ``LEVEL_STEP`` times the correspondence
distance. The large first moves cost a fraction of the searches; the last level
uses every point and ends by the stage's own criteria, so the result is a
minimum of the full problem.

The covariance is the robust "sandwich" of an M-estimator (Huber 1967; White
1980), ``C = N^-1 M N^-1`` with ``N = sum_i w_i J_i^T J_i`` and
``M = sum_b g_b g_b^T``, ``g_b = sum_{i in b} w_i r_i J_i^T`` summed over blocks
``b`` of correspondences (cubes of ``covariance_block`` metres; one block per
correspondence when ``None``), times the small-sample factor
``K / (K - 1) * (n - 1) / (n - 6)`` of ``K`` blocks and ``n`` correspondences. Unlike
``sigma^2 N^-1`` it needs neither one residual variance for all points (the
near ground, averaged over many LiDAR returns per voxel, has far smaller
residuals than the far walls that fix x, y and heading) nor independent
residuals: errors shared by the points of one block (a surface's share of the
map error, voxel-centroid bias along edges and facets) add up in ``g_b``.
:func:`~fabflow.positioning.icp_weakness.weakest_direction` reads the least
constrained direction off the information.

Build the target once with :func:`prepare_target` when the same map is used for
many registrations (scan-to-map localization): its KD-tree and normals are then
not recomputed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.icp_search import (
    Matches,
    Workspace,
    levels,
    row_cross,
    row_dot,
    transformed,
)
from fabflow.positioning.icp_shared import SharedErrors, group_sums, shared_errors, shared_rows
from fabflow.positioning.pointcloud import as_points, estimate_normals
from fabflow.transforms.so3 import exp_so3_one, skew

FloatArray = NDArray[np.float64]
Method = Literal["point_to_point", "point_to_plane"]
Kernel = Literal["none", "huber", "tukey", "cauchy"]

MIN_CORRESPONDENCES = 10
"""Fewer inlier correspondences than this is a failed registration."""
MIN_BLOCKS = 30
"""Fewer occupied covariance blocks than this: the blocked sum is too coarse to
estimate a 6x6 matrix (cluster-robust estimators want some tens of clusters), and
each correspondence becomes its own block."""
LEVEL_STEP = 0.1
"""A coarse level hands over to the next when an update moves no point by more than
this fraction of the stage's correspondence distance."""


@dataclass(frozen=True, eq=False)
class IcpTarget:
    """A target cloud prepared for repeated registration.

    Attributes
    ----------
    points
        ``(M, 3)`` target points (metres, target frame).
    normals
        ``(M, 3)`` unit normals, or ``None`` (point-to-point only).
    tree
        KD-tree over ``points``.
    """

    points: FloatArray
    normals: FloatArray | None
    tree: cKDTree

    def __len__(self) -> int:
        return len(self.points)


def prepare_target(
    points: ArrayLike,
    normals: ArrayLike | None = None,
    *,
    with_normals: bool = True,
    normal_k: int = 20,
) -> IcpTarget:
    """Build the KD-tree (and normals, if not given) of a target cloud.

    Parameters
    ----------
    points
        ``(M, 3)`` target points (metres).
    normals
        ``(M, 3)`` normals to use; estimated by PCA over ``normal_k`` neighbours when
        ``None`` and ``with_normals`` is true.
    with_normals
        Whether normals are needed (point-to-plane).
    normal_k
        Neighbourhood size for normal estimation.
    """
    p = as_points(points, "target")
    if len(p) < MIN_CORRESPONDENCES:
        raise InputError(f"target cloud needs at least {MIN_CORRESPONDENCES} points, has {len(p)}")
    tree = cKDTree(p)
    n: FloatArray | None = None
    if normals is not None:
        n = as_points(normals, "target normals")
        if len(n) != len(p):
            raise InputError("target normals must have one row per target point")
    elif with_normals:
        n = estimate_normals(p, k=normal_k, tree=tree)  # type: ignore[assignment]
    return IcpTarget(points=p, normals=n, tree=tree)


@dataclass(frozen=True, eq=False)
class IcpResult:
    """The outcome of one ICP registration.

    Attributes
    ----------
    T
        4x4 transform mapping source points into the target frame.
    fitness
        Fraction of source points with a correspondence within the final maximum
        correspondence distance (0..1).
    inlier_rmse
        RMS distance of those correspondences (metres; point-to-plane distances for
        ``point_to_plane``, Euclidean for ``point_to_point``).
    iterations
        Total iterations (updates of the pose) over all stages and their levels.
    covariance
        6x6 covariance of ``T`` over ``[dx, dy, dz, rx, ry, rz]`` (target frame;
        m^2, rad^2): the sandwich of the final correspondences (module docstring).
    information
        The 6x6 information matrix (inverse of ``covariance``; 1/m^2, 1/rad^2).
    n_inliers
        Number of inlier correspondences at the end.
    converged
        Whether the final stage met its convergence tolerances before ``max_iterations``.
    condition
        Ratio of smallest to largest eigenvalue of the unit information
        ``sum_i w_i J_i^T J_i`` (rotations in radians, so their rows carry the lever
        arms in metres; 0 = degenerate geometry, e.g. a single plane).
    residuals
        ``(n_inliers,)`` final residuals (metres; signed point-to-plane distances or
        Euclidean distances).
    n_blocks
        Number of blocks the covariance summed the residuals over.
    """

    T: FloatArray
    fitness: float
    inlier_rmse: float
    iterations: int
    covariance: FloatArray
    information: FloatArray
    n_inliers: int
    converged: bool
    condition: float
    residuals: FloatArray
    n_blocks: int = 0

    @property
    def transformation(self) -> FloatArray:
        """Alias of :attr:`T` (Open3D's name)."""
        return self.T


def _kernel_weights(r: FloatArray, kernel: Kernel, scale: float) -> FloatArray:
    if kernel == "none":
        return np.ones_like(r)
    a = np.abs(r) / scale
    if kernel == "huber":
        return np.where(a <= 1.0, 1.0, 1.0 / np.maximum(a, 1e-12))
    if kernel == "tukey":
        return np.where(a < 1.0, (1.0 - a * a) ** 2, 0.0)
    return 1.0 / (1.0 + a * a)


def _kabsch(p: FloatArray, q: FloatArray, w: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Weighted rigid transform (R, t) minimizing sum w |R p + t - q|^2."""
    ws = w.sum()
    cp = (w[:, None] * p).sum(axis=0) / ws
    cq = (w[:, None] * q).sum(axis=0) / ws
    H = (w[:, None] * (p - cp)).T @ (q - cq)
    U, _, Vt = np.linalg.svd(H)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ D @ U.T
    return R, cq - R @ cp


def _plane_system(
    p: FloatArray, n: FloatArray, r: FloatArray, w: FloatArray, work: Workspace
) -> tuple[FloatArray, FloatArray]:
    """Weighted normal equations of point-to-plane residuals r = n.(p - q), assembled
    in 3x3 blocks in ``work``'s arrays.

    Rows of the Jacobian for the update ``p <- Exp(w) p + v`` are ``[n, p x n]``.
    """
    m = len(p)
    c = row_cross(p, n, out=work.cross[:m])
    nw = np.multiply(n, w[:, None], out=work.nw[:m])
    cw = np.multiply(c, w[:, None], out=work.cw[:m])
    A = np.empty((6, 6))
    A[:3, :3] = nw.T @ n
    A[:3, 3:] = nw.T @ c
    A[3:, :3] = A[:3, 3:].T
    A[3:, 3:] = cw.T @ c
    return A, np.concatenate([nw.T @ r, cw.T @ r])


def _block_sums(scores: FloatArray, points: FloatArray, block: float | None) -> FloatArray:
    """Sum the rows of ``scores`` over cubes of edge ``block`` of ``points`` (or keep them)."""
    if not block:
        return scores
    keys = np.floor(points / block).astype(np.int64)
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    if int(inverse.max()) + 1 < MIN_BLOCKS:
        return scores
    return group_sums(scores, inverse)


def _sandwich(
    info_unit: FloatArray,
    sums: FloatArray,
    n: int,
    sigma2: float,
    shared: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, float]:
    """Covariance ``N^-1 M N^-1``, its inverse and the condition of ``N``.

    ``info_unit`` is ``N``; ``sums`` the ``(K, 6)`` score sums of the blocks
    (``M = sums^T sums``); ``n`` the number of correspondences; ``shared`` the
    ``(G, 6)`` rows of errors of known size shared by groups of points, added to
    ``M`` as they are (no small-sample factor). Along numerically
    degenerate directions of ``N`` (eigenvalue below 1e-12 of the largest) the
    scores carry nothing; there the covariance falls back to ``sigma2 / lambda``
    with the eigenvalue floored, i.e. a huge variance.
    """
    evals, evecs = np.linalg.eigh(info_unit)
    top = max(float(evals[-1]), 1e-300)
    condition = float(max(evals[0], 0.0) / top)
    lam = np.maximum(evals, top * 1e-12)
    k = len(sums)
    factor = k / max(k - 1, 1) * (n - 1) / max(n - 6, 1)
    M = (sums.T @ sums) * factor
    if shared is not None:
        M = M + shared.T @ shared
    Mv = evecs.T @ M @ evecs
    Cv = Mv / np.outer(lam, lam)
    weak = evals <= top * 1e-12
    Cv[weak, weak] = np.maximum(Cv[weak, weak], max(sigma2, 1e-18) / lam[weak])
    cov = evecs @ Cv @ evecs.T
    cov = 0.5 * (cov + cov.T)
    cev, cvec = np.linalg.eigh(cov)
    cev = np.maximum(cev, max(float(cev[-1]), 1e-300) * 1e-15)
    return cov, (cvec / cev) @ cvec.T, condition


def icp(
    source: ArrayLike,
    target: ArrayLike | IcpTarget,
    init: ArrayLike | None = None,
    method: Method = "point_to_plane",
    max_correspondence_distance: float | Sequence[float] = (1.0, 0.3, 0.1),
    max_iterations: int = 30,
    relative_fitness: float = 1e-4,
    relative_rmse: float = 1e-4,
    kernel: Kernel = "huber",
    kernel_scale: float | None = None,
    target_normals: ArrayLike | None = None,
    min_step: float = 1e-5,
    workers: int = -1,
    covariance_block: float | None = None,
    ray_groups: ArrayLike | None = None,
    ray_sigma: float = 0.0,
    target_groups: ArrayLike | None = None,
    target_sigma: float = 0.0,
    map_rays: tuple[ArrayLike, ArrayLike, float] | None = None,
) -> IcpResult:
    """Register ``source`` to ``target`` with ICP.

    Parameters
    ----------
    source
        ``(N, 3)`` source points (metres, source frame).
    target
        ``(M, 3)`` target points (metres, target frame), or an :class:`IcpTarget` from
        :func:`prepare_target` (reuses its KD-tree and normals).
    init
        Initial 4x4 guess of the source-to-target transform (identity when ``None``).
    method
        ``"point_to_plane"`` (needs target normals; estimated if absent) or
        ``"point_to_point"``.
    max_correspondence_distance
        Maximum correspondence distance in metres, or a coarse-to-fine schedule of
        them (one ICP stage per value, in the given order). Fitness and RMSE refer to
        the last value.
    max_iterations
        Iteration limit per stage, and per level of a stage on a large source
        (module docstring).
    relative_fitness, relative_rmse
        A stage has converged when the relative changes of fitness and of inlier
        RMSE between iterations both fall below these.
    kernel
        Robust kernel for iteratively reweighted least squares: ``"huber"``,
        ``"tukey"``, ``"cauchy"`` or ``"none"``.
    kernel_scale
        Kernel scale (metres); default: a third of the stage's correspondence distance.
    target_normals
        ``(M, 3)`` target normals when ``target`` is an array (else estimated).
    min_step
        A stage also ends when an update moves no source point by more than this
        (metres; bounded by the centroid's motion plus rotation angle times the
        source radius).
    workers
        Threads for the KD-tree queries (``-1``: all cores); a query for fewer than
        :data:`~fabflow.positioning.icp_search.PARALLEL_QUERY_MIN` source points runs
        on one.
    covariance_block
        Edge (metres, target frame) of the cubes whose correspondences the
        covariance treats as sharing their errors (module docstring); ``None``: each
        correspondence alone (independent residuals of unequal variance).
    ray_groups, ray_sigma
        ``(N,)`` integer group of every source point whose range errs by one shared
        amount (a spinning LiDAR's laser channel, whose range bias the residuals
        cannot show), and that amount's standard deviation (metres, along the ray
        from the source frame's origin). Adds ``ray_sigma^2 N^-1 (sum_k g_k g_k^T)
        N^-1`` to the covariance, ``g_k`` the sum over group ``k`` of ``w_i
        J_i^T`` times the residual's change per metre of range (``n_i . u_i``).
        ``None`` or 0: no such term. point_to_plane only
        (:class:`~fabflow.errors.UnsupportedError` otherwise).
    target_groups, target_sigma
        ``(M,)`` integer group of every target point that moves with one rigid
        part of the target (a block of the as-built structure added to a map at
        its design pose; ``-1``: none), and the standard deviation per axis of
        that part's translation (metres). Adds the same sandwich over groups and
        axes, the residual's change per metre of shift being ``-n_i``;
        point_to_plane only.
    map_rays
        ``(groups (M,), directions (M, 3), sigma)``: the channel of the mapping
        run that measured each target point (``-1``: none), the unit direction
        it measured it along, and that channel's range bias (metres): the same
        sandwich, a residual changing by ``-n_i . u_i`` per metre of bias
        (:mod:`fabflow.positioning.icp_shared`); point_to_plane only.

    Returns
    -------
    IcpResult
        ``.T``, ``.fitness``, ``.inlier_rmse``, ``.iterations``, ``.covariance`` and more.

    Raises
    ------
    InputError
        Malformed inputs (shapes, non-finite values, an unknown method or kernel).
    LocalizationError
        Fewer than 10 correspondences within the correspondence distance at any
        stage: the initial guess is too far off or the clouds do not overlap.
    """
    if method not in ("point_to_point", "point_to_plane"):
        raise InputError(
            f"unknown ICP method {method!r}; expected point_to_plane or point_to_point"
        )
    if kernel not in ("none", "huber", "tukey", "cauchy"):
        raise InputError(f"unknown robust kernel {kernel!r}; expected huber, tukey, cauchy or none")
    src = as_points(source, "source")
    if isinstance(target, IcpTarget):
        tgt = target
        if method == "point_to_plane" and tgt.normals is None:
            tgt = prepare_target(tgt.points)
    else:
        tgt = prepare_target(target, target_normals, with_normals=method == "point_to_plane")
    schedule = np.atleast_1d(np.asarray(max_correspondence_distance, dtype=float))
    if schedule.ndim != 1 or len(schedule) == 0 or np.any(schedule <= 0):
        raise InputError("max_correspondence_distance must be positive (or a list of them)")
    T = np.eye(4) if init is None else np.array(init, dtype=float).reshape(4, 4)
    if not np.all(np.isfinite(T)):
        raise InputError("init must be a finite 4x4 matrix")
    if len(src) < MIN_CORRESPONDENCES:
        raise InputError(
            f"source cloud needs at least {MIN_CORRESPONDENCES} points, has {len(src)}"
        )
    shared = shared_errors(
        method == "point_to_plane",
        len(src),
        len(tgt.points),
        (ray_groups, ray_sigma),
        (target_groups, target_sigma),
        map_rays,
    )

    plane = method == "point_to_plane"
    src_mean = src.mean(axis=0)
    src_radius = float(np.max(np.linalg.norm(src - src_mean, axis=1)))
    n_all = tgt.normals
    iterations = 0
    converged = False
    matches = Matches(tgt.tree, tgt.points, len(src), workers)
    work = Workspace(len(src))
    parts = [(rows, src if rows is None else src[rows]) for rows in levels(len(src))]
    scale = 0.0
    for dmax in schedule.tolist():
        scale = float(kernel_scale) if kernel_scale is not None else dmax / 3.0
        converged = False
        for rows, part in parts:
            fine = rows is None
            stop = min_step if fine else max(min_step, LEVEL_STEP * dmax)
            prev: tuple[float, float] | None = None
            for _ in range(max_iterations):
                p = transformed(T, part, out=work.moved[: len(part)])
                at, ii, e, dist = matches.find(p, dmax, rows)
                n_ok = len(at)
                if n_ok < MIN_CORRESPONDENCES:
                    if not fine:
                        break  # too few in the subset: go on with more points
                    raise LocalizationError(
                        f"ICP found only {n_ok} correspondences within {dmax:g} m; "
                        "the initial pose is too far off or the clouds do not overlap"
                    )
                if plane:
                    assert n_all is not None
                    nn = np.take(n_all, ii, axis=0, out=work.normals[:n_ok])
                    r = row_dot(e, nn)
                else:
                    r = dist
                fitness = n_ok / len(part)
                rmse = float(np.sqrt(np.einsum("i,i->", r, r) / n_ok))
                if prev is not None:
                    df = abs(fitness - prev[0]) / max(fitness, 1e-12)
                    dr = abs(rmse - prev[1]) / max(rmse, 1e-12)
                    if df < relative_fitness and dr < relative_rmse:
                        converged = fine
                        break
                prev = (fitness, rmse)
                w = _kernel_weights(r, kernel, scale)
                iterations += 1
                if n_ok < len(p):
                    p = np.take(p, at, axis=0)
                dT = np.eye(4)
                if plane:
                    A, b = _plane_system(p, nn, r, w, work)
                    try:
                        x = -np.linalg.solve(A + 1e-12 * np.trace(A) * np.eye(6), b)
                    except np.linalg.LinAlgError:
                        raise LocalizationError(
                            "ICP normal equations are singular (degenerate geometry)"
                        ) from None
                    dT[:3, :3] = exp_so3_one(*x[3:])
                    dT[:3, 3] = x[:3]
                else:
                    dT[:3, :3], dT[:3, 3] = _kabsch(p, p - e, w)
                c = T[:3, :3] @ src_mean + T[:3, 3]
                angle = float(np.arccos(np.clip((np.trace(dT[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
                moved = float(np.linalg.norm(dT[:3, :3] @ c + dT[:3, 3] - c)) + angle * src_radius
                T = dT @ T
                if moved < stop:
                    converged = fine
                    break

    return _final_result(
        src,
        tgt,
        T,
        float(schedule[-1]),
        plane,
        (kernel, scale),
        iterations,
        converged,
        matches,
        covariance_block,
        shared,
    )


def _final_result(
    src: FloatArray,
    tgt: IcpTarget,
    T: FloatArray,
    dmax: float,
    plane: bool,
    robust: tuple[Kernel, float],
    iterations: int,
    converged: bool,
    matches: Matches,
    block: float | None,
    errors: SharedErrors | None = None,
) -> IcpResult:
    p = transformed(T, src)
    at, ii, e, dist = matches.find(p, dmax)
    n_ok = len(at)
    if n_ok < MIN_CORRESPONDENCES:
        raise LocalizationError(f"ICP ended with only {n_ok} correspondences within {dmax:g} m")
    p = np.take(p, at, axis=0)
    ok = np.zeros(len(src), dtype=bool)
    ok[at] = True
    # Jacobian w.r.t. fabflow's pose error [d, r] applied as [Exp(r) R, t + d]:
    # p_true = Exp(r) R s + t + d, so dp/dd = I and dp/dr = -skew(R s).
    Rs = p - T[:3, 3]
    if plane:
        assert tgt.normals is not None
        nn = np.take(tgt.normals, ii, axis=0)
        r = row_dot(e, nn)
        w = _kernel_weights(r, *robust)
        J = np.empty((n_ok, 6))
        J[:, :3] = nn
        J[:, 3:] = row_cross(Rs, nn)
        info_unit = (J * w[:, None]).T @ J
        scores = J * (w * r)[:, None]
        sigma2 = float(np.sum(w * r * r) / max(n_ok - 6, 1))
    else:
        r = dist
        w = _kernel_weights(r, *robust)
        S = skew(Rs)
        sw = w.sum()
        Ssum = (w[:, None, None] * S).sum(axis=0)
        StS = np.einsum("n,nji,njk->ik", w, S, S)
        info_unit = np.zeros((6, 6))
        info_unit[:3, :3] = sw * np.eye(3)
        info_unit[:3, 3:] = -Ssum
        info_unit[3:, :3] = -Ssum.T
        info_unit[3:, 3:] = StS
        # J_i^T e_i with J_i = [I, -skew(R s_i)]
        scores = w[:, None] * np.c_[e, row_cross(Rs, e)]
        sigma2 = float(np.sum(w * r * r) / max(3 * n_ok - 6, 1))
    sums = _block_sums(scores, p, block)
    shared = None
    if plane and errors is not None:
        shared = shared_rows(errors, J * w[:, None], nn, Rs, ok, ii)
    cov, info, condition = _sandwich(info_unit, sums, n_ok, sigma2, shared)
    return IcpResult(
        T=T,
        fitness=n_ok / len(src),
        inlier_rmse=float(np.sqrt(np.mean(r * r))),
        iterations=iterations,
        covariance=cov,
        information=info,
        n_inliers=n_ok,
        converged=converged,
        condition=condition,
        residuals=r,
        n_blocks=len(sums),
    )
