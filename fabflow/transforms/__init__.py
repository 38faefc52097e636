"""Poses, frame graph with uncertainty, vendor conventions (KUKA, ABB, UR)."""
