"""``feedmon recover broken.mcap -o fixed.mcap`` — salvage a recording whose writer was killed.

Examples::

    feedmon recover run-0412.mcap -o run-0412-fixed.mcap
    feedmon recover run-0412.mcap -o fixed.mcap --json     # machine-readable report

Copies every complete chunk (with its schemas, channels and messages), the
metadata and attachments of a cut-off or partly corrupt MCAP file into a new,
complete file and reports messages per channel, the last log time and how many
bytes were dropped. Exit code 0 when messages were recovered (or the source was
complete), 1 when the source was cut off before its first complete chunk (the
output then holds only header, metadata and declarations), 2 on errors (not an
MCAP file, no complete header, unreadable or unwritable file).
"""

from __future__ import annotations

import argparse
import json


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "recover",
        help="salvage a cut-off MCAP recording (writer killed) into a valid file",
        description=(
            "Read an MCAP file sequentially, stop at the first truncated or corrupt record and write "
            "the header, schemas, channels, metadata, attachments and all messages of the complete "
            "chunks into a new valid MCAP file (zstd chunks as written by feedmon)."
        ),
    )
    p.add_argument("input", metavar="BROKEN.mcap", help="MCAP file to recover (it is only read)")
    p.add_argument("-o", "--output", required=True, metavar="FIXED.mcap",
                   help="output MCAP file (written to a temporary file and renamed when complete)")
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd",
                   help="chunk compression of the output (default zstd, as feedmon writes)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from replay.recover import recover

    rep = recover(args.input, args.output, compression=args.compression)
    if args.json:
        print(json.dumps({
            "source": rep.source,
            "output": rep.output,
            "source_bytes": rep.source_bytes,
            "bytes_used": rep.bytes_used,
            "bytes_dropped": rep.bytes_dropped,
            "complete": rep.complete,
            "data_complete": rep.data_complete,
            "stop_offset": rep.stop_offset,
            "stop_reason": rep.stop_reason,
            "chunks": rep.chunks,
            "chunks_dropped": rep.chunks_dropped,
            "messages": rep.messages,
            "orphan_messages": rep.orphan_messages,
            "metadata": rep.metadata,
            "attachments": rep.attachments,
            "last_log_time_ns": rep.last_log_time,
            "channels": {c.topic: {"messages": c.messages, "first_log_time_ns": c.first_log_time,
                                   "last_log_time_ns": c.last_log_time, "message_encoding": c.message_encoding,
                                   "schema": c.schema_name}
                         for c in rep.channels.values()},
        }, indent=2))
    else:
        print(rep.summary())
    return 0 if (rep.messages or rep.complete) else 1
