"""Reachability maps for the station planner.

For a tool orientation (tool z axis pointing down, any yaw about the vertical),
which TCP positions can the arm reach? The answer only depends on the distance
``r`` from axis 1 and the height ``z`` in the base frame, because axis 1 turns
the whole arm through at least a full turn on every catalogue model. The map is
computed once on an ``(r, z)`` grid from inverse kinematics (closed form for the
six-axis arms, damped least squares for the others) and then queried with a
conservative lookup: a point is reachable when the four grid nodes around it
are.

The lift of the mobile platform is not part of the map: a caller that raises
the arm base by ``h`` shifts the query points down by ``h`` (or equivalently
uses ``T_world_base`` of the lifted base), see docs/robots.md.

Maps are cached in memory and, unless disabled, on disk under the user cache
directory (``$FABFLOW_CACHE_DIR`` or platformdirs' ``user_cache_dir("fabflow")``)
keyed by a hash of the robot geometry, the tool and the grid.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError, UnsupportedError
from fabflow.robots.catalog import get_robot
from fabflow.robots.chain import RobotModel
from fabflow.robots.planar_ik import is_pitch_chain, pitch_chain_ik
from fabflow.transforms.so3 import R_FLIP_X

FloatArray = NDArray[np.float64]

_MAP_VERSION = 2
_MEMORY: dict[str, ReachMap] = {}


@dataclass(frozen=True, eq=False)
class ReachMap:
    """Reachable TCP positions for one robot, tool and tool orientation.

    Attributes
    ----------
    robot_name
        Catalogue name of the arm.
    tool_axis
        ``"down"`` or ``"up"``: the direction of the tool z axis (base frame).
    r
        ``(nr,)`` grid distances from axis 1 (metres, ascending, uniform).
    z
        ``(nz,)`` grid heights above the base (metres, ascending, uniform).
    grid
        ``(nr, nz)`` bool: some sampled yaw has an IK solution within limits.
    yaw_fraction
        ``(nr, nz)`` share of the sampled yaws that are reachable.
    n_yaw
        Number of yaw angles sampled per node.
    r_min, r_max, z_min, z_max
        Extent of the reachable nodes (metres; NaN when nothing is reachable).
    """

    robot_name: str
    tool_axis: str
    r: FloatArray
    z: FloatArray
    grid: NDArray[np.bool_]
    yaw_fraction: FloatArray
    n_yaw: int
    r_min: float
    r_max: float
    z_min: float
    z_max: float

    @property
    def step(self) -> float:
        """Grid spacing (metres)."""
        return float(self.r[1] - self.r[0])

    def reachable(self, p_base: ArrayLike) -> NDArray[np.bool_]:
        """Whether TCP positions can be reached with the map's tool orientation.

        Parameters
        ----------
        p_base
            ``(N, 3)`` or ``(3,)`` TCP positions in the robot base frame (metres).

        Returns
        -------
        numpy.ndarray
            ``(N,)`` bool (conservative: all four surrounding grid nodes reachable).
        """
        p = np.atleast_2d(np.asarray(p_base, dtype=float))
        if p.shape[-1] != 3:
            raise InputError(f"reachable() expects (N, 3) positions, got shape {p.shape}")
        rr = np.hypot(p[:, 0], p[:, 1])
        zz = p[:, 2]
        h = self.step
        fi = (rr - self.r[0]) / h
        fj = (zz - self.z[0]) / h
        inside = (fi >= 0) & (fi <= len(self.r) - 1) & (fj >= 0) & (fj <= len(self.z) - 1)
        i0 = np.clip(np.floor(fi).astype(int), 0, len(self.r) - 2)
        j0 = np.clip(np.floor(fj).astype(int), 0, len(self.z) - 2)
        g = self.grid
        ok = g[i0, j0] & g[i0 + 1, j0] & g[i0, j0 + 1] & g[i0 + 1, j0 + 1]
        return inside & ok

    def to_dict(self) -> dict[str, object]:
        """Extent and grid description (JSON-compatible, without the grid itself)."""
        return {
            "robot": self.robot_name,
            "tool_axis": self.tool_axis,
            "step": self.step,
            "n_yaw": self.n_yaw,
            "r_min": self.r_min,
            "r_max": self.r_max,
            "z_min": self.z_min,
            "z_max": self.z_max,
            "reachable_fraction": float(self.grid.mean()),
        }


def _tool_rotation(tool_axis: str) -> FloatArray:
    if tool_axis == "down":
        return R_FLIP_X.copy()
    if tool_axis == "up":
        return np.eye(3)
    raise UnsupportedError(f"tool_axis must be 'down' or 'up', got {tool_axis!r}")


def _cache_key(
    robot: RobotModel, T_flange_tool: FloatArray, tool_axis: str, step: float, n_yaw: int
) -> str:
    h = hashlib.sha256()
    h.update(f"v{_MAP_VERSION}|{robot.name}|{tool_axis}|{step:.6f}|{n_yaw}".encode())
    geometry = (robot.dh,) if robot.chain is None else (robot.chain.T_base_0, robot.chain.links)
    for arr in (*geometry, robot.joint_sign, robot.joint_limits, robot.T_n_flange):
        h.update((np.round(np.asarray(arr, dtype=float), 12) + 0.0).tobytes())
    h.update((np.round(T_flange_tool, 9) + 0.0).tobytes())  # + 0.0 turns -0.0 into 0.0
    return h.hexdigest()[:32]


def _cache_dir() -> Path:
    env = os.environ.get("FABFLOW_CACHE_DIR")
    if env:
        return Path(env) / "reach"
    import platformdirs

    return Path(platformdirs.user_cache_dir("fabflow")) / "reach"


def reach_map(
    robot_name: str,
    T_flange_tool: ArrayLike,
    tool_axis: str = "down",
    *,
    step: float | None = None,
    n_yaw: int = 12,
    disk_cache: bool = True,
) -> ReachMap:
    """The (cached) reachability map of an arm with a tool.

    Parameters
    ----------
    robot_name
        Catalogue name (see :func:`fabflow.robots.catalog.get_robot`).
    T_flange_tool
        4x4 TCP pose in the flange frame (metres).
    tool_axis
        ``"down"`` (tool z axis along -z of the base) or ``"up"``.
    step
        Grid spacing in r and z (metres); default: 1/100 of the robot's reach,
        rounded to millimetres, at least 2 cm.
    n_yaw
        Yaw angles about the vertical sampled per grid node; a node is reachable
        when any of them is. When the tool sits on the axis of a last joint with
        a full turn of range (all catalogue arms with an axial tool), yaw is
        only a turn of that joint and a single sample is used.
    disk_cache
        Read and write the map under the user cache directory.

    Returns
    -------
    ReachMap
        The map; repeated calls with the same inputs return the same object.
    """
    robot = get_robot(robot_name)
    T_ft = np.asarray(T_flange_tool, dtype=float)
    if T_ft.shape != (4, 4):
        raise InputError(f"T_flange_tool must be a 4x4 pose, got shape {T_ft.shape}")
    if step is None:
        step = max(0.02, round(robot.reach / 100.0, 3))
    if step <= 0 or n_yaw < 1:
        raise InputError(f"reach_map needs step > 0 and n_yaw >= 1, got {step}, {n_yaw}")
    R_tool = _tool_rotation(tool_axis)
    if robot.joint_limits[0, 1] - robot.joint_limits[0, 0] < 2 * np.pi - 1e-9:
        raise UnsupportedError(
            f"reach_map assumes axis 1 of {robot.name} turns through a full circle"
        )
    key = _cache_key(robot, T_ft, tool_axis, step, n_yaw)
    if key in _MEMORY:
        return _MEMORY[key]
    path = _cache_dir() / f"{key}.npz" if disk_cache else None
    if path is not None and path.is_file():
        try:
            m = _load(path, robot.name, tool_axis)
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            m = None
        if m is not None:
            _MEMORY[key] = m
            return m
    if robot.analytic_ik is None and not is_pitch_chain(robot):
        raise UnsupportedError(f"reach_map has no inverse kinematics for {robot.name}")
    m = _compute(robot, T_ft, tool_axis, R_tool, step, n_yaw)
    _MEMORY[key] = m
    if path is not None:
        _save(path, m)
    return m


def _yaw_invariant(robot: RobotModel, T_flange_tool: FloatArray) -> bool:
    """Whether turning the tool about the vertical is just a turn of the last joint.

    True when the last joint axis is the flange z axis through the flange origin,
    the last joint has at least a full turn of range, and the tool lies on that
    axis (TCP offset along flange z, tool z parallel to flange z). Then any yaw
    reaches the same points, and one yaw sample is enough.
    """
    if robot.dh is None:
        return False
    a, alpha = robot.dh[-1, 0], robot.dh[-1, 1]
    Tn = robot.T_n_flange
    lo, hi = robot.joint_limits[-1]

    def axial(T: FloatArray) -> bool:
        return bool(
            np.allclose(T[:3, 2], [0.0, 0.0, 1.0], atol=1e-12)
            and np.allclose(T[:2, 3], 0.0, atol=1e-12)
        )

    return (
        robot.analytic_ik is not None
        and abs(a) < 1e-12
        and abs(alpha) < 1e-12
        and axial(Tn)
        and axial(T_flange_tool)
        and hi - lo >= 2 * np.pi - 1e-9
    )


def _compute(
    robot: RobotModel,
    T_flange_tool: FloatArray,
    tool_axis: str,
    R_tool: FloatArray,
    step: float,
    n_yaw: int,
) -> ReachMap:
    tool_len = float(np.linalg.norm(T_flange_tool[:3, 3]))
    extent = robot.reach + tool_len + step
    r = np.arange(0.0, extent + step / 2, step)
    z_lo = robot.dh[0, 2] - extent
    z = np.arange(np.floor(z_lo / step) * step, robot.dh[0, 2] + extent + step / 2, step)
    R_grid, Z_grid = np.meshgrid(r, z, indexing="ij")
    yaw = np.arange(n_yaw) * (2 * np.pi / n_yaw)
    if _yaw_invariant(robot, T_flange_tool):
        yaw = yaw[:1]
    T_flange_tool_inv = np.linalg.inv(T_flange_tool)
    n_nodes = R_grid.size
    hits = np.zeros((n_nodes, n_yaw), dtype=bool)
    pr, pz = R_grid.ravel(), Z_grid.ravel()
    chunk = 20000 if robot.analytic_ik is not None else 2000
    for k, psi in enumerate(yaw):
        c, s = np.cos(psi), np.sin(psi)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R_tool
        for a in range(0, n_nodes, chunk):
            b = min(a + chunk, n_nodes)
            T_base_tool = np.tile(np.eye(4), (b - a, 1, 1))
            T_base_tool[:, :3, :3] = R
            T_base_tool[:, 0, 3] = pr[a:b]
            T_base_tool[:, 2, 3] = pz[a:b]
            T_base_flange = T_base_tool @ T_flange_tool_inv
            hits[a:b, k] = _any_solution(robot, T_base_flange)
        if robot.analytic_ik is None or len(yaw) == 1:
            # Further yaws give the same answer: the pitch-chain solver ignores the
            # roll about the tool axis (the slew sets it), and a yaw-invariant
            # arm/tool only turns its last joint.
            hits[:, k + 1 :] = hits[:, [k]]
            break
    grid = hits.any(axis=1).reshape(R_grid.shape)
    frac = hits.mean(axis=1).reshape(R_grid.shape)
    if grid.any():
        rs, zs = R_grid[grid], Z_grid[grid]
        ext = (float(rs.min()), float(rs.max()), float(zs.min()), float(zs.max()))
    else:
        ext = (np.nan, np.nan, np.nan, np.nan)
    return ReachMap(robot.name, tool_axis, r, z, grid, frac, n_yaw, *ext)


def _any_solution(robot: RobotModel, T_base_flange: FloatArray) -> NDArray[np.bool_]:
    if robot.analytic_ik is not None:
        _, valid = robot.ik_batch(T_base_flange)
        return valid.any(axis=1)

    if is_pitch_chain(robot):
        _, valid = pitch_chain_ik(robot, T_base_flange)
        return valid.any(axis=1)
    raise UnsupportedError(f"reach_map has no inverse kinematics for {robot.name}")


def _save(path: Path, m: ReachMap) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz.tmp")
        with os.fdopen(fd, "wb") as f:
            np.savez_compressed(
                f,
                r=m.r,
                z=m.z,
                grid=m.grid,
                yaw_fraction=m.yaw_fraction,
                n_yaw=m.n_yaw,
                extent=np.array([m.r_min, m.r_max, m.z_min, m.z_max]),
            )
        os.replace(tmp, path)
    except OSError:
        # A read-only or full cache directory only costs a recomputation next time.
        return


def _load(path: Path, robot_name: str, tool_axis: str) -> ReachMap:
    with np.load(path) as d:
        ext = d["extent"]
        return ReachMap(
            robot_name,
            tool_axis,
            d["r"],
            d["z"],
            d["grid"].astype(bool),
            d["yaw_fraction"],
            int(d["n_yaw"]),
            float(ext[0]),
            float(ext[1]),
            float(ext[2]),
            float(ext[3]),
        )
