"""``feedmon wear show``: a wear history's sections and their verdicts (``docs/process-monitoring.md``, "Wear").

Example::

    feedmon wear show x.wear.json          # judged with the defaults of [monitors.wear]
"""

from __future__ import annotations

import argparse


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("wear", help="show a wear history (feedmon run --wear-history)",
                              description="The wear history across parts: per section, its parts and the trend.")
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    sp = sub.add_parser("show", help="print a wear history's sections and their verdicts")
    sp.add_argument("file", metavar="FILE")
    sp.set_defaults(func=_show)
    return p


def _show(args: argparse.Namespace) -> int:
    from monitor.process_monitor.settings import WearSettings
    from monitor.process_monitor.wear import judge, load_history

    hist = load_history(args.file)
    s = WearSettings(history=args.file)
    print(f"{args.file}: {sum(len(a.sections) for a in hist.axes)} section(s); trend over the last {s.window} parts, "
          f"alarm when t > {s.sensitivity:g} and rise > {s.min_rise:.0%} (the defaults)")
    print(f"{'axis':<20} {'section':<18} {'parts':>5} {'last part':<24} {'|F| N':>8} {'rise':>7} {'t':>6}")
    for a in hist.axes:
        for sec in a.sections:
            last = sec.parts[-1] if sec.parts else None
            v = judge([p.mean_force_N for p in sec.parts], s)
            trend = f"{v.rise:>+7.1%} {v.t:>6.1f}{'  WEAR' if v.alarm else ''}" if v is not None else f"{'—':>7} {'—':>6}"
            print(f"{a.machine + '/' + a.axis:<20} {sec.key:<18} {len(sec.parts):>5} "
                  f"{last.part if last else '—':<24} {abs(last.mean_force_N) if last else 0:>8.1f} {trend}")
    return 0
