"""``feedmon recover broken.mcap -o fixed.mcap`` — salvage a recording that was cut off or damaged.

Examples::

    feedmon recover run-0412.mcap -o run-0412-fixed.mcap
    feedmon recover run-0412.mcap -o fixed.mcap --json     # machine-readable report

Copies every intact chunk (with its schemas, channels and messages), the complete
records of chunks that were cut off, the metadata and attachments of a cut-off or
damaged MCAP file into a new, complete file. After damage (a flipped bit, a half-written
chunk left by a full disk) it resynchronises on the next intact record and goes on; the
report lists every skipped range (offset, length, reason, messages dropped), the
messages per channel, the last log time and how many bytes were dropped. Exit code 0 when
messages were recovered (or the source was complete), 1 when nothing could be recovered
(the output then holds only header, metadata and declarations), 2 on errors (not an MCAP
file, no complete header, unreadable or unwritable file).
"""

from __future__ import annotations

import argparse
import json


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "recover",
        help="salvage a cut-off or damaged MCAP recording into a valid file",
        description=(
            "Read an MCAP file record by record, check every chunk (size limits, decompression, CRC), "
            "skip damaged ranges and resynchronise on the next intact record, and write the header, "
            "schemas, channels, metadata, attachments and the messages of every intact chunk (and the "
            "complete records of cut-off chunks) into a new valid MCAP file."
        ),
    )
    p.add_argument("input", metavar="BROKEN.mcap", help="MCAP file to recover (it is only read)")
    p.add_argument("-o", "--output", required=True, metavar="FIXED.mcap",
                   help="output MCAP file (written to a temporary file and renamed when complete)")
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd",
                   help="chunk compression of the output (default zstd, as feedmon writes)")
    p.add_argument("--salvage-damaged", action="store_true",
                   help="also keep the messages of chunks that fail their CRC (a changed byte may be in any of them)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from replay.recover import recover

    rep = recover(args.input, args.output, compression=args.compression, salvage_damaged=args.salvage_damaged)
    if args.json:
        print(json.dumps(rep.as_dict(), indent=2))
    else:
        print(rep.summary())
    return 0 if (rep.messages or rep.complete) else 1
