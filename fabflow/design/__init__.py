"""What to build: elements (blocks, print paths, task points) in the world frame.

- :func:`generate_elements` runs every ``elements`` source of a project.
- :mod:`~fabflow.design.cabin`: the parametric log cabin.
- :mod:`~fabflow.design.print_path`: print paths from DXF drawings or meshes,
  tool frames and constant-speed Hermite sampling.
- :mod:`~fabflow.design.dxf_in` / :mod:`~fabflow.design.site_plan`: DXF in and out.
- :mod:`~fabflow.design.supports`: which block rests on which.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from fabflow.design.elements import Element, element_poses, elements_from_json, elements_to_json

if TYPE_CHECKING:
    from fabflow.design.cabin import CabinBlocks, cabin_blocks, cabin_elements
    from fabflow.design.dxf_in import Contour, DxfWarning, read_dxf_contours
    from fabflow.design.generate import (
        generate_elements,
        task_point_elements,
        with_block_supports,
    )
    from fabflow.design.geometry import blocks_mesh, element_mesh
    from fabflow.design.print_path import (
        LayerPath,
        SampledPath,
        element_tool_frames,
        order_contours,
        print_path_elements,
        sample_hermite,
        sample_print_path,
        slice_mesh,
        tool_frames,
    )
    from fabflow.design.site_plan import site_plan_document, write_site_plan
    from fabflow.design.supports import compute_supports, max_overlap_volume

# Everything but the element model is imported on first use, so that importing
# ``fabflow.design.elements`` does not pull in ezdxf, trimesh and shapely.
_LAZY = {
    "CabinBlocks": "cabin",
    "cabin_blocks": "cabin",
    "cabin_elements": "cabin",
    "Contour": "dxf_in",
    "DxfWarning": "dxf_in",
    "read_dxf_contours": "dxf_in",
    "blocks_mesh": "geometry",
    "element_mesh": "geometry",
    "generate_elements": "generate",
    "task_point_elements": "generate",
    "with_block_supports": "generate",
    "LayerPath": "print_path",
    "SampledPath": "print_path",
    "element_tool_frames": "print_path",
    "order_contours": "print_path",
    "print_path_elements": "print_path",
    "sample_hermite": "print_path",
    "sample_print_path": "print_path",
    "slice_mesh": "print_path",
    "tool_frames": "print_path",
    "site_plan_document": "site_plan",
    "write_site_plan": "site_plan",
    "compute_supports": "supports",
    "max_overlap_volume": "supports",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(f"fabflow.design.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'fabflow.design' has no attribute {name!r}")


__all__ = [
    "CabinBlocks",
    "Contour",
    "DxfWarning",
    "Element",
    "LayerPath",
    "SampledPath",
    "blocks_mesh",
    "cabin_blocks",
    "cabin_elements",
    "compute_supports",
    "element_mesh",
    "element_poses",
    "element_tool_frames",
    "elements_from_json",
    "elements_to_json",
    "generate_elements",
    "max_overlap_volume",
    "order_contours",
    "print_path_elements",
    "read_dxf_contours",
    "sample_hermite",
    "sample_print_path",
    "site_plan_document",
    "slice_mesh",
    "task_point_elements",
    "tool_frames",
    "with_block_supports",
    "write_site_plan",
]
