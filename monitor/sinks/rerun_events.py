"""Readable events from the per-sample estimate flags of one axis (the dashboard's event log).

The monitor flags every estimate row (``feedio.schema`` bits STALE, GAP, REJECTED, WARMUP,
REDUCED). A log line per flagged sample would bury what matters, so :class:`FlagDigest` turns the
flag columns into a few events:

=========  =================================================================  =========
flag       event                                                               level
=========  =================================================================  =========
GAP        one per gap: where, how many samples were missing                   WARN
REJECTED   one per run of consecutive rejected samples (first, count)          WARN
STALE      one per run of repeated measurements (recording glitch)             INFO
WARMUP     when a warm-up starts and when it ends                              INFO
REDUCED    one summary per ``summary_s`` seconds of data (count, share)        DEBUG
=========  =================================================================  =========

Every event is stamped at the sample it concerns (row ``j`` flags sample ``j``). At most
``max_lines`` events of one kind are listed per ``summary_s`` seconds of data; the rest are
counted and reported in one line when that window closes, so a flood (a bridge sending garbage,
a network dropping every other message) costs a bounded number of lines. Windows run on the
samples' own time, not wall time: a replay at any speed gives the same log.

Other producers (the health monitor) log through the same :class:`Event` type.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from feedio import schema as S

__all__ = ["Event", "FlagDigest", "EVENT_LEVELS", "alarm_line"]

#: Rerun TextLog levels used, most severe first
EVENT_LEVELS = ("CRITICAL", "ERROR", "WARN", "INFO", "DEBUG")

_RUN_KINDS = {S.STALE: ("STALE", "INFO", "repeated measurement (recording glitch), not learned"),
              S.REJECTED: ("REJECTED", "WARN", "non-finite or absurd input, not learned")}


def alarm_line(a: S.AlarmEvent) -> str:
    """The event-log line of a process alarm (:class:`~feedio.schema.AlarmEvent`): kind, measured against
    limit, the σ it was judged with, NC line and tool, the monitor's detail."""
    where = "".join(f", {k} {v}" for k, v in (("line", a.program_line), ("tool", a.tool)) if v is not None)
    if a.kind == "wear":  # a rise across parts, relative (1 = 100 %)
        sigma = f", spread {a.sigma:.1%}" if a.sigma is not None else ""
        measured = f"rise {a.value:.1%} against limit {a.limit:.1%}{sigma}"
    else:
        sigma = f", σ {a.sigma:.2f} N" if a.sigma is not None else ""
        measured = f"{a.value:.1f} against limit {a.limit:.1f} N{sigma}"
    return f"ALARM {a.kind} at t = {a.t:.3f} s: {measured}{where} ({a.monitor}{'; ' + a.detail if a.detail else ''})"


@dataclass(frozen=True)
class Event:
    """One line of the event log: the sample it concerns (``seq``, ``t`` in s), level, text."""

    seq: int
    t: float
    level: str
    text: str


@dataclass
class _Limiter:
    """At most ``max_lines`` lines of one kind per window of ``span`` s of data; the rest counted."""

    span: float
    max_lines: int
    start: float | None = None
    listed: int = 0
    held: int = 0  # events not listed in this window
    held_samples: int = 0
    last: tuple[int, float] = (0, 0.0)

    def admit(self, t: float, samples: int, out: list[Event], kind: str) -> bool:
        self.roll(t, out, kind)
        if self.start is None:
            self.start = t
        if self.listed < self.max_lines:
            self.listed += 1
            return True
        self.held += 1
        self.held_samples += samples
        return False

    def note(self, seq: int, t: float) -> None:
        self.last = (seq, t)

    def roll(self, t: float | None, out: list[Event], kind: str) -> None:
        """Close the window if ``t`` is past its end (``None``: close it now)."""
        if self.start is None or (t is not None and t < self.start + self.span):
            return
        if self.held:
            seq, tl = self.last
            what = "" if self.held_samples == self.held else f" ({self.held_samples} samples)"
            out.append(Event(seq, tl, "WARN" if kind in ("GAP", "REJECTED") else "INFO",
                             f"{kind}: {self.held} more{what} in t = {self.start:.3f}–{tl:.3f} s, not listed"))
        self.start, self.listed, self.held, self.held_samples = None, 0, 0, 0


@dataclass
class _Run:
    first_seq: int
    first_t: float
    last_seq: int
    last_t: float
    count: int


@dataclass
class FlagDigest:
    """Events from the flag column of one axis, fed block by block (see the module docstring).

    Parameters
    ----------
    summary_s:
        seconds of data per REDUCED summary and per rate-limit window.
    max_lines:
        events of one kind listed per window; more are counted in one closing line.
    """

    summary_s: float = 10.0
    max_lines: int = 5
    _prev_seq: int | None = None
    _warm: bool = False
    _runs: dict[int, _Run | None] = field(default_factory=lambda: {bit: None for bit in _RUN_KINDS})
    _limits: dict[str, _Limiter] = field(default_factory=dict)
    _reduced_start: float | None = None
    _reduced_count: int = 0
    _reduced_n: int = 0
    _reduced_last: tuple[int, float] = (0, 0.0)

    def __post_init__(self) -> None:
        if not (self.summary_s > 0) or self.max_lines < 1:
            raise ValueError(f"summary_s must be > 0 and max_lines ≥ 1, got {self.summary_s}, {self.max_lines}")

    def _limit(self, kind: str) -> _Limiter:
        lim = self._limits.get(kind)
        if lim is None:
            lim = self._limits[kind] = _Limiter(self.summary_s, self.max_lines)
        return lim

    def _emit(self, out: list[Event], kind: str, ev: Event, samples: int = 1) -> None:
        lim = self._limit(kind)
        if lim.admit(ev.t, samples, out, kind):
            out.append(ev)
        lim.note(ev.seq, ev.t)

    # ---- runs (STALE, REJECTED) ---------------------------------------------------------
    def _close_run(self, bit: int, out: list[Event]) -> None:
        run = self._runs[bit]
        if run is None:
            return
        self._runs[bit] = None
        kind, level, why = _RUN_KINDS[bit]
        if run.count == 1:
            text = f"{kind}: sample {run.first_seq} (t = {run.first_t:.3f} s): {why}"
        else:
            text = (f"{kind}: {run.count} samples {run.first_seq}–{run.last_seq} "
                    f"(t = {run.first_t:.3f}–{run.last_t:.3f} s): {why}")
        self._emit(out, kind, Event(run.first_seq, run.first_t, level, text), run.count)

    def _runs_of(self, bit: int, seq: np.ndarray, t: np.ndarray, flags: np.ndarray, out: list[Event]) -> None:
        rows = np.flatnonzero(flags & bit)
        run = self._runs[bit]
        if rows.size == 0:
            self._close_run(bit, out)
            return
        # a run continues over consecutive rows (and consecutive sequence numbers)
        breaks = np.flatnonzero((np.diff(rows) != 1) | (np.diff(seq[rows]) != 1)) + 1
        starts = np.concatenate(([0], breaks))
        ends = np.concatenate((breaks, [rows.size]))
        for k, (a, b) in enumerate(zip(starts, ends)):
            i, j = rows[a], rows[b - 1]
            if k == 0 and run is not None and i == 0 and int(seq[0]) == run.last_seq + 1:
                run.last_seq, run.last_t, run.count = int(seq[j]), float(t[j]), run.count + (b - a)
            else:
                self._close_run(bit, out)
                self._runs[bit] = _Run(int(seq[i]), float(t[i]), int(seq[j]), float(t[j]), int(b - a))
            if j != len(seq) - 1:  # ended inside this block
                self._close_run(bit, out)
            run = self._runs[bit]

    # ---- feeding ------------------------------------------------------------------------------
    def feed(self, seq: np.ndarray, t: np.ndarray, flags: np.ndarray) -> list[Event]:
        """Events of the next estimate rows of this axis (``seq``, ``t`` in s, ``flags`` bitmask)."""
        out: list[Event] = []
        n = len(seq)
        if n == 0:
            return out
        seq = np.asarray(seq, dtype=np.int64)
        t = np.asarray(t, dtype=np.float64)
        flags = np.asarray(flags, dtype=np.int64)
        prev = np.concatenate(([-1 if self._prev_seq is None else self._prev_seq], seq[:-1]))
        for i in np.flatnonzero(flags & S.GAP):
            known = self._prev_seq is not None or i > 0
            missing = int(seq[i] - prev[i] - 1) if known else 0
            what = (f"{missing} sample{'s' if missing != 1 else ''} missing before it" if missing > 0
                    else "sequence restarted or time went backwards" if known else "samples missing before it")
            self._emit(out, "GAP", Event(int(seq[i]), float(t[i]), "WARN",
                                         f"GAP at sample {int(seq[i])} (t = {t[i]:.3f} s): {what}; "
                                         f"the tracker's regressor chain restarts"))
        for bit in _RUN_KINDS:
            self._runs_of(bit, seq, t, flags, out)
        warm = (flags & S.WARMUP) != 0
        before = np.concatenate(([self._warm], warm[:-1]))
        for i in np.flatnonzero(warm != before):
            if warm[i]:
                text = f"WARMUP from sample {int(seq[i])} (t = {t[i]:.3f} s): estimates not trusted yet"
            else:
                text = f"WARMUP ended at sample {int(seq[i])} (t = {t[i]:.3f} s): estimates trusted from here"
            self._emit(out, "WARMUP", Event(int(seq[i]), float(t[i]), "INFO", text))
        self._warm = bool(warm[-1])
        self._reduced(seq, t, (flags & S.REDUCED) != 0, out)
        for kind, lim in self._limits.items():
            lim.roll(float(t[-1]), out, kind)
        self._prev_seq = int(seq[-1])
        out.sort(key=lambda e: e.seq)
        return out

    def _reduced(self, seq: np.ndarray, t: np.ndarray, red: np.ndarray, out: list[Event]) -> None:
        """Count REDUCED rows per window of ``summary_s`` s of data; a window closes at the first
        row past its end (or before its start: time going backwards)."""
        i, n = 0, len(seq)
        while i < n:
            if self._reduced_start is None:
                self._reduced_start = float(t[i])
            start = self._reduced_start
            outside = np.flatnonzero((t[i:] >= start + self.summary_s) | (t[i:] < start))
            k = n if outside.size == 0 else i + int(outside[0])
            if k > i:
                self._reduced_count += int(red[i:k].sum())
                self._reduced_n += k - i
                self._reduced_last = (int(seq[k - 1]), float(t[k - 1]))
            if k < n:
                self._close_reduced(out)
            i = k

    def _close_reduced(self, out: list[Event]) -> None:
        if self._reduced_count:
            seq, tl = self._reduced_last
            share = 100.0 * self._reduced_count / max(1, self._reduced_n)
            out.append(Event(seq, tl, "DEBUG",
                             f"REDUCED: {self._reduced_count} of {self._reduced_n} samples ({share:.0f} %) in "
                             f"t = {self._reduced_start:.3f}–{tl:.3f} s: the dictionary was full and the newest "
                             f"element was pruned at once (it added little)"))
        self._reduced_start, self._reduced_count, self._reduced_n = None, 0, 0

    def close(self) -> list[Event]:
        """Events still open at the end (runs in progress, the last summaries)."""
        out: list[Event] = []
        for bit in _RUN_KINDS:
            self._close_run(bit, out)
        self._close_reduced(out)
        for kind, lim in self._limits.items():
            lim.roll(None, out, kind)
        out.sort(key=lambda e: e.seq)
        return out
