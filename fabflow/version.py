"""The fabflow version: one literal, read by the package metadata and by the outputs."""

__version__ = "0.1.0"
