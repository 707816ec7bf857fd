"""Checked, bounded reading of MCAP files: records, chunks, CRCs and size limits.

The reader of :mod:`feedio.mcapio` and the salvager :mod:`replay.recover` parse MCAP
(https://mcap.dev/spec) here rather than with the ``mcap`` package's reader, because a
trial file is untrusted input: every length is checked against what is left of the file
and against a limit *before* anything is read or allocated, every chunk is decompressed
with a bound on its output, and every CRC the writer stored is verified.

Limits (:class:`Limits`; the defaults are the module constants below; README "Input
limits"). A file beyond a limit is refused with a :class:`TrialFileError` naming the
file, the byte offset and the limit — never a traceback, a hang or unbounded memory.

Integrity: the chunk CRC (of the uncompressed records) is checked before any record of
the chunk is used; the data-section CRC (``DataEnd``) and the summary CRC (``Footer``),
when the writer stored them (feedmon's writer does), are checked when the file is
opened, so a flipped bit anywhere in a feedmon file is an error, not a changed value.
"""

from __future__ import annotations

import os
import re
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from .mcapspec import MAGIC, OP_NAMES, RECORD_HEAD, Op

__all__ = [
    "TrialFileError",
    "Limits",
    "DEFAULT_LIMITS",
    "RecordError",
    "parse_record",
    "decompress",
    "iter_inner",
    "McapFile",
    "json_depth",
    "RECOVER_HINT",
]

# ---- limits (README "Input limits"; configurable through Limits) -----------------------------
#: largest record read into memory (a chunk's compressed bytes, a message, a schema), bytes.
#: feedmon's writers close a chunk at 4 MiB uncompressed, so no real trial file comes near it.
MAX_RECORD_BYTES = 64 * 2**20
#: largest declared uncompressed size of a chunk, bytes (a zstd bomb claims far more)
MAX_CHUNK_BYTES = 64 * 2**20
#: uncompressed / compressed size above which a chunk is refused (measured: ≤ 15 for sensor data) ...
MAX_COMPRESSION_RATIO = 1000
#: ... once its uncompressed size exceeds this many bytes (small chunks may compress as they like)
RATIO_FLOOR_BYTES = 2**20
#: largest summary section (channels, schemas, indexes), bytes
MAX_SUMMARY_BYTES = 64 * 2**20
#: largest metadata record (feedmon.trial holds the TrialMeta JSON), bytes
MAX_METADATA_BYTES = 2**20
#: most channels / schemas / metadata records in one file (feedmon writes 4 channels per axis)
MAX_CHANNELS = 40_000
MAX_SCHEMAS = 4096
MAX_METADATA_RECORDS = 40_000
#: deepest nesting of JSON objects/arrays in metadata (TrialMeta needs 5; 50 000 crashed msgspec)
MAX_JSON_DEPTH = 32

RECOVER_HINT = "salvage what is intact with 'feedmon recover {path} -o FIXED.mcap'"


class TrialFileError(ValueError):
    """A trial file cannot be read or written as asked; the message names file, channel, problem."""


@dataclass(frozen=True)
class Limits:
    """Size limits applied while reading (defaults: the module constants)."""

    record_bytes: int = MAX_RECORD_BYTES
    chunk_bytes: int = MAX_CHUNK_BYTES
    compression_ratio: float = MAX_COMPRESSION_RATIO
    ratio_floor_bytes: int = RATIO_FLOOR_BYTES
    summary_bytes: int = MAX_SUMMARY_BYTES
    metadata_bytes: int = MAX_METADATA_BYTES
    channels: int = MAX_CHANNELS
    schemas: int = MAX_SCHEMAS
    metadata_records: int = MAX_METADATA_RECORDS
    json_depth: int = MAX_JSON_DEPTH


DEFAULT_LIMITS = Limits()


# field layout of each record (MCAP spec): B/H/I/Q little-endian ints, s u32-prefixed UTF-8,
# b4/b8 u32/u64-prefixed bytes, m map<string,string> and mq map<uint16,uint64> (u32 byte length),
# a16 array of 16-byte entries (u32 byte length), rest = the remaining bytes
_SPECS: dict[int, tuple[str, ...]] = {
    Op.HEADER: ("s", "s"),
    Op.FOOTER: ("Q", "Q", "I"),
    Op.SCHEMA: ("H", "s", "s", "b4"),
    Op.CHANNEL: ("H", "H", "s", "s", "m"),
    Op.MESSAGE: ("H", "I", "Q", "Q", "rest"),
    Op.CHUNK: ("Q", "Q", "Q", "I", "s", "b8"),
    Op.MESSAGE_INDEX: ("H", "a16"),
    Op.CHUNK_INDEX: ("Q", "Q", "Q", "Q", "mq", "Q", "s", "Q", "Q"),
    Op.ATTACHMENT: ("Q", "Q", "s", "s", "b8", "I"),
    Op.ATTACHMENT_INDEX: ("Q", "Q", "Q", "Q", "Q", "s", "s"),
    Op.STATISTICS: ("Q", "H", "I", "I", "I", "I", "Q", "Q", "mq"),
    Op.METADATA: ("s", "m"),
    Op.METADATA_INDEX: ("Q", "Q", "s"),
    Op.SUMMARY_OFFSET: ("B", "Q", "Q"),
    Op.DATA_END: ("I",),
}
_INT = {"B": struct.Struct("<B"), "H": struct.Struct("<H"), "I": struct.Struct("<I"), "Q": struct.Struct("<Q")}
_U32, _U64 = _INT["I"], _INT["Q"]
_MSG_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
FOOTER_BYTES = 9 + 20
DATA_END_BYTES = 9 + 4


class RecordError(ValueError):
    """A record's fields do not fit its length (or are not valid UTF-8)."""


class Header(NamedTuple):
    profile: str
    library: str


class Schema(NamedTuple):
    id: int
    name: str
    encoding: str
    data: bytes


class Channel(NamedTuple):
    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict


class Message(NamedTuple):
    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: Any  # bytes or memoryview


class Chunk(NamedTuple):
    message_start_time: int
    message_end_time: int
    uncompressed_size: int
    uncompressed_crc: int
    compression: str
    data: Any


class Metadata(NamedTuple):
    name: str
    metadata: dict


class Attachment(NamedTuple):
    log_time: int
    create_time: int
    name: str
    media_type: str
    data: bytes
    crc: int


class MetadataIndex(NamedTuple):
    offset: int
    length: int
    name: str


class Footer(NamedTuple):
    summary_start: int
    summary_offset_start: int
    summary_crc: int


class DataEnd(NamedTuple):
    data_section_crc: int


_TYPES = {Op.HEADER: Header, Op.SCHEMA: Schema, Op.CHANNEL: Channel, Op.MESSAGE: Message, Op.CHUNK: Chunk,
          Op.METADATA: Metadata, Op.ATTACHMENT: Attachment, Op.METADATA_INDEX: MetadataIndex,
          Op.FOOTER: Footer, Op.DATA_END: DataEnd}


def _fields(buf, spec: tuple[str, ...], *, copy: bool) -> tuple[list, int]:
    """Parse ``spec`` from ``buf`` (a memoryview); returns (values, bytes used)."""
    n = len(buf)
    pos = 0
    out: list = []

    def need(k: int, what: str) -> None:
        if k < 0 or pos + k > n:
            raise RecordError(f"{what} of {k} bytes at record byte {pos} overruns the record ({n} bytes)")

    def text(k: int) -> str:
        try:
            return bytes(buf[pos:pos + k]).decode("utf-8")
        except UnicodeDecodeError:
            raise RecordError(f"string at record byte {pos} is not valid UTF-8") from None

    for f in spec:
        if f in _INT:
            st = _INT[f]
            need(st.size, "integer")
            out.append(st.unpack_from(buf, pos)[0])
            pos += st.size
        elif f == "s":
            need(4, "string length")
            k = _U32.unpack_from(buf, pos)[0]
            pos += 4
            need(k, "string")
            out.append(text(k))
            pos += k
        elif f in ("b4", "b8"):
            st = _U32 if f == "b4" else _U64
            need(st.size, "byte-array length")
            k = st.unpack_from(buf, pos)[0]
            pos += st.size
            need(k, "byte array")
            out.append(bytes(buf[pos:pos + k]) if copy else buf[pos:pos + k])
            pos += k
        elif f == "rest":
            out.append(bytes(buf[pos:]) if copy else buf[pos:])
            pos = n
        elif f in ("m", "mq", "a16"):
            need(4, "map length")
            k = _U32.unpack_from(buf, pos)[0]
            pos += 4
            need(k, "map")
            end = pos + k
            if f == "a16":
                if k % 16:
                    raise RecordError(f"index array of {k} bytes is not a whole number of 16-byte entries")
                out.append(k // 16)
                pos = end
                continue
            d: dict = {}
            while pos < end:
                if f == "mq":
                    if pos + 10 > end:
                        raise RecordError("map entry overruns the map")
                    d[_INT["H"].unpack_from(buf, pos)[0]] = _U64.unpack_from(buf, pos + 2)[0]
                    pos += 10
                    continue
                pair = []
                for _ in range(2):
                    if pos + 4 > end:
                        raise RecordError("map entry overruns the map")
                    kk = _U32.unpack_from(buf, pos)[0]
                    pos += 4
                    if kk > end - pos:
                        raise RecordError("map string overruns the map")
                    pair.append(text(kk))
                    pos += kk
                d[pair[0]] = pair[1]
            out.append(d)
        else:  # pragma: no cover - spec typo
            raise AssertionError(f)
    return out, pos


def parse_record(opcode: int, body, *, exact: bool = False, copy: bool = True):
    """The record of ``opcode`` in ``body`` (bytes or memoryview), as a NamedTuple for the kinds
    this module uses, a list of field values for the other known kinds, ``None`` for unknown
    opcodes. ``exact``: the fields must fill the record (no trailing bytes), the strict check
    used when resynchronising. Raises :class:`RecordError`."""
    spec = _SPECS.get(opcode)
    if spec is None:
        return None
    buf = body if isinstance(body, memoryview) else memoryview(body)
    vals, used = _fields(buf, spec, copy=copy)
    if exact and used != len(buf):
        raise RecordError(f"{len(buf) - used} unexpected byte(s) after the fields")
    t = _TYPES.get(opcode)
    if t is Channel:  # field order on disk: id, schema id, topic, encoding, metadata
        return Channel(vals[0], vals[1], vals[2], vals[3], vals[4])
    return t(*vals) if t is not None else vals


# ---- chunks -----------------------------------------------------------------------------------
#: bytes asked of the zstd stream per read when a damaged chunk is decompressed in part: a read
#: that meets the damage returns nothing, so small reads keep all but < 4 KiB of what decoded
#: before it (zstd blocks are up to 128 KiB). An intact chunk is read 1 MiB at a time.
_ZSTD_PIECE_PARTIAL = 1 << 12
_ZSTD_PIECE = 1 << 20


def check_chunk_size(chunk: Chunk, limits: Limits, compressed_size: int | None = None) -> str | None:
    """Why ``chunk`` is refused before decompression (None: acceptable). ``compressed_size``:
    the chunk's full compressed size when ``chunk.data`` is only the part that is present."""
    if chunk.compression not in ("", "zstd", "lz4"):
        return f"unsupported chunk compression {chunk.compression!r}"
    size = chunk.uncompressed_size
    if size > limits.chunk_bytes:
        return f"chunk declares {size} uncompressed bytes, more than the limit of {limits.chunk_bytes}"
    full = len(chunk.data) if compressed_size is None else compressed_size
    comp = max(full, 1)
    if chunk.compression and size > limits.ratio_floor_bytes and size > limits.compression_ratio * comp:
        return (f"chunk declares {size} uncompressed bytes from {full} compressed "
                f"(ratio {size / comp:.0f}, more than the limit of {limits.compression_ratio:g}): a decompression bomb")
    if not chunk.compression and size != full:
        return f"uncompressed chunk declares {size} bytes but holds {full}"
    return None


def decompress(chunk: Chunk, limits: Limits = DEFAULT_LIMITS, *, partial: bool = False,
               compressed_size: int | None = None) -> tuple[bytes, str | None]:
    """Decompressed records of ``chunk`` and ``None``, or (what could be decompressed, why not all).

    The output never exceeds the declared ``uncompressed_size`` (itself bounded by
    :func:`check_chunk_size`); its CRC is checked when the writer stored one. With
    ``partial=False`` every problem is raised as :class:`RecordError`; with ``partial=True``
    the longest prefix that decompressed cleanly is returned with the reason (recover uses
    the complete records of that prefix).
    """
    why = check_chunk_size(chunk, limits, compressed_size)
    if why is not None:
        raise RecordError(why)
    size = chunk.uncompressed_size
    data = chunk.data
    problem = None
    if chunk.compression == "":
        out = bytes(data[:size])
    elif chunk.compression == "zstd":
        import zstandard

        buf = bytearray()
        try:
            reader = zstandard.ZstdDecompressor().stream_reader(bytes(data), read_across_frames=True)
            while len(buf) <= size:
                piece = reader.read(min(_ZSTD_PIECE_PARTIAL if partial else _ZSTD_PIECE, size + 1 - len(buf)))
                if not piece:
                    break
                buf += piece
        except zstandard.ZstdError as exc:
            problem = f"zstd: {exc}"
        out = bytes(buf)
    else:
        import lz4.frame

        dec = lz4.frame.LZ4FrameDecompressor()
        try:
            out = dec.decompress(bytes(data), max_length=size + 1)
            if len(out) <= size and not dec.eof:
                problem = "lz4: the compressed data ends early"
        except RuntimeError as exc:
            out, problem = b"", f"lz4: {exc}"
    if problem is None and len(out) != size:
        problem = (f"decompresses to more than the declared {size} bytes" if len(out) > size
                   else f"decompresses to {len(out)} bytes, not the declared {size}")
    if problem is None and chunk.uncompressed_crc and zlib.crc32(out) != chunk.uncompressed_crc:
        problem = f"CRC mismatch (stored {chunk.uncompressed_crc:#010x}, computed {zlib.crc32(out):#010x})"
    if problem is not None and not partial:
        raise RecordError(problem)
    return out[:size], problem


def iter_inner(data, *, strict: bool = True) -> Iterator[tuple[int, int, memoryview]]:
    """``(offset, opcode, body)`` of the records inside decompressed chunk data. A record that
    overruns the data raises :class:`RecordError` (``strict``) or ends the iteration."""
    buf = memoryview(data)
    n = len(buf)
    pos = 0
    while pos < n:
        if pos + 9 > n:
            if strict:
                raise RecordError(f"record header at chunk byte {pos} is cut off")
            return
        opcode, length = RECORD_HEAD.unpack_from(buf, pos)
        if length > n - pos - 9:
            if strict:
                raise RecordError(f"record at chunk byte {pos} declares {length} bytes, {n - pos - 9} left")
            return
        yield pos, opcode, buf[pos + 9:pos + 9 + length]
        pos += 9 + length


# ---- metadata JSON ----------------------------------------------------------------------------
_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.S)
_OPEN_CLOSE = np.zeros(256, dtype=np.int8)
_OPEN_CLOSE[[ord("["), ord("{")]] = 1
_OPEN_CLOSE[[ord("]"), ord("}")]] = -1


def json_depth(text: str | bytes) -> int:
    """Deepest nesting of arrays/objects in a JSON text (strings ignored), in linear time."""
    raw = text.encode() if isinstance(text, str) else bytes(text)
    stripped = _JSON_STRING.sub(b'""', raw)
    if not stripped:
        return 0
    steps = _OPEN_CLOSE[np.frombuffer(stripped, dtype=np.uint8)]
    return int(np.cumsum(steps, dtype=np.int64).max(initial=0))


# ---- files ------------------------------------------------------------------------------------
def _crc_of_file(f, start: int, end: int, crc: int = 0) -> int:
    f.seek(start)
    left = end - start
    while left > 0:
        piece = f.read(min(left, 1 << 22))
        if not piece:
            break
        crc = zlib.crc32(piece, crc)
        left -= len(piece)
    return crc


@dataclass
class McapFile:
    """An MCAP file opened for checked reading.

    Opening checks the magic at both ends, the footer, the summary (CRC, record layout,
    limits) and the data-section CRC when stored. :meth:`messages` then reads the data
    section once, in file order, checking every chunk. Use as a context manager.
    """

    path: str
    limits: Limits = DEFAULT_LIMITS
    size: int = 0
    header: Header | None = None
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    data_end: int = 0  # offset of the DataEnd record (end of the data section)
    data_crc: int = 0
    metadata_index: list[MetadataIndex] = field(default_factory=list)
    metadata_count: int | None = None  # from the Statistics record, when present

    def __post_init__(self) -> None:
        self.path = os.fspath(self.path)
        try:
            self._f = open(self.path, "rb")
        except OSError as exc:
            raise TrialFileError(f"cannot open trial file {self.path}: {exc.strerror or exc}") from exc
        try:
            self._open()
        except BaseException:
            self._f.close()
            raise

    # -- helpers --------------------------------------------------------------------------------
    def error(self, offset: int | None, what: str, *, hint: bool = True) -> TrialFileError:
        where = f" at byte {offset}" if offset is not None else ""
        tail = f"; {RECOVER_HINT.format(path=self.path)}" if hint else ""
        return TrialFileError(f"{self.path} is corrupt{where}: {what}{tail}")

    def _read_at(self, offset: int, n: int) -> bytes:
        self._f.seek(offset)
        data = self._f.read(n)
        if len(data) != n:
            raise self.error(offset, f"{n} bytes expected, {len(data)} present")
        return data

    def _record_at(self, offset: int, end: int, limit: int, what: str) -> tuple[int, bytes]:
        """(opcode, body) of the record at ``offset`` that must end by ``end``."""
        if offset + 9 > end:
            raise self.error(offset, f"{what}: record header overruns its section")
        opcode, length = RECORD_HEAD.unpack(self._read_at(offset, 9))
        if length > end - offset - 9:
            raise self.error(offset, f"{what}: {OP_NAMES.get(opcode, hex(opcode))} record declares {length} "
                                     f"bytes but its section has {end - offset - 9} left")
        if length > limit:
            raise TrialFileError(
                f"{self.path}: {OP_NAMES.get(opcode, hex(opcode))} record at byte {offset} holds {length} bytes, "
                f"more than the limit of {limit} for {what}")
        return opcode, self._read_at(offset + 9, length)

    def _parse(self, opcode: int, body, offset: int, what: str):
        try:
            return parse_record(opcode, body)
        except RecordError as exc:
            raise self.error(offset, f"{what}: {OP_NAMES.get(opcode, hex(opcode))} record: {exc}") from None

    # -- opening --------------------------------------------------------------------------------
    def _open(self) -> None:
        f, path = self._f, self.path
        self.size = size = os.fstat(f.fileno()).st_size
        head = f.read(8)
        if head != MAGIC:
            raise TrialFileError(f"{path} is not an MCAP file (it starts with {head[:8]!r}, not the MCAP magic {MAGIC!r})")
        f.seek(max(size - 8, 0))
        if size < 8 + 9 + DATA_END_BYTES + FOOTER_BYTES + 8 or f.read(8) != MAGIC:
            raise TrialFileError(
                f"{path} is truncated: {size} bytes and no MCAP end magic — the recording was not closed "
                f"properly (writer killed or disk full); {RECOVER_HINT.format(path=path)}")
        foot_off = size - 8 - FOOTER_BYTES
        opcode, body = self._record_at(foot_off, size - 8, 64, "footer")
        if opcode != Op.FOOTER or len(body) != 20:
            raise self.error(foot_off, "no Footer record before the end magic")
        footer = parse_record(Op.FOOTER, body)
        s0 = footer.summary_start
        if s0 == 0:
            raise TrialFileError(f"{path} has no summary section (channels unknown); rewrite it with "
                                 f"'feedmon recover {path} -o FIXED.mcap'")
        if not 8 + DATA_END_BYTES <= s0 <= foot_off:
            raise self.error(foot_off, f"the footer's summary start {s0} lies outside the file")
        if foot_off - s0 > self.limits.summary_bytes:
            raise TrialFileError(f"{path}: summary section of {foot_off - s0} bytes is larger than the limit of "
                                 f"{self.limits.summary_bytes}")
        summary = self._read_at(s0, foot_off - s0)
        if footer.summary_crc:
            crc = zlib.crc32(self._read_at(foot_off, 25), zlib.crc32(summary))
            if crc != footer.summary_crc:
                raise self.error(s0, f"the summary section fails its CRC (stored {footer.summary_crc:#010x}, "
                                     f"computed {crc:#010x})")
        self.data_end = de = s0 - DATA_END_BYTES
        opcode, body = self._record_at(de, s0, 16, "data end")
        if opcode != Op.DATA_END or len(body) != 4:
            raise self.error(de, "no DataEnd record before the summary section")
        self.data_crc = parse_record(Op.DATA_END, body).data_section_crc
        self._read_summary(summary, s0)
        opcode, body = self._record_at(8, de, 1 << 16, "header")
        if opcode != Op.HEADER:
            raise self.error(8, f"the first record is {OP_NAMES.get(opcode, hex(opcode))}, not a Header")
        self.header = self._parse(opcode, body, 8, "header")
        if self.data_crc:
            crc = _crc_of_file(f, 0, de)
            if crc != self.data_crc:
                raise self.error(8, f"the data section fails its CRC (stored {self.data_crc:#010x}, computed {crc:#010x}): "
                                    "some bytes between the header and the summary were changed")

    def _read_summary(self, summary: bytes, base: int) -> None:
        lim = self.limits
        buf = memoryview(summary)
        pos = 0
        while pos < len(buf):
            if pos + 9 > len(buf):
                raise self.error(base + pos, "summary record header cut off")
            opcode, length = RECORD_HEAD.unpack_from(buf, pos)
            if length > len(buf) - pos - 9:
                raise self.error(base + pos, f"summary record declares {length} bytes, {len(buf) - pos - 9} left")
            body = buf[pos + 9:pos + 9 + length]
            if opcode in (Op.SCHEMA, Op.CHANNEL, Op.METADATA_INDEX, Op.STATISTICS):
                rec = self._parse(opcode, body, base + pos, "summary")
                if opcode == Op.SCHEMA:
                    self.schemas[rec.id] = rec
                    if len(self.schemas) > lim.schemas:
                        raise TrialFileError(f"{self.path} declares more than {lim.schemas} schemas (the limit)")
                elif opcode == Op.CHANNEL:
                    self.channels[rec.id] = rec
                    if len(self.channels) > lim.channels:
                        raise TrialFileError(f"{self.path} declares more than {lim.channels} channels (the limit)")
                elif opcode == Op.METADATA_INDEX:
                    self.metadata_index.append(rec)
                    if len(self.metadata_index) > lim.metadata_records:
                        raise TrialFileError(f"{self.path} holds more than {lim.metadata_records} metadata records "
                                             "(the limit)")
                else:
                    self.metadata_count = rec[4]
            pos += 9 + length

    # -- data section ---------------------------------------------------------------------------
    def top_level(self) -> Iterator[tuple[int, int, int]]:
        """``(offset, opcode, length)`` of every record of the data section (bodies not read)."""
        pos = 8
        while pos < self.data_end:
            if pos + 9 > self.data_end:
                raise self.error(pos, "record header overruns the data section")
            opcode, length = RECORD_HEAD.unpack(self._read_at(pos, 9))
            if length > self.data_end - pos - 9:
                raise self.error(pos, f"{OP_NAMES.get(opcode, hex(opcode))} record declares {length} bytes, "
                                      f"the data section has {self.data_end - pos - 9} left")
            yield pos, opcode, length
            pos += 9 + length

    def metadata(self) -> list[Metadata]:
        """Every metadata record (through the summary's index when present, else by a scan)."""
        lim = self.limits
        spots = [(m.offset, m.length - 9) for m in self.metadata_index]
        if not spots and self.metadata_count != 0:
            spots = [(off, n) for off, op, n in self.top_level() if op == Op.METADATA]
            if len(spots) > lim.metadata_records:
                raise TrialFileError(f"{self.path} holds more than {lim.metadata_records} metadata records (the limit)")
        out = []
        for off, _ in spots:
            if not 8 <= off < self.data_end:
                raise self.error(off, "a metadata index points outside the data section")
            opcode, body = self._record_at(off, self.data_end, lim.metadata_bytes, "a metadata record")
            if opcode != Op.METADATA:
                raise self.error(off, f"the metadata index points at a {OP_NAMES.get(opcode, hex(opcode))} record")
            out.append(self._parse(opcode, body, off, "metadata"))
        return out

    def messages(self, channel_ids) -> Iterator[tuple[int, Message]]:
        """``(record offset, Message)`` of the wanted channels in file order; chunks checked
        (limits, decompression, CRC) before any of their messages is yielded."""
        wanted = frozenset(channel_ids)
        lim = self.limits
        for off, opcode, length in self.top_level():
            if opcode == Op.CHUNK:
                _, body = self._record_at(off, self.data_end, lim.record_bytes, "a chunk")
                chunk = self._parse(opcode, body, off, "chunk")
                try:
                    data, _ = decompress(chunk, lim)
                    inner = list(iter_inner(data))
                except RecordError as exc:
                    raise self.error(off, f"chunk: {exc}") from None
                for ioff, iop, ibody in inner:
                    if iop != Op.MESSAGE:
                        continue
                    if len(ibody) < 22:
                        raise self.error(off, f"message at chunk byte {ioff} is shorter than its header")
                    cid, seq, lt, pt = _MSG_HEAD.unpack_from(ibody, 0)
                    if cid in wanted:
                        yield off, Message(cid, seq, lt, pt, ibody[22:])
            elif opcode == Op.MESSAGE:
                if length < 22:
                    raise self.error(off, "message shorter than its header")
                head = _MSG_HEAD.unpack(self._read_at(off + 9, 22))
                if head[0] in wanted:
                    _, body = self._record_at(off, self.data_end, lim.record_bytes, "a message")
                    yield off, Message(*head, memoryview(body)[22:])

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> McapFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
