"""``feedmon status``: ask running monitors for their status (Zenoh query on ``<prefix>/monitor/status``).

Examples::

    feedmon status                          # the monitor on this host (tcp/127.0.0.1:7448)
    feedmon status --connect tcp/router:7447 --json

Prints one table per answering monitor (``--json``: the raw JSON, a list with one
object per monitor). Exit code 0 when at least one monitor answered within
``--timeout`` seconds, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys

from feedio.transport import add_zenoh_arguments, query_status


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "status",
        help="show the status of running monitors (counters, drops, latency, sinks)",
        description="Query <prefix>/monitor/status and print what every answering monitor reports.",
    )
    p.add_argument("--json", action="store_true", help="print the raw JSON (a list, one object per monitor)")
    p.add_argument("--timeout", type=float, default=5.0, metavar="SECONDS",
                   help="give up when no monitor answered within this time (default 5)")
    add_zenoh_arguments(p, role="connect")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from feedio.transport import session_from_args

    if not args.timeout > 0:
        raise ValueError(f"--timeout must be > 0, got {args.timeout}")
    session = session_from_args(args)
    try:
        replies = query_status(session, args.prefix, args.timeout)
    finally:
        session.close()
    if not replies:
        print(f"feedmon status: no monitor answered on {args.prefix}/monitor/status within {args.timeout:g} s "
              "(is 'feedmon run' running? check --connect/--prefix)", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(replies, indent=2))
        return 0
    from monitor.status import format_status

    for st in replies:
        format_status(st)
    return 0
