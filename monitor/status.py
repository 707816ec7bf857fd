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
:class:`BoundedCounter` counts per name up to a fixed number of names (the rest in
``overflow``), so names chosen by a peer never grow memory or the status document.

Names and keys that come from the network end up in log lines and tables:
:func:`safe_text` escapes control characters repr-style (CR LF → ``\\r\\n``, ESC →
``\\x1b``) and shortens long strings, so one log record stays one line and no peer can
forge log lines or drive the terminal; :func:`format_status` also escapes rich markup.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .status_doc import (
    AxisLatency,
    AxisModelRef,
    AxisReport,
    AxisStateRef,
    InputInfo,
    MonitorInfo,
    Percentiles,
    lenient,
)

__all__ = ["LatencyRing", "StageRing", "STAGES", "BurstLog", "BoundedCounter", "AxisStatus", "DROP_REASONS",
           "format_status", "safe_text", "EscapingFormatter"]

#: counter names that mean "input produced no (or a NaN) estimate row"; units in the README
DROP_REASONS = (
    "duplicate",
    "out_of_order",
    "rejected_non_finite",
    "rejected_out_of_range",
    "rejected_missing_field",
    "rejected_seq_range",
    "malformed",
    "too_large",
    "key_mismatch",
    "input_queue_full",
    "shutdown_discarded",
    "estimator_error",
)


def safe_text(value: Any, limit: int = 200) -> str:
    """``str(value)`` for a log line or a table cell: control and other non-printable characters
    escaped repr-style (``\\n``, ``\\x1b``, ``\\u2028``), cut to ``limit`` characters (``…(+N)``)."""
    s = value if isinstance(value, str) else str(value)
    cut = len(s) - limit
    if cut > 0:
        s = s[:limit]
    if not s.isprintable():
        s = "".join(c if c.isprintable() else repr(c)[1:-1] for c in s)
    return f"{s}…(+{cut} chars)" if cut > 0 else s


class EscapingFormatter(logging.Formatter):
    """A formatter whose message part is always one line of printable text (:func:`safe_text`,
    no length cut); tracebacks keep their lines."""

    def formatMessage(self, record: logging.LogRecord) -> str:  # noqa: N802 - logging's name
        record.message = safe_text(record.message, limit=1 << 30)
        return super().formatMessage(record)


def log_format() -> str | None:
    """The format of this process' log lines, for a child process to log alike (None: not configured)."""
    root = logging.getLogger()
    return getattr(root.handlers[0].formatter, "_fmt", None) if root.handlers and root.handlers[0].formatter else None


def install_log_format(fmt: str | None) -> None:
    """In a child process: log INFO and above to stderr with ``fmt`` through :class:`EscapingFormatter`
    (nothing when ``fmt`` is None)."""
    if not fmt:
        return
    handler = logging.StreamHandler()
    handler.setFormatter(EscapingFormatter(fmt))
    logging.getLogger().addHandler(handler)
    logging.getLogger().setLevel(logging.INFO)


class BoundedCounter:
    """Counts per name for at most ``limit`` distinct names; counts of further names go to
    :attr:`overflow`. Written by one thread; :meth:`to_dict` may be called from another."""

    def __init__(self, limit: int) -> None:
        self.limit = int(limit)
        self.counts: dict[str, int] = {}
        self.overflow = 0

    def add(self, name: str, n: int = 1) -> bool:
        """Count ``n`` for ``name``; False when the table is full and ``name`` is not in it."""
        c = self.counts
        if name in c:
            c[name] += n
            return True
        if len(c) < self.limit:
            c[name] = n
            return True
        self.overflow += n
        return False

    def to_dict(self) -> dict[str, int]:
        return dict(self.counts)  # one C call: consistent under the GIL


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


#: the stages of a message inside the monitor, in order (µs each; see :class:`StageRing`)
STAGES = ("queue", "decode", "estimate", "encode", "publish", "sinks")


class StageRing:
    """Fixed-size ring of per-message stage times (µs), one row per stage of :data:`STAGES`:

    * ``queue``: from the arrival in the Zenoh callback to the start of decoding: the callback's
      own bookkeeping (size check, lock, copy of the payload) and, for a message that went through
      the input queue, its wait there and the hand-over to the estimator thread;
    * ``decode``: JSON → :class:`~feedio.schema.SampleBlock`, schema and key checks;
    * ``estimate``: routing and the estimator (the compiled tracker loop and the Python around it);
    * ``encode``: the :class:`~feedio.schema.EstimateBlock` and its JSON;
    * ``publish``: the Zenoh ``put``;
    * ``sinks``: handing the input and the estimate to the sinks (after the publish; not part of
      the latency).

    :meth:`record` writes one column in place (O(1), no allocation); percentiles are computed on
    demand over the last ``size`` messages."""

    def __init__(self, size: int = 4096) -> None:
        if size < 1:
            raise ValueError(f"stage ring size must be ≥ 1, got {size}")
        self._buf = np.zeros((len(STAGES), int(size)), dtype=np.float64)
        self._n = 0

    def record(self, queue: float, decode: float, estimate: float, encode: float, publish: float,
               sinks: float) -> None:
        """One message's stage times in seconds."""
        i = self._n % self._buf.shape[1]
        b = self._buf
        b[0, i] = queue * 1e6
        b[1, i] = decode * 1e6
        b[2, i] = estimate * 1e6
        b[3, i] = encode * 1e6
        b[4, i] = publish * 1e6
        b[5, i] = sinks * 1e6
        self._n += 1

    @property
    def count(self) -> int:
        return self._n

    def values(self) -> np.ndarray:
        """Copy of the recorded stage times, shape ``(len(STAGES), window)`` (µs, unordered)."""
        return self._buf[:, :min(self._n, self._buf.shape[1])].copy()

    @staticmethod
    def summarize(values: np.ndarray) -> dict[str, dict[str, float | None]]:
        """``{stage: {"p50", "p99"}}`` (µs, None without values) of a ``values()`` array."""
        if values.shape[1] == 0:
            return {s: {"p50": None, "p99": None} for s in STAGES}
        pct = np.percentile(values, [50.0, 99.0], axis=1)
        return {s: {"p50": round(float(pct[0, k]), 1), "p99": round(float(pct[1, k]), 1)}
                for k, s in enumerate(STAGES)}

    def summary(self) -> dict[str, dict[str, float | None]]:
        return self.summarize(self.values())


class BurstLog:
    """Log once per burst: the first event is logged, later ones counted until ``quiet`` s without events.

    String arguments are passed through :func:`safe_text`. At most ``max_keys`` burst keys are
    tracked; events of further keys share one key (a peer inventing keys cannot grow memory or
    the number of log lines).
    """

    OVERFLOW_KEY = "(other keys)"

    def __init__(self, logger: logging.Logger, quiet: float = 10.0, max_keys: int = 4096) -> None:
        self.log = logger
        self.quiet = float(quiet)
        self.max_keys = int(max_keys)
        self._last: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()

    def __call__(self, key: str, msg: str, *args: Any, level: int = logging.WARNING) -> None:
        now = time.monotonic()
        if key not in self._last and len(self._last) >= self.max_keys:
            key = self.OVERFLOW_KEY
        args = tuple(safe_text(a) if isinstance(a, str) else a for a in args)
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
    stages: StageRing = field(default_factory=StageRing)
    state: str = "fresh"  # fresh | restored | ignored (mismatch) | unreadable
    state_path: str | None = None
    last_seq: int | None = None
    last_t: float | None = None
    blocks: int = 0
    health: dict | None = None  # the last health report (state, reasons, values) and since when its state holds
    health_changes: int = 0  # changes of the health state since start

    @property
    def name(self) -> str:
        return f"{self.machine}/{self.axis}"

    def note_health(self, report) -> str | None:
        """Take a :class:`~feedio.schema.Health` report; returns the previous state when the state changed
        (``"ok"`` before the first report), else None. The first report in state ok is no change."""
        import msgspec

        doc = msgspec.to_builtins(report)
        prev = self.health
        was = prev["state"] if prev else "ok"
        changed = doc["state"] != was
        if changed or prev is None:
            since = {"since_t": doc["t"], "since_seq": doc["seq"], "since_unix": time.time()}
        else:
            since = {k: prev[k] for k in ("since_t", "since_seq", "since_unix")}
        doc.pop("machine", None)
        doc.pop("axis", None)
        self.health = {**doc, **since}
        if changed:
            self.health_changes += 1
            return was
        return None

    def report(self, estimator_counters: Counter, dict_size: int,
               refused: dict[str, int] | None = None, input_health: dict[str, Any] | None = None,
               process: dict[str, Any] | None = None) -> AxisReport:
        """The axis' status; ``refused``: per-reason counts kept outside this object (the Zenoh
        callback's refusals, discards at shutdown), merged into ``drops`` and ``counters``; ``input_health``:
        the input-health verdict of the axis; ``process``: the process monitors' (None: off).

        Built on the status thread while the estimating thread runs: ``last_seq``/``last_t`` are read
        *before* the counters. The estimator counts a block before the pipeline sets ``last_seq`` to
        its end, so the document never shows a sample as the last one seen without it in
        ``samples_in`` (read the other way round, a switch of the interpreter lock in between let a
        status show ``last_seq`` 199 with ``samples_in`` 100)."""
        last_seq, last_t = self.last_seq, self.last_t
        c = dict(estimator_counters)
        for src in (dict(self.counters), refused or {}):
            for k, v in src.items():
                c[k] = c.get(k, 0) + v
        drops = {r: int(c[r]) for r in DROP_REASONS if c.get(r)}
        return AxisReport(
            machine=self.machine,
            axis=self.axis,
            samples_in=int(c.get("samples_in", 0)),
            estimates_out=int(c.get("estimates_out", 0)),
            blocks=self.blocks,
            trained=int(c.get("trained", 0)),
            gaps=int(c.get("gaps", 0)),
            missing_samples=int(c.get("missing_samples", 0)),
            stale=int(c.get("stale", 0)),
            restarts=int(c.get("restarts", 0)),
            drops=drops,
            dropped_total=int(sum(drops.values())),
            counters={k: int(v) for k, v in sorted(c.items())},
            latency_us=AxisLatency(**self.latency.summary()),
            stages_us={k: Percentiles(**v) for k, v in self.stages.summary().items()},
            dict_size=int(dict_size),
            last_seq=last_seq,
            last_t=last_t,
            model=AxisModelRef(path=self.model_path, sha256=self.model_sha256),
            state=AxisStateRef(origin=self.state, path=self.state_path),
            health=None if self.health is None else {**self.health, "changes": self.health_changes},
            input=input_health,
            process=process,
        )


def _is_num(v) -> bool:
    """A real number of a status document (bool is not one)."""
    return isinstance(v, int | float) and not isinstance(v, bool)


def _fmt_us(v) -> str:
    return f"{v:,.0f}" if _is_num(v) and math.isfinite(v) else "–"


def _cell(value: Any, limit: int = 200):
    """A table cell / text from a status document (which may come from any peer): control
    characters escaped, long text cut, no rich markup interpreted."""
    from rich.text import Text

    return Text(safe_text("" if value is None else value, limit))


def _counts(value: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in value.items())


def _num(v: Any) -> str:
    return f"{v:.3f}" if _is_num(v) and math.isfinite(v) else "–"


def _health_values(h: dict) -> str:
    """``inertia 300.1 ± 0.5 kg, …`` of a health report (values not given are left out)."""
    parts = []
    for key, unit in (("inertia", "kg"), ("damping", "N·s/m"), ("coulomb", "N"), ("offset", "N")):
        v, se = h.get(key), h.get(f"{key}_se")
        if _is_num(v) and _is_num(se):
            parts.append(f"{key} {v:.4g} ± {se:.2g} {unit}")
    nu2 = h.get("nu2")
    if _is_num(nu2):
        parts.append(f"mean ν² {nu2:.2f}")
    return ", ".join(parts) + f"; β adaptation {h.get('adaptation')}"


def format_status(status: dict[str, Any], console=None) -> None:
    """Print a status dict (as answered by a monitor) as rich tables.

    Every value is shown as plain text (:func:`safe_text`, no markup): a machine named ``[/]``
    or a name with ANSI escapes prints as itself. Each section is read as its Struct of
    :mod:`monitor.status_doc` (:func:`~monitor.status_doc.lenient`): a section of an unexpected shape
    prints as empty instead of raising.
    """
    from rich.console import Console
    from rich.table import Table
    from rich.text import Text

    console = console or Console()
    doc = status if isinstance(status, dict) else {}
    mon, inp = lenient(doc.get("monitor"), MonitorInfo), lenient(doc.get("input"), InputInfo)
    axes = {name: lenient(a, AxisReport) for name, a in doc.get("axes").items()} \
        if isinstance(doc.get("axes"), dict) else {}
    up = f"{mon.uptime_s:.1f}" if _is_num(mon.uptime_s) else "?"
    head = Text("feedmon monitor", style="bold")
    head.append(safe_text(
        f" pid {mon.pid} on {mon.host}, prefix {mon.prefix!r}, {mon.state}, up {up} s; "
        f"input: {inp.received} msgs, queue {inp.pending}/{inp.capacity}, "
        f"refused: queue_full {inp.queue_full}, too_large {inp.too_large}, "
        f"malformed {inp.malformed}, key_mismatch {inp.key_mismatch_total}", limit=2000))
    console.print(head)
    t = Table(title="axes")
    for col in ("axis", "in", "out", "dropped", "gaps", "p50 µs", "p99 µs", "dict", "state", "health", "input"):
        t.add_column(col, justify="left" if col in ("axis", "dropped", "state", "health", "input") else "right")
    for name, a in axes.items():
        t.add_row(_cell(name), _cell(a.samples_in), _cell(a.estimates_out), _cell(_counts(a.drops) or "0"),
                  _cell(a.gaps), _fmt_us(a.latency_us.p50), _fmt_us(a.latency_us.p99), _cell(a.dict_size),
                  _cell(a.state.origin), _cell((a.health or {}).get("state", "–")),
                  _cell((a.input or {}).get("state", "–")))
    console.print(t)
    if any(a.stages_us for a in axes.values()):
        st = Table(title="latency by stage, µs (p50 / p99): queue, decode, estimate, encode, publish, then sinks")
        st.add_column("axis")
        for stage in STAGES:
            st.add_column(stage, justify="right")
        for name, a in axes.items():
            none = Percentiles()
            st.add_row(_cell(name), *(f"{_fmt_us(a.stages_us.get(k, none).p50)} / "
                                      f"{_fmt_us(a.stages_us.get(k, none).p99)}" for k in STAGES))
        console.print(st)
    for name, a in axes.items():
        console.print(_cell(f"  {name}: model {a.model.path} sha256 {a.model.sha256}", 1000))
    for name, a in axes.items():
        h = a.health
        if h:
            console.print(_cell(f"  {name}: health {str(h.get('state', '?')).upper()} since t = {_num(h.get('since_t'))} s "
                                f"(seq {h.get('since_seq')}); last report t = {_num(h.get('t'))} s; "
                                + _health_values(h), 2000))
            reasons = h.get("reasons")
            for r in reasons if isinstance(reasons, list) else []:
                console.print(_cell(f"    - {r}", 1000))
    for name, a in axes.items():  # the process monitors (monitor.process_monitor): count and last alarm
        pm = a.process if isinstance(a.process, dict) else None
        if pm:
            last = pm.get("last") if isinstance(pm.get("last"), dict) else None
            kinds = pm.get("by_kind") if isinstance(pm.get("by_kind"), dict) else ""
            said = (f"; last {last.get('kind')} at t = {_num(last.get('t'))} s (seq {last.get('seq')}): "
                    f"{_num(last.get('value'))} against {_num(last.get('limit'))} N") if last else ""
            console.print(_cell(f"  {name}: process alarms {pm.get('alarms', 0)} {kinds or ''}{said}", 1000))
    for key, what in (("no_model", "samples of axes without a model (dropped)"),
                      ("key_mismatch", "messages whose payload names another axis than their key (refused)")):
        table = getattr(inp, key)
        over = getattr(inp, f"{key}_overflow")
        if table or over:
            console.print(_cell(f"{what}: {_counts(table)}" + (f"; more names: {over}" if over else ""), 2000))
    sinks = [s for s in doc.get("sinks") if isinstance(s, dict)] if isinstance(doc.get("sinks"), list) else []
    if sinks:
        st = Table(title="sinks")
        cols = ("name", "state", "accepted", "written", "dropped", "lost", "failures", "restarts", "pending")
        for col in cols:
            st.add_column("sink" if col == "name" else col)
        for s in sinks:
            st.add_row(*(_cell(s.get(c, 0 if c in ("lost", "restarts") else None)) for c in cols))
        console.print(st)
        for s in sinks:
            where = [x for x in (s.get("current_file"), s.get("rrd_path"), s.get("server_uri")) if x]
            if where:
                console.print(_cell(f"  {s.get('name')}: {', '.join(map(str, where))}", 1000))
            if s.get("state") not in ("ok", "closed", None) or s.get("lost") or s.get("restarts"):
                why = s.get("degraded") if s.get("state") == "degraded" else s.get("last_error")
                console.print(_cell(f"  {s.get('name')} {str(s.get('state')).upper()}: {why}", 2000))
            for key, what in (("incomplete_files", f"incomplete ({s.get('incomplete_note') or 'cut short'})"),
                              ("removed_files", "removed while being written")):
                if s.get(key):
                    console.print(_cell(f"  {s.get('name')}: {what}: {', '.join(map(str, s[key]))}", 2000))
