"""Total station polar observations: the instrument model, conversions and error propagation.

A total station measures, for each target, a horizontal angle ``Hz``, a vertical
(zenith) angle ``V`` and a slope distance ``sd``. In the instrument frame (origin
at the station mark, ``z`` up, ``y`` the Hz zero direction, ``x`` = ``y`` turned
90 degrees clockwise seen from above, i.e. east when ``y`` is north) a target is::

    x = sd sin(V) sin(Hz)
    y = sd sin(V) cos(Hz)
    z = sd cos(V) + instrument_height - prism_height

Hz grows clockwise from ``y``; ``V`` is 0 at the zenith and 90 degrees (100 gon)
on the horizon. Angles are radians inside fabflow; gon and degrees are converted
at the edges with :data:`GON` and :data:`DEG`.

The accuracy model is the one on instrument data sheets: a distance standard
deviation of ``a + b * sd`` (``a`` metres, ``b`` parts per million) and one angle
standard deviation for both Hz and V.

Readings from files are checked here (:func:`reading_problem`): a slope
distance from :data:`MIN_DISTANCE_M` to :data:`MAX_DISTANCE_M`, angles within a
turn, a zenith angle at least :data:`MIN_ZENITH_DISTANCE` from straight up or
down (where the Hz reading, and with it the covariance, degenerates), coordinates up to
:data:`MAX_COORDINATE_M` and heights up to :data:`MAX_HEIGHT_M`. The file
bounds shared by the readers are :data:`MAX_READINGS_BYTES` and :data:`MAX_READINGS`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fabflow.errors import InputError
from fabflow.files import show

GON = math.pi / 200.0
"""One gon in radians."""
DEG = math.pi / 180.0
"""One degree in radians."""
ARCSEC = DEG / 3600.0
"""One arc second in radians."""

MAX_READINGS_BYTES = 2 * 2**20
"""Largest observation, GSI or robot point file read (bytes); a station's
readings take a few kilobytes."""
MAX_READINGS = 5000
"""Most readings (or robot points) one file may hold; at most
:data:`~fabflow.positioning.total_station.MAX_PRISM_POINTS` of them are adjusted."""
MIN_DISTANCE_M = 0.2
"""Shortest slope distance read (metres): no total station measures a prism closer."""
MAX_DISTANCE_M = 10_000.0
"""Longest slope distance read (metres): beyond any total station's reach to a prism."""
MIN_ZENITH_DISTANCE = 0.1 * GON
"""Closest a zenith angle may come to straight up (0) or down (200 gon), in radians."""
MAX_COORDINATE_M = 1e8
"""Largest magnitude of a coordinate computed by the instrument (metres; projected
grid coordinates are below 1e7)."""
MAX_HEIGHT_M = 100.0
"""Largest magnitude of a prism or instrument height (metres)."""


@dataclass(frozen=True)
class Instrument:
    """The stated accuracy of a total station.

    Attributes
    ----------
    name
        Instrument name, for reports.
    distance_sigma
        Constant part of the distance standard deviation (metres).
    distance_ppm
        Distance-proportional part (parts per million of the slope distance).
    angle_sigma
        Standard deviation of the Hz and V angle readings (radians).
    centring_sigma
        Standard deviation per axis of where a sighted prism's optical centre
        lies off its nominal point (metres), drawn per sighting: a 360 deg prism
        seen from another side, a round prism not facing the instrument.
    atmosphere_ppm
        Standard deviation of the scale error the atmospheric correction leaves
        (ppm of the distance; about 1 ppm per degree Celsius or 3 hPa entered
        wrongly), shared by a set-up's distances.
    """

    name: str
    distance_sigma: float
    distance_ppm: float
    angle_sigma: float
    centring_sigma: float = 0.0
    atmosphere_ppm: float = 0.0

    def sigma_distance(self, sd: np.ndarray | float) -> np.ndarray:
        """Distance standard deviation (metres) at slope distances ``sd`` (metres)."""
        return self.distance_sigma + self.distance_ppm * 1e-6 * np.asarray(sd, dtype=float)


INSTRUMENTS: dict[str, Instrument] = {
    "leica_ms50": Instrument("leica_ms50", 0.001, 1.5, 1.0 * ARCSEC),
    "hilti_pos150": Instrument("hilti_pos150", 0.002, 0.0, 5.0 * ARCSEC),
}
"""Data-sheet accuracies: Leica Nova MS50 (1 mm + 1.5 ppm, 1"), Hilti POS 150 (2 mm, 5")."""


INSTRUMENT_BOUNDS = {
    "distance_sigma_mm": (0.01, 1000.0, "mm"),
    "distance_ppm": (0.0, 1000.0, "ppm"),
    "angle_sigma_arcsec": (0.01, 3600.0, "arc seconds"),
    "prism_centring_mm": (0.0, 100.0, "mm"),
    "atmosphere_ppm": (0.0, 1000.0, "ppm"),
}
"""Accepted accuracies ``(low, high, unit)``, bounds included: a zero sigma makes
every point's covariance singular; the best instruments state 0.5 mm and 0.5"."""


def make_instrument(
    name: str,
    distance_sigma_mm: float | None = None,
    distance_ppm: float | None = None,
    angle_sigma_arcsec: float | None = None,
    prism_centring_mm: float | None = None,
    atmosphere_ppm: float | None = None,
) -> Instrument:
    """An instrument by preset name, with any of its accuracies overridden.

    Parameters
    ----------
    name
        ``"leica_ms50"``, ``"hilti_pos150"`` or ``"custom"`` (then all three
        accuracies must be given).
    distance_sigma_mm, distance_ppm, angle_sigma_arcsec
        Overrides in data-sheet units: millimetres, ppm, arc seconds, within
        :data:`INSTRUMENT_BOUNDS`.
    prism_centring_mm, atmosphere_ppm
        The prism's centring and the atmosphere's scale error
        (:class:`Instrument`), in millimetres and ppm.

    Raises
    ------
    InputError
        An unknown name, a missing accuracy of ``custom``, or an accuracy that
        is not a finite number within its bounds (naming the parameter).
    """
    given = {
        "distance_sigma_mm": distance_sigma_mm,
        "distance_ppm": distance_ppm,
        "angle_sigma_arcsec": angle_sigma_arcsec,
        "prism_centring_mm": prism_centring_mm,
        "atmosphere_ppm": atmosphere_ppm,
    }
    for field, value in given.items():
        low, high, unit = INSTRUMENT_BOUNDS[field]
        if value is not None and not (math.isfinite(value) and low <= value <= high):
            raise InputError(
                f"expected at least {low:g} and at most {high:g} {unit}, got {value}",
                location=field,
            )
    if name == "custom":
        missing = [
            field
            for field, value in (
                ("distance_sigma_mm", distance_sigma_mm),
                ("distance_ppm", distance_ppm),
                ("angle_sigma_arcsec", angle_sigma_arcsec),
            )
            if value is None
        ]
        if missing:
            raise InputError(
                "instrument 'custom' needs its accuracies; missing " + ", ".join(missing)
            )
        base = Instrument("custom", 0.0, 0.0, 0.0)
    elif name in INSTRUMENTS:
        base = INSTRUMENTS[name]
    else:
        raise InputError(
            f"unknown instrument {name!r}; expected one of " + ", ".join([*INSTRUMENTS, "custom"])
        )
    return Instrument(
        name=base.name,
        distance_sigma=base.distance_sigma
        if distance_sigma_mm is None
        else distance_sigma_mm * 1e-3,
        distance_ppm=base.distance_ppm if distance_ppm is None else float(distance_ppm),
        angle_sigma=base.angle_sigma if angle_sigma_arcsec is None else angle_sigma_arcsec * ARCSEC,
        centring_sigma=(prism_centring_mm or 0.0) * 1e-3,
        atmosphere_ppm=float(atmosphere_ppm or 0.0),
    )


def polar_to_cartesian(
    hz: np.ndarray,
    v: np.ndarray,
    sd: np.ndarray,
    instrument_height: float | np.ndarray = 0.0,
    prism_height: float | np.ndarray = 0.0,
) -> np.ndarray:
    """Target positions in the instrument frame from polar observations.

    Parameters
    ----------
    hz, v
        Horizontal and zenith angles (radians), any matching shape ``(...)``.
    sd
        Slope distances (metres), same shape.
    instrument_height, prism_height
        Height of the trunnion axis above the station mark and of the prism
        centre below the measured point (metres).

    Returns
    -------
    numpy.ndarray
        ``(..., 3)`` points in metres.
    """
    hz, v, sd = (np.asarray(a, dtype=float) for a in (hz, v, sd))
    sv = np.sin(v)
    dz = np.asarray(instrument_height, dtype=float) - np.asarray(prism_height, dtype=float)
    return np.stack(
        [sd * sv * np.sin(hz), sd * sv * np.cos(hz), sd * np.cos(v) + dz],
        axis=-1,
    )


def cartesian_to_polar(
    points: np.ndarray,
    instrument_height: float | np.ndarray = 0.0,
    prism_height: float | np.ndarray = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`polar_to_cartesian`: ``(hz, v, sd)`` in radians and metres.

    ``hz`` is in ``[0, 2 pi)``; ``points`` is ``(..., 3)`` in the instrument frame.
    """
    p = np.asarray(points, dtype=float)
    dz = np.asarray(instrument_height, dtype=float) - np.asarray(prism_height, dtype=float)
    x, y, z = p[..., 0], p[..., 1], p[..., 2] - dz
    horizontal = np.hypot(x, y)
    sd = np.hypot(horizontal, z)
    hz = np.mod(np.arctan2(x, y), 2.0 * np.pi)
    v = np.arctan2(horizontal, z)
    return hz, v, sd


def polar_jacobian(hz: np.ndarray, v: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` derivative of the Cartesian point by ``(hz, v, sd)``."""
    hz, v, sd = (np.asarray(a, dtype=float) for a in (hz, v, sd))
    sh, ch, sv, cv = np.sin(hz), np.cos(hz), np.sin(v), np.cos(v)
    zero = np.zeros_like(sh)
    return np.stack(
        [
            np.stack([sd * sv * ch, sd * cv * sh, sv * sh], axis=-1),
            np.stack([-sd * sv * sh, sd * cv * ch, sv * ch], axis=-1),
            np.stack([zero, -sd * sv, cv], axis=-1),
        ],
        axis=-2,
    )


def polar_covariance(
    hz: np.ndarray, v: np.ndarray, sd: np.ndarray, instrument: Instrument
) -> np.ndarray:
    """First-order covariance (m^2) of the Cartesian points, ``(..., 3, 3)``, instrument frame.

    The angles and the distance are taken as independent with the instrument's
    stated standard deviations; the atmosphere's scale error adds to the
    distance's variance (shared by a set-up's distances in truth, taken per point
    here; 1 ppm at the tens of metres of a building site is a few hundredths of
    a millimetre), and the prism's centring adds ``centring_sigma^2`` per axis.
    """
    J = polar_jacobian(hz, v, sd)
    sig_a = instrument.angle_sigma
    sd_var = instrument.sigma_distance(sd) ** 2
    sd_var = sd_var + (instrument.atmosphere_ppm * 1e-6 * np.asarray(sd, dtype=float)) ** 2
    var = np.stack(
        np.broadcast_arrays(
            np.full(np.shape(sd), sig_a**2),
            np.full(np.shape(sd), sig_a**2),
            sd_var,
        ),
        axis=-1,
    )
    cov = np.einsum("...ik,...k,...jk->...ij", J, var, J)
    return cov + instrument.centring_sigma**2 * np.eye(3)


def to_world(
    T_world_instrument: np.ndarray, points: np.ndarray, cov: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Move instrument-frame points ``(..., 3)`` and covariances ``(..., 3, 3)`` into the world."""
    T = np.asarray(T_world_instrument, dtype=float)
    R = T[:3, :3]
    p = np.asarray(points, dtype=float) @ R.T + T[:3, 3]
    if cov is None:
        return p, None
    return p, R @ np.asarray(cov, dtype=float) @ R.T


@dataclass(frozen=True, eq=False)
class Observations:
    """Observations of prism targets read from a file.

    Each row has either polar readings (``hz``, ``v``, ``sd``) or, when the
    instrument exported only computed coordinates, ``xyz``; missing values are NaN.

    Attributes
    ----------
    point_ids
        Target ids, matched against the robot points.
    hz, v
        ``(n,)`` horizontal and zenith angles (radians).
    sd
        ``(n,)`` slope distances (metres).
    xyz
        ``(n, 3)`` coordinates computed by the instrument in its job frame (metres).
    prism_height
        ``(n,)`` prism heights (metres).
    instrument_height
        Height of the instrument above the station mark (metres).
    station_xyz
        Station coordinates exported with the observations (job frame), if any.
    source
        The file the observations came from.
    lines
        1-based line of each row in ``source``.
    """

    point_ids: tuple[str, ...]
    hz: np.ndarray
    v: np.ndarray
    sd: np.ndarray
    xyz: np.ndarray
    prism_height: np.ndarray
    instrument_height: float = 0.0
    station_xyz: np.ndarray | None = None
    source: str | None = None
    lines: tuple[int, ...] = ()

    def __len__(self) -> int:
        return len(self.point_ids)

    def at(self, k: int) -> str | None:
        """The location of row ``k`` in :attr:`source`, ``"line N"`` (``None`` without lines)."""
        return f"line {self.lines[k]}" if self.lines else None

    def points(
        self, instrument: Instrument, T_world_instrument: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """World points ``(n, 3)`` and their covariances ``(n, 3, 3)``.

        Polar rows are converted with :func:`polar_to_cartesian` in the
        instrument frame and moved by ``T_world_instrument`` (identity when
        ``None``). Coordinate-only rows are taken as they are (the instrument's
        job frame is then the world); their covariance is propagated from the
        polar readings they imply, seen from the station (``station_xyz``, else
        the translation of ``T_world_instrument``).
        """
        T = np.eye(4) if T_world_instrument is None else np.asarray(T_world_instrument, float)
        n = len(self)
        polar = np.isfinite(self.hz) & np.isfinite(self.v) & np.isfinite(self.sd)
        coords = ~polar & np.all(np.isfinite(self.xyz), axis=1)
        bad = ~(polar | coords)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"target {show(self.point_ids[i])} has neither Hz, V and slope distance "
                "nor coordinates",
                self.source,
                self.at(i),
            )
        out = np.zeros((n, 3))
        cov = np.zeros((n, 3, 3))
        if polar.any():
            local = polar_to_cartesian(
                self.hz[polar],
                self.v[polar],
                self.sd[polar],
                self.instrument_height,
                self.prism_height[polar],
            )
            local_cov = polar_covariance(self.hz[polar], self.v[polar], self.sd[polar], instrument)
            out[polar], cov[polar] = to_world(T, local, local_cov)
        if coords.any():
            station = T[:3, 3] if self.station_xyz is None else self.station_xyz
            hz, v, sd = cartesian_to_polar(self.xyz[coords] - station)
            steep = (sd < MIN_DISTANCE_M) | (np.abs(np.sin(v)) < math.sin(MIN_ZENITH_DISTANCE))
            if steep.any():
                i = int(np.flatnonzero(coords)[np.argmax(steep)])
                raise InputError(
                    f"target {show(self.point_ids[i])} lies at or straight above or below the "
                    "station: its coordinates cannot be weighted as a reading",
                    self.source,
                    self.at(i),
                )
            out[coords] = self.xyz[coords]
            cov[coords] = polar_covariance(hz, v, sd, instrument)
        return out, cov


def reading_problem(obs: Observations) -> tuple[int, str] | None:
    """The first reading beyond what a total station measures, and why.

    Parameters
    ----------
    obs
        Readings as read from a file: polar rows (Hz, V, slope distance) or
        coordinate rows (x, y, z), with prism heights.

    Returns
    -------
    ``(row, message)`` of the first offending row, or ``None``: a value that is
    not finite where it is given, a slope distance below :data:`MIN_DISTANCE_M` or
    beyond :data:`MAX_DISTANCE_M`, an angle beyond a full turn, a zenith angle within
    :data:`MIN_ZENITH_DISTANCE` of straight up or down, a coordinate beyond
    :data:`MAX_COORDINATE_M`, a prism height beyond :data:`MAX_HEIGHT_M`.
    """
    polar = ~np.isnan(obs.hz) | ~np.isnan(obs.v) | ~np.isnan(obs.sd)
    turn = 2.0 * math.pi
    with np.errstate(invalid="ignore"):
        sin_v = np.abs(np.sin(obs.v))
        checks = [
            (~np.isfinite(obs.prism_height), lambda k: "the prism height is not finite"),
            (
                np.abs(obs.prism_height) > MAX_HEIGHT_M,
                lambda k: f"prism height {obs.prism_height[k]:.6g} m is beyond {MAX_HEIGHT_M:g} m",
            ),
            (
                polar & ~(np.isfinite(obs.hz) & np.isfinite(obs.v) & np.isfinite(obs.sd)),
                lambda k: "needs Hz, V and slope distance, all finite",
            ),
            (
                polar & ((obs.sd < MIN_DISTANCE_M) | (obs.sd > MAX_DISTANCE_M)),
                lambda k: (
                    f"slope distance {obs.sd[k]:.6g} m is not between {MIN_DISTANCE_M:g} and "
                    f"{MAX_DISTANCE_M:g} m"
                ),
            ),
            (
                polar & ((np.abs(obs.hz) > turn) | (obs.v < 0) | (obs.v > turn)),
                lambda k: (
                    f"angles Hz = {obs.hz[k] / GON:.6g} gon, V = {obs.v[k] / GON:.6g} gon "
                    "lie beyond a full turn (Hz within +-400 gon, V within 0 to 400 gon)"
                ),
            ),
            (
                polar & (sin_v < math.sin(MIN_ZENITH_DISTANCE)),
                lambda k: (
                    f"zenith angle V = {obs.v[k] / GON:.6g} gon points straight up or "
                    f"down (within {MIN_ZENITH_DISTANCE / GON:g} gon), where Hz is not defined"
                ),
            ),
            (
                ~polar & ~np.all(np.isfinite(obs.xyz), axis=1),
                lambda k: "needs Hz, V and slope distance, or x, y, z, all finite",
            ),
            (
                ~polar & (np.abs(obs.xyz).max(axis=1) > MAX_COORDINATE_M),
                lambda k: f"a coordinate is beyond {MAX_COORDINATE_M:g} m",
            ),
        ]
    first: tuple[int, str] | None = None
    for mask, message in checks:
        hits = np.flatnonzero(mask)
        if hits.size and (first is None or hits[0] < first[0]):
            k = int(hits[0])
            first = (k, f"point {show(obs.point_ids[k])}: {message(k)}")
    return first
