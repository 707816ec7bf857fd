"""Monitor status: per-axis counters, latency percentiles, uptime, sinks, model provenance.

Everything here is cheap on the hot path (the estimator thread) and safe to read
from another thread (the Zenoh queryable callback): counters are plain ints and
``Counter`` objects copied with ``dict(...)`` (one C call under the GIL), the
latency ring is a fixed NumPy array written in place.

:class:`LatencyRing` keeps the last ``size`` latencies (µs) of one stream; the
percentiles are computed on demand (``np.percentile`` over at most ``size``
values), so recording is O(1) and memory is fixed however long the monitor runs.
:class:`BurstLog` logs the first event of a burst and counts the rest until the
source has been quiet for ``quiet`` seconds (one log line per burst, never a flood).
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["LatencyRing", "BurstLog", "AxisStatus", "DROP_REASONS", "format_status"]

#: counter names that mean "a sample produced no (or a NaN) estimate row"
DROP_REASONS = (
    "duplicate",
    "out_of_order",
    "rejected_non_finite",
    "rejected_out_of_range",
    "rejected_missing_field",
    "rejected_seq_range",
    "malformed",
    "input_queue_full",
    "estimator_error",
)


class LatencyRing:
    """Fixed-size ring of the most recent latencies in microseconds."""

    def __init__(self, size: int = 4096) -> None:
        if size < 1:
            raise ValueError(f"latency ring size must be ≥ 1, got {size}")
        self._buf = np.zeros(int(size), dtype=np.float64)
        self._n = 0  # total recorded
        self.max_us = 0.0

    def record(self, seconds: float) -> None:
        us = seconds * 1e6
        self._buf[self._n % self._buf.size] = us
        self._n += 1
        if us > self.max_us:
            self.max_us = us

    @property
    def count(self) -> int:
        return self._n

    def values(self) -> np.ndarray:
        """Copy of the latencies in the ring (µs, unordered)."""
        n = min(self._n, self._buf.size)
        return self._buf[:n].copy()

    def summary(self) -> dict[str, Any]:
        """``{"p50", "p99", "max", "count", "window"}`` in µs (None before the first value)."""
        v = self.values()
        if v.size == 0:
            return {"p50": None, "p99": None, "max": None, "count": 0, "window": 0}
        p50, p99 = np.percentile(v, [50.0, 99.0])
        return {"p50": round(float(p50), 1), "p99": round(float(p99), 1), "max": round(float(self.max_us), 1),
                "count": int(self._n), "window": int(v.size)}


class BurstLog:
    """Log once per burst: the first event is logged, later ones counted until ``quiet`` s without events."""

    def __init__(self, logger: logging.Logger, quiet: float = 10.0) -> None:
        self.log = logger
        self.quiet = float(quiet)
        self._last: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()

    def __call__(self, key: str, msg: str, *args: Any, level: int = logging.WARNING) -> None:
        now = time.monotonic()
        last = self._last.get(key)
        self._last[key] = now
        if last is not None and now - last < self.quiet:
            self._suppressed[key] += 1
            return
        n = self._suppressed.pop(key, 0)
        tail = f" ({n} more since the last report)" if n else ""
        self.log.log(level, msg + tail + " [further ones are counted, logged again after %.0f s quiet]",
                     *args, self.quiet)


@dataclass
class AxisStatus:
    """Monitor-side bookkeeping of one axis (the estimator keeps its own ``counters``)."""

    machine: str
    axis: str
    model_path: str
    model_sha256: str
    counters: Counter = field(default_factory=Counter)  # malformed, input_queue_full, estimator_error, ...
    latency: LatencyRing = field(default_factory=LatencyRing)
    state: str = "fresh"  # fresh | restored | ignored (mismatch) | unreadable
    state_path: str | None = None
    last_seq: int | None = None
    last_t: float | None = None
    blocks: int = 0

    @property
    def name(self) -> str:
        return f"{self.machine}/{self.axis}"

    def report(self, estimator_counters: Counter, dict_size: int) -> dict[str, Any]:
        c = dict(estimator_counters)
        for k, v in dict(self.counters).items():
            c[k] = c.get(k, 0) + v
        drops = {r: int(c[r]) for r in DROP_REASONS if c.get(r)}
        return {
            "machine": self.machine,
            "axis": self.axis,
            "samples_in": int(c.get("samples_in", 0)),
            "estimates_out": int(c.get("estimates_out", 0)),
            "blocks": self.blocks,
            "trained": int(c.get("trained", 0)),
            "gaps": int(c.get("gaps", 0)),
            "missing_samples": int(c.get("missing_samples", 0)),
            "stale": int(c.get("stale", 0)),
            "restarts": int(c.get("restarts", 0)),
            "drops": drops,
            "dropped_total": int(sum(drops.values())),
            "counters": {k: int(v) for k, v in sorted(c.items())},
            "latency_us": self.latency.summary(),
            "dict_size": int(dict_size),
            "last_seq": self.last_seq,
            "last_t": self.last_t,
            "model": {"path": self.model_path, "sha256": self.model_sha256},
            "state": {"origin": self.state, "path": self.state_path},
        }


def _fmt_us(v) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:,.0f}"


def format_status(status: dict[str, Any], console=None) -> None:
    """Print a status dict (as answered by the monitor) as rich tables."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    mon = status.get("monitor", {})
    inp = status.get("input", {})
    console.print(
        f"[bold]feedmon monitor[/] pid {mon.get('pid')} on {mon.get('host')}, "
        f"prefix {mon.get('prefix')!r}, {mon.get('state')}, up {mon.get('uptime_s', 0):.1f} s; "
        f"input: {inp.get('received', 0)} msgs, queue {inp.get('pending', 0)}/{inp.get('capacity', 0)}, "
        f"dropped {inp.get('queue_full', 0)}, malformed {inp.get('malformed', 0)}"
    )
    t = Table(title="axes")
    for col in ("axis", "in", "out", "dropped", "gaps", "p50 µs", "p99 µs", "dict", "state"):
        t.add_column(col, justify="left" if col in ("axis", "dropped", "state") else "right")
    for name, a in status.get("axes", {}).items():
        drops = ", ".join(f"{k}={v}" for k, v in a.get("drops", {}).items()) or "0"
        lat = a.get("latency_us", {})
        t.add_row(name, str(a.get("samples_in")), str(a.get("estimates_out")), drops, str(a.get("gaps")),
                  _fmt_us(lat.get("p50")), _fmt_us(lat.get("p99")), str(a.get("dict_size")),
                  a.get("state", {}).get("origin", ""))
    console.print(t)
    for name, a in status.get("axes", {}).items():
        m = a.get("model", {})
        console.print(f"  {name}: model {m.get('path')} sha256 {m.get('sha256')}")
    nm = inp.get("no_model") or {}
    if nm:
        console.print("samples of axes without a model (dropped): " + ", ".join(f"{k}={v}" for k, v in nm.items()))
    sinks = status.get("sinks") or []
    if sinks:
        st = Table(title="sinks")
        for col in ("sink", "state", "accepted", "written", "dropped", "failures", "pending"):
            st.add_column(col)
        for s in sinks:
            st.add_row(str(s.get("name")), str(s.get("state")), str(s.get("accepted")), str(s.get("written")),
                       str(s.get("dropped")), str(s.get("failures")), str(s.get("pending")))
        console.print(st)
        for s in sinks:
            where = [x for x in (s.get("current_file"), s.get("rrd_path"), s.get("server_uri")) if x]
            if where:
                console.print(f"  {s.get('name')}: {', '.join(map(str, where))}")
