"""Sampler rows → runs of consecutive samples with feedmon's columns (SI units), ready to publish.

Sequence numbers and time
-------------------------
``seq`` is the configured counter column (a servo-cycle counter such as ``threadtest.0.count``),
unwrapped: HAL counters are 32 bits (u32 wraps after 2³² cycles, 49.7 days at 1 kHz; an s32 is read
modulo 2³²), so each row's step is taken modulo 2³². A step of 1 is the next sample; a step of
2 … 2³¹ means cycles the sampler did not deliver — FIFO overruns (the FIFO was full: the bridge read
too late) or a disabled sampler — and starts a new run: the monitor sees a gap of exactly those
samples. The FIFO's own sample number cannot serve: it counts only the samples written, so an
overrun leaves no trace in it. A step beyond 2³¹ is the counter going back: HAL restarted, a new
session.

``t = (seq + k₀)·Ts`` (s): servo-cycle time, with the offset ``k₀`` (whole cycles) fixed once per
session so that the newest sample's time is the host's CLOCK_MONOTONIC when it was read. Time
therefore never goes back, across restarts of LinuxCNC or of the bridge, and the monitor tells a new
session (the counter starts again, the clock goes on) from a gap (both jump together).

Columns
-------
Velocities and positions are scaled by ``length_scale`` (m per machine unit), ``u`` by
``force_scale``, ``current`` by ``current_scale``; ``v_meas`` from a position is the backward
difference ``(x(k) − x(k−1))/Ts`` (HAL's ``ddt``): the first sample of a run (after a gap or at a
session's start) has none, so it is not sent — it only gives the next sample its velocity (counted
in :attr:`Mapper.held`; the monitor sees a gap one sample longer);
``spindle_angle = 2π·revs`` (rad); ``spindle_rpm`` from rpm or rps. A non-finite value becomes
null (the monitor rejects that sample) and is counted per pin in :attr:`Mapper.nonfinite`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .config import BridgeConfig

__all__ = ["Run", "Mapper", "WRAP"]

WRAP = 1 << 32
_HALF = 1 << 31


@dataclass
class Run:
    """Consecutive samples (``seq0``, ``seq0 + 1``, …): ``t`` (s) and the columns, keyed
    ``"<axis>.<field>"`` (float64 in SI units, NaN = null) and ``program_line`` / ``tool`` (int64)."""

    seq0: int
    t: np.ndarray
    cols: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t.size)

    @property
    def end(self) -> int:
        """The sequence number after the last sample."""
        return self.seq0 + len(self)

    def cut(self, i: int, j: int) -> Run:
        return Run(self.seq0 + i, self.t[i:j], {k: v[i:j] for k, v in self.cols.items()})

    def join(self, other: Run) -> Run:
        return Run(self.seq0, np.concatenate((self.t, other.t)),
                   {k: np.concatenate((v, other.cols[k])) for k, v in self.cols.items()})


class Mapper:
    """Maps the rows of one sampler (see the module docstring); one per bridge, across HAL sessions."""

    def __init__(self, cfg: BridgeConfig) -> None:
        self.cfg = cfg
        self.Ts = float(cfg.servo_period)
        self._counter = cfg.column(cfg.counter)
        keys, cols, scales = [], [], []  # the float columns: "<axis>.<field>", sampler column, scale to SI
        self._positions: list[str] = []  # axes whose v_meas is the difference of their position
        for axis, ax in cfg.axes.items():
            si = {"v_ref": ax.length_scale, "v_meas": ax.length_scale, "position": ax.length_scale,
                  "u": ax.force_scale, "current": ax.current_scale, "spindle_revs": 2.0 * math.pi,
                  "spindle_speed": 60.0 if ax.spindle_speed_unit == "rps" else 1.0}
            for f, col in ax.pins().items():
                keys.append(f"{axis}.{f}")
                cols.append(cfg.column(col))
                scales.append(si[f])
            if ax.v_meas is None:
                self._positions.append(axis)
        self._keys, self._cols, self._scales = keys, np.array(cols), np.array(scales)
        self._context = [(name, cfg.column(col)) for name, col in cfg.context().items()]
        #: non-finite values per HAL column name (the sample goes out as null)
        self.nonfinite: dict[str, int] = {}
        self.sessions = 0  # HAL sessions seen
        self.gaps = 0  # runs that started after missing samples
        self.missing = 0  # samples the counter says were not delivered
        self.held = 0  # first samples of a run not sent: their velocity (a position difference) is unknown
        self._low: int | None = None  # last counter value (mod 2**32)
        self._seq = 0  # its unwrapped value
        self._k0 = 0  # t = (seq + k0) Ts
        self._t_last = -math.inf
        self._last_x: dict[str, float] = {}

    def new_session(self) -> None:
        """Forget the counter: the next rows start a session (a new HAL, or the bridge re-attached)."""
        self._low = None

    def map(self, rows: np.ndarray, t_read: float) -> list[Run]:
        """The runs in ``rows`` (n × columns, as the FIFO gave them); ``t_read``: CLOCK_MONOTONIC (s)
        when they were read."""
        n = rows.shape[0]
        if n == 0:
            return []
        low = np.asarray(rows[:, self._counter], dtype=np.int64) % WRAP
        if self._low is not None and (int(low[0]) - self._low) % WRAP == 1 and \
                (n == 1 or bool(np.all(np.diff(low) % WRAP == 1))):  # the usual case: the next samples
            self._seq += n
            self._low = int(low[-1])
            return [self._run(rows, self._seq - n + 1, True)]
        step = np.empty(n, dtype=np.int64)
        step[1:] = (low[1:] - low[:-1]) % WRAP
        step[0] = 0 if self._low is None else (int(low[0]) - self._low) % WRAP
        back = step >= _HALF
        if self._low is None:
            back[0] = True
        starts = np.flatnonzero(back | (step != 1))
        if starts.size == 0 or starts[0] != 0:
            starts = np.concatenate(([0], starts))
        runs = []
        for a, b in zip(starts, np.append(starts[1:], n)):
            if back[a]:  # a session starts: the counter's value is the sequence number
                self._session(int(low[a]), int(low[b - 1]), t_read)
            elif step[a] != 1:
                self.gaps += 1
                self.missing += int(step[a]) - 1
                self._seq += int(step[a])
            else:
                self._seq += 1
            seq0 = self._seq
            self._seq += int(b - a) - 1
            continues = not back[a] and step[a] == 1
            run = self._run(rows[a:b], seq0, continues)
            if not continues and self._positions:  # its velocity is unknown: it only gives the next one's
                run = run.cut(1, len(run))
                self.held += 1
            if len(run):
                runs.append(run)
        self._low = int(low[-1])
        return runs

    def _session(self, first_low: int, last_low: int, t_read: float) -> None:
        self.sessions += 1
        self._seq = first_low
        newest = first_low + (last_low - first_low) % WRAP
        k0 = int(round(t_read / self.Ts)) - newest
        first_t = (first_low + k0) * self.Ts
        if first_t <= self._t_last:  # the monotonic clock cannot go back; a stamp could be early
            k0 += int(math.floor((self._t_last - first_t) / self.Ts)) + 1
        self._k0 = k0
        self._last_x.clear()

    def _run(self, rows: np.ndarray, seq0: int, continues: bool) -> Run:
        n = rows.shape[0]
        t = (np.arange(seq0, seq0 + n, dtype=np.float64) + self._k0) * self.Ts
        self._t_last = float(t[-1])
        X = rows[:, self._cols] * self._scales
        bad = ~np.isfinite(X)
        if bad.any():
            X[bad] = np.nan
            for i in np.flatnonzero(bad.any(axis=0)):
                name = self.cfg.columns[self._cols[i]]
                self.nonfinite[name] = self.nonfinite.get(name, 0) + int(bad[:, i].sum())
        cols = {key: X[:, i] for i, key in enumerate(self._keys)}
        for axis in self._positions:
            x = cols[f"{axis}.position"]
            prev = self._last_x.get(axis, math.nan) if continues else math.nan
            v = np.empty(n)
            v[0] = (x[0] - prev) / self.Ts
            v[1:] = np.diff(x) / self.Ts
            cols[f"{axis}.v_meas"] = v
            self._last_x[axis] = float(x[-1])
        for name, col in self._context:
            cols[name] = np.asarray(rows[:, col], dtype=np.int64)
        return Run(seq0, t, cols)
