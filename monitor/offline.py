"""The offline twin of the monitor (``feedmon run --from``): a recorded trial through the same
:class:`~monitor.pipeline.Pipeline`, as fast as the machine goes.

How the work is spread
----------------------
One axis (``jobs=1``): three threads of this process — a reader (MCAP chunks, zstd, CRCs, JSON
decoding), the estimator (this thread: :meth:`Pipeline.estimate`, whose compiled tracker loop
releases the interpreter lock) and a writer (JSON encoding, the per-sample scalars, MCAP records,
zstd). The writer runs the writes in the order the input came, so the file is the one that
writing inline would give.

Several axes (``jobs`` > 1, default: as many processes as cores, at most one per axis): the axes
are shared out round-robin among child processes (``spawn``); each reads the trial (only its axes'
channels are decoded), estimates its axes and encodes everything it will write — block messages
as the JSON :func:`feedio.schema.encode` writes, the per-sample scalars as finished MCAP records —
and sends them to this process through a pipe (length-prefixed frames of bytes and NumPy
columns, no pickling). This process merges the children's streams in the order of the one-process
run — by the time of the input block's last sample, then the axis' position, then the block's
position in its axis (the key :func:`_merged_blocks` orders by) — and writes them with one
:class:`~feedio.mcapio.TrialWriter`, so the chunks (by controller time) and every byte of the file
are those of ``jobs=1``. At the end each child sends its axes' counters and tracker states (NumPy
arrays, checked like a saved state when restored), so the :class:`AxisRuntime` objects passed in
end as after a one-process run. Axes whose estimator does not start fresh from its model file
(a restored tracker, other estimator options) are estimated in this process (``jobs`` is then 1).

Per input item the work is the same in both cases (:class:`_Encoder`): a truth block is copied
and paired with the rows it belongs to; a samples block is copied, estimated, its estimates
written, and the scalars that became complete written (:class:`~feedio.scalars.ScalarsPairer`);
at the end the scalars still waiting are written, axis by axis in the order the axes first
reached the pairer. The health reports of a block (:attr:`~monitor.pipeline.Estimated.health`)
are written on ``/<machine>/<axis>/health`` right after the estimates and scalars of their block,
each stamped at its sample (the block's log time minus the controller time from the report to the
block's last sample) — in :meth:`_Encoder.samples`, the one place both paths go through.
"""

from __future__ import annotations

import enum
import heapq
import io
import json
import math
import multiprocessing
import os
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np

from feedio import schema as S
from feedio.limits import DEFAULT, InputLimits
from kernels.errors import ParameterError

from .axes import AxisRuntime
from .input_health import InputHealthSettings
from .pipeline import Estimated, Pipeline
from .state import learned_snapshot
from .status import install_log_format, log_format

__all__ = ["OfflineResult", "run_offline"]


@dataclass
class OfflineResult:
    output: str
    samples: int
    estimates: int
    truth_blocks: int
    seconds: float
    axes: list[str]
    skipped_axes: list[str]
    jobs: int = 1
    health_reports: int = 0
    #: the wear monitor's report at the end of the run, one line per section judged (empty: no wear monitor)
    wear_report: list[str] = field(default_factory=list)
    #: why the wear history could not be saved (None: saved, or no wear monitor)
    wear_error: str | None = None

    @property
    def rate(self) -> float:
        return self.samples / self.seconds if self.seconds > 0 else math.inf


def _merged_blocks(path: str, axes: list[str], index: dict[str, int] | None = None
                   ) -> Iterator[tuple[tuple[float, int, int], str, str, int, Any]]:
    """``(key, axis_name, kind, log_time, block)`` of several axes merged by ``key`` = (time of the
    block's last sample, the axis' position in ``index`` (default: in ``axes``), the block's
    position in its axis' stream), from one pass over the file (:func:`feedio.mcapio.iter_axes`)."""
    from feedio.mcapio import iter_axes

    index = index or {a: i for i, a in enumerate(axes)}
    streams = iter_axes(path, axes, kinds=("samples", "truth"))

    def one(name: str):
        idx = index[name]
        for j, (kind, lt, b) in enumerate(streams[name]):
            yield (float(b.t[-1]), idx, j), name, kind, lt, b

    yield from heapq.merge(*(one(a) for a in axes), key=lambda x: x[0])


# ---- the work per input item (both paths) -----------------------------------------------------
#: kinds of block channels, as sent by the children
_KINDS = ("samples", "truth", "disturbance")


class _Encoder:
    """What one input item puts into the output, encoded: block messages ``("B", kind, machine, axis,
    data, seq, n, t0, t1, log_time)``, per-sample scalars ``("C", machine, axis, records, sizes,
    log_ns, t, seq)`` (:meth:`feedio.scalars.ScalarsBatch.records`, channel id set by the writer) and
    health reports ``("H", machine, axis, data, log_time)`` (the JSON of a :class:`~feedio.schema.Health`)."""

    def __init__(self, has_truth: set[tuple[str, str]]) -> None:
        from feedio.scalars import ScalarsPairer

        self.pairer = ScalarsPairer(expect_truth=has_truth)
        self.has_truth = has_truth
        self.touched: dict[str, tuple] = {}  # axis name -> key of the first item that reached the pairer

    @staticmethod
    def _scalars(batches) -> list[tuple]:
        out = []
        for b in batches:
            records, sizes = b.records(0)
            out.append(("C", b.machine, b.axis, records, sizes, b.log_ns, b.t, b.seq))
        return out

    def truth(self, key: tuple, name: str, block: S.TruthBlock, lt: int) -> list[tuple]:
        m, a = name.split("/", 1)
        out = [("B", "truth", m, a, S.encode(block), block.seq, len(block.t), float(block.t[0]), float(block.t[-1]),
                lt)]
        if (m, a) in self.has_truth:
            self.touched.setdefault(name, key)
            out += self._scalars(self.pairer.add_truth(m, a, block))
        return out

    def samples(self, key: tuple, block: S.SampleBlock, lt: int, res: Estimated) -> list[tuple]:
        m, a = block.machine, block.axis
        n = len(block.t)
        out = [("B", "samples", m, a, S.encode(block), block.seq, n, float(block.t[0]), float(block.t[-1]), lt)]
        est = res.est
        if est is not None:
            out.append(("B", "disturbance", m, a, est.json(), est.seq, len(est), float(est.t[0]),
                        float(est.t[-1]), lt))
            self.touched.setdefault(f"{m}/{a}", key)
            out += self._scalars(self.pairer.add_rows(m, a, est.seq, est.t, lt, **est.scalar_columns()))
        t_end = float(block.t[-1])
        for h in res.health:  # stamped at its sample: the block's log time minus the time to its end
            out.append(("H", m, a, S.encode(h), max(0, lt - round((t_end - h.t) * 1e9))))
        for e in res.alarms:  # likewise
            out.append(("A", m, a, S.encode(e), max(0, lt - round((t_end - e.t) * 1e9))))
        return out

    def drain(self) -> dict[str, list[tuple]]:
        """The scalars still waiting, per axis name."""
        per: dict[str, list[tuple]] = {}
        for entry in self._scalars(self.pairer.drain()):
            per.setdefault(f"{entry[1]}/{entry[2]}", []).append(entry)
        return per


def _write(w, entries: list[tuple]) -> None:
    for e in entries:
        if e[0] == "B":
            _, kind, m, a, data, seq, n, t0, t1, lt = e
            w.write_encoded(m, a, kind, data, seq=seq, n=n, t0=t0, t1=t1, log_time=lt)
        elif e[0] == "C":
            _, m, a, records, sizes, log_ns, t, seq = e
            w.write_scalar_records(m, a, records, sizes, log_ns, t, seq)
        elif e[0] == "A":  # a process alarm
            w.write_alarm(S.decode_alarm(e[3]), log_time=e[4])
        else:  # "H": the report is checked again by the writer (bounds of seq and t)
            w.write_health(S.decode_health(e[3]), log_time=e[4])


# ---- the entry point ------------------------------------------------------------------------------
def run_offline(trial: str | os.PathLike, output: str | os.PathLike,
                axes: dict[tuple[str, str], AxisRuntime], *, limits: InputLimits = DEFAULT,
                jobs: int | None = None, input_health: InputHealthSettings | None = None,
                monitors=None) -> OfflineResult:
    """Estimate a recorded trial without Zenoh, as fast as the machine goes.

    Every samples block of the axes that have a model goes through the same
    :class:`Pipeline` as in the live monitor; samples and estimates are written
    with :class:`~feedio.mcapio.TrialWriter` (the writer of the MCAP sink) and the
    truth blocks are copied through, each with the log time its input block had (the
    estimates of a block get the log time of its samples), and so do the per-sample
    ``disturbance/scalars`` (:class:`~feedio.scalars.ScalarsPairer`, stamped from those
    log times) and the health reports (``/<machine>/<axis>/health``, stamped at their sample).
    The trial's own metadata (with its truth and start time) is kept, with the model file and
    hash added to the provenance details. Chunks follow controller time only, so the same input
    gives the same bytes — whatever ``jobs`` is.

    ``jobs``: processes for a trial with several modelled axes (None: one per core, at most one
    per axis; 1: this process only). See the module docstring. ``input_health``: thresholds of the
    input-health verdict merged into the health reports (:mod:`monitor.input_health`). ``monitors``: the
    process monitors' settings (:class:`monitor.process_monitor.MonitorSettings`; None or not enabled:
    none run); their alarms go on ``/<machine>/<axis>/alarm``, stamped at their row. With a wear history
    (``monitors.wear.history``) the run is one part: its section statistics are appended, its ``wear`` alarms
    stamped at the axis' last block, and it runs in this process (one history, one writer).
    """
    from feedio.mcapio import OpenTrial, TrialWriter

    trial, output = os.fspath(trial), os.fspath(output)
    if os.path.abspath(trial) == os.path.abspath(output):
        raise ValueError(f"output {output!r} would overwrite the input trial")
    if jobs is not None and (isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1):
        raise ValueError(f"jobs must be an integer ≥ 1, got {jobs!r}")
    with OpenTrial(trial) as f:
        present = f.axes()
        metas = {key: f.meta(*key) for key in present if key in axes}
        starts = {f.start_ns(*key) for key in metas}
        has_truth = {(m, a) for (m, a) in metas if f"/{m}/{a}/truth" in f.channels}
    missing = [f"{m}/{a}" for (m, a) in axes if (m, a) not in present]
    if missing:
        raise ParameterError(f"{trial} has no axis {', '.join(missing)} (axes present: "
                             f"{', '.join(f'{m}/{a}' for m, a in present) or 'none'}); check the model files of axes",
                             "axes")
    skipped = [f"{m}/{a}" for (m, a) in present if (m, a) not in axes]
    out_metas = []
    for key, meta in metas.items():
        ax = axes[key]
        if ax.model.form != meta.form:
            raise ValueError(f"axis {key[0]}/{key[1]}: model form {ax.model.form!r} but the trial is {meta.form!r}")
        if not math.isclose(float(ax.model.Ts), float(meta.Ts), rel_tol=0.01):
            raise ValueError(f"axis {key[0]}/{key[1]}: the model file has Ts = {float(ax.model.Ts):.6g} s but the trial "
                             f"is sampled at Ts = {float(meta.Ts):.6g} s; β is a discrete-time model of one sampling "
                             "rate: identify the model on a trial at this rate (feedmon identify)")
        details = dict(meta.provenance.details)
        details.update(estimated_by="feedmon run --from", model_file=ax.status.model_path,
                       model_sha256=ax.status.model_sha256, tracker_state=ax.status.state)
        out_metas.append(msgspec.structs.replace(meta, provenance=msgspec.structs.replace(meta.provenance,
                                                                                           details=details)))
    names = [f"{m}/{a}" for (m, a) in metas]
    jobs = min(os.cpu_count() or 1, len(names)) if jobs is None else min(jobs, max(1, len(names)))
    if jobs > 1 and threading.active_count() > 1 and not all(_fresh(axes[key]) for key in metas):
        jobs = 1  # a spawned child builds its estimators from the model files: only when that is what they are
    if getattr(monitors, "enabled", False) and monitors.wear.history is not None:
        jobs = 1  # the wear history is one file, updated by the process that judged every axis
    start = min((s for s in starts if s is not None), default=0)  # files without one: log times as they were
    t0 = time.perf_counter()
    wear: dict[str, Any] = {"report": [], "error": None}
    built = _monitors(axes, monitors) if jobs == 1 else None  # a bad reference or history: refused before any output
    with TrialWriter(output, out_metas, start=start) as w:
        if jobs > 1:
            counts = _run_children(trial, w, names, {n: axes[k] for n, k in zip(names, metas)}, has_truth, limits,
                                   jobs, input_health, monitors)
        else:
            counts = _run_here(trial, w, names, axes, has_truth, limits, input_health, built, wear)
    seconds = time.perf_counter() - t0
    return OfflineResult(output, counts["samples"], counts["estimates"], counts["truth"], seconds, names, skipped,
                         jobs, counts["health"], wear["report"], wear["error"])


def _run_here(trial: str, w, names: list[str], axes, has_truth, limits, input_health, process=None,
              wear: dict[str, Any] | None = None) -> dict[str, int]:
    """``jobs=1``: reader thread → estimation here (``process``: the built process monitors) → writer thread
    (encoding and writing); at the end the wear monitor's alarms (stamped at the axis' last block), its report
    and a failure to save into ``wear``."""
    pipe = Pipeline(axes, limits=limits, input_health=input_health, monitors=process)
    enc = _Encoder(has_truth)
    last_lt: dict[tuple[str, str], int] = {}
    with _WriterThread() as out:
        counts = _estimate_items(_merged_blocks(trial, names), pipe, enc, out, lambda _key, entries: _write(w, entries),
                                 last_lt)
        if pipe.process is not None and pipe.process.wear is not None:
            when = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
            ends = pipe.finish(os.path.basename(trial), when)
            wear["report"] += pipe.process.wear.report
            wear["error"] = pipe.process.wear.error
            entries = [("A", m, a, S.encode(e), last_lt.get((m, a), 0)) for (m, a), alarms in ends.items()
                       for e in alarms]
            out.put(lambda: _write(w, entries))
        out.put(lambda: _write_drain(w, enc.drain(), {n: enc.touched.get(n) for n in names}))
    return counts


def _estimate_items(items: Iterator, pipe: Pipeline, enc: _Encoder, out: _WriterThread,
                    emit: Callable[[tuple, list[tuple]], None], last_lt: dict | None = None) -> dict[str, int]:
    """The work per input item of both paths: estimate each samples block (here, on the reader's
    items), and hand what the item puts into the output (:class:`_Encoder`) to ``emit(key, entries)``
    on the writer thread. A refused block (too long, no model) is counted by the pipeline, not
    copied, as live. Returns the counts (samples estimated, estimates, truth blocks, health reports);
    ``last_lt`` gets each axis' last log time."""
    counts = {"samples": 0, "estimates": 0, "truth": 0, "health": 0}
    for key, name, kind, lt, block in _prefetch(items):
        if kind == "truth":
            counts["truth"] += 1
            out.put(lambda k=key, n=name, b=block, t=lt: emit(k, enc.truth(k, n, b, t)), _held(block))
            continue
        res = pipe.estimate(block)
        if res.ax is None:
            continue
        counts["samples"] += len(block.t)
        if res.est is not None:
            counts["estimates"] += len(res.est)
        counts["health"] += len(res.health)
        if last_lt is not None:
            last_lt[res.ax.key] = lt
        out.put(lambda k=key, b=block, t=lt, r=res: emit(k, enc.samples(k, b, t, r)), _held(block, res))
    return counts


def _monitors(axes, settings):
    """The process monitors of ``axes`` (None when ``settings`` is None or not enabled)."""
    if settings is None:
        return None
    from .process_monitor import build_monitors
    from .process_monitor.settings import MonitorSettings

    if isinstance(settings, dict):
        settings = msgspec.convert(settings, MonitorSettings)
    return build_monitors(axes, settings)


def _write_drain(w, per_axis: dict[str, list[tuple]], touched: dict[str, tuple | None]) -> None:
    """The scalars still waiting, axis by axis in the order the axes first reached the pairer."""
    for name in sorted((n for n in per_axis if touched.get(n) is not None), key=lambda n: touched[n]):
        _write(w, per_axis[name])


def _fresh(ax: AxisRuntime) -> bool:
    """The estimator is what a spawned child process builds from the model file: fresh, default
    options, the model as the file has it (no ``--config`` override of its settings)."""
    from kernels import online

    from .model_file import load_model

    e = ax.estimator
    if not (e.trained == 0 and e.tracker.size == 0 and not e.counters and e.warmup == ax.model.tracker.budget
            and e.stale_detection and e.reorder_window == online.REORDER_WINDOW and ax.status.state == "fresh"
            and os.path.isfile(ax.status.model_path)):
        return False
    try:
        return load_model(ax.status.model_path) == ax.model
    except (OSError, ValueError):
        return False


class _Fifo:
    """A FIFO between two threads, bounded in items and in bytes (each item's ``size``; an item
    larger than the bound passes alone): what waits in it never grows past the bounds, whatever
    the trial holds. ``put`` gives up (False) once ``stop`` is set."""

    def __init__(self, items: int, max_bytes: int) -> None:
        self.items, self.max_bytes = int(items), int(max_bytes)
        self._q: deque = deque()
        self._bytes = 0
        self._cv = threading.Condition()

    def put(self, item: Any, size: int, stop: threading.Event | None = None) -> bool:
        with self._cv:
            while self._q and (len(self._q) >= self.items or self._bytes + size > self.max_bytes):
                if stop is not None and stop.is_set():
                    return False
                self._cv.wait(0.1)
            self._q.append((item, size))
            self._bytes += size
            self._cv.notify_all()
            return True

    def get(self) -> Any:
        with self._cv:
            while not self._q:
                self._cv.wait()
            item, size = self._q.popleft()
            self._bytes -= size
            self._cv.notify_all()
            return item


def _held(block, res: Estimated | None = None) -> int:
    """About the bytes a queued item holds: the decoded block (:func:`feedio.mcapio.held_bytes`) and,
    for a samples block, its estimate rows (float64 and int64 columns) and health reports."""
    from feedio.mcapio import held_bytes

    n = held_bytes(block)
    if res is not None and res.est is not None:
        e = res.est
        n += e.rows.nbytes + e.irows.nbytes + e.t.nbytes + e.v_meas.nbytes + (0 if e.force is None else e.force.nbytes)
    return n + 1024 * len(res.health if res is not None else ())


#: bytes of decoded blocks the reader thread may hold ahead of the estimator (:func:`_prefetch`)
PREFETCH_BYTES = 16 * 2**20
#: bytes of blocks and their results waiting for the writer thread (:class:`_WriterThread`)
WRITE_BEHIND_BYTES = 32 * 2**20


def _prefetch(items: Iterator, depth: int = 64, max_bytes: int = PREFETCH_BYTES) -> Iterator:
    """Iterate ``items`` (``(key, name, kind, log_time, block)``) on a second thread (MCAP reading,
    zstd decompression and JSON decoding overlap with the estimation), at most ``depth`` items and
    ``max_bytes`` of blocks (:func:`feedio.mcapio.held_bytes`) ahead; exceptions are re-raised
    here, order is kept."""
    from feedio.mcapio import held_bytes

    q = _Fifo(depth, max_bytes)
    done = object()
    stop = threading.Event()

    def run() -> None:
        try:
            for item in items:
                if stop.is_set() or not q.put((None, item), held_bytes(item[-1]), stop):
                    return
        except BaseException as exc:  # noqa: BLE001 - re-raised in the consumer
            q.put((exc, None), 0)
            return
        q.put((None, done), 0)

    th = threading.Thread(target=run, name="offline-reader", daemon=True)
    th.start()
    try:
        while True:
            exc, item = q.get()
            if exc is not None:
                raise exc
            if item is done:
                return
            yield item
    finally:
        stop.set()
        th.join()


class _WriterThread:
    """Runs callables on a second thread, in order (the writes of :func:`run_offline`, or the
    encoding and sending of a child), at most ``depth`` of them and ``max_bytes`` of what they hold
    (the ``size`` given to :meth:`put`) waiting.

    The tracker loop (``@njit(nogil=True)``) and zstd compression both release the GIL, so
    estimating and encoding/compressing/writing overlap on two cores; one thread and a FIFO
    keep the output byte-identical to writing inline. An error is raised in the caller.
    """

    def __init__(self, depth: int = 256, max_bytes: int = WRITE_BEHIND_BYTES) -> None:
        self._q = _Fifo(depth, max_bytes)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="offline-writer", daemon=True)

    def __enter__(self) -> _WriterThread:
        self._thread.start()
        return self

    def put(self, fn: Callable[[], Any], size: int = 0) -> None:
        if self._error is not None:
            raise self._error
        self._q.put(fn, size)

    def _run(self) -> None:
        while True:
            fn = self._q.get()
            if fn is None:
                return
            if self._error is None:
                try:
                    fn()
                except BaseException as exc:  # noqa: BLE001 - re-raised in the caller
                    self._error = exc

    def __exit__(self, *exc) -> None:
        self._q.put(None, 0)
        self._thread.join()
        if self._error is not None and exc[0] is None:
            raise self._error


# ---- several processes ------------------------------------------------------------------------------
class _Frame(bytes, enum.Enum):
    """Frames child → parent, one pipe message holding several: the tag byte, then the frame."""

    ITEM = b"I"  #: key (t f8, axis i4, j i8), entry count u4, entries
    DRAIN = b"D"  #: axis i4, key present u1 (+ key), entry count u4, entries
    FINAL = b"F"  #: JSON length u4, JSON (counters), then per axis: npz length u8, npz bytes (tracker state)
    ERROR = b"E"  #: JSON {"type", "message"}


class _Entry(bytes, enum.Enum):
    """The entries of an item or a drain: the tag byte, then the entry."""

    BLOCK = b"B"  #: kind u1, seq i8, n i8, t0 f8, t1 f8, log_time i8, data length u4, data
    SCALARS = b"C"  #: count u4, records length u8, sizes i8[count], log_ns i8[count], t f8[count], seq i8[count], records
    HEALTH = b"H"  #: log_time i8, data length u4, data (the JSON of a Health report)
    ALARM = b"A"  #: as HEALTH, the JSON of an AlarmEvent (process monitors)


_KEY = struct.Struct("<dqi")
_B = struct.Struct("<BqqddqI")
_C = struct.Struct("<IQ")
_H = struct.Struct("<qI")
_SEND_BYTES = 1 << 18


def _pack_entries(entries: list[tuple], buf: list[bytes]) -> None:
    buf.append(struct.pack("<I", len(entries)))
    for e in entries:
        if e[0] == "B":
            _, kind, _m, _a, data, seq, n, t0, t1, lt = e
            buf += (_Entry.BLOCK, _B.pack(_KINDS.index(kind), seq, n, t0, t1, lt, len(data)), data)
        elif e[0] == "C":
            _, _m, _a, records, sizes, log_ns, t, seq = e
            buf += (_Entry.SCALARS, _C.pack(sizes.size, records.size), sizes.astype("<i8").tobytes(),
                    log_ns.astype("<i8").tobytes(), t.astype("<f8").tobytes(), seq.astype("<i8").tobytes(),
                    records.tobytes())
        else:  # "H" health report, "A" process alarm: the same frame
            _, _m, _a, data, lt = e
            buf += (_Entry.HEALTH if e[0] == "H" else _Entry.ALARM, _H.pack(lt, len(data)), data)


def _unpack_entries(view: memoryview, pos: int, name: str) -> tuple[list[tuple], int]:
    m, a = name.split("/", 1)
    (count,) = struct.unpack_from("<I", view, pos)
    pos += 4
    out = []
    for _ in range(count):
        tag = view[pos:pos + 1].tobytes()
        pos += 1
        if tag == _Entry.BLOCK:
            kind, seq, n, t0, t1, lt, size = _B.unpack_from(view, pos)
            pos += _B.size
            out.append(("B", _KINDS[kind], m, a, view[pos:pos + size].tobytes(), seq, n, t0, t1, lt))
            pos += size
        elif tag in (_Entry.HEALTH, _Entry.ALARM):
            lt, size = _H.unpack_from(view, pos)
            pos += _H.size
            out.append((tag.decode(), m, a, view[pos:pos + size].tobytes(), lt))
            pos += size
        else:
            k, size = _C.unpack_from(view, pos)
            pos += _C.size
            cols = np.frombuffer(view, dtype="<i8", count=4 * k, offset=pos).copy()
            pos += 32 * k
            records = np.frombuffer(view, dtype=np.uint8, count=size, offset=pos).copy()
            pos += size
            out.append(("C", m, a, records, cols[:k], cols[k:2 * k], cols[2 * k:3 * k].view("<f8"), cols[3 * k:]))
    return out, pos


def _run_children(trial: str, w, names: list[str], axes: dict[str, AxisRuntime], has_truth, limits,
                  jobs: int, input_health: InputHealthSettings | None, monitors=None) -> dict[str, int]:
    """``jobs`` > 1: children estimate and encode, this process merges and writes (module docstring)."""
    # fork when this process has no other thread (the command line): the children start at once with the
    # estimators as they are; else spawn (a thread holding a lock at fork time would leave it held), and
    # the children build their estimators from the model files
    fork = threading.active_count() == 1
    ctx = multiprocessing.get_context("fork" if fork else "spawn")
    groups = [names[i::jobs] for i in range(jobs)]
    children = []
    try:
        for group in groups:
            conn, child = ctx.Pipe(duplex=False)
            spec = {"trial": trial, "axes": group, "index": {n: names.index(n) for n in group},
                    "models": {n: axes[n].status.model_path for n in group},
                    "sha256": {n: axes[n].status.model_sha256 for n in group},
                    "has_truth": [list(k) for k in has_truth], "limits": msgspec.to_builtins(limits),
                    "input_health": None if input_health is None else msgspec.to_builtins(input_health),
                    "monitors": None if monitors is None else msgspec.to_builtins(monitors),
                    "log_format": None if fork else log_format()}
            own = {axes[n].key: axes[n] for n in group} if fork else None
            p = ctx.Process(target=_child_main, args=(child, json.dumps(spec), own), name="feedmon-offline",
                            daemon=True)
            p.start()
            child.close()
            children.append((p, conn))
        results: list[dict] = []
        drains: dict[str, tuple[tuple | None, list[tuple]]] = {}

        def stream(conn) -> Iterator[tuple[tuple, str, list[tuple]]]:
            for msg in _read_ahead(conn):
                if msg is None:
                    raise RuntimeError("an offline worker process ended without finishing")
                view, pos = memoryview(msg), 0
                while pos < len(view):
                    tag = view[pos:pos + 1].tobytes()
                    pos += 1
                    if tag == _Frame.ITEM:
                        key = _KEY.unpack_from(view, pos)
                        pos += _KEY.size
                        name = names[key[1]]
                        entries, pos = _unpack_entries(view, pos, name)
                        yield key, name, entries
                    elif tag == _Frame.DRAIN:
                        idx, has_key = struct.unpack_from("<iB", view, pos)
                        pos += 5
                        key = None
                        if has_key:
                            key = _KEY.unpack_from(view, pos)
                            pos += _KEY.size
                        entries, pos = _unpack_entries(view, pos, names[idx])
                        drains[names[idx]] = (key, entries)
                    elif tag == _Frame.FINAL:
                        results.append(_read_final(view, pos, axes))
                        return
                    else:
                        err = json.loads(view[pos:].tobytes())
                        cls = {"OSError": OSError, "TrialFileError": ValueError, "ValueError": ValueError}.get(
                            err["type"], RuntimeError)
                        raise cls(err["message"])

        for _key, _name, entries in heapq.merge(*(stream(c) for _, c in children), key=lambda x: x[0]):
            _write(w, entries)
        _write_drain(w, {n: e for n, (_, e) in drains.items()}, {n: k for n, (k, _) in drains.items()})
        for p, _ in children:
            p.join(30)
    finally:
        for p, conn in children:
            if p.is_alive():
                p.kill()
                p.join(5)
            conn.close()
    return {k: sum(r[k] for r in results) for k in ("samples", "estimates", "truth", "health")}


#: pipe messages of one worker read ahead (each about _SEND_BYTES): a worker whose axes run ahead in time
#: is not held by the merge, which waits for the others — at most this many messages and READ_AHEAD_BYTES
_READ_AHEAD = 256
READ_AHEAD_BYTES = 64 * 2**20


def _read_ahead(conn) -> Iterator[bytes | None]:
    """The pipe messages of a worker, read on a thread of their own into a FIFO bounded in messages
    and bytes, until the worker closes the pipe (then None)."""
    q = _Fifo(_READ_AHEAD, READ_AHEAD_BYTES)
    stop = threading.Event()

    def run() -> None:
        while True:
            try:
                msg = conn.recv_bytes()
            except (EOFError, OSError):
                q.put(None, 0, stop)
                return
            if not q.put(msg, len(msg), stop):
                return

    th = threading.Thread(target=run, name="offline-merge-reader", daemon=True)
    th.start()
    try:
        while True:
            msg = q.get()
            yield msg
            if msg is None:
                return
    finally:
        stop.set()


def _read_final(view: memoryview, pos: int, axes: dict[str, AxisRuntime]) -> dict:
    """The child's counters and tracker states, applied to the parent's axes."""
    (size,) = struct.unpack_from("<I", view, pos)
    pos += 4
    doc = json.loads(view[pos:pos + size].tobytes())
    pos += size
    for name, a in doc["axes"].items():
        (nz,) = struct.unpack_from("<Q", view, pos)
        pos += 8
        ax = axes[name]
        if nz:  # else the child's tracker never stepped: the parent's is as fresh
            with np.load(io.BytesIO(view[pos:pos + nz].tobytes()), allow_pickle=False) as z:
                ax.estimator.restore({k: z[k] for k in z.files})
        pos += nz
        ax.estimator.counters.update(a["estimator"])
        ax.status.counters.update(a["status"])
        ax.status.blocks = a["blocks"]
        ax.status.last_seq, ax.status.last_t = a["last_seq"], a["last_t"]
        ax.status.health, ax.status.health_changes = a["health"], a["health_changes"]
    return doc


def _child_main(conn, spec_json: str, axes: dict | None = None) -> None:
    """An offline worker: read its axes, estimate, encode, send (module docstring). ``axes``: the
    parent's (forked), else built from the model files."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops it (and the pipe closing does)
    try:
        _child(conn, json.loads(spec_json), axes)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises
        try:
            conn.send_bytes(_Frame.ERROR + json.dumps({"type": type(exc).__name__, "message": str(exc)}).encode())
        except (OSError, ValueError):
            pass
    finally:
        conn.close()


def _child(conn, spec: dict, axes: dict | None = None) -> None:
    from feedio.mcapio import TrialFileError
    from monitor.axes import load_axes

    install_log_format(spec.get("log_format"))

    if axes is None:
        axes = load_axes([spec["models"][n] for n in spec["axes"]])
        for ax in axes.values():
            if ax.status.model_sha256 != spec["sha256"][ax.status.name]:
                raise TrialFileError(f"model file {ax.status.model_path} changed after the run started; run again")
    by_name = {f"{m}/{a}": ax for (m, a), ax in axes.items()}
    ih = spec.get("input_health")
    ms = spec.get("monitors")
    pipe = Pipeline(axes, limits=msgspec.convert(spec["limits"], InputLimits),
                    input_health=None if ih is None else msgspec.convert(ih, InputHealthSettings),
                    monitors=None if ms is None else _monitors(axes, ms))
    enc = _Encoder({tuple(k) for k in spec["has_truth"]})
    index = spec["index"]
    buf: list[bytes] = []
    size = [0]

    def send(part: list[bytes], force: bool = False) -> None:
        buf.extend(part)
        size[0] += sum(len(x) for x in part)
        if size[0] >= _SEND_BYTES or force:
            conn.send_bytes(b"".join(buf))
            buf.clear()
            size[0] = 0

    def item(key, entries) -> None:
        part = [_Frame.ITEM, _KEY.pack(*key)]
        _pack_entries(entries, part)
        send(part)

    with _WriterThread() as out:
        counts = _estimate_items(_merged_blocks(spec["trial"], spec["axes"], index), pipe, enc, out, item)

        def finish() -> None:
            drained = enc.drain()
            for name in spec["axes"]:
                key = enc.touched.get(name)
                part = [_Frame.DRAIN, struct.pack("<iB", index[name], key is not None)]
                if key is not None:
                    part.append(_KEY.pack(*key))
                _pack_entries(drained.get(name, []), part)
                send(part)
            doc = {**counts, "axes": {}}
            snaps = []
            for name in spec["axes"]:
                ax = by_name[name]
                doc["axes"][name] = {"estimator": dict(ax.estimator.counters), "status": dict(ax.status.counters),
                                     "blocks": ax.status.blocks, "last_seq": ax.status.last_seq,
                                     "last_t": ax.status.last_t, "health": ax.status.health,
                                     "health_changes": ax.status.health_changes}
                snap = learned_snapshot(ax.estimator)  # None: its tracker never stepped, nothing to hand back
                z = io.BytesIO()
                if snap is not None:
                    np.savez(z, **snap)
                snaps.append(z.getvalue())
            body = json.dumps(doc).encode()
            part = [_Frame.FINAL, struct.pack("<I", len(body)), body]
            for snap in snaps:
                part += (struct.pack("<Q", len(snap)), snap)
            send(part, force=True)

        out.put(finish)
