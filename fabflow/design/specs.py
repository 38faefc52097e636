"""The element sources of a project file: what to build, as the user writes it.

One entry of ``elements`` is a parametric cabin (:class:`CabinSpec`), print paths
from a drawing or a mesh (:class:`PrintPathSpec`) or explicit task points
(:class:`TaskPoint`), a dry-stone wall course filled with found stones
(:class:`StoneWallSpec`) or elements made elsewhere, read from a file
(:class:`ElementFileSpec`). Lengths are metres, ``*_deg`` fields degrees. The design
functions (:mod:`fabflow.design.cabin`, :mod:`fabflow.design.print_path`,
:mod:`fabflow.design.generate`) turn them into elements in the world frame.
"""

from __future__ import annotations

import itertools
import math
from typing import Annotated, Literal

from pydantic import (
    Field,
    model_validator,
)

from fabflow.schema import (
    Count,
    Fraction,
    ModelPath,
    NonNegativeFloat,
    PoseSpec,
    PositiveFloat,
    Real,
    StrictModel,
    Switch,
    Vec3,
)

MAX_LAYER = 100_000
"""Highest build-order layer a task point may name."""


class BlockSize(StrictModel):
    """Timber block dimensions (metres): length along the wall, width across, height."""

    length: PositiveFloat = 0.60
    width: PositiveFloat = 0.105
    height: PositiveFloat = 0.105
    density: PositiveFloat | None = None
    """kg/m^3 (softwood timber about 450): each block then carries its ``mass``
    attribute (kg, of its own length), which the programs add to the tool's load
    while the block is held."""


class Opening(StrictModel):
    """A door or window in one wall of the cabin (metres).

    ``center`` is measured along the wall from its start corner (the corner at
    x = 0 for the left and right walls, at y = 0 for the front and rear walls),
    ``sill`` is the height of the bottom edge above the floor. Every block
    layer that overlaps ``[sill, sill + height]`` is left open; a lintel spans
    the opening in the first layer above it.
    """

    wall: Literal["front", "rear", "left", "right"]
    kind: Literal["door", "window"] = "window"
    center: Real
    width: PositiveFloat
    sill: NonNegativeFloat = 0.0
    height: PositiveFloat


def _default_openings() -> list[Opening]:
    return [
        Opening(wall="front", kind="door", center=1.65, width=0.9, sill=0.0, height=2.1),
        Opening(wall="left", kind="window", center=1.0, width=0.9, sill=0.84, height=1.05),
        Opening(wall="left", kind="window", center=3.0, width=0.9, sill=0.84, height=1.05),
        Opening(wall="right", kind="window", center=1.0, width=0.9, sill=0.84, height=1.05),
        Opening(wall="right", kind="window", center=3.0, width=0.9, sill=0.84, height=1.05),
    ]


CabinPiece = Literal["front", "rear", "left", "right", "front_gable", "rear_gable"]


def _default_parts() -> dict[str, str]:
    return {
        "left": "A",
        "rear": "B",
        "right": "C",
        "front": "front",
        "front_gable": "front",
        "rear_gable": "rear",
    }


class CabinSpec(StrictModel):
    """Parameters of the parametric log cabin (defaults: the cabin of the UWB paper).

    Cabin frame: origin at the outer corner of the front and right walls, x along
    ``length`` (the left and right walls, which carry the eaves), y along
    ``width`` (the front wall at x = 0 and the rear wall at x = length, which
    carry the gables), z up; ``origin`` and ``heading_deg`` place it in the
    world. ``height`` is the ridge height, ``eave_height`` the top of the four
    walls; above it the front and rear walls continue as stepped gables.
    ``parts`` names the part of each wall (and of each gable); the parts in
    ``robot_parts`` are built by the robot, the others are pre-built.
    """

    origin: Vec3 = (0.0, 0.0, 0.0)
    heading_deg: Real = 0.0
    length: PositiveFloat = 4.00
    width: PositiveFloat = 3.30
    height: PositiveFloat = 4.20
    eave_height: PositiveFloat = 3.15
    block: BlockSize = BlockSize()
    openings: list[Opening] = Field(default_factory=_default_openings)
    lintel_bearing: PositiveFloat = 0.15
    """How far a lintel reaches past each side of its opening (metres)."""
    min_piece: PositiveFloat = 0.15
    """Shortest cut block at the end of a row (metres)."""
    parts: dict[CabinPiece, str] = Field(default_factory=_default_parts)
    robot_parts: list[str] = ["A", "B", "C"]

    @model_validator(mode="after")
    def _geometry(self) -> CabinSpec:
        b = self.block
        if self.eave_height > self.height:
            raise ValueError("'eave_height' must not exceed 'height' (the ridge)")
        if self.eave_height < b.height:
            raise ValueError("'eave_height' must be at least one block height")
        if min(self.length, self.width) < 2 * b.width + self.min_piece:
            raise ValueError("'length' and 'width' must exceed two block widths plus 'min_piece'")
        if self.min_piece > b.length / 2:
            raise ValueError("'min_piece' must not exceed half the block length")
        pieces = ("front", "rear", "left", "right", "front_gable", "rear_gable")
        missing = [k for k in pieces if k not in self.parts]
        if missing:
            raise ValueError(f"'parts' lacks {', '.join(missing)}")
        unknown = [p for p in self.robot_parts if p not in self.parts.values()]
        if unknown:
            raise ValueError(
                f"'robot_parts' names {unknown[0]!r}, which no wall or gable belongs to "
                f"(the parts are {', '.join(sorted(set(self.parts.values())))})"
            )
        n_wall = math.floor(self.eave_height / b.height + 1e-6)
        spans = {"front": self.width, "rear": self.width, "left": self.length, "right": self.length}
        reach: dict[str, list[tuple[float, float, int]]] = {}
        for i, o in enumerate(self.openings):
            lo = o.center - o.width / 2 - self.lintel_bearing
            hi = o.center + o.width / 2 + self.lintel_bearing
            if lo < b.width - 1e-9 or hi > spans[o.wall] - b.width + 1e-9:
                raise ValueError(
                    f"openings[{i}]: the opening plus its lintel bearings "
                    f"({lo:.3f}..{hi:.3f} m along the {o.wall} wall) must lie between the "
                    f"corners ({b.width:.3f}..{spans[o.wall] - b.width:.3f} m)"
                )
            if math.ceil((o.sill + o.height) / b.height - 1e-6) >= n_wall:
                raise ValueError(
                    f"openings[{i}]: the top of the opening plus its lintel must stay below "
                    f"the eave ({self.eave_height} m)"
                )
            reach.setdefault(o.wall, []).append((lo, hi, i))
        for wall, spans_on_wall in reach.items():
            ordered = sorted(spans_on_wall)
            for (_, hi0, i), (lo1, _, j) in itertools.pairwise(ordered):
                if lo1 < hi0:
                    raise ValueError(
                        f"openings[{min(i, j)}] and openings[{max(i, j)}] overlap (with lintel "
                        f"bearings) on the {wall} wall"
                    )
        return self


class PrintPathSpec(StrictModel):
    """Print paths from a DXF drawing (named layers) or a mesh (sliced into layers).

    The drawing is a plan: its contours, placed at ``origin``, are printed
    ``n_layers`` times, each ``layer_height`` higher. A mesh is sliced every
    ``layer_height`` into closed contours (all of its height unless ``n_layers``
    is given).
    """

    dxf: ModelPath | None = None
    mesh: ModelPath | None = None
    layers: list[str] = []
    """DXF layers holding the path geometry (all layers when empty)."""
    units: Literal["auto", "m", "cm", "mm", "in", "ft"] = "auto"
    """Drawing units; ``auto``: $INSUNITS of a DXF (mm when unset), metres for a mesh."""
    closed: Switch = True
    """Every contour must be closed (a wall outline); ``false`` allows open paths."""
    origin: PoseSpec = PoseSpec()
    """Where the drawing's origin sits in the world."""
    layer_height: PositiveFloat = 0.02
    n_layers: Annotated[Count, Field(ge=1)] = 10
    bead_width: PositiveFloat = 0.03
    speed: PositiveFloat = 0.1
    """Tool speed along the path (m/s)."""
    sample_rate_hz: PositiveFloat = 100.0

    @model_validator(mode="after")
    def _source(self) -> PrintPathSpec:
        if (self.dxf is None) == (self.mesh is None):
            raise ValueError("give exactly one of 'dxf' or 'mesh'")
        return self


class TaskPoint(StrictModel):
    """An explicit tool frame with an action (drill, mark, measure)."""

    id: Annotated[str, Field(min_length=1)]
    pose: PoseSpec
    action: Literal["drill", "mark", "measure"] = "mark"
    params: dict[str, Real | str] = {}
    layer: Annotated[Count, Field(le=MAX_LAYER)] = 0
    """Build-order layer (0 = first)."""


MAX_STONES = 200
"""Most stones a simulated stockpile may hold (each is meshed, scanned and registered)."""


class StoneSlot(StrictModel):
    """A place in a dry-stone wall course for one found stone.

    ``pose`` is the slot's centre, x along the wall, z up; ``size`` its length
    (x), width (y) and height (z) in metres. The stone chosen for it is the one
    whose principal extents match ``size`` best; it is set with its longest axis
    along x, its shortest up, its centroid over the slot's centre and its lowest
    point on the slot's floor.
    """

    id: Annotated[str, Field(min_length=1, max_length=64)]
    pose: PoseSpec
    size: tuple[PositiveFloat, PositiveFloat, PositiveFloat]


class Stockpile(StrictModel):
    """The stones to build from, as the simulated site lays them out (seeded).

    The build scans this site with the machine's LiDARs (and, with
    ``vision_map``, a drone reconstruction): the stones' geometry and pose come
    from the scans, never from here.
    """

    seed: Count = 0
    n_stones: Annotated[int, Field(strict=True, ge=1, le=MAX_STONES)] = 7
    region_min: tuple[Real, Real] = (2.0, -4.0)
    region_max: tuple[Real, Real] = (8.0, 4.0)
    volume_range: tuple[PositiveFloat, PositiveFloat] = (0.5, 1.0)
    """Stone volumes (m^3): paper 002's gneiss rocks, 0.5 to 1 m^3."""
    convex_share: Fraction = 0.5
    """Share of convex rocks; the others have dents (non-convex meshes)."""
    terrain_rms: Annotated[float, Field(strict=True, ge=0.0, le=0.5)] = 0.03
    """RMS height of the uneven ground (metres): gentle undulations that the 10 cm
    margin of the ground plane fit accounts for (paper 002, section 4.3)."""
    terrain_wavelength: Annotated[float, Field(strict=True, ge=0.5, le=100.0)] = 4.0
    """Typical wavelength of the undulations (metres)."""

    @model_validator(mode="after")
    def _ordered(self) -> Stockpile:
        if self.volume_range[0] > self.volume_range[1]:
            raise ValueError("'volume_range' must be [min, max] with min <= max")
        if any(a >= b for a, b in zip(self.region_min, self.region_max, strict=True)):
            raise ValueError("'region_min' must lie below 'region_max' in x and y")
        return self


class StoneWallSpec(StrictModel):
    """A dry-stone wall course filled with found stones (paper 002).

    The machine stands at ``station`` (the paper keeps the base fixed while it
    manipulates), scans the stockpile by swinging its cabin through
    ``swing_deg`` (degrees about the base's z, at ``swing_step_deg`` steps),
    segments the stones, and sets one in each slot in the order given.
    """

    slots: Annotated[list[StoneSlot], Field(min_length=1, max_length=MAX_STONES)]
    station: PoseSpec = PoseSpec()
    stockpile: Stockpile = Stockpile()
    vision_map: Switch = True
    """Register a drone reconstruction of the stockpile to the LiDAR map (section
    4.4) and merge the matched segments into the object models."""
    swing_deg: tuple[Real, Real] = (-100.0, 100.0)
    swing_step_deg: Annotated[float, Field(strict=True, ge=1.0, le=90.0)] = 10.0

    @model_validator(mode="after")
    def _unique_slots(self) -> StoneWallSpec:
        ids = [s.id for s in self.slots]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"slot id {dup[0]!r} is used twice")
        if self.swing_deg[0] > self.swing_deg[1]:
            raise ValueError("'swing_deg' must be [from, to] with from <= to")
        return self


class ElementFileSpec(StrictModel):
    """Elements made elsewhere (Grasshopper, COMPAS, a script), read from a file.

    ``path`` is an ``elements.json`` (``fabflow schema --elements`` prints its
    schema), a COMPAS JSON file of Boxes, Meshes and Frames, or a Rhino .3dm
    file of boxes, breps, meshes and points; see docs/grasshopper.md. Written
    as ``file: walls.json`` when the defaults suit.
    """

    path: ModelPath
    format: Literal["auto", "fabflow", "compas", "3dm"] = "auto"
    """``auto``: .3dm by its suffix; a .json file holding ``T_world_element``
    records is fabflow's, one holding ``dtype`` objects COMPAS's."""
    type: Literal["block", "task_point"] = "block"
    """Type of an object the file does not type (by user text or layer)."""
    supports: Literal["auto", "file", "computed"] = "auto"
    """What each block rests on: ``file`` as the file says, ``computed`` from the
    geometry of all blocks (as for a cabin), ``auto`` the file's when it names
    any, else computed."""
    part: Annotated[str, Field(min_length=1, max_length=64)] | None = None
    """Part of the elements that do not name one."""
    robot_built: Switch = True
    """Whether the robot builds the elements that do not say."""
    layers: list[Annotated[str, Field(min_length=1)]] = []
    """.3dm only: read these layers (full paths, ``Walls::North``) and the layers
    below them; empty: all."""
    units: Literal["auto", "m", "mm", "cm", "in", "ft"] = "auto"
    """.3dm only: the file's coordinates; ``auto`` its model units. JSON files are
    in metres."""

    @model_validator(mode="before")
    @classmethod
    def _path_alone(cls, data: object) -> object:
        return {"path": data} if isinstance(data, str) else data


ELEMENT_KINDS = ("cabin", "print_path", "task_points", "stone_wall", "file")
"""The keys of one ``elements`` entry."""


class ElementSource(StrictModel):
    """One entry of ``elements``: exactly one of :data:`ELEMENT_KINDS`."""

    cabin: CabinSpec | None = None
    print_path: PrintPathSpec | None = None
    task_points: list[TaskPoint] | None = None
    stone_wall: StoneWallSpec | None = None
    file: ElementFileSpec | None = None

    @model_validator(mode="after")
    def _exactly_one(self) -> ElementSource:
        given = [k for k in ELEMENT_KINDS if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(
                "each entry needs exactly one of "
                + ", ".join(f"'{k}'" for k in ELEMENT_KINDS)
                + (f" (got {', '.join(given)})" if given else "")
            )
        return self
