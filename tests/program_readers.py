"""Readers that parse the written programs back: KRL, RAPID and URScript targets.

Independent of the writers: each reader turns the vendor's text (millimetres
and degrees, quaternions, rotation vectors) back into 4x4 poses in metres, so
the tests can re-project every target through the program's base frame.
"""

from __future__ import annotations

import re

import numpy as np

from fabflow.transforms.so3 import exp_so3, matrix_from_abc, matrix_from_quat

# ----------------------------------------------------------------------- readers


def kuka_pose(values: list[float]) -> np.ndarray:
    x, y, z, a, b, c = values
    T = np.eye(4)
    T[:3, :3] = matrix_from_abc(*np.radians([a, b, c]))
    T[:3, 3] = np.array([x, y, z]) / 1000.0
    return T


def read_krl_module(src: str, dat: str) -> tuple[np.ndarray, list[tuple], list[str]]:
    num = r"(-?\d+\.\d+)"
    frame = rf"X {num},Y {num},Z {num},A {num},B {num},C {num}"
    base = re.search(rf"DECL FRAME BASE_WORLD={{{frame}}}", dat)
    points = {}
    for m in re.finditer(rf"DECL E6POS (\w+)={{{frame}(?:,S (\d+),T (\d+))?}}", dat):
        st = (int(m.group(8)), int(m.group(9))) if m.group(8) else ()
        points[m.group(1)] = (kuka_pose([float(g) for g in m.groups()[1:7]]), st)
    moves = [
        (kind.lower(), *points[name], comment.strip())
        for kind, name, comment in re.findall(r"^(PTP|LIN) (\w+)[^;\n]*;?(.*)$", src, flags=re.M)
    ]
    calls = re.findall(r"^(\w+)\( \)$", src, flags=re.M)
    return kuka_pose([float(g) for g in base.groups()]), moves, calls


def read_krl(files: dict[str, str]) -> tuple[np.ndarray, list[tuple[str, np.ndarray, tuple, str]]]:
    """$BASE and the motions (kind, T in $BASE, (S, T) or (), comment) of a KRL program.

    ``files`` holds the main module and its sub-program modules; the motions are
    returned in execution order (sub-programs expanded where they are called).
    """
    modules = {
        name[:-4]: read_krl_module(text, files[name[:-4] + ".dat"])
        for name, text in files.items()
        if name.endswith(".src")
    }
    called = {c for _, _, calls in modules.values() for c in calls}
    (root,) = [m for m in modules if m not in called]

    def expand(name: str) -> list[tuple]:
        _, moves, calls = modules[name]
        return moves + [m for c in calls for m in expand(c)]

    return modules[root][0], expand(root)


def abb_pose(p: list[float], q: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(np.array(q))
    T[:3, 3] = np.array(p) / 1000.0
    return T


def read_rapid(text: str) -> tuple[np.ndarray, list[tuple[str, np.ndarray]]]:
    """Work object frame and the motions (kind, T in the work object) of a RAPID module."""
    vec = r"\[(-?[\d.]+),(-?[\d.]+),(-?[\d.]+)\]"
    quat = r"\[(-?[\d.]+),(-?[\d.]+),(-?[\d.]+),(-?[\d.]+)\]"
    w = re.search(rf"wobjdata wobj_world := \[FALSE,TRUE,\"\",\[{vec},{quat}\]", text)
    wobj = abb_pose([float(g) for g in w.groups()[:3]], [float(g) for g in w.groups()[3:]])
    targets = {
        m.group(1): abb_pose(
            [float(g) for g in m.groups()[1:4]], [float(g) for g in m.groups()[4:]]
        )
        for m in re.finditer(rf"CONST robtarget (\w+) := \[{vec},{quat}", text)
    }
    moves = [
        ("ptp" if kind == "MoveJ" else "lin", targets[name])
        for kind, name in re.findall(r"(MoveJ|MoveL) (\w+),", text)
    ]
    return wobj, moves


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
