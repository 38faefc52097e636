"""Robots a project file defines itself: OPW parameters, a DH table or a URDF file.

``robot: {model: custom, custom: {...}}`` describes the arm in one of three ways
(exactly one of ``opw``, ``dh``, ``urdf``) plus what every machine model carries::

    robot:
      model: custom
      custom:
        name: my_kr60              # letters, digits, _ . -
        vendor: kuka               # a VENDORS key: program language, controllers
        opw: {a1: 0.350, a2: -0.145, b: 0.0, c1: 0.815, c2: 0.850, c3: 0.820, c4: 0.170,
              offsets_deg: [0, -90, 0, 0, 0, 0], signs: [-1, 1, 1, -1, 1, -1]}
        joint_limits_deg: [[-185, 185], [-135, 35], [-120, 158], [-350, 350], [-119, 119],
                           [-350, 350]]
        joint_speeds_deg_s: [128, 102, 128, 260, 245, 322]
        home_deg: [0, -90, 90, 0, 0, 0]
        nominal_deg: [0, -90, 90, 0, 45, 0]
        payload: 60.0

* ``opw`` - the ortho-parallel parameters of :class:`~fabflow.robots.opw.OPWParameters`
  (metres; ``offsets_deg`` in degrees): closed-form IK. The model's DH table
  is derived from them (``a = a1, c2, -a2, 0, 0, 0``, ``alpha = -90, 0, -90,
  90, -90, 0 deg``, ``d = c1, b, 0, c3, 0, c4``, offsets ``0, -90, -90, 0, 0,
  180 deg`` minus ``offsets_deg``, joint signs ``signs``), the catalogue's
  convention for the KR 60-3 and the IRB 4600.
* ``dh`` - ``a``, ``alpha_deg``, ``d``, ``offset_deg`` and ``joint_sign`` (standard
  DH, ``theta = sign * q + offset``), 1 to 12 joints. A six-axis table in the
  convention above with a spherical wrist is recognised as OPW (checked on
  sampled configurations) and gets the closed-form IK; any other table takes
  numerical IK.
* ``urdf`` - a URDF file (relative to the project file) with ``base_link`` and
  ``tip_link``: the chain between them (:mod:`fabflow.robots.urdf`), its joint
  limits and speeds from the file, numerical IK.

``joint_limits_deg`` ([lower, upper] per joint) and ``joint_speeds_deg_s`` are
required for ``opw`` and ``dh`` (a URDF brings its own). ``home_deg``: the HOME
configuration; ``nominal_deg``: a well-conditioned working configuration
(default HOME); ``payload`` in kg; ``reach`` (metres; default: the stretched
OPW arm's distance from axis 1, else the largest over sampled configurations);
``flange``: the flange in the last joint frame (``{xyz, abc_deg}``, default
none); ``capsules``: the links for collision checks (default 0.1 m between
consecutive frames). In the ``*_deg`` lists a prismatic joint's value is in
millimetres.

Validating the project builds the model and registers it
(:func:`fabflow.robots.catalog.register_robot`) as ``custom:NAME@HASH``, the
hash over the definition (and the URDF text), so that every function taking a
robot name takes it; :func:`register_custom_robot` does it again in any other
process (a Dask worker unpickling the project).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import replace
from functools import partial
from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, PrivateAttr

from fabflow.errors import InputError
from fabflow.robots.catalog import (
    CUSTOM_MODEL,
    CUSTOM_PREFIX,
    VENDORS,
    is_registered,
    register_robot,
    vendor_formats,
)
from fabflow.robots.chain import RobotModel, dh_table
from fabflow.robots.geometry import LinkCapsule
from fabflow.robots.opw import OPWParameters, opw_fk, opw_ik
from fabflow.robots.urdf import MAX_URDF_JOINTS, UrdfError, read_urdf_text, urdf_arm
from fabflow.schema import (
    Count,
    ExistingPath,
    PoseSpec,
    PositiveFloat,
    Real,
    StrictModel,
    Vec3,
)

FloatArray = NDArray[np.float64]

VendorName = Literal[tuple(VENDORS)]  # type: ignore[valid-type]
Sign = Literal[-1, 1]
Six = Annotated[tuple[Real, ...], Field(min_length=6, max_length=6)]
Joints = Annotated[list[Real], Field(min_length=1, max_length=MAX_URDF_JOINTS)]

OPW_ALPHA_DEG = (-90.0, 0.0, -90.0, 90.0, -90.0, 0.0)
"""DH twists of an OPW arm in the catalogue's convention (degrees)."""
OPW_THETA_DEG = (0.0, -90.0, -90.0, 0.0, 0.0, 180.0)
"""DH angle of each joint at the OPW zero pose (degrees): ``theta = q_opw + this``."""
MAX_LIMIT_DEG = 720.0
"""Largest magnitude of a joint limit (degrees: two turns)."""
REACH_SAMPLES = 20_000
"""Configurations sampled for the reach of an arm without an OPW geometry."""
_DEG = np.pi / 180.0


class OPWSpec(StrictModel):
    """An ortho-parallel arm with a spherical wrist (metres; see :class:`OPWParameters`)."""

    a1: Real
    a2: Real
    b: Real = 0.0
    c1: Real
    c2: PositiveFloat
    c3: PositiveFloat
    c4: Real
    offsets_deg: Six = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    """``q_opw = sign * q - offset`` per joint (degrees)."""
    signs: Annotated[tuple[Sign, ...], Field(min_length=6, max_length=6)] = (1, 1, 1, 1, 1, 1)


class DHSpec(StrictModel):
    """A standard DH table, one entry per joint: ``Rz(theta) Tz(d) Tx(a) Rx(alpha)``."""

    a: Joints
    """metres"""
    alpha_deg: Joints
    d: Joints
    """metres"""
    offset_deg: Joints
    joint_sign: Annotated[list[Sign], Field(max_length=MAX_URDF_JOINTS)] | None = None
    """``theta = sign * q + offset``; default +1 for every joint."""


class CapsuleSpec(StrictModel):
    """One link for collision checks: a segment from ``p_a`` in frame ``frame_a`` to
    ``p_b`` in frame ``frame_b`` (metres), every point within ``radius`` of it.

    Frames as :meth:`fabflow.robots.chain.RobotModel.frames` numbers them: 0 the base
    (a URDF arm: joint 1's frame), 1 to dof the joint frames, dof + 1 the flange."""

    name: str = "link"
    frame_a: Count
    p_a: Vec3 = (0.0, 0.0, 0.0)
    frame_b: Count
    p_b: Vec3 = (0.0, 0.0, 0.0)
    radius: PositiveFloat


class CustomRobot(StrictModel):
    """A robot defined in the project file (module docstring)."""

    name: Annotated[str, Field(pattern=r"^[A-Za-z][A-Za-z0-9_.-]{0,39}$")]
    vendor: VendorName
    """The maker: picks the program language and the controller profiles."""
    description: str = ""
    opw: OPWSpec | None = None
    dh: DHSpec | None = None
    urdf: ExistingPath | None = None
    """A URDF file; the arm is its chain from ``base_link`` to ``tip_link``."""
    base_link: str | None = None
    tip_link: str | None = None
    joint_limits_deg: (
        Annotated[list[tuple[Real, Real]], Field(max_length=MAX_URDF_JOINTS)] | None
    ) = None
    """[lower, upper] per joint, the controller's values (degrees; mm for a prismatic joint)."""
    joint_speeds_deg_s: Annotated[list[PositiveFloat], Field(max_length=MAX_URDF_JOINTS)] | None = (
        None
    )
    home_deg: Joints
    nominal_deg: Joints | None = None
    payload: PositiveFloat
    """Rated payload at the flange (kg)."""
    reach: PositiveFloat | None = None
    """Largest distance of the flange from axis 1 (metres); computed when absent."""
    flange: PoseSpec = PoseSpec()
    """The flange frame in the last joint frame (OPW: the OPW flange; URDF: tip_link)."""
    capsules: Annotated[list[CapsuleSpec], Field(max_length=64)] | None = None

    _urdf_text: str | None = PrivateAttr(default=None)
    _key: str | None = PrivateAttr(default=None)


class RobotDefinitionError(InputError):
    """A custom robot definition that does not describe a robot; ``field`` is the path
    of the field under ``custom`` (empty: the definition as a whole)."""

    def __init__(self, field: tuple[str | int, ...], message: str) -> None:
        super().__init__(message)
        self.field = field


def opw_dh(p: OPWSpec) -> tuple[FloatArray, FloatArray]:
    """The DH table and joint signs of an OPW arm (module docstring)."""
    dh = dh_table(
        a=[p.a1, p.c2, -p.a2, 0.0, 0.0, 0.0],
        alpha_deg=list(OPW_ALPHA_DEG),
        d=[p.c1, p.b, 0.0, p.c3, 0.0, p.c4],
        offset_deg=np.array(OPW_THETA_DEG) - np.array(p.offsets_deg, dtype=float),
    )
    return dh, np.array(p.signs, dtype=float)


def opw_parameters(p: OPWSpec) -> OPWParameters:
    """The spec in radians."""
    return OPWParameters(
        a1=p.a1,
        a2=p.a2,
        b=p.b,
        c1=p.c1,
        c2=p.c2,
        c3=p.c3,
        c4=p.c4,
        offsets=tuple(float(v) for v in np.radians(np.array(p.offsets_deg, dtype=float))),
        signs=tuple(float(s) for s in p.signs),
    )


def opw_of_dh(spec: DHSpec) -> OPWSpec | None:
    """The OPW form of a DH table in the catalogue's convention, or ``None`` (structure only:
    :func:`_opw_holds` checks it on sampled configurations)."""
    a, d = np.array(spec.a, dtype=float), np.array(spec.d, dtype=float)
    if (
        len(a) != 6
        or not np.allclose(spec.alpha_deg, OPW_ALPHA_DEG, rtol=0.0, atol=1e-9)
        or np.any(np.abs(a[3:]) > 1e-12)
        or abs(d[4]) > 1e-12
        or a[1] < 1e-9
        or d[3] < 1e-9
    ):
        return None
    return OPWSpec(
        a1=float(a[0]),
        a2=float(-a[2]),
        b=float(d[1] + d[2]),
        c1=float(d[0]),
        c2=float(a[1]),
        c3=float(d[3]),
        c4=float(d[5]),
        offsets_deg=tuple(
            float(v) for v in np.array(OPW_THETA_DEG) - np.array(spec.offset_deg, dtype=float)
        ),
        signs=tuple(spec.joint_sign or (1,) * 6),
    )


def _opw_holds(robot: RobotModel, p: OPWParameters) -> bool:
    """Whether the OPW formulas reproduce the model's DH chain: forward kinematics
    within 1e-9 and every sampled configuration among the closed-form solutions."""
    rng = np.random.default_rng(0)
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    q = rng.uniform(np.maximum(lo, -np.pi), np.minimum(hi, np.pi), (32, 6))
    T_dh = robot.fk(q) @ np.linalg.inv(robot.T_n_flange)
    if not np.allclose(opw_fk(p, q), T_dh, rtol=0.0, atol=1e-9):
        return False
    sols, exists = opw_ik(p, T_dh, q)
    d = np.abs(np.angle(np.exp(1j * (sols - q[:, None, :])))).max(axis=2)
    return bool(np.all(np.any(exists & (d < 1e-6), axis=1)))


def _opw_ik_with_flange(
    p: OPWParameters,
    T_flange_n: FloatArray,
    T_base_flange: FloatArray,
    q_ref: FloatArray | None = None,
    arms: Sequence[int] | None = None,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """:func:`opw_ik` of an arm whose flange is offset from the OPW flange."""
    return opw_ik(p, np.asarray(T_base_flange, dtype=float) @ T_flange_n, q_ref, arms)


def _check_length(values: Sequence[object] | None, dof: int, field: tuple[str, ...]) -> None:
    """``values`` (if given) has one entry per joint."""
    if values is not None and len(values) != dof:
        raise RobotDefinitionError(
            field, f"{dof} values expected (one per joint of this robot), got {len(values)}"
        )


def _capsules(spec: CustomRobot, dof: int) -> tuple[LinkCapsule, ...] | None:
    if spec.capsules is None:
        return None
    caps = []
    for i, c in enumerate(spec.capsules):
        for field, frame in (("frame_a", c.frame_a), ("frame_b", c.frame_b)):
            if frame > dof + 1:
                raise RobotDefinitionError(
                    ("capsules", i, field), f"frame {frame} of {dof + 2} (0 to {dof + 1})"
                )
        caps.append(LinkCapsule(c.name, c.frame_a, c.p_a, c.frame_b, c.p_b, c.radius))
    return tuple(caps)


def _reach(robot: RobotModel, p: OPWParameters | None) -> float:
    """The largest distance of the flange from axis 1 (metres, module docstring)."""
    t = float(np.linalg.norm(robot.T_n_flange[:3, 3]))
    if p is not None:
        return float(np.hypot(p.a1 + p.c2 + np.hypot(p.a2, p.c3) + abs(p.c4) + t, p.b))
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    q = np.random.default_rng(0).uniform(lo, hi, (REACH_SAMPLES, robot.dof))
    p_flange = robot.fk(q)[:, :3, 3]
    return float(np.hypot(p_flange[:, 0], p_flange[:, 1]).max())


def custom_robot_model(spec: CustomRobot, name: str, urdf_text: str | None = None) -> RobotModel:
    """The machine model a definition describes, named ``name``.

    Parameters
    ----------
    spec
        The definition.
    name
        The model's name (:func:`register_custom_robot` gives ``custom:NAME@HASH``).
    urdf_text
        The URDF file's text, for a ``urdf`` definition (read from ``spec.urdf`` if ``None``).

    Raises
    ------
    RobotDefinitionError
        Naming the field under ``custom`` that is missing, of the wrong length,
        outside the limits, or the URDF problem.
    """
    given = [k for k in ("opw", "dh", "urdf") if getattr(spec, k) is not None]
    if len(given) != 1:
        raise RobotDefinitionError(
            (), "give exactly one of 'opw', 'dh' or 'urdf' to define the robot's kinematics"
        )
    for key in ("base_link", "tip_link"):
        if (getattr(spec, key) is None) == (spec.urdf is not None):
            why = "required with 'urdf'" if spec.urdf is not None else "only with 'urdf'"
            raise RobotDefinitionError((key,), why)
    opw: OPWSpec | None = spec.opw
    dh: FloatArray | None = None
    chain = None
    T_n_flange = spec.flange.matrix()
    if np.array_equal(T_n_flange, np.eye(4)):
        T_n_flange = np.eye(4)
    if spec.opw is not None:
        dh, joint_sign = opw_dh(spec.opw)
    elif spec.dh is not None:
        t = spec.dh
        dof = len(t.a)
        for key in ("alpha_deg", "d", "offset_deg", "joint_sign"):
            _check_length(getattr(t, key), dof, ("dh", key))
        dh = dh_table(t.a, t.alpha_deg, t.d, t.offset_deg)
        joint_sign = np.array(t.joint_sign or [1] * dof, dtype=float)
        opw = opw_of_dh(t)
    else:
        assert spec.urdf is not None and spec.base_link and spec.tip_link
        for key in ("joint_limits_deg", "joint_speeds_deg_s"):
            if getattr(spec, key) is not None:
                raise RobotDefinitionError((key,), "a URDF robot takes them from its file")
        try:
            text = read_urdf_text(spec.urdf) if urdf_text is None else urdf_text
            arm = urdf_arm(text, spec.base_link, spec.tip_link, spec.urdf)
        except UrdfError as exc:
            raise RobotDefinitionError((exc.field,), str(exc)) from None
        except InputError as exc:
            raise RobotDefinitionError(("urdf",), str(exc)) from None
        chain, joint_sign = arm.chain, np.ones(arm.chain.dof)
    dof = len(joint_sign)
    if chain is None:
        for key, what in (
            ("joint_limits_deg", "the joint limits, [lower, upper] per joint (degrees)"),
            ("joint_speeds_deg_s", "the joint speeds (deg/s)"),
        ):
            if getattr(spec, key) is None:
                raise RobotDefinitionError((key,), f"required field is missing: {what}")
            _check_length(getattr(spec, key), dof, (key,))
        lim_deg = np.array(spec.joint_limits_deg, dtype=float)
        bad = np.flatnonzero(
            (lim_deg[:, 0] >= lim_deg[:, 1]) | (np.abs(lim_deg).max(axis=1) > MAX_LIMIT_DEG)
        )
        if bad.size:
            raise RobotDefinitionError(
                ("joint_limits_deg", int(bad[0])),
                f"[lower, upper] with lower < upper, within +-{MAX_LIMIT_DEG:g} deg (two turns)",
            )
        joint_limits = lim_deg * _DEG
        velocity_limits = np.array(spec.joint_speeds_deg_s, dtype=float) * _DEG
    else:
        joint_limits, velocity_limits = arm.joint_limits, arm.velocity_limits
    _check_length(spec.home_deg, dof, ("home_deg",))
    _check_length(spec.nominal_deg, dof, ("nominal_deg",))
    robot = RobotModel(
        name=name,
        dh=dh,
        joint_sign=joint_sign,
        joint_limits=joint_limits,
        velocity_limits=velocity_limits,
        T_n_flange=T_n_flange,
        reach=1.0,
        description=spec.description or f"{spec.name}: a robot defined in a project file",
        motion_groups=(tuple(range(dof)),),
        payload=spec.payload,
        chain=chain,
        capsules=_capsules(spec, dof),
    )
    q_home = robot.from_deg(spec.home_deg)
    q_nominal = q_home if spec.nominal_deg is None else robot.from_deg(spec.nominal_deg)
    for key, q in (("home_deg", q_home), ("nominal_deg", q_nominal)):
        if not robot.within_limits(q):
            raise RobotDefinitionError((key,), "outside the joint limits")
    p = None if opw is None else opw_parameters(opw)
    if p is not None and spec.dh is not None and not _opw_holds(robot, p):
        p = None
    analytic = None
    if p is not None:
        if np.array_equal(T_n_flange, np.eye(4)):
            analytic = partial(opw_ik, p)
        else:
            analytic = partial(_opw_ik_with_flange, p, np.linalg.inv(T_n_flange))
    return replace(
        robot,
        analytic_ik=analytic,
        opw=p,
        q_home=q_home,
        q_nominal=q_nominal,
        reach=spec.reach if spec.reach is not None else _reach(robot, p),
    )


def custom_robot_name(spec: CustomRobot, urdf_text: str | None) -> str:
    """``custom:NAME@HASH``: the hash is over the definition and the URDF text, not the path."""
    h = hashlib.sha256(spec.model_dump_json(exclude={"urdf"}).encode())
    h.update(b"\0" + (urdf_text or "").encode())
    return f"{CUSTOM_PREFIX}{spec.name}@{h.hexdigest()[:10]}"


def register_custom_robot(spec: CustomRobot) -> str:
    """Build and register the robot of a definition in this process; its name.

    Idempotent and cheap once done. The URDF text read the first time is kept
    with the definition (and pickled with it), so a process without the file
    rebuilds the same robot under the same name.

    Raises
    ------
    RobotDefinitionError
        As :func:`custom_robot_model`.
    """
    if spec._key is not None and is_registered(spec._key):
        return spec._key
    text = spec._urdf_text
    if spec.urdf is not None and text is None:
        try:
            text = read_urdf_text(spec.urdf)
        except InputError as exc:
            raise RobotDefinitionError(("urdf",), str(exc)) from None
    name = custom_robot_name(spec, text)
    if not is_registered(name):
        register_robot(custom_robot_model(spec, name, text), spec.vendor)
    spec._urdf_text, spec._key = text, name
    return name


def robot_section_problem(
    model: str, custom: CustomRobot | None
) -> tuple[tuple[str | int, ...], str] | None:
    """Why a project's ``robot.model`` and ``robot.custom`` do not name one robot.

    Registers the defined robot (:func:`register_custom_robot`) when they do.

    Returns
    -------
    tuple or None
        (field path under ``robot``, message), or ``None`` when all is well.
    """
    if model == CUSTOM_MODEL and custom is None:
        return ("model",), "model: custom needs a 'custom' robot definition"
    if custom is not None and model != CUSTOM_MODEL:
        return ("custom",), f"a robot definition needs model: custom, not {model}"
    if custom is not None:
        try:
            register_custom_robot(custom)
        except RobotDefinitionError as exc:
            return ("custom", *exc.field), exc.message
    return None


def custom_formats(robot: object) -> tuple[str, ...] | None:
    """The program formats of the robot a raw ``robot`` section defines (its vendor's,
    :func:`~fabflow.robots.catalog.vendor_formats`); ``None`` if it defines none."""
    custom = robot.get("custom") if isinstance(robot, dict) else None
    if not isinstance(robot, dict) or robot.get("model") != CUSTOM_MODEL:
        return None
    vendor = custom.get("vendor") if isinstance(custom, dict) else None
    return vendor_formats(vendor) if vendor in VENDORS else None
