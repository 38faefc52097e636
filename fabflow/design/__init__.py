"""What to build: elements (blocks, print paths, task points) in the world frame.

- :func:`generate_elements` runs every ``elements`` source of a project.
- :mod:`~fabflow.design.cabin`: the parametric log cabin.
- :mod:`~fabflow.design.print_path`: print paths from DXF drawings or meshes,
  tool frames and constant-speed Hermite sampling.
- :mod:`~fabflow.design.dxf_in` / :mod:`~fabflow.design.site_plan`: DXF in and out.
- :mod:`~fabflow.design.supports`: which block rests on which.
"""

from fabflow.design.cabin import CabinBlocks, cabin_blocks, cabin_elements
from fabflow.design.dxf_in import Contour, DxfWarning, read_dxf_contours
from fabflow.design.elements import Element, element_poses, elements_from_json, elements_to_json
from fabflow.design.generate import generate_elements, task_point_elements, with_block_supports
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

__all__ = [
    "CabinBlocks",
    "Contour",
    "DxfWarning",
    "Element",
    "LayerPath",
    "SampledPath",
    "cabin_blocks",
    "cabin_elements",
    "compute_supports",
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
