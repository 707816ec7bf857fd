"""Salvage an MCAP file whose writer died (SIGKILL, power loss, disk full).

A writer killed mid-run leaves a file without the summary section, footer and end
magic, possibly ending in a half-written chunk. :func:`recover` reads such a file
*sequentially* with mcap's low-level :class:`mcap.stream_reader.StreamReader`
(``emit_chunks=True``: chunks are checked and unpacked here, one at a time), stops
cleanly at the first truncated or corrupt record and writes everything before it
into a new, complete MCAP file:

* the header (profile and library string kept), schemas, channels (topics,
  encodings, channel metadata), metadata records and attachments;
* every message of every *complete* chunk (CRC of the uncompressed data checked
  when the writer stored one), with log time, publish time, sequence and data
  unchanged; chunk boundaries are kept (one output chunk per source chunk, the
  same compression and maximum chunk size as :class:`feedio.mcapio.TrialWriter`);
* one extra metadata record ``feedmon.recover`` saying what was done (source
  file, bytes read and dropped, where and why reading stopped).

A chunk is all-or-nothing: a chunk that is cut off or fails its CRC is dropped
whole. Index, statistics and summary records of the source are not copied; the
writer regenerates them. Message payloads are copied as opaque bytes and never
decoded, so any MCAP file can be recovered, not only feedmon trials.

On a healthy file the result is a lossless copy (same records, same chunking,
plus the ``feedmon.recover`` record).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["RECOVER_METADATA_NAME", "ChannelStats", "RecoverReport", "recover"]

RECOVER_METADATA_NAME = "feedmon.recover"
_MAGIC = b"\x89MCAP0\r\n"
_MAX_UNCOMPRESSED = 1 << 31  # a chunk claiming more than 2 GiB uncompressed is taken as corrupt
_COMPRESSIONS = ("zstd", "lz4", "none")


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
class RecoverReport:
    """What :func:`recover` read, kept and dropped."""

    source: str
    output: str
    source_bytes: int
    bytes_used: int = 0  # offset just after the last record that was read completely and kept
    complete: bool = False  # footer and end magic found: nothing was lost
    data_complete: bool = False  # data section read to its end (DataEnd record); only summary lost
    stop_offset: int | None = None  # offset of the record where reading stopped
    stop_reason: str | None = None
    chunks: int = 0
    chunks_dropped: int = 0  # complete-looking chunks rejected (CRC / decompression / record error)
    unchunked_messages: int = 0
    orphan_messages: int = 0  # messages of a channel that was never declared (dropped)
    schemas: int = 0
    metadata: int = 0
    attachments: int = 0
    channels: dict[int, ChannelStats] = field(default_factory=dict)  # output channel id -> stats

    @property
    def bytes_dropped(self) -> int:
        return self.source_bytes - self.bytes_used

    @property
    def messages(self) -> int:
        return sum(c.messages for c in self.channels.values())

    @property
    def last_log_time(self) -> int | None:
        times = [c.last_log_time for c in self.channels.values() if c.last_log_time is not None]
        return max(times) if times else None

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
            lines.append(f"the source was complete (footer and end magic present): all {self.source_bytes} bytes read, nothing lost")
        else:
            where = "summary section" if self.data_complete else "data section"
            lines.append(
                f"the source is incomplete: stopped at byte {self.stop_offset} of {self.source_bytes} "
                f"in the {where} ({self.stop_reason}); {self.bytes_dropped} byte(s) dropped"
                + ("; all messages were recovered (only the index was lost)" if self.data_complete else "")
            )
        if self.chunks_dropped:
            lines.append(f"{self.chunks_dropped} chunk(s) failed their check and were dropped")
        if self.orphan_messages:
            lines.append(f"{self.orphan_messages} message(s) on undeclared channels were dropped")
        return "\n".join(lines)


class _Stop(Exception):
    """Reading stops here: the record at ``offset`` is truncated or corrupt."""

    def __init__(self, offset: int, reason: str):
        super().__init__(reason)
        self.offset = offset
        self.reason = reason


def _record_header(fd: int, offset: int) -> tuple[int, int] | None:
    """(opcode, length) of the record at ``offset`` (read with pread, the stream position is untouched)."""
    raw = os.pread(fd, 9, offset)
    if len(raw) < 9:
        return None
    opcode, length = struct.unpack("<BQ", raw)
    return opcode, length


def _known_opcodes() -> frozenset[int]:
    from mcap.opcode import Opcode

    return frozenset(int(o) for o in Opcode)


_KNOWN_OPCODES = _known_opcodes()


def _opname(opcode: int | None) -> str:
    from mcap.opcode import Opcode

    if opcode is None:
        return "record header"
    try:
        return Opcode(opcode).name.title().replace("_", "") + " record"
    except ValueError:
        return f"record with unknown opcode 0x{opcode:02x}"


def _unpack_chunk(chunk):
    """Records inside a chunk (CRC checked); raises ValueError when the chunk is damaged."""
    from mcap.stream_reader import breakup_chunk

    if chunk.compression not in ("", "zstd", "lz4"):
        raise ValueError(f"unsupported chunk compression {chunk.compression!r}")
    if chunk.uncompressed_size > _MAX_UNCOMPRESSED:
        raise ValueError(f"implausible uncompressed size {chunk.uncompressed_size}")
    try:
        records = breakup_chunk(chunk, validate_crc=True)
    except Exception as exc:  # noqa: BLE001 - zstd/lz4 errors, CRCValidationError, EndOfFile, struct.error, UnicodeDecodeError
        raise ValueError(f"{type(exc).__name__}: {exc}") from None
    return records


class _Copier:
    """Re-writes records into a new MCAP file, mapping source ids to output ids."""

    def __init__(self, stream, header, compression: str, chunk_size: int, chunk_seconds: float, report: RecoverReport):
        from mcap.writer import CompressionType, Writer

        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
        self.writer = Writer(stream, chunk_size=chunk_size, compression=comp)
        self.writer.start(profile=header.profile, library=header.library)
        self.report = report
        self.schema_ids: dict[int, int] = {0: 0}  # source schema id -> output id (0 = no schema)
        self.schema_names: dict[int, str] = {0: ""}
        self.channel_ids: dict[int, int] = {}
        self.chunk_seconds_ns = int(chunk_seconds * 1e9)
        self._loose_t0: int | None = None  # first log time of unchunked messages since the last flush

    def schema(self, rec) -> None:
        if rec.id == 0 or rec.id in self.schema_ids:
            return  # repeated (summary section) or invalid id 0
        self.schema_ids[rec.id] = self.writer.register_schema(name=rec.name, encoding=rec.encoding, data=rec.data)
        self.schema_names[rec.id] = rec.name
        self.report.schemas += 1

    def channel(self, rec) -> bool:
        if rec.id in self.channel_ids:
            return True
        sid = self.schema_ids.get(rec.schema_id)
        if sid is None:
            return False  # schema never seen: the channel cannot be written correctly
        cid = self.writer.register_channel(
            topic=rec.topic, message_encoding=rec.message_encoding, schema_id=sid, metadata=dict(rec.metadata)
        )
        self.channel_ids[rec.id] = cid
        self.report.channels[cid] = ChannelStats(
            topic=rec.topic, message_encoding=rec.message_encoding, schema_name=self.schema_names[rec.schema_id]
        )
        return True

    def message(self, rec) -> None:
        cid = self.channel_ids.get(rec.channel_id)
        if cid is None:
            self.report.orphan_messages += 1
            return
        self.writer.add_message(
            channel_id=cid, log_time=rec.log_time, data=rec.data, publish_time=rec.publish_time, sequence=rec.sequence
        )
        st = self.report.channels[cid]
        st.messages += 1
        st.first_log_time = rec.log_time if st.first_log_time is None else min(st.first_log_time, rec.log_time)
        st.last_log_time = rec.log_time if st.last_log_time is None else max(st.last_log_time, rec.log_time)

    def loose_message(self, rec) -> None:
        """A message outside any chunk (unchunked source): chunk by ``chunk_seconds`` of log time."""
        self.message(rec)
        self.report.unchunked_messages += 1
        if self._loose_t0 is None:
            self._loose_t0 = rec.log_time
        elif rec.log_time - self._loose_t0 >= self.chunk_seconds_ns:
            self.flush()

    def chunk(self, records) -> None:
        from mcap.records import Channel, Message, Schema

        self.flush()  # a source chunk never shares an output chunk with loose messages
        for r in records:
            if isinstance(r, Schema):
                self.schema(r)
            elif isinstance(r, Channel):
                self.channel(r)
            elif isinstance(r, Message):
                self.message(r)
        self.flush()
        self.report.chunks += 1

    def flush(self) -> None:
        self.writer.flush()
        self._loose_t0 = None


def recover(
    source: str | os.PathLike,
    output: str | os.PathLike,
    *,
    compression: str = "zstd",
    chunk_size: int = 4 * 1024 * 1024,
    chunk_seconds: float = 1.0,
) -> RecoverReport:
    """Copy every complete record of ``source`` (an MCAP file, possibly cut off) into ``output``.

    ``compression`` (zstd, lz4, none) and ``chunk_size`` (bytes, uncompressed) as in
    :class:`feedio.mcapio.TrialWriter`; source chunks are kept as they are (split
    further only if larger than ``chunk_size``); messages written outside chunks are
    grouped into chunks of ``chunk_seconds`` of log time.

    The output is written to a temporary file next to it and renamed at the end, so
    it is either a complete MCAP file or not there. Raises ``ValueError`` (naming the
    file) when ``source`` is not an MCAP file or not even its header is complete,
    ``OSError`` when a file cannot be read or written.
    """
    from mcap.records import Attachment, Channel, Chunk, DataEnd, Header, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

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
        if head != _MAGIC:
            if not head:
                raise ValueError(f"{src} is empty (0 bytes): nothing to recover")
            if _MAGIC.startswith(head):
                raise ValueError(f"{src} ends inside the MCAP magic ({size} bytes): nothing to recover")
            raise ValueError(f"{src} is not an MCAP file (it starts with {head!r}, not the MCAP magic {_MAGIC!r})")
        f.seek(0)
        report = RecoverReport(source=str(src), output=str(dst), source_bytes=size)
        reader = StreamReader(f, skip_magic=False, emit_chunks=True, validate_crcs=False, record_size_limit=size)
        records = iter(reader.records)
        fd = f.fileno()

        last = [None]  # type of the previous record

        def next_record():
            """(offset, record) of the next record, None at the end; raises _Stop when it is damaged."""
            offset = max(f.tell(), 8)  # the first call starts before the magic
            hdr = _record_header(fd, offset)
            what = _opname(hdr[0] if hdr else None)
            if last[0] == "Footer":
                hdr, what = None, "end magic after the footer"
            try:
                rec = next(records)
            except StopIteration:
                return None
            except Exception as exc:  # noqa: BLE001 - EndOfFile, struct.error, UnicodeDecodeError, RecordLengthLimitExceeded...
                cut = hdr is None or offset + 9 + hdr[1] > size or type(exc).__name__ == "EndOfFile"
                why = "cut off" if cut else "corrupt"
                detail = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                raise _Stop(offset, f"{what} {why} ({detail})") from None
            # a known record must end exactly where its length says (unknown opcodes are skipped
            # by the reader, so then the next record it yields starts later: no check)
            if hdr is not None and hdr[0] in _KNOWN_OPCODES and f.tell() != offset + 9 + hdr[1]:
                raise _Stop(offset, f"{what} is corrupt (its fields overrun its declared length {hdr[1]})")
            last[0] = type(rec).__name__
            return offset, rec

        try:
            first = next_record()
        except _Stop as stop:
            raise ValueError(f"{src}: no complete MCAP header record ({stop.reason}): nothing to recover") from None
        if first is None or not isinstance(first[1], Header):
            got = "nothing" if first is None else type(first[1]).__name__
            raise ValueError(f"{src}: the first MCAP record is {got}, not a Header: not a valid MCAP file")
        report.bytes_used = f.tell()

        tmp = dst.with_name(f".{dst.name}.{os.getpid()}.recover-tmp")
        try:
            with open(tmp, "wb") as out:
                cp = _Copier(out, first[1], compression, chunk_size, chunk_seconds, report)
                while True:
                    try:
                        item = next_record()
                    except _Stop as stop:
                        report.stop_offset, report.stop_reason = stop.offset, stop.reason
                        break
                    if item is None:
                        report.bytes_used = f.tell()
                        report.complete = True  # the reader only ends after the footer and the end magic
                        break
                    offset, rec = item
                    if isinstance(rec, Chunk):
                        try:
                            inner = _unpack_chunk(rec)
                        except ValueError as exc:
                            report.chunks_dropped += 1
                            report.stop_offset, report.stop_reason = offset, f"Chunk record is corrupt ({exc})"
                            break
                        cp.chunk(inner)
                    elif isinstance(rec, Schema):
                        cp.schema(rec)
                    elif isinstance(rec, Channel):
                        cp.channel(rec)  # schema never seen: channel skipped, its messages become orphans
                    elif isinstance(rec, Message):
                        cp.loose_message(rec)
                    elif isinstance(rec, Metadata):
                        cp.flush()
                        cp.writer.add_metadata(rec.name, dict(rec.metadata))
                        report.metadata += 1
                    elif isinstance(rec, Attachment):
                        cp.flush()
                        cp.writer.add_attachment(
                            create_time=rec.create_time, log_time=rec.log_time, name=rec.name,
                            media_type=rec.media_type, data=rec.data,
                        )
                        report.attachments += 1
                    elif isinstance(rec, DataEnd):
                        report.data_complete = True
                    elif isinstance(rec, Header):
                        report.stop_offset, report.stop_reason = offset, "second Header record (corrupt file)"
                        break
                    # indexes, statistics, summary offsets, footer: regenerated by the writer
                    report.bytes_used = f.tell()
                if report.complete:
                    report.data_complete = True
                    report.stop_offset = None
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
        "messages": str(report.messages),
        "tool": f"feedmon recover {__version__}",
    }
    if report.stop_reason:
        meta["stop_offset"] = str(report.stop_offset)
        meta["stop_reason"] = report.stop_reason
    return meta
