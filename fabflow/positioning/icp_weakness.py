"""The least constrained direction of a registered pose, read off its information.

A registration against a corridor or a single wall is well determined across
it and not along it; the smallest eigenvalue of the information (rotations
scaled by the constraints' lever arm) names that direction and its sigma.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

AXES = ("x", "y", "z")


@dataclass(frozen=True, eq=False)
class WeakDirection:
    """The least constrained direction of a pose, read off its information.

    Translations (metres) and rotations (radians) are made comparable by the
    ``lever``: a rotation counts as the displacement it causes at that distance.

    Attributes
    ----------
    vector
        ``(6,)`` unit vector over ``[dx, dy, dz, lever rx, lever ry, lever rz]``.
    sigma
        Standard deviation of the pose along ``vector`` (metres; for a rotation the
        displacement at ``lever``).
    lever
        ``sqrt(tr(I_rot) / tr(I_trans))`` of the information ``I`` (metres): the RMS
        lever arm of the constraints, at which rotation and translation are on
        average equally well determined.
    translation_share
        ``|vector[:3]|^2``: 1 for a pure translation, 0 for a pure rotation.
    label
        ``"translation x"`` (``y``, ``z``) or ``"rotation about z (heading)"``
        (``x (roll)``, ``y (pitch)``): the part and axis that dominate ``vector``.
    condition
        Smallest over largest eigenvalue of the scaled information.
    eigenvalues
        ``(6,)`` eigenvalues of the scaled information, ascending (1/m^2).
    """

    vector: FloatArray
    sigma: float
    lever: float
    translation_share: float
    label: str
    condition: float
    eigenvalues: FloatArray


def weakest_direction(information: ArrayLike) -> WeakDirection:
    """The eigenvector of the smallest eigenvalue of the (scaled) 6x6 information.

    Parameters
    ----------
    information
        6x6 information over ``[dx, dy, dz, rx, ry, rz]`` (1/m^2, 1/rad^2), e.g.
        :attr:`IcpResult.information`.
    """
    info = np.asarray(information, dtype=float).reshape(6, 6)
    t_tr = float(np.trace(info[:3, :3]))
    lever = float(np.sqrt(np.trace(info[3:, 3:]) / t_tr)) if t_tr > 0 else 1.0
    lever = lever if np.isfinite(lever) and lever > 0 else 1.0
    scale = np.r_[np.ones(3), np.full(3, 1.0 / lever)]
    scaled = info * np.outer(scale, scale)
    evals, evecs = np.linalg.eigh(0.5 * (scaled + scaled.T))
    v = evecs[:, 0] * (1.0 if evecs[np.argmax(np.abs(evecs[:, 0])), 0] >= 0 else -1.0)
    share = float(np.sum(v[:3] ** 2))
    if share >= 0.5:
        label = f"translation {AXES[int(np.argmax(np.abs(v[:3])))]}"
    else:
        axis = int(np.argmax(np.abs(v[3:])))
        label = f"rotation about {AXES[axis]} ({('roll', 'pitch', 'heading')[axis]})"
    top = max(float(evals[-1]), 1e-300)
    return WeakDirection(
        vector=v,
        sigma=float(1.0 / np.sqrt(max(float(evals[0]), 1e-300))),
        lever=lever,
        translation_share=share,
        label=label,
        condition=float(max(float(evals[0]), 0.0) / top),
        eigenvalues=evals,
    )
