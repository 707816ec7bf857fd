"""The live monitor daemon (``feedmon run``).

Threads of the live monitor
---------------------------
* **Zenoh callback** (a Zenoh runtime thread): for each sample on
  ``<prefix>/*/*/samples`` it first checks the payload length against
  ``max_message_bytes`` (``len`` of the Zenoh buffer, no copy; beyond: refused, counted
  ``too_large``), then copies the payload bytes, takes the receive time and
  ``put_nowait`` s ``(key, bytes, t_recv, size)`` into the input queue, which is bounded in
  messages (``queue_messages``) and in payload bytes (``queue_bytes``); when either bound is
  reached the message is refused and counted (``queue_full``). No decoding. Refusals are counted
  per modelled axis (looked up by the exact key) or monitor-wide, so a peer inventing keys cannot
  grow any table.
* **Estimator thread** (one): takes items in arrival order and runs the
  :class:`~monitor.pipeline.Pipeline` (decode, key check, route, estimate; refusals counted and
  logged once per burst), publishes the :class:`~feedio.schema.EstimateBlock` on
  ``<prefix>/<machine>/<axis>/disturbance`` (publisher declared once per axis, congestion control
  DROP, express), records the latency *receive → published*, then offers the input and the
  estimate to the sinks; the health reports the block produced (about one per second of data)
  go to ``<prefix>/<machine>/<axis>/health`` and to the sinks (``offer_health``). Only blocks the schema accepted reach a sink (times within
  ``[0, T_MAX]``, names and ``seq`` bounded), so no sink sees a value it cannot store. Sinks are
  :class:`~monitor.sinks.QueuedSink` s: ``offer`` never blocks and counts its drops.
* **Sink workers** (one per sink, inside the sinks).
* **Queryable** ``<prefix>/monitor/status`` (a Zenoh thread) answers a cached JSON document,
  rebuilt at most every ``status_refresh_s`` on that thread (never on the estimator thread, no
  work per message); replies are rate-limited (token bucket, ``status_rate`` /
  ``status_burst``), queries beyond are not answered and counted (``status.refused``).
* The **main thread** waits for SIGINT/SIGTERM (see :mod:`feedmon.run_cmd`).

Shutdown (:meth:`Monitor.stop`) always finishes; every step is guarded, its errors logged and
returned: stop accepting input (later messages counted ``shutdown_discarded``), undeclare the
subscribers, let the estimator thread drain the queue for up to ``drain_seconds``, then discard
(and count, per axis) what is still queued and join the thread; close the sinks (MCAP finished
and readable, .rrd finalised); save the tracker states — only when the estimator thread has
stopped (a state it may still be changing is never written); undeclare the rest.

The per-sample work is :class:`~monitor.pipeline.Pipeline`, shared with
:func:`monitor.offline.run_offline`, so a trial estimated offline gives the same numbers, sample
for sample, as the same trial replayed to the live monitor. Tracker states are saved by
:class:`~monitor.state.StateStore`.
"""

from __future__ import annotations

import json
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
from feedio.limits import DEFAULT, InputLimits

from .axes import AxisRuntime
from .pipeline import Pipeline
from .state import StateStore

__all__ = ["Monitor"]

log = logging.getLogger("monitor.daemon")

_STOP = object()
#: callback-side refusal reasons (status name in ``input`` → per-axis ``drops`` name)
_CALLBACK_REASONS = {"too_large": "too_large", "queue_full": "input_queue_full",
                     "shutdown_discarded": "shutdown_discarded"}


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
    limits:
        :class:`~feedio.limits.InputLimits` (message size, block length, input queue, unknown
        axes, status rate).
    record_truth:
        also subscribe to ``<prefix>/*/*/truth`` and hand truth blocks to the sinks (not to the estimator).
    state:
        :class:`StateStore` to save the tracker state to at :meth:`stop` (None: do not save).
    drain_seconds:
        at :meth:`stop`, how long the estimator may work off the queued input before the rest is
        discarded (and counted).
    finish_seconds:
        at :meth:`stop`, after that: how long the estimator may take to finish the block in progress
        (at most ``max_block_samples`` samples) before the monitor gives up on it (and does not save
        the tracker states).
    """

    def __init__(
        self,
        axes: dict[tuple[str, str], AxisRuntime],
        session,
        *,
        prefix: str = "feedmon",
        sinks: Sequence[Any] = (),
        limits: InputLimits = DEFAULT,
        record_truth: bool = False,
        state: StateStore | None = None,
        endpoints: Sequence[str] = (),
        drain_seconds: float = 30.0,
        finish_seconds: float = 10.0,
    ) -> None:
        if not drain_seconds >= 0 or not finish_seconds >= 0:
            raise ValueError(f"drain_seconds and finish_seconds must be ≥ 0, got {drain_seconds}, {finish_seconds}")
        self.pipeline = Pipeline(axes, prefix=prefix, limits=limits)
        self.axes = axes
        self.session = session
        self.prefix = prefix
        self.limits = limits
        self.sinks = list(sinks)
        self.record_truth = record_truth
        self.state_store = state
        self.endpoints = list(endpoints)
        self.drain_seconds = float(drain_seconds)
        self.finish_seconds = float(finish_seconds)
        self._q: queue.Queue = queue.Queue(maxsize=limits.queue_messages)
        # input side (Zenoh callback threads), under _in_lock
        self._in_lock = threading.Lock()
        self._accepting = True
        self.received = 0  # messages put into the queue
        self._bytes_in = 0
        self._refused: Counter[tuple[str, str]] = Counter()  # (reason, axis name or "") -> messages
        # estimator thread
        self._bytes_out = 0
        self.handled = 0  # messages taken off the queue and handled
        self.truth_blocks = 0
        self.publish_errors = 0
        # status queryable (Zenoh threads), under _status_lock
        self._status_lock = threading.Lock()
        self._status_doc: bytes | None = None
        self._status_built = -float("inf")
        self._tokens = float(limits.status_burst)
        self._tokens_t = time.monotonic()
        self.status_served = 0
        self.status_refused = 0
        self._subs: list[Any] = []
        self._pubs: dict[tuple[str, str], Any] = {}
        self._health_pubs: dict[tuple[str, str], Any] = {}
        self._queryable = None
        self._thread: threading.Thread | None = None
        self._started_mono = time.monotonic()
        self._started_wall = time.time()
        self.state = "new"
        self.saved_states: list[str] = []
        self.problems: list[str] = []  # what went wrong while stopping (empty: a clean stop)

    # ---- Zenoh side ----------------------------------------------------------------------------
    def _refuse(self, reason: str, key) -> None:
        ax = self.pipeline.axis_of_key(str(key))
        with self._in_lock:
            self._refused[(reason, ax.status.name if ax is not None else "")] += 1

    def _on_sample(self, sample) -> None:
        """Zenoh callback: size check, copy, enqueue. No decoding, never blocks."""
        t = time.perf_counter()
        payload = sample.payload
        size = len(payload)
        if size > self.limits.max_message_bytes:  # before anything else: no copy of a huge payload
            self._refuse("too_large", sample.key_expr)
            return
        key = str(sample.key_expr)
        with self._in_lock:
            if not self._accepting:
                reason = "shutdown_discarded"
            elif self._bytes_in - self._bytes_out + size > self.limits.queue_bytes:
                reason = "queue_full"
            else:
                try:
                    self._q.put_nowait((key, payload.to_bytes(), t, size))
                except queue.Full:
                    reason = "queue_full"
                else:
                    self._bytes_in += size
                    self.received += 1
                    return
        self._refuse(reason, key)

    def _on_query(self, query) -> None:
        """Status queryable: a cached document, rate-limited (a refused query gets no reply)."""
        with self._status_lock:
            now = time.monotonic()
            lim = self.limits
            self._tokens = min(float(lim.status_burst), self._tokens + (now - self._tokens_t) * lim.status_rate)
            self._tokens_t = now
            if self._tokens < 1.0:
                self.status_refused += 1
                return
            self._tokens -= 1.0
            self.status_served += 1
            if self._status_doc is None or now - self._status_built >= lim.status_refresh_s:
                try:
                    body = json.dumps(self.status(), allow_nan=False, default=str)
                except Exception as exc:  # noqa: BLE001 - answer something rather than nothing
                    body = json.dumps({"error": f"{type(exc).__name__}: {exc}"})
                self._status_doc = body.encode()
                self._status_built = now
            doc = self._status_doc
        import zenoh

        from feedio.transport import status_key

        try:
            query.reply(status_key(self.prefix), doc, encoding=zenoh.Encoding.APPLICATION_JSON)
        except Exception as exc:  # noqa: BLE001 - the querier went away, the session is closing
            log.debug("status reply failed: %s", exc)

    def start(self) -> None:
        """Declare publishers, queryable and subscriber(s); start the estimator thread."""
        import zenoh

        from feedio.transport import disturbance_key, health_key, samples_key, status_key, truth_key

        for key in self.axes:
            self._pubs[key] = self.session.declare_publisher(
                disturbance_key(self.prefix, *key), encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.DATA_HIGH, express=True,
            )
            self._health_pubs[key] = self.session.declare_publisher(
                health_key(self.prefix, *key), encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.DATA,
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
            key, payload, t_recv, size = item
            self._bytes_out += size
            self.handled += 1
            try:
                self.handle(key, payload, t_recv)
            except Exception:  # noqa: BLE001 - the estimator thread must survive anything
                self.pipeline.counters["internal_error"] += 1
                log.exception("internal error while handling a message (counted, continuing)")

    def handle(self, key: str, payload: bytes, t_recv: float) -> S.EstimateBlock | None:
        """Process one received message (estimator thread)."""
        p = self.pipeline
        if key.endswith("/truth"):
            self._handle_truth(key, payload)
            return None
        block = p.receive(key, payload)
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
                p.burst(f"publish:{ax.status.name}", "publishing the estimate of %s failed: %s", ax.status.name,
                        str(exc))
            ax.status.latency.record(time.perf_counter() - t_recv)
        for sink in self.sinks:
            sink.offer(block)
            if est is not None:
                sink.offer(est)
        if p.last_health:
            self._publish_health(ax, p.last_health)
        return est

    def _publish_health(self, ax: AxisRuntime, reports: list[S.Health]) -> None:
        """Health reports of an axis: on Zenoh (``<prefix>/<machine>/<axis>/health``) and to every sink
        that takes them (MCAP channel, Rerun event log)."""
        pub = self._health_pubs.get(ax.key)
        for h in reports:
            try:
                pub.put(S.encode(h))
            except Exception as exc:  # noqa: BLE001 - session closing, etc.
                self.publish_errors += 1
                self.pipeline.burst(f"publish_health:{ax.status.name}", "publishing the health of %s failed: %s",
                                    ax.status.name, str(exc))
            for sink in self.sinks:
                offer = getattr(sink, "offer_health", None)
                if offer is not None:
                    offer(h.machine, h.axis, h)

    def _handle_truth(self, key: str, payload: bytes) -> None:
        ax = self.pipeline.axis_of_key(key)
        if ax is None:  # truth of an axis without a model: not recorded
            self.pipeline.counters["truth_no_model"] += 1
            return
        try:
            block = S.decode_truth(payload, what="truth block")
        except S.SchemaError as exc:
            self.pipeline.counters["malformed_truth"] += 1
            self.pipeline.burst(f"malformed_truth:{ax.status.name}", "dropping malformed truth message on %s: %s",
                                key, str(exc))
            return
        self.truth_blocks += 1
        for sink in self.sinks:
            offer = getattr(sink, "offer_truth", None)
            if offer is not None:
                offer(ax.model.machine, ax.model.axis, block)

    # ---- shutdown ----------------------------------------------------------------------------
    def _problem(self, msg: str, *args: Any) -> None:
        text = msg % args if args else msg
        self.problems.append(text)
        log.error("%s", text)

    def _discard_queued(self) -> int:
        """Take every queued item off the queue and count it (per axis); returns how many."""
        n = 0
        while True:
            try:
                item = self._q.get_nowait()
            except queue.Empty:
                return n
            if item is _STOP:
                continue
            key, _, _, size = item
            self._bytes_out += size
            self._refuse("shutdown_discarded", key)
            n += 1

    def _stop_estimator(self) -> bool:
        """Stop the estimator thread: drain for up to ``drain_seconds``, then discard the rest.
        True when the thread has ended."""
        th = self._thread
        if th is None or not th.is_alive():  # never started (or gone): what is queued will not be estimated
            n = self._discard_queued()
            if n:
                log.warning("%d queued message(s) discarded at stop (status: shutdown_discarded)", n)
            return True
        deadline = time.monotonic() + self.drain_seconds
        try:
            self._q.put(_STOP, timeout=max(0.0, self.drain_seconds))
        except queue.Full:
            pass
        th.join(max(0.0, deadline - time.monotonic()))
        if not th.is_alive():
            return True
        n = self._discard_queued()
        log.error("the estimator did not work off the input queue within %.3g s: %d queued message(s) discarded "
                  "(status: shutdown_discarded)", self.drain_seconds, n)
        try:
            self._q.put(_STOP, timeout=5.0)
        except queue.Full:  # only if the estimator is stuck and callbacks refilled it, which _accepting prevents
            pass
        th.join(self.finish_seconds)  # the block in progress (at most max_block_samples samples)
        return not th.is_alive()

    def stop(self, timeout: float = 30.0) -> list[str]:
        """Stop input, drain the queue, close the sinks, save the tracker states. Idempotent and always
        finishes; returns the problems (also in :attr:`problems`; empty for a clean stop).

        ``timeout``: how long each sink may take to finish its files.
        """
        if self.state in ("stopping", "stopped"):
            return self.problems
        self.state = "stopping"
        try:
            with self._in_lock:
                self._accepting = False  # from now on every arriving message is counted, not queued
            for sub in self._subs:
                try:
                    sub.undeclare()
                except Exception as exc:  # noqa: BLE001 - the session may be closing
                    log.warning("undeclaring a subscriber failed: %s", exc)
            self._subs.clear()
            stopped = True
            try:
                stopped = self._stop_estimator()
            except Exception as exc:  # noqa: BLE001
                stopped = self._thread is None or not self._thread.is_alive()
                self._problem("stopping the estimator thread failed: %s: %s", type(exc).__name__, exc)
            if not stopped:
                self._problem("the estimator thread did not stop (a block still in progress); tracker states are "
                              "NOT saved, the saved ones are left as they were")
            for sink in self.sinks:
                try:
                    if not sink.close(timeout):
                        self._problem("sink %s did not finish within %.0f s", sink.name, timeout)
                except Exception as exc:  # noqa: BLE001
                    self._problem("closing sink %s failed: %s: %s", getattr(sink, "name", sink), type(exc).__name__, exc)
            # never overwrite a state when start failed (no thread) or the estimator may still change it
            if self.state_store is not None and self._thread is not None and stopped:
                for ax in self.axes.values():
                    try:
                        self.saved_states.append(str(self.state_store.save(ax)))
                    except Exception as exc:  # noqa: BLE001 - OSError, a bad name, anything: say it, go on
                        self._problem("cannot save the tracker state of %s: %s: %s", ax.status.name,
                                      type(exc).__name__, exc)
            for obj in [*self._pubs.values(), *self._health_pubs.values(), self._queryable]:
                try:
                    if obj is not None:
                        obj.undeclare()
                except Exception as exc:  # noqa: BLE001
                    log.warning("undeclaring a publisher/queryable failed: %s", exc)
            self._pubs.clear()
            self._health_pubs.clear()
            self._queryable = None
        except BaseException as exc:  # noqa: BLE001 - even an interrupt must not leave "stopping" behind
            self._problem("shutdown interrupted: %s: %s", type(exc).__name__, exc)
            raise
        finally:
            self.state = "stopped"
        return self.problems

    # ---- status ------------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        """The status document (built fresh; the queryable serves a cached copy)."""
        from feedio import __version__

        p = self.pipeline
        with self._in_lock:
            refused = dict(self._refused)
            received, bytes_in = self.received, self._bytes_in
        per_axis: dict[str, dict[str, int]] = {}
        totals = Counter()
        for (reason, name), n in refused.items():
            totals[reason] += n
            if name:
                per_axis.setdefault(name, {})[_CALLBACK_REASONS[reason]] = n
        axes = {ax.status.name: ax.status.report(ax.estimator.counters, ax.estimator.tracker.size,
                                                 per_axis.get(ax.status.name))
                for ax in self.axes.values()}
        all_lat = [ax.status.latency.values() for ax in self.axes.values()]
        lat = np.concatenate(all_lat) if all_lat else np.zeros(0)
        latency = {"p50": None, "p99": None, "count": int(lat.size)}
        if lat.size:
            p50, p99 = np.percentile(lat, [50.0, 99.0])
            latency.update(p50=round(float(p50), 1), p99=round(float(p99), 1))
        pc = dict(p.counters)

        def axis_sum(reason: str) -> int:
            return sum(int(ax.status.counters.get(reason, 0)) for ax in self.axes.values())

        lim = self.limits
        return {
            "monitor": {
                "version": __version__, "pid": os.getpid(), "host": socket.gethostname(), "prefix": self.prefix,
                "state": self.state, "started_unix": self._started_wall,
                "uptime_s": round(time.monotonic() - self._started_mono, 3), "endpoints": self.endpoints,
            },
            "input": {
                "received": received, "handled": self.handled, "pending": self._q.qsize(),
                "capacity": lim.queue_messages,
                "pending_bytes": max(0, bytes_in - self._bytes_out), "capacity_bytes": lim.queue_bytes,
                "queue_full": int(totals["queue_full"]),
                "too_large": int(totals["too_large"]) + axis_sum("too_large"),
                "malformed": int(pc.get("malformed", 0)),
                "key_mismatch": p.key_mismatch.to_dict(), "key_mismatch_overflow": p.key_mismatch.overflow,
                "key_mismatch_total": int(pc.get("key_mismatch", 0)) + axis_sum("key_mismatch"),
                "no_model": p.no_model.to_dict(), "no_model_overflow": p.no_model.overflow,
                "no_model_blocks": int(pc.get("no_model_blocks", 0)),
                "shutdown_discarded": int(totals["shutdown_discarded"]),
                "truth_blocks": self.truth_blocks, "malformed_truth": int(pc.get("malformed_truth", 0)),
                "truth_no_model": int(pc.get("truth_no_model", 0)),
                "publish_errors": self.publish_errors, "internal_errors": int(pc.get("internal_error", 0)),
            },
            "limits": {f: getattr(lim, f) for f in lim.__struct_fields__},
            "status": {"served": self.status_served, "refused": self.status_refused},
            "latency_us": latency,
            "axes": axes,
            "sinks": [dict(s.status()) for s in self.sinks],
        }
