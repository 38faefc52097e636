"""Where the robot is: UWB, robotic total station and LiDAR ICP localization."""

from fabflow.positioning.result import BasePose

__all__ = ["BasePose"]
