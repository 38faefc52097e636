"""Readers that parse the written programs back: KRL, RAPID and URScript.

Independent of the writers: each reader turns the vendor's text (millimetres
and degrees, quaternions, rotation vectors) back into 4x4 poses in metres, so
the tests can re-project every target through the program's base frame. The
KRL and RAPID readers are strict: every line must be a statement they know
(an unknown line fails the test), and sub-programs are expanded where they are
called, so a test sees the motions in the order the controller runs them.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fabflow.transforms.so3 import exp_so3, matrix_from_abc, matrix_from_quat


@dataclass
class Motion:
    """One motion statement read back.

    ``T`` is the Cartesian target in the base frame / work object (metres), or
    ``None`` for a joint target, whose axes are in ``axes_deg``; ``status_turn``
    holds KRL's (S, T) or RAPID's confdata; ``external`` the external axis values
    (mm) by name (``E1``); ``exact`` whether the motion stops at its point.
    ``module`` names the module it was read from, ``first`` whether it is the
    module's first motion; ``wrist`` marks a linear move with the wrist axes
    interpolated (KRL ``$ORI_TYPE = #JOINT``, RAPID ``SingArea \\Wrist``), which the
    reader requires to be switched back right after it.
    """

    kind: str
    T: np.ndarray | None
    axes_deg: np.ndarray | None
    status_turn: tuple
    external: dict[str, float]
    exact: bool
    comment: str
    module: str
    first: bool = False
    last: bool = False
    wrist: bool = False


@dataclass
class ReadProgram:
    """A program read back: frames, load, operator stops and the motions in order."""

    base: np.ndarray
    tool: np.ndarray
    load_mass: float
    load_cog: np.ndarray
    motions: list[Motion] = field(default_factory=list)
    operator_steps: list[tuple[int, str]] = field(default_factory=list)
    """(number of motions before the stop, the message the operator reads)."""
    modules: dict[str, int] = field(default_factory=dict)
    """Motions per module."""
    load_changes: list[tuple[int, float, np.ndarray]] = field(default_factory=list)
    """(number of motions before, mass, centre of gravity) of every later load
    statement: KRL ``$LOAD`` (flange frame), RAPID ``GripLoad`` (tool frame)."""

    @property
    def moves(self) -> list[tuple[str, np.ndarray | None, tuple, str]]:
        """(kind, T, status/turn, comment) per motion (the older reader's tuples)."""
        return [(m.kind, m.T, m.status_turn, m.comment) for m in self.motions]


def program_files(folder: Path, name: str) -> dict[str, str]:
    """The files of the program ``name`` in ``folder``: its main module and sub-modules."""
    return {
        p.name: p.read_text()
        for p in folder.iterdir()
        if p.stem == name or re.fullmatch(rf"{re.escape(name)}_[PM]\d\d", p.stem)
    }


# --------------------------------------------------------------------------- KRL

NUM = r"(-?\d+(?:\.\d+)?)"


def kuka_pose(values: list[float]) -> np.ndarray:
    x, y, z, a, b, c = values
    T = np.eye(4)
    T[:3, :3] = matrix_from_abc(*np.radians([a, b, c]))
    T[:3, 3] = np.array([x, y, z]) / 1000.0
    return T


def _aggregate(text: str) -> dict[str, float]:
    """``X 1.0,Y 2.0,S 2`` -> {"X": 1.0, ...}."""
    out = {}
    for part in text.split(","):
        key, value = part.strip().split(" ")
        out[key] = float(value)
    return out


FRAME_KEYS = ("X", "Y", "Z", "A", "B", "C")


def _read_krl_dat(dat: str) -> tuple[dict[str, np.ndarray], dict[str, dict[str, float]]]:
    frames: dict[str, np.ndarray] = {}
    points: dict[str, dict[str, float]] = {}
    for line in dat.splitlines():
        if line.startswith(("&", "DEFDAT ", ";")) or line == "ENDDAT":
            continue
        m = re.fullmatch(r"DECL (FRAME|E6POS|E6AXIS) (\w+)=\{([^{}]*)\}", line)
        assert m, f"unknown .dat line: {line!r}"
        values = _aggregate(m.group(3))
        if m.group(1) == "FRAME":
            frames[m.group(2)] = kuka_pose([values[k] for k in FRAME_KEYS])
        else:
            assert m.group(2) not in points, f"{m.group(2)} declared twice"
            points[m.group(2)] = {"type": m.group(1), **values}  # type: ignore[dict-item]
    return frames, points


def _krl_motion(kind: str, point: dict, exact: bool, comment: str, module: str) -> Motion:
    external = {k: v for k, v in point.items() if re.fullmatch(r"E\d", k)}
    if point["type"] == "E6AXIS":
        axes = np.array([point[f"A{i}"] for i in range(1, 7)])
        return Motion(kind, None, axes, (), external, exact, comment, module)
    st = (int(point["S"]), int(point["T"])) if "S" in point else ()
    T = kuka_pose([point[k] for k in FRAME_KEYS])
    return Motion(kind, T, None, st, external, exact, comment, module)


KRL_STATEMENTS = (
    r"BAS \(#INITMOV,0\)",
    r"\$BASE = BASE_WORLD",
    r"\$TOOL = TOOL_TCP",
    rf"\$VEL_AXIS\[[1-6]\] = {NUM}",
    rf"\$VEL\.CP = {NUM}",
    rf"\$APO\.CDIS = {NUM}",
    rf"\$APO\.CPTP = {NUM}",
    r"\$OUT\[\d+\] = (TRUE|FALSE)",
    rf"WAIT SEC {NUM}",
)


def read_krl(files: dict[str, str]) -> ReadProgram:
    """A KRL program: the main module and its sub-programs (``{file name: text}``).

    Raises ``AssertionError`` on any line the reader does not know.
    """
    modules = {}
    for name, src in files.items():
        if name.endswith(".src"):
            modules[name[:-4]] = (src, _read_krl_dat(files[name[:-4] + ".dat"]))
    called: set[str] = set()
    for src, _ in modules.values():
        called |= set(re.findall(r"^(\w+)\( \)$", src, flags=re.M))
    (root,) = [m for m in modules if m not in called]
    frames, _ = modules[root][1]
    program = ReadProgram(frames["BASE_WORLD"], frames["TOOL_TCP"], float("nan"), np.zeros(3))

    def run(module: str) -> None:
        src, (_, points) = modules[module]
        count = 0
        pending_message = ""
        start = len(program.motions)
        wrist = restore = False
        for line in src.splitlines():
            if line.startswith(("&", "DEF ")) or line == "END":
                continue
            assert not restore or line == "$ORI_TYPE = #VAR", f"{module}: #JOINT left on"
            if line == "$ORI_TYPE = #VAR":
                assert restore, f"{module}: a stray $ORI_TYPE = #VAR"
                restore = False
                continue
            if re.fullmatch(r"\$ORI_TYPE = #JOINT(?: ; .*)?", line):
                wrist = True
                continue
            if line.startswith(";"):
                pending_message = line[1:].strip()
                continue
            if line == "HALT":
                program.operator_steps.append((len(program.motions), pending_message))
                continue
            load = re.fullmatch(
                rf"\$LOAD = \{{M {NUM},CM \{{X {NUM},Y {NUM},Z {NUM},A 0\.0,B 0\.0,C 0\.0\}},"
                r"J \{X 0\.0,Y 0\.0,Z 0\.0\}\}",
                line,
            )
            if load:
                mass = float(load.group(1))
                cog = np.array([float(g) for g in load.groups()[1:]]) / 1000.0
                if np.isnan(program.load_mass):
                    program.load_mass, program.load_cog = mass, cog
                else:
                    program.load_changes.append((len(program.motions), mass, cog))
                continue
            call = re.fullmatch(r"(\w+)\( \)", line)
            if call:
                assert call.group(1) in modules, f"call of an unknown module {line!r}"
                run(call.group(1))
                continue
            motion = re.fullmatch(r"(PTP|LIN) (\w+)( C_PTP| C_DIS)?(?: ; (.*))?", line)
            if motion:
                kind, point, approx, comment = motion.groups()
                assert point in points, f"{module}: {point} is not declared"
                read = _krl_motion(kind.lower(), points[point], not approx, comment or "", module)
                assert not wrist or kind == "LIN", f"{module}: #JOINT before a PTP"
                read.wrist, restore, wrist = wrist, wrist, False
                program.motions.append(read)
                count += 1
                continue
            assert any(re.fullmatch(p, line) for p in KRL_STATEMENTS), f"unknown line {line!r}"
        own = [m for m in program.motions[start:] if m.module == module]
        if own:
            own[0].first = own[-1].last = True
        program.modules[module] = count

    run(root)
    return program


# -------------------------------------------------------------------------- RAPID


def abb_pose(p: list[float], q: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(np.array(q))
    T[:3, 3] = np.array(p) / 1000.0
    return T


def _numbers(text: str) -> list[float]:
    return [float(v) for v in re.findall(r"-?\d+(?:\.\d+)?(?:E\d+)?", text)]


def _extax(values: list[float]) -> dict[str, float]:
    return {f"E{i + 1}": v for i, v in enumerate(values) if v < 9e8}


RAPID_STATEMENTS = (
    r"ConfJ \\On;",
    r"ConfL \\On;",
    r"SetDO do_\w+, [01];",
    rf"WaitTime {NUM};",
    r"VAR num answer;",
)


DECLARATION = r"(?:CONST|PERS) (robtarget|jointtarget|tooldata|wobjdata|loaddata) (\w+) := (.*);"
CONFIRM = r'TPReadFK answer, "[^"]*", "OK", stEmpty, stEmpty, stEmpty, stEmpty;'
MOVE = (
    r"(MoveJ|MoveL|MoveAbsJ) (\w+)(?:\\NoEOffs)?, v\d+, (fine|z\d+), \w+\\WObj:=wobj_world;"
    r"(?: ! (.*))?"
)


def read_rapid(files: dict[str, str] | str) -> ReadProgram:
    """A RAPID program: the main module and its sub-modules (``{file name: text}``).

    Raises ``AssertionError`` on any line the reader does not know.
    """
    if isinstance(files, str):
        files = {"main.mod": files}
    procs: dict[str, tuple[str, list[str]]] = {}
    targets: dict[str, tuple[str, list[float]]] = {}
    data: dict[str, str] = {}
    loads: dict[str, list[float]] = {"load0": [0.0, 0.0, 0.0, 0.0]}
    for text in files.values():
        lines = text.splitlines()
        module = re.fullmatch(r"MODULE (\w+)", lines[0]).group(1)
        assert lines[-1] == "ENDMODULE"
        proc = None
        for line in lines[1:-1]:
            s = line.strip()
            if s.startswith("!"):
                if proc is not None:
                    procs[proc][1].append(s)
                continue
            m = re.fullmatch(r"PROC (\w+)\(\)", s)
            if m:
                proc = m.group(1)
                procs[proc] = (module, [])
                continue
            if s == "ENDPROC":
                proc = None
                continue
            if proc is not None:
                procs[proc][1].append(s)
                continue
            m = re.fullmatch(DECLARATION, s)
            assert m, f"unknown declaration {s!r}"
            assert m.group(2) not in targets and m.group(2) not in data, f"{m.group(2)} twice"
            if m.group(1) in ("robtarget", "jointtarget"):
                targets[m.group(2)] = (m.group(1), _numbers(m.group(3)))
            elif m.group(1) == "loaddata":
                loads[m.group(2)] = _numbers(m.group(3))
            else:
                data[m.group(1)] = m.group(3)
    tool = _numbers(data["tooldata"].replace("TRUE", ""))
    wobj = _numbers(data["wobjdata"].replace('FALSE,TRUE,"",', ""))
    program = ReadProgram(
        abb_pose(wobj[:3], wobj[3:7]),
        abb_pose(tool[:3], tool[3:7]),
        tool[7],
        np.array(tool[8:11]) / 1000.0,
    )

    def run(proc: str) -> None:
        module, statements = procs[proc]
        start = len(program.motions)
        count = 0
        message = ""
        wrist = restore = False
        for s in statements:
            if s.startswith("!"):
                continue
            assert not restore or s == "SingArea \\Off;", f"{module}: SingArea \\Wrist left on"
            if s == "SingArea \\Off;":
                assert restore, f"{module}: a stray SingArea \\Off"
                restore = False
                continue
            if re.fullmatch(r"SingArea \\Wrist;(?: ! .*)?", s):
                wrist = True
                continue
            m = re.fullmatch(r'TPWrite "(.*)";', s)
            if m:
                message = m.group(1)
                continue
            if re.fullmatch(CONFIRM, s):
                program.operator_steps.append((len(program.motions), message))
                continue
            m = re.fullmatch(r"GripLoad (\w+);", s)
            if m:
                mass, *cog = loads[m.group(1)][:4]
                program.load_changes.append((len(program.motions), mass, np.array(cog) / 1000.0))
                continue
            m = re.fullmatch(r"(\w+);", s)
            if m and m.group(1) in procs:
                run(m.group(1))
                continue
            m = re.fullmatch(MOVE, s)
            if m:
                instr, name, zone, comment = m.groups()
                kind, values = targets[name]
                if instr == "MoveAbsJ":
                    assert kind == "jointtarget"
                    motion = Motion(
                        "ptp",
                        None,
                        np.array(values[:6]),
                        (),
                        _extax(values[6:]),
                        zone == "fine",
                        comment or "",
                        module,
                    )
                else:
                    assert kind == "robtarget"
                    motion = Motion(
                        "ptp" if instr == "MoveJ" else "lin",
                        abb_pose(values[:3], values[3:7]),
                        None,
                        tuple(int(v) for v in values[7:11]),
                        _extax(values[11:]),
                        zone == "fine",
                        comment or "",
                        module,
                    )
                assert not wrist or instr == "MoveL", f"{module}: SingArea \\Wrist before {instr}"
                motion.wrist, restore, wrist = wrist, wrist, False
                program.motions.append(motion)
                count += 1
                continue
            assert any(re.fullmatch(p, s) for p in RAPID_STATEMENTS), f"unknown line {s!r}"
        own = [m for m in program.motions[start:] if m.module == module]
        if own:
            own[0].first = own[-1].last = True
        program.modules[module] = count

    run("main")
    return program


# ------------------------------------------------------------------------ URScript


def ur_pose(values: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = exp_so3(np.array(values[3:]))
    T[:3, 3] = values[:3]
    return T


def read_urscript(text: str) -> tuple[np.ndarray, list[tuple[str, np.ndarray]]]:
    """world_in_base and the motions (kind, T world or q) of a URScript program."""
    p = r"p\[([^\]]+)\]"
    base = ur_pose([float(v) for v in re.search(rf"world_in_base = {p}", text).group(1).split(",")])
    moves = []
    for kind, args in re.findall(r"(movej|movel)\((.*?)\)?, a=", text):
        if kind == "movej":
            moves.append(("ptp", np.array([float(v) for v in args.strip("[]").split(",")])))
        else:
            values = re.search(p, args).group(1).split(",")
            moves.append(("lin", ur_pose([float(v) for v in values])))
    return base, moves
