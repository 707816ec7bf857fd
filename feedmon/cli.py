"""The ``feedmon`` command line: one entry point, one sub-command per module.

Each sub-command lives in its own module exposing ``register(subparsers)``,
which adds an argparse parser and sets ``func`` to a callable taking the parsed
arguments and returning an exit code. Modules are imported lazily so that
``feedmon --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# name -> module providing register(subparsers); one line per sub-command
COMMANDS: dict[str, str] = {
    "simulate": "feedmon.simulate_cmd",
    "import": "feedmon.import_cmd",
    "replay": "feedmon.replay_cmd",
    "identify": "feedmon.identify_cmd",
    "demo": "feedmon.demo_cmd",
    "run": "feedmon.run_cmd",
    "status": "feedmon.status_cmd",
    "recover": "feedmon.recover_cmd",
    "bridge": "feedmon.bridge_cmd",
    "reference": "feedmon.reference_cmd",
    "alarm": "feedmon.alarm_cmd",
    "wear": "feedmon.wear_cmd",
}


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="feedmon",
        description="Real-time disturbance monitor for CNC feed drives.",
    )
    parser.add_argument("--version", action="version", version=f"feedmon {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module_name in COMMANDS.values():
        importlib.import_module(module_name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (ValueError, OSError) as exc:  # user-facing errors: say what and how to fix (+ the flags)
        from .errors import report

        report(exc, args.command)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
