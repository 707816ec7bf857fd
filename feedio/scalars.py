"""Per-sample scalars of the disturbance estimate, for tools other than feedmon.

The monitor's :class:`~feedio.schema.EstimateBlock` rows are columnar and, by
construction, one row late for the filtered values: row j's ``f``, ``f_var``,
``force``, ``force_var`` describe sample j−1 (docs/estimates.md, "What a value
describes, in time"). :class:`ScalarsPairer` turns the rows (and the truth blocks, when recorded)
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
``hold_samples`` samples of its axis wait, when :meth:`ScalarsPairer.expire` finds it older
than the hold time (live), or at :meth:`ScalarsPairer.drain` (end of file). Memory is bounded
by ``hold_samples`` samples and ``4 × hold_samples`` truth values per axis.

Fast path
---------
The per-sample channel is the largest one of a log (one message per sample), so nothing here
works per sample in Python. The pairer keeps each axis' waiting samples as columns (NumPy)
and releases them as a :class:`ScalarsBatch` (columns of one axis, in sample order).
:meth:`ScalarsBatch.records` builds the MCAP message records of a batch — header and JSON —
in one compiled pass (:func:`_build_records`) from the columns as ``msgspec`` formats them
(one ``encode`` of all columns, so every number is written exactly as
``feedio.schema.encode(DisturbanceScalars(...))`` writes it; a missing value is JSON
``null`` there and is left out of the message). :meth:`ScalarsBatch.messages` gives the same
messages as :class:`~feedio.schema.DisturbanceScalars` objects (the reference the tests
compare the records with, byte for byte), and ``tests/scalars_reference.py`` keeps the first,
per-sample implementation of the pairing, which the tests compare this one with message for
message.
"""

from __future__ import annotations

from dataclasses import dataclass

import msgspec
import numpy as np
from numba import njit

from . import schema as S
from .mcapwriter import MESSAGE_HEADER

__all__ = ["ScalarsPairer", "ScalarsBatch", "HOLD_SAMPLES", "HOLD_NS", "FIELDS", "VALUES"]

#: most samples of one axis waiting for their next row / truth (bounds memory; at 333 Hz ≈ 12 s)
HOLD_SAMPLES = 4096
#: wall-clock time a sample waits for its next row / truth before it is written without them (live)
HOLD_NS = 2 * 10**9
#: controller-time span of one block beyond which sample stamps are not offset further (s)
_MAX_SPAN_S = 3600.0
#: largest log time a stamp may take (int64 ns, what MCAP tools hold)
_MAX_NS = 2**63 - 1

#: the fields of a scalars message, in the order of :class:`~feedio.schema.DisturbanceScalars`
FIELDS = tuple(S.DisturbanceScalars.__struct_fields__)
#: the optional (float) fields, left out of a message when missing: the rows of :attr:`ScalarsBatch.values`
VALUES = FIELDS[3:]
assert FIELDS[:3] == ("t", "seq", "flags") and VALUES == (
    "v_meas", "f", "f_sd", "f_next", "force", "force_sd", "force_next", "truth_force", "truth_f", "dynamometer")

_I_SEQ, _I_FLAGS = 0, 2  # rows of _Axis.ints (seq, log, flags)
_F_T = 0  # row of _Axis.floats


def _column(values, n: int) -> np.ndarray:
    """A block column as float64, NaN where missing or non-finite."""
    if values is None:
        return np.full(n, np.nan)
    a = np.array(values, dtype=np.float64)  # None -> NaN
    a[~np.isfinite(a)] = np.nan
    return a


# ---- the batch and its records -------------------------------------------------------------------
_KEYS = [(b"{" if i == 0 else b",") + b'"' + name.encode() + b'":' for i, name in enumerate(FIELDS)]
_KEY_BYTES = np.frombuffer(b"".join(_KEYS), dtype=np.uint8)
_KEY_OFFSETS = np.cumsum([0] + [len(k) for k in _KEYS]).astype(np.int64)
_encoder = msgspec.json.Encoder()


@dataclass
class ScalarsBatch:
    """Scalars messages of one axis, in sample order, as columns: ``log_ns`` (their log times,
    ns since the epoch, increasing), ``seq``, ``t`` (s), ``flags`` and ``values`` (rows
    :data:`VALUES`, NaN = missing: left out of the message)."""

    machine: str
    axis: str
    log_ns: np.ndarray
    seq: np.ndarray
    t: np.ndarray
    flags: np.ndarray
    values: np.ndarray

    def __len__(self) -> int:
        return int(self.seq.size)

    def messages(self) -> list[S.DisturbanceScalars]:
        """The messages as :class:`~feedio.schema.DisturbanceScalars` (missing values left out)."""
        out = []
        vals = self.values.T.tolist()
        for t, seq, flags, row in zip(self.t.tolist(), self.seq.tolist(), self.flags.tolist(), vals):
            out.append(S.DisturbanceScalars(t=t, seq=seq, flags=flags,
                                            **{k: v for k, v in zip(VALUES, row) if v == v}))
        return out

    def records(self, channel_id: int) -> tuple[np.ndarray, np.ndarray]:
        """The MCAP message records of the batch on channel ``channel_id`` back to back (uint8:
        31-byte header — sequence ``seq mod 2³²``, log and publish time ``log_ns`` — then the JSON
        of :class:`~feedio.schema.DisturbanceScalars`), and the size of each record."""
        n = len(self)
        text = _encoder.encode([self.t.tolist(), self.seq.tolist(), self.flags.tolist(), *self.values.tolist()])
        buf = np.frombuffer(text, dtype=np.uint8)
        sizes = np.empty(n, dtype=np.int64)
        out = _build_records(buf, len(FIELDS), n, _KEY_BYTES, _KEY_OFFSETS, channel_id,
                             np.ascontiguousarray(self.seq, dtype=np.int64),
                             np.ascontiguousarray(self.log_ns, dtype=np.int64), sizes)
        return out, sizes


@njit(cache=True, nogil=True)
def _put_le(out, pos, value, nbytes):
    for k in range(nbytes):
        out[pos + k] = (value >> (8 * k)) & 0xFF


@njit(cache=True, nogil=True)
def _build_records(text, n_fields, n, keys, key_offsets, channel_id, seq, log_ns, sizes):
    """Assemble message records from ``text`` = ``msgspec`` JSON of ``n_fields`` lists of ``n``
    numbers each (``[[…],[…],…]``: numbers and ``null``, no strings, so ``,`` and ``]`` only
    separate tokens). Message i is ``{"t":…,"seq":…,"flags":…`` followed by ``,"name":value``
    for every later field whose token is not ``null``, then ``}``; each is
    preceded by the 31 bytes of an MCAP message record (opcode 5, record length, channel id,
    sequence = seq mod 2³², log time, publish time = log time). ``sizes`` receives the record
    sizes; returns the records back to back."""
    start = np.empty((n_fields, n), dtype=np.int64)
    stop = np.empty((n_fields, n), dtype=np.int64)
    pos = 1                                    # after the outer '['
    for f in range(n_fields):
        pos += 1                               # '['
        for i in range(n):
            start[f, i] = pos
            while text[pos] != 44 and text[pos] != 93:   # ',' ']'
                pos += 1
            stop[f, i] = pos
            pos += 1                           # the ',' or ']' after it
        pos += 1                               # ',' between the lists (or the final ']')
    hsize = MESSAGE_HEADER
    total = 0
    for i in range(n):
        size = hsize + 1                       # the closing '}'
        for f in range(n_fields):
            length = stop[f, i] - start[f, i]
            if f >= 3 and length == 4 and text[start[f, i]] == 110:   # "null": left out
                continue
            size += key_offsets[f + 1] - key_offsets[f] + length
        sizes[i] = size
        total += size
    out = np.empty(total, dtype=np.uint8)
    p = 0
    for i in range(n):
        out[p] = 5
        # widths as np.int64, not literals: one compiled _put_le, not one per width
        _put_le(out, p + 1, sizes[i] - 9, np.int64(8))    # record length: after opcode and length
        _put_le(out, p + 9, channel_id, np.int64(2))
        _put_le(out, p + 11, seq[i] & 0xFFFFFFFF, np.int64(4))
        _put_le(out, p + 15, log_ns[i], np.int64(8))
        _put_le(out, p + 23, log_ns[i], np.int64(8))
        p += MESSAGE_HEADER
        for f in range(n_fields):
            a, b = start[f, i], stop[f, i]
            if f >= 3 and b - a == 4 and text[a] == 110:
                continue
            for k in range(key_offsets[f], key_offsets[f + 1]):
                out[p] = keys[k]
                p += 1
            for k in range(a, b):
                out[p] = text[k]
                p += 1
        out[p] = 125                           # '}'
        p += 1
    return out


assert MESSAGE_HEADER == 31  # the record layout written by _build_records


# ---- the pairer ---------------------------------------------------------------------------------
# waiting samples of an axis, oldest at ``head``: ``ints`` rows (seq, log, flags), ``floats`` rows
# (t, v_meas, f_next, force_next, then the filtered values of the next row f, f_sd, force, force_sd;
# NaN: none), ``done`` (the next row came)
_N_INTS, _N_FLOATS = 3, 8


class _Axis:
    __slots__ = ("ints", "floats", "done", "head", "tail", "truth_seq", "truth_vals", "truth_end", "last_ns",
                 "released")

    def __init__(self, capacity: int = 256) -> None:
        self.ints = np.empty((_N_INTS, capacity), dtype=np.int64)
        self.floats = np.empty((_N_FLOATS, capacity))
        self.done = np.empty(capacity, dtype=np.bool_)
        self.head = self.tail = 0
        self.truth_seq = np.empty(0, dtype=np.int64)  # sorted, unique
        self.truth_vals = np.empty((3, 0))  # force, f, dynamometer
        self.truth_end: int | None = None  # highest truth seq seen + 1 (None: no truth yet)
        self.last_ns = -1
        self.released: int | None = None  # seq of the last sample written

    @property
    def pending(self) -> int:
        return self.tail - self.head

    def room(self, n: int) -> None:
        """Make room for ``n`` more samples after ``tail`` (moves the waiting ones to the front, grows)."""
        cap = self.done.size
        if self.tail + n <= cap:
            return
        k = self.pending
        if k + n > cap // 2:
            cap = max(2 * cap, 2 * (k + n))
            ints, floats, done = (np.empty((_N_INTS, cap), dtype=np.int64), np.empty((_N_FLOATS, cap)),
                                  np.empty(cap, dtype=np.bool_))
        else:
            ints, floats, done = self.ints, self.floats, self.done
        ints[:, :k] = self.ints[:, self.head:self.tail]
        floats[:, :k] = self.floats[:, self.head:self.tail]
        done[:k] = self.done[self.head:self.tail]
        self.ints, self.floats, self.done = ints, floats, done
        self.head, self.tail = 0, k


class ScalarsPairer:
    """Pairs estimate rows (and truth) into per-sample :class:`DisturbanceScalars`.

    Every method returns the messages that became complete, as a list of :class:`ScalarsBatch`
    (at most one per axis, in sample order). ``expect_truth``: False when no truth will come
    (messages go out as soon as the next row is there), True to wait for it, None to wait for
    it until the hold expires unless the axis' truth has already passed that sample, or the set
    of ``(machine, axis)`` that have truth (True for those, False for the others).
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
    def add_estimates(self, block: S.EstimateBlock, last_ns: int) -> list[ScalarsBatch]:
        """Add the rows of ``block``; ``last_ns`` is the log time of its last sample (ns)."""
        n = len(block.t)
        return self.add_rows(
            block.machine, block.axis, block.seq, np.array(block.t, dtype=np.float64), last_ns,
            v_meas=_column(block.v_meas, n), f=_column(block.f, n), f_var=_column(block.f_var, n),
            f_next=_column(block.f_next, n), force=_column(block.force, n), force_var=_column(block.force_var, n),
            force_next=_column(block.force_next, n), flags=np.array(block.flags, dtype=np.int64))

    def add_rows(self, machine: str, axis: str, seq0: int, t: np.ndarray, last_ns: int, *, v_meas, f, f_var, f_next,
                 force=None, force_var=None, force_next=None, flags) -> list[ScalarsBatch]:
        """:meth:`add_estimates` for rows given as float64 columns (any value that is not finite, and a
        negative variance, counts as missing; ``force*`` None: the model has no force scale) and
        ``flags`` (int64); ``t`` (s) of the ``n`` rows, the first with sequence number ``seq0``;
        ``last_ns`` the log time of the last row (0 … 2⁶³ − 1 ns)."""
        n = int(t.size)
        if n == 0:
            return []
        last_ns = int(last_ns)
        if not 0 <= last_ns <= _MAX_NS:
            raise ValueError(f"scalars of {machine}/{axis}: log time {last_ns} ns is outside 0…2**63−1")
        st = self._axis(machine, axis)
        span = t[-1] - t
        span[~(np.isfinite(span) & (span > 0.0))] = 0.0
        log_ns = last_ns - np.round(np.minimum(span, _MAX_SPAN_S) * 1e9).astype(np.int64)
        if force is None:
            force = force_var = force_next = _NO_FORCE if n <= _NO_FORCE.size else np.full(n, np.nan)
        st.room(n)
        _append(st.ints, st.floats, st.done, st.head, st.tail, int(seq0), t, log_ns, v_meas, f, f_var, f_next,
                force, force_var, force_next, flags)
        st.tail += n
        return self._ready(machine, axis, st)

    def add_truth(self, machine: str, axis: str, block: S.TruthBlock) -> list[ScalarsBatch]:
        """Add a truth block of ``machine/axis`` (samples ``seq … seq+len−1``)."""
        st = self._axis(machine, axis)
        n = len(block.t)
        vals = np.stack((_column(block.force, n), _column(block.f, n), _column(block.dynamometer, n)))
        seq = block.seq + np.arange(n, dtype=np.int64)
        floor = int(st.ints[_I_SEQ, st.head]) if st.pending else (None if st.released is None else st.released + 1)
        if floor is not None and seq[0] < floor:
            keep = seq >= floor
            seq, vals = seq[keep], vals[:, keep]
        if seq.size:
            if not st.truth_seq.size or seq[0] > st.truth_seq[-1]:
                st.truth_seq = np.concatenate((st.truth_seq, seq))
                st.truth_vals = np.concatenate((st.truth_vals, vals), axis=1)
            else:  # overlapping: merge, a newer value replaces an older one of the same seq
                all_seq = np.concatenate((st.truth_seq, seq))
                order = np.argsort(all_seq, kind="stable")
                s = all_seq[order]
                last = np.ones(s.size, dtype=bool)
                last[:-1] = s[1:] != s[:-1]
                st.truth_seq = s[last]
                st.truth_vals = np.concatenate((st.truth_vals, vals), axis=1)[:, order[last]]
        end = block.seq + n
        st.truth_end = end if st.truth_end is None else max(st.truth_end, end)
        cap = 4 * self.hold_samples
        if st.truth_seq.size > cap:  # keep the newest (the oldest can no longer be paired)
            st.truth_seq = st.truth_seq[-cap:]
            st.truth_vals = st.truth_vals[:, -cap:]
        return self._ready(machine, axis, st)

    # -- output ---------------------------------------------------------------------------------
    def expire(self, older_than_ns: int) -> list[ScalarsBatch]:
        """Release every waiting sample stamped before ``older_than_ns`` (live: now − hold)."""
        out = []
        for (machine, axis), st in self._axes.items():
            out += self._ready(machine, axis, st, before_ns=older_than_ns)
        return out

    def drain(self) -> list[ScalarsBatch]:
        """Release everything (end of the recording)."""
        out = []
        for (machine, axis), st in self._axes.items():
            out += self._ready(machine, axis, st, force=True)
        return out

    def _expects(self, key: tuple[str, str]) -> bool:
        expect = self.expect_truth
        if isinstance(expect, (set, frozenset)):
            return key in expect
        return expect is not False

    def _ready(self, machine: str, axis: str, st: _Axis, *, force: bool = False,
               before_ns: int | None = None) -> list[ScalarsBatch]:
        L = st.pending
        if L == 0:
            return []
        truth_end = -1 if st.truth_end is None else st.truth_end
        before = 0 if before_ns is None else min(max(int(before_ns), -_MAX_NS), _MAX_NS)
        pos = np.empty(L, dtype=np.int64)
        ns = np.empty(L, dtype=np.int64)
        vals = np.empty((len(VALUES), L))
        # C order whatever slicing made truth_vals: one compiled _release, not one per layout
        r = _release(st.ints, st.floats, st.done, st.head, st.tail, st.truth_seq, np.ascontiguousarray(st.truth_vals),
                     truth_end, self._expects((machine, axis)), self.hold_samples, before_ns is not None, before, force,
                     st.last_ns, pos, ns, vals)
        if r == 0:
            return []
        if r < 0:
            raise ValueError(f"scalars of {machine}/{axis}: log times beyond 2**63−1 ns")
        used = pos[:r]
        used = used[used >= 0]
        if used.size:  # the truth of these samples: paired, and gone from the table (a dict pop)
            keep = np.ones(st.truth_seq.size, dtype=bool)
            keep[used] = False
            st.truth_seq, st.truth_vals = st.truth_seq[keep], st.truth_vals[:, keep]
        h = st.head
        st.last_ns = int(ns[r - 1])
        st.released = int(st.ints[_I_SEQ, h + r - 1])
        batch = ScalarsBatch(machine, axis, ns[:r], st.ints[_I_SEQ, h:h + r].copy(), st.floats[_F_T, h:h + r].copy(),
                             st.ints[_I_FLAGS, h:h + r].copy(), vals[:, :r])
        st.head += r
        if st.head == st.tail:
            st.head = st.tail = 0
        return [batch]


_NO_FORCE = np.full(4096, np.nan)
_NO_FORCE.setflags(write=False)


@njit(cache=True, nogil=True)
def _value(x):
    return x if np.isfinite(x) else np.nan


@njit(cache=True, nogil=True)
def _sd(var):
    return np.sqrt(var) if np.isfinite(var) and var >= 0.0 else np.nan


@njit(cache=True, nogil=True)
def _append(ints, floats, done, head, tail, seq0, t, log_ns, v_meas, f, f_var, f_next, force, force_var, force_next,
            flags):
    """Append the ``n`` rows at ``tail`` (room made): row i is sample seq0 + i; it waits for row i+1, whose
    filtered values (f, sd of f_var, force, sd of force_var) describe it — within the block always, and
    for the sample waiting before the block when its seq is seq0 − 1 (else a gap: nothing to pair)."""
    n = t.shape[0]
    if tail > head and not done[tail - 1]:
        done[tail - 1] = True
        if ints[0, tail - 1] == seq0 - 1:
            floats[4, tail - 1] = _value(f[0])
            floats[5, tail - 1] = _sd(f_var[0])
            floats[6, tail - 1] = _value(force[0])
            floats[7, tail - 1] = _sd(force_var[0])
    for i in range(n):
        k = tail + i
        ints[0, k] = seq0 + i
        ints[1, k] = log_ns[i]
        ints[2, k] = flags[i]
        floats[0, k] = t[i]
        floats[1, k] = _value(v_meas[i])
        floats[2, k] = _value(f_next[i])
        floats[3, k] = _value(force_next[i])
        if i + 1 < n:
            floats[4, k] = _value(f[i + 1])
            floats[5, k] = _sd(f_var[i + 1])
            floats[6, k] = _value(force[i + 1])
            floats[7, k] = _sd(force_var[i + 1])
            done[k] = True
        else:
            floats[4, k] = np.nan
            floats[5, k] = np.nan
            floats[6, k] = np.nan
            floats[7, k] = np.nan
            done[k] = False


@njit(cache=True, nogil=True)
def _release(ints, floats, done, head, tail, truth_seq, truth_vals, truth_end, expects, hold, has_before, before,
             force, last_ns, pos, ns, vals):
    """How many waiting samples go out now (a prefix), walking them in order as the per-sample rule
    says: sample j waits (and so do all after it) unless ``force``, or more than ``hold`` samples wait
    from j on, or it was stamped before ``before`` (when ``has_before``), or it has its next row
    (``done``) and does not wait for truth — it waits when truth is expected, none is there for its
    ``seq`` (a truth value goes to the first sample of that seq only) and the truth seen so far does
    not reach past it (``truth_end`` < 0: none seen). Fills, per released sample, ``pos`` (its truth
    position, −1: none), ``ns`` (stamps: max(log, previous + 1, 0), the previous starting at
    ``last_ns``) and ``vals`` (rows :data:`VALUES`); returns the count, or −1 when a stamp would pass
    2⁶³ − 1."""
    L = tail - head
    T = truth_seq.shape[0]
    used = np.zeros(T, dtype=np.bool_)
    prev = last_ns
    for j in range(L):
        k = head + j
        s = ints[0, k]
        p = np.searchsorted(truth_seq, s)
        hit = p < T and truth_seq[p] == s and not used[p]
        if not force and L - j <= hold and (not has_before or ints[1, k] >= before):
            if not done[k] or (expects and not hit and (truth_end < 0 or s >= truth_end)):
                return j
        if prev == 9223372036854775807:
            return -1
        stamp = max(ints[1, k], prev + 1, 0)
        ns[j] = stamp
        prev = stamp
        vals[0, j] = floats[1, k]   # v_meas
        vals[1, j] = floats[4, k]   # f
        vals[2, j] = floats[5, k]   # f_sd
        vals[3, j] = floats[2, k]   # f_next
        vals[4, j] = floats[6, k]   # force
        vals[5, j] = floats[7, k]   # force_sd
        vals[6, j] = floats[3, k]   # force_next
        if hit:
            used[p] = True
            pos[j] = p
            vals[7, j] = truth_vals[0, p]
            vals[8, j] = truth_vals[1, p]
            vals[9, j] = truth_vals[2, p]
        else:
            pos[j] = -1
            vals[7, j] = np.nan
            vals[8, j] = np.nan
            vals[9, j] = np.nan
    return L


def warm_up() -> None:
    """Load the compiled pairing and record code now (from Numba's cache, or compile it): a logging process
    about to drop to a low priority would otherwise pay for it — seconds of CPU — on its first estimate
    block, on a busy host long enough to be taken for stalled."""
    pairer = ScalarsPairer(expect_truth=False)
    z, t = np.zeros(2), np.array([0.0, 1e-3])
    batches = pairer.add_rows("warm", "up", 0, t, 1, v_meas=z, f=z, f_var=z, f_next=z, force=z, force_var=z,
                              force_next=z, flags=np.zeros(2, np.int64)) + pairer.drain()
    for batch in batches:
        batch.records(1)
