"""MCAP trial files: one writer, one reader, one schema (:mod:`feedio.schema`).

Layout of a trial file
----------------------
* Messages are JSON (``message_encoding = "json"``) encoded with ``msgspec``; every
  channel carries the ``jsonschema`` schema generated from the Struct
  (:data:`feedio.schema.JSON_SCHEMAS`).
* Channels per axis: ``/<machine>/<axis>/samples`` (:class:`SampleBlock`),
  ``/<machine>/<axis>/truth`` (:class:`TruthBlock`, simulated trials and pulse
  ground truth), ``/<machine>/<axis>/truth/events`` (:class:`TruthEvent`, one known
  process event per message, simulated process scenarios), ``/<machine>/<axis>/disturbance`` (:class:`EstimateBlock`,
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

Reading goes through :mod:`feedio.mcapfile` (limits, CRCs); messages are read in file
order, which for feedmon's writers is sequence order on every channel.

A failed write never corrupts the writer: every value that could overflow the file
format is checked before the record writer sees it, and the writer writes into memory
(:class:`_StagedFile`) that is committed to the file on flush — a disk that refuses the
bytes leaves the file ending on a complete record and the bytes waiting for the next
flush (up to :data:`MAX_PENDING_BYTES`, then the file is given up, see
:attr:`TrialWriter.failed`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime

import msgspec
import numpy as np

from feedio import schema as S
from kernels.errors import ParameterError

from .mcapfile import DEFAULT_LIMITS, Limits, McapFile, TrialFileError, json_depth
from .mcapwriter import MESSAGE_HEADER, McapWriter

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
    "KINDS",
    "SCALARS",
    "HEALTH",
    "TRUTH_EVENTS",
    "MAX_LOG_TIME_NS",
    "MAX_MESSAGE_BYTES",
    "MAX_PENDING_BYTES",
    "MAX_READ_AHEAD_BYTES",
    "AxisStreams",
    "held_bytes",
    "ZSTD_LEVEL",
    "Limits",
]

METADATA_NAME = "feedmon.trial"
SCALARS = "disturbance/scalars"
HEALTH = "health"
KINDS = {"samples": S.SampleBlock, "truth": S.TruthBlock, "disturbance": S.EstimateBlock,
         SCALARS: S.DisturbanceScalars, HEALTH: S.Health}
#: the process monitors' alarms (:class:`feedio.schema.AlarmEvent`), channel ``/<machine>/<axis>/alarm``
ALARM = "alarm"
KINDS[ALARM] = S.AlarmEvent
#: message types of one sample each (``t`` a number, not a column)
_SINGLE = (S.DisturbanceScalars, S.Health, S.AlarmEvent)
#: known process events of a simulated trial (:class:`~feedio.schema.TruthEvent`), one per message
TRUTH_EVENTS = "truth/events"
KINDS[TRUTH_EVENTS] = S.TruthEvent
_SINGLE += (S.TruthEvent,)

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
    if kind not in KINDS:
        raise ValueError(f"unknown channel kind {kind!r}; use one of {', '.join(KINDS)}")
    return f"/{machine}/{axis}/{kind}"


def _split_topic(name: str) -> tuple[str, str, str] | None:
    """(machine, axis, kind) of a feedmon topic, None for other topics."""
    parts = name.split("/", 3)
    if len(parts) == 4 and parts[0] == "" and parts[3] in KINDS and parts[1] and parts[2]:
        return parts[1], parts[2], parts[3]
    return None


def _check_name(what: str, value: str) -> str:
    if not value or "/" in value or value.strip() != value:
        raise ValueError(f"{what} {value!r} must be a non-empty name without '/' or surrounding spaces")
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError(f"{what} {value!r} is not valid Unicode text (a lone surrogate)") from None
    return value


def _library() -> str:
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


def _now_ns() -> int:
    return time.time_ns() // 10**6 * 10**6  # the creation time, to the millisecond


# ============================================================================================
# writer
# ============================================================================================
class _StagedFile:
    """The stream the mcap ``Writer`` writes to: bytes are staged in memory and committed to
    the file by :meth:`commit`. Each ``write`` of the mcap writer holds complete records, so
    the pieces are committed one by one; a piece the disk refuses is cut back (the file is
    truncated to the end of the last piece written) and kept, with the pieces after it, for the
    next attempt. The file therefore always ends on a complete record, as much as fits is on
    disk, and the mcap ``Writer``'s offsets and state never disagree with the file.
    ``damaged`` when even the truncation failed."""

    def __init__(self, path: str, exclusive: bool = False):
        # OSError propagates with the path; exclusive: FileExistsError rather than overwrite a file
        self.file = open(path, "xb" if exclusive else "wb", buffering=0)
        self.committed = 0
        self.staged: deque[tuple[bytes, int]] = deque()  # (piece, messages written before it ends)
        self.staged_bytes = 0
        self.damaged = False
        self.messages = 0  # set by the TrialWriter: messages handed to the mcap writer so far
        self.messages_on_disk = 0  # messages of the chunks committed so far

    def write(self, data) -> int:
        piece = bytes(data)
        if piece:
            self.staged.append((piece, self.messages))
            self.staged_bytes += len(piece)
        return len(piece)

    def tell(self) -> int:
        return self.committed + self.staged_bytes

    def flush(self) -> None:
        """No-op: the mcap writer calls it in ``Writer.flush``; :meth:`commit` does the I/O."""

    def drop(self) -> None:
        """Forget what is staged (the file is given up)."""
        self.staged.clear()
        self.staged_bytes = 0

    def commit(self) -> None:
        while self.staged:
            piece, messages = self.staged[0]
            done = 0
            try:
                with memoryview(piece) as view:
                    while done < len(piece):
                        n = self.file.write(view[done:])
                        if not n:
                            raise OSError(f"the file accepted no bytes at offset {self.committed + done}")
                        done += n
            except OSError:
                if done:
                    try:
                        self.file.truncate(self.committed)
                        self.file.seek(self.committed)
                    except OSError:
                        self.damaged = True
                raise
            self.staged.popleft()
            self.staged_bytes -= len(piece)
            self.committed += len(piece)
            if piece[0] == 0x06:  # a chunk record: its messages are on disk
                self.messages_on_disk = messages

    def close(self) -> None:
        self.file.close()


class TrialWriter:
    """Write a trial file. Use as a context manager::

        with TrialWriter("trial.mcap", meta, start="2024-05-01T08:00:00Z") as w:
            w.write_samples(block)
            w.write_truth(truth_block, machine, axis)

    ``meta`` is one :class:`TrialMeta` or a sequence of them (one per axis). Blocks of an
    axis not declared in ``meta`` are refused. ``chunk_seconds`` closes a chunk every so
    many seconds of controller time; ``chunk_size`` (bytes, uncompressed) as well.
    ``start`` (ISO 8601, datetime or ns; default: now) is the wall-clock time of controller
    time 0 for messages written without an explicit ``log_time``.

    Errors: a block that cannot be written (log time outside 1970…2262, sequence number
    beyond :data:`~feedio.schema.SEQ_MAX`, message larger than :data:`MAX_MESSAGE_BYTES`)
    raises ``ValueError`` and leaves the writer as it was. A disk that refuses a flush makes
    :meth:`flush`, :meth:`flush_if_due` and :meth:`close` raise ``OSError`` (a write that
    closes a chunk only records it in :attr:`last_flush_error`); the bytes are kept for the
    next flush, so nothing is lost when space comes back. After a
    failure inside the mcap writer, or when more than ``max_pending_bytes`` wait for the disk,
    the writer is :attr:`failed`: the file ends on its last complete record (readable after
    ``feedmon recover``), :attr:`messages_lost` counts what never reached it, and every later
    write raises :class:`TrialFileError`. ``exclusive``: create the file, never overwrite one
    (``FileExistsError``), so two writers can never share a file.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        meta: S.TrialMeta | Sequence[S.TrialMeta],
        *,
        chunk_seconds: float = 1.0,
        chunk_size: int = 4 * 1024 * 1024,
        compression: str = "zstd",
        start=None,
        max_pending_bytes: int = MAX_PENDING_BYTES,
        compression_level: int = ZSTD_LEVEL,
        exclusive: bool = False,
    ):
        metas = [meta] if isinstance(meta, S.TrialMeta) else list(meta)
        if not metas:
            raise ValueError("TrialWriter needs the TrialMeta of at least one axis")
        self.path = os.fspath(path)
        self.metas: dict[tuple[str, str], S.TrialMeta] = {}
        for m in metas:
            if not isinstance(m, S.TrialMeta):
                raise TypeError(f"meta must be TrialMeta, got {type(m).__name__}")
            key = (_check_name("machine", m.machine), _check_name("axis", m.axis))
            if key in self.metas:
                raise ValueError(f"axis {m.machine}/{m.axis} declared twice")
            self.metas[key] = m
        if not (chunk_seconds > 0):
            raise ValueError("chunk_seconds must be > 0")
        comp = {"zstd": "zstd", "lz4": "lz4", "none": ""}.get(compression)
        if comp is None:
            raise ValueError(f"compression {compression!r}: use zstd, lz4 or none")
        self.start_ns = _now_ns() if start is None else parse_time(start)
        self.max_pending_bytes = int(max_pending_bytes)
        self._schemas: dict[type, int] = {}
        self._channels: dict[str, int] = {}
        self._chunk_seconds = float(chunk_seconds)
        self._chunk_t0: float | None = None  # controller time of the first message in the open chunk
        self._pending = 0  # messages in the open chunk
        self._last_wall = time.monotonic()
        self._closed = False
        self.failed: str | None = None  # why the file was given up
        self.messages = 0  # messages accepted
        self.messages_lost = 0  # accepted but never written to the file (the writer failed)
        self.finished = False  # summary written and committed: a complete file
        self.last_flush_error: OSError | None = None  # the disk's last refusal during a write
        self._stream = _StagedFile(self.path, exclusive)
        try:
            self._start(chunk_size, comp, int(compression_level))
        except BaseException:
            self._stream.close()
            raise

    def _start(self, chunk_size: int, comp: str, level: int) -> None:
        """Header, one metadata record and the samples channel per axis (into memory)."""
        self._writer = McapWriter(self._stream, chunk_size=chunk_size, compression=comp, compression_level=level,
                                  enable_data_crcs=True)
        self._writer.start(profile="", library=_library())
        for (machine, axis), m in self.metas.items():
            self._writer.add_metadata(
                METADATA_NAME,
                {
                    "meta": S.encode(m).decode(),
                    "machine": machine,
                    "axis": axis,
                    "form": m.form,
                    "Ts": repr(float(m.Ts)),
                    "source": m.provenance.source,
                    "schema": "feedmon/1",
                    "start_time": format_time(self.start_ns),
                    "start_time_ns": str(self.start_ns),
                },
            )
            self._channel(machine, axis, "samples")

    # -- context manager ------------------------------------------------------------------
    def __enter__(self) -> TrialWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def pending_bytes(self) -> int:
        """Bytes written to the writer that the disk has not taken yet."""
        return self._stream.staged_bytes

    @property
    def bytes_on_disk(self) -> int:
        return self._stream.committed

    @property
    def messages_on_disk(self) -> int:
        """Messages in the chunks committed to the file so far (the first ones written)."""
        return self._stream.messages_on_disk

    def is_gone(self) -> bool:
        """True when the path no longer names the file being written (removed, renamed away or replaced:
        what is written goes nowhere anyone will find it)."""
        try:
            mine = os.fstat(self._stream.file.fileno())
            there = os.stat(self.path)
        except FileNotFoundError:
            return True
        except (OSError, ValueError):  # a closed file, a directory we may not search: not known to be gone
            return False
        return mine.st_nlink == 0 or (mine.st_dev, mine.st_ino) != (there.st_dev, there.st_ino)

    def give_up(self, why: str) -> None:
        """Stop writing this file (it keeps what was committed: complete records) and close it; what
        never reached it is counted in :attr:`messages_lost`."""
        self._fail(why)
        self.close()

    # -- failure ------------------------------------------------------------------------------
    def _fail(self, why: str) -> TrialFileError:
        """Give the file up: it keeps what was committed (complete records); the rest is lost."""
        if self.failed is None:
            self.failed = why
            self.messages_lost += self.messages - self._stream.messages_on_disk
            self._stream.drop()
        return TrialFileError(
            f"{self.path}: the writer failed ({self.failed}); the file ends at byte {self._stream.committed} "
            f"on its last complete record — finish it with 'feedmon recover {self.path} -o FIXED.mcap'")

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"{self.path}: writer is closed")
        if self.failed is not None:
            raise self._fail(self.failed)

    def _inside(self, fn, *args):
        """Call the mcap writer; anything it raises leaves it in an unknown state: fail the file."""
        try:
            return fn(*args)
        except OSError:
            raise
        except Exception as exc:  # noqa: BLE001 - the mcap writer's state is unknown after this
            raise self._fail(f"{type(exc).__name__} inside the MCAP writer: {exc}") from exc

    # -- channels ---------------------------------------------------------------------------
    def _channel(self, machine: str, axis: str, kind: str) -> int:
        name = topic(machine, axis, kind)
        cid = self._channels.get(name)
        if cid is not None:
            return cid
        if (machine, axis) not in self.metas:
            declared = ", ".join(f"{m}/{a}" for m, a in self.metas)
            raise ValueError(f"{self.path}: axis {machine}/{axis} has no TrialMeta in this file (declared: {declared})")
        import json

        type_ = KINDS[kind]
        sid = self._schemas.get(type_)
        if sid is None:
            data = json.dumps(S.json_schema(type_), sort_keys=True).encode()
            sid = self._inside(self._writer.register_schema, S.SCHEMA_NAMES[type_], "jsonschema", data)
            self._schemas[type_] = sid
        cid = self._inside(self._writer.register_channel, name, "json", sid,
                           {"machine": machine, "axis": axis, "kind": kind})
        self._channels[name] = cid
        return cid

    # -- writing ------------------------------------------------------------------------------
    def log_time_of(self, t: float, what: str) -> int:
        """ns since the epoch of controller time ``t`` (``start + t``); ValueError when outside 1970…2262."""
        x = float(t) * 1e9
        if not (math.isfinite(x) and -self.start_ns <= x <= MAX_LOG_TIME_NS - self.start_ns):
            raise ValueError(
                f"{self.path}: {what} at controller time t = {t!r} s cannot be logged: start "
                f"{format_time(self.start_ns)} + t lies outside 1970…2262, the range of MCAP log times")
        return min(max(self.start_ns + int(round(x)), 0), MAX_LOG_TIME_NS)

    def _add(self, cid: int, data: bytes, log_time: int, seq: int, t0: float, t1: float, kind: str) -> None:
        """Validate everything that could overflow the file format, then add one message
        (``kind`` names the message in errors: "<kind> seq <seq>")."""
        if not isinstance(log_time, int) or not 0 <= log_time <= MAX_LOG_TIME_NS:
            raise ValueError(f"{self.path}: {kind} seq {seq}: log time {log_time!r} ns is outside 0…2**63−1 "
                             "(1970…2262)")
        if len(data) > MAX_MESSAGE_BYTES:
            raise ValueError(f"{self.path}: {kind} seq {seq} is {len(data)} bytes encoded, more than the limit of "
                             f"{MAX_MESSAGE_BYTES}; write it as several blocks")
        self._stream.messages = self.messages + 1  # a chunk finished inside add_message holds this one
        try:
            self._inside(self._writer.add_message, cid, log_time, data, log_time, seq & 0xFFFFFFFF)
        finally:
            self._stream.messages = self.messages
        self.messages += 1
        self._stream.messages = self.messages
        self._pending += 1
        if self._chunk_t0 is None or not math.isfinite(self._chunk_t0):
            self._chunk_t0 = t0
        if not (t1 - self._chunk_t0 < self._chunk_seconds):  # also when a time is not finite
            try:
                self.flush()
            except OSError as exc:  # the bytes wait for the next flush; flush()/close() report it
                self.last_flush_error = exc

    def _add_block(self, cid: int, block, log_time: int | None, kind: str) -> None:
        self._check_open()
        self._check_seq(block.seq, len(block.t), kind)
        try:
            data = S.encode(block)
        except (OverflowError, TypeError, ValueError, msgspec.EncodeError) as exc:
            raise ValueError(f"{self.path}: {kind} seq {block.seq} cannot be encoded: {exc}") from None
        self._add_encoded(cid, data, int(block.seq), float(block.t[0]), float(block.t[-1]), log_time, kind)

    def _check_seq(self, seq: int, n: int, kind: str) -> None:
        if not 0 <= seq <= S.SEQ_MAX - (n - 1):
            raise ValueError(f"{self.path}: {kind} seq {seq}: sequence numbers must lie in 0…SEQ_MAX = 2**53 − 1 "
                             f"(this block ends at {seq + n - 1})")

    def _add_encoded(self, cid: int, data: bytes, seq: int, t0: float, t1: float, log_time: int | None,
                     kind: str) -> None:
        lt = self.log_time_of(t1, f"{kind} seq {seq}") if log_time is None else log_time
        self._add(cid, data, lt, seq, t0, t1, kind)

    #: what a block channel's messages are called in errors
    _KIND_NAMES = {"samples": "sample block", "truth": "truth block", "disturbance": "estimate block"}

    def write_encoded(self, machine: str, axis: str, kind: str, data: bytes, *, seq: int, n: int, t0: float,
                      t1: float, log_time: int | None = None) -> None:
        """Append a block message already encoded (``data``: the JSON of a :class:`SampleBlock`,
        :class:`TruthBlock` or :class:`EstimateBlock` as :func:`feedio.schema.encode` wrote it) on
        ``/<machine>/<axis>/<kind>`` (kind ``samples``, ``truth`` or ``disturbance``): the same record
        as the ``write_*`` method of the decoded block. ``seq`` and ``n`` are its first sequence number
        and sample count, ``t0``, ``t1`` the times of its first and last sample (s)."""
        if kind not in self._KIND_NAMES:
            raise ValueError(f"write_encoded: kind {kind!r} is not a block channel (samples, truth, disturbance)")
        self._check_open()
        name = self._KIND_NAMES[kind]
        self._check_seq(seq, n, name)
        self._add_encoded(self._channel(machine, axis, kind), data, seq, t0, t1, log_time, name)

    def write_samples(self, block: S.SampleBlock, *, log_time: int | None = None) -> None:
        """Append a :class:`SampleBlock` on ``/<machine>/<axis>/samples``; ``log_time`` (ns since
        the epoch, default ``start + t[-1]``) is the time of its last sample."""
        if not isinstance(block, S.SampleBlock):
            raise TypeError(f"write_samples needs a SampleBlock, got {type(block).__name__}")
        block.validate()
        self._check_open()
        self._add_block(self._channel(block.machine, block.axis, "samples"), block, log_time, "sample block")

    def write_truth(self, block: S.TruthBlock, machine: str, axis: str, *, log_time: int | None = None) -> None:
        """Append a :class:`TruthBlock` on ``/<machine>/<axis>/truth``."""
        if not isinstance(block, S.TruthBlock):
            raise TypeError(f"write_truth needs a TruthBlock, got {type(block).__name__}")
        self._check_open()
        self._add_block(self._channel(machine, axis, "truth"), block, log_time, "truth block")

    def write_estimates(self, block: S.EstimateBlock, *, log_time: int | None = None) -> None:
        """Append an :class:`EstimateBlock` on ``/<machine>/<axis>/disturbance``."""
        if not isinstance(block, S.EstimateBlock):
            raise TypeError(f"write_estimates needs an EstimateBlock, got {type(block).__name__}")
        self._check_open()
        self._add_block(self._channel(block.machine, block.axis, "disturbance"), block, log_time, "estimate block")

    def write_scalars(self, machine: str, axis: str, items: Sequence[tuple[int, S.DisturbanceScalars]]) -> None:
        """Append ``(log_time_ns, DisturbanceScalars)`` messages on ``/<machine>/<axis>/disturbance/scalars``."""
        if not items:
            return
        self._check_open()
        cid = self._channel(machine, axis, SCALARS)
        encode = S.encode
        for lt, sc in items:
            if type(sc) is not S.DisturbanceScalars:
                raise TypeError(f"write_scalars needs DisturbanceScalars, got {type(sc).__name__}")
            if not (0 <= sc.seq <= S.SEQ_MAX and math.isfinite(sc.t)):
                raise ValueError(f"{self.path}: scalars seq {sc.seq} at t = {sc.t!r} s: the sequence number must lie "
                                 "in 0…SEQ_MAX and the time must be finite")
            self._add(cid, encode(sc), lt, sc.seq, sc.t, sc.t, "scalars")

    def write_scalars_batch(self, batch) -> None:
        """Append the messages of a :class:`~feedio.scalars.ScalarsBatch` on
        ``/<machine>/<axis>/disturbance/scalars``: the same bytes as :meth:`write_scalars` with
        ``batch.messages()`` (records built in one compiled pass, added in bulk; chunks closed
        after the same messages). ``ValueError`` before anything is written when a message could
        not be (sequence number beyond ``SEQ_MAX``, a time not finite, a log time outside
        1970…2262)."""
        n = len(batch)
        if not n:
            return
        self._check_open()
        cid = self._channel(batch.machine, batch.axis, SCALARS)
        seq, t, lt = batch.seq, batch.t, batch.log_ns
        bad = np.flatnonzero((seq < 0) | (seq > S.SEQ_MAX) | ~np.isfinite(t) | (lt < 0))
        if bad.size:
            i = int(bad[0])
            raise ValueError(f"{self.path}: scalars seq {int(seq[i])} at t = {float(t[i])!r} s, log time {int(lt[i])}: "
                             "the sequence number must lie in 0…SEQ_MAX, the time must be finite and the log time "
                             "within 1970…2262")
        records, sizes = batch.records(cid)
        self._add_scalar_records(cid, records, sizes, lt, t)

    def write_scalar_records(self, machine: str, axis: str, records, sizes: np.ndarray, log_ns: np.ndarray,
                             t: np.ndarray, seq: np.ndarray) -> None:
        """:meth:`write_scalars_batch` for records already built elsewhere (another process):
        ``records`` (a writable uint8 array) as :meth:`ScalarsBatch.records
        <feedio.scalars.ScalarsBatch.records>` made them, ``sizes`` of each, and the batch's
        ``log_ns``, ``t`` and ``seq``; the channel id field of every record is set here to this
        file's ``/<machine>/<axis>/disturbance/scalars``."""
        n = int(sizes.size)
        if not n:
            return
        self._check_open()
        cid = self._channel(machine, axis, SCALARS)
        starts = np.cumsum(sizes) - sizes
        if (not (log_ns.size == t.size == seq.size == n) or records.size != int(starts[-1] + sizes[-1])
                or seq.min() < 0 or seq.max() > S.SEQ_MAX or log_ns.min() < 0 or not np.isfinite(t).all()
                or (records[starts] != 5).any()):
            raise ValueError(f"{self.path}: scalars records of {machine}/{axis} that cannot be written")
        records[starts + 9] = cid & 0xFF
        records[starts + 10] = cid >> 8
        self._add_scalar_records(cid, records, sizes, log_ns, t)

    def _add_scalar_records(self, cid: int, records, sizes: np.ndarray, lt: np.ndarray, t: np.ndarray) -> None:
        n = int(sizes.size)
        if int(sizes.max()) - MESSAGE_HEADER > MAX_MESSAGE_BYTES:
            raise ValueError(f"{self.path}: a scalars message is larger than {MAX_MESSAGE_BYTES} bytes")
        t0 = self._chunk_t0 if self._chunk_t0 is not None and math.isfinite(self._chunk_t0) else float(t[0])
        if float(t.max()) - t0 < self._chunk_seconds and self._writer.records_fitting(sizes) == n \
                and not (n and self._writer.closes_after(int(records.size))):
            # the usual case: every message goes into the open chunk, none closes it
            self._stream.messages = self.messages + n
            try:
                self._inside(self._writer.add_records, cid, records, sizes, lt)
            finally:
                self._stream.messages = self.messages
            self.messages += n
            self._stream.messages = self.messages
            self._pending += n
            if self._chunk_t0 is None or not math.isfinite(self._chunk_t0):
                self._chunk_t0 = t0
            return
        ends = np.cumsum(sizes)
        i = 0
        while i < n:
            # the messages up to the one that closes the chunk: by size (the record writer) or by
            # controller time (chunk_seconds after the first message of the chunk, as _add)
            k = self._writer.records_fitting(sizes[i:])
            t0 = self._chunk_t0 if self._chunk_t0 is not None and math.isfinite(self._chunk_t0) else float(t[i])
            late = np.flatnonzero(~(t[i:i + k] - t0 < self._chunk_seconds))
            by_time = late.size > 0
            if by_time:
                k = int(late[0]) + 1
            a, b = (int(ends[i - 1]) if i else 0), int(ends[i + k - 1])
            self._stream.messages = self.messages + k  # a chunk closed by size holds these
            try:
                self._inside(self._writer.add_records, cid, records[a:b], sizes[i:i + k], lt[i:i + k])
            finally:
                self._stream.messages = self.messages
            self.messages += k
            self._stream.messages = self.messages
            self._pending += k
            if self._chunk_t0 is None or not math.isfinite(self._chunk_t0):
                self._chunk_t0 = t0
            if by_time:
                try:
                    self.flush()
                except OSError as exc:  # the bytes wait for the next flush; flush()/close() report it
                    self.last_flush_error = exc
            i += k

    def write_health(self, report: S.Health, *, log_time: int | None = None) -> None:
        """Append a :class:`Health` report on ``/<machine>/<axis>/health``; ``log_time`` (ns since the
        epoch) defaults to ``start + t``."""
        if type(report) is not S.Health:
            raise TypeError(f"write_health needs a Health report, got {type(report).__name__}")
        self._check_open()
        cid = self._channel(report.machine, report.axis, HEALTH)
        what = f"health seq {report.seq}"
        if not (0 <= report.seq <= S.SEQ_MAX and math.isfinite(report.t)):
            raise ValueError(f"{self.path}: {what} at t = {report.t!r} s: the sequence number must lie in 0…SEQ_MAX "
                             "and the time must be finite")
        lt = self.log_time_of(report.t, what) if log_time is None else log_time
        self._add(cid, S.encode(report), lt, report.seq, report.t, report.t, "health")

    def write_alarm(self, event: S.AlarmEvent, *, log_time: int | None = None) -> None:
        """Append an :class:`AlarmEvent` on ``/<machine>/<axis>/alarm``; ``log_time`` (ns since the epoch)
        defaults to ``start + t``."""
        if type(event) is not S.AlarmEvent:
            raise TypeError(f"write_alarm needs an AlarmEvent, got {type(event).__name__}")
        self._check_open()
        cid = self._channel(event.machine, event.axis, ALARM)
        what = f"alarm seq {event.seq}"
        lt = self.log_time_of(event.t, what) if log_time is None else log_time
        self._add(cid, S.encode(event), lt, event.seq, event.t, event.t, ALARM)

    def write_truth_event(self, event: S.TruthEvent, machine: str, axis: str, *, log_time: int | None = None) -> None:
        """Append a :class:`TruthEvent` on ``/<machine>/<axis>/truth/events``; ``log_time`` (ns since
        the epoch) defaults to ``start + t_s``."""
        if type(event) is not S.TruthEvent:
            raise TypeError(f"write_truth_event needs a TruthEvent, got {type(event).__name__}")
        self._check_open()
        cid = self._channel(machine, axis, TRUTH_EVENTS)
        what = f"truth event seq {event.seq}"
        lt = self.log_time_of(event.t_s, what) if log_time is None else log_time
        self._add(cid, S.encode(event), lt, event.seq, event.t_s, event.t_s, "truth event")

    def flush(self) -> None:
        """Close the open chunk (if it has messages) and write everything to the file.
        ``OSError`` when the disk refuses (the bytes are kept for the next flush)."""
        if self._closed or self.failed is not None:
            return
        if self._pending:
            self._inside(self._writer.flush)  # closes the chunk into memory (the stream's flush is a no-op)
            self._pending = 0
            self._chunk_t0 = None
        self._commit()
        self._last_wall = time.monotonic()

    def _commit(self) -> None:
        try:
            self._stream.commit()
        except OSError as exc:
            if self._stream.damaged:
                raise self._fail(f"{exc.strerror or exc}, and the file could not be cut back to its last record") from exc
            if self._stream.staged_bytes > self.max_pending_bytes:
                raise self._fail(f"{exc.strerror or exc}; more than {self.max_pending_bytes} bytes waited for the disk") \
                    from exc
            raise

    def flush_if_due(self, now: float | None = None) -> bool:
        """For live writers: close the chunk when ``chunk_seconds`` of wall time passed
        since the last flush (``now`` from ``time.monotonic()``). Returns True if flushed."""
        now = time.monotonic() if now is None else now
        if (self._pending or self.pending_bytes) and now - self._last_wall >= self._chunk_seconds:
            self.flush()
            return True
        return False

    def close(self) -> None:
        """Write the summary and close the file (idempotent). A failed writer only closes the
        file (it ends on its last complete record); ``OSError`` when the disk refuses the end
        of the file (then it too ends on its last complete record)."""
        if self._closed:
            return
        self._closed = True
        try:
            if self.failed is None:
                self._inside(self._writer.finish)
                self._pending = 0
                self._commit()
                self.finished = True
        finally:
            if not self.finished and self.failed is None:
                self.messages_lost += self.messages - self._stream.messages_on_disk
                self.failed = "the end of the file could not be written"
            self._stream.close()


def write_arrays(path, meta: S.TrialMeta, samples: dict, truth: dict | None = None, *, block: int = 100,
                 start=None, events: Sequence[S.TruthEvent] = ()) -> None:
    """Write one axis given as arrays: ``samples`` maps :class:`SampleBlock` fields (``t``,
    ``v_ref``, ``v_meas`` and optional columns; ``None`` = absent) to arrays, ``truth`` maps
    :class:`TruthBlock` fields to arrays; both are cut into blocks of ``block`` samples with
    ``seq`` from 0 (the one writer of the simulator and the importers). ``events``
    (:class:`TruthEvent`, sorted by ``seq``) follow the block that holds their sample. ``start``:
    the trial's start time (default ``meta.provenance.created`` when set, else now)."""
    n = len(samples["t"])
    if start is None and meta.provenance.created:
        start = parse_time(meta.provenance.created, what="provenance.created")

    def cut(cols: dict, i: int, j: int) -> dict:
        return {k: None if a is None else np.asarray(a[i:j]).tolist() for k, a in cols.items()}

    events = sorted(events, key=lambda ev: (ev.seq, ev.t_s))
    e = 0
    with TrialWriter(os.fspath(path), meta, start=start) as w:
        for i in range(0, n, block):
            j = min(i + block, n)
            w.write_samples(S.SampleBlock(machine=meta.machine, axis=meta.axis, seq=i, **cut(samples, i, j)))
            if truth is not None:
                w.write_truth(S.TruthBlock(seq=i, **cut(truth, i, j)), meta.machine, meta.axis)
            while e < len(events) and events[e].seq < j:
                w.write_truth_event(events[e], meta.machine, meta.axis)
                e += 1
        for event in events[e:]:  # beyond the last sample: kept, in order
            w.write_truth_event(event, meta.machine, meta.axis)


# ============================================================================================
# reader
# ============================================================================================
@dataclass
class TruthArrays:
    """Ground truth as arrays aligned by ``seq`` with the samples (see :class:`TruthBlock`)."""

    seq: np.ndarray
    t: np.ndarray
    force: np.ndarray  # N, T_c of method §1
    f: np.ndarray  # m/s, −b·T_c
    dynamometer: np.ndarray | None = None
    v_true: np.ndarray | None = None
    glitch: np.ndarray | None = None  # bool
    inertia: np.ndarray | None = None  # kg, true J(t)
    damping: np.ndarray | None = None  # N·s/m, true B(t)
    coulomb_pos: np.ndarray | None = None  # N, true Coulomb friction for v > Ω
    coulomb_neg: np.ndarray | None = None  # N, magnitude for v < −Ω


@dataclass
class Trial:
    """One axis of a trial file as NumPy arrays (NaN where a sample was null)."""

    path: str
    machine: str
    axis: str
    meta: S.TrialMeta
    seq: np.ndarray
    t: np.ndarray
    v_ref: np.ndarray
    v_meas: np.ndarray
    u: np.ndarray | None = None
    current: np.ndarray | None = None
    position: np.ndarray | None = None
    spindle_rpm: np.ndarray | None = None
    spindle_angle: np.ndarray | None = None  # rad, unwrapped
    program_line: np.ndarray | None = None  # NC program line (float64: NaN where not known)
    tool: np.ndarray | None = None  # tool number (float64: NaN where not known)
    truth: TruthArrays | None = None
    channels: list[str] = field(default_factory=list)
    truth_events: list[S.TruthEvent] = field(default_factory=list)  # known process events (simulated trials)
    start_ns: int | None = None  # wall-clock time of controller time 0 (None: files without one)

    @property
    def Ts(self) -> float:
        return float(self.meta.Ts)

    @property
    def form(self) -> str:
        return self.meta.form

    def __len__(self) -> int:
        return int(self.t.size)

    def window(self, start: float | None = None, end: float | None = None) -> Trial:
        """The samples with ``start ≤ t − t₀ < end`` (s from the first sample; None: the record's
        start or end), and the truth of the same sequence numbers. Raises ``ValueError`` naming the
        parameter when the window is empty or ``start ≥ end`` (a :class:`~kernels.errors.ParameterError`)."""
        if start is None and end is None:
            return self
        for name, x in (("start", start), ("end", end)):
            if x is not None and not (math.isfinite(x) and x >= 0.0):
                raise ParameterError(f"window {name} must be a time ≥ 0 s from the trial's first sample, got {x!r}",
                                     name)
        if start is not None and end is not None and not start < end:
            raise ParameterError(f"window start ({start:g} s) must come before its end ({end:g} s)", "start", "end")
        rel = self.t - self.t[0] if self.t.size else self.t
        keep = (rel >= (start or 0.0)) & (rel < (math.inf if end is None else end))
        if not keep.any():
            raise ParameterError(f"{self.path}: no sample between {start or 0.0:g} s and "
                                 f"{'the end' if end is None else f'{end:g} s'} (the trial lasts "
                                 f"{float(rel[-1]):.6g} s)", "start", "end")
        idx = np.flatnonzero(keep)
        cols = {k: None if getattr(self, k) is None else getattr(self, k)[idx]
                for k in ("seq", *S.SAMPLE_COLUMNS)}
        truth = self.truth
        if truth is not None:
            lo, hi = int(self.seq[idx[0]]), int(self.seq[idx[-1]])
            sel = (truth.seq >= lo) & (truth.seq <= hi)
            truth = dataclasses.replace(truth, **{f.name: None if getattr(truth, f.name) is None
                                                  else getattr(truth, f.name)[sel]
                                                  for f in dataclasses.fields(truth)})
        lo, hi = int(self.seq[idx[0]]), int(self.seq[idx[-1]])
        events = [e for e in self.truth_events if lo <= e.seq <= hi]
        return dataclasses.replace(self, **cols, truth=truth, truth_events=events)


class _Open:
    """An opened, checked trial file (:class:`~feedio.mcapfile.McapFile`) with feedmon's
    conventions: axes, their metadata, decoded messages."""

    def __init__(self, path, limits: Limits = DEFAULT_LIMITS):
        self.file = McapFile(path, limits)
        self.path = self.file.path
        self.limits = limits
        try:
            self.channels = {}
            self._ids: dict[str, list[int]] = {}
            for c in self.file.channels.values():
                self.channels.setdefault(c.topic, c)
                self._ids.setdefault(c.topic, []).append(c.id)
            self._topic_of = {c.id: c.topic for c in self.file.channels.values()}
            self._axes: list[tuple[str, str]] | None = None
            self._by_name: dict[str, list[tuple[str, str]]] = {}
            self._trial_meta: dict[tuple[str, str], dict] = {}
            self._n_trial_meta = 0
            for rec in self.file.metadata():
                if rec.name == METADATA_NAME:
                    self._n_trial_meta += 1
                    key = (rec.metadata.get("machine"), rec.metadata.get("axis"))
                    self._trial_meta.setdefault(key, rec.metadata)
        except BaseException:
            self.file.close()
            raise

    def close(self):
        self.file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def axes(self) -> list[tuple[str, str]]:
        if self._axes is None:
            out = []
            for name in sorted(self.channels):
                parts = name.split("/")
                if len(parts) == 4 and parts[0] == "" and parts[3] == "samples" and parts[1] and parts[2]:
                    out.append((parts[1], parts[2]))
            self._axes = out
            by_name: dict[str, list[tuple[str, str]]] = {}
            for m, a in out:
                by_name.setdefault(f"{m}/{a}", []).append((m, a))
                by_name.setdefault(a, []).append((m, a))
            self._by_name = by_name
        return list(self._axes)

    def select(self, axis: str | None) -> tuple[str, str]:
        if self._axes is None:
            self.axes()
        if axis is not None and len(self._by_name.get(axis, ())) == 1:
            return self._by_name[axis][0]
        axes = self._axes
        if not axes:
            listed = ", ".join(sorted(self.channels)[:20]) or "none"
            raise TrialFileError(
                f"{self.path} has no samples channel (/<machine>/<axis>/samples); channels present: {listed}"
            )
        names = [f"{m}/{a}" for m, a in axes]
        if axis is None:
            if len(axes) > 1:
                shown = ", ".join(names[:20]) + (", …" if len(names) > 20 else "")
                raise TrialFileError(f"{self.path} holds {len(axes)} axes ({shown}); choose one with axis=")
            return axes[0]
        hits = [(m, a) for m, a in axes if axis in (a, f"{m}/{a}")]
        if not hits:
            shown = ", ".join(names[:20]) + (", …" if len(names) > 20 else "")
            raise TrialFileError(f"{self.path} has no axis {axis!r}; axes present: {shown}")
        if len(hits) > 1:
            raise TrialFileError(
                f"{self.path}: axis {axis!r} exists on several machines ({', '.join(f'{m}/{a}' for m, a in hits)}); "
                "give it as machine/axis"
            )
        return hits[0]

    def _record(self, machine: str, axis: str) -> dict:
        rec = self._trial_meta.get((machine, axis))
        if rec is None:
            raise TrialFileError(
                f"{self.path}: missing metadata record {METADATA_NAME!r} for axis {machine}/{axis} "
                f"(sampling time and input form unknown); found {self._n_trial_meta} {METADATA_NAME} record(s)"
            )
        return rec

    def meta(self, machine: str, axis: str) -> S.TrialMeta:
        rec = self._record(machine, axis)
        if "meta" not in rec:
            raise TrialFileError(f"{self.path}: metadata record {METADATA_NAME} of {machine}/{axis} has no 'meta' key")
        raw = rec["meta"]
        depth = json_depth(raw)
        if depth > self.limits.json_depth:
            raise TrialFileError(
                f"{self.path}: metadata {METADATA_NAME} of {machine}/{axis} nests {depth} levels deep, more than "
                f"the limit of {self.limits.json_depth}")
        try:
            return S.decode_meta(raw, what=f"metadata {METADATA_NAME} of {machine}/{axis}")
        except S.SchemaError as exc:
            raise TrialFileError(f"{self.path}: {exc}") from None

    def start_ns(self, machine: str, axis: str) -> int | None:
        raw = self._record(machine, axis).get("start_time_ns")
        if raw is None:
            return None
        try:
            return parse_time(int(raw), what="start_time_ns")
        except ValueError as exc:
            raise TrialFileError(f"{self.path}: metadata {METADATA_NAME} of {machine}/{axis}: {exc}") from None

    def check_channel(self, name: str) -> None:
        ch = self.channels[name]
        if ch.message_encoding != "json":
            raise TrialFileError(f"{self.path}: channel {name} has message encoding {ch.message_encoding!r}, expected 'json'")
        sch = self.file.schemas.get(ch.schema_id)
        if sch is None or sch.encoding != "jsonschema":
            got = "no schema" if sch is None else f"schema encoding {sch.encoding!r}"
            raise TrialFileError(f"{self.path}: channel {name} has {got}, expected a 'jsonschema' schema")

    def messages(self, topics: list[str]) -> Iterator[tuple[str, int, object]]:
        """Decoded (topic, log_time, block) in file order; errors name file, channel and message index."""
        kinds = {}
        for name in topics:
            self.check_channel(name)
            split = _split_topic(name)
            if split is None:
                raise ValueError(f"{name} is not a feedmon channel (/<machine>/<axis>/<kind>)")
            kinds[name] = KINDS[split[2]]
        ids = [i for name in topics for i in self._ids[name]]
        counters = dict.fromkeys(topics, 0)
        for _, msg in self.file.messages(ids):
            name = self._topic_of[msg.channel_id]
            idx = counters[name]
            counters[name] = idx + 1
            type_ = kinds[name]
            try:
                block = S.decode(msg.data, type_, what=f"message {idx}")
            except S.SchemaError as exc:
                raise TrialFileError(f"{self.path}: channel {name}, {exc}") from None
            seq = block.seq
            last = seq + (len(block.t) - 1 if type_ not in _SINGLE else 0)
            if last > S.SEQ_MAX:
                raise TrialFileError(
                    f"{self.path}: channel {name}, message {idx}: sequence number {seq} "
                    f"{'' if last == seq else f'(+{last - seq}) '}is beyond the largest the schema allows "
                    f"(SEQ_MAX = 2**53 − 1 = {S.SEQ_MAX}); the bridge that wrote it broke the schema")
            yield name, msg.log_time, block


def list_axes(path) -> list[str]:
    """``machine/axis`` of every samples channel in a trial file."""
    with _Open(path) as f:
        return [f"{m}/{a}" for m, a in f.axes()]


def iter_blocks(path, axis: str | None = None, kinds: Sequence[str] = ("samples",)) -> Iterator[tuple[str, object]]:
    """Replay iterator: ``(kind, block)`` of one axis in file (sequence) order.

    ``kinds`` any of "samples", "truth", "disturbance", "disturbance/scalars", "health" (absent
    channels are skipped).
    """
    f = _Open(path)
    try:
        machine, ax = f.select(axis)
        topics = [topic(machine, ax, k) for k in kinds]
        topics = [t for t in topics if t in f.channels]
        for name, _, block in f.messages(topics):
            yield _split_topic(name)[2], block
    finally:
        f.close()


def iter_file(path, axes: Sequence[str], kinds: Sequence[str] = ("samples",)) -> Iterator[tuple[str, str, int, object]]:
    """``(axis, kind, log_time, block)`` of the given axes (``machine/axis``) and kinds in file
    order, in one pass over the file."""
    f = _Open(path)
    try:
        wanted: dict[str, tuple[str, str]] = {}
        for name in axes:
            machine, ax = f.select(name)
            for k in kinds:
                tp = topic(machine, ax, k)
                if tp in f.channels:
                    wanted[tp] = (name, k)
        for tp, lt, block in f.messages(list(wanted)):
            name, kind = wanted[tp]
            yield name, kind, lt, block
    finally:
        f.close()


class AxisStreams(dict):
    """What :func:`iter_axes` returns: axis name → iterator, plus how the read-ahead went."""

    own_passes = 0  #: axes that left the shared pass and re-read the file on their own
    peak_bytes = 0  #: most bytes of blocks (:func:`held_bytes`) that waited at once


def held_bytes(block) -> int:
    """About the memory (bytes) a decoded block holds: 32 per list element (a float object and its
    pointer), 64 per field and 256 for the object. What the byte bounds of read-ahead buffers count."""
    n = 256
    for name in block.__struct_fields__:
        v = getattr(block, name)
        n += 64 + (32 * len(v) if isinstance(v, list) else 0)
    return n


def iter_axes(path, axes: Sequence[str], kinds: Sequence[str] = ("samples",), *,
              read_ahead_bytes: int = MAX_READ_AHEAD_BYTES) -> AxisStreams:
    """One iterator of ``(kind, log_time, block)`` per axis (``machine/axis``), fed by **one**
    pass over the file (:func:`iter_file`) as long as the axes are interleaved in time, so reading
    N axes costs one read, not N. Blocks of the axes not being consumed wait in memory, at most
    ``read_ahead_bytes`` of them (:func:`held_bytes`); beyond, those axes are dropped from the
    shared pass and each re-reads the file on its own from the block it had reached (its waiting
    blocks are read again), so memory stays bounded whatever the order of the file, at the cost
    of one more read per such axis (counted in the result's :attr:`AxisStreams.own_passes`).
    Meant for consuming the axes together, e.g. merged with ``heapq.merge``."""
    source = iter_file(path, axes, kinds)
    queues: dict[str, deque] = {name: deque() for name in axes}
    given = dict.fromkeys(axes, 0)  # items handed out per axis
    own: set[str] = set()  # axes that left the shared pass
    state = {"held": 0, "done": False, "open": len(axes)}
    info = AxisStreams()

    def spill(consumer: str) -> None:
        for name, q in queues.items():
            if name != consumer and q:
                state["held"] -= sum(size for *_, size in q)
                q.clear()
                own.add(name)
                info.own_passes += 1

    def own_pass(axis_name: str) -> Iterator[tuple[str, int, object]]:
        for j, (_, kind, lt, block) in enumerate(iter_file(path, [axis_name], kinds)):
            if j >= given[axis_name]:
                yield kind, lt, block

    def stream(axis_name: str) -> Iterator[tuple[str, int, object]]:
        q = queues[axis_name]
        try:
            while axis_name not in own:
                if q:
                    *item, size = q.popleft()
                    state["held"] -= size
                    given[axis_name] += 1
                    yield tuple(item)
                    continue
                if state["done"]:
                    return
                try:
                    target, kind, lt, block = next(source)
                except StopIteration:
                    state["done"] = True
                    continue
                if target == axis_name:
                    given[axis_name] += 1
                    yield kind, lt, block
                elif target not in own:
                    size = held_bytes(block)
                    queues[target].append((kind, lt, block, size))
                    state["held"] += size
                    info.peak_bytes = max(info.peak_bytes, state["held"])
                    if state["held"] > read_ahead_bytes:
                        spill(axis_name)
            yield from own_pass(axis_name)
        finally:
            state["open"] -= 1
            if state["open"] == 0:
                source.close()

    info.update((name, stream(name)) for name in axes)
    return info


def _column(blocks, name: str, n_total: int) -> np.ndarray | None:
    cols = [getattr(b, name) for b in blocks]
    if all(c is None for c in cols):
        return None
    out = []
    for b, c in zip(blocks, cols):
        out.extend(c if c is not None else [None] * len(b.t))
    arr = np.array(out, dtype=np.float64)
    assert arr.size == n_total
    return arr


def _seq(blocks) -> np.ndarray:
    if not blocks:
        return np.zeros(0, dtype=np.int64)
    return np.concatenate([np.arange(b.seq, b.seq + len(b.t), dtype=np.int64) for b in blocks])


#: most samples :func:`read_trial` keeps of one axis (the decoded blocks take ~200 bytes per sample while
#: reading: ~2 GB at this limit); ``feedmon run --from`` and ``replay`` stream a trial of any length
MAX_TRIAL_SAMPLES = 10_000_000


class TrialTooLong(TrialFileError):
    """The axis holds more than the ``max_samples`` :func:`read_trial` was given (``limit``)."""

    def __init__(self, message: str, limit: int) -> None:
        super().__init__(message)
        self.limit = limit


def read_trial(path, axis: str | None = None, *, limits: Limits = DEFAULT_LIMITS,
               max_samples: int = MAX_TRIAL_SAMPLES) -> Trial:
    """Read one axis of a trial file into arrays.

    ``axis`` "X" or "machine/X"; required when the file holds several axes. Reading stops with
    :class:`TrialTooLong` as soon as the axis has more than ``max_samples`` samples (memory stays bounded).
    Raises :class:`TrialFileError` (a ValueError) naming file, channel and problem.
    """
    with _Open(path, limits) as f:
        machine, ax = f.select(axis)
        meta = f.meta(machine, ax)
        start = f.start_ns(machine, ax)
        t_s, t_t, t_e = topic(machine, ax, "samples"), topic(machine, ax, "truth"), topic(machine, ax, TRUTH_EVENTS)
        topics = [t_s] + [x for x in (t_t, t_e) if x in f.channels]
        samples, truths, events = [], [], []
        held = {t_s: 0, t_t: 0, t_e: 0}
        for name, _, block in f.messages(topics):
            if name == t_e:
                events.append(block)
                held[name] += 1
            else:
                (samples if name == t_s else truths).append(block)
                held[name] += len(block.t)
            if held[name] > max_samples:
                raise TrialTooLong(f"{f.path}: axis {machine}/{ax} holds more than {max_samples:,} samples, the most "
                                   "read into memory at once; identify a window of it or a shorter recording (the offline "
                                   "run and the replay stream a trial of any length)", max_samples)
        if not samples:
            raise TrialFileError(f"{f.path}: channel {t_s} has no messages")
        n = sum(len(b.t) for b in samples)
        trial = Trial(
            path=f.path,
            machine=machine,
            axis=ax,
            meta=meta,
            seq=_seq(samples),
            t=np.array([x for b in samples for x in b.t], dtype=np.float64),
            v_ref=_column(samples, "v_ref", n),
            v_meas=_column(samples, "v_meas", n),
            u=_column(samples, "u", n),
            current=_column(samples, "current", n),
            position=_column(samples, "position", n),
            spindle_rpm=_column(samples, "spindle_rpm", n),
            spindle_angle=_column(samples, "spindle_angle", n),
            program_line=_column(samples, "program_line", n),
            tool=_column(samples, "tool", n),
            channels=sorted(f.channels),
            start_ns=start,
            truth_events=events,
        )
        if truths:
            m = sum(len(b.t) for b in truths)
            glitch = None
            if any(b.glitch is not None for b in truths):
                glitch = np.array(
                    [g for b in truths for g in (b.glitch if b.glitch is not None else [False] * len(b.t))], dtype=bool
                )
            trial.truth = TruthArrays(
                seq=_seq(truths),
                t=np.array([x for b in truths for x in b.t], dtype=np.float64),
                force=_column(truths, "force", m),
                f=_column(truths, "f", m),
                dynamometer=_column(truths, "dynamometer", m),
                v_true=_column(truths, "v_true", m),
                glitch=glitch,
                inertia=_column(truths, "inertia", m),
                damping=_column(truths, "damping", m),
                coulomb_pos=_column(truths, "coulomb_pos", m),
                coulomb_neg=_column(truths, "coulomb_neg", m),
            )
        return trial
