"""The MCAP format's constants (https://mcap.dev/spec), defined once for the reader
(:mod:`feedio.mcapfile`), the writer (:mod:`feedio.mcapwriter`) and the salvager
(:mod:`replay.recover`).

Every record is ``opcode u8, length u64, body`` (:data:`RECORD_HEAD`), little-endian; a file
starts and ends with :data:`MAGIC`.
"""

from __future__ import annotations

import struct

__all__ = ["MAGIC", "Op", "OP_NAMES", "RECORD_HEAD"]

MAGIC = b"\x89MCAP0\r\n"
#: the head of every record: opcode (u8) and body length (u64)
RECORD_HEAD = struct.Struct("<BQ")


class Op:
    """MCAP opcodes: a plain namespace of ints, not an ``IntEnum`` — the readers compare an opcode per
    record, and an enum member's lookup costs ~4x a class attribute's on CPython 3.11."""

    HEADER = 0x01
    FOOTER = 0x02
    SCHEMA = 0x03
    CHANNEL = 0x04
    MESSAGE = 0x05
    CHUNK = 0x06
    MESSAGE_INDEX = 0x07
    CHUNK_INDEX = 0x08
    ATTACHMENT = 0x09
    ATTACHMENT_INDEX = 0x0A
    STATISTICS = 0x0B
    METADATA = 0x0C
    METADATA_INDEX = 0x0D
    SUMMARY_OFFSET = 0x0E
    DATA_END = 0x0F


#: opcode → the record's name in the specification (``MessageIndex``)
OP_NAMES = {v: k.title().replace("_", "") for k, v in vars(Op).items() if k.isupper()}
