"""``feedmon simulate SCENARIO -o trial.mcap`` — a simulated trial with known truth;
``feedmon simulate SCENARIO --parts N -o DIR`` — a series of N parts (:mod:`replay.parts`)."""

from __future__ import annotations

import argparse
import time

from replay import scenarios as SC
from replay.parts import MAX_PARTS


def _scenario_table() -> str:
    desc = SC.describe()
    width = max(map(len, desc))
    return "\n".join(f"  {name:<{width}}  {text}" for name, text in desc.items())


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="simulate a feed-drive trial with known truth and write it as MCAP",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Simulate a closed-loop feed-drive trial (method §1) after the thesis case studies and\n"
            "write samples, ground truth (disturbance force, true drive constants per sample) and\n"
            "metadata to an MCAP trial file. An unstable closed loop or a non-finite/absurd result\n"
            "is refused and nothing is written. Process scenarios (milling-part, milling-tooth-break, …)\n"
            "add NC line and tool columns and truth events (/<machine>/<axis>/truth/events); with\n"
            "--parts N a process scenario is cut N times with part-to-part variation ([series] of the\n"
            "scenario: material, spindle speed, feed override, optional wear), one file per part in the\n"
            "directory -o. Scenarios (--list):\n\n" + _scenario_table()
        ),
    )
    p.add_argument("scenario", metavar="SCENARIO", nargs="?", choices=SC.SCENARIOS,
                   help="built-in scenario (see --list)")
    p.add_argument("-o", "--output", help="output MCAP file")
    p.add_argument("--list", action="store_true", help="list the scenarios with their descriptions and exit")
    p.add_argument("--seed", type=int, default=0, help="random seed (noise, glitches); default 0")
    p.add_argument("--duration", type=float, default=None, help="trial length in seconds (default: scenario)")
    p.add_argument("--config", default=None, help="TOML file overriding any scenario constant")
    p.add_argument("--fine", action="store_true",
                   help="integrate the plant at 10 kHz, anti-alias filter and decimate to Ts (as recorded on the machine)")
    p.add_argument("--created", default=None,
                   help="creation time (ISO 8601, e.g. 2024-05-01T08:00:00Z) stored in the provenance and used as the "
                        "trial's start time, which the MCAP log times count from (default: now, not stored); give it "
                        "for byte-identical files")
    p.add_argument("--show", action="store_true", help="print the scenario constants and exit")
    p.add_argument("--parts", type=int, default=None, metavar="N",
                   help=f"simulate a series of N parts (1 … {MAX_PARTS}) of a process scenario into the directory -o "
                        "(part-0000.mcap, …), each varied as its [series] table says")
    p.add_argument("--wear", type=float, default=None, metavar="REL",
                   help="with --parts: relative force increase per part by tool wear (0.01 = +1 %% per part; "
                        "default: the scenario's series.wear_per_part)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from replay.simulator import simulate, write_trial

    if args.list:
        print(_scenario_table())
        return 0
    if args.scenario is None:
        raise ValueError(f"give a SCENARIO (one of {', '.join(SC.SCENARIOS)}; --list describes them)")
    if args.output is None and not args.show:
        raise ValueError("give the output trial file with -o/--output")
    if args.seed < 0:
        raise ValueError(f"--seed must be ≥ 0, got {args.seed}")
    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be > 0 s, got {args.duration}")
    if args.wear is not None and args.parts is None:
        raise ValueError("--wear belongs to a part series: give --parts N too")
    sc = SC.load_scenario(args.scenario, args.config, duration=args.duration)
    if args.parts is not None and not args.show:
        return _series(args, sc)
    if args.show:
        import json

        print(json.dumps(sc, indent=2))
        return 0
    t0 = time.perf_counter()
    res = simulate(sc, seed=args.seed, fine=args.fine, created=args.created)
    write_trial(res, args.output)
    beta = ", ".join(f"{n}={b:.6g}" for n, b in zip(res.meta.truth.beta_names, res.beta))
    varying = res.meta.provenance.details.get("time_varying")
    print(
        f"wrote {args.output}: {args.scenario}, {len(res)} samples, Ts = {res.meta.Ts:.6g} s, "
        f"seed {args.seed}{', fine' if args.fine else ''} ({time.perf_counter() - t0:.2f} s); true β"
        f"{' at t = 0' if varying else ''}: {beta}"
        + (f"; time-varying: {', '.join(varying)} (per sample in the truth channel)" if varying else "")
    )
    return 0


def _series(args: argparse.Namespace, sc: dict) -> int:
    from replay.parts import part_duration, part_variations, simulate_series

    if not 1 <= args.parts <= MAX_PARTS:
        raise ValueError(f"--parts must be 1 … {MAX_PARTS}, got {args.parts}")
    if args.output is None:
        raise ValueError("give the output directory of the part files with -o/--output")
    t0 = time.perf_counter()
    paths = simulate_series(sc, args.parts, args.output, seed=args.seed, created=args.created, wear_per_part=args.wear,
                            fine=args.fine)
    cut = sum(part_duration(sc, v.feed_override)
              for v in part_variations(sc, args.parts, seed=args.seed, wear_per_part=args.wear))
    print(f"wrote {len(paths)} parts of {args.scenario} to {args.output} ({paths[0].name} … {paths[-1].name}): "
          f"{cut:.0f} s of machining in {time.perf_counter() - t0:.1f} s, seed {args.seed}")
    return 0
