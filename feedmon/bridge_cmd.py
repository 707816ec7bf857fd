"""``feedmon bridge linuxcnc --config bridge.toml`` — a LinuxCNC machine ⇄ the monitor, over Zenoh;
``feedmon bridge streamer-file TRIAL -o force.txt`` — a trial's true force for a HAL ``streamer``."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading

from feedio import transport as T


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "bridge", help="connect a controller (LinuxCNC): servo samples to the monitor, its alarms back to HAL",
        description="Controller bridges. See docs/linuxcnc.md (Connect a LinuxCNC machine).")
    sub = p.add_subparsers(dest="bridge", metavar="BRIDGE")
    lc = sub.add_parser(
        "linuxcnc", formatter_class=argparse.RawDescriptionHelpFormatter,
        help="LinuxCNC: read a HAL sampler, publish sample blocks, drive HAL pins from the monitor's outputs",
        description=(
            "Read the HAL sampler FIFO the config names, publish one sample block per axis on\n"
            "<prefix>/<machine>/<axis>/samples (and/or record a trial file), and own the HAL component\n"
            "whose pins carry the monitor's force estimate, health and alarm back (wire the alarm to\n"
            "motion.feed-hold). Runs until SIGINT/SIGTERM; waits for LinuxCNC when it is not running."))
    lc.add_argument("--config", required=True, metavar="FILE", help="bridge configuration (TOML)")
    lc.add_argument("--record", metavar="TRIAL.mcap",
                    help="also write the samples to this trial file (for feedmon identify)")
    lc.add_argument("--duration", type=float, metavar="S", help="stop after S seconds of samples")
    lc.add_argument("--no-publish", action="store_true", help="do not open Zenoh (record only)")
    T.add_zenoh_arguments(lc, role="connect")
    lc.set_defaults(func=run_linuxcnc)
    sf = sub.add_parser("streamer-file", help="a trial's true disturbance force as a halstreamer input file",
                        description="Write the truth force (N) of a trial made by feedmon simulate, one value per "
                                    "line, for 'halstreamer' feeding a HAL plant's streamer.")
    sf.add_argument("trial", metavar="TRIAL.mcap")
    sf.add_argument("-o", "--output", required=True, help="output text file")
    sf.add_argument("--axis", default=None, help="axis (or machine/axis) of a trial with several")
    sf.add_argument("--scale", type=float, default=1.0, help="factor on the force (default 1)")
    sf.add_argument("--servo-period", type=float, default=None, metavar="S",
                    help="the plant's servo period (s): refuse a trial sampled at another rate")
    sf.set_defaults(func=run_streamer_file)
    p.set_defaults(func=lambda _args: (p.print_help(), 2)[1])


def _logging() -> None:
    root = logging.getLogger()
    if not root.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("feedmon bridge: %(levelname)s: %(message)s"))
        root.addHandler(handler)
        root.setLevel(logging.INFO)


def run_linuxcnc(args: argparse.Namespace) -> int:
    from bridge.linuxcnc.config import load_config
    from bridge.linuxcnc.run import run_bridge, trial_metas

    from . import __version__

    cfg = load_config(args.config)
    if args.duration is not None and not 0 < args.duration <= 1e7:
        raise ValueError(f"--duration must be 0 < S <= 1e7 seconds, got {args.duration}")
    _logging()
    if os.geteuid() == 0 and cfg.hal.user is None:
        logging.getLogger("bridge.linuxcnc").warning(
            "running as root without [hal] user: the HAL helper runs as root, which LinuxCNC's shutdown cannot "
            "signal; set [hal] user to the user LinuxCNC runs as")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    session = None if args.no_publish else T.session_from_args(args)
    writer = None
    try:
        if args.record:
            import time

            from feedio.mcapio import TrialWriter

            writer = TrialWriter(args.record, trial_metas(cfg, tool="feedmon bridge linuxcnc", version=__version__),
                                 start=time.time_ns() - time.monotonic_ns())  # log time = wall clock of t
        counts = run_bridge(cfg, session=session, prefix=args.prefix, writer=writer, duration=args.duration,
                            stop=stop)
    finally:
        if writer is not None:
            writer.close()
        if session is not None:
            session.close()
    print("feedmon bridge: stopped; " + ", ".join(f"{k} {v}" for k, v in counts.items() if v), file=sys.stderr)
    return 0


def run_streamer_file(args: argparse.Namespace) -> int:
    from bridge.linuxcnc.streamer import write_streamer_file

    n = write_streamer_file(args.trial, args.output, axis=args.axis, scale=args.scale,
                            servo_period=args.servo_period)
    print(f"wrote {args.output}: {n} force values (N), one per servo cycle")
    return 0
