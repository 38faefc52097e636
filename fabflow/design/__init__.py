"""What to build: elements (blocks, print paths, task points) in the world frame.

- :mod:`~fabflow.design.elements`: the element model, JSON in and out.
- :mod:`~fabflow.design.specs`: the element sources of a project file.
- :mod:`~fabflow.design.generate`: every element of a project's sources.
- :mod:`~fabflow.design.cabin`: the parametric log cabin.
- :mod:`~fabflow.design.print_path`: print paths from DXF drawings or meshes,
  tool frames and constant-speed Hermite sampling.
- :mod:`~fabflow.design.dxf_in` / :mod:`~fabflow.design.site_plan`: DXF in and out.
- :mod:`~fabflow.design.supports`: which block rests on which.
- :mod:`~fabflow.design.geometry`: element meshes.

Import from the modules; this package itself loads nothing, so that using the
element model does not pull in ezdxf, trimesh and shapely.
"""
