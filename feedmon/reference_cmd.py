"""``feedmon reference``: reference envelopes for the process monitors (``docs/process-monitoring.md``).

Examples::

    feedmon reference learn good-01.mcap … good-10.mcap -o part.ref.json   # estimates logs of good runs
    feedmon reference show part.ref.json
    feedmon run --from part-11.mcap --model x.model.toml -o out.mcap --reference part.ref.json
"""

from __future__ import annotations

import argparse


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("reference", help="learn or show a process reference (force envelope per NC section)",
                              description="Reference envelopes of the process monitors: the mean force over "
                                          "program progress per tool/NC section and its spread over good runs.")
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    lp = sub.add_parser("learn", help="learn a reference from the estimates logs of good runs")
    lp.add_argument("logs", nargs="+", metavar="LOG", help="estimates logs (feedmon run -o / --mcap), ≥ 2")
    lp.add_argument("-o", "--output", required=True, metavar="FILE", help="reference file to write (JSON)")
    lp.add_argument("--axis", default=None, metavar="MACHINE/AXIS", help="the axis (when a log has several)")
    lp.add_argument("--bin", dest="bin_s", type=float, default=0.05, metavar="S",
                    help="progress bin width in s (default 0.05; 0.001 … 60)")
    lp.set_defaults(func=_learn)
    sp = sub.add_parser("show", help="print a reference file's sections")
    sp.add_argument("file", metavar="FILE")
    sp.set_defaults(func=_show)
    return p


def _learn(args: argparse.Namespace) -> int:
    from monitor.process_monitor.reference import learn_reference, save_reference

    ref = learn_reference(args.logs, axis=args.axis, bin_s=args.bin_s)
    if not ref.sections:
        raise ValueError("no section is common to every run: nothing to learn (are these runs of one program?)")
    save_reference(ref, args.output)
    print(f"wrote {args.output}: {ref.machine}/{ref.axis}, {len(ref.sections)} section(s) from {len(args.logs)} runs")
    return 0


def _show(args: argparse.Namespace) -> int:
    import numpy as np

    from monitor.process_monitor.reference import load_reference

    ref = load_reference(args.file)
    print(f"{args.file}: axis {ref.machine}/{ref.axis}, from {len(ref.sources)} runs ({', '.join(ref.sources[:5])}"
          f"{', …' if len(ref.sources) > 5 else ''})")
    print(f"{'section':<24} {'runs':>4} {'length s':>9} {'mean N':>8} {'max N':>8} {'spread N':>9}")
    for s in ref.sections:
        m, sp = s.mean_array, s.spread_array
        print(f"{s.key:<24} {s.runs:>4} {m.size * s.bin_s:>9.2f} {float(np.mean(m)) if m.size else 0:>8.1f} "
              f"{float(np.max(m)) if m.size else 0:>8.1f} {float(np.median(sp)) if sp.size else 0:>9.2f}")
    return 0
