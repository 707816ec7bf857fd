"""``feedmon replay``: publish a recorded trial on Zenoh with its original timing.

Examples::

    feedmon replay trial.mcap                 # real time, to the monitor on this host
    feedmon replay trial.mcap --rate 10       # ten times faster
    feedmon replay trial.mcap --max --loop    # as fast as possible, forever (Ctrl-C stops)
    feedmon replay trial.mcap --connect tcp/router:7447 --block 10

By default the replay is a Zenoh peer connecting to the monitor's endpoint
(``tcp/127.0.0.1:7448``, see :mod:`feedio.transport`); it waits up to
``--wait`` seconds for the monitor to subscribe before it starts.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys

from feedio.transport import add_zenoh_arguments, session_from_args


class ProgressBar:
    """The replay's rich progress bar, fed by :func:`replay.player.replay`'s ``progress(sent, total)``
    callback: it appears when sending starts (the first call) and stays when the ``with`` block ends."""

    def __init__(self, path) -> None:
        self._name = os.path.basename(os.fspath(path))
        self._bar = None
        self._task = None

    def __call__(self, sent: int, total: int | None) -> None:
        if self._bar is None:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self._bar = Progress(TextColumn("[bold]replay[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("samples"), TimeElapsedColumn(), TimeRemainingColumn(), transient=False)
            self._bar.start()
            self._task = self._bar.add_task(self._name, total=total)
        self._bar.update(self._task, completed=sent)

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc) -> None:
        if self._bar is not None:
            self._bar.stop()


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "replay",
        help="publish a recorded trial (.mcap) on Zenoh with its original timing",
        description="Publish a recorded trial (.mcap) on Zenoh with its original timing, scaled by --rate.",
    )
    p.add_argument("trial", help="trial file (.mcap) written by feedmon")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument("--rate", type=float, default=1.0,
                       help="time scale: 1 = real time (default), 10 = ten times faster")
    speed.add_argument("--max", action="store_true", help="as fast as possible (no timing)")
    loop = p.add_mutually_exclusive_group()
    loop.add_argument("--loop", action="store_true",
                      help="repeat forever until Ctrl-C (seq and time continue across passes)")
    loop.add_argument("--passes", type=int, default=None, metavar="N",
                      help="repeat N times (seq and time continue across passes)")
    p.add_argument("--block", type=int, default=None, metavar="N",
                   help="re-cut samples into blocks of N samples (default: as recorded)")
    p.add_argument("--axis", default=None, help="replay only this axis (X or machine/X)")
    p.add_argument("--no-truth", action="store_true", help="do not publish ground-truth blocks")
    p.add_argument("--wait", type=float, default=10.0, metavar="SECONDS",
                   help="wait up to this long for a subscriber before starting (default 10)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_zenoh_arguments(p, role="connect")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from replay.player import replay

    if args.rate is not None and not args.rate > 0:
        raise ValueError(f"--rate must be > 0, got {args.rate}")
    if args.passes is not None and args.passes < 1:
        raise ValueError(f"--passes must be at least 1, got {args.passes}")
    if args.block is not None and args.block < 1:
        raise ValueError(f"--block must be at least 1, got {args.block}")
    rate = None if args.max else args.rate
    interactive = sys.stdout.isatty() and not args.quiet
    session = session_from_args(args)
    try:
        with ProgressBar(args.trial) if interactive else contextlib.nullcontext() as bar:
            stats = replay(
                args.trial,
                session,
                rate=rate,
                block=args.block,
                loop=True if args.loop else (args.passes or 1),
                prefix=args.prefix,
                progress=bar,
                axis=args.axis,
                truth=not args.no_truth,
                wait_for_subscriber=args.wait,
            )
    finally:
        session.close()
    if not stats.matched:
        print(f"feedmon replay: warning: no subscriber on {args.prefix}/<machine>/<axis>/samples "
              f"within {args.wait:g} s; samples were published anyway", file=sys.stderr)
    speed = "max" if rate is None else f"x{rate:g}"
    print(
        f"replayed {stats.samples} samples in {stats.blocks} blocks"
        + (f" (+{stats.truth_blocks} truth blocks)" if stats.truth_blocks else "")
        + f" of {', '.join(stats.axes)}, {stats.passes} pass(es), {stats.duration:.2f} s of trial"
        + f" in {stats.wall_time:.2f} s wall ({speed}"
        + (f", worst lateness {stats.max_lateness * 1e3:.1f} ms" if rate is not None else "")
        + ")"
        + (" — interrupted" if stats.interrupted else "")
    )
    return 130 if stats.interrupted else 0
