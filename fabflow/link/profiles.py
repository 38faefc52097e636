"""The timing and limits of each kind of machine link.

* ``hydraulic``: paper 004's BROKK 170 behind an Arduino CAN gateway, joint
  sensors read at 30 Hz, so the control computer sends a setpoint every
  1/30 s; the valves answer after a pressure build-up of about 1.3 s
  (:class:`~fabflow.robots.hydraulic.HydraulicJoints`), so the joints lag the
  setpoints by far more than a servo's.
* ``rsi``: a KUKA RSI-style exchange: the controller sends its state every
  4 ms (or 12 ms) and must have the answer within that cycle.

The watchdog, tracking bound and settling tolerance are fabflow's defaults
(docs/link.md), not a vendor's: each can be set on the command line.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from fabflow.errors import InputError
from fabflow.link.protocol import PROFILES, Profile
from fabflow.robots.catalog import vendor_of


@dataclass(frozen=True)
class LinkProfile:
    """One kind of link (SI units, joint angles in radians).

    Attributes
    ----------
    name
        ``"hydraulic"`` or ``"rsi"``.
    cycle_s
        The link's cycle: a setpoint per cycle (hydraulic, sent by the streamer)
        or a state per cycle (RSI, sent by the gateway).
    watchdog_s
        Silence after which either side stops the machine.
    tracking_bound
        Largest joint difference between the setpoint and the feedback before
        the streamer stops the machine (radians, any joint).
    settle_tolerance, settle_timeout_s
        After the last setpoint, the machine must come within this of it
        (radians, every joint) within this time (s) for the program to count
        as completed.
    """

    name: Profile
    cycle_s: float
    watchdog_s: float
    tracking_bound: float
    settle_tolerance: float
    settle_timeout_s: float

    def __post_init__(self) -> None:
        ok = (
            self.name in PROFILES
            and 0.001 <= self.cycle_s <= 1.0
            and self.cycle_s < self.watchdog_s <= 60.0
            and 0.0 < self.tracking_bound <= 6.3
            and 0.0 < self.settle_tolerance <= self.tracking_bound
            and 0.0 < self.settle_timeout_s <= 600.0
        )
        if not ok:
            raise InputError(
                f"link profile {self.name!r}: need a cycle of 1 ms to 1 s, a watchdog longer "
                "than the cycle (at most 60 s), 0 < settle tolerance <= tracking bound <= "
                "6.3 rad and a settle timeout of at most 600 s"
            )

    def with_options(
        self,
        cycle_s: float | None = None,
        watchdog_s: float | None = None,
        tracking_bound: float | None = None,
    ) -> LinkProfile:
        """This profile with the given values replaced (``None``: kept)."""
        changes = {
            k: v
            for k, v in (
                ("cycle_s", cycle_s),
                ("watchdog_s", watchdog_s),
                ("tracking_bound", tracking_bound),
            )
            if v is not None
        }
        return replace(self, **changes)


HYDRAULIC = LinkProfile(
    name="hydraulic",
    cycle_s=1.0 / 30.0,
    watchdog_s=0.5,
    tracking_bound=0.6,
    settle_tolerance=0.01,
    settle_timeout_s=30.0,
)
"""Paper 004's machine: 30 Hz, a 1.3 s valve dead time behind it."""

RSI = LinkProfile(
    name="rsi",
    cycle_s=0.004,
    watchdog_s=0.1,
    tracking_bound=0.05,
    settle_tolerance=0.001,
    settle_timeout_s=2.0,
)
"""A KUKA RSI-style exchange at 4 ms (``cycle_s=0.012`` for the 12 ms mode)."""

LINK_PROFILES = {"hydraulic": HYDRAULIC, "rsi": RSI}


def profile_for(robot: str, name: str | None = None) -> LinkProfile:
    """The named profile, or the robot's: hydraulic for a construction machine, else RSI.

    Raises
    ------
    InputError
        For an unknown profile name.
    """
    if name is None:
        return HYDRAULIC if vendor_of(robot) in ("brokk", "heap") else RSI
    if name not in LINK_PROFILES:
        raise InputError(f"unknown link profile {name!r}; use {' or '.join(LINK_PROFILES)}")
    return LINK_PROFILES[name]
