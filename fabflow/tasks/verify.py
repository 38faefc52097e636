"""Check a plan's targets with the arm's inverse kinematics.

For every work package the tool targets are taken into the arm base frame of
that visit (``T_world_base`` of the station at its lift), turned into flange
poses with the tool, and solved with the robot's closed-form IK (all
branches, joint limits applied); a target passes when some branch exists. A
chain without closed-form IK is solved numerically, one target at a time.
"""

from __future__ import annotations

import numpy as np

from fabflow.project import Project
from fabflow.robots import platform
from fabflow.robots.catalog import get_robot
from fabflow.tasks.plan import Plan


def base_targets(plan: Plan, project: Project) -> list[np.ndarray]:
    """Tool targets of every work package in its arm base frame.

    Returns
    -------
    list of np.ndarray
        Per work package, (n, 4, 4) ``T_base_tool`` (metres).
    """
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    out = []
    for wp in plan.work_packages:
        T_wb = wp.station.T_world_base(T_platform_base)
        out.append(np.linalg.inv(T_wb)[None] @ np.asarray(wp.T_world_targets))
    return out


def unreachable_targets(plan: Plan, project: Project) -> list[str]:
    """Element ids whose target has no inverse-kinematics solution at its station.

    Returns
    -------
    list of str
        The failing element ids (empty when all pass).
    """
    robot = get_robot(project.robot.name)
    T_tool_flange = np.linalg.inv(project.robot.tool.T_flange_tool.matrix())
    failed: list[str] = []
    for wp, T_base_tool in zip(plan.work_packages, base_targets(plan, project), strict=True):
        if len(T_base_tool) == 0:
            continue
        T_base_flange = T_base_tool @ T_tool_flange
        if robot.analytic_ik is not None:
            _, valid = robot.ik_batch(T_base_flange)
            ok = valid.any(axis=1)
        else:
            ok = np.array([len(robot.ik(T)) > 0 for T in T_base_flange])
        failed += [e for e, good in zip(wp.elements, ok, strict=True) if not good]
    return failed


def ik_lift_masks(
    project: Project,
    T_world_platform: np.ndarray,
    T_world_tool: np.ndarray,
    lifts: np.ndarray,
) -> np.ndarray | None:
    """Lift levels at which full tool poses have an inverse-kinematics solution.

    Used for targets whose tool does not point down (the reach table assumes it does).

    Parameters
    ----------
    project
        Robot, tool and platform mounting.
    T_world_platform
        (P, 4, 4) platform poses (metres).
    T_world_tool
        (P, 4, 4) tool poses to reach, paired with the platform poses.
    lifts
        (L,) lift heights (metres), L <= 32.

    Returns
    -------
    np.ndarray or None
        (P,) int64 bit masks (bit l: reachable at ``lifts[l]``), or ``None`` when
        the robot has no closed-form IK.
    """
    robot = get_robot(project.robot.name)
    if robot.analytic_ik is None:
        return None
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    T_tool_flange = np.linalg.inv(project.robot.tool.T_flange_tool.matrix())
    masks = np.zeros(len(T_world_tool), dtype=np.int64)
    for bit, h in enumerate(lifts):
        T_world_base = platform.T_world_base(T_world_platform, h, T_platform_base)
        T_base_flange = np.linalg.inv(T_world_base) @ T_world_tool @ T_tool_flange
        _, valid = robot.ik_batch(T_base_flange)
        masks |= valid.any(axis=1).astype(np.int64) << bit
    return masks
