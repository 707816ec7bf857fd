"""The live monitor daemon (``feedmon run``).

Threads of the live monitor
---------------------------
* **Zenoh callback** (a Zenoh runtime thread): for each sample on
  ``<prefix>/*/*/samples`` it only copies the payload bytes, takes the receive
  time and ``put_nowait`` s ``(key, bytes, t_recv)`` into a bounded
  :class:`queue.Queue`. When the queue is full the message is dropped and
  counted (``input_queue_full``, per key). No decoding, no locks of ours.
* **Estimator thread** (one): takes items in arrival order, decodes
  (:func:`feedio.schema.decode_samples`; errors are counted ``malformed`` and
  logged once per burst), routes the block to its axis'
  :class:`~monitor.estimator.AxisEstimator`, publishes the
  :class:`~feedio.schema.EstimateBlock` on ``<prefix>/<machine>/<axis>/disturbance``
  (publisher declared once per axis, congestion control DROP, express), records
  the latency *receive → published*, then offers the input and the estimate to
  the sinks. Sinks are :class:`~monitor.sinks.QueuedSink` s: ``offer`` never
  blocks and counts its drops, so a slow disk or viewer never stalls estimation.
* **Sink workers** (one per sink, inside the sinks).
* **Queryable** ``<prefix>/monitor/status`` (a Zenoh thread) answers
  :meth:`Monitor.status` as JSON.
* The **main thread** waits for SIGINT/SIGTERM (see :mod:`feedmon.run_cmd`).

Shutdown (:meth:`Monitor.stop`): undeclare the subscriber (no new input), let
the estimator thread drain the queue, close the sinks (MCAP finished and
readable, .rrd finalised), save the tracker state, undeclare the rest.

The per-sample work — decode, route, estimate — is :class:`~monitor.pipeline.Pipeline`,
shared with :func:`monitor.offline.run_offline`, so a trial estimated offline gives the same
numbers, sample for sample, as the same trial replayed to the live monitor. Tracker states
are saved by :class:`~monitor.state.StateStore`.
"""

from __future__ import annotations

import logging
import os
import queue
import socket
import threading
import time
from collections import Counter
from collections.abc import Sequence
from typing import Any

import numpy as np

from feedio import schema as S

from .axes import AxisRuntime
from .pipeline import Pipeline
from .state import StateStore

__all__ = ["Monitor"]

log = logging.getLogger("monitor.daemon")

_STOP = object()


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

        from feedio.transport import status_key

        try:
            body = json.dumps(self.status(), allow_nan=False, default=str)
        except Exception as exc:  # noqa: BLE001 - answer something rather than nothing
            body = json.dumps({"error": f"{type(exc).__name__}: {exc}"})
        query.reply(status_key(self.prefix), body.encode(), encoding=zenoh.Encoding.APPLICATION_JSON)

    def start(self) -> None:
        """Declare publishers, queryable and subscriber(s); start the estimator thread."""
        import zenoh

        from feedio.transport import disturbance_key, samples_key, status_key, truth_key

        for key in self.axes:
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
        from feedio import __version__

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
