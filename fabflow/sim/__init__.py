"""Sensor simulators, simulated construction runs and Monte Carlo studies."""
