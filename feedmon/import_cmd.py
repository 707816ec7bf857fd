"""``feedmon import emps|csv …`` — real recordings to MCAP trial files."""

from __future__ import annotations

import argparse

_START_HELP = ("wall-clock time of the first sample, ISO 8601 (e.g. 2024-05-01T08:00:00Z; no zone = UTC); "
               "the MCAP log times count from it (default: now, the creation time — give it for byte-identical files)")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "import",
        help="import a recording (EMPS .mat, CSV) into an MCAP trial file",
        description="Convert a recorded trial into an MCAP trial file (SI units, feedmon schema).",
    )
    sub = p.add_subparsers(dest="source", metavar="SOURCE", required=True)

    e = sub.add_parser("emps", help="EMPS benchmark drive (DATA_EMPS.mat or DATA_EMPS_PULSES.mat)",
                       description="EMPS benchmark (nonlinearbenchmark.org), force-input form: u = gtau·vir (N), "
                                   "velocity from zero-phase filtered position. For the PULSES file the PD-law force is "
                                   "the command and the pulse force goes on the truth channel.")
    e.add_argument("data", metavar="DATA.mat")
    e.add_argument("-o", "--output", required=True, help="output MCAP file")
    e.add_argument("--rate", type=int, choices=(333, 1000), default=333,
                   help="333: decimate by 3 (Ts = 3 ms, force averaged over each interval); 1000: keep 1 kHz")
    e.add_argument("--start", default=None, metavar="TIME", help=_START_HELP)
    e.set_defaults(func=run_emps)

    c = sub.add_parser("csv", help="CSV export of any controller",
                       description="CSV with a header row. Units: s, ms, us, m/s, mm/s, mm/min, m/min, N, kN, A, mA, "
                                   "m, mm, um, rpm, rev/s.")
    c.add_argument("file", metavar="FILE")
    c.add_argument("-o", "--output", required=True, help="output MCAP file")
    c.add_argument("--map", required=True,
                   help="feedmon field=CSV column, comma separated: t=…,v_meas=…[,v_ref=…,u=…,current=…,position=…,spindle_rpm=…]")
    c.add_argument("--units", default=None, help="field=unit, comma separated (default SI: t in s), e.g. "
                                                    "t=ms,v_meas=mm/min")
    c.add_argument("--form", choices=("velocity-loop", "force-input"), default="velocity-loop",
                   help="velocity-loop (default): the controller closes a velocity loop, map v_ref; force-input: "
                        "the command is a force or current, map u")
    c.add_argument("--machine", default="machine",
                   help="machine name in the trial (letters, digits, _ . -; default 'machine'): the monitor's "
                        "model files and Zenoh keys use it")
    c.add_argument("--axis", default="X", help="axis name in the trial (letters, digits, _ . -; default 'X')")
    c.add_argument("--loop-gain", type=float, default=None, help="velocity loop gain K (N·s/m) when known")
    c.add_argument("--Ts", type=float, default=None, help="sampling time (s); default: median time step")
    c.add_argument("--start", default=None, metavar="TIME", help=_START_HELP)
    c.set_defaults(func=run_csv)


def run_emps(args: argparse.Namespace) -> int:
    from replay.importers import import_emps

    tr = import_emps(args.data, args.output, rate=args.rate, start=args.start)
    extra = ", pulse truth on the truth channel" if tr.truth_force is not None else ""
    print(f"wrote {args.output}: EMPS, {len(tr)} samples, Ts = {tr.meta.Ts:g} s, force-input form{extra}")
    return 0


def run_csv(args: argparse.Namespace) -> int:
    from replay.importers import import_csv

    tr = import_csv(args.file, args.output, args.map, args.units, form=args.form, machine=args.machine,
                    axis=args.axis, loop_gain=args.loop_gain, Ts=args.Ts, start=args.start)
    print(f"wrote {args.output}: {tr.meta.machine}/{tr.meta.axis}, {len(tr)} samples, Ts = {tr.meta.Ts:g} s, {tr.meta.form} form")
    return 0
