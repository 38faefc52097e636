"""The live machine link (paper 004): stream a program to a machine gateway over UDP.

:mod:`~fabflow.link.protocol` (the messages, versioned), :mod:`~fabflow.link.profiles`
(cycle, delays and limits of each kind of machine), :mod:`~fabflow.link.gateway`
(``fabflow machine-sim``: a simulated gateway and machine) and
:mod:`~fabflow.link.streamer` (``fabflow stream``).
"""
