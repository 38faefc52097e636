"""Machine models, kinematics, inverse kinematics and motion control.

Public API::

    from fabflow.robots.catalog import get_robot
    from fabflow.robots.kuka_config import kuka_status_turn
    from fabflow.robots import reach_map

    robot = get_robot("kuka_kr60_3")          # or any name in ROBOT_NAMES (below)
    T_base_flange = robot.fk(q)               # q (dof,) or (N, dof), radians
    solutions = robot.ik(T_base_flange, q_ref=q)
    S, T = kuka_status_turn(q)
    rm = reach_map("kuka_kr60_3", T_flange_tool)
    ok = rm.reachable(p_base)                 # (N, 3) TCP positions, tool pointing down

The catalogue (:data:`ROBOT_NAMES`): ``kuka_kr60_3`` (KUKA KR 60-3),
``abb_irb4600_60_205`` (ABB IRB 4600-60/2.05), ``ur10e`` (Universal Robots
UR10e), ``brokk_170`` (5-axis demolition machine in the style of the BROKK 170,
APPROXIMATE), ``excavator_gripper`` (walking-excavator-like arm in the style
of HEAP with a two-jaw rotating gripper, APPROXIMATE) and ``excavator_printer``
(the same arm with a print head, APPROXIMATE). A robot defined in a project file
(``robot.model: custom``: OPW parameters, a DH table or a URDF chain,
:mod:`fabflow.robots.custom`) is found by ``get_robot(project.robot.name)``.
"""

from fabflow.robots.catalog import ROBOT_NAMES, get_robot
from fabflow.robots.chain import RobotModel
from fabflow.robots.clik import Clik, ClikGains, ClikResult, divide_path
from fabflow.robots.hydraulic import HydraulicJoints, contact_search, tracking_rmse
from fabflow.robots.kuka_config import kuka_status_turn
from fabflow.robots.platform import MobilePlatform
from fabflow.robots.reach import ReachMap, reach_map

__all__ = [
    "ROBOT_NAMES",
    "Clik",
    "ClikGains",
    "ClikResult",
    "HydraulicJoints",
    "MobilePlatform",
    "ReachMap",
    "RobotModel",
    "contact_search",
    "divide_path",
    "get_robot",
    "kuka_status_turn",
    "reach_map",
    "tracking_rmse",
]
