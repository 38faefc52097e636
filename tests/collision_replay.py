"""An independent collision replay of JSON command streams (issue 18, "Done when").

Nothing here comes from fabflow's planner or collision check: the forward
kinematics is the OPW form (Brandstoetter et al. 2014) written out from the
manufacturers' lengths, the links are capsules given by their end points in
that kinematics and sampled as spheres a fifth of their radius apart (the
spheres' union falls short of the capsule by at most 0.5 % of the radius), a held
block is its surface sampled every 2 cm, the structure as built is the design's boxes (a printed
layer one box per extruding segment), and the distance of a point from a box is
computed here with numpy. PTP moves are interpolated in joint space every
1 deg of the largest joint change; linear moves are replayed at their
setpoints (one controller step apart).

Rules, as in docs/robots.md: the tool may touch the element its motion belongs
to (for a piece of a split print layer, any piece of that layer: they meet at
the seams, where the nozzle joins new bead to old); a held block may touch (not
penetrate by more than 1 mm) on the linear move out of the magazine and on the
linear moves before its release that end at the height of its place (into its
place, and for a block slid in, down onto its bed beside it); an element counts
as built from its release (a block) or from the first setpoint of another
element (a print path, a task point); an element the robot does not build
stands once every element it rests on stands, coming (by hand) when the tool
has left, at the next element's first setpoint (``built_before`` lists the
robot-built elements of earlier programs).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

OPW = {
    "kuka_kr60_3": {
        "a1": 0.35, "a2": -0.145, "c1": 0.815, "c2": 0.85, "c3": 0.82, "c4": 0.17,
        "offset": [0, np.pi / 2, 0, 0, 0, 0], "sign": [-1, 1, 1, -1, 1, -1],
        "radii": [0.30, 0.25, 0.20, 0.15, 0.15, 0.12, 0.09],
    },
    "abb_irb4600_60_205": {
        "a1": 0.175, "a2": -0.175, "c1": 0.495, "c2": 0.9, "c3": 0.96, "c4": 0.135,
        "offset": [0, 0, np.pi / 2, 0, 0, 0], "sign": [1, 1, 1, 1, 1, 1],
        "radii": [0.28, 0.22, 0.18, 0.13, 0.13, 0.10, 0.08],
    },
}  # fmt: skip
"""OPW parameters, joint offsets and signs to the controllers' axes, capsule radii
(base, carousel, axis-2 housing, upper arm, elbow, forearm, wrist)."""
TOOL_RADIUS = 0.05
PTP_STEP = np.radians(1.0)
SEAT_TOLERANCE = 0.001
SEAT_HEIGHT = 0.001


def _rz(t: np.ndarray) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    R = np.zeros((*t.shape, 3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1
    return R


def _ry(t: np.ndarray) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    R = np.zeros((*t.shape, 3, 3))
    R[..., 0, 0], R[..., 0, 2], R[..., 2, 0], R[..., 2, 2], R[..., 1, 1] = c, s, -s, c, 1
    return R


def opw_fk(robot: str, q: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Key points (N, 3) of the arm and the flange pose (N, 4, 4), base frame."""
    p = OPW[robot]
    th = np.atleast_2d(q) * p["sign"] + p["offset"]
    R1 = _rz(th[:, 0])
    Rc = R1 @ _ry(th[:, 1] + th[:, 2])
    Re = Rc @ _rz(th[:, 3]) @ _ry(th[:, 4]) @ _rz(th[:, 5])
    a2 = R1 @ np.array([p["a1"], 0.0, p["c1"]])
    a3 = a2 + (R1 @ _ry(th[:, 1])) @ np.array([0.0, 0.0, p["c2"]])
    elbow = a3 + Rc @ np.array([p["a2"], 0.0, 0.0])
    wrist = a3 + Rc @ np.array([p["a2"], 0.0, p["c3"]])
    T = np.repeat(np.eye(4)[None], len(th), axis=0)
    T[:, :3, :3] = Re
    T[:, :3, 3] = wrist + p["c4"] * Re[:, :, 2]
    axis2 = R1[:, :, 1]
    points = {"a2": a2, "a3": a3, "elbow": elbow, "wrist": wrist, "axis2": axis2}
    return points, T


def capsules(
    robot: str, q: np.ndarray, T_flange_tool: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Link segments (N, L, 2, 3), radii (L,), flange poses and link names."""
    pts, T = opw_fk(robot, q)
    n = len(T)
    r = OPW[robot]["radii"]
    z = np.zeros((n, 3))

    def up(h: float) -> np.ndarray:
        return z + np.array([0.0, 0.0, h])

    tcp = T[:, :3, :3] @ T_flange_tool[:3, 3] + T[:, :3, 3]
    axis = (tcp - T[:, :3, 3]) / np.linalg.norm(T_flange_tool[:3, 3])
    segs = [
        (up(r[0]), up(0.25)),
        (up(0.45), pts["a2"]),
        (pts["a2"] - 0.12 * pts["axis2"], pts["a2"] + 0.12 * pts["axis2"]),
        (pts["a2"], pts["a3"]),
        (pts["a3"], pts["elbow"]),
        (pts["elbow"], pts["wrist"]),
        (pts["wrist"], T[:, :3, 3]),
        (T[:, :3, 3], tcp - TOOL_RADIUS * axis),
    ]
    names = ["base", "carousel", "A2 housing", "upper arm", "elbow", "forearm", "wrist", "tool"]
    seg = np.stack([np.stack(s, axis=1) for s in segs], axis=1)
    return seg, np.array([*r, TOOL_RADIUS]), T, names


@dataclass
class Boxes:
    """World boxes: centre frames, full extents, owning element ids."""

    T: np.ndarray
    extents: np.ndarray
    owner: np.ndarray


def structure_boxes(elements: Iterable) -> Boxes:
    """Design boxes of blocks and one box per extruding segment of a print path."""
    T, ext, owner = [], [], []
    for e in elements:
        if e.extents is not None:
            T.append(np.asarray(e.T_world_element, float)[None])
            ext.append(np.asarray(e.extents, float)[None])
            owner.append(e.id)
        elif e.polyline is not None and len(e.polyline) > 1:
            p = np.asarray(e.polyline, float)
            on = np.asarray(e.attributes.get("extrude", np.ones(len(p) - 1)), bool)
            a, b = p[:-1][on], p[1:][on]
            d = b - a
            length = np.linalg.norm(d[:, :2], axis=1)
            u = d[:, :2] / np.maximum(length, 1e-12)[:, None]
            h = float(e.attributes.get("layer_height", 0.02))
            w = float(e.attributes.get("bead_width", 0.02))
            Tl = np.repeat(np.eye(4)[None], len(a), axis=0)
            Tl[:, :2, 0], Tl[:, :2, 1] = u, np.c_[-u[:, 1], u[:, 0]]
            Tl[:, :3, 3] = 0.5 * (a + b) - [0.0, 0.0, 0.5 * h]
            T.append(np.asarray(e.T_world_element, float) @ Tl)
            ext.append(np.c_[length, np.full(len(a), w), np.full(len(a), h)])
            owner += [e.id] * len(a)
    if not T:
        return Boxes(np.zeros((0, 4, 4)), np.zeros((0, 3)), np.zeros(0, dtype=object))
    return Boxes(np.concatenate(T), np.concatenate(ext), np.array(owner, dtype=object))


def point_box_distance(p: np.ndarray, T: np.ndarray, extents: np.ndarray) -> np.ndarray:
    """Signed distance of points p (n, 3) from boxes (n) paired with them."""
    local = np.einsum("nji,nj->ni", T[:, :3, :3], p - T[:, :3, 3])
    q = np.abs(local) - 0.5 * extents
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    return outside + np.minimum(q.max(axis=1), 0.0)


def _held_surface(extents: np.ndarray, step: float = 0.02) -> np.ndarray:
    """Points on the surface of a box centred at the origin, at most ``step`` apart."""
    axes = [np.linspace(-0.5, 0.5, max(2, int(np.ceil(x / step)) + 1)) * x for x in extents]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    on = np.isclose(np.abs(pts), 0.5 * extents).any(axis=1)
    return pts[on]


def replay(
    stream: str,
    elements: Sequence,
    built_before: Sequence[str],
    clearance: float = 0.01,
    first_only: bool = False,
) -> list[tuple[str, str, str, str, float]]:
    """Contacts of one JSON command stream: (element, label, body, obstacle, distance).

    One entry per setpoint interval, body and obstacle (the smallest distance).
    """
    doc = json.loads(stream)
    robot = doc["robot"]
    T_world_base = np.linalg.inv(np.array(doc["T_base_world"]))
    T_flange_tool = np.array(doc["T_flange_tool"])
    by_id = {e.id: e for e in elements}
    # setpoints: (q, kind, element, label, gripper on)
    rows: list[tuple[np.ndarray, str, str, str, bool]] = []
    gripping = False
    done: list[tuple[int, str]] = []  # (setpoint index from which it stands, element id)
    # hand-built elements (robot_built False) stand once everything under them does
    hand = [e for e in elements if not e.robot_built and e.id not in built_before]
    up = set(built_before)

    pending: list[str] = []  # hand-built, coming once the tool has left

    def finish(k: int, element: str | None) -> None:
        if element is not None:
            done.append((k, element))
            up.add(element)
        grown = True
        while grown:
            new = [e for e in hand if e.id not in up and set(e.supports) <= up]
            grown = bool(new)
            for e in new:
                (pending if element is not None else done_now).append(e.id)
                up.add(e.id)

    done_now: list[str] = []
    finish(0, None)  # those standing from the start
    done += [(0, e) for e in done_now]
    for c in doc["commands"]:
        if c["type"] == "io" and c["name"] == "gripper":
            gripping = bool(c["value"])
            if not gripping and rows:
                finish(len(rows), rows[-1][2])
        elif c["type"] == "setpoint":
            previous = rows[-1][2] if rows else None
            if (
                previous is not None
                and c["element"] != previous
                and by_id[previous].type != "block"
            ):
                finish(len(rows), rows[-1][2])
            if c["element"] != previous:  # the next element's first setpoint
                done += [(len(rows), e) for e in pending]
                pending.clear()
            rows.append((np.array(c["q"], float), c["kind"], c["element"], c["label"], gripping))
    # runs of setpoints of one move label
    starts = [0] + [i for i in range(1, len(rows)) if rows[i][1:4] != rows[i - 1][1:4]]
    ends = [*starts[1:], len(rows)]
    all_boxes = structure_boxes([by_id[e] for e in {*built_before, *(d[1] for d in done)}])
    contacts: dict[tuple[str, str, str, str], float] = {}
    surfaces: dict[str, np.ndarray] = {}
    # the tool's height at the end of every run, and the runs down onto the bed:
    # the linear runs right before a release that end at the place's height
    last_q = np.array([rows[b - 1][0] for b in ends]).reshape(len(ends), -1)
    end_p = (T_world_base @ opw_fk(robot, last_q)[1] @ T_flange_tool)[:, :3, 3]
    end_z = end_p[:, 2]
    # a joint run straight down from the run before (a descent through the wrist
    # singularity) is a way onto the bed too
    drop = np.diff(end_p, axis=0)
    down = np.r_[False, (np.hypot(drop[:, 0], drop[:, 1]) <= SEAT_HEIGHT) & (drop[:, 2] < 0)]
    on_bed = np.zeros(len(starts), dtype=bool)
    for r, b in enumerate(ends):
        if rows[b - 1][4] and (b == len(rows) or not rows[b][4]):  # released after run r
            k = r
            while k >= 0 and rows[starts[k]][4]:
                joint = rows[starts[k]][1] != "lin"
                if (joint and not down[k]) or abs(end_z[k] - end_z[r]) > SEAT_HEIGHT:
                    break
                on_bed[k] = True
                if joint:  # the way down ends the way onto the bed
                    break
                k -= 1
    for r, (a, b) in enumerate(zip(starts, ends, strict=True)):
        _, kind, element, label, grip = rows[a]
        samples = []
        for i in range(max(a, 1), b):
            q = rows[i][0]
            if kind == "ptp":
                q0 = rows[i - 1][0]
                n = max(1, int(np.ceil(np.abs(q - q0).max() / PTP_STEP)))
                samples.append(q0 + (np.arange(1, n + 1) / n)[:, None] * (q - q0))
            else:
                samples.append(q[None])
        if not samples:
            continue
        held = element if grip else None
        seat = held is not None and kind == "lin" and (r == 0 or not rows[starts[r - 1]][4])
        seat = seat or bool(on_bed[r])
        standing = set(built_before) | {e for k, e in done if k <= a}
        keep = np.array([o in standing for o in all_boxes.owner], dtype=bool)
        boxes = Boxes(all_boxes.T[keep], all_boxes.extents[keep], all_boxes.owner[keep])
        found = _contacts(robot, np.vstack(samples), T_world_base, T_flange_tool, boxes, element,
                          held, seat, surfaces, by_id, clearance)  # fmt: skip
        for (body, obstacle), d in found.items():
            key = (element, label, body, obstacle)
            contacts[key] = min(d, contacts.get(key, np.inf))
        if first_only and contacts:
            break
    return [(*k, d) for k, d in contacts.items()]


def _contacts(robot, qs, T_world_base, T_flange_tool, boxes, element, held, seat, surfaces,
              by_id, clearance) -> dict[tuple[str, str], float]:  # fmt: skip
    if not len(boxes.T):
        return {}
    seg, radii, T_flange, names = capsules(robot, qs, T_flange_tool)
    L = seg.shape[1]
    # spheres a fifth of the radius apart along every capsule, in the world
    length = np.linalg.norm(seg[0, :, 1] - seg[0, :, 0], axis=1)
    k = np.maximum(2, np.ceil(length / (0.2 * radii)) + 1).astype(int)
    pts, body = [], []
    for j in range(L):
        t = np.linspace(0.0, 1.0, k[j])[None, :, None]
        p = seg[:, j, :1] + t * (seg[:, j, 1:] - seg[:, j, :1])
        pts.append(p.reshape(-1, 3))
        body.append(np.full(p.shape[0] * p.shape[1], j))
    limit = [clearance] * L
    radius = list(radii)
    if held is not None:
        e = by_id[held]
        if held not in surfaces:
            surfaces[held] = _held_surface(np.asarray(e.extents, float))
        # the grip: the block's pose in the tool frame at its place target
        T_place_tool = _place_tool(e)
        T_tool_block = np.linalg.inv(T_place_tool) @ np.asarray(e.T_world_element, float)
        T_block = T_flange @ T_flange_tool @ T_tool_block
        s = surfaces[held]
        p = np.einsum("nij,kj->nki", T_block[:, :3, :3], s) + T_block[:, None, :3, 3]
        pts.append(p.reshape(-1, 3))
        body.append(np.full(p.shape[0] * p.shape[1], L))
        limit.append(-SEAT_TOLERANCE if seat else clearance)
        radius.append(0.0)
    P = np.concatenate(pts) @ T_world_base[:3, :3].T + T_world_base[:3, 3]
    B = np.concatenate(body)
    R = np.asarray(radius)[B]
    half = 0.5 * np.linalg.norm(boxes.extents, axis=1).max()
    box_tree = cKDTree(boxes.T[:, :3, 3])
    i_all, j_all = [], []
    for b in np.unique(B):  # one query radius per body
        rows = np.flatnonzero(B == b)
        pairs = cKDTree(P[rows]).sparse_distance_matrix(
            box_tree, half + radius[b] + clearance, output_type="ndarray"
        )
        i_all.append(rows[pairs["i"]])
        j_all.append(pairs["j"])
    i, j = np.concatenate(i_all), np.concatenate(j_all)
    if not len(i):
        return {}
    d = point_box_distance(P[i], boxes.T[j], boxes.extents[j]) - R[i]

    def layer(e: str) -> str:
        return str(by_id[e].attributes.get("parent", e)) if e in by_id else e

    owner_layer = np.array([layer(o) for o in boxes.owner], dtype=object)
    own = (B[i] == names.index("tool")) & (owner_layer[j] == layer(element))
    hit = (d < np.asarray(limit)[B[i]]) & ~own
    out: dict[tuple[str, str], float] = {}
    for b, o, dist in zip(B[i][hit], boxes.owner[j][hit], d[hit], strict=True):
        key = ("held" if b == L else names[b], str(o))
        out[key] = min(float(dist), out.get(key, np.inf))
    return out


def _place_tool(e) -> np.ndarray:
    """The tool pose placing a block: the centre of its top face, tool z down, x along it."""
    T = np.asarray(e.T_world_element, float).copy()
    h = float(np.asarray(e.extents)[2])
    T[:3, 3] = T[:3, 3] + T[:3, 2] * 0.5 * h
    T[:3, :3] = T[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    return T
