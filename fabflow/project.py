"""The project file: a declarative description of one fabrication job.

A project is a YAML file validated by the pydantic models below. Lengths are in
metres, angles in the field's named unit (``*_deg`` fields are degrees), poses
are given as ``{xyz: [x, y, z], abc_deg: [A, B, C]}`` with R = Rz(A) Ry(B) Rx(C)
(the KUKA convention). Relative paths resolve against the project file's folder.

Load with :func:`load_project`; every problem becomes a :class:`~fabflow.errors.InputError`
naming the file, the field path (``elements[0].cabin.block.length``) and the line.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    Field,
    Strict,
    ValidationError,
    model_validator,
)

from fabflow.design.generate import element_count_bound
from fabflow.design.specs import ELEMENT_KINDS, ElementSource, StoneWallSpec
from fabflow.errors import InputError, UnsupportedError
from fabflow.localization_setup import IcpSetup, IntegrityPolicy, TotalStationSetup, UwbSetup
from fabflow.robots.catalog import (
    CONTROLLERS,
    CUSTOM_MODEL,
    GCODE_FLAVORS,
    PRINT_FORMATS,
    PROGRAM_FORMATS,
    ROBOT_NAMES,
    controller_mismatch,
    format_mismatch,
    formats_of,
    robot_setup_problems,
)
from fabflow.robots.custom import (
    CustomRobot,
    custom_formats,
    register_custom_robot,
    robot_section_problem,
)
from fabflow.schema import (
    Count,
    Limits,
    NonNegativeFloat,
    PoseSpec,
    PositiveCount,
    PositiveFloat,
    Real,
    StrictModel,
    Switch,
    Vec2,
    Vec3,
    error_lines,
    located,
)
from fabflow.schema import format_loc as format_loc  # the field paths of every message
from fabflow.yaml_input import parse_yaml, read_yaml

LOCALIZATION_METHODS: tuple[str, ...] = ("uwb", "total_station", "icp")
"""The localization methods, one setup section each below; :mod:`fabflow.localize.methods`
maps each to its ``localize_station``."""

RobotName = Literal[(*ROBOT_NAMES, CUSTOM_MODEL)]  # type: ignore[valid-type]
ControllerName = Literal[tuple(CONTROLLERS)]  # type: ignore[valid-type]
ExternalAxis = Literal["E1", "E2", "E3", "E4", "E5", "E6"]
ProgramFormat = Literal[PROGRAM_FORMATS]  # type: ignore[valid-type]
LocalizationMethod = Literal[LOCALIZATION_METHODS]  # type: ignore[valid-type]


# --------------------------------------------------------------------------- site


class BoxObstacle(StrictModel):
    """An axis-aligned box obstacle in the site frame (metres)."""

    name: str = "box"
    min: Vec3
    max: Vec3

    @model_validator(mode="after")
    def _ordered(self) -> BoxObstacle:
        if any(lo >= hi for lo, hi in zip(self.min, self.max, strict=True)):
            raise ValueError("every component of 'min' must be smaller than 'max'")
        return self


class PolygonObstacle(StrictModel):
    """A vertical prism obstacle: a plan polygon (metres) extruded from ``z_min`` to ``z_max``."""

    name: str = "polygon"
    points: Annotated[list[Vec2], Field(min_length=3)]
    z_min: Real = 0.0
    z_max: Real = 3.0

    @model_validator(mode="after")
    def _ordered(self) -> PolygonObstacle:
        if self.z_min >= self.z_max:
            raise ValueError("'z_min' must be smaller than 'z_max'")
        return self


class Obstacle(StrictModel):
    """One obstacle, either ``box: {...}`` or ``polygon: {...}``."""

    box: BoxObstacle | None = None
    polygon: PolygonObstacle | None = None

    @model_validator(mode="after")
    def _exactly_one(self) -> Obstacle:
        if (self.box is None) == (self.polygon is None):
            raise ValueError("give exactly one of 'box' or 'polygon'")
        return self


class Site(StrictModel):
    """The building site: usable ground rectangle and obstacles, in the site (world) frame."""

    frame: str = "world"
    extent_min: Vec2 = (-5.0, -5.0)
    extent_max: Vec2 = (10.0, 10.0)
    obstacles: list[Obstacle] = []

    @model_validator(mode="after")
    def _ordered(self) -> Site:
        if any(lo >= hi for lo, hi in zip(self.extent_min, self.extent_max, strict=True)):
            raise ValueError("'extent_min' must be smaller than 'extent_max' in x and y")
        return self


# -------------------------------------------------------------------------- robot


class Tool(StrictModel):
    """The end effector: its name, the tool centre point and its load in the flange frame."""

    name: str = "gripper"
    T_flange_tool: PoseSpec = PoseSpec(xyz=(0.0, 0.0, 0.20))
    mass: PositiveFloat = 10.0
    """Mass of the tool in kg, written as the controller's load data (KRL ``$LOAD``,
    RAPID ``tooldata``, URScript ``set_payload``); at most the robot's rated payload.
    Set it for the real tool: the default is a stand-in the program header names."""
    cog: Vec3 = (0.0, 0.0, 0.1)
    """Centre of gravity of the tool in the flange frame (metres)."""


class Platform(StrictModel):
    """The mobile platform carrying the arm.

    ``footprint`` is the platform's plan rectangle (length along its x axis, width
    along y) centred on the platform origin; ``lift`` the range of the arm base
    height above the ground (metres); ``T_platform_base`` the arm mounting at the
    lowest lift position; ``safety_margin`` the clearance kept around the footprint.
    """

    footprint: tuple[PositiveFloat, PositiveFloat] = (2.2, 1.6)
    lift: Vec2 = (0.0, 1.2)
    T_platform_base: PoseSpec = PoseSpec(xyz=(0.0, 0.0, 0.6))
    safety_margin: NonNegativeFloat = 0.3
    T_platform_pick: PoseSpec = PoseSpec(xyz=(-0.9, 0.0, 0.7))
    """Where the robot picks blocks from (a magazine on the platform)."""
    lift_axis: ExternalAxis | None = None
    """The controller's external axis that drives the lift (``E1`` ... ``E6``; its
    value the lift height above the lowest position in mm): the programs carry the
    height in every target. Without one the operator sets the lift: each program
    stops before its first motion, names the height and waits for confirmation."""

    @model_validator(mode="after")
    def _lift(self) -> Platform:
        if self.lift[0] > self.lift[1]:
            raise ValueError("'lift' must be [min, max] with min <= max")
        return self


class Robot(StrictModel):
    """The robot arm, its tool and the platform it stands on."""

    model: RobotName = "kuka_kr60_3"
    custom: CustomRobot | None = None
    """The robot itself when ``model`` is ``custom``: OPW parameters, a DH table or a
    URDF file, with limits, speeds, HOME and payload (:mod:`fabflow.robots.custom`)."""
    tool: Tool = Tool()
    platform: Platform = Platform()
    home_deg: tuple[Real, ...] | None = None
    """The HOME joint configuration every program starts and ends at (degrees, the
    controller's joint values); default: the catalogue robot's home."""

    @property
    def name(self) -> str:
        """The name robot functions take (``get_robot``, writers): the catalogue ``model``,
        or ``custom:NAME@HASH`` of the robot in ``custom``, registered here if not yet."""
        if self.custom is None:
            return self.model
        return register_custom_robot(self.custom)

    def __setstate__(self, state: dict[Any, Any]) -> None:
        # A project unpickled in another process (a Dask worker) registers its robot there.
        super().__setstate__(state)
        if self.custom is not None:
            register_custom_robot(self.custom)

    @model_validator(mode="after")
    def _home_and_load_fit_the_arm(self) -> Robot:
        why = robot_section_problem(self.model, self.custom)  # registers a defined robot
        if why is not None:
            raise located(("robot", *why[0]), why[1])
        problems = robot_setup_problems(self.name, self.home_deg, self.tool.mass)
        if problems:
            field_path, why = problems[0]
            raise located(("robot", *field_path), why)
        return self


# ------------------------------------------------------------------- localization


class Localization(StrictModel):
    """Which method localizes the platform at each station, with that method's setup."""

    method: LocalizationMethod = "total_station"
    uwb: UwbSetup | None = None
    total_station: TotalStationSetup | None = None
    icp: IcpSetup | None = None
    integrity: IntegrityPolicy = IntegrityPolicy()

    @model_validator(mode="after")
    def _setup_present(self) -> Localization:
        if self.method == "uwb" and self.uwb is None:
            raise ValueError(
                "method 'uwb' needs a 'uwb' section (its anchors are planned when it names none)"
            )
        return self

    def setup(self) -> UwbSetup | TotalStationSetup | IcpSetup:
        """The setup of the chosen method (defaults filled in where optional)."""
        if self.method == "uwb":
            assert self.uwb is not None
            return self.uwb
        if self.method == "total_station":
            return self.total_station or TotalStationSetup()
        return self.icp or IcpSetup()


# ------------------------------------------------------------------- the rest


class Tolerances(StrictModel):
    """Allowed deviation of an as-built element from its design pose."""

    position: PositiveFloat = 0.01
    """metres"""
    rotation_deg: PositiveFloat = 1.0


class Planning(StrictModel):
    """Station planning settings."""

    max_stations: PositiveCount | None = None
    """Fail when the plan needs more stations than this (no limit when absent)."""
    candidate_spacing: PositiveFloat = 0.25
    """Grid spacing of candidate platform positions (metres)."""
    headings_deg: Annotated[list[Real], Field(min_length=1)] = [0.0, 90.0, 180.0, 270.0]
    lift_step: PositiveFloat = 0.25
    """Spacing of the lift heights the planner considers (metres)."""
    reach_margin: NonNegativeFloat = 0.08
    """Every target stays this far inside the arm's reach (metres), for parking error."""
    start: Vec2 | None = None
    """Where the platform enters the site; the tour starts near it (default: extent_min)."""


class GcodeSettings(StrictModel):
    """How ``program.format: gcode`` writes print paths (docs/programs.md, G-code)."""

    flavor: Literal[GCODE_FLAVORS] = "marlin"  # type: ignore[valid-type]
    """``marlin``: RepRap/Marlin G-code, E the filament length (mm, ``M82`` absolute);
    ``robot``: for a robot's G-code interpreter driving an extruder, E the deposited
    volume (mm^3). Both write positions in the robot base frame at the station."""
    filament_diameter: PositiveFloat = 0.00175
    """Diameter of the filament, or of the material column the extruder feeds, whose
    length E counts in the ``marlin`` flavour (metres; RepRap's 1.75 mm by default)."""


class ProgramSettings(StrictModel):
    """Robot program output settings."""

    format: ProgramFormat = "krl"
    """Default: the robot's own language (``krl``, ``rapid``, ``urscript``; ``json``
    for a machine without one). ``gcode`` writes print paths only, for any robot."""
    gcode: GcodeSettings = GcodeSettings()
    """The G-code flavour and filament (``format: gcode``)."""
    speed: PositiveFloat = 0.25
    """Cartesian speed for linear moves (m/s)."""
    approach: PositiveFloat = 0.10
    """Approach and retract distance above a target (metres); for a block at least its
    height plus twice the clearance (the held block clears its neighbours)."""
    clearance: NonNegativeFloat = 0.01
    """Smallest distance of the arm, tool and held block from the structure as built,
    the platform, the magazine and site obstacles along every motion (metres)."""
    check_collisions: bool | Literal["report"] = True
    """Check every program for collisions and re-plan what collides; what still does
    is an error naming the move (true), or is written into the program header and
    the build report (``report``); false skips the check."""
    blend: NonNegativeFloat = 0.01
    """Blending (approximation) distance (metres)."""
    controller: ControllerName | None = None
    """The controller profile (``krc4``, ``krc5``, ``irc5``, ``omnicore``, ...): how
    many motions one program module may hold. Default: the robot vendor's first."""
    module_motions: Annotated[int, Strict(), Field(ge=20, le=100_000)] | None = None
    """Most motions per program module, overriding the controller profile's."""


class Simulation(StrictModel):
    """Sensor and execution noise for simulated runs."""

    seed: Annotated[Count, Field(lt=2**63)] = 0
    driving_error: NonNegativeFloat = 0.02
    """Standard deviation of the platform's parking error per axis (metres)."""
    driving_heading_error_deg: NonNegativeFloat = 0.5
    robot_repeatability: NonNegativeFloat = 0.0002
    """Standard deviation of the placed tool position per axis (metres)."""
    lift_error: NonNegativeFloat = 0.001
    """Standard deviation of the lift height at each placement (metres, vertical)."""
    sensor_noise: Switch = True
    """``false``: simulated localization is exact (estimate = true base pose, zero
    covariance), e.g. to isolate driving and execution errors in ``fabflow simulate``."""
    runs: PositiveCount = 100
    """Default number of Monte Carlo runs of ``fabflow simulate``."""


class Tracking(StrictModel):
    """How ``fabflow track`` runs a print on the simulated hydraulic machine (paper 000).

    The sensor errors are :class:`~fabflow.sensors.excavator.ExcavatorErrors`'
    (``simulation.sensor_noise: false`` turns them off); docs/tracking.md
    states each with its source.
    """

    dead_time_s: Annotated[float, Field(ge=0.0, le=2.0)] = 0.08
    """Delay between a valve command and the joint's response (s)."""
    lag_s: Annotated[float, Field(ge=0.0, le=2.0)] = 0.1
    """Time constant of the flow build-up (s)."""
    deadband: Annotated[float, Field(ge=0.0, lt=0.5)] = 0.02
    """Valve fraction below which no oil flows."""
    icp_latency_s: Annotated[float, Field(ge=0.0, le=1.0)] = 0.1
    """Time from a LiDAR scan to its ICP pose reaching the filter (s)."""
    kp: Annotated[float, Field(ge=0.0, le=5.0)] = 0.5
    """Print-head loop: proportional gain (the share of the pose error corrected at once)."""
    ki: Annotated[float, Field(ge=0.0, le=5.0)] = 0.5
    """Print-head loop: integral gain (1/s); a bias decays with ``(1 + kp) / ki`` seconds."""
    settle_s: Annotated[float, Field(ge=0.0, le=60.0)] = 10.0
    """Time the machine holds the path's start before it prints (s): the loop settles."""
    max_duration_s: Annotated[float, Field(gt=0.0, le=3600.0)] = 600.0
    """The longest print accepted (s): bounds the simulation's work."""


def _grid_points(lo: float, hi: float, spacing: float) -> float:
    return math.floor((hi - lo) / spacing) + 1.0


class Project(StrictModel):
    """A fabflow project: site, robot, localization, elements and tolerances."""

    name: Annotated[str, Field(min_length=1)]
    description: str = ""
    site: Site = Site()
    robot: Robot = Robot()
    localization: Localization = Localization()
    elements: Annotated[list[ElementSource], Field(min_length=1)]
    tolerances: Tolerances = Tolerances()
    planning: Planning = Planning()
    program: ProgramSettings = ProgramSettings()
    simulation: Simulation = Simulation()
    tracking: Tracking = Tracking()
    """Settings of ``fabflow track`` (a print path on a hydraulic machine)."""
    limits: Limits = Limits()
    """The most work the project may ask for (:class:`~fabflow.schema.Limits`)."""
    allow_outside_paths: Switch = False
    """Files named in the project may lie outside its folder (absolute paths, ``../``)."""

    path: Path | None = Field(default=None, exclude=True)
    """The file the project was loaded from (not part of the file itself)."""

    @model_validator(mode="before")
    @classmethod
    def _default_format_of_the_robot(cls, data: Any) -> Any:
        """Without ``program.format`` a robot gets its vendor's language (JSON if none)."""
        robot = data.get("robot") if isinstance(data, dict) else None
        model = robot.get("model", "kuka_kr60_3") if isinstance(robot, dict) else None
        program = data.get("program", {}) if isinstance(data, dict) else None
        formats = formats_of(model) if model in ROBOT_NAMES else custom_formats(robot)
        if formats and isinstance(program, dict) and "format" not in program:
            data = {**data, "program": {**program, "format": formats[0]}}
        return data

    @model_validator(mode="after")
    def _format_fits_robot(self) -> Project:
        why = format_mismatch(self.program.format, self.robot.name)
        if why is None:
            why = self._print_format_problem(self.program.format)
        if why is not None:
            raise located(("program", "format"), why)
        why = controller_mismatch(self.program.controller, self.robot.name)
        if why is not None:
            raise located(("program", "controller"), why)
        return self

    @model_validator(mode="after")
    def _stone_wall_alone(self) -> Project:
        walls = [i for i, e in enumerate(self.elements) if e.stone_wall is not None]
        if walls and len(self.elements) > 1:
            raise located(
                ("elements", walls[0], "stone_wall"),
                "a stone wall is built from found stones by its own pipeline: make it the "
                "project's only 'elements' entry",
            )
        return self

    def _print_format_problem(self, fmt: str) -> str | None:
        """Why ``fmt``, a format for print paths only, cannot carry the elements; ``None``
        when it can (or is not such a format)."""
        if fmt not in PRINT_FORMATS:
            return None
        for i, source in enumerate(self.elements):
            kind = next((k for k in ELEMENT_KINDS if getattr(source, k) is not None), None)
            if kind is not None and kind != "print_path":
                fits = " or ".join(f"'{f}'" for f in formats_of(self.robot.name))
                return (
                    f"'{fmt}' programs carry print paths only, but elements[{i}] is a "
                    f"'{kind}' source; use format {fits}"
                )
        return None

    def with_program_format(self, fmt: str) -> Project:
        """This project writing its programs in ``fmt`` (``fabflow program --format``).

        Raises
        ------
        UnsupportedError
            When ``fmt`` is not a program format, does not run on the robot, or
            cannot carry the project's elements (G-code: print paths only).
        """
        if fmt not in PROGRAM_FORMATS:
            known = ", ".join(PROGRAM_FORMATS)
            raise UnsupportedError(f"unknown program format '{fmt}'; known: {known}")
        why = format_mismatch(fmt, self.robot.name) or self._print_format_problem(fmt)
        if why is not None:
            raise UnsupportedError(why, self.path)
        return self.model_copy(update={"program": self.program.model_copy(update={"format": fmt})})

    def stone_wall(self) -> StoneWallSpec | None:
        """The project's stone wall (its only element source), or ``None``."""
        return self.elements[0].stone_wall

    def without_stone_wall(self, command: str) -> Project:
        """This project; an :class:`InputError` if it is a stone wall, which ``command`` does
        not handle (no stations to plan: the machine stands still)."""
        if self.stone_wall() is not None:
            raise InputError(
                f"'fabflow {command}' plans stations for designed elements; a stone wall is "
                "built from found stones by 'fabflow build' (its preview.html included) and "
                "studied by 'fabflow simulate'",
                self.path,
                "elements[0].stone_wall",
            )
        return self

    @model_validator(mode="after")
    def _work_within_limits(self) -> Project:
        lim = self.limits
        bounds = [element_count_bound(source) for source in self.elements]
        if sum(bounds) > lim.max_elements:
            i = max(range(len(bounds)), key=bounds.__getitem__)
            kind = next(k for k in ELEMENT_KINDS if getattr(self.elements[i], k) is not None)
            raise located(
                ("elements", i, kind),
                f"the project makes up to {sum(bounds):.4g} elements ({bounds[i]:.4g} from "
                f"this entry), more than limits.max_elements = {lim.max_elements}; raise it "
                "in a 'limits' section if this is meant",
            )
        spacing = self.planning.candidate_spacing
        (x0, y0), (x1, y1) = self.site.extent_min, self.site.extent_max
        n_cand = (
            _grid_points(x0, x1, spacing)
            * _grid_points(y0, y1, spacing)
            * len(self.planning.headings_deg)
        )
        if n_cand > lim.max_candidates:
            raise located(
                ("planning", "candidate_spacing"),
                f"a site of {x1 - x0:g} x {y1 - y0:g} m at {spacing:g} m spacing with "
                f"{len(self.planning.headings_deg)} headings makes {n_cand:.4g} candidate "
                f"stations, more than limits.max_candidates = {lim.max_candidates}",
            )
        uwb = self.localization.uwb
        if uwb is not None:
            ranges = uwb.dwell_s * uwb.rate_hz * len(uwb.tags) * len(uwb.anchors)
            imu = uwb.dwell_s * uwb.imu_rate_hz
            if max(ranges, imu) > lim.max_sensor_samples:
                raise located(
                    ("localization", "uwb", "dwell_s"),
                    f"{uwb.dwell_s:g} s of ranging at {uwb.rate_hz:g} Hz ({len(uwb.tags)} tags, "
                    f"{len(uwb.anchors)} anchors) and IMU records at {uwb.imu_rate_hz:g} Hz make "
                    f"{max(ranges, imu):.4g} samples per station, more than "
                    f"limits.max_sensor_samples = {lim.max_sensor_samples}",
                )
        if self.simulation.runs > lim.max_runs:
            raise located(
                ("simulation", "runs"),
                f"{self.simulation.runs} runs, more than limits.max_runs = {lim.max_runs}",
            )
        return self


# ------------------------------------------------------------------------ loading


def parse_project(
    text: str, source: str | Path = "<string>", base_dir: Path | None = None
) -> Project:
    """Parse and validate project YAML text.

    Parameters
    ----------
    text
        The YAML document.
    source
        Name of the file, used in error messages.
    base_dir
        The project folder: relative paths resolve against it, and files must lie
        inside it unless the project sets ``allow_outside_paths: true`` (default:
        the working folder).

    Raises
    ------
    InputError
        For YAML that does not parse or a project that does not validate; the
        message names the file, the line, the field path and what was expected.
    """
    doc = parse_yaml(text, source)
    return _validate(doc.node, doc.data, source, base_dir)


def _validate(node: Any, data: Any, source: str | Path, base_dir: Path | None) -> Project:
    if not isinstance(data, dict):
        raise InputError("expected a mapping of project fields at the top level", source)
    context = {"base_dir": base_dir, "allow_outside_paths": data.get("allow_outside_paths")}
    try:
        return Project.model_validate(data, context=context)
    except ValidationError as exc:
        lines = error_lines(exc, Project, node)
        message = "invalid project\n  " + "\n  ".join(lines)
        raise InputError(message, source) from None


def load_project(path: str | Path) -> Project:
    """Load and validate a project file.

    Parameters
    ----------
    path
        A project YAML file, or a folder holding ``project.yaml``; at most
        :data:`~fabflow.yaml_input.MAX_YAML_BYTES`, UTF-8.

    Returns
    -------
    Project
        The validated project, with ``path`` set to the resolved file.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "project.yaml"
    doc = read_yaml(path, "project file")
    project = _validate(doc.node, doc.data, path, path.parent.resolve())
    return project.model_copy(update={"path": path.resolve()})


def project_json_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of the project file."""
    schema = Project.model_json_schema(mode="validation")
    schema.get("properties", {}).pop("path", None)
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "fabflow project"
    return schema
