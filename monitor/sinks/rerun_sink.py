"""``RerunSink``: the live and recorded Rerun dashboard of the monitor (thesis Figure 4.8 per axis).

What it shows, and where each value is placed in time, is in :mod:`monitor.sinks.rerun_layout`;
the event log in :mod:`monitor.sinks.rerun_events`; the spectra in :mod:`monitor.sinks.rerun_spectra`; the
process monitors' limits, alarms and per-tooth panel in :mod:`monitor.sinks.rerun_monitors`.

Outputs
-------
A private :class:`rerun.RecordingStream` (never the global one) with

* a :class:`rerun.FileSink` when ``rrd_path`` is given (``feedmon run --rrd FILE``),
* a :class:`rerun.GrpcServerSink` when ``serve_port`` is given: the *monitor* hosts a gRPC server
  that buffers up to ``memory_limit`` (oldest data dropped first) and a viewer connects whenever
  it likes with ``rerun --connect rerun+http://<host>:<port>/proxy``. The sink never pushes to a
  viewer: an absent viewer must not stall or break the monitor.

Without either, data go to Rerun's in-memory buffered sink (useful in tests only).

Hot path and batching
---------------------
``offer`` (from :class:`~monitor.sinks.queued.QueuedSink`) never blocks. ``handle`` only checks a
block and appends it to its axis (O(1) per block); every ``batch_interval`` (default 0.1 s, about
10×/s) the worker builds NumPy columns and sends one ``send_columns`` chunk per entity. The
spectra are refreshed every ``psd_every`` samples *of data* (not wall time), so a replay at any
speed records the same number of spectra. ``written`` in :meth:`status` counts blocks taken into
a batch. In ``feedmon run`` the whole sink runs in a child process
(:class:`~monitor.sinks.rerun_process.RerunProcessSink`).

Failures
--------
Every failure is counted in ``failures`` (per lost block, also counted ``lost``): a block that
cannot be recorded (a time outside Rerun's nanosecond timeline, ±292 years), an exception while
sending, too many axes (``max_axes``). A block is ``written`` when its batch was sent. The
recording is flushed every ``flush_interval`` s; a flush that does not finish within
``flush_timeout`` s makes the sink ``degraded`` (a busy machine: Rerun still holds the data, nothing
is lost, nothing alarming is logged), and ``broken_after`` such flushes in a row are a failure
(e.g. the disk is full: Rerun's file writer stopped): the output is declared broken, later blocks
are dropped and counted instead of piling up in Rerun's buffers, and the final flush is skipped
(it would wait for ever).

The ``.rrd`` file is written with a footer (``rerun rrd verify`` needs it); the footer index is
kept in memory until the file is closed, which grows with the number of chunks on very long runs.
"""

from __future__ import annotations

import logging
import math
import os
import uuid
from collections.abc import Mapping
from dataclasses import dataclass, field
from itertools import chain
from typing import Any

import msgspec
import numpy as np

from feedio import schema as S

from . import rerun_layout as L
from .queued import QueuedSink
from .rerun_events import EVENT_LEVELS, Event, FlagDigest
from .rerun_layout import AxisInfo, describe_model
from .rerun_monitors import send_alarms, send_views
from .rerun_spectra import marker_frequencies, psd_above_floor

__all__ = ["RerunSink", "AxisInfo", "describe_model", "TIME_LIMIT_S", "axis_root"]

log = logging.getLogger("monitor.sinks")

#: |t| (s) beyond this cannot be placed on Rerun's int64-nanosecond ``time`` timeline
TIME_LIMIT_S = 9.2e9
#: longest event text logged (characters); longer texts are cut
MAX_EVENT_TEXT = 2000
_HEALTH_LEVEL = {"ok": "INFO", "warn": "WARN", "alarm": "ERROR"}


def axis_root(machine: str, axis: str) -> str:
    """Entity path of one axis, ``/<machine>/<axis>`` (each part escaped for Rerun)."""
    import rerun as rr

    return f"/{rr.escape_entity_path_part(machine)}/{rr.escape_entity_path_part(axis)}"


@dataclass(frozen=True)
class _EventItem:
    machine: str
    axis: str
    event: Event


@dataclass(frozen=True)
class _HealthItem:
    machine: str
    axis: str
    health: Mapping[str, Any]


class _Tail:
    """The last ``cap`` values of a signal with the sample numbers they describe."""

    def __init__(self, cap: int) -> None:
        self.cap = cap
        self.seq = np.empty(0, dtype=np.int64)
        self.val = np.empty(0, dtype=np.float64)

    def extend(self, seq: np.ndarray, val: np.ndarray) -> None:
        self.seq = np.concatenate((self.seq, seq))[-self.cap:]
        self.val = np.concatenate((self.val, val))[-self.cap:]

    def window(self, hi: int, n: int) -> np.ndarray:
        """Values describing samples hi−n+1 … hi."""
        keep = (self.seq > hi - n) & (self.seq <= hi)
        return self.val[keep]


class _Rolling:
    """Per-row count of true values over the last ``w`` rows (carried across batches)."""

    def __init__(self) -> None:
        self.tail = np.zeros(0, dtype=np.int64)

    def counts(self, x: np.ndarray, w: int) -> np.ndarray:
        z = np.concatenate((self.tail[-(w - 1):] if w > 1 else self.tail[:0], x.astype(np.int64)))
        m = z.size - x.size
        cs = np.concatenate(([0], np.cumsum(z)))
        hi = np.arange(m + 1, z.size + 1)
        out = cs[hi] - cs[np.maximum(hi - w, 0)]
        self.tail = z[-(w - 1):] if w > 1 else z[:0]
        return out


@dataclass
class _Axis:
    machine: str
    axis: str
    root: str
    info: AxisInfo
    digest: FlagDigest
    residual: _Tail
    estimate: _Tail
    actual: _Tail
    force: bool | None = None
    has_samples: bool = False
    samples: list = field(default_factory=list)  # blocks waiting for the next batch
    estimates: list = field(default_factory=list)
    truth: list = field(default_factory=list)
    events: list = field(default_factory=list)
    Ts: float | None = None  # measured sampling period (median over consecutive rows)
    last_seq: int | None = None
    last_t: float | None = None
    since_psd: int = 0
    rpm: float | None = None
    markers_said: tuple | None = None
    health: str | None = None
    context: bool = False  # the estimates carry context columns (NC program line, tool)
    pruned: _Rolling = field(default_factory=_Rolling)
    reduced: _Rolling = field(default_factory=_Rolling)
    process: bool = False  # process monitors judge the axis (their views arrive): the per-tooth panel
    views: list = field(default_factory=list)  # ProcessViews waiting for the next batch
    alarms: list = field(default_factory=list)  # AlarmEvents waiting for the estimate of their row
    alarm_kinds: set = field(default_factory=set)  # kinds whose marker style is logged

    @property
    def sample_period(self) -> float | None:
        """Ts (s): from ``axis_info``, else measured."""
        return self.info.Ts or self.Ts


def _index(blocks: list) -> tuple[np.ndarray, np.ndarray]:
    """``seq`` and ``t`` columns of consecutive blocks (each block: seq, seq+1, ...)."""
    lengths = np.fromiter((len(b.t) for b in blocks), dtype=np.int64, count=len(blocks))
    starts = np.fromiter((b.seq for b in blocks), dtype=np.int64, count=len(blocks))
    offsets = np.arange(int(lengths.sum()), dtype=np.int64) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    seq = np.repeat(starts, lengths) + offsets
    t = np.fromiter(chain.from_iterable(b.t for b in blocks), dtype=np.float64, count=len(seq))
    return seq, t


def _column(blocks: list, name: str, n: int, dtype=np.float64) -> np.ndarray | None:
    """One column over blocks; ``None`` entries (and absent optional columns) become NaN."""
    cols = [getattr(b, name) for b in blocks]
    if all(c is None for c in cols):
        return None
    flat = chain.from_iterable(c if c is not None else [None] * len(b.t) for b, c in zip(blocks, cols))
    if dtype is np.float64:
        return np.array(list(flat), dtype=np.float64)  # None -> nan
    return np.fromiter(flat, dtype=dtype, count=n)


def _sqrt(v: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.where(v >= 0, v, np.nan))


class RerunSink(QueuedSink):
    """Queued Rerun dashboard; see the module docstring.

    Parameters
    ----------
    rrd_path:
        write the recording to this ``.rrd`` file.
    serve_port:
        host a gRPC server on this port for live viewers (``serve_host`` to bind, default loopback).
    memory_limit:
        gRPC server buffer (``"25%"`` of RAM or e.g. ``"2GB"``); oldest data dropped first.
    application_id, recording_id:
        Rerun application / recording ids (recording id random by default).
    axis_info:
        ``{"machine/axis": {"period": s, "teeth": n, "Ts": s, "force": bool}}`` (see :class:`AxisInfo`,
        :func:`describe_model`).
    window:
        rolling window (s of controller time) of the time-series views; default 10 s when serving
        live, the whole run for a file only.
    detail:
        length (s) of the detail panel next to the force panel (the waveform, sample by sample).
    batch_interval:
        seconds between ``send_columns`` batches (≈ 10×/s).
    psd_window, psd_every, psd_nperseg:
        spectra over the last ``psd_window`` samples, refreshed every ``psd_every`` samples of data,
        Welch segments of ``psd_nperseg``.
    rate_window:
        seconds of data over which pruning rates are counted.
    summary_s, max_event_lines:
        event log: REDUCED summary period and rate-limit window (s of data), lines per kind and window.
    flush_interval, flush_timeout, broken_after:
        durability check of the outputs (see Failures).
    max_axes:
        axes recorded at most; blocks of further axes are refused and counted.
    """

    #: blocks are only buffered by ``handle``: a batch sent and flushed proves the output works
    recover_on_tick = True
    #: a block is written when its batch was sent (events and health reports when taken)
    counts_written = False

    def __init__(
        self,
        rrd_path: str | os.PathLike | None = None,
        serve_port: int | None = None,
        memory_limit: str = "25%",
        *,
        serve_host: str = "127.0.0.1",
        application_id: str = "feedmon",
        recording_id: str | None = None,
        axis_info: Mapping[str, Mapping[str, Any]] | None = None,
        window: float | None = None,
        detail: float = 0.25,
        batch_interval: float = 0.1,
        psd_window: int = 4096,
        psd_every: int = 1000,
        psd_nperseg: int = 512,
        rate_window: float = 1.0,
        summary_s: float = 10.0,
        max_event_lines: int = 5,
        flush_interval: float = 1.0,
        flush_timeout: float = 2.0,
        broken_after: int = 3,
        max_axes: int = 64,
        maxsize: int = 4096,
        max_bytes: int | None = None,
        name: str = "rerun",
    ) -> None:
        import rerun as rr

        from .rerun_process import check_outputs

        check_outputs(rrd_path, serve_port)
        if not 16 <= psd_window <= 1_000_000 or not 1 <= psd_every <= 10_000_000 or not 16 <= psd_nperseg:
            raise ValueError(f"psd_window must be 16..1e6 samples, psd_every 1..1e7, psd_nperseg ≥ 16; got "
                             f"{psd_window}, {psd_every}, {psd_nperseg}")
        for label, v in (("window", window), ("detail", detail), ("batch_interval", batch_interval),
                         ("rate_window", rate_window), ("flush_interval", flush_interval),
                         ("flush_timeout", flush_timeout)):
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"{label} must be a positive number of seconds, got {v!r}")
        self.infos = {str(k): AxisInfo.parse(str(k), v) for k, v in (axis_info or {}).items()}
        self.rrd_path = None if rrd_path is None else os.fspath(rrd_path)
        self.serve_port = None if serve_port is None else int(serve_port)
        self.window = window if window is not None else (10.0 if serve_port is not None else None)
        self.detail = float(detail)
        self.batch_interval = float(batch_interval)
        self.psd_window, self.psd_every, self.psd_nperseg = int(psd_window), int(psd_every), int(psd_nperseg)
        self.rate_window = float(rate_window)
        self.summary_s, self.max_event_lines = float(summary_s), int(max_event_lines)
        self.flush_interval, self.flush_timeout = float(flush_interval), float(flush_timeout)
        self.broken_after, self.max_axes = max(1, int(broken_after)), int(max_axes)
        self.rec = rr.RecordingStream(application_id, recording_id=recording_id or uuid.uuid4())
        sinks: list[Any] = []
        if self.rrd_path is not None:
            sinks.append(rr.FileSink(self.rrd_path))
        self.server_uri: str | None = None
        if self.serve_port is not None:
            server = rr.GrpcServerSink(serve_host, self.serve_port, server_memory_limit=memory_limit)
            self.server_uri = server.uri
            sinks.append(server)
        if sinks:
            self.rec.set_sinks(*sinks)
        self._axes: dict[tuple[str, str], _Axis] = {}
        self._last_batch = 0.0
        self._last_flush = 0.0
        self._flush_failures = 0  # consecutive
        self.broken = False
        self.batches = 0
        self.psd_updates = 0
        self.events_logged = 0
        self._layout: tuple = ()
        self._tick_failed = False
        super().__init__(maxsize, name=name, tick_interval=min(0.05, self.batch_interval / 2), max_bytes=max_bytes)

    # ---- producer helpers ----------------------------------------------------------------
    def offer_truth(self, machine: str, axis: str, block: S.TruthBlock) -> bool:
        """Queue a :class:`TruthBlock` of ``machine/axis`` (plotted as the true force / dynamometer)."""
        return self.offer((machine, axis, block))

    def offer_event(self, machine: str, axis: str, seq: int, t: float, level: str, text: str) -> bool:
        """Queue one line for the event log of ``machine/axis`` at sample ``seq`` (time ``t`` s).

        ``level`` one of CRITICAL, ERROR, WARN, INFO, DEBUG. For producers other than the flags
        (the health monitor); never blocks.
        """
        return self.offer(_EventItem(machine, axis, Event(int(seq), float(t), str(level), str(text))))

    def offer_alarm(self, event: S.AlarmEvent, received_ns: int | None = None) -> bool:
        """Queue a process alarm: an ERROR line in the event log of its axis (:func:`alarm_line`) and a marker
        on its force panel (:func:`~monitor.sinks.rerun_monitors.send_alarms`)."""
        return self.offer(event)

    def offer_process_view(self, view: S.ProcessView) -> bool:
        """Queue a process monitors' view of an axis: its limits on the force panel, the per-tooth panel
        (:mod:`monitor.sinks.rerun_monitors`)."""
        return self.offer(view)

    def offer_health(self, machine: str, axis: str, health: Mapping[str, Any]) -> bool:
        """Queue a health report (``{"seq", "t", "state": "ok"|"warn"|"alarm", "reasons": [...]}``):
        the event log gets a line when the state of the axis changes."""
        if isinstance(health, msgspec.Struct):  # a feedio.schema.Health message
            health = msgspec.to_builtins(health)
        return self.offer(_HealthItem(machine, axis, dict(health)))

    def extra_status(self) -> dict[str, Any]:
        return {"rrd_path": self.rrd_path, "server_uri": self.server_uri, "batches": self.batches,
                "psd_updates": self.psd_updates, "events": self.events_logged, "broken": self.broken,
                "axes": [f"{m}/{a}" for m, a in self._axes]}

    # ---- worker side: taking items -----------------------------------------------------------
    def _axis(self, machine: str, axis: str) -> _Axis:
        key = (machine, axis)
        ax = self._axes.get(key)
        if ax is None:
            if len(self._axes) >= self.max_axes:
                raise ValueError(f"more than max_axes = {self.max_axes} axes: {machine}/{axis} is not recorded")
            info = self.infos.get(f"{machine}/{axis}", AxisInfo())
            cap = 2 * self.psd_window
            ax = self._axes[key] = _Axis(machine, axis, axis_root(machine, axis), info,
                                         FlagDigest(self.summary_s, self.max_event_lines),
                                         _Tail(cap), _Tail(cap), _Tail(cap), force=info.force)
        return ax

    @staticmethod
    def _check_times(kind: str, t: list[float]) -> None:
        if t and not (-TIME_LIMIT_S <= min(t) and max(t) <= TIME_LIMIT_S):
            raise ValueError(f"{kind}: time outside ±{TIME_LIMIT_S:g} s cannot be placed on Rerun's nanosecond "
                             f"timeline; block not recorded")

    def handle(self, item: Any) -> None:
        # O(1)-ish per block: the monitor offers one block per sample and axis; the conversion
        # work happens once per batch in _send_batches.
        if isinstance(item, S.SampleBlock):
            self._check_times("samples", item.t)
            ax = self._axis(item.machine, item.axis)
            ax.has_samples = True
            ax.samples.append(item)
        elif isinstance(item, S.EstimateBlock):
            self._check_times("estimates", item.t)
            self._axis(item.machine, item.axis).estimates.append(item)
        elif isinstance(item, tuple) and len(item) == 3 and isinstance(item[2], S.TruthBlock):
            self._check_times("truth", item[2].t)
            self._axis(str(item[0]), str(item[1])).truth.append(item[2])
        elif isinstance(item, _EventItem):
            ev = item.event
            if ev.level not in EVENT_LEVELS:
                raise ValueError(f"event level must be one of {', '.join(EVENT_LEVELS)}, got {ev.level!r}")
            self._check_times("event", [ev.t])
            self._axis(item.machine, item.axis).events.append(
                Event(ev.seq, ev.t, ev.level, ev.text[:MAX_EVENT_TEXT]))
        elif isinstance(item, _HealthItem):
            self._take_health(item)
        elif isinstance(item, S.AlarmEvent | S.ProcessView):
            self._take_process(item)
        else:
            raise TypeError(f"RerunSink accepts SampleBlock, EstimateBlock, (machine, axis, TruthBlock), AlarmEvent, "
                            f"ProcessView, events and health reports, got {type(item).__name__}")
        if isinstance(item, _EventItem | _HealthItem | S.AlarmEvent | S.ProcessView):
            self.count_written(1)  # (an event line is sent with the flags' lines; a report is one only on a change)

    def _take_process(self, item: S.AlarmEvent | S.ProcessView) -> None:
        from .rerun_events import alarm_line

        self._check_times("process", [item.t])
        ax = self._axis(item.machine, item.axis)
        if isinstance(item, S.ProcessView):
            ax.process = True
            ax.views.append(item)
        else:
            ax.events.append(Event(item.seq, item.t, "ERROR", alarm_line(item)[:MAX_EVENT_TEXT]))
            ax.alarms.append(item)

    def _take_health(self, item: _HealthItem) -> None:
        h = item.health
        state, reasons = h.get("state"), h.get("reasons", [])
        if state not in _HEALTH_LEVEL:
            raise ValueError(f"health 'state' must be ok, warn or alarm, got {state!r}")
        if not isinstance(reasons, list | tuple) or not all(isinstance(r, str) for r in reasons):
            raise ValueError("health 'reasons' must be a list of strings")
        seq, t = h.get("seq"), h.get("t")
        if not isinstance(seq, int) or isinstance(seq, bool) or not isinstance(t, int | float):
            raise ValueError("health 'seq' (integer) and 't' (s) are required")
        self._check_times("health", [float(t)])
        ax = self._axis(item.machine, item.axis)
        if state == ax.health or (ax.health is None and state == "ok"):
            ax.health = state
            return
        was, ax.health = ax.health or "ok", state
        why = "; ".join(reasons) if reasons else "no reason given"
        ax.events.append(Event(seq, float(t), _HEALTH_LEVEL[state],
                               f"HEALTH {was} → {state} at t = {float(t):.3f} s: {why}"[:MAX_EVENT_TEXT]))

    # ---- worker side: sending ------------------------------------------------------------------
    def _send(self, ax: _Axis, ent: str, seq: np.ndarray, t: np.ndarray, v: np.ndarray | None,
              mask: np.ndarray | None = None) -> None:
        import rerun as rr

        if v is None:
            return
        if mask is not None:
            if not mask.any():
                return
            seq, t, v = seq[mask], t[mask], v[mask]
        self.rec.send_columns(
            f"{ax.root}/{ent}",
            indexes=[rr.TimeColumn(L.SEQUENCE, sequence=seq), rr.TimeColumn(L.TIMELINE, duration=t)],
            columns=rr.Scalars.columns(scalars=v),
            strict=True,
        )

    def _style(self, ax: _Axis) -> None:
        """Static styling of every series of an axis (legend names, colours, aggregation)."""
        import rerun as rr

        for ent, s in L.series_styles(bool(ax.force is None or ax.force), ax.context, ax.process).items():
            self.rec.log(f"{ax.root}/{ent}", rr.SeriesLines(names=s.label, colors=s.colour, widths=s.width,
                                                            aggregation_policy=s.aggregation), static=True, strict=True)

    def _send_layout(self) -> None:
        views = tuple(L.AxisView(ax.root, m, a, bool(ax.force is None or ax.force), ax.context, ax.process)
                      for (m, a), ax in sorted(self._axes.items()))
        if views == self._layout:
            return
        for ax in self._axes.values():
            self._style(ax)
        self.rec.send_blueprint(L.blueprint_for(views, self.window, self.detail), make_active=True, make_default=True)
        self._layout = views

    def _send_samples(self, ax: _Axis, blocks: list) -> None:
        seq, t = _index(blocks)
        n = len(t)
        for name, ent in (("v_ref", "velocity/reference"), ("v_meas", "velocity/measured")):
            v = _column(blocks, name, n)
            self._send(ax, ent, seq, t, None if v is None else 1e3 * v)  # mm/s
        rpm = _column(blocks, "spindle_rpm", n)
        if rpm is not None:
            ok = rpm[np.isfinite(rpm) & (rpm > 0)]
            ax.rpm = float(np.median(ok)) if ok.size else ax.rpm

    def _send_truth(self, ax: _Axis, blocks: list) -> None:
        seq, t = _index(blocks)
        n = len(t)
        force = _column(blocks, "force", n)
        dyn = _column(blocks, "dynamometer", n)
        if ax.force is None or ax.force:
            self._send(ax, "force/actual", seq, t, force)
            if dyn is not None:
                dyn = -dyn  # measured along the axis; the disturbance force opposes motion
                self._send(ax, "force/dynamometer", seq, t, dyn)
            measured = dyn if dyn is not None else force
        else:
            measured = 1e6 * _column(blocks, "f", n)  # µm/s
            self._send(ax, "disturbance/actual", seq, t, measured)
        ax.actual.extend(seq, measured)

    def _send_estimates(self, ax: _Axis, blocks: list) -> None:
        seq, t = _index(blocks)
        n = len(t)
        col = lambda name: _column(blocks, name, n)  # noqa: E731
        # --- where each value belongs in time: filtered values describe sample j−1 ---
        Ts = ax.sample_period
        consecutive = seq[1:] == seq[:-1] + 1
        if n > 1 and consecutive.any():
            ax.Ts = float(np.median(np.diff(t)[consecutive]))
            Ts = ax.sample_period
        step = Ts if Ts is not None else math.nan
        t_prev = np.empty(n)
        t_prev[1:] = np.where(consecutive, t[:-1], t[1:] - step)
        t_prev[0] = ax.last_t if ax.last_seq is not None and ax.last_seq == seq[0] - 1 else t[0] - step
        seq_prev = seq - 1
        was = (seq_prev >= 0) & np.isfinite(t_prev)
        sp, tp = seq_prev[was], t_prev[was]
        # --- values in display units ---
        f, f_var, f_next, f_next_var = col("f"), col("f_var"), col("f_next"), col("f_next_var")
        force = col("force")
        if force is not None:
            est, var, pred = force, col("force_var"), col("force_next")
            with np.errstate(invalid="ignore", divide="ignore"):
                pred_var = f_next_var * var / f_var  # same gain b in both: (N per m/s)² = force_var/f_var
        else:
            est, var, pred, pred_var = 1e6 * f, 1e12 * f_var, 1e6 * f_next, 1e12 * f_next_var  # µm/s
        g = L.group_of(force is not None)
        sigma = _sqrt(var)
        self._send(ax, f"{g}/estimate", sp, tp, est[was])
        self._send(ax, f"{g}/upper", sp, tp, (est + 2.0 * sigma)[was])
        self._send(ax, f"{g}/lower", sp, tp, (est - 2.0 * sigma)[was])
        self._send(ax, "sigma/estimate", sp, tp, sigma[was])
        self._send(ax, f"{g}/prediction", seq, t, pred)
        self._send(ax, "sigma/prediction", seq, t, _sqrt(pred_var))
        if not ax.has_samples:
            self._send(ax, "velocity/measured", seq, t, 1e3 * col("v_meas"))
        self._send(ax, "velocity/predicted", seq, t, 1e3 * col("v_pred"))
        for name in S.CONTEXT_COLUMNS:  # NC program line, tool number of sample j, at j
            self._send(ax, f"context/{name}", seq, t, col(name))
        # --- dictionary ---
        size = _column(blocks, "dict_size", n, dtype=np.int64)
        removed = _column(blocks, "removed", n, dtype=np.int64)
        flags = _column(blocks, "flags", n, dtype=np.int64)
        self._send(ax, "dictionary/size", seq, t, size.astype(np.float64))
        if Ts is not None and Ts > 0:
            w = max(1, int(round(self.rate_window / Ts)))
            self._send(ax, "dictionary/pruned", seq, t, ax.pruned.counts(removed >= 0, w) / (w * Ts))
            self._send(ax, "dictionary/reduced", seq, t, ax.reduced.counts((flags & S.REDUCED) != 0, w) / (w * Ts))
        # --- events and spectra ---
        ax.events.extend(ax.digest.feed(seq, t, flags))
        self._spectra(ax, sp, col("residual")[was], est[was], t[was], seq[was])
        ax.last_seq, ax.last_t = int(seq[-1]), float(t[-1])

    def _spectra(self, ax: _Axis, sp: np.ndarray, residual: np.ndarray, est: np.ndarray, t: np.ndarray,
                 seq: np.ndarray) -> None:
        """Feed the spectra's windows; refresh the spectra at every ``psd_every``-th sample of data."""
        n = len(sp)
        k = np.arange(1, n + 1) + ax.since_psd
        lo = 0
        for c in np.flatnonzero(k % self.psd_every == 0):
            ax.residual.extend(sp[lo:c + 1], residual[lo:c + 1])
            ax.estimate.extend(sp[lo:c + 1], est[lo:c + 1])
            lo = c + 1
            self._log_spectra(ax, int(sp[c]), int(seq[c]), float(t[c]))
        ax.residual.extend(sp[lo:], residual[lo:])
        ax.estimate.extend(sp[lo:], est[lo:])
        ax.since_psd = int((ax.since_psd + n) % self.psd_every)

    def _log_spectra(self, ax: _Axis, hi: int, seq: int, t: float) -> None:
        import rerun as rr

        Ts = ax.sample_period
        if Ts is None or not Ts > 0:
            return
        fs = 1.0 / Ts
        spectra = {
            "residual_psd/residual": (ax.residual.window(hi, self.psd_window), L.SPECTRUM_COLOURS["residual"]),
            "disturbance_psd/estimate": (ax.estimate.window(hi, self.psd_window), L.SPECTRUM_COLOURS["estimate"]),
            "disturbance_psd/actual": (ax.actual.window(hi, self.psd_window), L.SPECTRUM_COLOURS["actual"]),
        }
        self.rec.set_time(L.SEQUENCE, sequence=seq)
        self.rec.set_time(L.TIMELINE, duration=t)
        top = 10.0
        logged = 0
        for ent, (x, colour) in spectra.items():
            res = psd_above_floor(x, fs, self.psd_nperseg)
            if res is None:
                continue
            freq, db = res
            top = max(top, float(db.max()))
            bin_width = freq[1] - freq[0] if freq.size > 1 else 1.0
            # the estimate's bars half as wide, drawn over the actual force's: both stay visible
            widths = np.full(freq.shape, bin_width * (0.5 if ent.endswith("estimate") else 1.0), dtype=np.float32)
            self.rec.log(f"{ax.root}/{ent}", rr.BarChart(db, abscissa=freq, widths=widths, color=colour), strict=True)
            logged += 1
        if not logged:
            return
        marks = marker_frequencies(fs, ax.info.period, ax.rpm, ax.info.teeth)
        width = np.float32(fs / 2 / 300)  # a thin line at any rate
        for label, colour in L.MARKER_COLOURS.items():
            hz = marks.get(label)
            path = f"{ax.root}/psd_markers/{label}"
            if hz is None:
                if ax.markers_said and label in dict(ax.markers_said):
                    self.rec.log(path, rr.Clear(recursive=False), strict=True)
                continue
            self.rec.log(path, rr.BarChart(np.full(hz.size, 1.05 * top), abscissa=hz,
                                           widths=np.full(hz.size, width, dtype=np.float32), color=colour), strict=True)
        said = tuple((k, round(float(v[0]), 1)) for k, v in sorted(marks.items()))
        if said != ax.markers_said:
            ax.markers_said = said
            ax.events.append(Event(seq, t, "INFO", f"spectrum markers from t = {t:.3f} s: "
                                   + _describe_markers(marks, ax)))
        self.psd_updates += 1

    def _log_events(self, ax: _Axis) -> None:
        import rerun as rr

        evs, ax.events = sorted(ax.events, key=lambda e: e.seq), []
        self.rec.send_columns(
            f"{ax.root}/events",
            indexes=[rr.TimeColumn(L.SEQUENCE, sequence=[e.seq for e in evs]),
                     rr.TimeColumn(L.TIMELINE, duration=[e.t for e in evs])],
            columns=rr.TextLog.columns(text=[e.text for e in evs], level=[e.level for e in evs]),
            strict=True,
        )
        self.events_logged += len(evs)

    def _attempt(self, fn, *args, items: int = 0) -> None:
        """Run one send step of ``items`` blocks: written when it worked, each counted lost (and a
        failure) when it did not."""
        try:
            fn(*args)
        except Exception as exc:  # noqa: BLE001 - one bad batch must not stop the recording
            self._tick_failed = True
            self._record_failure(exc)
            with self._lock:
                self.failures += max(0, items - 1)
            self.count_lost(items)
            return
        self.count_written(items)

    def _record_success(self) -> None:
        # a tick clears the failed state only when everything in it was sent and the output takes data
        if not (self.broken or self._flush_failures or self._tick_failed):
            super()._record_success()

    def _send_batches(self) -> None:
        if self.broken:
            lost = 0
            for ax in self._axes.values():
                lost += len(ax.samples) + len(ax.estimates) + len(ax.truth)
                ax.samples, ax.estimates, ax.truth, ax.events = [], [], [], []
            if lost:
                with self._lock:
                    self.failures += lost
                self.count_lost(lost)
            return
        for ax in self._axes.values():  # the estimates tell whether the axis is in newtons, has context
            if ax.estimates:
                ax.force = ax.estimates[-1].force is not None
                ax.context |= any(getattr(b, c) is not None for b in ax.estimates for c in S.CONTEXT_COLUMNS)
        self._attempt(self._send_layout)
        for ax in self._axes.values():
            for kind, send in (("samples", self._send_samples), ("truth", self._send_truth),
                               ("estimates", self._send_estimates)):
                blocks = getattr(ax, kind)
                if blocks:
                    setattr(ax, kind, [])
                    self._attempt(send, ax, blocks, items=len(blocks))
                    self.batches += 1
            if ax.views:
                views, ax.views = ax.views, []
                self._attempt(send_views, self.rec, ax.root, views)
            self._send_alarms(ax)
            if ax.events:
                self._attempt(self._log_events, ax)

    def _send_alarms(self, ax: _Axis, final: bool = False) -> None:
        """The markers of the alarms whose row's estimate was sent (all of them at the end)."""
        ready = [a for a in ax.alarms if final or (ax.last_seq is not None and a.seq <= ax.last_seq)]
        if ready:
            ax.alarms = [a for a in ax.alarms if a not in ready]
            self._attempt(send_alarms, self.rec, ax.root, ready, ax.alarm_kinds, lambda seq: _force_at(ax, seq))

    def _flush(self, timeout: float) -> None:
        """Flush the recording; one that does not finish in ``timeout`` s makes the sink ``degraded`` (Rerun
        still holds the data: a busy machine), ``broken_after`` in a row a failure and the output broken."""
        try:
            self.rec.flush(timeout_sec=timeout)
        except Exception as exc:  # noqa: BLE001 - Rerun raises RuntimeError when the writer is stuck
            self._flush_failures += 1
            why = f"a flush of the recording did not finish in {timeout:g} s ({self._flush_failures} in a row: {exc})"
            if self._flush_failures < self.broken_after:
                self.set_degraded(why)
                return
            self._record_failure(TimeoutError(why), f"TimeoutError: {why}")
            if not self.broken:
                self.broken = True
                self.log.say(logging.ERROR, "the Rerun output does not take data any more (%s); further blocks are "
                             "dropped and counted lost", why)
            return
        self._flush_failures = 0
        self.set_degraded(None)

    def tick(self, now: float) -> None:
        self._tick_failed = False
        if now - self._last_batch >= self.batch_interval:
            self._last_batch = now
            self._send_batches()
        if not self.broken and now - self._last_flush >= self.flush_interval:
            self._last_flush = now
            self._flush(self.flush_timeout)

    def finish(self) -> None:
        self._send_batches()
        if not self.broken:
            for ax in self._axes.values():
                ax.events.extend(ax.digest.close())
                if ax.since_psd and ax.last_seq is not None:
                    self._attempt(self._log_spectra, ax, ax.last_seq - 1, ax.last_seq, ax.last_t)
                self._send_alarms(ax, final=True)
                if ax.events:
                    self._attempt(self._log_events, ax)
            self._flush(max(10.0, self.flush_timeout))
        if self._flush_failures:  # Rerun's disconnect waits for ever on a writer that stopped
            self.broken = True
            if not self.failed:
                why = "the last flush of the recording did not finish: it may end without its footer"
                self._record_failure(TimeoutError(why), f"TimeoutError: {why}")
        if not self.broken:
            self.rec.disconnect()  # finalises the .rrd footer and stops the gRPC server


def _force_at(ax: _Axis, seq: int) -> float:
    """The filtered estimate of row ``seq`` (it describes sample seq − 1), from the spectra's window; NaN: gone."""
    keep = np.flatnonzero(ax.estimate.seq == seq - 1)
    return float(ax.estimate.val[keep[-1]]) if keep.size else math.nan


def _describe_markers(marks: dict[str, np.ndarray], ax: _Axis) -> str:
    parts = []
    if "1_over_psi" in marks:
        parts.append(f"1/ψ = {marks['1_over_psi'][0]:.1f} Hz (kernel period ψ = {1e3 * ax.info.period:.2f} ms)")
    if "tooth_passing" in marks:
        parts.append(f"tooth passing {marks['tooth_passing'][0]:.1f} Hz ({ax.rpm:.0f} rpm × {ax.info.teeth} teeth)"
                     + (f" and {len(marks['tooth_passing']) - 1} harmonic(s)" if len(marks["tooth_passing"]) > 1 else ""))
    if "spindle" in marks:
        parts.append(f"spindle {marks['spindle'][0]:.1f} Hz ({ax.rpm:.0f} rpm; teeth unknown)")
    return "; ".join(parts) if parts else "none (no kernel period, no spindle speed)"
