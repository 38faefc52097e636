"""A vendor-neutral robot program: the data every program writer reads.

Frames: the controller's base (work object) frame is the design's world frame,
placed by ``T_base_world`` (the world expressed in the robot base frame, the
inverse of the station's localized ``T_world_base``). Cartesian targets are
tool poses ``T_world_tool`` in that frame, so the design coordinates appear
unchanged in the program and the localization changes only one frame. Every
target also carries the joint configuration ``q`` (radians) that inverse
kinematics chose for it, from which the writers derive configuration bits.
A joint move (``Move.joint``) is the exception: its target is the joint
configuration itself (the HOME move every program starts and ends with).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

MoveKind = Literal["ptp", "lin"]


@dataclass(frozen=True, eq=False)
class Move:
    """A motion to a Cartesian tool target.

    Attributes
    ----------
    kind
        ``"ptp"`` (joint interpolated) or ``"lin"`` (straight line of the tool centre point).
    T_world_tool
        4x4 tool target in the program's base frame (the design world), metres.
    q
        Joint configuration at the target (radians), as chosen by inverse kinematics.
    speed
        Cartesian speed for ``lin`` (m/s); fraction of the maximum joint speed for ``ptp``.
    blend
        Approximation distance (metres); 0 means stop exactly at the target.
    label
        Short name of the target (``"approach"``, ``"place"``, ...).
    element
        Id of the element the move belongs to, if any.
    time
        Planned time at the target, seconds from program start.
    via_q
        (k, dof) joint configurations along a linear move, before the target,
        at most one controller step apart (from the inverse kinematics check).
    via_T_world_tool
        (k, 4, 4) tool poses matching ``via_q``.
    wrist_interpolated
        A linear move past the wrist singularity: the tool centre point follows
        the line, the orientation follows the wrist axes interpolated between
        the two ends, both of the same status (KRL ``$ORI_TYPE = #JOINT``,
        RAPID ``SingArea \\Wrist``); ``via_q`` holds that joint path.
    joint
        True when the target is the joint configuration ``q`` itself (an axis
        target: KRL ``E6AXIS``, RAPID ``jointtarget``); ``T_world_tool`` is then
        its forward kinematics, for readers that want the pose. Only ``ptp``.
    """

    kind: MoveKind
    T_world_tool: np.ndarray
    q: np.ndarray
    speed: float
    blend: float = 0.0
    label: str = ""
    element: str | None = None
    time: float = 0.0
    via_q: np.ndarray | None = None
    via_T_world_tool: np.ndarray | None = None
    wrist_interpolated: bool = False
    joint: bool = False


@dataclass(frozen=True)
class SetOutput:
    """Switch a digital output (gripper, extruder, tool action)."""

    name: str
    value: bool
    element: str | None = None
    time: float = 0.0


@dataclass(frozen=True)
class Wait:
    """Dwell for a number of seconds."""

    seconds: float
    element: str | None = None
    time: float = 0.0


@dataclass(frozen=True)
class Comment:
    """A comment line in the program (an element boundary, a note)."""

    text: str
    element: str | None = None
    time: float = 0.0


@dataclass(frozen=True, eq=False)
class Load:
    """A load as a point mass: the tool at the flange, or the element it holds.

    Attributes
    ----------
    mass
        Mass in kg (> 0).
    cog
        (3,) centre of gravity, metres: in the flange frame for the tool's load
        (``Program.load``), in the tool frame for a held element's
        (``SetPayload.payload``).
    """

    mass: float
    cog: np.ndarray


@dataclass(frozen=True, eq=False)
class SetPayload:
    """From here on the tool holds ``payload`` (an element's load), or nothing (``None``)."""

    payload: Load | None
    element: str | None = None
    time: float = 0.0


Instruction = Move | SetOutput | Wait | Comment | SetPayload


@dataclass(frozen=True)
class Lift:
    """Where the platform's lift must stand while the program runs.

    Attributes
    ----------
    height
        Lift height above its lowest position (metres), from the plan's station.
    axis
        External axis that drives the lift (``"E1"`` ... ``"E6"``), carried in
        every target of the formats that have external axes; ``None`` when the
        operator sets the lift by hand: the program then stops before its first
        motion and waits for the operator's confirmation.
    """

    height: float
    axis: str | None = None


@dataclass(frozen=True)
class Bead:
    """The cross-section of the bead a print path lays: ``width`` x ``height`` (metres)."""

    width: float
    height: float


@dataclass(frozen=True)
class GcodeOptions:
    """How the G-code writer writes a print program (``program.gcode`` of the project).

    Attributes
    ----------
    flavor
        ``"marlin"`` (RepRap/Marlin: E is filament length) or ``"robot"`` (a robot's
        G-code interpreter: E is the deposited volume).
    filament_diameter
        Diameter of the filament, or of the material column the extruder feeds,
        whose length E counts in the ``marlin`` flavour (metres).
    """

    flavor: str = "marlin"
    filament_diameter: float = 0.00175


@dataclass(frozen=True, eq=False)
class Program:
    """One robot program: the work package of one station visit.

    Attributes
    ----------
    name
        Program name (sanitized by each writer to its language's rules).
    robot
        Robot model name (``kuka_kr60_3``, ...).
    T_base_world
        4x4 pose of the design world in the robot base frame (from the localization).
    T_flange_tool
        4x4 tool centre point in the flange frame.
    instructions
        The motion and I/O instructions in order.
    outputs
        Digital output names mapped to controller output numbers.
    header
        Ordered key/value pairs written as header comments (project, station,
        element range, localization method and residuals, fabflow version).
    tool_name
        Name of the tool.
    checks
        The configuration figures of the moves
        (:func:`fabflow.programs.motion_checks.program_checks`): needless swings,
        configuration changes between targets and inside linear moves.
    load
        The tool's load at the flange (mass and centre of gravity).
    lift
        The lift height and how it is set, or ``None`` (no lift to set).
    module_motions
        Most motion instructions one program module may hold (the controller
        profile); longer programs are split between elements. ``None``: no limit.
    confirm
        Messages the operator must confirm before the first motion, after the
        lift's (the program stops for each): moves that still collide.
    beads
        The bead cross-section of every print path element of the program, by
        element id (from its ``bead_width`` and ``layer_height``): what a format
        that meters material (G-code) extrudes along its moves.
    gcode
        The G-code flavour and filament (:class:`GcodeOptions`).
    """

    name: str
    robot: str
    T_base_world: np.ndarray
    T_flange_tool: np.ndarray
    instructions: tuple[Instruction, ...]
    outputs: dict[str, int] = field(default_factory=dict)
    header: dict[str, Any] = field(default_factory=dict)
    tool_name: str = "tool"
    checks: dict[str, Any] = field(default_factory=dict)
    load: Load = field(default_factory=lambda: Load(1.0, np.zeros(3)))
    lift: Lift | None = None
    module_motions: int | None = None
    confirm: tuple[str, ...] = ()
    beads: dict[str, Bead] = field(default_factory=dict)
    gcode: GcodeOptions = field(default_factory=GcodeOptions)

    @property
    def moves(self) -> list[Move]:
        """The motion instructions only, in order."""
        return [i for i in self.instructions if isinstance(i, Move)]

    @property
    def duration(self) -> float:
        """Planned duration in seconds (time of the last instruction)."""
        return max((i.time for i in self.instructions), default=0.0)


def sanitize_identifier(name: str, max_length: int, upper: bool = False) -> str:
    """Make ``name`` a valid identifier for a robot language.

    Letters, digits and underscores only, starting with a letter, at most
    ``max_length`` characters (KRL: 24; RAPID: 32). Over-long names keep their
    start and end so numbered names stay distinct.

    Parameters
    ----------
    name
        Any text.
    max_length
        Longest identifier the language accepts.
    upper
        Upper-case the result.
    """
    cleaned = re.sub(r"[^A-Za-z0-9_]+", "_", name).strip("_") or "P"
    if not cleaned[0].isalpha():
        cleaned = "P" + cleaned
    if len(cleaned) > max_length:
        tail = max_length // 3
        cleaned = cleaned[: max_length - tail - 1] + "_" + cleaned[-tail:]
    return cleaned.upper() if upper else cleaned
