"""The tags of the frames the monitor sends to a sink's child process (the MCAP logging process, the
Rerun recording process), defined once for both ends.

A frame is its tag byte followed by the message in the child's wire format (see
:mod:`monitor.sinks.mcap_sink` and :mod:`monitor.sinks.rerun_process` for the layout around it).
"""

from __future__ import annotations

import enum

__all__ = ["Tag"]


class Tag(bytes, enum.Enum):
    """One byte naming what a frame holds. A member equals its byte string (``Tag.SAMPLES == b"S"``), so a
    tag read from a pipe compares to it directly."""

    SAMPLES = b"S"  #: a SampleBlock, JSON of the schema (as received)
    ESTIMATES = b"E"  #: an EstimateBlock, JSON of the schema (as published)
    TRUTH = b"T"  #: a TruthBlock of one axis (the axis named beside it)
    HEALTH = b"H"  #: a Health report (MCAP: the schema's JSON; Rerun: ``{machine, axis, health}``)
    ALARM = b"A"  #: a process monitor's AlarmEvent, JSON of the schema
    PROCESS = b"P"  #: the process monitors' ProcessView of an axis (Rerun only), JSON of the schema
    EVENT = b"V"  #: an event for the Rerun timeline, JSON ``{machine, axis, seq, t, level, text}``
    QUIT = b"Q"  #: finish and exit (the whole message)
