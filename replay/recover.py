"""Salvage an MCAP file whose writer died (SIGKILL, power loss, disk full) or that was damaged.

A writer killed mid-run leaves a file without the summary section, footer and end
magic, possibly ending in a half-written chunk; a disk that filled up may leave a
half-written chunk *in the middle*, followed by what was written once space came
back; a bad sector or a flipped bit damages one chunk among many. :func:`recover`
reads the file record by record (:mod:`feedio.mcapfile`: every length checked, every
chunk decompressed under a bound and CRC-checked) and **resynchronises after damage**
on the next record that is provably intact, and writes everything intact into a new,
complete MCAP file:

* the header (profile and library string kept), schemas, channels (topics,
  encodings, channel metadata), metadata records and attachments;
* every message of every intact chunk, with log time, publish time, sequence and data
  unchanged; chunk boundaries are kept (one output chunk per source chunk, the same
  compression and maximum chunk size as :class:`feedio.mcapio.TrialWriter`);
* of a chunk cut off by the end of the file, every *complete* record of the part that
  decompresses — the writer stopped there, so these bytes are as written (counted as
  ``partial_messages``; no CRC covers a partial chunk). A chunk cut off *inside* the file
  (an intact record starts within it) is skipped whole: that is a write that failed and was
  retried (a full disk), and its records are in the retry;
* of a chunk that fails its CRC or its decompression, the schema and channel declarations
  (so the messages of later chunks keep their channel); its messages are dropped, as a
  flipped bit may be in any of them (``salvage_damaged=True`` keeps those that parse);
* when the file's summary section is intact, its schemas and channels stand in for
  declarations lost with a damaged chunk;
* one extra metadata record ``feedmon.recover`` saying what was done (source file, bytes
  dropped, every skipped range with its offset and reason, where the file was cut off).

A record is accepted after damage only when its layout is exact (every length consistent)
and, for a chunk, it decompresses and passes its CRC; other records must also be followed
by a plausible record header. Index, statistics and summary records of the source are not
copied; the writer regenerates them. Message payloads are copied as opaque bytes and never
decoded, so any MCAP file can be recovered, not only feedmon trials.

On a healthy file the result is a lossless copy (same records, same chunking, plus the
``feedmon.recover`` record).
"""

from __future__ import annotations

import mmap
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from feedio.mcapfile import (
    DEFAULT_LIMITS,
    Chunk,
    Limits,
    RecordError,
    check_chunk_size,
    decompress,
    iter_inner,
    parse_record,
)
from feedio.mcapspec import MAGIC, OP_NAMES, RECORD_HEAD, Op

__all__ = ["RECOVER_METADATA_NAME", "ChannelStats", "Skipped", "RecoverReport", "recover", "MAX_SKIPPED_LISTED"]

RECOVER_METADATA_NAME = "feedmon.recover"
_COMPRESSIONS = ("zstd", "lz4", "none")
_KNOWN = frozenset(OP_NAMES)
#: skipped ranges listed one by one in the report (the rest are counted)
MAX_SKIPPED_LISTED = 100
_WINDOW = 1 << 22  # bytes scanned per numpy pass while resynchronising


@dataclass
class ChannelStats:
    """Messages recovered on one channel."""

    topic: str
    message_encoding: str
    schema_name: str
    messages: int = 0
    first_log_time: int | None = None  # ns
    last_log_time: int | None = None  # ns


@dataclass
class Skipped:
    """A damaged range of the source that was skipped."""

    offset: int
    length: int
    reason: str
    messages_dropped: int = 0  # messages known to be in it and not kept (damaged chunk that could be read)


@dataclass
class RecoverReport:
    """What :func:`recover` read, kept and dropped."""

    source: str
    output: str
    source_bytes: int
    bytes_dropped: int = 0  # bytes of skipped ranges, of partly kept chunks and of a cut-off end
    complete: bool = False  # footer and end magic found and nothing skipped: nothing was lost
    data_complete: bool = False  # data section read to its end (DataEnd record)
    data_crc_ok: bool | None = None  # the DataEnd's CRC matched (None: not stored or not reached)
    stop_offset: int | None = None  # where the file is cut off (None: it ends properly)
    stop_reason: str | None = None
    chunks: int = 0  # intact chunks copied
    chunks_dropped: int = 0  # chunks that failed their check (messages dropped, declarations kept)
    partial_chunks: int = 0  # cut-off chunks whose complete records were kept
    partial_messages: int = 0  # messages kept from cut-off chunks
    damaged_messages: int = 0  # messages of damaged chunks (dropped, or kept with salvage_damaged)
    unchunked_messages: int = 0
    orphan_messages: int = 0  # messages of a channel that was never declared (dropped)
    schemas: int = 0
    metadata: int = 0
    attachments: int = 0
    skipped: list[Skipped] = field(default_factory=list)  # the first MAX_SKIPPED_LISTED ranges
    skipped_ranges: int = 0
    channels: dict[int, ChannelStats] = field(default_factory=dict)  # output channel id -> stats
    salvage_damaged: bool = False  # messages of damaged chunks were kept

    @property
    def bytes_used(self) -> int:
        return self.source_bytes - self.bytes_dropped

    @property
    def messages(self) -> int:
        return sum(c.messages for c in self.channels.values())

    @property
    def last_log_time(self) -> int | None:
        times = [c.last_log_time for c in self.channels.values() if c.last_log_time is not None]
        return max(times) if times else None

    def skip(self, offset: int, length: int, reason: str, messages: int = 0) -> None:
        self.skipped_ranges += 1
        self.bytes_dropped += length
        if len(self.skipped) < MAX_SKIPPED_LISTED:
            self.skipped.append(Skipped(offset, length, reason, messages))

    def summary(self) -> str:
        """Human-readable report (several lines)."""
        lines = [
            f"recovered {self.source} -> {self.output}: {self.chunks} chunk(s), "
            f"{len(self.channels)} channel(s), {self.messages} message(s), {self.metadata} metadata record(s)"
            + (f", {self.attachments} attachment(s)" if self.attachments else "")
        ]
        width = max((len(c.topic) for c in self.channels.values()), default=0)
        for c in self.channels.values():
            span = "no messages"
            if c.messages:
                span = f"log time {c.first_log_time / 1e9:.6f} … {c.last_log_time / 1e9:.6f} s"
            lines.append(f"  {c.topic:<{width}}  {c.messages:>8} messages  {span}")
        last = self.last_log_time
        if last is not None:
            lines.append(f"last log time: {last / 1e9:.6f} s ({last} ns)")
        if self.complete:
            lines.append(f"the source was complete (footer and end magic present): all {self.source_bytes} bytes read, "
                         "nothing lost")
        if self.skipped_ranges:
            lines.append(f"skipped {self.skipped_ranges} damaged range(s) and resynchronised after each:")
            for s in self.skipped[:10]:
                lost = f", {s.messages_dropped} message(s) dropped" if s.messages_dropped else ""
                lines.append(f"  bytes {s.offset}…{s.offset + s.length} ({s.length} bytes): {s.reason}{lost}")
            if self.skipped_ranges > 10:
                lines.append(f"  … {self.skipped_ranges - 10} more (see --json)")
        if self.stop_reason is not None:
            where = "summary section" if self.data_complete else "data section"
            lines.append(f"the source is incomplete: it ends at byte {self.stop_offset} of {self.source_bytes} in the "
                         f"{where} ({self.stop_reason})"
                         + ("; all messages were recovered (only the index was lost)"
                            if self.data_complete and not self.skipped_ranges else ""))
        if not self.complete:
            lines.append(f"{self.bytes_dropped} byte(s) dropped")
        if self.partial_chunks:
            lines.append(f"{self.partial_messages} message(s) kept from {self.partial_chunks} cut-off chunk(s) "
                         "(their complete records)")
        if self.chunks_dropped:
            kept = "kept unverified (--salvage-damaged)" if self.salvage_damaged else "dropped"
            lines.append(f"{self.chunks_dropped} chunk(s) failed their check; their {self.damaged_messages} "
                         f"message(s) were {kept}, their declarations kept")
        if self.data_crc_ok is False:
            lines.append("the data section's CRC does not match: bytes were changed (the damaged chunks above)")
        if self.orphan_messages:
            lines.append(f"{self.orphan_messages} message(s) on undeclared channels were dropped")
        return "\n".join(lines)

    def as_dict(self) -> dict:
        """The report as plain JSON types (``feedmon recover --json``)."""
        return {
            "source": self.source, "output": self.output, "source_bytes": self.source_bytes,
            "bytes_used": self.bytes_used, "bytes_dropped": self.bytes_dropped,
            "complete": self.complete, "data_complete": self.data_complete, "data_crc_ok": self.data_crc_ok,
            "stop_offset": self.stop_offset, "stop_reason": self.stop_reason,
            "chunks": self.chunks, "chunks_dropped": self.chunks_dropped,
            "partial_chunks": self.partial_chunks, "partial_messages": self.partial_messages,
            "damaged_messages": self.damaged_messages, "messages": self.messages,
            "orphan_messages": self.orphan_messages, "metadata": self.metadata, "attachments": self.attachments,
            "skipped_ranges": self.skipped_ranges,
            "skipped": [{"offset": s.offset, "length": s.length, "reason": s.reason,
                         "messages_dropped": s.messages_dropped} for s in self.skipped],
            "last_log_time_ns": self.last_log_time,
            "channels": {c.topic: {"messages": c.messages, "first_log_time_ns": c.first_log_time,
                                   "last_log_time_ns": c.last_log_time, "message_encoding": c.message_encoding,
                                   "schema": c.schema_name}
                         for c in self.channels.values()},
        }


class _Copier:
    """Re-writes records into a new MCAP file, mapping source ids to output ids."""

    def __init__(self, stream, header, compression: str, chunk_size: int, chunk_seconds: float, report: RecoverReport,
                 fallback_schemas: dict, fallback_channels: dict):
        from feedio.mcapio import ZSTD_LEVEL
        from feedio.mcapwriter import McapWriter

        # the trial writer's own writer and zstd level: a healthy chunk feedmon wrote comes out as it went in
        self.writer = McapWriter(stream, chunk_size=chunk_size, compression={"none": ""}.get(compression, compression),
                                 compression_level=ZSTD_LEVEL, enable_data_crcs=True)
        self.writer.start(profile=header.profile, library=header.library)
        self.report = report
        self.schema_ids: dict[int, int] = {0: 0}  # source schema id -> output id (0 = no schema)
        self.schema_names: dict[int, str] = {0: ""}
        self.channel_ids: dict[int, int] = {}
        self.known_schemas: dict = {}  # declarations seen in the source, registered or not
        self.known_channels: dict = {}
        self.fallback_schemas = fallback_schemas
        self.fallback_channels = fallback_channels
        self.chunk_seconds_ns = int(chunk_seconds * 1e9)
        self._loose_t0: int | None = None  # first log time of unchunked messages since the last flush

    def schema(self, rec) -> None:
        self.known_schemas.setdefault(rec.id, rec)
        if rec.id == 0 or rec.id in self.schema_ids:
            return  # repeated (summary section) or invalid id 0
        self.schema_ids[rec.id] = self.writer.register_schema(name=rec.name, encoding=rec.encoding, data=rec.data)
        self.schema_names[rec.id] = rec.name
        self.report.schemas += 1

    def channel(self, rec) -> bool:
        self.known_channels.setdefault(rec.id, rec)
        if rec.id in self.channel_ids:
            return True
        if rec.schema_id not in self.schema_ids:
            fallback = self.known_schemas.get(rec.schema_id) or self.fallback_schemas.get(rec.schema_id)
            if fallback is None:
                return False  # schema never seen: the channel cannot be written correctly
            self.schema(fallback)
        cid = self.writer.register_channel(
            topic=rec.topic, message_encoding=rec.message_encoding, schema_id=self.schema_ids[rec.schema_id],
            metadata=dict(rec.metadata),
        )
        self.channel_ids[rec.id] = cid
        self.report.channels[cid] = ChannelStats(
            topic=rec.topic, message_encoding=rec.message_encoding, schema_name=self.schema_names[rec.schema_id]
        )
        return True

    def message(self, rec) -> bool:
        cid = self.channel_ids.get(rec.channel_id)
        if cid is None:
            decl = self.known_channels.get(rec.channel_id) or self.fallback_channels.get(rec.channel_id)
            if decl is None or not self.channel(decl):
                self.report.orphan_messages += 1
                return False
            cid = self.channel_ids[rec.channel_id]
        self.writer.add_message(channel_id=cid, log_time=rec.log_time, data=bytes(rec.data),
                                publish_time=rec.publish_time, sequence=rec.sequence)
        st = self.report.channels[cid]
        st.messages += 1
        st.first_log_time = rec.log_time if st.first_log_time is None else min(st.first_log_time, rec.log_time)
        st.last_log_time = rec.log_time if st.last_log_time is None else max(st.last_log_time, rec.log_time)
        return True

    def loose_message(self, rec) -> None:
        """A message outside any chunk (unchunked source): chunk by ``chunk_seconds`` of log time."""
        if self.message(rec):
            self.report.unchunked_messages += 1
        if self._loose_t0 is None:
            self._loose_t0 = rec.log_time
        elif rec.log_time - self._loose_t0 >= self.chunk_seconds_ns:
            self.flush()

    def records(self, records, *, messages: bool = True) -> int:
        """Copy ``(opcode, parsed record)`` of one source chunk as one output chunk; messages kept."""
        self.flush()  # a source chunk never shares an output chunk with loose messages
        kept = 0
        for opcode, r in records:
            if opcode == Op.SCHEMA:
                self.schema(r)
            elif opcode == Op.CHANNEL:
                self.channel(r)
            elif opcode == Op.MESSAGE and messages:
                kept += self.message(r)
        self.flush()
        return kept

    def flush(self) -> None:
        self.writer.flush()
        self._loose_t0 = None


def _inner_records(data: bytes, *, strict: bool) -> tuple[list, int]:
    """Parsed (opcode, record) of decompressed chunk data and the number of messages among them.
    ``strict``: any damage raises RecordError; else the complete, well-formed prefix."""
    out = []
    n_msg = 0
    try:
        for _, opcode, body in iter_inner(data, strict=strict):
            if opcode in (Op.SCHEMA, Op.CHANNEL, Op.MESSAGE):
                out.append((opcode, parse_record(opcode, body, exact=True)))
                n_msg += opcode == Op.MESSAGE
    except RecordError:
        if strict:
            raise
    return out, n_msg


class _Source:
    """The source file, memory-mapped, with the record checks used while resynchronising."""

    def __init__(self, mm: mmap.mmap, size: int, limits: Limits):
        self.mm, self.size, self.limits = mm, size, limits
        self.channel_ids: set[int] = set()  # channels declared so far (plausibility of loose messages)

    def header_at(self, pos: int) -> tuple[int, int] | None:
        if pos + 9 > self.size:
            return None
        return RECORD_HEAD.unpack_from(self.mm, pos)

    def plausible_next(self, pos: int, *, strict: bool) -> bool:
        """Could a record (or the end of the file) start at ``pos``?"""
        if pos == self.size:
            return True
        hdr = self.header_at(pos)
        if hdr is None:
            return not strict  # a cut-off header
        opcode, length = hdr
        if pos + 8 == self.size and self.mm[pos:pos + 8] == MAGIC:
            return True
        if opcode not in _KNOWN and opcode < 0x80:
            return False
        return not strict or length <= self.size - pos - 9

    def chunk(self, pos: int, length: int) -> Chunk:
        return parse_record(Op.CHUNK, self.mm[pos + 9:pos + 9 + length], exact=True)

    def valid_at(self, pos: int) -> bool:
        """Strict check that an intact record starts at ``pos`` (resynchronisation)."""
        hdr = self.header_at(pos)
        if hdr is None:
            return False
        opcode, length = hdr
        if opcode not in _KNOWN or opcode == Op.HEADER or length > self.size - pos - 9:
            return False
        end = pos + 9 + length
        if opcode == Op.FOOTER:
            return length == 20 and end + 8 == self.size and self.mm[end:end + 8] == MAGIC
        if length > self.limits.record_bytes:
            return False
        try:
            rec = parse_record(opcode, self.mm[pos + 9:end], exact=True)
            if opcode == Op.CHUNK:
                data, problem = decompress(rec, self.limits, partial=False)
                if not rec.uncompressed_crc:
                    _inner_records(data, strict=True)
                return True
            if opcode == Op.MESSAGE and rec.channel_id not in self.channel_ids:
                return False
            if opcode == Op.ATTACHMENT and rec.crc and zlib.crc32(self.mm[pos + 9:end - 4]) != rec.crc:
                return False
            if opcode == Op.DATA_END and length != 4:
                return False
        except RecordError:
            return False
        return self.plausible_next(end, strict=True)

    def resync(self, start: int, stop: int | None = None) -> int | None:
        """The first offset in [``start``, ``stop``) where :meth:`valid_at` holds (None: none)."""
        mm, size = self.mm, self.size
        limit = size - 9 if stop is None else min(size - 9, stop - 1)
        pos = start
        while pos <= limit:
            stop = min(limit, pos + _WINDOW)  # candidate starts in [pos, stop]
            arr = np.frombuffer(mm, dtype=np.uint8, count=stop + 9 - pos, offset=pos)
            op = arr[: stop - pos + 1]
            cand = (op >= 1) & (op <= 0x0F)
            for k in range(5, 9):  # length < 2**32: its four high bytes are zero
                cand &= arr[k: k + stop - pos + 1] == 0
            hits = np.flatnonzero(cand)
            del arr, op, cand
            for h in hits.tolist():
                if self.valid_at(pos + h):
                    return pos + h
            pos = stop + 1
        return None


def _crc(mm, start: int, end: int) -> int:
    crc = 0
    for a in range(start, end, _WINDOW):
        crc = zlib.crc32(mm[a:min(end, a + _WINDOW)], crc)
    return crc


def _summary_declarations(mm, size: int, limits: Limits) -> tuple[dict, dict]:
    """Schemas and channels of the source's summary section, when its footer and CRC are intact."""
    schemas: dict = {}
    channels: dict = {}
    foot = size - 8 - 29
    if foot < 8 or mm[size - 8:size] != MAGIC:
        return schemas, channels
    opcode, length = RECORD_HEAD.unpack_from(mm, foot)
    if opcode != Op.FOOTER or length != 20:
        return schemas, channels
    footer = parse_record(Op.FOOTER, mm[foot + 9:foot + 29])
    s0 = footer.summary_start
    if not 8 < s0 < foot:
        return schemas, channels
    if footer.summary_crc and _crc(mm, s0, foot + 25) != footer.summary_crc:
        return schemas, channels
    if foot - s0 > limits.summary_bytes:
        return schemas, channels
    try:
        for _, opcode, body in iter_inner(mm[s0:foot]):
            if opcode == Op.SCHEMA:
                rec = parse_record(opcode, body)
                schemas[rec.id] = rec
            elif opcode == Op.CHANNEL:
                rec = parse_record(opcode, body)
                channels[rec.id] = rec
    except RecordError:
        pass
    return schemas, channels


def recover(
    source: str | os.PathLike,
    output: str | os.PathLike,
    *,
    compression: str = "zstd",
    chunk_size: int = 4 * 1024 * 1024,
    chunk_seconds: float = 1.0,
    salvage_damaged: bool = False,
    limits: Limits = DEFAULT_LIMITS,
) -> RecoverReport:
    """Copy every intact record of ``source`` (an MCAP file, possibly cut off or damaged) into ``output``.

    ``compression`` (zstd, lz4, none) and ``chunk_size`` (bytes, uncompressed) as in
    :class:`feedio.mcapio.TrialWriter`; source chunks are kept as they are (split
    further only if larger than ``chunk_size``); messages written outside chunks are
    grouped into chunks of ``chunk_seconds`` of log time. ``salvage_damaged``: also keep
    the messages of chunks that fail their CRC (they may hold a changed byte).

    The output is written to a temporary file next to it and renamed at the end, so
    it is either a complete MCAP file or not there. Raises ``ValueError`` (naming the
    file) when ``source`` is not an MCAP file or not even its header is complete,
    ``OSError`` when a file cannot be read or written.
    """
    if compression not in _COMPRESSIONS:
        raise ValueError(f"compression {compression!r}: use {', '.join(_COMPRESSIONS)}")
    if not chunk_size > 0:
        raise ValueError(f"chunk size must be > 0 bytes, got {chunk_size}")
    if not chunk_seconds > 0:
        raise ValueError(f"chunk seconds must be > 0, got {chunk_seconds}")
    src, dst = Path(source), Path(output)
    if not src.is_file():
        raise FileNotFoundError(f"{src}: no such file")
    if dst.exists() and os.path.samefile(src, dst):
        raise ValueError(f"output {dst} is the input file; write the recovered copy to another file")

    with open(src, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        head = f.read(8)
        if head != MAGIC:
            if not head:
                raise ValueError(f"{src} is empty (0 bytes): nothing to recover")
            if MAGIC.startswith(head):
                raise ValueError(f"{src} ends inside the MCAP magic ({size} bytes): nothing to recover")
            raise ValueError(f"{src} is not an MCAP file (it starts with {head!r}, not the MCAP magic {MAGIC!r})")
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            return _recover(mm, size, src, dst, compression, chunk_size, chunk_seconds, salvage_damaged, limits)
        finally:
            mm.close()


def _recover(mm, size, src, dst, compression, chunk_size, chunk_seconds, salvage_damaged, limits) -> RecoverReport:
    source = _Source(mm, size, limits)
    hdr = source.header_at(8)
    if hdr is None or hdr[1] > size - 17:
        raise ValueError(f"{src}: no complete MCAP header record (cut off at byte {size}): nothing to recover")
    if hdr[0] != Op.HEADER:
        raise ValueError(f"{src}: the first MCAP record is {OP_NAMES.get(hdr[0], f'opcode {hdr[0]:#04x}')}, "
                         "not a Header: not a valid MCAP file")
    try:
        header = parse_record(Op.HEADER, mm[17:17 + hdr[1]])
    except RecordError as exc:
        raise ValueError(f"{src}: the MCAP header record is corrupt ({exc}): nothing to recover") from None
    report = RecoverReport(source=str(src), output=str(dst), source_bytes=size)
    report.salvage_damaged = salvage_damaged
    fb_schemas, fb_channels = _summary_declarations(mm, size, limits)
    source.channel_ids.update(fb_channels)
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.recover-tmp")
    try:
        with open(tmp, "wb") as out:
            cp = _Copier(out, header, compression, chunk_size, chunk_seconds, report, fb_schemas, fb_channels)
            _copy_records(source, cp, report, salvage_damaged, 17 + hdr[1])
            cp.flush()
            cp.writer.add_metadata(RECOVER_METADATA_NAME, _recover_metadata(report))
            cp.writer.finish()
        os.replace(tmp, dst)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return report


def _copy_records(source: _Source, cp: _Copier, report: RecoverReport, salvage_damaged: bool, pos: int) -> None:
    mm, size, limits = source.mm, source.size, source.limits
    last_op = Op.HEADER
    while True:
        if pos == size:
            if last_op != Op.FOOTER:
                report.stop_offset = size
                report.stop_reason = ("the file ends after a complete record, before its "
                                      + ("summary section" if report.data_complete else "DataEnd record")
                                      + " (the writer stopped)")
            break
        if last_op == Op.FOOTER:
            if size - pos == 8 and mm[pos:size] == MAGIC:
                report.complete = report.skipped_ranges == 0
                break
            report.stop_offset, report.stop_reason = pos, "no end magic after the footer"
            report.bytes_dropped += size - pos
            break
        hdr = source.header_at(pos)
        if hdr is None:
            report.stop_offset, report.stop_reason = pos, "record header cut off"
            report.bytes_dropped += size - pos
            break
        opcode, length = hdr
        name = OP_NAMES.get(opcode, f"record with opcode {opcode:#04x}")
        end = pos + 9 + length
        fits = length <= size - pos - 9
        if fits and opcode >= 0x80:  # user opcodes: skipped, not damage
            pos = end
            continue
        if fits and opcode == Op.ATTACHMENT and length > limits.record_bytes and source.plausible_next(end, strict=True):
            report.skip(pos, 9 + length, f"attachment of {length} bytes, larger than the limit of "
                                         f"{limits.record_bytes}: not copied")
            pos = end
            continue
        problem = None
        if not fits:
            problem = f"{name} record declares {length} bytes, only {size - pos - 9} left"
        elif opcode not in _KNOWN:
            problem = f"invalid opcode {opcode:#04x}"
        elif length > limits.record_bytes:
            problem = f"{name} record of {length} bytes is larger than the limit of {limits.record_bytes}"
        elif not source.plausible_next(end, strict=False):
            problem = f"{name} record is followed by no valid record header (its length field is damaged)"
        rec = None
        if problem is None:
            body = mm[pos + 9:end]
            try:
                rec = parse_record(opcode, body, exact=True)
            except RecordError as exc:
                problem = f"{name} record is corrupt ({exc})"
                if opcode not in (Op.CHUNK, Op.DATA_END, Op.FOOTER) and source.plausible_next(end, strict=True):
                    try:  # a record with fields added by a newer MCAP version: trailing bytes allowed
                        rec, problem = parse_record(opcode, body), None
                    except RecordError:
                        pass
        if problem is not None:
            nxt = source.resync(pos + 1)
            if opcode == Op.CHUNK and nxt is None:  # the writer stopped inside this chunk: keep what it wrote
                _partial_chunk(source, cp, report, pos, size)
                report.stop_offset, report.stop_reason = pos, f"Chunk record cut off ({problem})"
                report.bytes_dropped += size - pos
                break
            if nxt is None:
                report.stop_offset = pos
                report.stop_reason = f"{name} {'cut off' if not fits else 'corrupt'} ({problem})"
                report.bytes_dropped += size - pos
                break
            else:
                report.skip(pos, nxt - pos, problem)
            pos = nxt
            continue
        # a record with an intact layout
        if opcode == Op.CHUNK:
            nxt = _chunk(source, cp, report, pos, length, rec, salvage_damaged)
            if nxt is not None:  # a damaged chunk that an intact record cuts short
                pos = nxt
                continue
        elif opcode == Op.SCHEMA:
            cp.schema(rec)
        elif opcode == Op.CHANNEL:
            cp.channel(rec)
            source.channel_ids.add(rec.id)
        elif opcode == Op.MESSAGE:
            cp.loose_message(rec)
        elif opcode == Op.METADATA:
            cp.flush()
            cp.writer.add_metadata(rec.name, dict(rec.metadata))
            report.metadata += 1
        elif opcode == Op.ATTACHMENT:
            cp.flush()
            cp.writer.add_attachment(create_time=rec.create_time, log_time=rec.log_time, name=rec.name,
                                     media_type=rec.media_type, data=bytes(rec.data))
            report.attachments += 1
        elif opcode == Op.DATA_END:
            report.data_complete = True
            if rec.data_section_crc:
                report.data_crc_ok = _crc(mm, 0, pos) == rec.data_section_crc
        elif opcode == Op.HEADER:
            nxt = source.resync(end)
            report.skip(pos, (nxt or size) - pos, "a second Header record (corrupt file)")
            if nxt is None:
                break
            pos = nxt
            continue
        # indexes, statistics, summary offsets, footer: regenerated by the writer
        last_op = opcode
        pos = end


def _chunk(source: _Source, cp: _Copier, report: RecoverReport, pos: int, length: int, chunk: Chunk,
           salvage_damaged: bool) -> int | None:
    """A chunk with an intact layout: copied when it decompresses and passes its CRC. Else, when an
    intact record starts inside it, it was a write cut short (and retried: a full disk) — skipped up
    to that record, whose offset is returned; otherwise it is damaged: its declarations are kept,
    its messages dropped (kept with ``salvage_damaged``)."""
    try:
        data, _ = decompress(chunk, source.limits)
        records, _ = _inner_records(data, strict=True)
    except RecordError as exc:
        problem = str(exc)
    else:
        cp.records(records)
        report.chunks += 1
        return None
    end = pos + 9 + length
    nxt = source.resync(pos + 1, stop=end)
    if nxt is not None and nxt < end:
        report.skip(pos, nxt - pos, f"chunk cut short by the record at byte {nxt} ({problem})")
        return nxt
    report.chunks_dropped += 1
    data = b""
    if check_chunk_size(chunk, source.limits) is None:
        data, _ = decompress(chunk, source.limits, partial=True)
    records, n_msg = _inner_records(data, strict=False)
    report.damaged_messages += n_msg
    for opcode, r in records:
        if opcode == Op.CHANNEL:
            source.channel_ids.add(r.id)
    cp.records(records, messages=salvage_damaged)
    report.skip(pos, 9 + length, f"damaged chunk ({problem})", 0 if salvage_damaged else n_msg)
    return None


def _partial_chunk(source: _Source, cp: _Copier, report: RecoverReport, pos: int, end: int) -> None:
    """A chunk cut off at ``end`` (the end of the file): its complete records."""
    mm = source.mm
    body = mm[pos + 9:end]
    # the chunk's fields up to its records; the records' bytes are what is present
    try:
        fixed = struct.unpack_from("<QQQI", body, 0)
        (clen,) = struct.unpack_from("<I", body, 28)
        compression = bytes(body[32:32 + clen]).decode("utf-8")
        (rlen,) = struct.unpack_from("<Q", body, 32 + clen)
    except (struct.error, UnicodeDecodeError):
        return
    start = 40 + clen
    data = body[start:start + rlen]
    chunk = Chunk(fixed[0], fixed[1], fixed[2], fixed[3], compression, data)
    if check_chunk_size(chunk, source.limits, compressed_size=rlen) is not None:
        return
    out, _ = decompress(chunk, source.limits, partial=True, compressed_size=rlen)
    records, n_msg = _inner_records(out, strict=False)
    if not records:
        return
    for opcode, r in records:
        if opcode == Op.CHANNEL:
            source.channel_ids.add(r.id)
    kept = cp.records(records)
    report.partial_chunks += 1
    report.partial_messages += kept


def _recover_metadata(report: RecoverReport) -> dict[str, str]:
    from feedio import __version__

    meta = {
        "source": os.path.basename(report.source),
        "source_bytes": str(report.source_bytes),
        "bytes_used": str(report.bytes_used),
        "bytes_dropped": str(report.bytes_dropped),
        "complete": "true" if report.complete else "false",
        "data_complete": "true" if report.data_complete else "false",
        "chunks": str(report.chunks),
        "chunks_dropped": str(report.chunks_dropped),
        "partial_messages": str(report.partial_messages),
        "messages": str(report.messages),
        "skipped_ranges": str(report.skipped_ranges),
        "skipped": "; ".join(f"{s.offset}+{s.length}: {s.reason}" for s in report.skipped[:20]),
        "tool": f"feedmon recover {__version__}",
    }
    if report.stop_reason:
        meta["stop_offset"] = str(report.stop_offset)
        meta["stop_reason"] = report.stop_reason
    return meta
