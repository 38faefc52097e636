"""The parametric log cabin: timber blocks laid in layers, crossing at the corners.

Cabin frame (see :class:`fabflow.design.specs.CabinSpec`): origin at the outer corner
of the front and right walls, x along the left and right walls (``length``), y
along the front and rear walls (``width``), z up. Layer ``k`` occupies
``k * h <= z <= (k + 1) * h`` with ``h`` the block height.

Construction rules
------------------
- Corners cross like a log cabin: in even layers the left and right walls run
  through the corners (0 <= x <= length) and the front and rear walls fit between
  them; in odd layers it is the other way round.
- Joints are staggered: every wall row is cut on a grid of block lengths measured
  from the wall's start corner, shifted by half a block in odd layers. A cut
  piece shorter than ``min_piece`` at the end of a row is merged with its
  neighbour and the merged length, when longer than a block, split in two equal
  pieces, so every piece is between ``min_piece`` and one block long.
- Openings leave gaps in every layer they overlap; the first layer above an
  opening carries a lintel reaching ``lintel_bearing`` past each side.
- Above ``eave_height`` the front and rear walls continue as stepped gables whose
  row length follows the roof line at the middle of each layer.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from fabflow.design.elements import Element
from fabflow.design.specs import CabinSpec
from fabflow.transforms.se3 import make_T
from fabflow.transforms.so3 import matrix_from_abc

_X_WALLS = ("right", "left")
_Y_WALLS = ("front", "rear")
_EPS = 1e-9


@dataclass(frozen=True)
class CabinBlocks:
    """The blocks of one cabin as parallel arrays (world frame, metres).

    Attributes
    ----------
    T_world_block
        (N, 4, 4) block poses: centre of the block, x along its length, z up.
    extents
        (N, 3) block sizes (length, width, height).
    layer
        (N,) layer index, 0 at the floor.
    wall
        (N,) ``"front"``, ``"rear"``, ``"left"`` or ``"right"``.
    piece
        (N,) the key of ``CabinSpec.parts`` the block belongs to (a wall or a gable).
    part
        (N,) part name (``"A"``, ``"front"``, ...).
    kind
        (N,) ``"block"`` or ``"lintel"``.
    robot_built
        (N,) whether the block's part is in ``CabinSpec.robot_parts``.
    """

    T_world_block: np.ndarray
    extents: np.ndarray
    layer: np.ndarray
    wall: np.ndarray
    piece: np.ndarray
    part: np.ndarray
    kind: np.ndarray
    robot_built: np.ndarray

    def __len__(self) -> int:
        return len(self.layer)


def _circular(d: float, L: float) -> float:
    """Distance of ``d`` from the nearest multiple of ``L``."""
    d = d % L
    return min(d, L - d)


def _cuts(a: float, b: float, phase: float, L: float, min_piece: float) -> np.ndarray:
    """Cut positions (including both ends) of the row segment ``[a, b]``.

    The fewest pieces (``ceil((b - a) / L)``) are used when their joints can lie
    within ``L / 8`` of the grid ``phase + k * L``; otherwise the joints fall on
    that grid exactly and short end pieces are merged (see the module docstring).
    """
    S = b - a
    if S <= L + _EPS:
        return np.array([a, b])
    n = math.ceil(S / L - _EPS)
    r = S - (n - 1) * L
    lo, hi = max(min_piece, r), min(L, L + r - min_piece)
    if hi >= lo - _EPS:
        m = math.ceil((a + lo - phase) / L - _EPS)
        e1 = phase + m * L - a
        if e1 > hi + _EPS:
            e1 = min((lo, hi), key=lambda e: _circular(a + e - phase, L))
        if _circular(a + e1 - phase, L) <= L / 8 + _EPS:
            return np.concatenate(([a], a + e1 + L * np.arange(n - 1), [b]))
    k0 = math.floor((a - phase) / L) + 1
    k1 = math.ceil((b - phase) / L) - 1
    joints = phase + L * np.arange(k0, k1 + 1)
    joints = joints[(joints > a + _EPS) & (joints < b - _EPS)]
    cuts = np.concatenate(([a], joints, [b]))
    if len(cuts) > 2 and cuts[1] - cuts[0] < min_piece - _EPS:
        cuts = np.delete(cuts, 1)
        if cuts[1] - cuts[0] > L + _EPS:
            cuts = np.insert(cuts, 1, 0.5 * (cuts[0] + cuts[1]))
    if len(cuts) > 2 and cuts[-1] - cuts[-2] < min_piece - _EPS:
        cuts = np.delete(cuts, -2)
        if cuts[-1] - cuts[-2] > L + _EPS:
            cuts = np.insert(cuts, -1, 0.5 * (cuts[-2] + cuts[-1]))
    return cuts


def _layer_range(sill: float, height: float, h: float) -> tuple[int, int]:
    """Layers ``[lo, hi)`` that overlap ``[sill, sill + height]``; ``hi`` holds the lintel."""
    return math.floor(sill / h + 1e-6), math.ceil((sill + height) / h - 1e-6)


def cabin_layer_counts(spec: CabinSpec) -> tuple[int, int]:
    """Number of wall layers (up to the eave) and of all layers (up to the ridge)."""
    h = spec.block.height
    return math.floor(spec.eave_height / h + 1e-6), math.floor(spec.height / h + 1e-6)


def cabin_block_bound(spec: CabinSpec) -> float:
    """An upper bound of the number of blocks of a cabin, without generating them.

    Every row of a wall between two openings is cut into at most
    ``span / block length + 2`` pieces, each opening adds a free interval and a
    lintel; the bound multiplies one layer of all four walls by the number of
    layers up to the ridge. Computed in floating point, so that a block height of a
    nanometre gives a large number quickly instead of a long loop.
    """
    h, L = spec.block.height, spec.block.length
    n_total = math.floor(spec.height / h + 1e-6)
    per_layer = 0.0
    for wall in ("right", "front", "left", "rear"):
        span = spec.length if wall in _X_WALLS else spec.width
        k = sum(o.wall == wall for o in spec.openings)
        per_layer += span / L + 2.0 * (k + 1) + k
    return float(n_total) * per_layer


def _rows(spec: CabinSpec) -> list[tuple[int, str, str, float, float, bool]]:
    """Every piece of every row: (layer, wall, piece key, start, end, is_lintel).

    ``start`` and ``end`` are measured along the wall from its start corner.
    """
    L, t, h = spec.block.length, spec.block.width, spec.block.height
    n_wall, n_total = cabin_layer_counts(spec)
    span = {"front": spec.width, "rear": spec.width, "left": spec.length, "right": spec.length}
    gaps: dict[str, list[tuple[int, int, float, float]]] = {w: [] for w in span}
    for o in spec.openings:
        lo, hi = _layer_range(o.sill, o.height, h)
        gaps[o.wall].append((lo, hi, o.center - o.width / 2, o.center + o.width / 2))

    rows: list[tuple[int, str, str, float, float, bool]] = []
    for k in range(n_total):
        grid0 = 0.5 * L * (k % 2)
        for wall in ("right", "front", "left", "rear"):
            if k < n_wall:
                through = (k % 2 == 0) == (wall in _X_WALLS)
                a, b = (0.0, span[wall]) if through else (t, span[wall] - t)
                piece = wall
            elif wall in _Y_WALLS:
                z_mid = (k + 0.5) * h
                # the roof line runs from the top of the walls to the ridge
                slope = (spec.height - z_mid) / (spec.height - n_wall * h)
                half = 0.5 * spec.width * min(1.0, slope)
                a, b = 0.5 * spec.width - half, 0.5 * spec.width + half
                if b - a < spec.min_piece:
                    continue
                piece = f"{wall}_gable"
            else:
                continue
            # the row as free intervals (between openings) and lintel intervals
            free = [(a, b)]
            lintels = []
            for lo, hi, g0, g1 in gaps[wall]:
                if lo <= k < hi:
                    free = [
                        part
                        for s0, s1 in free
                        for part in ((s0, min(s1, g0)), (max(s0, g1), s1))
                        if part[1] - part[0] > _EPS
                    ]
                elif k == hi:
                    l0, l1 = g0 - spec.lintel_bearing, g1 + spec.lintel_bearing
                    lintels.append((l0, l1))
                    free = [
                        part
                        for s0, s1 in free
                        for part in ((s0, min(s1, l0)), (max(s0, l1), s1))
                        if part[1] - part[0] > _EPS
                    ]
            for s0, s1 in free:
                cuts = _cuts(s0, s1, grid0, L, spec.min_piece)
                rows.extend((k, wall, piece, c0, c1, False) for c0, c1 in itertools.pairwise(cuts))
            rows.extend((k, wall, piece, l0, l1, True) for l0, l1 in lintels)
    return rows


def cabin_blocks(spec: CabinSpec) -> CabinBlocks:
    """Generate the blocks of a cabin.

    Parameters
    ----------
    spec
        The cabin parameters (validated project model).

    Returns
    -------
    CabinBlocks
        Blocks sorted by layer, then wall (right, front, left, rear), then along
        the wall.
    """
    t, h = spec.block.width, spec.block.height
    rows = _rows(spec)
    layer = np.array([r[0] for r in rows], dtype=int)
    wall = np.array([r[1] for r in rows])
    piece = np.array([r[2] for r in rows])
    s0 = np.array([r[3] for r in rows])
    s1 = np.array([r[4] for r in rows])
    lintel = np.array([r[5] for r in rows], dtype=bool)

    s_mid = 0.5 * (s0 + s1)
    offset = {"right": t / 2, "left": spec.width - t / 2, "front": t / 2}
    offset["rear"] = spec.length - t / 2
    across = np.array([offset[w] for w in wall.tolist()], dtype=float)
    along_x = np.isin(wall, _X_WALLS)
    centre = np.stack(
        [np.where(along_x, s_mid, across), np.where(along_x, across, s_mid), (layer + 0.5) * h],
        axis=1,
    )
    yaw = np.where(along_x, 0.0, math.pi / 2)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(rows), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    T_cabin_block = make_T(R, centre)
    T_world_cabin = make_T(matrix_from_abc(math.radians(spec.heading_deg), 0.0, 0.0), spec.origin)
    extents = np.stack([s1 - s0, np.full_like(s0, t), np.full_like(s0, h)], axis=1)
    part = np.array([spec.parts[p] for p in piece]) if len(piece) else piece
    return CabinBlocks(
        T_world_block=T_world_cabin @ T_cabin_block,
        extents=extents,
        layer=layer,
        wall=wall,
        piece=piece,
        part=part,
        kind=np.where(lintel, "lintel", "block"),
        robot_built=np.isin(part, spec.robot_parts),
    )


def cabin_elements(spec: CabinSpec, id_start: int = 0) -> list[Element]:
    """The cabin's blocks as :class:`Element` objects (``supports`` left empty).

    Parameters
    ----------
    spec
        The cabin parameters.
    id_start
        Number of the first block id (``"B0000"`` for 0); ids count up from it.
    """
    blocks = cabin_blocks(spec)
    density = spec.block.density
    mass = None if density is None else np.prod(blocks.extents, axis=1) * density
    return [
        Element(
            id=f"B{id_start + i:04d}",
            type="block",
            T_world_element=blocks.T_world_block[i],
            layer=int(blocks.layer[i]),
            part=str(blocks.part[i]),
            robot_built=bool(blocks.robot_built[i]),
            extents=blocks.extents[i],
            attributes={
                "wall": str(blocks.wall[i]),
                "piece": str(blocks.piece[i]),
                "kind": str(blocks.kind[i]),
                **({} if mass is None else {"mass": round(float(mass[i]), 4)}),
            },
        )
        for i in range(len(blocks))
    ]
