"""Writing trial files (layout: :mod:`feedio.trialformat`): :class:`TrialWriter`, and
:func:`write_arrays` for an axis given as arrays.

A failed write never corrupts the writer: every value that could overflow the file format is checked
before the record writer (:class:`feedio.mcapwriter.McapWriter`) sees it, and the records are written
into memory (:class:`_StagedFile`) that is committed to the file on flush — a disk that refuses the
bytes leaves the file ending on a complete record and the bytes waiting for the next flush (up to
:data:`~feedio.trialformat.MAX_PENDING_BYTES`, then the file is given up, see :attr:`TrialWriter.failed`).
"""

from __future__ import annotations

import math
import os
import time
from collections import deque
from collections.abc import Sequence

import msgspec
import numpy as np

from feedio import schema as S

from .mcapfile import TrialFileError
from .mcapwriter import MESSAGE_HEADER, McapWriter
from .trialformat import (
    ALARM,
    CHANNEL_KINDS,
    HEALTH,
    MAX_LOG_TIME_NS,
    MAX_MESSAGE_BYTES,
    MAX_PENDING_BYTES,
    METADATA_NAME,
    SCALARS,
    TRUTH_EVENTS,
    ZSTD_LEVEL,
    check_name,
    format_time,
    library,
    now_ns,
    parse_time,
    topic,
)

__all__ = ["TrialWriter", "write_arrays"]


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
            key = (check_name("machine", m.machine), check_name("axis", m.axis))
            if key in self.metas:
                raise ValueError(f"axis {m.machine}/{m.axis} declared twice")
            self.metas[key] = m
        if not (chunk_seconds > 0):
            raise ValueError("chunk_seconds must be > 0")
        comp = {"zstd": "zstd", "lz4": "lz4", "none": ""}.get(compression)
        if comp is None:
            raise ValueError(f"compression {compression!r}: use zstd, lz4 or none")
        self.start_ns = now_ns() if start is None else parse_time(start)
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
        self._writer.start(profile="", library=library())
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

        type_ = CHANNEL_KINDS[kind]
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
