"""The per-axis process monitor: estimate rows in, :class:`~feedio.schema.AlarmEvent` s out. No I/O.

:class:`ProcessMonitors` is what the :class:`~monitor.pipeline.Pipeline` calls after the estimator, so the
live monitor and ``feedmon run --from`` judge the same rows the same way. The force of estimate row ``j``
describes sample ``j − 1`` (:mod:`monitor.estimator`), so it is paired with that sample's spindle angle;
an alarm carries row ``j``'s sequence number, time and context (the row on which it was decided).

Sections: a contiguous run of rows with the same ``(tool, program_line)`` (the n-th such run of a key is
its own section: a line inside a loop is run many times); without context columns the whole run is one
section. Progress within a section (s since its first row) indexes the reference envelope.
"""

from __future__ import annotations

import logging
import math
from collections import deque

import numpy as np

from feedio import schema as S
from kernels import force_monitors as fm

from .reference import ReferenceFile, section_key
from .settings import MonitorSettings

__all__ = ["AxisProcessMonitor", "ProcessMonitors", "build_monitors", "VIEW_INTERVAL_S"]

log = logging.getLogger("monitor.process")

_IMPULSE_KINDS = ("collision", "overload")
_ENVELOPE_KINDS = ("missing_cut", "over_band")
#: monitor names an acknowledgement may name
MONITORS = S.ALARM_MONITORS


#: s of data between two dashboard views of an axis (:meth:`AxisProcessMonitor.take_view`): at most 50 a second
#: whatever the rate of blocks, about one per revolution at 3000 rpm
VIEW_INTERVAL_S = 0.02


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _mean_of(arrays) -> np.ndarray:
    """Element-wise mean of equal-length arrays over their finite values (NaN where none is)."""
    x = np.array(arrays)
    ok = np.isfinite(x)
    n = ok.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, np.where(ok, x, 0.0).sum(axis=0) / n, np.nan)


class AxisProcessMonitor:
    """Monitors of one axis (settings :class:`~monitor.process_monitor.settings.MonitorSettings`)."""

    def __init__(self, machine: str, axis: str, settings: MonitorSettings, Ts: float,
                 reference: ReferenceFile | None = None, v_min: float = 0.0) -> None:
        self.machine, self.axis, self.s, self.Ts = machine, axis, settings, float(Ts)
        #: m/s: below it (the model's dead band Ω or min_speed) the friction law does not hold
        self.v_min = float(v_min)
        self._v_last = math.nan  # the previous block's last measured velocity
        imp = settings.impulse
        self._window = max(2, int(round(imp.window_s / self.Ts)))
        self._impulse = fm.new_impulse_state(self._window, imp.bins)
        ts = settings.tooth
        self._teeth = fm.ToothAccumulator(ts.teeth, ts.bins)
        self._tooth = self._new_detector()
        self.reference = reference
        self._env = fm.new_envelope_state()
        self._persist = max(1, int(round(settings.envelope.persist_s / self.Ts)))
        self.widen = dict.fromkeys(MONITORS, 1.0)
        self._theta_last = math.nan  # the angle of the previous block's last sample
        self._key: tuple | None = None  # (tool, program_line) of the current section
        self._occurrence: dict[tuple, int] = {}
        self._t0 = math.nan  # time of the current section's first row
        self._ref_sec = None
        self.counts: dict[str, int] = {}
        self.last: S.AlarmEvent | None = None
        #: the last revolution (row seq, t, record of ToothAccumulator) and whether it is new; the angle profiles
        #: and per-tooth peaks of the last TOOTH_VIEW_REVOLUTIONS
        self._rev: tuple | None = None
        self._revs: deque = deque(maxlen=S.TOOTH_VIEW_REVOLUTIONS)
        self._rev_new = False
        self._row: tuple | None = None  # (seq, t, σ, section key) of the last row judged
        self._view_t = -math.inf  # time of the last view
        self.sections: list[dict] = []  # per finished section: key, occurrence, rows, mean force (N), energy (J)
        self._acc = [0, 0.0, 0.0]
        #: revolutions ending before this time are not judged per tooth: an impulse distorts their fit
        self._tooth_quiet_until = -math.inf

    def _new_detector(self) -> fm.ToothDetector:
        ts = self.s.tooth
        return fm.ToothDetector(learn=ts.learn_revolutions, cut_min=ts.cut_min_N, sensitivity=ts.sensitivity,
                                broken_fraction=ts.broken_fraction, runout_fraction=ts.runout_fraction,
                                settle=ts.settle_revolutions)

    # ---- operator --------------------------------------------------------------------------------------
    def acknowledge(self, monitor: str) -> float:
        """An operator called the last alarm of ``monitor`` a false alarm: widen its limits by ``ack_widen``
        (logged); returns the new factor."""
        if monitor not in MONITORS:
            raise ValueError(f"unknown monitor {monitor!r}; one of {', '.join(MONITORS)}")
        self.widen[monitor] *= self.s.ack_widen
        self._tooth.widen = self.widen["tooth"]
        if monitor == "tooth":
            self._tooth.latched.clear()
        log.warning("axis %s/%s: false alarm acknowledged for monitor %s: its limits widened ×%.3g", self.machine,
                    self.axis, monitor, self.widen[monitor])
        return self.widen[monitor]

    # ---- rows ------------------------------------------------------------------------------------------
    def update(self, est, block: S.SampleBlock) -> list[S.AlarmEvent]:
        """Judge the estimate rows ``est`` (:class:`~monitor.estimate_rows.EstimateRows`) of ``block``."""
        if est is None or est.force is None or len(est) == 0:
            return []
        n = len(est)
        force = est.force[0]
        sd = np.sqrt(np.maximum(est.force[1], 0.0))
        raw = self._raw_force(est)
        judged = self._judged(est, raw)
        theta = self._angles(est, block)
        tool = est.context.get("tool")
        line = est.context.get("program_line")
        out: list[S.AlarmEvent] = []
        start = 0
        while start < n:  # split at section changes (rows of one key together)
            key = (tool[start] if tool else None, line[start] if line else None)
            stop = start + 1
            while stop < n and (tool[stop] if tool else None, line[stop] if line else None) == key:
                stop += 1
            if key != self._key or not math.isfinite(self._t0):
                self._new_section(key, float(est.t[start]))
            out += self._segment(est, start, stop, force, sd, theta, key, raw, judged)
            start = stop
        self._row = (int(est.seq + n - 1), float(est.t[-1]), float(sd[-1]), key)
        for a in out:
            self.counts[a.kind] = self.counts.get(a.kind, 0) + 1
            self.last = a
        return out

    @property
    def last_row(self) -> tuple[int, float] | None:
        """(seq, t) of the last row judged (where an end-of-run alarm is stamped)."""
        return None if self._row is None else self._row[:2]

    def _raw_force(self, est) -> np.ndarray:
        """The measured force of each row (N): the one-step residual ``v(j−1) = v_m(j) − βᵀz(j−1)`` scaled like
        the filtered force (``F = −f/b``, the row's own scale ``force/f``). It carries the force of sample
        j − 1 plus the measurement noise; the tracker's filtered force smooths what its kernel does not
        expect (a once-per-revolution component under a tooth-period kernel), the per-tooth fit needs it."""
        from kernels.online import R_F, R_RESID

        f = est.rows[R_F]
        good = np.abs(f) > 0
        with np.errstate(over="ignore", invalid="ignore"):
            scale = est.force[0][good] / f[good]
        scale = scale[np.isfinite(scale)]
        if not scale.size:
            return np.full(len(est), np.nan)
        # one row per message is the live case: np.median of one value costs ~25 µs for nothing
        return est.rows[R_RESID] * float(scale[0] if scale.size == 1 else np.median(scale))

    def _angles(self, est, block: S.SampleBlock) -> np.ndarray:
        """Spindle angle (rad) of the sample each row's force describes (row j: sample j − 1)."""
        n = len(est)
        if block.spindle_angle is None:
            self._theta_last = math.nan
            return np.full(n, np.nan)
        ang = np.array(block.spindle_angle, dtype=np.float64)
        first = est.seq - block.seq
        theta = np.empty(n)
        theta[0] = ang[first - 1] if first >= 1 else self._theta_last
        theta[1:] = ang[first:first + n - 1]
        self._theta_last = float(ang[-1])
        return theta

    def _new_section(self, key: tuple, t0: float) -> None:
        self._close_section()
        self._key, self._t0 = key, t0
        occ = self._occurrence[key] = self._occurrence.get(key, -1) + 1
        self._env[:] = 0.0
        self._ref_sec = None if self.reference is None else self.reference.find(section_key(*key, occ))

    def _close_section(self) -> None:
        n, fsum, energy = self._acc
        if self._key is not None and n:
            self.sections.append({"tool": self._key[0], "program_line": self._key[1],
                                  "occurrence": self._occurrence.get(self._key, 0), "rows": n,
                                  "mean_force_N": fsum / n, "energy_J": energy})
            del self.sections[:-10_000]
        self._acc = [0, 0.0, 0.0]

    def finish(self) -> list[dict]:
        """End of the run: close the open section; returns the per-section statistics (wear trend input)."""
        self._close_section()
        self._key = None
        return self.sections

    def _impulse_limits(self, key: tuple) -> tuple[float, float, float, float, float]:
        """(ratio, ratio_angle, k, collision floor, overload limit) of the impulse test (M1, M2) in a section, the
        operator's widening applied."""
        imp, w = self.s.impulse, self.widen["impulse"]
        floor, over = self._limits(key)
        return imp.ratio * w, imp.ratio_angle * w, imp.sensitivity * w, floor * w, over

    def _limits(self, key: tuple) -> tuple[float, float]:
        """(collision floor, overload limit) of a section: the last matching ``[[monitors.section]]`` wins."""
        imp = self.s.impulse
        floor, over = imp.limit_N, imp.overload_N if imp.overload_N is not None else math.inf
        for sec in self.s.section:
            if (sec.tool is None or sec.tool == key[0]) and (sec.program_line is None or sec.program_line == key[1]):
                floor = sec.limit_N if sec.limit_N is not None else floor
                over = sec.overload_N if sec.overload_N is not None else over
        return floor, over

    def _judged(self, est, raw: np.ndarray) -> np.ndarray:
        """The measured force where the friction law holds: NaN on rows whose velocity, or the previous
        row's, is at or below :attr:`v_min`. There the Coulomb column of the regression switches while the
        real friction does not (stiction, the stop and the breakaway), so the one-step residual is the
        friction model's error, not a process force: a stop at the end of a part read as a 90 N impulse."""
        v = np.abs(np.asarray(est.v_meas, dtype=float))
        prev = np.concatenate(([abs(self._v_last)], v[:-1]))
        self._v_last = float(v[-1]) if v.size else self._v_last
        slow = ~(np.minimum(v, prev) > self.v_min)  # NaN velocities are not judged either
        return np.where(slow, np.nan, raw)

    def _segment(self, est, a: int, b: int, force, sd, theta, key, raw, judged) -> list[S.AlarmEvent]:
        f, s, th = force[a:b], sd[a:b], theta[a:b]
        m = b - a
        ok = np.isfinite(f)
        self._acc[0] += int(ok.sum())
        self._acc[1] += float(f[ok].sum())
        v = est.v_meas[a:b]
        good = ok & np.isfinite(v)
        self._acc[2] += float((f[good] * v[good]).sum() * self.Ts)
        out: list[S.AlarmEvent] = []
        kind, value, limit = np.full(m, -1, np.int64), np.zeros(m), np.zeros(m)
        imp = self.s.impulse
        if imp.enabled:
            ratio, ratio_angle, k, floor, over = self._impulse_limits(key)
            fi = judged[a:b] if imp.signal == "measured" else f
            if fm.impulse_step(self._impulse, th, fi, s, ratio, ratio_angle, k, floor, over, imp.persist, imp.alpha,
                               kind, value, limit):
                for i in np.nonzero(kind >= 0)[0]:
                    self._tooth_quiet_until = float(est.t[a + i]) + 3 * imp.window_s
                    out.append(self._event(est, a + i, _IMPULSE_KINDS[kind[i]], "impulse", value[i], limit[i],
                                           s[i] if kind[i] == 0 else None, "|F − expected|" if kind[i] == 0 else "|F|"))
        if self.s.tooth.enabled and np.isfinite(th).any():
            out += self._tooth_rows(est, a, th, raw[a:b], s)
        ref = self._ref_sec
        if ref is not None:
            env = self.s.envelope
            w = self.widen["envelope"]
            progress = est.t[a:b] - self._t0
            if fm.envelope_step(self._env, progress, f, s, ref.mean_array, ref.spread_array, ref.bin_s,
                                env.sensitivity * w, env.band_min_N * w, env.cut_min_N, self._persist,
                                kind, value, limit):
                for i in np.nonzero(kind >= 0)[0]:
                    out.append(self._event(est, a + i, _ENVELOPE_KINDS[kind[i]], "envelope", value[i], limit[i],
                                           s[i], f"reference section {ref.key}, {progress[i]:.3f} s in"))
        out.sort(key=lambda e: e.seq)
        return out

    def _tooth_rows(self, est, a: int, th, f, s) -> list[S.AlarmEvent]:
        rows, prof = self._teeth.update(th, f)
        out = []
        for r, p in zip(rows, prof):
            i = a + int(r[0])
            self._rev, self._rev_new = (int(est.seq + i), float(est.t[i]), r), True
            self._revs.append((p, r[5:]))
            quiet = float(est.t[i]) <= self._tooth_quiet_until
            for kind, excess, lim in self._tooth.update(math.nan if quiet else float(r[1]), float(r[2])):
                # after a runout alarm, a step means a tooth stopped cutting; the force cannot tell a breakage
                # from a runout that now exceeds the feed per tooth (the tooth's edge force ends with its chip)
                cause = "one tooth cuts less: a breakage, or the runout alarmed before now exceeds the feed per " \
                    "tooth; " if kind == "broken_tooth" and "runout" in self._tooth.latched else ""
                out.append(self._event(est, i, kind, "tooth", excess, lim, self._tooth.sd1,
                                       f"{cause}once-per-revolution amplitude {r[2]:.1f} N against "
                                       f"{self._tooth.mean1:.1f} N learned, mean force {r[1]:.1f} N; tooth peaks "
                                       + ", ".join(f"{x:.1f}" for x in r[5:]) + " N"))
        return out

    def _event(self, est, i: int, kind: str, monitor: str, value: float, limit: float, sigma, detail: str):
        ctx = {k: est.context[k][i] for k in ("program_line", "tool") if k in est.context}
        sig = None if sigma is None or not math.isfinite(sigma) else float(sigma)
        return S.AlarmEvent(machine=self.machine, axis=self.axis, seq=int(est.seq + i), t=float(est.t[i]), kind=kind,
                            monitor=monitor, value=float(value), limit=float(limit), sigma=sig,
                            detail=detail[:S.ALARM_DETAIL_CHARS_MAX], **ctx)

    # ---- dashboard ---------------------------------------------------------------------------------------
    def take_view(self) -> S.ProcessView | None:
        """What the monitors judge against at the last row (:class:`~feedio.schema.ProcessView`), for the
        dashboard; None until :data:`VIEW_INTERVAL_S` s of data passed since the last one (the caller asks once a
        block: the cost is per view, not per sample). The collision range and the envelope band are the
        kernels' own (M1, M6: :func:`~kernels.force_monitors.impulse_band`, ``envelope_band``)."""
        if self._row is None or self._view_t <= self._row[1] < self._view_t + VIEW_INTERVAL_S:
            return None  # (time going backwards, a new bridge session, is due at once)
        seq, t, sd, key = self._row
        self._view_t = t
        imp, lo, hi, over = self.s.impulse, math.nan, math.nan, math.nan
        if imp.enabled:
            ratio, ratio_angle, k, floor, over = self._impulse_limits(key)
            lo, hi = fm.impulse_band(self._impulse, ratio, ratio_angle, k, floor)
        b_lo, b_hi, ref = math.nan, math.nan, self._ref_sec
        if ref is not None:
            env, w = self.s.envelope, self.widen["envelope"]
            b_lo, b_hi = fm.envelope_band(t - self._t0, sd, ref.mean_array, ref.spread_array, ref.bin_s,
                                          env.sensitivity * w, env.band_min_N * w)
        tooth = None
        if self._rev_new:
            self._rev_new = False
            r_seq, r_t, r = self._rev
            a0, a1 = float(r[1]), float(r[2])
            lim_b, lim_r = self._tooth.limits(a0) if self._tooth.learned else (math.nan, math.nan)
            m1 = self._tooth.mean1
            prof, peaks = (_mean_of(x) for x in zip(*self._revs))
            tooth = S.ToothView(seq=r_seq, t=r_t, profile=[_num(x) for x in prof], peaks=[_num(x) for x in peaks],
                                a0=_num(a0), a1=_num(a1), a1_broken=_num(m1 + lim_b), a1_runout=_num(m1 + lim_r))
        return S.ProcessView(machine=self.machine, axis=self.axis, seq=seq, t=t, collision_low=_num(lo),
                             collision_high=_num(hi), overload=_num(over), band_low=_num(b_lo),
                             band_high=_num(b_hi), tooth=tooth)

    def status(self) -> dict:
        """Counts per kind and the last alarm (``feedmon status``)."""
        last = self.last
        return {"alarms": sum(self.counts.values()), "by_kind": dict(self.counts),
                "last": None if last is None else {"kind": last.kind, "t": last.t, "seq": last.seq,
                                                   "value": last.value, "limit": last.limit},
                "widen": {k: v for k, v in self.widen.items() if v != 1.0}}


class ProcessMonitors:
    """The process monitors of every axis (those whose model scales to newtons), keyed like the axes."""

    def __init__(self, axes: dict, settings: MonitorSettings, references: dict | None = None, wear=None) -> None:
        self.settings = settings
        #: the wear history across parts (:class:`~.wear.WearMonitor`; None: no wear monitor)
        self.wear = wear
        refs = references or {}
        self.by_axis = {key: AxisProcessMonitor(key[0], key[1], settings, float(ax.model.Ts), refs.get(key),
                                                v_min=max(float(ax.model.omega),
                                                          float(ax.model.online.adaptation.min_speed)))
                        for key, ax in axes.items()}

    def update(self, key: tuple[str, str], est, block: S.SampleBlock) -> list[S.AlarmEvent]:
        mon = self.by_axis.get(key)
        return [] if mon is None else mon.update(est, block)

    def take_view(self, key: tuple[str, str]) -> S.ProcessView | None:
        """The dashboard's view of an axis when one is due (:meth:`AxisProcessMonitor.take_view`)."""
        mon = self.by_axis.get(key)
        return None if mon is None else mon.take_view()

    def finish(self, part: str, when: str) -> dict[tuple[str, str], list[S.AlarmEvent]]:
        """End of a run (one part): each axis' section statistics into the wear history, saved; the ``wear``
        alarms per axis. ``part`` labels the run in the history, ``when`` is its UTC time (ISO 8601). A history
        that cannot be saved is left as it was, the reason in ``wear.error`` (the alarms are still returned)."""
        if self.wear is None:
            return {}
        out = {}
        for key, mon in self.by_axis.items():
            alarms = self.wear.add_run(key[0], key[1], mon.finish(), part, when, mon.last_row)
            for a in alarms:
                mon.counts[a.kind] = mon.counts.get(a.kind, 0) + 1
                mon.last = a
            out[key] = alarms
        try:
            self.wear.save()
        except (OSError, ValueError) as exc:
            self.wear.error = f"{type(exc).__name__}: {exc}"
            log.error("wear history %s NOT saved: %s", self.wear.path, self.wear.error)
        return out


def build_monitors(axes: dict, settings: MonitorSettings) -> ProcessMonitors | None:
    """The process monitors of ``axes`` with the reference files and the wear history of ``settings`` (None: not
    enabled). ``ValueError`` for a reference file that cannot be read or names no monitored axis, and for a wear
    history that cannot be used."""
    if settings is None or not settings.enabled:
        return None
    from .reference import load_reference

    refs = {}
    for path in settings.envelope.reference:
        ref = load_reference(path)
        key = (ref.machine, ref.axis)
        if key not in axes:
            raise ValueError(f"reference file {path} is of axis {ref.machine}/{ref.axis}, which has no model here")
        if key in refs:
            raise ValueError(f"reference file {path}: a second reference for axis {ref.machine}/{ref.axis}")
        refs[key] = ref
    wear = None
    if settings.wear.history is not None:
        from .wear import WearMonitor

        wear = WearMonitor(settings.wear)
    return ProcessMonitors(axes, settings, refs, wear)
