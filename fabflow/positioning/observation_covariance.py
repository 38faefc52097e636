"""Observation covariances in the two shapes the adjustments need, with fast solves.

Block-diagonal (the 3x3 covariance of each measured point) or diagonal plus a
low-rank part (ranges sharing an anchor's calibration error), so that
:func:`fabflow.positioning.adjustment_tests.adjustment_test` tests thousands of
observations in linear time (Woodbury's identity for the low-rank part).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Covariance:
    """An observation covariance ``Q = diag(d) + U diag(s) U^T`` or block-diagonal.

    Attributes
    ----------
    diag
        (m,) variances of the independent part (m^2).
    low_rank
        (m, k) columns ``U`` of errors shared by groups of observations (e.g. an
        indicator per anchor), or ``None``.
    low_rank_var
        (k,) variances of the shared errors.
    blocks
        (m // b, b, b) covariance blocks of consecutive observations (e.g. the 3x3
        covariance of each measured point); replaces ``diag`` when given.
    """

    diag: np.ndarray | None = None
    low_rank: np.ndarray | None = None
    low_rank_var: np.ndarray | None = None
    blocks: np.ndarray | None = None

    @property
    def size(self) -> int:
        """Number of observations."""
        if self.blocks is not None:
            return int(self.blocks.shape[0] * self.blocks.shape[1])
        assert self.diag is not None
        return int(self.diag.shape[0])

    def solve(self, X: np.ndarray) -> np.ndarray:
        """``Q^-1 X`` for ``X`` of shape (m,) or (m, k).

        A diagonal-plus-low-rank ``Q`` may hold a stack of covariances of one shape
        (``diag`` (..., m), ``low_rank`` (..., m, k), ``low_rank_var`` (..., k): the
        tests of many solutions at once); ``X`` is then (..., m) or (..., m, k).
        """
        X = np.asarray(X, dtype=float)
        if self.blocks is not None:
            vec = X.ndim == 1
            X2 = X[:, None] if vec else X
            b = self.blocks.shape[1]
            Xb = X2.reshape(-1, b, X2.shape[1])
            out = np.linalg.solve(self.blocks, Xb).reshape(X2.shape)
            return out[:, 0] if vec else out
        Di, DU, core = self._woodbury
        vec = X.ndim == Di.ndim
        X2 = X[..., None] if vec else X
        out = Di[..., None] * X2
        if DU is not None and core is not None:
            out = out - DU @ np.linalg.solve(core, np.swapaxes(DU, -1, -2) @ X2)
        return out[..., 0] if vec else out

    @functools.cached_property
    def _woodbury(self) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """``D^-1``, ``D^-1 U`` and ``diag(s)^-1 + U^T D^-1 U`` of Woodbury's identity, made
        once: an adjustment's tests solve with the same ``Q`` several times."""
        assert self.diag is not None
        Di = 1.0 / self.diag
        if self.low_rank is None or self.low_rank_var is None:
            return Di, None, None
        U = self.low_rank
        DU = Di[..., None] * U
        k = U.shape[-1]
        inv_var = 1.0 / np.asarray(self.low_rank_var, dtype=float)
        prior = np.zeros((*inv_var.shape, k))
        prior[..., np.arange(k), np.arange(k)] = inv_var
        return Di, DU, prior + np.swapaxes(U, -1, -2) @ DU

    def inverse_diag(self) -> np.ndarray:
        """The diagonal of ``Q^-1`` (m,)."""
        if self.blocks is not None:
            return np.linalg.inv(self.blocks).diagonal(axis1=1, axis2=2).reshape(-1)
        Di, DU, core = self._woodbury
        if DU is None or core is None:
            return Di
        return Di - np.einsum("ij,ij->i", DU, np.linalg.solve(core, DU.T).T)
