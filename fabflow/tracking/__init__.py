"""Printing with a hydraulic excavator: online end-effector estimation and closed-loop tracking.

Paper 000's loop (``fabflow track``): the reference path of a print
(:mod:`~fabflow.tracking.reference`), the machine and its sensors
(:mod:`fabflow.sensors.excavator`), LiDAR scan-to-map ICP
(:mod:`~fabflow.tracking.lidar`), the EKF fusing it with the kinematics
(:class:`~fabflow.positioning.icp_fusion.IcpKinematicsFilter`), the controller
(:mod:`~fabflow.tracking.controller`), the loop (:mod:`~fabflow.tracking.run`)
and its outputs (:mod:`~fabflow.tracking.report`).
"""
