"""What to build: elements (blocks, print paths, task points) in the world frame."""

from fabflow.design.elements import Element, element_poses, elements_from_json, elements_to_json

__all__ = ["Element", "element_poses", "elements_from_json", "elements_to_json"]
