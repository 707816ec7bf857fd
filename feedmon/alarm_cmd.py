"""``feedmon alarm``: an operator's word on a process alarm, sent to the running monitor over Zenoh.

    feedmon alarm ack cnc-mill/X --monitor tooth     # the last tooth alarm was a false alarm

The monitor widens that monitor's limits by ``[monitors] ack_widen`` and logs it (``feedmon status``
shows the factor); key ``<prefix>/<machine>/<axis>/ack``.
"""

from __future__ import annotations

import argparse
import json

from feedio.schema import ALARM_MONITORS as MONITORS
from feedio.transport import add_zenoh_arguments


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("alarm", help="acknowledge a process alarm as false (widens that monitor)")
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    ap = sub.add_parser("ack", help="the last alarm of a monitor was a false alarm")
    ap.add_argument("axis", metavar="MACHINE/AXIS")
    ap.add_argument("--monitor", required=True, choices=MONITORS)
    add_zenoh_arguments(ap, role="connect")
    ap.set_defaults(func=_ack)
    return p


def _ack(args: argparse.Namespace) -> int:
    from feedio.schema import check_name
    from feedio.transport import ack_key, session_from_args

    machine, sep, axis = args.axis.partition("/")
    if not sep:
        raise ValueError(f"axis {args.axis!r}: give MACHINE/AXIS, e.g. cnc-mill/X")
    check_name(machine, "machine")
    check_name(axis, "axis")
    session = session_from_args(args)
    try:
        session.put(ack_key(args.prefix, machine, axis), json.dumps({"monitor": args.monitor}))
    finally:
        session.close()
    print(f"acknowledged a false alarm of monitor {args.monitor} on {machine}/{axis}")
    return 0
