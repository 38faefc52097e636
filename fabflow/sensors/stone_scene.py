"""Irregular stones on rough terrain, scanned by a swinging excavator and mapped by a drone.

Paper 002: an excavator maps and grasps seven gneiss rocks of 0.5 to 1 m^3 on rough
terrain; two VLP-16s on its cabin roof map while the cabin swings, and a point
cloud from drone images (the "vision" map) is registered to that map. World frame:
z up, metres. The excavator is not in the scene: rays its cabin, arm and legs
would block reach what lies behind (the real pipeline self-filters its points).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.sensors.lidar import VLP16, LidarModel, simulate_scan
from fabflow.sensors.lidar_errors import NO_ERRORS, LidarErrorModel, draw_channel_bias
from fabflow.transforms.se3 import apply_T, make_T
from fabflow.transforms.so3 import check_rotation, exp_so3

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

CONCAVE_FILL = 0.92
"""A non-convex rock's volume is at most this share of its convex hull's (redrawn until so)."""

SINK = 0.02
"""How deep a placed stone sits below its first contact with the terrain (metres)."""

HEAP_LIDARS = make_T(
    exp_so3(np.radians([[0.0, 25.0, 0.0], [0.0, 65.0, 0.0]])),
    [[1.0, 0.6, 2.8], [1.0, -0.6, 2.8]],
)
"""``T_cabin_lidar`` of the two VLP-16s, ``(2, 4, 4)`` (metres); the cabin frame is on the
swing axis at the base's ground level, x forward, z up. Both sit on the front edge
of the cabin roof, 2.8 m up, 0.6 m left and right. The paper gives no angles;
assumed here:

* 0, "horizontal": spin axis tilted forward by 25 deg, so its forward beams
  look 10 to 40 deg down and meet the ground from about 4 m ahead (level, its
  lowest beam would meet the ground only 10 m out, passing over the stones);
* 1, "vertical": spin axis along the cabin's x, tilted 25 deg up: its scan fan
  stands across the cabin, the downward part leaning 10 to 40 deg forward, ahead
  of the cabin's front; swinging the cabin sweeps the fan over the ground.
"""
HEAP_LIDARS.flags.writeable = False

SWING_YAWS_DEG = tuple(float(a) for a in np.linspace(-90.0, 90.0, 8))
"""Cabin yaws of a simulated swing (degrees): 8 stops over -90..+90 deg, a coarse stand-in
for a 20 s swing at 10 Hz (200 revolutions per LiDAR): 16 scans instead of 400."""


def _vector(value: ArrayLike, n: int, name: str) -> FloatArray:
    a = np.asarray(value, dtype=float).reshape(-1)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise InputError(f"{name} must be {n} finite numbers, got {value!r}")
    return a


def _poses(value: ArrayLike, name: str) -> FloatArray:
    T = np.asarray(value, dtype=float)
    T = T[None] if T.ndim == 2 else T
    if T.ndim != 3 or T.shape[1:] != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"{name} must be finite 4x4 poses, got shape {T.shape}")
    if len(T):
        check_rotation(T[:, :3, :3], name=name)
    return T


def rock_mesh(
    rng: np.random.Generator, extents: ArrayLike, convex: bool, subdivisions: int = 3
) -> trimesh.Trimesh:
    """An irregular rock in its own frame (metres), centre of mass at the origin.

    Parameters
    ----------
    rng
        Source of the shape.
    extents
        ``(3,)`` edge lengths of the rock's axis-aligned bounding box in its own
        frame (metres): an irregular ellipsoid with these axes; the volume is
        about ``0.50 * extents.prod()`` (convex) or ``0.46 * extents.prod()``.
    convex
        ``True``: the convex hull of points in random directions at 75 to 100 %
        of the ellipsoid's radius (a faceted, blocky stone). ``False``: an
        icosphere whose radius varies smoothly by four random bumps and dents
        plus a groove about an axis near x (the long axis when the extents are
        sorted): a concavity, the volume at most :data:`CONCAVE_FILL` of the
        convex hull's (shapes are redrawn until so, at most 20 times, keeping
        the most concave). Watertight either way.
    subdivisions
        Icosphere subdivisions: ``10 * 4**subdivisions + 2`` hull points or
        vertices; 3 gives about 250 (convex) or 1280 faces.
    """
    ext = _vector(extents, 3, "rock extents")
    if not np.all(ext > 0) or not 1 <= subdivisions <= 5:
        raise InputError("a rock needs positive extents and 1 <= subdivisions <= 5")
    sphere = trimesh.creation.icosphere(subdivisions)
    if convex:
        d = rng.standard_normal(sphere.vertices.shape)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        mesh = trimesh.convex.convex_hull(d * rng.uniform(0.75, 1.0, (len(d), 1)))
    else:
        mesh = _concave_rock(rng, sphere)
    lo, hi = mesh.bounds
    rock = trimesh.Trimesh((mesh.vertices - lo) * (ext / (hi - lo)), mesh.faces, process=False)
    rock.apply_translation(-rock.center_mass)
    return rock


def _concave_rock(rng: np.random.Generator, sphere: trimesh.Trimesh) -> trimesh.Trimesh:
    """A unit sphere with smooth radial bumps, dents and a groove: see :func:`rock_mesh`."""
    u = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1, keepdims=True)
    best, best_fill = sphere, 1.0
    for _ in range(20):
        centres = rng.standard_normal((4, 3))
        centres /= np.linalg.norm(centres, axis=1, keepdims=True)
        angle = np.arccos(np.clip(u @ centres.T, -1.0, 1.0))
        width, height = rng.uniform(0.35, 0.6, 4), rng.uniform(-0.2, 0.2, 4)
        radius = 1.0 + (height * np.exp(-0.5 * (angle / width) ** 2)).sum(axis=1)
        axis = np.array([1.0, 0.0, 0.0]) + rng.uniform(-0.3, 0.3, 3)
        along = u @ (axis / np.linalg.norm(axis)) - rng.uniform(-0.3, 0.3)
        groove = rng.uniform(0.3, 0.45) * np.exp(-0.5 * (along / rng.uniform(0.2, 0.3)) ** 2)
        radius = np.maximum(radius - groove, 0.3)[:, None]
        mesh = trimesh.Trimesh(u * radius, sphere.faces, process=False)
        fill = mesh.volume / mesh.convex_hull.volume
        if fill < best_fill:
            best, best_fill = mesh, fill
        if fill <= CONCAVE_FILL:
            break
    return best


@dataclass(frozen=True, eq=False)
class Ground:
    """A terrain height field on a regular grid (world frame, metres).

    Attributes
    ----------
    x0, y0, spacing
        World position of grid node ``(0, 0)`` and the node spacing (metres).
    heights
        ``(nx, ny)`` terrain height (world z) at node ``(i, j)``, which lies at
        ``(x0 + i * spacing, y0 + j * spacing)`` (metres); at least 2 x 2.
    """

    x0: float
    y0: float
    spacing: float
    heights: FloatArray

    def __post_init__(self) -> None:
        h = np.array(self.heights, dtype=float)
        if h.ndim != 2 or min(h.shape) < 2 or not np.all(np.isfinite(h)):
            raise InputError(f"ground heights must be a finite (nx, ny) grid, >= 2x2: {h.shape}")
        if not (np.isfinite(self.x0) and np.isfinite(self.y0) and self.spacing > 0):
            raise InputError("ground needs a finite origin and a positive grid spacing")
        h.flags.writeable = False
        object.__setattr__(self, "heights", h)

    @property
    def bounds(self) -> FloatArray:
        """``[[x_min, y_min], [x_max, y_max]]`` of the grid (metres)."""
        lo = np.array([self.x0, self.y0])
        return np.array([lo, lo + (np.array(self.heights.shape) - 1) * self.spacing])

    def height(self, xy: ArrayLike) -> FloatArray:
        """Bilinear terrain height ``(N,)`` at world ``xy`` ``(N, 2)`` (metres), clamped to grid."""
        p = np.asarray(xy, dtype=float).reshape(-1, 2)
        last = np.array(self.heights.shape) - 1
        f = np.clip((p - [self.x0, self.y0]) / self.spacing, 0.0, last)
        i = np.minimum(np.floor(f).astype(np.intp), last - 1)
        tx, ty = (f - i).T
        h, i, j = self.heights, i[:, 0], i[:, 1]
        low = h[i, j] * (1 - tx) + h[i + 1, j] * tx
        high = h[i, j + 1] * (1 - tx) + h[i + 1, j + 1] * tx
        return low * (1 - ty) + high * ty

    def mesh(self) -> trimesh.Trimesh:
        """The terrain as two triangles per grid cell, normals up (world frame, metres).

        The triangles share the grid nodes; inside a cell they differ from the
        bilinear :meth:`height` by at most ``|h00 - h10 - h01 + h11| / 4``
        (millimetres on the smooth terrain of :func:`uneven_ground`).
        """
        nx, ny = self.heights.shape
        gx, gy = np.meshgrid(
            self.x0 + np.arange(nx) * self.spacing,
            self.y0 + np.arange(ny) * self.spacing,
            indexing="ij",
        )
        vertices = np.stack([gx, gy, self.heights], axis=-1).reshape(-1, 3)
        node = np.arange(nx * ny).reshape(nx, ny)
        v00, v10 = node[:-1, :-1].ravel(), node[1:, :-1].ravel()
        v01, v11 = node[:-1, 1:].ravel(), node[1:, 1:].ravel()
        faces = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
        return trimesh.Trimesh(vertices, faces, process=False)


def uneven_ground(
    rng: np.random.Generator,
    extent_min: ArrayLike,
    extent_max: ArrayLike,
    amplitude: float = 0.08,
    wavelength: float = 2.0,
    spacing: float = 0.25,
    n_waves: int = 6,
) -> Ground:
    """Smooth random terrain, a sum of plane sinusoids: paper 002's "rough terrain".

    Parameters
    ----------
    rng
        Source of the waves' directions, wavelengths and phases.
    extent_min, extent_max
        ``(2,)`` world x-y corners the grid covers (metres); the far edge is
        rounded up to a whole number of cells.
    amplitude
        Root-mean-square terrain height about z = 0 (metres); each wave's
        amplitude is ``amplitude * sqrt(2 / n_waves)``. An assumption: the paper
        shows the terrain but gives no figure.
    wavelength, n_waves
        Typical wavelength (metres; each wave's is 0.6 to 1.5 times it) and the
        number of waves.
    spacing
        Grid spacing (metres); 0.25 m resolves the waves and keeps a 20 m x 20 m
        ground at 12 800 triangles.
    """
    lo = _vector(extent_min, 2, "ground extent_min")
    hi = _vector(extent_max, 2, "ground extent_max")
    if not (np.all(hi > lo) and spacing > 0 and amplitude >= 0 and wavelength > 0 and n_waves > 0):
        raise InputError(
            "uneven ground needs extent_max > extent_min, spacing > 0, wavelength > 0, "
            "amplitude >= 0 and n_waves >= 1"
        )
    n = np.ceil((hi - lo) / spacing - 1e-9).astype(int) + 1
    x = lo[0] + np.arange(n[0]) * spacing
    y = lo[1] + np.arange(n[1]) * spacing
    heading = rng.uniform(0.0, 2.0 * np.pi, n_waves)
    k = 2.0 * np.pi / (wavelength * rng.uniform(0.6, 1.5, n_waves))
    phase = rng.uniform(0.0, 2.0 * np.pi, n_waves)
    arg = x[:, None, None] * (k * np.cos(heading)) + y[None, :, None] * (k * np.sin(heading))
    heights = amplitude * np.sqrt(2.0 / n_waves) * np.sin(arg + phase).sum(axis=-1)
    return Ground(float(lo[0]), float(lo[1]), float(spacing), heights)


@dataclass(frozen=True, eq=False)
class StoneSite:
    """Stones lying on the ground (world frame, metres).

    Attributes
    ----------
    ground
        The terrain.
    models
        Each stone's mesh in its own frame (centre of mass at the origin, metres).
    T_world_stone
        ``(K, 4, 4)`` pose of each stone in the world.
    """

    ground: Ground
    models: tuple[trimesh.Trimesh, ...]
    T_world_stone: FloatArray

    def __post_init__(self) -> None:
        T = _poses(np.reshape(self.T_world_stone, (-1, 4, 4)), "T_world_stone").copy()
        if len(T) != len(self.models):
            raise InputError(f"a stone site has {len(T)} poses for {len(self.models)} stones")
        T.flags.writeable = False
        object.__setattr__(self, "models", tuple(self.models))
        object.__setattr__(self, "T_world_stone", T)

    @property
    def n_stones(self) -> int:
        """Number of stones."""
        return len(self.models)

    def centers_of_mass(self) -> FloatArray:
        """``(K, 3)`` the stones' centres of mass in the world (metres): the poses' origins."""
        return self.T_world_stone[:, :3, 3].copy()

    def _index(self, i: int) -> int:
        if not -self.n_stones <= i < self.n_stones:
            raise InputError(f"no stone {i}: the site has {self.n_stones}")
        return i % self.n_stones

    def _kept(self, exclude: Sequence[int]) -> list[int]:
        return sorted(set(range(self.n_stones)) - {self._index(int(i)) for i in exclude})

    def stone_mesh(self, i: int) -> trimesh.Trimesh:
        """Stone ``i`` at its pose (world frame, metres)."""
        i = self._index(i)
        vertices = apply_T(self.T_world_stone[i], self.models[i].vertices)
        return trimesh.Trimesh(vertices, self.models[i].faces, process=False)

    def face_owner(self, exclude: Sequence[int] = ()) -> IntArray:
        """``(F,)`` owner of each face of ``scene(exclude)``: -1 the ground, ``i`` stone ``i``."""
        kept = self._kept(exclude)
        nx, ny = self.ground.heights.shape
        counts = [2 * (nx - 1) * (ny - 1), *(len(self.models[i].faces) for i in kept)]
        return np.repeat(np.array([-1, *kept], dtype=np.int64), counts)

    def scene(self, exclude: Sequence[int] = ()) -> trimesh.Trimesh:
        """Ground and stones as one mesh in the world frame (metres), for ray casting.

        The ground's faces come first, then each stone's in index order, less the
        stones in ``exclude`` (e.g. the one in the gripper); the faces' owners
        (:meth:`face_owner`) are also in ``face_attributes["owner"]``.
        """
        parts = [self.ground.mesh(), *(self.stone_mesh(i) for i in self._kept(exclude))]
        offsets = np.cumsum([0, *(len(p.vertices) for p in parts[:-1])])
        return trimesh.Trimesh(
            np.concatenate([p.vertices for p in parts]),
            np.concatenate([p.faces + o for p, o in zip(parts, offsets, strict=True)]),
            face_attributes={"owner": self.face_owner(exclude)},
            process=False,
        )

    def moved(self, i: int, T_world_stone_new: ArrayLike) -> StoneSite:
        """The same site with stone ``i`` at a new 4x4 pose (world frame, metres)."""
        T = np.array(self.T_world_stone)
        T[self._index(i)] = _poses(T_world_stone_new, "T_world_stone_new")[0]
        return replace(self, T_world_stone=T)


def _place(
    rng: np.random.Generator, radius: FloatArray, box: FloatArray, gap: float, tries: int
) -> FloatArray | None:
    """Footprint centres ``(K, 2)`` in ``box`` (metres), largest first; ``None`` if jammed."""
    centres = np.zeros((len(radius), 2))
    placed: list[int] = []
    for i in np.argsort(-radius, kind="stable"):
        spots = rng.uniform(box[0] + radius[i], box[1] - radius[i], (tries, 2))
        gaps = np.linalg.norm(spots[:, None] - centres[placed][None], axis=2)
        free = np.all(gaps >= radius[i] + radius[placed] + gap, axis=1)
        if not free.any():
            return None
        centres[i] = spots[np.argmax(free)]
        placed.append(int(i))
    return centres


def stone_site(
    rng: np.random.Generator,
    n_stones: int = 7,
    region_min: ArrayLike = (2.5, -4.0),
    region_max: ArrayLike = (9.5, 4.0),
    volume_range: tuple[float, float] = (0.5, 1.0),
    convex_share: float = 0.5,
    min_gap: float = 0.4,
    ground: Ground | None = None,
    sink: float = SINK,
    max_tries: int = 500,
) -> StoneSite:
    """Stones at random spots on the ground, apart from each other, each resting on it.

    Each has a random yaw and extents ``a >= b >= c`` (``b / a`` in 0.6..0.95,
    ``c / b`` in 0.55..0.9, the shortest axis up as a stone lies flat), scaled to
    its volume exactly.

    Parameters
    ----------
    rng
        Source of the shapes, sizes, spots and yaws (and of the default ground).
    n_stones
        Number of stones (paper 002: seven).
    region_min, region_max
        ``(2,)`` world x-y corners of the region holding the stones' footprints
        (metres). Default: 7 m x 8 m from 2.5 m ahead of a machine at the origin
        facing +x (the paper's region of interest: about 50 m^2, within reach).
    volume_range
        Each stone's volume is uniform in this range (m^3).
    convex_share
        Share of convex stones (rounded); the others have a concavity.
    min_gap
        Least distance between two stones' footprints (metres): the circles about
        the centres of mass holding the plan views. Spread out, as the paper needs
        for each stone to segment alone.
    ground
        The terrain; default :func:`uneven_ground` over the region and the
        origin, 6 m beyond both.
    sink
        How far a stone is lowered after its lowest vertex touches the terrain
        (metres), as a heavy stone settles into the soil.
    max_tries
        Random spots tried per stone; when one finds none, the placement starts
        over, and after 10 starts :class:`InputError` is raised.
    """
    lo, hi = _vector(region_min, 2, "region_min"), _vector(region_max, 2, "region_max")
    v_lo, v_hi = (float(v) for v in volume_range)
    ok = np.all(hi > lo) and 0 < v_lo <= v_hi and 0 <= convex_share <= 1 and max_tries >= 1
    if not ok or min(n_stones, min_gap, sink) < 0:
        raise InputError(
            "a stone site needs region_max > region_min, 0 < volume_range[0] <= volume_range[1], "
            "convex_share in [0, 1], max_tries >= 1 and n_stones, min_gap, sink >= 0"
        )
    if ground is None:
        ground = uneven_ground(rng, np.minimum(lo, 0.0) - 6.0, np.maximum(hi, 0.0) + 6.0)
    g_lo, g_hi = ground.bounds
    if np.any(lo < g_lo - 1e-9) or np.any(hi > g_hi + 1e-9):
        raise InputError(f"the stone region {lo}..{hi} is not within the ground {g_lo}..{g_hi}")
    convex = rng.permutation(np.arange(n_stones) < round(convex_share * n_stones))
    volume = rng.uniform(v_lo, v_hi, n_stones)
    ratios = rng.uniform([0.6, 0.55], [0.95, 0.9], (n_stones, 2))
    shape = np.cumprod(np.c_[np.ones(n_stones), ratios], axis=1)
    models = []
    for i in range(n_stones):
        # drawn as an ellipsoid of the volume, then scaled to the volume exactly
        extents = shape[i] * np.cbrt(volume[i] / (np.pi / 6 * shape[i].prod()))
        rock = rock_mesh(rng, extents, bool(convex[i]))
        rock.apply_scale(np.cbrt(volume[i] / rock.volume))
        rock.apply_translation(-rock.center_mass)
        models.append(rock)
    radius = np.array([np.linalg.norm(m.vertices[:, :2], axis=1).max() for m in models])
    if np.any(hi - lo < 2 * radius.max(initial=0.0)):
        raise InputError(f"a stone {2 * radius.max():.2f} m across does not fit in {lo}..{hi}")
    for _ in range(10):  # a jammed placement starts over
        if (centres := _place(rng, radius, np.array([lo, hi]), min_gap, max_tries)) is not None:
            break
    else:
        raise InputError(
            f"cannot place {n_stones} stones {min_gap} m apart in the region {lo}..{hi} "
            f"(10 starts, {max_tries} spots per stone); enlarge the region or lower "
            "n_stones, min_gap or volume_range"
        )
    yaw = rng.uniform(-np.pi, np.pi, n_stones)
    T = make_T(exp_so3(np.c_[np.zeros((n_stones, 2)), yaw]), np.c_[centres, np.zeros(n_stones)])
    for i, model in enumerate(models):
        v = apply_T(T[i], model.vertices)
        T[i, 2, 3] = np.max(ground.height(v[:, :2]) - v[:, 2]) - sink
    return StoneSite(ground, tuple(models), T)


def cabin_swing_poses(
    T_world_base: ArrayLike,
    yaws_deg: ArrayLike = SWING_YAWS_DEG,
    lidar_offsets: ArrayLike = HEAP_LIDARS,
) -> FloatArray:
    """LiDAR poses ``T_world_lidar`` ``(Y * L, 4, 4)`` as the cabin swings about the base's z.

    Pose ``m`` is LiDAR ``m % L`` at yaw ``m // L``.

    Parameters
    ----------
    T_world_base
        4x4 pose of the base (undercarriage) in the world: origin on the swing
        axis at ground level, z up along the axis (metres).
    yaws_deg
        ``(Y,)`` cabin yaws about the base's z (degrees; 0: cabin x along base x).
    lidar_offsets
        ``(L, 4, 4)`` ``T_cabin_lidar`` of each LiDAR (metres); default
        :data:`HEAP_LIDARS`.
    """
    T_base = _poses(T_world_base, "T_world_base")[0]
    offsets = _poses(lidar_offsets, "lidar_offsets")
    yaw = np.radians(np.asarray(yaws_deg, dtype=float).reshape(-1))
    if not np.all(np.isfinite(yaw)):
        raise InputError("cabin yaws must be finite (degrees)")
    T_base_cabin = make_T(exp_so3(np.c_[np.zeros((len(yaw), 2)), yaw]), np.zeros(3))
    return (T_base @ T_base_cabin[:, None] @ offsets[None]).reshape(-1, 4, 4)


@dataclass(frozen=True, eq=False)
class SiteScan:
    """The returns of several LiDAR scans, labelled with what they hit.

    Attributes
    ----------
    points_world
        ``(N, 3)`` measured points in the world frame (metres), noise included.
    owner
        ``(N,)`` what each return hit: -1 the ground, ``i`` stone ``i``.
    lidar_index
        ``(N,)`` the scan pose (row of ``T_world_lidars``) each return came from.
    face_index
        ``(N,)`` face of ``site.scene()`` each return hit (ground truth, e.g. normals).
    T_world_lidars
        ``(M, 4, 4)`` the scan poses (metres).
    """

    points_world: FloatArray
    owner: IntArray
    lidar_index: IntArray
    face_index: IntArray
    T_world_lidars: FloatArray

    def __len__(self) -> int:
        return len(self.points_world)


def scan_site(
    site: StoneSite,
    T_world_lidars: ArrayLike,
    rng: np.random.Generator,
    model: LidarModel = VLP16,
    errors: LidarErrorModel = NO_ERRORS,
    sensor_of_pose: ArrayLike | None = None,
) -> SiteScan:
    """One simulated revolution from each pose against the site, in the world frame.

    Parameters
    ----------
    site
        The stones and the ground (one scene for all scans).
    T_world_lidars
        ``(M, 4, 4)`` sensor poses (metres), e.g. :func:`cabin_swing_poses`;
        each scan is taken standing still.
    rng, model, errors
        Source of the range noise and channel biases; the LiDAR (default
        :data:`~fabflow.sensors.lidar.VLP16`); range errors beyond white noise.
    sensor_of_pose
        ``(M,)`` which physical LiDAR took each scan: the scans of one share its
        channel bias (one run). Default: all one LiDAR. For
        :func:`cabin_swing_poses` with ``L`` LiDARs: ``np.arange(M) % L``.
    """
    T = _poses(T_world_lidars, "T_world_lidars")
    sensor = np.zeros(len(T), int) if sensor_of_pose is None else np.asarray(sensor_of_pose)
    if sensor.shape != (len(T),) or sensor.dtype.kind not in "iu" or np.any(sensor < 0):
        raise InputError(f"sensor_of_pose must be {len(T)} non-negative integers")
    n_sensors = int(sensor.max(initial=-1)) + 1
    bias = [draw_channel_bias(errors, model.n_beams, rng) for _ in range(n_sensors)]
    scene, owner = site.scene(), site.face_owner()
    scans = [simulate_scan(scene, T[m], rng, model, errors, bias[sensor[m]]) for m in range(len(T))]
    face = np.concatenate([np.zeros(0, np.int64), *(s.face_index for s in scans)])
    points = [apply_T(T[m], s.points) for m, s in enumerate(scans)]
    return SiteScan(
        points_world=np.concatenate([np.zeros((0, 3)), *points]),
        owner=owner[face],
        lidar_index=np.repeat(np.arange(len(T), dtype=np.int64), [len(s) for s in scans]),
        face_index=face,
        T_world_lidars=T,
    )


def vision_map(
    site: StoneSite,
    rng: np.random.Generator,
    spacing: float = 0.03,
    sigma: float = 0.01,
    T_source_world: ArrayLike | None = None,
    region_min: ArrayLike | None = None,
    region_max: ArrayLike | None = None,
) -> FloatArray:
    """The drone's photogrammetric point cloud of the site: what is seen from above.

    Points are drawn area-uniformly at random on the stones and the ground in the
    region (one per ``spacing**2``); a point is kept if its surface faces up and a
    ray straight up from it (started 2 mm off the surface along its normal)
    hits nothing: undersides and the ground under overhangs are not seen. Looking
    straight down is a simplification: oblique views see steep flanks a bit lower.

    Parameters
    ----------
    site, rng
        The stones and the ground; the source of the samples and noise.
    spacing
        Mean point spacing on the surface (metres); 3 cm, the paper's LiDAR map
        voxel, gives about 1100 points per m^2 (its vision maps: 74k and 98k).
    sigma
        Standard deviation of isotropic Gaussian noise on each point (metres): an
        assumption, the paper states no accuracy of its reconstruction.
    T_source_world
        4x4 pose of the world in the reconstruction's own frame (metres): the
        points come as ``T_source_world @ p``. Default identity.
    region_min, region_max
        ``(2,)`` world x-y corners of the ground flown over (metres). Default (either
        ``None``): the stones' plan bounds grown by 1.5 m.

    Returns
    -------
    numpy.ndarray
        ``(N, 3)`` points in the source frame (metres).
    """
    if not (spacing > 0 and sigma >= 0):
        raise InputError("a vision map needs spacing > 0 and sigma >= 0")
    T_src = np.eye(4) if T_source_world is None else _poses(T_source_world, "T_source_world")[0]
    if region_min is not None and region_max is not None:
        lo, hi = _vector(region_min, 2, "region_min"), _vector(region_max, 2, "region_max")
    elif site.n_stones:
        xy = np.concatenate([site.stone_mesh(i).vertices[:, :2] for i in range(site.n_stones)])
        lo, hi = xy.min(axis=0) - 1.5, xy.max(axis=0) + 1.5
    else:
        raise InputError("a vision map of a site without stones needs region_min and region_max")
    scene = site.scene()
    centre = scene.triangles_center[:, :2]
    flown = np.all((centre >= lo) & (centre <= hi), axis=1) | (site.face_owner() >= 0)
    surface = trimesh.Trimesh(scene.vertices, scene.faces[flown], process=False)
    n = round(surface.area / spacing**2)
    points, face = trimesh.sample.sample_surface(surface, n, seed=int(rng.integers(2**31)))
    facing = surface.face_normals[face, 2] > 0
    points, normals = np.asarray(points)[facing], surface.face_normals[face[facing]]
    up = np.broadcast_to([0.0, 0.0, 1.0], points.shape)
    seen = ~scene.ray.intersects_any(points + 0.002 * normals, up)
    noisy = points[seen] + sigma * rng.standard_normal((int(seen.sum()), 3))
    return apply_T(T_src, noisy)
