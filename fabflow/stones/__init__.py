"""Dry-stone walls from found stones: scans to objects, grasps, programs (paper 002)."""
