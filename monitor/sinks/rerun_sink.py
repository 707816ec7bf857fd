"""``RerunSink``: live and recorded Rerun view of the monitor (thesis Figure 4.8 per axis).

Sinks of the recording
----------------------
A private :class:`rerun.RecordingStream` (never the global one) with

* a :class:`rerun.FileSink` when ``rrd_path`` is given (``feedmon run --rrd FILE``),
* a :class:`rerun.GrpcServerSink` when ``serve_port`` is given: the *monitor*
  hosts a gRPC server that buffers up to ``memory_limit`` (oldest data dropped
  first) and a viewer connects whenever it likes with
  ``rerun rerun+http://<host>:<port>/proxy``. The sink never pushes to a viewer
  (``connect_grpc``/``spawn``): an absent viewer must not stall or break the monitor.

Without either, data go to Rerun's in-memory buffered sink (useful in tests only).

Entity paths (``<m>``/``<a>`` machine and axis)
---------------------------------------------
========================================  =====================================================
``/<m>/<a>/velocity/reference``            v_ref (SampleBlock)
``/<m>/<a>/velocity/measured``             v_meas (SampleBlock; from EstimateBlock if no samples)
``/<m>/<a>/velocity/predicted``            v_pred (one-step prediction)
``/<m>/<a>/disturbance/estimate``          f (m/s)
``/<m>/<a>/disturbance/upper|lower``       f ± 2σ, σ = √f_var
``/<m>/<a>/disturbance/truth``             TruthBlock.f (replayed simulated trials)
``/<m>/<a>/variance/f``                    f_var
``/<m>/<a>/dictionary/size``               dict_size
``/<m>/<a>/dictionary/removed``            index of the pruned element (markers, only when one was pruned)
``/<m>/<a>/dictionary/reduced``            marker at dict_size where the newest element was pruned at once
``/<m>/<a>/residual/value``                residual (m/s)
``/<m>/<a>/residual/psd``                  Welch PSD of the last ``psd_window`` residuals, dB re (m/s)²/Hz
                                           (BarChart, abscissa in Hz), refreshed every ``psd_interval`` s
========================================  =====================================================

Timelines: ``sample`` (sequence = sample ``seq``) and ``time`` (duration =
controller time in seconds).

Batching: ``handle`` only appends a block to its axis (O(1), ~6 µs per block);
every ``batch_interval`` (default 0.1 s, i.e. about 10×/s) the worker builds
NumPy columns and sends one ``send_columns`` chunk per entity. ``written`` in
:meth:`status` therefore counts blocks taken into a batch. ``scipy.signal`` is
imported with this module (it takes about a second; never on the worker).

The ``.rrd`` file is written with a footer (``rerun rrd verify`` needs it); the
footer index is kept in memory until the file is closed, which grows with the
number of chunks on very long runs.
"""

from __future__ import annotations

import math
import os
import uuid
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from itertools import chain
from typing import Any

import numpy as np
from scipy.signal import welch  # imported here, not on the worker: scipy.signal takes ~1 s to import

from feedio import schema as S

from .queued import QueuedSink

__all__ = ["RerunSink", "axis_blueprint", "blueprint_for"]

# colours (RGB): measured / predicted / reference, estimate / band / truth
_C = {
    "measured": (31, 119, 180),
    "predicted": (255, 127, 14),
    "reference": (150, 150, 150),
    "estimate": (214, 39, 40),
    "band": (255, 152, 150),
    "truth": (44, 160, 44),
    "variance": (148, 103, 189),
    "size": (23, 190, 207),
    "removed": (214, 39, 40),
    "reduced": (127, 127, 127),
    "residual": (140, 86, 75),
    "psd": (140, 86, 75),
}

# entity -> (legend name, colour key, kind)  kind: "line" | "points"
_SERIES: dict[str, tuple[str, str, str]] = {
    "velocity/reference": ("v_ref", "reference", "line"),
    "velocity/measured": ("v_meas", "measured", "line"),
    "velocity/predicted": ("v_pred", "predicted", "line"),
    "disturbance/estimate": ("f", "estimate", "line"),
    "disturbance/upper": ("f + 2σ", "band", "line"),
    "disturbance/lower": ("f − 2σ", "band", "line"),
    "disturbance/truth": ("f true", "truth", "line"),
    "variance/f": ("var f", "variance", "line"),
    "dictionary/size": ("size", "size", "line"),
    "dictionary/removed": ("removed index", "removed", "points"),
    "dictionary/reduced": ("newest pruned", "reduced", "points"),
    "residual/value": ("residual", "residual", "line"),
}


def axis_blueprint(machine: str, axis: str):
    """The per-axis layout (Figure 4.8): velocity, disturbance ±2σ (+truth), variance,
    dictionary, residual and its PSD."""
    import rerun.blueprint as rrb

    o = f"/{machine}/{axis}"
    return rrb.Vertical(
        rrb.TimeSeriesView(origin=f"{o}/velocity", name=f"{axis}: measured vs predicted velocity (m/s)"),
        rrb.TimeSeriesView(origin=f"{o}/disturbance", name=f"{axis}: disturbance estimate ±2σ (m/s)"),
        rrb.TimeSeriesView(origin=f"{o}/variance", name=f"{axis}: variance of f ((m/s)²)"),
        rrb.TimeSeriesView(origin=f"{o}/dictionary", name=f"{axis}: dictionary (size, removals)"),
        rrb.Horizontal(
            rrb.TimeSeriesView(origin=f"{o}/residual", contents="$origin/value", name=f"{axis}: residual (m/s)"),
            rrb.BarChartView(origin=f"{o}/residual/psd", name=f"{axis}: residual PSD (dB re (m/s)²/Hz vs Hz)"),
            column_shares=[2, 1],
        ),
        row_shares=[2, 2, 1, 1, 1.5],
        name=f"{machine}/{axis}",
    )


def blueprint_for(axes: Sequence[tuple[str, str]]):
    """Blueprint with one tab per axis (one axis: just its layout)."""
    import rerun.blueprint as rrb

    views = [axis_blueprint(m, a) for m, a in axes]
    if not views:
        root = rrb.Vertical(rrb.TextDocumentView(origin="/", name="waiting for data"))
    elif len(views) == 1:
        root = views[0]
    else:
        root = rrb.Tabs(*views)
    return rrb.Blueprint(root, rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
                         rrb.TimePanel(state="collapsed"))


@dataclass
class _Axis:
    machine: str
    axis: str
    residual: deque  # last psd_window residuals
    has_samples: bool = False
    samples: list = field(default_factory=list)  # blocks waiting for the next batch
    estimates: list = field(default_factory=list)
    truth: list = field(default_factory=list)
    Ts: float | None = None  # median sampling period seen
    last_t: float | None = None
    last_seq: int = 0
    new_residuals: int = 0


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


class RerunSink(QueuedSink):
    """Queued Rerun logger; see the module docstring.

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
    batch_interval:
        seconds between ``send_columns`` batches (≈ 10×/s).
    psd_window, psd_interval, psd_nperseg:
        residual PSD over the last ``psd_window`` samples, every ``psd_interval`` s, Welch segments of ``psd_nperseg``.
    """

    def __init__(
        self,
        rrd_path: str | os.PathLike | None = None,
        serve_port: int | None = None,
        memory_limit: str = "25%",
        *,
        serve_host: str = "127.0.0.1",
        application_id: str = "feedmon",
        recording_id: str | None = None,
        batch_interval: float = 0.1,
        psd_window: int = 4096,
        psd_interval: float = 3.0,
        psd_nperseg: int = 512,
        maxsize: int = 4096,
        name: str = "rerun",
    ) -> None:
        import rerun as rr

        from .rerun_process import check_outputs

        check_outputs(rrd_path, serve_port)
        if psd_window < 16:
            raise ValueError(f"psd_window must be at least 16 samples, got {psd_window}")
        self.rrd_path = None if rrd_path is None else os.fspath(rrd_path)
        self.serve_port = None if serve_port is None else int(serve_port)
        self.batch_interval = float(batch_interval)
        self.psd_window = int(psd_window)
        self.psd_interval = float(psd_interval)
        self.psd_nperseg = int(psd_nperseg)
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
        self._last_psd = 0.0
        self.batches = 0
        self.psd_updates = 0
        self._blueprint_axes: tuple = ()
        super().__init__(maxsize, name=name, tick_interval=min(0.05, self.batch_interval / 2))

    # ---- producer helpers ----------------------------------------------------------------
    def offer_truth(self, machine: str, axis: str, block: S.TruthBlock) -> bool:
        """Queue a :class:`TruthBlock` of ``machine/axis`` (plotted as ``disturbance/truth``)."""
        return self.offer((machine, axis, block))

    def extra_status(self) -> dict[str, Any]:
        return {"rrd_path": self.rrd_path, "server_uri": self.server_uri, "batches": self.batches,
                "psd_updates": self.psd_updates, "axes": [f"{m}/{a}" for m, a in self._axes]}

    # ---- worker side -----------------------------------------------------------------------
    def _axis(self, machine: str, axis: str) -> _Axis:
        key = (machine, axis)
        ax = self._axes.get(key)
        if ax is None:
            import rerun as rr

            ax = self._axes[key] = _Axis(machine, axis, residual=deque(maxlen=self.psd_window))
            for ent, (label, colour, kind) in _SERIES.items():  # static styling of every series
                style = (rr.SeriesLines(names=label, colors=_C[colour], widths=1.5) if kind == "line"
                         else rr.SeriesPoints(names=label, colors=_C[colour], markers="circle", marker_sizes=3.0))
                self.rec.log(f"/{machine}/{axis}/{ent}", style, static=True, strict=True)
            self._send_blueprint()
        return ax

    def _send_blueprint(self) -> None:
        axes = tuple(sorted(self._axes))
        if axes != self._blueprint_axes:
            self.rec.send_blueprint(blueprint_for(axes), make_active=True, make_default=True)
            self._blueprint_axes = axes

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
            f"/{ax.machine}/{ax.axis}/{ent}",
            indexes=[rr.TimeColumn("sample", sequence=seq), rr.TimeColumn("time", duration=t)],
            columns=rr.Scalars.columns(scalars=v),
            strict=True,
        )
        self.batches += 1

    def handle(self, item: Any) -> None:
        # O(1) per block: the hot path of the monitor offers one block per sample and axis;
        # all conversion work happens once per batch in _send_batches.
        if isinstance(item, S.SampleBlock):
            ax = self._axis(item.machine, item.axis)
            ax.has_samples = True
            ax.samples.append(item)
        elif isinstance(item, S.EstimateBlock):
            self._axis(item.machine, item.axis).estimates.append(item)
        elif isinstance(item, tuple) and len(item) == 3 and isinstance(item[2], S.TruthBlock):
            self._axis(str(item[0]), str(item[1])).truth.append(item[2])
        else:
            raise TypeError(
                f"RerunSink accepts SampleBlock, EstimateBlock or (machine, axis, TruthBlock), got {type(item).__name__}"
            )

    def _send_samples(self, ax: _Axis, blocks: list) -> None:
        seq, t = _index(blocks)
        self._send(ax, "velocity/reference", seq, t, _column(blocks, "v_ref", len(t)))
        self._send(ax, "velocity/measured", seq, t, _column(blocks, "v_meas", len(t)))

    def _send_truth(self, ax: _Axis, blocks: list) -> None:
        seq, t = _index(blocks)
        self._send(ax, "disturbance/truth", seq, t, _column(blocks, "f", len(t)))

    def _send_estimates(self, ax: _Axis, blocks: list) -> None:
        seq, t = _index(blocks)
        n = len(t)
        if not ax.has_samples:
            self._send(ax, "velocity/measured", seq, t, _column(blocks, "v_meas", n))
        self._send(ax, "velocity/predicted", seq, t, _column(blocks, "v_pred", n))
        f = _column(blocks, "f", n)
        var = _column(blocks, "f_var", n)
        with np.errstate(invalid="ignore"):
            two_sigma = 2.0 * np.sqrt(np.where(var >= 0, var, np.nan))
        self._send(ax, "disturbance/estimate", seq, t, f)
        self._send(ax, "disturbance/upper", seq, t, f + two_sigma)
        self._send(ax, "disturbance/lower", seq, t, f - two_sigma)
        self._send(ax, "variance/f", seq, t, var)
        size = _column(blocks, "dict_size", n, dtype=np.int64).astype(np.float64)
        removed = _column(blocks, "removed", n, dtype=np.int64)
        flags = _column(blocks, "flags", n, dtype=np.int64)
        self._send(ax, "dictionary/size", seq, t, size)
        self._send(ax, "dictionary/removed", seq, t, removed.astype(np.float64), mask=removed >= 0)
        self._send(ax, "dictionary/reduced", seq, t, size, mask=(flags & S.REDUCED) != 0)
        res = _column(blocks, "residual", n)
        self._send(ax, "residual/value", seq, t, res)
        ax.residual.extend(res.tolist())
        ax.new_residuals += n
        # sampling period for the PSD: consecutive samples only (gaps excluded)
        if n > 1:
            ok = np.diff(seq) == 1
            if ok.any():
                ax.Ts = float(np.median(np.diff(t)[ok]))
        ax.last_t, ax.last_seq = float(t[-1]), int(seq[-1])

    def tick(self, now: float) -> None:
        if now - self._last_batch >= self.batch_interval:
            self._last_batch = now
            self._send_batches()
        if now - self._last_psd >= self.psd_interval:
            self._last_psd = now
            self._update_psd()

    def _send_batches(self) -> None:
        for ax in self._axes.values():
            for kind, send in (("samples", self._send_samples), ("estimates", self._send_estimates),
                               ("truth", self._send_truth)):
                blocks = getattr(ax, kind)
                if not blocks:
                    continue
                setattr(ax, kind, [])
                send(ax, blocks)

    def _update_psd(self) -> None:
        import rerun as rr

        for ax in self._axes.values():
            if ax.new_residuals == 0 or ax.last_t is None:
                continue
            x = np.asarray(ax.residual, dtype=np.float64)
            x = x[np.isfinite(x)]
            if x.size < 16:
                continue
            if ax.Ts is None or not (ax.Ts > 0 and math.isfinite(ax.Ts)):
                continue
            fs = 1.0 / ax.Ts
            nperseg = min(self.psd_nperseg, x.size)
            freq, pxx = welch(x, fs=fs, nperseg=nperseg, detrend="constant")
            db = 10.0 * np.log10(np.maximum(pxx, 1e-300))
            self.rec.set_time("sample", sequence=ax.last_seq)
            self.rec.set_time("time", duration=ax.last_t)
            widths = np.full(freq.shape, freq[1] - freq[0] if freq.size > 1 else 1.0, dtype=np.float32)
            self.rec.log(f"/{ax.machine}/{ax.axis}/residual/psd",
                         rr.BarChart(db, abscissa=freq, widths=widths, color=_C["psd"]), strict=True)
            ax.new_residuals = 0
            self.psd_updates += 1

    def finish(self) -> None:
        try:
            self._send_batches()
            self._update_psd()
        finally:
            self.rec.flush(timeout_sec=10.0)
            self.rec.disconnect()  # finalises the .rrd footer and stops the gRPC server
