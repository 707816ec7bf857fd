#!/usr/bin/env python3
"""Plot a feedmon MCAP log in Rerun: ``disturbance/scalars`` channels → a Rerun recording (.rrd).

``rerun mcap convert log.mcap -o log.rrd`` (Rerun 0.41) keeps JSON channels as raw message bytes
(``McapMessage:data``), so nothing is plotted. This script reads every
``/<machine>/<axis>/disturbance/scalars`` channel with the plain ``mcap`` reader and writes each
numeric field as a Rerun time series at ``/<machine>/<axis>/<field>`` (``force``, ``force_sd``,
``truth_force``, ``f``, …) on the timeline ``log_time`` (the message's wall-clock log time) and
``sample`` (its sequence number)::

    python deploy/mcap_scalars_to_rerun.py logs/feedmon-20240501-080000-000.mcap -o log.rrd
    rerun log.rrd                       # then: a time-series view of /<machine>/<axis>/force

Only the ``mcap``, ``numpy`` and ``rerun-sdk`` packages are needed (no feedmon).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict

import numpy as np


def convert(source: str, output: str, application_id: str = "feedmon-mcap") -> dict[str, int]:
    """Write the scalars of ``source`` to ``output`` (.rrd); returns messages per channel."""
    import rerun as rr
    from mcap.reader import make_reader

    per_topic: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    counts: dict[str, int] = defaultdict(int)
    with open(source, "rb") as f:
        reader = make_reader(f)
        for _, channel, message in reader.iter_messages(log_time_order=False):
            if not channel.topic.endswith("/disturbance/scalars"):
                continue
            msg = json.loads(message.data)
            cols = per_topic[channel.topic]
            n = counts[channel.topic]
            for key, value in msg.items():
                if isinstance(value, (int, float)) and not isinstance(value, bool):
                    col = cols[key]
                    col.extend([math.nan] * (n - len(col)))  # a field left out of earlier messages
                    col.append(float(value))
            cols["__log_time"].append(message.log_time)
            counts[channel.topic] = n + 1
    rec = rr.RecordingStream(application_id)
    rec.save(output)
    for topic, cols in per_topic.items():
        base = topic[: -len("/disturbance/scalars")]
        n = counts[topic]
        times = np.array(cols.pop("__log_time"), dtype="datetime64[ns]")
        seq = np.array(cols.get("seq", np.arange(n)), dtype=np.int64)
        for key, values in cols.items():
            if key in ("seq", "t"):
                continue
            v = np.array(values + [math.nan] * (n - len(values)), dtype=np.float64)
            ok = np.isfinite(v)
            if not ok.any():
                continue
            rec.send_columns(
                f"{base}/{key}",
                indexes=[rr.TimeColumn("log_time", timestamp=times[ok]), rr.TimeColumn("sample", sequence=seq[ok])],
                columns=rr.Scalars.columns(scalars=v[ok]),
            )
    rec.flush()
    rec.disconnect()
    return dict(counts)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("mcap", help="feedmon MCAP log (live --mcap, run --from output)")
    p.add_argument("-o", "--output", required=True, help="Rerun recording to write (.rrd)")
    args = p.parse_args(argv)
    counts = convert(args.mcap, args.output)
    if not counts:
        print(f"{args.mcap}: no /<machine>/<axis>/disturbance/scalars channel", file=sys.stderr)
        return 1
    for topic, n in counts.items():
        print(f"{topic}: {n} samples")
    print(f"wrote {args.output}; open it with: rerun {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
