"""fabflow: from an architectural design to a mobile construction robot.

The package is organised by stage (see the README): ``design`` (what to build),
``tasks`` (stations and work packages), ``positioning`` (where the robot is),
``transforms`` (frames and vendor conventions), ``robots`` (kinematics and
program writers), ``preview`` (browser scene) and ``sim`` (simulated runs).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("fabflow")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
