"""MCAP trial files: one writer, one reader, one schema (:mod:`feedio.schema`) — the names the rest of
feedmon imports, from :mod:`feedio.trialformat` (the layout), :mod:`feedio.trialwriter` and
:mod:`feedio.trialreader`.
"""

from __future__ import annotations

from .mcapfile import Limits, TrialFileError
from .trialformat import (
    ALARM,
    CHANNEL_KINDS,
    HEALTH,
    MAX_LOG_TIME_NS,
    MAX_MESSAGE_BYTES,
    MAX_PENDING_BYTES,
    MAX_READ_AHEAD_BYTES,
    METADATA_NAME,
    SCALARS,
    TRUTH_EVENTS,
    ZSTD_LEVEL,
    format_time,
    parse_time,
    topic,
)
from .trialreader import (
    MAX_TRIAL_SAMPLES,
    AxisStreams,
    OpenTrial,
    Trial,
    TrialTooLong,
    TruthArrays,
    held_bytes,
    iter_axes,
    iter_blocks,
    iter_file,
    list_axes,
    read_trial,
)
from .trialwriter import TrialWriter, write_arrays

__all__ = [
    "TrialFileError",
    "TrialTooLong",
    "MAX_TRIAL_SAMPLES",
    "TrialWriter",
    "write_arrays",
    "Trial",
    "TruthArrays",
    "read_trial",
    "list_axes",
    "iter_blocks",
    "iter_axes",
    "iter_file",
    "topic",
    "parse_time",
    "format_time",
    "METADATA_NAME",
    "CHANNEL_KINDS",
    "SCALARS",
    "HEALTH",
    "ALARM",
    "TRUTH_EVENTS",
    "MAX_LOG_TIME_NS",
    "MAX_MESSAGE_BYTES",
    "MAX_PENDING_BYTES",
    "MAX_READ_AHEAD_BYTES",
    "AxisStreams",
    "held_bytes",
    "ZSTD_LEVEL",
    "Limits",
    "OpenTrial",
]
