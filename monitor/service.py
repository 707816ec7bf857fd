"""The monitor daemon (``feedmon run``) and its offline twin (``feedmon run --from``).

Threads of the live monitor
---------------------------
* **Zenoh callback** (a Zenoh runtime thread): for each sample on
  ``<prefix>/*/*/samples`` it only copies the payload bytes, takes the receive
  time and ``put_nowait`` s ``(key, bytes, t_recv)`` into a bounded
  :class:`queue.Queue`. When the queue is full the message is dropped and
  counted (``input_queue_full``, per key). No decoding, no locks of ours.
* **Estimator thread** (one): takes items in arrival order, decodes
  (:func:`monitor.schema.decode_samples`; errors are counted ``malformed`` and
  logged once per burst), routes the block to its axis'
  :class:`~monitor.estimator.AxisEstimator`, publishes the
  :class:`~monitor.schema.EstimateBlock` on ``<prefix>/<machine>/<axis>/disturbance``
  (publisher declared once per axis, congestion control DROP, express), records
  the latency *receive → published*, then offers the input and the estimate to
  the sinks. Sinks are :class:`~monitor.sinks.QueuedSink` s: ``offer`` never
  blocks and counts its drops, so a slow disk or viewer never stalls estimation.
* **Sink workers** (one per sink, inside the sinks).
* **Queryable** ``<prefix>/monitor/status`` (a Zenoh thread) answers
  :meth:`Monitor.status` as JSON.
* The **main thread** waits for SIGINT/SIGTERM (see :mod:`monitor.run_cmd`).

Shutdown (:meth:`Monitor.stop`): undeclare the subscriber (no new input), let
the estimator thread drain the queue, close the sinks (MCAP finished and
readable, .rrd finalised), save the tracker state, undeclare the rest.

The per-sample work — decode, route, estimate — is :class:`Pipeline`, shared
with :func:`run_offline`, so a trial estimated offline gives the same numbers,
sample for sample, as the same trial replayed to the live monitor.

Tracker state
-------------
:class:`StateStore` saves each axis' :meth:`AxisEstimator.snapshot` with
``np.savez`` (plain arrays; loaded with ``allow_pickle=False``) plus the model
file's SHA-256. A state whose hash differs from the model file now in use is
ignored with a warning (the model changed: its tracker state is meaningless).
"""

from __future__ import annotations

import heapq
import logging
import math
import os
import queue
import socket
import threading
import time
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from . import schema as S
from .estimator import AxisEstimator
from .model_file import AxisModel, file_sha256, load_model
from .status import AxisStatus, BurstLog

__all__ = ["AxisRuntime", "warm_up", "Pipeline", "StateStore", "Monitor", "OfflineResult", "run_offline", "load_axes",
           "live_meta"]

log = logging.getLogger("monitor.service")

STATE_FORMAT = 1
_STOP = object()
#: estimator counters that mean bad input; :meth:`Pipeline.estimate` logs them once per burst
_LOGGED_REASONS = (
    ("rejected_non_finite", "rejected: non-finite value"),
    ("rejected_out_of_range", "rejected: absurd magnitude"),
    ("duplicate", "dropped: duplicate sequence number"),
    ("out_of_order", "dropped: out-of-order sequence number"),
    ("gaps", "after a sequence gap: chain restarted"),
    ("time_backwards", "with time going backwards: chain restarted"),
)


# ============================================================================================
# axes, state
# ============================================================================================
@dataclass
class AxisRuntime:
    """One monitored axis: its model, estimator and status."""

    model: AxisModel
    estimator: AxisEstimator
    status: AxisStatus

    @property
    def key(self) -> tuple[str, str]:
        return (self.model.machine, self.model.axis)


def load_axes(model_paths: Sequence[str | os.PathLike]) -> dict[tuple[str, str], AxisRuntime]:
    """Load model files (one per axis); two files for the same axis are an error."""
    if not model_paths:
        raise ValueError("at least one --model file is needed")
    axes: dict[tuple[str, str], AxisRuntime] = {}
    for p in model_paths:
        path = Path(p)
        model = load_model(path)
        key = (model.machine, model.axis)
        if key in axes:
            raise ValueError(f"two model files for axis {model.machine}/{model.axis}: "
                             f"{axes[key].status.model_path} and {path}")
        st = AxisStatus(model.machine, model.axis, str(path), file_sha256(path))
        axes[key] = AxisRuntime(model, AxisEstimator(model), st)
    return axes


def warm_up(axes: dict[tuple[str, str], AxisRuntime]) -> None:
    """Run each axis' code path once on throw-away estimators, so that Numba compilation (or loading
    its cache) happens before the monitor says it is ready, not on the first real sample."""
    for ax in axes.values():
        m = ax.model
        n = 8
        t = [i * m.Ts for i in range(n)]
        v = [1e-3 * i for i in range(n)]
        block = S.SampleBlock(machine=m.machine, axis=m.axis, seq=0, t=t, v_ref=v, v_meas=v,
                              u=v if m.form == "force-input" else None)
        est = AxisEstimator(m).process(block)
        if est is not None:
            S.encode(est)


class StateStore:
    """Where tracker snapshots live: ``<dir>/<machine>_<axis>.state.npz`` with ``state_dir``,
    else next to the model file (``axis-x.model.toml`` → ``axis-x.model.state.npz``)."""

    def __init__(self, state_dir: str | os.PathLike | None = None) -> None:
        self.dir = None if state_dir is None else Path(state_dir)
        if self.dir is not None and not self.dir.is_dir():
            self.dir.mkdir(parents=True, exist_ok=True)  # OSError: reported by the CLI

    def path_for(self, ax: AxisRuntime) -> Path:
        if self.dir is not None:
            return self.dir / f"{ax.model.machine}_{ax.model.axis}.state.npz"
        mp = Path(ax.status.model_path)
        stem = mp.name[:-5] if mp.name.endswith(".toml") else mp.name
        return mp.with_name(stem + ".state.npz")

    def save(self, ax: AxisRuntime) -> Path:
        """Atomically write the axis' snapshot (+ model hash)."""
        path = self.path_for(ax)
        snap = dict(ax.estimator.snapshot())
        snap["meta.format"] = np.array(STATE_FORMAT, dtype=np.int64)
        snap["meta.model_sha256"] = np.array(ax.status.model_sha256)
        snap["meta.machine"] = np.array(ax.model.machine)
        snap["meta.axis"] = np.array(ax.model.axis)
        snap["meta.saved_unix"] = np.array(time.time())
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as fh:
            np.savez(fh, **snap)
        os.replace(tmp, path)
        ax.status.state_path = str(path)
        return path

    def load(self, ax: AxisRuntime) -> str:
        """Restore the axis' tracker if a matching state exists; returns what happened:
        ``fresh`` (none), ``restored``, ``ignored`` (other model) or ``unreadable``."""
        path = self.path_for(ax)
        ax.status.state_path = str(path)
        if not path.exists():
            ax.status.state = "fresh"
            return "fresh"
        try:
            with np.load(path, allow_pickle=False) as z:
                snap = {k: z[k] for k in z.files}
        except Exception as exc:  # noqa: BLE001 - corrupt file: warn and start fresh
            log.warning("tracker state %s of %s is unreadable (%s); starting fresh", path, ax.status.name, exc)
            ax.status.state = "unreadable"
            return "unreadable"
        saved = str(snap.pop("meta.model_sha256", np.array(""))[()])
        if saved != ax.status.model_sha256:
            log.warning("tracker state %s was saved with another model file (sha256 %s…, now %s…); "
                        "ignoring it and starting fresh", path, saved[:12], ax.status.model_sha256[:12])
            ax.status.state = "ignored"
            return "ignored"
        try:
            ax.estimator.restore({k: v for k, v in snap.items() if not k.startswith("meta.")})
        except Exception as exc:  # noqa: BLE001
            log.warning("tracker state %s of %s cannot be restored (%s); starting fresh", path, ax.status.name, exc)
            ax.estimator = AxisEstimator(ax.model)
            ax.status.state = "unreadable"
            return "unreadable"
        ax.status.state = "restored"
        return "restored"


def live_meta(ax: AxisRuntime, source: str = "live") -> S.TrialMeta:
    """TrialMeta of a monitored axis for the MCAP log (Ts and form from the model file)."""
    from . import __version__

    m = ax.model
    return S.TrialMeta(
        Ts=float(m.Ts), form=m.form, machine=m.machine, axis=m.axis, loop_gain=m.loop_gain,
        units=dict(S.UNITS),
        provenance=S.Provenance(source=source, tool="feedmon run", version=__version__,
                                details={"model_file": ax.status.model_path, "model_sha256": ax.status.model_sha256,
                                         "tracker_state": ax.status.state}),
        description="feedmon monitor log: input samples and disturbance estimates",
    )


# ============================================================================================
# the pipeline (shared by live and offline)
# ============================================================================================
class Pipeline:
    """Decode → route → estimate. No I/O; one thread only."""

    def __init__(self, axes: dict[tuple[str, str], AxisRuntime], *, prefix: str = "feedmon") -> None:
        self.axes = axes
        self.prefix = prefix
        self.counters: Counter[str] = Counter()  # global: malformed (axis unknown), ...
        self.no_model: Counter[str] = Counter()  # "machine/axis" -> samples dropped
        self.burst = BurstLog(log)

    def axis_of_key(self, key: str) -> AxisRuntime | None:
        parts = key.split("/")
        if len(parts) >= 3:
            return self.axes.get((parts[-3], parts[-2]))
        return None

    def decode(self, key: str, payload: bytes) -> S.SampleBlock | None:
        try:
            return S.decode_samples(payload, what=f"sample block on {key}")
        except S.SchemaError as exc:
            ax = self.axis_of_key(key)
            (ax.status.counters if ax is not None else self.counters)["malformed"] += 1
            self.burst(f"malformed:{key}", "dropping malformed message: %s", exc)
            return None

    def estimate(self, block: S.SampleBlock) -> tuple[AxisRuntime | None, S.EstimateBlock | None]:
        """Route ``block`` to its axis' estimator; ``(None, None)`` when no model covers it."""
        ax = self.axes.get((block.machine, block.axis))
        if ax is None:
            name = f"{block.machine}/{block.axis}"
            self.no_model[name] += len(block.t)
            self.burst(f"no_model:{name}", "no model for axis %s: dropping its samples (have models for %s)",
                       name, ", ".join(f"{m}/{a}" for m, a in self.axes) or "none")
            return None, None
        st = ax.status
        st.blocks += 1
        c = ax.estimator.counters
        before = [c.get(k, 0) for k, _ in _LOGGED_REASONS]
        try:
            est = ax.estimator.process(block)
        except ValueError as exc:  # e.g. the model's form needs a column the block lacks
            self.burst(f"error:{st.name}", "axis %s: block dropped: %s", st.name, exc)
            return ax, None
        except Exception as exc:  # noqa: BLE001 - never fatal; counted and logged
            st.counters["estimator_error"] += len(block.t)
            self.burst(f"error:{st.name}", "axis %s: estimator failed on a block: %s: %s", st.name,
                       type(exc).__name__, exc, level=logging.ERROR)
            return ax, None
        for (k, what), b in zip(_LOGGED_REASONS, before):
            d = c.get(k, 0) - b
            if d:  # the estimator only counts; say it once per burst (per reason and axis)
                self.burst(f"{k}:{st.name}", "axis %s: %d sample(s) %s (status counter %r)", st.name, d, what, k)
        if est is not None:
            st.last_seq = est.seq + len(est.t) - 1
            st.last_t = est.t[-1]
        return ax, est


# ============================================================================================
# live monitor
# ============================================================================================
class Monitor:
    """The live daemon: Zenoh in, estimates out (Zenoh + sinks), status queryable.

    Parameters
    ----------
    axes:
        from :func:`load_axes` (tracker state already restored if wanted).
    session:
        an open Zenoh session (the caller closes it).
    sinks:
        :class:`~monitor.sinks.QueuedSink` s offered every input block and estimate
        (``offer_truth`` too when ``record_truth``); closed by :meth:`stop`.
    queue_size:
        capacity of the input queue (messages) between the Zenoh callback and the estimator.
    record_truth:
        also subscribe to ``<prefix>/*/*/truth`` and hand truth blocks to the sinks (not to the estimator).
    state:
        :class:`StateStore` to save the tracker state to at :meth:`stop` (None: do not save).
    """

    def __init__(
        self,
        axes: dict[tuple[str, str], AxisRuntime],
        session,
        *,
        prefix: str = "feedmon",
        sinks: Sequence[Any] = (),
        queue_size: int = 8192,
        record_truth: bool = False,
        state: StateStore | None = None,
        endpoints: Sequence[str] = (),
    ) -> None:
        if queue_size < 1:
            raise ValueError(f"queue size must be ≥ 1, got {queue_size}")
        self.pipeline = Pipeline(axes, prefix=prefix)
        self.axes = axes
        self.session = session
        self.prefix = prefix
        self.sinks = list(sinks)
        self.record_truth = record_truth
        self.state_store = state
        self.endpoints = list(endpoints)
        self.queue_size = int(queue_size)
        self._q: queue.Queue = queue.Queue(maxsize=self.queue_size)
        self.received = 0
        self.queue_full: Counter[str] = Counter()  # key -> messages dropped at the input queue
        self.truth_blocks = 0
        self._subs: list[Any] = []
        self._pubs: dict[tuple[str, str], Any] = {}
        self._queryable = None
        self._thread: threading.Thread | None = None
        self._started_mono = time.monotonic()
        self._started_wall = time.time()
        self.state = "new"
        self.publish_errors = 0
        self.saved_states: list[str] = []

    # ---- Zenoh side ----------------------------------------------------------------------------
    def _on_sample(self, sample) -> None:
        """Zenoh callback: no decoding, never blocks."""
        t = time.perf_counter()
        key = str(sample.key_expr)
        try:
            self._q.put_nowait((key, sample.payload.to_bytes(), t))
        except queue.Full:
            self.queue_full[key] += 1
            return
        self.received += 1

    def _on_query(self, query) -> None:
        import json

        import zenoh

        from .transport import status_key

        try:
            body = json.dumps(self.status(), allow_nan=False, default=str)
        except Exception as exc:  # noqa: BLE001 - answer something rather than nothing
            body = json.dumps({"error": f"{type(exc).__name__}: {exc}"})
        query.reply(status_key(self.prefix), body.encode(), encoding=zenoh.Encoding.APPLICATION_JSON)

    def start(self) -> None:
        """Declare publishers, queryable and subscriber(s); start the estimator thread."""
        import zenoh

        from .transport import disturbance_key, samples_key, status_key, truth_key

        for key, ax in self.axes.items():
            self._pubs[key] = self.session.declare_publisher(
                disturbance_key(self.prefix, *key), encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.DATA_HIGH, express=True,
            )
        self._queryable = self.session.declare_queryable(status_key(self.prefix), self._on_query)
        self._thread = threading.Thread(target=self._run, name="estimator", daemon=True)
        self._thread.start()
        self._subs.append(self.session.declare_subscriber(samples_key(self.prefix), self._on_sample))
        if self.record_truth:
            self._subs.append(self.session.declare_subscriber(truth_key(self.prefix), self._on_sample))
        self.state = "running"

    # ---- estimator thread ---------------------------------------------------------------------
    def _run(self) -> None:
        q = self._q
        while True:
            item = q.get()
            if item is _STOP:
                return
            try:
                self.handle(*item)
            except Exception:  # noqa: BLE001 - the estimator thread must survive anything
                self.pipeline.counters["internal_error"] += 1
                log.exception("internal error while handling a message (counted, continuing)")

    def handle(self, key: str, payload: bytes, t_recv: float) -> S.EstimateBlock | None:
        """Process one received message (estimator thread)."""
        p = self.pipeline
        if key.endswith("/truth"):
            self._handle_truth(key, payload)
            return None
        block = p.decode(key, payload)
        if block is None:
            return None
        ax, est = p.estimate(block)
        if ax is None:
            return None
        if est is not None:
            pub = self._pubs.get(ax.key)
            try:
                pub.put(S.encode(est))
            except Exception as exc:  # noqa: BLE001 - session closing, etc.
                self.publish_errors += 1
                p.burst(f"publish:{ax.status.name}", "publishing the estimate of %s failed: %s", ax.status.name, exc)
            ax.status.latency.record(time.perf_counter() - t_recv)
        for sink in self.sinks:
            sink.offer(block)
            if est is not None:
                sink.offer(est)
        return est

    def _handle_truth(self, key: str, payload: bytes) -> None:
        try:
            block = S.decode_truth(payload, what=f"truth block on {key}")
        except S.SchemaError as exc:
            self.pipeline.counters["malformed_truth"] += 1
            self.pipeline.burst(f"malformed:{key}", "dropping malformed truth message: %s", exc)
            return
        parts = key.split("/")
        machine, axis = parts[-3], parts[-2]
        if (machine, axis) not in self.axes:
            return
        self.truth_blocks += 1
        for sink in self.sinks:
            offer = getattr(sink, "offer_truth", None)
            if offer is not None:
                offer(machine, axis, block)

    # ---- shutdown ----------------------------------------------------------------------------
    def stop(self, timeout: float = 30.0) -> None:
        """Stop input, drain the queue, close the sinks, save the tracker state. Idempotent."""
        if self.state == "stopped":
            return
        self.state = "stopping"
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception:  # noqa: BLE001
                pass
        self._subs.clear()
        if self._thread is not None:
            self._q.put(_STOP)  # blocks only while the queue is full; the thread is draining it
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("estimator thread did not drain the input queue within %.0f s", timeout)
        for sink in self.sinks:
            if not sink.close(timeout):
                log.error("sink %s did not finish within %.0f s", sink.name, timeout)
        if self.state_store is not None and self._thread is not None:  # never overwrite a state when start failed
            for ax in self.axes.values():
                try:
                    self.saved_states.append(str(self.state_store.save(ax)))
                except OSError as exc:
                    log.error("cannot save the tracker state of %s: %s", ax.status.name, exc)
        for obj in [*self._pubs.values(), self._queryable]:
            try:
                if obj is not None:
                    obj.undeclare()
            except Exception:  # noqa: BLE001
                pass
        self._pubs.clear()
        self._queryable = None
        self.state = "stopped"

    # ---- status ------------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        from . import __version__

        p = self.pipeline
        axes = {ax.status.name: ax.status.report(ax.estimator.counters, ax.estimator.tracker.size)
                for ax in self.axes.values()}
        qf = dict(self.queue_full)
        for key, n in qf.items():  # attribute input-queue drops to their axis
            ax = p.axis_of_key(key)
            if ax is not None and ax.status.name in axes:
                a = axes[ax.status.name]
                a["drops"]["input_queue_full"] = a["drops"].get("input_queue_full", 0) + n
                a["dropped_total"] += n
        all_lat = [ax.status.latency.values() for ax in self.axes.values()]
        lat = np.concatenate(all_lat) if all_lat else np.zeros(0)
        latency = {"p50": None, "p99": None, "count": int(lat.size)}
        if lat.size:
            p50, p99 = np.percentile(lat, [50.0, 99.0])
            latency.update(p50=round(float(p50), 1), p99=round(float(p99), 1))
        return {
            "monitor": {
                "version": __version__, "pid": os.getpid(), "host": socket.gethostname(), "prefix": self.prefix,
                "state": self.state, "started_unix": self._started_wall,
                "uptime_s": round(time.monotonic() - self._started_mono, 3), "endpoints": self.endpoints,
            },
            "input": {
                "received": self.received, "pending": self._q.qsize(), "capacity": self.queue_size,
                "queue_full": int(sum(qf.values())), "malformed": int(p.counters.get("malformed", 0)),
                "no_model": dict(p.no_model), "truth_blocks": self.truth_blocks,
                "publish_errors": self.publish_errors, "internal_errors": int(p.counters.get("internal_error", 0)),
            },
            "latency_us": latency,
            "axes": axes,
            "sinks": [dict(s.status()) for s in self.sinks],
        }


# ============================================================================================
# offline
# ============================================================================================
@dataclass
class OfflineResult:
    output: str
    samples: int
    estimates: int
    truth_blocks: int
    seconds: float
    axes: list[str]
    skipped_axes: list[str]

    @property
    def rate(self) -> float:
        return self.samples / self.seconds if self.seconds > 0 else math.inf


def _merged_blocks(path: str, axes: Iterable[str]) -> Iterator[tuple[str, str, Any]]:
    """``(axis_name, kind, block)`` of several axes merged by the time of their last sample."""
    from .mcapio import iter_blocks

    def one(idx: int, name: str):
        for j, (kind, b) in enumerate(iter_blocks(path, name, kinds=("samples", "truth"))):
            yield float(b.t[-1]), idx, j, name, kind, b

    for _, _, _, name, kind, b in heapq.merge(*(one(i, a) for i, a in enumerate(axes)),
                                              key=lambda x: (x[0], x[1], x[2])):
        yield name, kind, b


def run_offline(trial: str | os.PathLike, output: str | os.PathLike,
                axes: dict[tuple[str, str], AxisRuntime]) -> OfflineResult:
    """Estimate a recorded trial without Zenoh, as fast as the machine goes.

    Every samples block of the axes that have a model goes through the same
    :class:`Pipeline` as in the live monitor; samples and estimates are written
    with :class:`~monitor.mcapio.TrialWriter` (the writer of the MCAP sink) and the
    truth blocks are copied through. The trial's own metadata (with its truth) is
    kept, with the model file and hash added to the provenance details. Chunks
    follow controller time only, so the same input gives the same bytes.
    """
    from .mcapio import TrialWriter, _Open

    trial, output = os.fspath(trial), os.fspath(output)
    if os.path.abspath(trial) == os.path.abspath(output):
        raise ValueError(f"output {output!r} would overwrite the input trial")
    with _Open(trial) as f:
        present = f.axes()
        metas = {key: f.meta(*key) for key in present if key in axes}
    missing = [f"{m}/{a}" for (m, a) in axes if (m, a) not in present]
    if missing:
        raise ValueError(f"{trial} has no axis {', '.join(missing)} (axes present: "
                         f"{', '.join(f'{m}/{a}' for m, a in present) or 'none'}); check the --model files")
    skipped = [f"{m}/{a}" for (m, a) in present if (m, a) not in axes]
    out_metas = []
    for key, meta in metas.items():
        ax = axes[key]
        if ax.model.form != meta.form:
            raise ValueError(f"axis {key[0]}/{key[1]}: model form {ax.model.form!r} but the trial is {meta.form!r}")
        details = dict(meta.provenance.details)
        details.update(estimated_by="feedmon run --from", model_file=ax.status.model_path,
                       model_sha256=ax.status.model_sha256, tracker_state=ax.status.state)
        out_metas.append(msgspec.structs.replace(meta, provenance=msgspec.structs.replace(meta.provenance,
                                                                                           details=details)))
    pipe = Pipeline(axes)
    names = [f"{m}/{a}" for (m, a) in metas]
    samples = estimates = truth = 0
    t0 = time.perf_counter()
    with TrialWriter(output, out_metas) as w, _WriterThread(w) as out:
        for name, kind, block in _prefetch(_merged_blocks(trial, names)):
            if kind == "truth":
                m, a = name.split("/", 1)
                out.put(w.write_truth, block, m, a)
                truth += 1
                continue
            samples += len(block.t)
            _, est = pipe.estimate(block)
            out.put(w.write_samples, block)
            if est is not None:
                out.put(w.write_estimates, est)
                estimates += len(est.t)
    seconds = time.perf_counter() - t0
    return OfflineResult(output, samples, estimates, truth, seconds, names, skipped)


def _prefetch(items: Iterator, depth: int = 64) -> Iterator:
    """Iterate ``items`` on a second thread (MCAP reading, zstd decompression and JSON decoding
    overlap with the estimation); exceptions are re-raised here, order is kept."""
    q: queue.Queue = queue.Queue(maxsize=depth)
    done = object()
    stop = threading.Event()

    def run() -> None:
        try:
            for item in items:
                if stop.is_set():
                    return
                q.put((None, item))
        except BaseException as exc:  # noqa: BLE001 - re-raised in the consumer
            q.put((exc, None))
        q.put((None, done))

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
        while th.is_alive():  # unblock a producer waiting on a full queue
            try:
                q.get_nowait()
            except queue.Empty:
                th.join(0.01)


class _WriterThread:
    """Runs the MCAP writes of :func:`run_offline` on a second thread, in order.

    The tracker loop (``@njit(nogil=True)``) and zstd compression both release the GIL, so
    estimating and encoding/compressing/writing overlap on two cores; one thread and a FIFO
    keep the output byte-identical to writing inline. A write error is raised in the caller.
    """

    def __init__(self, writer, depth: int = 256) -> None:
        self._q: queue.Queue = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="offline-writer", daemon=True)

    def __enter__(self) -> "_WriterThread":
        self._thread.start()
        return self

    def put(self, fn, *args) -> None:
        if self._error is not None:
            raise self._error
        self._q.put((fn, args))

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            if self._error is None:
                try:
                    item[0](*item[1])
                except BaseException as exc:  # noqa: BLE001 - re-raised in the caller
                    self._error = exc

    def __exit__(self, *exc) -> None:
        self._q.put(None)
        self._thread.join()
        if self._error is not None and exc[0] is None:
            raise self._error
