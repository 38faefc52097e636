"""UWB ranging simulator: error model, per-anchor bias, calibration campaign, paper layouts.

The error model follows the UWB paper (seeds/003, section 3.3.1) and common
two-way-ranging behaviour: a measured range is

``y = a + b * d + sigma(d) * n + e_nlos``

with ``d`` the true tag-anchor distance (metres), ``(a, b)`` an unknown linear
bias per anchor (what the ranging calibration fits), ``sigma(d)`` a noise
standard deviation growing with distance and ``e_nlos`` a positive excess
delay on a small fraction of ranges (non-line-of-sight).

The trajectories of a moving tag are :mod:`fabflow.sensors.uwb_trajectories`';
the paper's are :func:`paper_trajectories`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from fabflow.errors import InputError
from fabflow.positioning.boxes import Boxes, segments_clear
from fabflow.sensors.uwb_multipath import MultipathField, draw_multipath
from fabflow.sensors.uwb_trajectories import PlanarTrajectory


@dataclass(frozen=True)
class UwbErrorModel:
    """How a simulated UWB range deviates from the true distance.

    Attributes
    ----------
    sigma_1m
        White range noise standard deviation at 1 m (metres). 0.033: the DW1000
        chip's line-of-sight precision, 10 cm at three sigma (Time Domain, *P330
        data sheet*, 6.4.1), the chip of most modules like paper 003's (unnamed).
    growth
        Increase of that standard deviation per metre of range (m/m; 0: the
        precision is stated for the chip's whole range).
    nlos_prob
        Probability that a line-of-sight range carries an NLOS excess.
    nlos_excess
        (low, high) bounds of the uniform NLOS excess (metres, positive).
    nlos_prob_occluded
        Probability of an NLOS excess on a range whose line of sight is blocked.
    offset_range
        (low, high) bounds of the uniform per-anchor range offset ``a`` (metres).
    scale_sigma
        Standard deviation of the per-anchor scale ``b - 1``.
    multipath_sigma, multipath_tau
        Optional time-correlated error per link (first-order Gauss-Markov, standard
        deviation in metres, correlation time in seconds), as multipath produces
        while a tag moves slowly. Off by default (the paper's error model has none);
        used to test how much of a filter's gain survives correlated errors.
    multipath_field_sigma, multipath_field_length, multipath_field_growth
        Optional position-dependent multipath per anchor
        (:mod:`fabflow.sensors.uwb_multipath`): an error that stays while the tag
        stays and changes over ``multipath_field_length`` metres as it moves
        (standard deviation in metres at 1 m, growing by the fraction
        ``multipath_field_growth`` of it per metre of range, as the default
        noise does). Drawn with the installation's bias (:func:`draw_bias`);
        a calibration campaign meets it too. Off by default.
    material_delay, material_delay_spread
        Excess range per metre of material the line of sight passes through
        (``sqrt(eps_r) - 1``: a signal slows to ``c / sqrt(eps_r)`` inside; 0.41
        for wood of relative permittivity 2, about 1.5-2.5 at UWB's 3-7 GHz
        depending on its moisture and grain, Torgovnikov 1993, *Dielectric
        Properties of Wood and Wood-Based Materials*), and the relative standard
        deviation of that factor at one site (moisture, species). The estimator
        corrects the excess it predicts from the design and counts the spread
        (:func:`material_excess`). Off by default.
    """

    sigma_1m: float = 0.033
    growth: float = 0.0
    nlos_prob: float = 0.02
    nlos_excess: tuple[float, float] = (0.3, 1.5)
    nlos_prob_occluded: float = 0.5
    offset_range: tuple[float, float] = (0.05, 0.25)
    scale_sigma: float = 0.005
    multipath_sigma: float = 0.0
    multipath_tau: float = 1.0
    multipath_field_sigma: float = 0.0
    multipath_field_length: float = 0.5
    multipath_field_growth: float = 0.2
    material_delay: float = 0.0
    material_delay_spread: float = 0.25

    @classmethod
    def gaussian(cls, sigma: float) -> UwbErrorModel:
        """Unbiased Gaussian noise of constant standard deviation ``sigma``, no outliers."""
        return cls(
            sigma_1m=sigma,
            growth=0.0,
            nlos_prob=0.0,
            nlos_prob_occluded=0.0,
            offset_range=(0.0, 0.0),
            scale_sigma=0.0,
        )

    def without_outliers(self) -> UwbErrorModel:
        """The same model with the NLOS outliers switched off."""
        return replace(self, nlos_prob=0.0, nlos_prob_occluded=0.0)

    def sigma(self, distance: np.ndarray | float) -> np.ndarray:
        """Range noise standard deviation (metres) at ``distance`` (metres)."""
        d = np.asarray(distance, dtype=float)
        return np.maximum(self.sigma_1m + self.growth * (d - 1.0), 0.25 * self.sigma_1m)

    def total_sigma(self, distance: np.ndarray | float) -> np.ndarray:
        """Standard deviation (metres) at ``distance`` (metres) of the white noise and both
        multipath terms: what a moving tag's ranges, taken as independent, weigh by."""
        white, field = self.sigma(distance), self.field_sigma(distance)
        return np.sqrt(white**2 + field**2 + self.multipath_sigma**2)

    def field_sigma(self, distance: np.ndarray | float) -> np.ndarray:
        """Standard deviation (metres) of the position-dependent multipath at ``distance``
        (metres): ``multipath_field_sigma`` at 1 m, growing by ``multipath_field_growth``
        of that per metre (a weaker first path, more reflectors along a longer one),
        never below a quarter of it."""
        d = np.asarray(distance, dtype=float)
        scale = np.maximum(1.0 + self.multipath_field_growth * (d - 1.0), 0.25)
        return self.multipath_field_sigma * scale


@dataclass(frozen=True)
class AnchorBias:
    """An installation's systematic range errors: per anchor a linear bias, measured
    mean ``= offset + scale * distance``, and optionally the position-dependent
    multipath (:class:`~fabflow.sensors.uwb_multipath.MultipathField`)."""

    offset: np.ndarray
    scale: np.ndarray
    multipath: MultipathField | None = None

    @classmethod
    def none(cls, n_anchors: int) -> AnchorBias:
        """No bias (offset 0, scale 1)."""
        return cls(offset=np.zeros(n_anchors), scale=np.ones(n_anchors))

    def take(self, index: np.ndarray) -> AnchorBias:
        """The bias of the anchors ``index`` (integer indices), in that order."""
        field = None if self.multipath is None else self.multipath.take(index)
        return AnchorBias(self.offset[index], self.scale[index], field)


def draw_bias(n_anchors: int, model: UwbErrorModel, rng: np.random.Generator) -> AnchorBias:
    """Draw the unknown per-anchor bias of one UWB installation."""
    lo, hi = model.offset_range
    offset = rng.uniform(lo, hi, n_anchors)
    scale = 1.0 + model.scale_sigma * rng.standard_normal(n_anchors)
    multipath = None
    if model.multipath_field_sigma > 0:
        multipath = draw_multipath(n_anchors, 1.0, model.multipath_field_length, rng)
    return AnchorBias(offset=offset, scale=scale, multipath=multipath)


@dataclass(frozen=True)
class SimulatedRanges:
    """Simulated ranges and the truth behind them.

    Attributes
    ----------
    ranges
        Measured ranges (..., n_anchors), metres.
    true_ranges
        True distances, same shape.
    nlos
        Boolean mask of ranges that carry an NLOS excess.
    """

    ranges: np.ndarray
    true_ranges: np.ndarray
    nlos: np.ndarray


def simulate_ranges(
    anchors: np.ndarray,
    tags: np.ndarray,
    model: UwbErrorModel,
    rng: np.random.Generator,
    bias: AnchorBias | None = None,
    occluded: np.ndarray | None = None,
    dt: float | None = None,
    link_excess: np.ndarray | None = None,
) -> SimulatedRanges:
    """Simulate UWB ranges from tag positions to every anchor.

    Parameters
    ----------
    anchors
        (n_anchors, dim) anchor positions (metres).
    tags
        (..., dim) tag positions in the same frame (metres).
    model
        The error model.
    rng
        Random generator.
    bias
        Per-anchor bias; none when omitted.
    occluded
        Optional boolean mask (..., n_anchors) of blocked lines of sight, which get
        ``model.nlos_prob_occluded`` instead of ``model.nlos_prob``.
    dt
        Sample spacing (s) along axis 0 of ``tags``; needed when the model has a
        time-correlated multipath error.
    link_excess
        Optional excess range (metres, broadcastable to ``(..., n_anchors)``) each
        range carries, e.g. the material its line of sight crosses
        (:func:`material_excess`).
    """
    anchors = np.asarray(anchors, dtype=float)
    tags = np.asarray(tags, dtype=float)
    if tags.ndim >= 2 and tags.strides[0] == 0:
        # a standing tag (one position broadcast over the epochs): its distances once
        d_once = np.linalg.norm(tags[0][..., None, :] - anchors, axis=-1)
        d, sigma = (
            np.broadcast_to(a, (len(tags), *a.shape)) for a in (d_once, model.sigma(d_once))
        )
        d = d.copy()
    else:
        d = np.linalg.norm(tags[..., None, :] - anchors, axis=-1)
        sigma = model.sigma(d)
    if bias is None:
        bias = AnchorBias.none(anchors.shape[0])
    p = np.full(d.shape, model.nlos_prob)
    if occluded is not None:
        p = np.where(occluded, model.nlos_prob_occluded, p)
    nlos = rng.random(d.shape) < p
    excess = np.where(nlos, rng.uniform(*model.nlos_excess, d.shape), 0.0)
    noise = sigma * rng.standard_normal(d.shape)
    y = bias.offset + bias.scale * d + noise + excess
    if link_excess is not None:
        y = y + np.asarray(link_excess, dtype=float)
    if bias.multipath is not None:  # drawn with unit deviation, scaled to the range's
        y = y + bias.multipath(tags) * model.field_sigma(d)
    if model.multipath_sigma > 0:
        if dt is None:
            raise InputError("a multipath error model needs the sample spacing 'dt'")
        from scipy.signal import lfilter

        phi = float(np.exp(-dt / model.multipath_tau))
        drive = model.multipath_sigma * np.sqrt(1 - phi**2) * rng.standard_normal(d.shape)
        drive[0] = model.multipath_sigma * rng.standard_normal(d.shape[1:])
        y = y + lfilter([1.0], [1.0, -phi], drive, axis=0)
    return SimulatedRanges(ranges=y, true_ranges=d, nlos=nlos)


def calibration_campaign(
    model: UwbErrorModel,
    bias: AnchorBias,
    rng: np.random.Generator,
    distances: np.ndarray | None = None,
    samples: int = 200,
) -> tuple[np.ndarray, np.ndarray]:
    """Simulate the paper's line-of-sight ranging calibration (section 3.3.1).

    A tag is placed at known distances from each anchor (default 0.5 to 10 m in
    0.5 m steps) and ``samples`` ranges are recorded at each.

    Returns
    -------
    distances
        (k,) true distances (metres).
    measured
        (k, samples, n_anchors) measured ranges (metres).
    """
    if distances is None:
        distances = np.arange(0.5, 10.0 + 1e-9, 0.5)
    distances = np.asarray(distances, dtype=float)
    n = bias.offset.shape[0]
    d = np.broadcast_to(distances[:, None, None], (distances.size, samples, n))
    noise = model.sigma(d) * rng.standard_normal(d.shape)
    measured = bias.offset + bias.scale * d + noise
    if model.multipath_field_sigma > 0:  # each spot's multipath, the same for its samples
        spot = model.field_sigma(distances)[:, None] * rng.standard_normal((distances.size, n))
        measured = measured + spot[:, None, :]
    return distances, measured


def segments_occluded(
    starts: np.ndarray, ends: np.ndarray, T_world_boxes: np.ndarray, extents: np.ndarray
) -> np.ndarray:
    """Whether each line segment passes through any of a set of oriented boxes.

    Parameters
    ----------
    starts, ends
        (m, 3) segment end points in the world (metres).
    T_world_boxes
        (k, 4, 4) box centre frames in the world.
    extents
        (k, 3) box side lengths along the box axes (metres).

    Returns
    -------
    np.ndarray
        (m,) boolean.
    """
    if len(T_world_boxes) == 0:
        return np.zeros(np.shape(starts)[0], dtype=bool)
    boxes = Boxes(np.asarray(T_world_boxes, dtype=float), np.asarray(extents, dtype=float))
    return ~segments_clear(starts, ends, boxes)


def material_excess(
    model: UwbErrorModel, inside: np.ndarray, rng: np.random.Generator | None = None
) -> np.ndarray:
    """Excess range (metres) of links whose line of sight crosses ``inside`` metres of
    material: ``material_delay * inside``, with each link's factor drawn from the
    spread when ``rng`` is given (the truth: each link crosses other logs, of their
    own moisture and grain), the nominal one otherwise (the prediction)."""
    inside = np.asarray(inside, dtype=float)
    factor = np.full(inside.shape, model.material_delay)
    if rng is not None and model.material_delay > 0:
        spread = model.material_delay_spread * rng.standard_normal(inside.shape)
        factor = np.maximum(0.0, factor * (1.0 + spread))
    return factor * inside


def ranging_schedule(
    duration: float, rate_hz: float, n_anchors: int, n_tags: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Timestamps of a two-way-ranging schedule: rounds at ``rate_hz``, ranges staggered.

    Each round ranges every (tag, anchor) pair in turn, evenly spread over the
    round, so every range has its own timestamp.

    Returns
    -------
    t
        (n_rounds, n_tags, n_anchors) timestamps (s).
    tag_index, anchor_index
        Index arrays of the same shape.
    """
    n_rounds = int(np.floor(duration * rate_hz))
    k = n_tags * n_anchors
    slot = np.arange(k).reshape(n_tags, n_anchors) / (k * rate_hz)
    t = np.arange(n_rounds)[:, None, None] / rate_hz + slot[None]
    tag_index = np.broadcast_to(np.arange(n_tags)[None, :, None], t.shape)
    anchor_index = np.broadcast_to(np.arange(n_anchors)[None, None, :], t.shape)
    return t, tag_index, anchor_index


# The paper's layouts (seeds/003, sections 4.1 and 4.2), in metres.
PAPER_ANCHORS_3D = np.array(
    [[0.0, 0.0, 1.00], [4.80, 0.0, 1.00], [4.80, 6.00, 1.00], [0.0, 6.00, 3.20]]
)
"""Table 2 layout: A1..A4."""
PAPER_POINTS_3D = np.array(
    [
        [1.85, 1.70, 2.00],
        [1.85, 3.20, 2.00],
        [0.75, 3.80, 2.20],
        [2.25, 3.80, 2.20],
        [1.85, 1.70, 2.40],
        [1.85, 3.20, 2.40],
    ]
)
"""Table 2 test points."""
PAPER_ANCHORS_2D = np.array(
    [[0.0, 0.0, 2.20], [6.60, 0.0, 2.20], [6.60, 7.00, 2.20], [0.0, 7.00, 2.20]]
)
"""The 6.6 x 7.0 m layout of section 4.1.1, anchors at 2.20 m (corners assumed; the paper
gives only the extent)."""
PAPER_POINTS_2D = np.array(
    [
        [1.60, 1.96],
        [1.60, 3.46],
        [1.60, 4.96],
        [2.35, 1.96],
        [2.35, 4.96],
        [3.10, 1.96],
        [3.10, 3.46],
        [3.10, 4.96],
    ]
)
"""Table 1 test points."""


def paper_trajectories() -> dict[str, list[PlanarTrajectory]]:
    """The moving experiments of the paper as simulated trajectories.

    ``rect2d`` (table 3: 1.5 x 3.0 m rectangle at 2.10/2.20/2.30 m, 2D layout),
    ``line3d`` (table 4: straight line at 1.60/2.00/2.40 m), ``rect3d`` (table 5:
    rectangle at 2.00/2.10/2.20 m) and ``u`` (table 7: U-shape driven by the
    platform, tag at 2.0 m, 2D layout). The paper gives the shapes and heights,
    not their placement; they are centred in the anchor area here.
    """
    rect3 = np.array([[1.65, 1.5], [3.15, 1.5], [3.15, 4.5], [1.65, 4.5], [1.65, 1.6]])
    rect2 = rect3 + np.array([0.9, 0.5])
    line = np.array([[1.2, 1.5], [3.6, 4.5]])
    u = np.array([[2.0, 5.0], [2.0, 2.0], [4.4, 2.0], [4.4, 5.0]])
    return {
        "rect2d": [PlanarTrajectory(rect2, h, name=f"rect2d H={h:.2f}") for h in (2.1, 2.2, 2.3)],
        "line3d": [PlanarTrajectory(line, h, name=f"line3d H={h:.2f}") for h in (1.6, 2.0, 2.4)],
        "rect3d": [PlanarTrajectory(rect3, h, name=f"rect3d H={h:.2f}") for h in (2.0, 2.1, 2.2)],
        "u": [PlanarTrajectory(u, 2.0, name="u H=2.00")],
    }
