"""Position-dependent multipath: a UWB range error that stays while the tag stays.

A UWB range is the first path's time of flight. Reflections from the floor,
walls and the structure arriving close behind it shift the detected first
path, by an amount that depends on where the tag stands relative to the
reflectors: it does not change while the tag stands still, so averaging a
static tag's ranges does not remove it, and it changes over a few decimetres
as the tag moves, which a moving tag sees as an error correlated in time
(correlation time about the correlation length over the speed). This is why a
static fix averaged over hundreds of epochs still errs by centimetres (paper
003, tables 1, 2 and 6) and why a filter cannot average a moving tag's error
down to the white noise floor (tables 3-5, 7).

The field of each anchor is a stationary Gaussian random field over the tag
position with a squared-exponential covariance
``sigma^2 exp(-|dx|^2 / (2 L^2))``, drawn by random Fourier features (Rahimi
and Recht 2007): ``f(x) = sigma sqrt(2 / K) sum_k cos(w_k . x + b_k)`` with
``w_k ~ N(0, I / L^2)`` and ``b_k ~ U(0, 2 pi)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

COMPONENTS = 64
"""Fourier features per anchor: enough for the field's values to be close to
Gaussian (the sum of 64 cosines) at small cost."""


@dataclass(frozen=True)
class MultipathField:
    """The multipath range error of each anchor over the tag position.

    Attributes
    ----------
    frequencies
        ``(n_anchors, K, 3)`` angular wave vectors (rad/m).
    phases
        ``(n_anchors, K)`` phases (rad).
    sigma
        Standard deviation of the error at a point (metres).
    """

    frequencies: np.ndarray
    phases: np.ndarray
    sigma: float

    def take(self, index: np.ndarray) -> MultipathField:
        """The field of the anchors ``index`` (integer indices), in that order."""
        return MultipathField(self.frequencies[index], self.phases[index], self.sigma)

    def __call__(self, tags: np.ndarray) -> np.ndarray:
        """The error (metres) of the range from each tag position to each anchor.

        Parameters
        ----------
        tags
            ``(..., dim)`` tag positions (metres), ``dim`` 2 or 3 (a plane's
            field is the 3-D field's section at height 0).

        Returns
        -------
        numpy.ndarray
            ``(..., n_anchors)``.
        """
        x = np.asarray(tags, dtype=float)
        w = self.frequencies[..., : x.shape[-1]]
        arg = np.einsum("...d,akd->...ak", x, w) + self.phases
        k = self.phases.shape[-1]
        return self.sigma * np.sqrt(2.0 / k) * np.cos(arg).sum(axis=-1)


def draw_multipath(
    n_anchors: int,
    sigma: float,
    length: float,
    rng: np.random.Generator,
    components: int = COMPONENTS,
) -> MultipathField:
    """Draw the multipath field of one installation (one per anchor).

    Parameters
    ----------
    n_anchors
        Number of anchors.
    sigma
        Standard deviation of the range error at a point (metres).
    length
        Correlation length of the field (metres): the tag moves about this far
        before the error changes.
    rng
        Random generator.
    components
        Fourier features per anchor.
    """
    if sigma < 0 or length <= 0 or components < 1:
        raise ValueError("multipath sigma must be >= 0, its length and components > 0")
    frequencies = rng.standard_normal((n_anchors, components, 3)) / length
    phases = rng.uniform(0.0, 2.0 * np.pi, (n_anchors, components))
    return MultipathField(frequencies, phases, float(sigma))
