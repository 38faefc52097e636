"""What fabflow keeps on the objects it exchanges with Rhino and COMPAS.

A Rhino object carries fabflow's data as user text (``Attributes > User Text``
in Rhino, ``rs.SetUserText`` in a script); a COMPAS element record carries the
same keys as plain fields. The element frame travels exactly as a 4x4 matrix,
so a file fabflow wrote reads back with the same poses; an object without a
frame (drawn by hand) gets one from its geometry
(:func:`fabflow.design.box_pose.box_pose_from_corners`).

Units are metres in both directions; a Rhino file in millimetres is scaled
when it is read.
"""

from __future__ import annotations

USER_TEXT_PREFIX = "fabflow."
"""Every user-text key fabflow reads or writes starts with this."""

KEY_ID = "fabflow.id"
KEY_TYPE = "fabflow.type"
KEY_LAYER = "fabflow.layer"
KEY_PART = "fabflow.part"
KEY_SUPPORTS = "fabflow.supports"
"""Comma-separated ids of the elements this one rests on."""
KEY_ROBOT_BUILT = "fabflow.robot_built"
"""``"true"`` or ``"false"``."""
KEY_FRAME = "fabflow.frame"
"""T_world_element as 16 numbers, row by row, in metres (JSON list)."""
KEY_STATION = "fabflow.station"
"""The station id of the plan that builds the element (exports only)."""
KEY_ATTRIBUTES = "fabflow.attributes"
"""The element's extra attributes as a JSON object (exports only)."""

LAYER_ROOT = "fabflow"
"""Root layer of an exported .3dm file: ``fabflow::elements::<station>::<part>``,
``fabflow::as_built``, ``fabflow::stations``, ``fabflow::anchors``,
``fabflow::setups``."""

KEY_EXTENTS = "fabflow.extents"
"""A box element's size (length, width, height) in metres as a JSON list (exports
only): with :data:`KEY_FRAME` it gives the box exactly, where the brep's corners
give it to rounding."""

LAYER_SEPARATOR = "::"
"""Between the names of a layer path, as Rhino writes it."""
LAYER_ELEMENTS = "elements"
"""Below the root: one layer per station, one per part below it."""
LAYER_UNPLANNED = "unplanned"
"""The station layer of elements no work package builds (hand-built, or no plan)."""
LAYER_NO_PART = "no_part"
"""The part layer of elements without a part (print paths, task points)."""
LAYER_AS_BUILT = "as_built"
LAYER_STATIONS = "stations"
LAYER_ANCHORS = "anchors"
LAYER_SETUPS = "setups"

COMPAS_FORMAT_KEY = "fabflow"
"""The key of an exported COMPAS JSON document that holds its format version."""
COMPAS_FORMAT_VERSION = 1
