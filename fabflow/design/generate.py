"""Turn the ``elements`` sources of a project file into :class:`Element` objects."""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fabflow.design.cabin import cabin_block_bound, cabin_elements
from fabflow.design.element_files import file_elements
from fabflow.design.elements import Element
from fabflow.design.print_path import print_path_elements
from fabflow.design.specs import ElementSource, StoneWallSpec, TaskPoint
from fabflow.design.supports import compute_supports
from fabflow.errors import InputError
from fabflow.schema import Limits


def element_count_bound(source: ElementSource) -> float:
    """An upper bound of the elements one ``elements`` entry makes, from the file alone.

    A cabin: :func:`~fabflow.design.cabin.cabin_block_bound`; print paths from a
    drawing: ``n_layers``; from a mesh: ``n_layers`` when given (its height is
    checked when it is read); task points: their number; a file: 0 (its elements
    are counted when it is read).
    """
    if source.cabin is not None:
        return cabin_block_bound(source.cabin)
    if source.print_path is not None:
        spec = source.print_path
        given = spec.dxf is not None or "n_layers" in spec.model_fields_set
        return float(spec.n_layers) if given else 0.0
    if source.stone_wall is not None:
        return float(len(source.stone_wall.slots))
    if source.file is not None:
        return 0.0
    return float(len(source.task_points or ()))


def stone_slot_elements(spec: StoneWallSpec, source_index: int = 0) -> list[Element]:
    """The slots of a stone wall as ``stone`` elements: a found object's target.

    The element's pose is the slot's (centre, x along the wall, z up) and its
    extents the slot's size; the stone that fills it, its geometry and its pose
    come from the scans at build time (``objects.json``).
    """
    return [
        Element(
            id=slot.id,
            type="stone",
            T_world_element=slot.pose.matrix(),
            layer=0,
            robot_built=True,
            extents=np.array(slot.size, dtype=float),
            attributes={"found_object": True, "source_index": source_index},
        )
        for slot in spec.slots
    ]


def task_point_elements(points: list[TaskPoint], source_index: int = 0) -> list[Element]:
    """Task points as ``task_point`` elements (the pose is the tool frame to reach)."""
    return [
        Element(
            id=p.id,
            type="task_point",
            T_world_element=p.pose.matrix(),
            layer=p.layer,
            part=None,
            robot_built=True,
            attributes={"action": p.action, "params": dict(p.params), "source_index": source_index},
        )
        for p in points
    ]


def with_block_supports(
    elements: list[Element], keep: frozenset[str] = frozenset()
) -> list[Element]:
    """Fill in ``supports`` of every block from the geometry of all blocks.

    A block rests on the blocks whose top faces touch its bottom face
    (:func:`fabflow.design.supports.compute_supports`). Blocks whose id is in
    ``keep`` (their supports given in a file) and other elements are returned
    unchanged.
    """
    idx = [i for i, e in enumerate(elements) if e.type == "block"]
    if not idx:
        return list(elements)
    T = np.stack([elements[i].T_world_element for i in idx])
    ext = np.stack([np.asarray(elements[i].extents, dtype=float) for i in idx])
    sup = compute_supports(T, ext)
    ids = np.array([elements[i].id for i in idx], dtype=object)
    out = list(elements)
    for k, i in enumerate(idx):
        if elements[i].id not in keep:
            out[i] = dataclasses.replace(elements[i], supports=tuple(ids[sup[k]].tolist()))
    return out


def generate_elements(
    sources: Sequence[ElementSource],
    source_file: str | Path | None = None,
    limits: Limits | None = None,
) -> list[Element]:
    """Every element of a project's sources, in file order, with unique ids.

    Block ids are ``B0000``, ``B0001``, ... counted over all cabins; print path
    layers are ``P000``, ... counted over all print path sources; task points
    keep their ids from the project file.

    Parameters
    ----------
    sources
        The ``elements`` entries of a project (``project.elements``).
    source_file
        The project file, named in error messages (``project.path``).
    limits
        The project's limits (``project.limits``; default
        :class:`~fabflow.schema.Limits`), checked against what a drawing or mesh
        holds before its layers are made.

    Raises
    ------
    InputError
        When a task point id is used twice or collides with a generated id, or a
        source's drawing or mesh is bad or asks for more work than ``limits``.
    """
    elements: list[Element] = []
    keep: set[str] = set()
    n_blocks = n_paths = 0
    for i, source in enumerate(sources):
        if source.cabin is not None:
            new = cabin_elements(source.cabin, id_start=n_blocks)
            n_blocks += len(new)
        elif source.print_path is not None:
            new = print_path_elements(
                source.print_path, id_start=n_paths, source_index=i, limits=limits
            )
            n_paths += len(new)
        elif source.stone_wall is not None:
            new = stone_slot_elements(source.stone_wall, source_index=i)
        elif source.file is not None:
            max_elements = (limits or Limits()).max_elements - len(elements)
            new, given = file_elements(source.file, i, max(max_elements, 0))
            if given:
                keep.update(e.id for e in new)
        else:
            assert source.task_points is not None
            new = task_point_elements(source.task_points, source_index=i)
        elements.extend(new)
    counts = Counter(e.id for e in elements)
    dup = [k for k, v in counts.items() if v > 1]
    if dup:
        where = next(
            (
                f"elements[{i}].task_points[{j}].id"
                for i, s in enumerate(sources)
                for j, p in enumerate(s.task_points or [])
                if p.id in dup
            ),
            None,
        )
        if where is None:
            i = next(
                (
                    e.attributes["source_index"]
                    for e in elements
                    if e.id == dup[0] and "source_index" in e.attributes
                ),
                None,
            )
            where = None if i is None else f"elements[{i}].file"
        raise InputError(
            f"element id {dup[0]!r} is used twice (ids of task points and of file elements "
            "must be unique and differ from generated ids such as B0000 and P000)",
            source_file,
            where,
        )
    return with_block_supports(elements, frozenset(keep))
