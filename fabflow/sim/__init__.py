"""Simulated construction runs of whole projects, and Monte Carlo studies of them on Dask."""
