"""The machines fabflow knows, as data, and :func:`get_robot`.

Joint values are the ones the robot's own controller shows (radians here):

* ``kuka_kr60_3`` - KUKA KR 60-3, A1..A6 in KUKA's sense (home A2 = -90 deg,
  A3 = +90 deg; A1, A4, A6 positive clockwise seen along the axis). DH lengths
  from DESIGN.md. The A2 range is the manufacturer's -135..+35 deg (DESIGN.md
  lists -35..135, which would exclude the home pose A2 = -90 deg; the sign was
  taken as a transcription slip).
* ``abb_irb4600_60_205`` - ABB IRB 4600-60/2.05, axes 1..6 in ABB's sense
  (all zero: upper arm vertical, forearm horizontal). Published geometry.
* ``ur10e`` - Universal Robots UR10e, the published DH parameters.
* ``brokk_170`` - a 5-axis demolition machine in the style of the BROKK 170
  (slew, boom, arm 2, arm 3, tool tilt; all but the slew pitch joints).
  APPROXIMATE geometry estimated from the brochure; not the manufacturer's data.
* ``excavator_gripper`` - a walking-excavator-like arm in the style of HEAP
  (paper 002) with a two-jaw rotating gripper: slew, boom, stick, and a wrist
  of three intersecting axes (pitch, tilt, rotator) with a closed-form IK
  (:mod:`fabflow.robots.excavator`). All zero: boom and stick level forward,
  the gripper continuing the stick; home 0, 30, -100, -20, 0, 0 deg with the
  gripper pointing down in front of the machine. APPROXIMATE, lengths
  estimated, not manufacturer data.
* ``excavator_printer`` - the same arm (HEAP is the Menzi Muck M545 of paper
  000 too) carrying a print head, a LiDAR and a prism on its tilt-rotator.

Besides the catalogue, a project file may define its own robot
(``robot.model: custom``, :mod:`fabflow.robots.custom`): validating the project
builds its model and registers it here (:func:`register_robot`) under a name
that carries a hash of its definition, ``custom:NAME@HASH``; every function of
this module then takes that name like a catalogue one, in this process.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from fabflow.errors import UnsupportedError
from fabflow.robots.chain import RobotModel, dh_table
from fabflow.robots.excavator import ExcavatorParameters, excavator_dh, excavator_ik
from fabflow.robots.opw import OPWParameters, opw_ik
from fabflow.robots.ur_ik import ur_ik

_DEG = np.pi / 180.0


def _rz_pi() -> np.ndarray:
    T = np.eye(4)
    T[0, 0] = T[1, 1] = -1.0
    return T


KR60_3_OPW = OPWParameters(
    a1=0.350,
    a2=-0.145,
    b=0.0,
    c1=0.815,
    c2=0.850,
    c3=0.820,
    c4=0.170,
    offsets=(0.0, -np.pi / 2, 0.0, 0.0, 0.0, 0.0),
    signs=(-1.0, 1.0, 1.0, -1.0, 1.0, -1.0),
)
"""KR 60-3 in OPW form (same numbers as the DH table: d1, a1, a2, a3, d4, d6)."""

IRB4600_60_205_OPW = OPWParameters(
    a1=0.175,
    a2=-0.175,
    b=0.0,
    c1=0.495,
    c2=0.900,
    c3=0.960,
    c4=0.135,
    offsets=(0.0, 0.0, -np.pi / 2, 0.0, 0.0, 0.0),
    signs=(1.0, 1.0, 1.0, 1.0, 1.0, 1.0),
)
"""IRB 4600-60/2.05 in OPW form (ABB product specification dimensions)."""


def _kuka_kr60_3() -> RobotModel:
    return RobotModel(
        name="kuka_kr60_3",
        dh=dh_table(
            a=[0.350, 0.850, 0.145, 0.0, 0.0, 0.0],
            alpha_deg=[-90, 0, -90, 90, -90, 0],
            d=[0.815, 0.0, 0.0, 0.820, 0.0, 0.170],
            offset_deg=[0, 0, -90, 0, 0, 180],
        ),
        joint_sign=np.array([-1.0, 1.0, 1.0, -1.0, 1.0, -1.0]),
        joint_limits=np.array(
            [[-185, 185], [-135, 35], [-120, 158], [-350, 350], [-119, 119], [-350, 350]],
            dtype=float,
        )
        * _DEG,
        velocity_limits=np.array([128, 102, 128, 260, 245, 322], dtype=float) * _DEG,
        T_n_flange=np.eye(4),
        reach=2.033 + 0.170,
        description="KUKA KR 60-3; DH from DESIGN.md, limits and speeds from the KUKA data sheet",
        motion_groups=((0, 1, 2, 3, 4, 5),),
        analytic_ik=lambda T, q_ref=None, arms=None: opw_ik(KR60_3_OPW, T, q_ref, arms),
        q_nominal=np.array([0, -90, 90, 0, 45, 0], dtype=float) * _DEG,
        q_home=np.array([0, -90, 90, 0, 0, 0], dtype=float) * _DEG,
        payload=60.0,
        opw=KR60_3_OPW,
    )


def _abb_irb4600_60_205() -> RobotModel:
    return RobotModel(
        name="abb_irb4600_60_205",
        dh=dh_table(
            a=[0.175, 0.900, 0.175, 0.0, 0.0, 0.0],
            alpha_deg=[-90, 0, -90, 90, -90, 0],
            d=[0.495, 0.0, 0.0, 0.960, 0.0, 0.135],
            offset_deg=[0, -90, 0, 0, 0, 180],
        ),
        joint_sign=np.ones(6),
        joint_limits=np.array(
            [[-180, 180], [-90, 150], [-180, 75], [-400, 400], [-125, 120], [-400, 400]],
            dtype=float,
        )
        * _DEG,
        velocity_limits=np.array([175, 175, 175, 250, 250, 360], dtype=float) * _DEG,
        T_n_flange=np.eye(4),
        reach=2.050,
        description="ABB IRB 4600-60/2.05; ABB product specification geometry and limits",
        motion_groups=((0, 1, 2, 3, 4, 5),),
        analytic_ik=lambda T, q_ref=None, arms=None: opw_ik(IRB4600_60_205_OPW, T, q_ref, arms),
        q_nominal=np.array([0, 0, 0, 0, 45, 0], dtype=float) * _DEG,
        q_home=np.array([0, 0, 0, 0, 30, 0], dtype=float) * _DEG,
        payload=60.0,
        opw=IRB4600_60_205_OPW,
    )


UR10E_DH = {
    "d1": 0.1807,
    "a2": -0.6127,
    "a3": -0.57155,
    "d4": 0.17415,
    "d5": 0.11985,
    "d6": 0.11655,
}
"""Universal Robots' published DH parameters of the UR10e (metres)."""


def _ur10e() -> RobotModel:

    p = UR10E_DH
    return RobotModel(
        name="ur10e",
        dh=dh_table(
            a=[0.0, p["a2"], p["a3"], 0.0, 0.0, 0.0],
            alpha_deg=[90, 0, 0, 90, -90, 0],
            d=[p["d1"], 0.0, 0.0, p["d4"], p["d5"], p["d6"]],
            offset_deg=[0, 0, 0, 0, 0, 0],
        ),
        joint_sign=np.ones(6),
        joint_limits=np.tile([-2 * np.pi, 2 * np.pi], (6, 1)),
        velocity_limits=np.array([120, 120, 180, 180, 180, 180], dtype=float) * _DEG,
        T_n_flange=np.eye(4),
        reach=1.300,
        description="Universal Robots UR10e; published DH parameters, +-360 deg on every joint",
        motion_groups=((0, 1, 2, 3, 4, 5),),
        analytic_ik=lambda T, q_ref=None: ur_ik(p, T, q_ref),
        q_nominal=np.array([0, -90, 90, -90, -90, 0], dtype=float) * _DEG,
        q_home=np.array([0, -90, 0, -90, 0, 0], dtype=float) * _DEG,
        payload=12.5,
    )


def _brokk_170() -> RobotModel:
    # Tool (breaker + chisel) along x5; the flange z axis is the chisel axis.
    T_5_flange = np.array(
        [[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    )
    return RobotModel(
        name="brokk_170",
        dh=dh_table(
            a=[0.25, 1.55, 1.25, 0.85, 0.75],
            alpha_deg=[90, 0, 0, 0, 0],
            d=[0.70, 0.0, 0.0, 0.0, 0.0],
            offset_deg=[0, 0, 0, 0, 0],
        ),
        joint_sign=np.ones(5),
        joint_limits=np.array(
            [[-180, 180], [-30, 75], [-160, -10], [-100, 60], [-110, 50]], dtype=float
        )
        * _DEG,
        velocity_limits=np.array([30, 15, 20, 25, 30], dtype=float) * _DEG,
        T_n_flange=T_5_flange,
        reach=0.25 + 1.55 + 1.25 + 0.85 + 0.75,
        approximate=True,
        description=(
            "APPROXIMATE 5-axis demolition machine in the style of the BROKK 170 "
            "(slew, boom, arm 2, arm 3, tool tilt); lengths estimated, not manufacturer data"
        ),
        motion_groups=((1,), (0, 2, 3, 4)),
        analytic_ik=None,
        q_nominal=np.array([0, 30, -90, -20, -40], dtype=float) * _DEG,
        q_home=np.array([0, 30, -90, -20, -40], dtype=float) * _DEG,
        payload=250.0,
    )


HEAP_GRIPPER = ExcavatorParameters(d1=1.80, a1=0.50, a2=4.00, a3=2.50, d6=0.40)
"""The excavator arm's lengths (metres), estimates for a machine of HEAP's size, not
measured: boom pivot 0.5 m ahead of and 1.8 m above the foot of the slew axis,
boom 4.0 m, stick 2.5 m (7.0 m from the boom pivot to the wrist centre), wrist
centre to flange 0.4 m."""


def _excavator(name: str, tool: str, paper: str) -> RobotModel:
    p = HEAP_GRIPPER
    return RobotModel(
        name=name,
        dh=excavator_dh(p),
        joint_sign=np.ones(6),
        joint_limits=np.array(
            [[-180, 180], [-40, 70], [-150, -30], [-90, 90], [-45, 45], [-360, 360]], dtype=float
        )
        * _DEG,
        velocity_limits=np.array([30, 20, 25, 30, 20, 40], dtype=float) * _DEG,
        T_n_flange=np.eye(4),
        reach=p.a1 + p.a2 + p.a3 + p.d6,
        approximate=True,
        description=(
            f"APPROXIMATE walking-excavator-like arm in the style of HEAP ({paper}) with "
            f"{tool}; lengths estimated, not manufacturer data"
        ),
        motion_groups=((0, 1, 2, 3, 4, 5),),
        analytic_ik=lambda T, q_ref=None: excavator_ik(p, T, q_ref),
        q_nominal=np.array([0, 15, -80, -25, 0, 0], dtype=float) * _DEG,
        q_home=np.array([0, 30, -100, -20, 0, 0], dtype=float) * _DEG,
        payload=4000.0,
    )


def _excavator_gripper() -> RobotModel:
    return _excavator("excavator_gripper", "a two-jaw rotating gripper", "paper 002")


def _excavator_printer() -> RobotModel:
    return _excavator("excavator_printer", "a print head on its tilt-rotator", "paper 000")


@dataclass(frozen=True)
class Vendor:
    """A machine maker and the controller fabflow writes programs for.

    Attributes
    ----------
    name
        The maker's name (``"KUKA"``).
    controller
        The controller and software generation the programs are written for.
    language
        The controller's program format in :data:`PROGRAM_FORMATS`, or ``None``
        when the machine has no language of its own (a retrofitted gateway).
    """

    name: str
    controller: str
    language: str | None


VENDORS: dict[str, Vendor] = {
    "kuka": Vendor("KUKA", "KR C4 / KSS 8.x", "krl"),
    "abb": Vendor("ABB", "IRC5 / RobotWare 6", "rapid"),
    "ur": Vendor("Universal Robots", "e-Series / PolyScope 5", "urscript"),
    "brokk": Vendor("Brokk", "retrofitted gateway (UDP/CAN)", None),
    "heap": Vendor("Menzi Muck (HEAP-style retrofit)", "retrofitted gateway (UDP/CAN)", None),
}
"""Makers by key; every catalogue robot names one."""


@dataclass(frozen=True)
class ControllerProfile:
    """Limits of one controller that shape how a program is cut into modules.

    Attributes
    ----------
    name
        The controller and software generation.
    vendor
        The :data:`VENDORS` key of its maker.
    module_motions
        Most motion instructions (and their point declarations) one program
        module holds, or ``None`` for no limit. Programs are split between
        elements below it.
    """

    name: str
    vendor: str
    module_motions: int | None


CONTROLLERS: dict[str, ControllerProfile] = {
    # KUKA publishes no hard limit per module; the robot program memory (R1) and
    # the smartPAD editor, slow beyond a few thousand lines, bound it in practice.
    # 1,000 motions make a .src of about 2,000 lines and a .dat of about 1,000.
    "krc4": ControllerProfile("KR C4 / KSS 8.x", "kuka", 1000),
    "krc5": ControllerProfile("KR C5 / KSS 8.7", "kuka", 1000),
    # RAPID modules live in the task's program memory; 2,000 robtargets keep a
    # module near 0.5 MB of text, quick to load and to open on the FlexPendant.
    "irc5": ControllerProfile("IRC5 / RobotWare 6", "abb", 2000),
    "omnicore": ControllerProfile("OmniCore / RobotWare 7", "abb", 2000),
    "ur_eseries": ControllerProfile("e-Series / PolyScope 5", "ur", None),
    "gateway": ControllerProfile("retrofitted gateway (UDP/CAN)", "brokk", None),
    "heap_gateway": ControllerProfile("retrofitted gateway (UDP/CAN)", "heap", None),
}
"""Controller profiles by key; every vendor's first is its default."""


def controller_mismatch(key: str | None, robot: str) -> str | None:
    """Why the controller profile ``key`` does not drive ``robot``; ``None`` when it does."""
    if key is None:
        return None
    if key not in CONTROLLERS:
        return f"unknown controller {key!r}; known: {', '.join(CONTROLLERS)}"
    profile, vendor = CONTROLLERS[key], vendor_of(robot)
    if profile.vendor == vendor:
        return None
    return (
        f"'{key}' ({profile.name}) is not a controller of the robot '{robot}' "
        f"({VENDORS[vendor].name})"
    )


def controller_profile(robot: str, key: str | None = None) -> ControllerProfile:
    """The controller profile ``key``, or the default of ``robot``'s vendor.

    Raises
    ------
    UnsupportedError
        For an unknown key, or a controller of another vendor than the robot's.
    """
    why = controller_mismatch(key, robot)
    if why is not None:
        raise UnsupportedError(why)
    if key is None:
        return next(p for p in CONTROLLERS.values() if p.vendor == vendor_of(robot))
    return CONTROLLERS[key]


def robot_setup_problems(
    name: str, home_deg: tuple[float, ...] | None, tool_mass: float
) -> list[tuple[tuple[str, ...], str]]:
    """What a project's HOME and tool mass get wrong for robot ``name``.

    Parameters
    ----------
    name
        Catalogue (or registered) robot.
    home_deg
        The HOME joint values in degrees (millimetres for a sliding joint), or
        ``None`` (the robot's own).
    tool_mass
        The tool's mass (kg).

    Returns
    -------
    list
        (field path under ``robot``, message) per problem; empty when none.
    """
    arm = get_robot(name)
    problems: list[tuple[tuple[str, ...], str]] = []
    if home_deg is not None and len(home_deg) != arm.dof:
        problems.append((("home_deg",), f"{name} has {arm.dof} axes, got {len(home_deg)}"))
    elif home_deg is not None:
        lo, hi = arm.to_deg(arm.joint_limits.T)
        outside = [
            f"axis {i + 1}: {v:g} not in [{lo[i]:g}, {hi[i]:g}]"
            for i, v in enumerate(home_deg)
            if not lo[i] <= v <= hi[i]
        ]
        if outside:
            problems.append((("home_deg",), "outside the joint limits: " + "; ".join(outside)))
    if tool_mass > arm.payload:
        why = f"{tool_mass:g} kg exceeds the {name}'s rated payload of {arm.payload:g} kg"
        problems.append((("tool", "mass"), why))
    return problems


NEUTRAL_FORMATS: tuple[str, ...] = ("json",)
"""Program formats any machine takes: a command stream its own gateway follows."""

PRINT_FORMATS: tuple[str, ...] = ("gcode",)
"""Neutral program formats for print paths only (G-code): any machine, no blocks or task points."""

GCODE_FLAVORS: tuple[str, ...] = ("marlin", "robot")
"""The dialects of the ``gcode`` format: RepRap/Marlin, or a robot's G-code interpreter."""

PROGRAM_FORMATS: tuple[str, ...] = (
    *(v.language for v in VENDORS.values() if v.language is not None),
    *NEUTRAL_FORMATS,
    *PRINT_FORMATS,
)
"""Every program format fabflow writes: the vendors' languages, the neutral ones, then
those for print paths only."""

_CATALOGUE = {
    "kuka_kr60_3": (_kuka_kr60_3, "kuka"),
    "ur10e": (_ur10e, "ur"),
    "abb_irb4600_60_205": (_abb_irb4600_60_205, "abb"),
    "brokk_170": (_brokk_170, "brokk"),
    "excavator_gripper": (_excavator_gripper, "heap"),
    "excavator_printer": (_excavator_printer, "heap"),
}

ROBOT_NAMES: tuple[str, ...] = tuple(_CATALOGUE)
"""Names of the catalogue robots, accepted by :func:`get_robot`."""

CUSTOM_MODEL = "custom"
"""``robot.model`` of a robot the project file defines itself (``robot.custom``)."""

CUSTOM_PREFIX = "custom:"
"""Registered robots are named ``custom:NAME@HASH``."""

_REGISTERED: dict[str, tuple[RobotModel, str]] = {}
"""Robots defined in project files, registered in this process: name to (model, vendor)."""


def register_robot(model: RobotModel, vendor: str) -> str:
    """Make a robot defined outside the catalogue known to :func:`get_robot` and the rest.

    Parameters
    ----------
    model
        The machine model; its ``name`` must start with :data:`CUSTOM_PREFIX` and
        should carry a hash of its definition (one name, one geometry).
    vendor
        Its maker's :data:`VENDORS` key (program language, controller profiles).

    Returns
    -------
    str
        ``model.name``. Registering the same name again keeps the first model.
    """
    if not model.name.startswith(CUSTOM_PREFIX) or vendor not in VENDORS:
        raise ValueError(f"cannot register {model.name!r} of vendor {vendor!r}")
    _REGISTERED.setdefault(model.name, (model, vendor))
    return model.name


def is_registered(name: str) -> bool:
    """Whether ``name`` is a robot registered in this process (not a catalogue one)."""
    return name in _REGISTERED


def vendor_of(name: str) -> str:
    """The :data:`VENDORS` key of a robot (``"kuka"`` for ``"kuka_kr60_3"``)."""
    _check_name(name)
    if name in _REGISTERED:
        return _REGISTERED[name][1]
    return _CATALOGUE[name][1]


def format_vendor(fmt: str) -> str | None:
    """The :data:`VENDORS` key whose controllers run programs of ``fmt``; ``None`` if any."""
    return next((k for k, v in VENDORS.items() if v.language == fmt), None)


def formats_of(name: str) -> tuple[str, ...]:
    """The program formats a robot runs: its vendor's language, then the neutral ones.

    ``("rapid", "json")`` for ``"abb_irb4600_60_205"``; a machine without a
    language of its own runs the neutral formats only.
    """
    return vendor_formats(vendor_of(name))


def vendor_formats(vendor: str) -> tuple[str, ...]:
    """The program formats the machines of a :data:`VENDORS` key run (see :func:`formats_of`)."""
    language = VENDORS[vendor].language
    return (*((language,) if language is not None else ()), *NEUTRAL_FORMATS)


def format_mismatch(fmt: str, name: str) -> str | None:
    """Why programs of ``fmt`` do not run on robot ``name``, with the formats that do.

    Returns
    -------
    str or None
        ``None`` when they do (or ``fmt`` is unknown: the caller reports that).
    """
    vendor = format_vendor(fmt)
    if vendor is None or vendor == vendor_of(name):
        return None
    fits = " or ".join(f"'{f}'" for f in formats_of(name))
    return (
        f"'{fmt}' programs run on {VENDORS[vendor].name} controllers, but the robot "
        f"'{name}' is by {VENDORS[vendor_of(name)].name}; use format {fits}"
    )


def _check_name(name: str) -> None:
    if isinstance(name, str) and (name in _CATALOGUE or name in _REGISTERED):
        return
    if isinstance(name, str) and name.startswith(CUSTOM_PREFIX):
        raise UnsupportedError(
            f"{name!r} is a robot defined in a project file (robot.custom), unknown "
            "here: load that project first; known models: " + ", ".join(ROBOT_NAMES)
        )
    raise UnsupportedError(f"unknown robot model {name!r}; known models: {', '.join(ROBOT_NAMES)}")


def get_robot(name: str) -> RobotModel:
    """The machine model for a name (one shared instance per name).

    Parameters
    ----------
    name
        One of :data:`ROBOT_NAMES`, or a robot registered with :func:`register_robot`.

    Raises
    ------
    UnsupportedError
        For an unknown name (the message lists the known ones).
    """
    _check_name(name)
    if name in _REGISTERED:
        return _REGISTERED[name][0]
    return _build(name)


@cache
def _build(name: str) -> RobotModel:
    return _CATALOGUE[name][0]()
