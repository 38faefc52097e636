"""Named errors of the transforms layer.

All derive from :class:`fabflow.errors.InputError`: a bad rotation, quaternion or
frame name almost always comes from user input (a project file, a measurement
file, a robot program) and is reported as one clear message.
"""

from __future__ import annotations

from fabflow.errors import InputError


class RotationError(InputError):
    """A rotation matrix is not orthonormal with determinant +1 (within tolerance)."""


class QuaternionError(RotationError):
    """A quaternion is zero, not finite, or too far from unit norm to be normalized."""


class FrameError(InputError):
    """A frame-graph query or edit cannot be carried out."""


class UnknownFrameError(FrameError):
    """A frame name is not in the frame graph."""


class FrameCycleError(FrameError):
    """Adding an edge would close a cycle (the frame graph must stay a tree)."""


class DisconnectedFramesError(FrameError):
    """Two frames exist but are not connected by any chain of poses."""


class DegenerateFrameError(InputError):
    """Three points do not define a frame (coincident or collinear points)."""
