"""The layout of feedmon's MCAP trial files, shared by the writer (:mod:`feedio.trialwriter`) and the
reader (:mod:`feedio.trialreader`): channel names and kinds, times, the size limits of the format.

Layout of a trial file
----------------------
* Messages are JSON (``message_encoding = "json"``) encoded with ``msgspec``; every
  channel carries the ``jsonschema`` schema generated from the Struct
  (:data:`feedio.schema.JSON_SCHEMAS`).
* Channels per axis: ``/<machine>/<axis>/samples`` (:class:`SampleBlock`),
  ``/<machine>/<axis>/truth`` (:class:`TruthBlock`, simulated trials and pulse
  ground truth), ``/<machine>/<axis>/disturbance`` (:class:`EstimateBlock`,
  written by the monitor) and ``/<machine>/<axis>/disturbance/scalars``
  (:class:`DisturbanceScalars`, one message of plain numbers per sample, written by
  the monitor for other tools; see :mod:`feedio.scalars`) and ``/<machine>/<axis>/health``
  (:class:`Health`, about one report per second of data, written by the monitor).
* One metadata record ``feedmon.trial`` per axis (MCAP metadata is map<str,str>):
  key ``meta`` holds the :class:`TrialMeta` JSON, plus readable keys ``machine``,
  ``axis``, ``form``, ``Ts``, ``source`` and the trial's start time ``start_time``
  (ISO 8601, UTC) / ``start_time_ns`` (ns since the Unix epoch).
* Log times are wall-clock times in ns since the Unix epoch. The log time of a block
  message is the time of its *last* sample (when a live monitor receives it): for a
  live log the receive time, for a written trial ``start + t[-1]`` (controller time
  counted from the start time). Publish time = log time. MCAP ``sequence`` = the
  block's ``seq`` (mod 2³²). The start time defaults to the creation time; give it
  (``start=``, ``--created``/``--start``) for byte-identical files.
* Chunked, zstd-compressed, chunk and data-section CRCs stored. A chunk is closed
  whenever the written data span ``chunk_seconds`` (default 1 s) of controller time,
  or its size exceeds ``chunk_size``; a live writer also calls
  :meth:`TrialWriter.flush_if_due` (wall clock) so that at most about a second is lost
  on a crash. Wall-clock flushing is never automatic: it would make chunk boundaries,
  hence bytes, depend on the machine's speed.
* The records are written by :class:`feedio.mcapwriter.McapWriter`, which writes the bytes of
  the ``mcap`` package's writer and appends many pre-built records at once:
  :meth:`TrialWriter.write_scalars_batch` writes a whole :class:`~feedio.scalars.ScalarsBatch`
  (the per-sample channel) that way — the same bytes as one :meth:`TrialWriter.write_scalars`
  call per message, chunk boundaries included.
"""

from __future__ import annotations

import time
from datetime import UTC, datetime

from feedio import schema as S

__all__ = ["METADATA_NAME", "SCALARS", "HEALTH", "ALARM", "TRUTH_EVENTS", "CHANNEL_KINDS", "SINGLE_SAMPLE_TYPES", "MAX_LOG_TIME_NS", "MAX_MESSAGE_BYTES", "MAX_PENDING_BYTES", "ZSTD_LEVEL", "MAX_READ_AHEAD_BYTES", "topic", "split_topic", "check_name", "library", "parse_time", "format_time", "now_ns"]

METADATA_NAME = "feedmon.trial"
SCALARS = "disturbance/scalars"
HEALTH = "health"
#: the process monitors' alarms (:class:`feedio.schema.AlarmEvent`), channel ``/<machine>/<axis>/alarm``
ALARM = "alarm"
#: known process events of a simulated trial (:class:`~feedio.schema.TruthEvent`), one per message
TRUTH_EVENTS = "truth/events"
CHANNEL_KINDS = {"samples": S.SampleBlock, "truth": S.TruthBlock, "disturbance": S.EstimateBlock,
                 SCALARS: S.DisturbanceScalars, HEALTH: S.Health, ALARM: S.AlarmEvent, TRUTH_EVENTS: S.TruthEvent}
#: message types of one sample each (``t`` a number, not a column)
SINGLE_SAMPLE_TYPES = (S.DisturbanceScalars, S.Health, S.AlarmEvent, S.TruthEvent)

#: largest log time, ns since the Unix epoch (int64, year 2262): what every MCAP tool can hold
MAX_LOG_TIME_NS = 2**63 - 1
#: largest message the writer accepts (encoded JSON bytes); the reader's record limit is larger
MAX_MESSAGE_BYTES = 16 * 2**20
#: bytes a writer keeps in memory while the disk refuses them (full, file too large) before it
#: gives the file up (it then ends on its last complete record; ``feedmon recover`` finishes it)
MAX_PENDING_BYTES = 64 * 2**20
#: zstd level of the chunks. Level 1, not mcap's 3: on an estimates log (``run --from``, 822 bytes of JSON
#: per sample) it compresses 2.0× faster (1.6 against 3.3 µs per sample) and smaller (ratio 3.4 against
#: 3.2). ``feedmon recover`` writes with the same writer and level: a healthy file written by feedmon comes
#: out byte for byte, one compressed at another level (an older feedmon, other tools) with the same records
ZSTD_LEVEL = 1
#: bytes of decoded blocks of other axes held while reading several axes in one pass, merged by time
#: (replay, run --from; :func:`held_bytes`); beyond, the axes not being consumed re-read the file on
#: their own (a file whose axes are not interleaved in time costs one more read, never more memory)
MAX_READ_AHEAD_BYTES = 64 * 2**20


def topic(machine: str, axis: str, kind: str) -> str:
    """``/<machine>/<axis>/<kind>`` with kind in samples, truth, disturbance, disturbance/scalars, health."""
    if kind not in CHANNEL_KINDS:
        raise ValueError(f"unknown channel kind {kind!r}; use one of {', '.join(CHANNEL_KINDS)}")
    return f"/{machine}/{axis}/{kind}"


def split_topic(name: str) -> tuple[str, str, str] | None:
    """(machine, axis, kind) of a feedmon topic, None for other topics."""
    parts = name.split("/", 3)
    if len(parts) == 4 and parts[0] == "" and parts[3] in CHANNEL_KINDS and parts[1] and parts[2]:
        return parts[1], parts[2], parts[3]
    return None


def check_name(what: str, value: str) -> str:
    if not value or "/" in value or value.strip() != value:
        raise ValueError(f"{what} {value!r} must be a non-empty name without '/' or surrounding spaces")
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError(f"{what} {value!r} is not valid Unicode text (a lone surrogate)") from None
    return value


def library() -> str:
    from mcap.writer import LIBRARY_IDENTIFIER

    from . import __version__

    return f"feedmon/{__version__}; {LIBRARY_IDENTIFIER}"


# ---- times ------------------------------------------------------------------------------------
def parse_time(value, *, what: str = "start time") -> int:
    """ns since the Unix epoch of ``value``: an ISO 8601 string (``2024-05-01T08:00:00Z``; no
    zone = UTC), a :class:`datetime`, or an int of ns. Between 1970 and 2262 (int64 ns)."""
    if isinstance(value, bool):
        raise ValueError(f"{what} {value!r} is not a time")
    if isinstance(value, int):
        ns = value
    else:
        if isinstance(value, str):
            try:
                value = datetime.fromisoformat(value.strip())
            except ValueError:
                raise ValueError(f"{what} {value!r} is not an ISO 8601 time such as 2024-05-01T08:00:00Z") from None
        if not isinstance(value, datetime):
            raise ValueError(f"{what} {value!r} is not a time (give ISO 8601, a datetime or ns)")
        if value.tzinfo is None:
            value = value.replace(tzinfo=UTC)
        delta = value - datetime(1970, 1, 1, tzinfo=UTC)
        ns = (delta.days * 86400 + delta.seconds) * 10**9 + delta.microseconds * 1000
    if not 0 <= ns <= MAX_LOG_TIME_NS:
        raise ValueError(f"{what} {value!r} is outside 1970…2262, the range of MCAP log times (int64 ns)")
    return ns


def format_time(ns: int) -> str:
    """ISO 8601 UTC of ``ns`` since the epoch, to the microsecond (``2024-05-01T08:00:00.000000Z``)."""
    sec, rem = divmod(int(ns), 10**9)
    dt = datetime.fromtimestamp(sec, tz=UTC).replace(microsecond=rem // 1000)
    return dt.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def now_ns() -> int:
    return time.time_ns() // 10**6 * 10**6  # the creation time, to the millisecond
