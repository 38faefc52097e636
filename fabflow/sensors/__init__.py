"""Sensor models and simulators: UWB ranging, IMU, LiDAR, total station, the site scene.

Everything here produces what a sensor would measure, from true poses and a
seeded random generator; the estimators that turn measurements into poses are
in :mod:`fabflow.positioning`.
"""
