"""Health of an axis' input stream: what the per-sample counters of the compiled loop say about the
samples themselves, beside the model-validity and drift tests of :mod:`kernels.health`.

Three conditions, each judged on the samples of the axis (time = samples × the model's Ts, so live and
offline judge a stream alike, whatever its blocks):

* **frozen measurement** — the fraction of the last ``window`` seconds' samples counted ``stale``
  (the controller repeated ``v_meas`` while the axis moves: a dead encoder, a stuck bridge). Those
  samples teach the tracker nothing; at a standstill a frozen value would even teach it a wrong one.
* **another rate** — the fraction counted ``interval_mismatch`` (a sample more than 25 % early or late
  against the model's Ts: a stream at another rate, or a controller skipping cycles). β is a
  discrete-time model of one sampling time: what is learned from such a stream is wrong.
* **nothing learned** — seconds of samples in a row of which none was learned (all stale, rejected,
  or refused by the estimator).

Each gives ``ok``, ``warn`` or ``alarm`` against its thresholds (:class:`InputHealthSettings`), the
fractions once a tenth of the window has been seen; a level clears once its fraction is below half
the warn threshold (hysteresis). The verdict is the worst of
the three, with one reason line each. :class:`~monitor.pipeline.Pipeline` merges it into the axis'
health reports (the worse of the two states, these reasons first) and makes a report of its own
when the verdict changes between two of the loop's.

Samples learned while the verdict is ``warn`` or ``alarm`` are counted in :attr:`InputHealth.tainted`:
a tracker state learned from a stream the monitor itself flagged is not saved over a good one
(:meth:`monitor.daemon.Monitor.stop`).

Memory is fixed: the window is kept as ``BUCKETS`` sums, whatever the block size and rate.
"""

from __future__ import annotations

import math
from collections import deque

import msgspec
import numpy as np

from feedio.limits import bounded_float
from kernels import online
from kernels.health import LEVELS

__all__ = ["InputHealthSettings", "InputHealth", "LEVELS", "BUCKETS", "REPORT_PERIOD"]

#: the window is kept as this many partial sums (its resolution: window / BUCKETS)
BUCKETS = 10
#: s of samples between two reports the pipeline makes of its own while the verdict is not ok and the
#: estimator makes none (the estimator's default health period)
REPORT_PERIOD = 1.0
#: recent sample intervals kept for the median the reason quotes
_DT_KEEP = 64

_C = {name: online.COUNTERS.index(name) for name in ("stale", "interval_mismatch", "trained")}


class InputHealthSettings(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``[run.input_health]`` of ``feedmon run --config``: thresholds of the input-health verdict (module
    docstring). Fractions are of the samples in the window; seconds are of data (samples × Ts)."""

    window: bounded_float(0.5, 600.0, "s of samples over which the fractions are judged (delay vs noise)") = 5.0
    stale_warn: bounded_float(0.001, 1.0, "fraction of samples stale (v_meas repeated while moving) for warn") = 0.2
    stale_alarm: bounded_float(0.001, 1.0, "fraction of samples stale for alarm") = 0.8
    interval_warn: bounded_float(0.001, 1.0, "fraction of samples at another interval than Ts for warn") = 0.05
    interval_alarm: bounded_float(0.001, 1.0, "fraction of samples at another interval than Ts for alarm") = 0.5
    learn_warn: bounded_float(1.0, 86400.0, "s of samples in a row with none learned for warn") = 30.0
    learn_alarm: bounded_float(1.0, 86400.0, "s of samples in a row with none learned for alarm") = 120.0

    def __post_init__(self) -> None:
        for a, b in (("stale_warn", "stale_alarm"), ("interval_warn", "interval_alarm"), ("learn_warn", "learn_alarm")):
            if getattr(self, a) > getattr(self, b):
                raise ValueError(f"input_health.{a} = {getattr(self, a)!r} must not exceed input_health.{b} = "
                                 f"{getattr(self, b)!r}")


class InputHealth:
    """The input-health verdict of one axis, fed once per block (:meth:`block`). Not thread-safe: one
    estimating thread at a time, like the estimator."""

    def __init__(self, Ts: float, settings: InputHealthSettings | None = None) -> None:
        if not (math.isfinite(Ts) and Ts > 0):
            raise ValueError(f"Ts must be a positive number of seconds, got {Ts!r}")
        self.Ts = float(Ts)
        self.settings = settings or InputHealthSettings()
        self._bucket_n = max(1, int(round(self.settings.window / self.Ts / BUCKETS)))
        self._buckets: deque[np.ndarray] = deque(maxlen=BUCKETS)  # [samples, stale, interval] per full bucket
        self._cur = np.zeros(3, dtype=np.int64)
        self._quiet = 0  # samples in a row none of which was learned
        self._dts: deque[float] = deque(maxlen=_DT_KEEP)
        self._last: tuple[int, float] | None = None  # (seq, t) of the last sample seen
        self.levels = {"stale": 0, "interval": 0, "learn": 0}
        self.level = 0
        self.reasons: list[str] = []
        self.tainted = 0  # samples learned while the verdict was warn or alarm
        self.flagged = 0  # blocks judged while the verdict was warn or alarm

    # ---- feeding -----------------------------------------------------------------------------
    def block(self, counts: np.ndarray, n: int, seq0: int | None = None, t: list | np.ndarray | None = None) -> bool:
        """Take one block: ``counts`` its :data:`kernels.online.COUNTERS` (None: the estimator refused it
        whole, nothing learned), ``n`` its samples, ``seq0``/``t`` its first sequence number and times (for
        the interval the reason quotes). True when the verdict changed."""
        if n <= 0:
            return False
        stale = int(counts[_C["stale"]]) if counts is not None else 0
        interval = int(counts[_C["interval_mismatch"]]) if counts is not None else 0
        trained = int(counts[_C["trained"]]) if counts is not None else 0
        self._add(n, stale, interval)
        self._quiet = 0 if trained else self._quiet + n
        if t is not None and seq0 is not None:
            self._intervals(seq0, t)
        before = self.level
        self._judge()
        if self.level:
            self.tainted += trained
            self.flagged += 1
        return self.level != before

    def _add(self, n: int, stale: int, interval: int) -> None:
        """Add a block's counts to the window (split across buckets as its samples fill them)."""
        self._cur += (n, stale, interval)
        while self._cur[0] >= self._bucket_n:
            if self._cur[0] == self._bucket_n or not self._cur[0]:
                self._buckets.append(self._cur)
                self._cur = np.zeros(3, dtype=np.int64)
            else:  # a block longer than a bucket: shared out pro rata (a fraction is all that is judged)
                part = self._cur * self._bucket_n // self._cur[0]
                part[0] = self._bucket_n
                self._buckets.append(part)
                self._cur = self._cur - part

    def _intervals(self, seq0: int, t) -> None:
        """Keep the block's sample intervals (and the one from the previous block when it follows on)."""
        t = np.asarray(t, dtype=np.float64)
        if not t.size:
            return
        joined = t if self._last is None or seq0 != self._last[0] + 1 else np.concatenate(([self._last[1]], t))
        d = np.diff(joined)
        self._dts.extend(d[np.isfinite(d) & (d > 0)][-_DT_KEEP:].tolist())
        self._last = (int(seq0) + t.size - 1, float(t[-1]))

    # ---- the verdict -------------------------------------------------------------------------
    def _window(self) -> np.ndarray:
        tot = self._cur.copy()
        for b in self._buckets:
            tot += b
        return tot

    @staticmethod
    def _level(x: float, was: int, warn: float, alarm: float) -> int:
        """ok / warn / alarm of ``x``; a level clears below half the warn threshold (hysteresis)."""
        if x >= alarm:
            return 2
        if x >= warn:
            return 1
        return min(was, 1) if x >= warn / 2 else 0

    def _judge(self) -> None:
        s = self.settings
        n, stale, interval = (int(v) for v in self._window())
        lv = self.levels
        if n >= self._bucket_n:  # a fraction of a handful of samples says nothing: a tenth of the window at least
            lv["stale"] = self._level(stale / n, lv["stale"], s.stale_warn, s.stale_alarm)
            lv["interval"] = self._level(interval / n, lv["interval"], s.interval_warn, s.interval_alarm)
        quiet_s = self._quiet * self.Ts
        lv["learn"] = 2 if quiet_s >= s.learn_alarm else 1 if quiet_s >= s.learn_warn else 0
        self.level = max(lv.values())
        secs = n * self.Ts
        reasons = []
        if lv["stale"]:
            reasons.append(f"input: v_meas frozen while the axis moves — {stale} of {n} samples stale in the last "
                           f"{secs:.3g} s ({100 * stale / n:.0f} %): a dead encoder or a stuck bridge? Nothing is "
                           "learned from them")
        if lv["interval"]:
            med = float(np.median(self._dts)) if self._dts else math.nan
            reasons.append(f"input: {interval} of {n} samples in the last {secs:.3g} s ({100 * interval / n:.0f} %) at "
                           f"another interval than the model's Ts = {1e3 * self.Ts:.4g} ms (recent median "
                           f"{1e3 * med:.4g} ms): β is of one sampling rate — identify a model at the stream's rate; "
                           "the tracker state learned meanwhile is not saved")
        if lv["learn"]:
            reasons.append(f"input: nothing learned from the last {self._quiet} samples ({quiet_s:.3g} s): all "
                           "stale, rejected or refused — see the axis' counters")
        self.reasons = reasons

    @property
    def state(self) -> str:
        return LEVELS[self.level]

    def status(self) -> dict:
        """For the status document: state, reasons, levels per condition, tainted samples."""
        return {"state": self.state, "reasons": list(self.reasons), "levels": {k: LEVELS[v] for k, v in
                                                                               self.levels.items()},
                "tainted": self.tainted}
