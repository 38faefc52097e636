"""A tree of named frames connected by poses, with first-order uncertainty.

Frames (``world``, ``uwb``, ``total_station``, ``platform``, ``base``, ``flange``,
``tool``, element frames, ...) are nodes; each edge stores one pose
``T_parent_child`` and optionally its 6x6 covariance in fabflow's convention
(:mod:`fabflow.transforms.se3`: error ``[dx, dy, dz, rx, ry, rz]`` in the parent
frame, true pose ``[Exp(r) R, t + d]``). Edges can be walked in both directions.

``graph.get("base", "tool")`` returns ``T_base_tool``;
``graph.get_with_covariance("world", "tool")`` also returns its covariance,
propagated to first order along the path assuming the edge errors are
independent (so a localization uncertainty on ``world -> base`` becomes a
target uncertainty on ``world -> tool``).

The graph must stay a tree: an edge that would close a cycle raises
:class:`~fabflow.transforms.errors.FrameCycleError`; unknown frames raise
:class:`~fabflow.transforms.errors.UnknownFrameError`; frames in separate
components raise :class:`~fabflow.transforms.errors.DisconnectedFramesError`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.transforms.errors import (
    DisconnectedFramesError,
    FrameCycleError,
    FrameError,
    UnknownFrameError,
)
from fabflow.transforms.pose import Pose
from fabflow.transforms.se3 import compose_covariance, inv_T, inverse_covariance

FloatArray = NDArray[np.float64]

COVARIANCE_TOL = 1e-12
"""Absolute part of the tolerance for covariance symmetry and the smallest eigenvalue
(plus 1e-9 times the largest entry)."""


def check_covariance(C: ArrayLike, name: str = "covariance") -> FloatArray:
    """Validate a 6x6 pose covariance (finite, symmetric, positive semi-definite).

    Raises
    ------
    InputError
        If ``C`` is not 6x6, not finite, not symmetric or has a negative eigenvalue,
        each beyond ``COVARIANCE_TOL + 1e-9 * max |C_ij|``.
    """
    C = np.array(C, dtype=float)  # a copy: later edits of the caller's array must not leak in
    if C.shape != (6, 6):
        raise InputError(f"{name} must be 6x6 over [dx, dy, dz, rx, ry, rz], got shape {C.shape}")
    if not np.all(np.isfinite(C)):
        raise InputError(f"{name} contains NaN or infinite values")
    tol = COVARIANCE_TOL + 1e-9 * float(np.abs(C).max())
    if np.abs(C - C.T).max() > tol:
        raise InputError(f"{name} must be symmetric")
    lo = float(np.linalg.eigvalsh(C).min())
    if lo < -tol:
        raise InputError(f"{name} must be positive semi-definite (smallest eigenvalue {lo:.3g})")
    return C


@dataclass(frozen=True)
class _Edge:
    parent: str
    child: str
    T_parent_child: Pose
    covariance: FloatArray | None


def _check_name(name: object) -> str:
    if not isinstance(name, str) or not name.strip():
        raise FrameError(f"frame names must be non-empty strings, got {name!r}")
    return name


class FrameGraph:
    """Named frames connected by poses (a forest; queries need a connecting path).

    Examples
    --------
    >>> g = FrameGraph()
    >>> g.add("world", "base", Pose.from_rotvec([0, 0, 0.5], [2.0, 1.0, 0.0]))
    >>> g.add("base", "tool", Pose.from_rotvec([0, 0, 0], [0.0, 0.0, 0.3]))
    >>> T_world_tool = g.get("world", "tool")
    """

    def __init__(self) -> None:
        self._edges: dict[frozenset[str], _Edge] = {}
        self._adj: dict[str, set[str]] = {}

    @property
    def frames(self) -> list[str]:
        """All frame names, sorted."""
        return sorted(self._adj)

    def __contains__(self, frame: object) -> bool:
        return frame in self._adj

    def add_frame(self, name: str) -> None:
        """Add an isolated frame (frames are also added implicitly by :meth:`add`)."""
        self._adj.setdefault(_check_name(name), set())

    def add(
        self,
        parent: str,
        child: str,
        T_parent_child: Pose,
        covariance: ArrayLike | None = None,
    ) -> None:
        """Connect ``child`` to ``parent`` by ``T_parent_child`` (optionally uncertain).

        Parameters
        ----------
        parent, child
            Frame names; created if new.
        T_parent_child
            A single :class:`Pose` of the child in the parent frame (m).
        covariance
            6x6 covariance of the pose in fabflow's convention (parent frame), or
            ``None`` for an exact pose.

        Raises
        ------
        FrameCycleError
            If ``parent`` and ``child`` are already connected (directly or not).
        FrameError
            If a name is invalid, ``parent == child`` or the pose is a batch.
        InputError
            If the covariance is not a valid 6x6 covariance.
        """
        _check_name(parent)
        _check_name(child)
        if parent == child:
            raise FrameError(f"cannot connect frame {parent!r} to itself")
        self._check_pose(T_parent_child, parent, child)
        C = (
            None
            if covariance is None
            else check_covariance(covariance, f"covariance of {parent}->{child}")
        )
        if parent in self._adj and child in self._adj and self._path(parent, child) is not None:
            raise FrameCycleError(
                f"frames {parent!r} and {child!r} are already connected; adding {parent}->{child}"
                " would close a cycle (use set() to replace an existing edge)"
            )
        self._adj.setdefault(parent, set()).add(child)
        self._adj.setdefault(child, set()).add(parent)
        self._edges[frozenset((parent, child))] = _Edge(parent, child, T_parent_child, C)

    def set(
        self,
        parent: str,
        child: str,
        T_parent_child: Pose,
        covariance: ArrayLike | None = None,
    ) -> None:
        """Replace the pose (and covariance) of the existing edge between two frames.

        The edge may have been added in either direction; it is stored as given here.

        Raises
        ------
        UnknownFrameError
            If a frame is unknown.
        FrameError
            If there is no direct edge between the two frames.
        """
        self._require(parent)
        self._require(child)
        key = frozenset((parent, child))
        if key not in self._edges:
            raise FrameError(f"there is no edge between {parent!r} and {child!r} to replace")
        self._check_pose(T_parent_child, parent, child)
        C = (
            None
            if covariance is None
            else check_covariance(covariance, f"covariance of {parent}->{child}")
        )
        self._edges[key] = _Edge(parent, child, T_parent_child, C)

    def remove(self, a: str, b: str) -> None:
        """Remove the edge between ``a`` and ``b`` (the frames stay)."""
        self._require(a)
        self._require(b)
        if self._edges.pop(frozenset((a, b)), None) is None:
            raise FrameError(f"there is no edge between {a!r} and {b!r}")
        self._adj[a].discard(b)
        self._adj[b].discard(a)

    def path(self, a: str, b: str) -> list[str]:
        """Frame names along the path from ``a`` to ``b`` (both included)."""
        self._require(a)
        self._require(b)
        p = self._path(a, b)
        if p is None:
            raise DisconnectedFramesError(
                f"frames {a!r} and {b!r} are not connected by any chain of poses"
            )
        return p

    def get(self, a: str, b: str) -> Pose:
        """``T_a_b``: the pose of frame ``b`` in frame ``a``, composed along the tree."""
        return self.get_with_covariance(a, b)[0]

    def get_with_covariance(self, a: str, b: str) -> tuple[Pose, FloatArray]:
        """``T_a_b`` and its 6x6 covariance (fabflow's convention, error in frame ``a``).

        Edge errors are treated as independent; the covariance is exact to first
        order in the edge errors (zero if no edge on the path is uncertain).
        """
        names = self.path(a, b)
        T = np.eye(4)
        C = np.zeros((6, 6))
        for u, v in pairwise(names):
            e = self._edges[frozenset((u, v))]
            T_e = e.T_parent_child.matrix
            if e.parent == u:
                step, C_step = T_e, e.covariance
            else:
                step = inv_T(T_e)
                C_step = None if e.covariance is None else inverse_covariance(T_e, e.covariance)
            C = compose_covariance(T, C, step, C_step)
            T = T @ step
        return Pose._trusted(T[:3, :3].copy(), T[:3, 3].copy()), 0.5 * (C + C.T)

    # ------------------------------------------------------------------ internals

    def _require(self, name: str) -> None:
        if name not in self._adj:
            known = ", ".join(self.frames) or "none"
            raise UnknownFrameError(f"unknown frame {name!r} (known frames: {known})")

    @staticmethod
    def _covariance(C: ArrayLike | None, parent: str, child: str) -> FloatArray | None:
        if C is None:
            return None
        return check_covariance(C, f"covariance of edge {parent}->{child}")

    @staticmethod
    def _check_pose(T: Pose, parent: str, child: str) -> None:
        if not isinstance(T, Pose) or T.is_batch:
            raise FrameError(f"edge {parent}->{child} needs a single Pose, got {type(T).__name__}")

    def _path(self, a: str, b: str) -> list[str] | None:
        prev: dict[str, str | None] = {a: None}
        queue = deque([a])
        while queue:
            u = queue.popleft()
            if u == b:
                out = [u]
                while prev[out[-1]] is not None:
                    out.append(prev[out[-1]])  # type: ignore[arg-type]
                return out[::-1]
            for v in self._adj.get(u, ()):
                if v not in prev:
                    prev[v] = u
                    queue.append(v)
        return None
