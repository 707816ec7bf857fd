"""Reference model of :mod:`feedio.scalars` for the tests: the per-sample pairing as it was written
first (one Python record per sample), kept unchanged so that ``test_scalars.py`` can check the
columnar :class:`feedio.scalars.ScalarsPairer` against it message for message.

Per-sample scalars of the disturbance estimate, for tools other than feedmon.

The monitor's :class:`~feedio.schema.EstimateBlock` rows are columnar and, by
construction, one row late for the filtered values: row j's ``f``, ``f_var``,
``force``, ``force_var`` describe sample j−1 (docs/estimates.md; docs/mcap.md, "The scalars
channel"). :class:`ScalarsPairer` turns the rows (and the truth blocks, when recorded)
into one :class:`~feedio.schema.DisturbanceScalars` per sample k, combining

* row k: ``t``, ``seq``, ``v_meas``, ``flags``, ``f_next``, ``force_next`` (the
  prediction for sample k, made when it arrived);
* row k+1: ``f``, ``f_sd``, ``force``, ``force_sd`` (the filtered disturbance of sample k);
* truth k: ``truth_force``, ``truth_f``, ``dynamometer``;

and stamps it with the wall-clock time of sample k: the log time of its block (the time of
the block's last sample) minus the controller-time difference to that last sample. Per axis
the stamps never decrease (a sample that would be stamped at or before the previous one
gets the previous stamp + 1 ns), so plots are time series.

A sample waits for row k+1 and, when truth is expected, for its truth; it goes out
without them when the next row has another ``seq`` (a gap), when more than
``hold_samples`` samples of its axis wait, when :meth:`expire` finds it older than the
hold time (live), or at :meth:`drain` (end of file). Memory is bounded by
``hold_samples`` samples and ``4 × hold_samples`` truth values per axis.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from feedio import schema as S

__all__ = ["ScalarsPairer"]

#: most samples of one axis waiting for their next row / truth (bounds memory; at 333 Hz ≈ 12 s)
HOLD_SAMPLES = 4096
#: wall-clock time a sample waits for its next row / truth before it is written without them (live)
HOLD_NS = 2 * 10**9
#: controller-time span of one block beyond which sample stamps are not offset further (s)
_MAX_SPAN_S = 3600.0


def _column(values, n: int, sqrt: bool = False) -> list[float]:
    """A block column as Python floats, NaN where missing or non-finite (``sqrt``: a variance → a
    standard deviation, NaN where negative)."""
    if values is None:
        return [math.nan] * n
    a = np.array(values, dtype=np.float64)  # None -> NaN
    if sqrt:
        with np.errstate(invalid="ignore"):
            a = np.sqrt(a)
    a[~np.isfinite(a)] = np.nan
    return a.tolist()


# per-sample record of the queue: [seq, t, log_ns, v_meas, f_next, force_next, flags, filtered, done]
# filtered = (f, f_sd, force, force_sd) of row k+1, or None
_SEQ, _T, _LOG, _VMEAS, _FNEXT, _FORCENEXT, _FLAGS, _FILT, _DONE = range(9)
_FILTERED = ("f", "f_sd", "force", "force_sd")
_TRUTH = ("truth_force", "truth_f", "dynamometer")


@dataclass
class _Axis:
    pending: deque = field(default_factory=deque)
    truth: dict = field(default_factory=dict)  # seq -> (force, f, dynamometer)
    truth_end: int | None = None  # highest truth seq seen + 1 (None: no truth yet)
    last_ns: int = -1
    released: int | None = None  # seq of the last sample written


class ScalarsPairer:
    """Pairs estimate rows (and truth) into per-sample :class:`DisturbanceScalars`.

    Every method returns the messages that became complete, as
    ``(machine, axis, log_time_ns, DisturbanceScalars)`` in sample order per axis.
    ``expect_truth``: False when no truth will come (messages go out as soon as the next
    row is there), True to wait for it, None to wait for it until the hold expires unless
    the axis' truth has already passed that sample, or the set of ``(machine, axis)`` that
    have truth (True for those, False for the others).
    """

    def __init__(self, *, hold_samples: int = HOLD_SAMPLES, expect_truth=None):
        if hold_samples < 1:
            raise ValueError(f"hold_samples must be ≥ 1, got {hold_samples}")
        self.hold_samples = int(hold_samples)
        self.expect_truth = expect_truth
        self._axes: dict[tuple[str, str], _Axis] = {}

    def _axis(self, machine: str, axis: str) -> _Axis:
        st = self._axes.get((machine, axis))
        if st is None:
            st = self._axes[(machine, axis)] = _Axis()
        return st

    # -- input ----------------------------------------------------------------------------------
    def add_estimates(self, block: S.EstimateBlock, last_ns: int) -> list:
        """Add the rows of ``block``; ``last_ns`` is the log time of its last sample (ns)."""
        st = self._axis(block.machine, block.axis)
        n = len(block.t)
        t = np.array(block.t, dtype=np.float64)
        span = t[-1] - t
        span[~(np.isfinite(span) & (span > 0.0))] = 0.0
        log_ns = (int(last_ns) - np.round(np.minimum(span, _MAX_SPAN_S) * 1e9).astype(np.int64)).tolist()
        f, f_sd = _column(block.f, n), _column(block.f_var, n, sqrt=True)
        force, force_sd = _column(block.force, n), _column(block.force_var, n, sqrt=True)
        v_meas, f_next, force_next = _column(block.v_meas, n), _column(block.f_next, n), _column(block.force_next, n)
        q = st.pending
        seq0 = block.seq
        for i in range(n):
            seq = seq0 + i
            if q:
                tail = q[-1]
                if not tail[_DONE]:
                    tail[_DONE] = True
                    if tail[_SEQ] == seq - 1:  # otherwise a gap: the values describe a sample never seen
                        tail[_FILT] = (f[i], f_sd[i], force[i], force_sd[i])
            q.append([seq, block.t[i], log_ns[i], v_meas[i], f_next[i], force_next[i], int(block.flags[i]), None,
                      False])
        return self._ready(block.machine, block.axis, st)

    def add_truth(self, machine: str, axis: str, block: S.TruthBlock) -> list:
        """Add a truth block of ``machine/axis`` (samples ``seq … seq+len−1``)."""
        st = self._axis(machine, axis)
        n = len(block.t)
        force, f, dyn = _column(block.force, n), _column(block.f, n), _column(block.dynamometer, n)
        floor = st.pending[0][_SEQ] if st.pending else (None if st.released is None else st.released + 1)
        for i in range(n):
            seq = block.seq + i
            if floor is not None and seq < floor:
                continue
            st.truth[seq] = (force[i], f[i], dyn[i])
        end = block.seq + n
        st.truth_end = end if st.truth_end is None else max(st.truth_end, end)
        cap = 4 * self.hold_samples
        if len(st.truth) > cap:
            for seq in sorted(st.truth)[: len(st.truth) - cap]:
                del st.truth[seq]
        return self._ready(machine, axis, st)

    # -- output ---------------------------------------------------------------------------------
    def expire(self, older_than_ns: int) -> list:
        """Release every waiting sample stamped before ``older_than_ns`` (live: now − hold)."""
        out = []
        for (machine, axis), st in self._axes.items():
            out += self._ready(machine, axis, st, before_ns=older_than_ns)
        return out

    def drain(self) -> list:
        """Release everything (end of the recording)."""
        out = []
        for (machine, axis), st in self._axes.items():
            out += self._ready(machine, axis, st, force=True)
        return out

    def _waiting_for_truth(self, key: tuple[str, str], st: _Axis, seq: int) -> bool:
        expect = self.expect_truth
        if isinstance(expect, (set, frozenset)):
            expect = key in expect
        if expect is False or seq in st.truth:
            return False
        return st.truth_end is None or seq >= st.truth_end

    def _ready(self, machine: str, axis: str, st: _Axis, *, force: bool = False, before_ns: int | None = None) -> list:
        out = []
        q = st.pending
        while q:
            p = q[0]
            if not force and len(q) <= self.hold_samples and (before_ns is None or p[_LOG] >= before_ns):
                if not p[_DONE] or self._waiting_for_truth((machine, axis), st, p[_SEQ]):
                    break
            q.popleft()
            st.released = p[_SEQ]
            ns = max(p[_LOG], st.last_ns + 1, 0)
            st.last_ns = ns
            out.append((machine, axis, ns, self._message(st, p)))
        return out

    @staticmethod
    def _message(st: _Axis, p: list) -> S.DisturbanceScalars:
        vals = {}
        for name, v in (("v_meas", p[_VMEAS]), ("f_next", p[_FNEXT]), ("force_next", p[_FORCENEXT])):
            if v == v:  # not NaN
                vals[name] = v
        if p[_FILT] is not None:
            for name, v in zip(_FILTERED, p[_FILT]):
                if v == v:
                    vals[name] = v
        truth = st.truth.pop(p[_SEQ], None)
        if truth is not None:
            for name, v in zip(_TRUTH, truth):
                if v == v:
                    vals[name] = v
        return S.DisturbanceScalars(t=p[_T], seq=p[_SEQ], flags=p[_FLAGS], **vals)
