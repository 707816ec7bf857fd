"""The live monitor daemon (``feedmon run``).

Threads of the live monitor
---------------------------
* **Zenoh callback** (a Zenoh runtime thread): for each sample on ``<prefix>/*/*/samples`` it
  first checks the payload length against ``max_message_bytes`` (``len`` of the Zenoh buffer, no
  copy; beyond: refused, counted ``too_large``). Then, when nothing is being estimated and nothing
  waits, and the message is small (at most ``inline_bytes``, 2 KiB: a few tens of samples, well
  under a millisecond of tracker work), it **estimates the message right there** — decode, key check, route,
  estimate, publish — so a sample costs no thread hand-off: the thread that received it publishes
  its estimate. Otherwise (a burst, a large block, or a message arriving while another one is
  being estimated) it copies the payload and appends ``(key, bytes, times)`` to the input queue,
  bounded in messages (``queue_messages``) and payload bytes (``queue_bytes``); when either bound
  is reached the message is refused and counted (``queue_full``). One token (``busy``, under the
  input lock) admits one message at a time to the estimators, so messages are estimated one at a
  time in arrival order, whichever thread does it. Refusals are counted per modelled axis (looked
  up by the exact key) or monitor-wide, so a peer inventing keys cannot grow any table.
* **Estimator thread** (one): works off the input queue, in order, taking the token for each
  message; it sleeps while the queue is empty.
* For each estimated message (on whichever of the two): the :class:`~monitor.pipeline.Pipeline`
  (decode, key check, route, estimate; refusals counted and logged once per burst), the
  :class:`~feedio.schema.EstimateBlock` encoded once and published on
  ``<prefix>/<machine>/<axis>/disturbance`` (publisher declared once per axis, congestion control
  DROP, express), the latency *receive → published* and the time of each stage recorded
  (:class:`~monitor.status.StageRing`: queue, decode, estimate, encode, publish, sinks), then the
  input and the estimate offered to the sinks — as the bytes received and published to sinks that
  take them (``offer_encoded``: the MCAP log, which runs in its own process), as objects to the
  others. Only blocks the schema accepted reach a sink (times within ``[0, T_MAX]``, names and
  ``seq`` bounded), so no sink sees a value it cannot store. Sinks are
  :class:`~monitor.sinks.QueuedSink` s: ``offer`` never blocks and never wakes their thread; a
  sink must keep that promise (a sink that blocks holds the thread that estimates).
  The health reports the block produced (``Estimated.health``, about one per second of data) go
  to ``<prefix>/<machine>/<axis>/health`` and to the sinks that take them (``offer_health``: the
  MCAP channel ``/<machine>/<axis>/health``, the Rerun event log).
* **Sink workers** (one per sink, inside the sinks; the MCAP and Rerun sinks forward to their
  own processes).
* **Queryable** ``<prefix>/monitor/status`` (a Zenoh thread) answers a cached JSON document,
  rebuilt at most every ``status_refresh_s`` on that thread (never on an estimating thread, no
  work per message); replies are rate-limited (token bucket, ``status_rate`` /
  ``status_burst``), queries beyond are not answered and counted (``status.refused``).
* The **main thread** waits for SIGINT/SIGTERM (see :mod:`feedmon.run_cmd`).

Shutdown (:meth:`Monitor.stop`) always finishes, within ``drain_seconds`` + ``finish_seconds`` +
the sinks' ``timeout``; every step is guarded, its errors logged and returned: stop accepting
input (later messages counted ``shutdown_discarded``), undeclare the subscribers, let the estimator
thread drain the queue for up to ``drain_seconds``, then discard (and count, per axis) what is
still queued and wait for the message in progress (on either thread) up to ``finish_seconds``; with
a wear history, append the run as one part and publish its ``wear`` alarms (Zenoh and sinks); close the sinks side by side, all by one deadline (MCAP finished and readable, .rrd finalised; a
sink process not done by then is killed and what it had not written counted), and return as a
problem what each did not write (:func:`sink_losses`); save the tracker states — only when no
message is being estimated any more (a state that may still be changing is never written), and
not the state of an axis that learned nothing or learned from input its health flagged
(:mod:`monitor.input_health`); undeclare the rest.

The per-sample work is :class:`~monitor.pipeline.Pipeline`, shared with
:func:`monitor.offline.run_offline`, so a trial estimated offline gives the same numbers, sample
for sample, as the same trial replayed to the live monitor. Tracker states are saved by
:class:`~monitor.state.StateStore`.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
from collections import Counter, deque
from collections.abc import Sequence
from typing import Any

import numpy as np

from feedio import schema as S
from feedio.limits import DEFAULT, InputLimits

from .axes import AxisRuntime
from .input_health import InputHealthSettings
from .pipeline import Pipeline
from .sinks.frames import Tag
from .sinks.protocols import AlarmSink, ClosingSink, EncodedSink, HealthSink, ProcessViewSink, Sink, TruthSink
from .state import StateStore
from .status import StageRing
from .status_doc import InputInfo, Latency, MonitorInfo, Percentiles, Served, StatusDoc, to_builtins

__all__ = ["Monitor", "INLINE_BYTES", "sink_losses"]

log = logging.getLogger("monitor.daemon")

#: callback-side refusal reasons (status name in ``input`` → per-axis ``drops`` name)
_CALLBACK_REASONS = {"too_large": "too_large", "queue_full": "input_queue_full",
                     "shutdown_discarded": "shutdown_discarded"}
#: messages up to this size (bytes) are estimated in the Zenoh callback when nothing else is (a few
#: tens of samples: well under a millisecond of tracker work); larger ones go through the input queue
INLINE_BYTES = 2048


def sink_losses(st: dict[str, Any]) -> str | None:
    """What a closed sink did not write, in one sentence (None: it wrote everything offered into complete
    files): messages refused by its full queue (``dropped``), accepted but never written (``lost``),
    written to files someone removed (``removed``), files left incomplete (given up, or of a process
    that was replaced), restarts of its process."""
    dropped, lost, removed = int(st.get("dropped") or 0), int(st.get("lost") or 0), int(st.get("removed") or 0)
    if not (dropped or lost or removed or st.get("incomplete_files") or st.get("restarts")):
        return None
    offered = st.get("offered", int(st.get("accepted") or 0) + dropped)
    parts = [f"{dropped + lost} of {offered} messages not written ({dropped} dropped: queue full, {lost} lost)"] \
        if dropped or lost else [f"all {offered} messages written"]
    if removed:
        parts.append(f"{removed} written to files removed while open ({', '.join(st.get('removed_files') or [])})")
    incomplete = st.get("incomplete_files") or []
    if incomplete:
        note = st.get("incomplete_note") or "they end where writing stopped"
        parts.append(f"incomplete files ({note}): {', '.join(map(str, incomplete))}")
    if st.get("restarts"):
        parts.append(f"its process was restarted {st['restarts']} time(s)")
    return f"sink {st.get('name')}: " + "; ".join(parts)


class Monitor:
    """The live daemon: Zenoh in, estimates out (Zenoh + sinks), status queryable.

    Parameters
    ----------
    axes:
        from :func:`load_axes` (tracker state already restored if wanted).
    session:
        an open Zenoh session (the caller closes it).
    sinks:
        :class:`~monitor.sinks.QueuedSink` s offered every input block and estimate (as bytes through
        ``offer_encoded`` when they have it, else as objects through ``offer``; ``offer_truth`` too when
        ``record_truth``); closed by :meth:`stop`.
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
    inline_bytes:
        messages up to this size are estimated in the Zenoh callback when nothing else is being
        estimated or waits (0: always through the queue and the estimator thread).
    input_health:
        thresholds of the input-health verdict (:mod:`monitor.input_health`; None: the defaults).
    """

    def __init__(
        self,
        axes: dict[tuple[str, str], AxisRuntime],
        session,
        *,
        prefix: str = "feedmon",
        sinks: Sequence[Sink] = (),
        limits: InputLimits = DEFAULT,
        record_truth: bool = False,
        state: StateStore | None = None,
        endpoints: Sequence[str] = (),
        drain_seconds: float = 30.0,
        finish_seconds: float = 10.0,
        inline_bytes: int = INLINE_BYTES,
        input_health: InputHealthSettings | None = None,
        monitors=None,
    ) -> None:
        if not drain_seconds >= 0 or not finish_seconds >= 0:
            raise ValueError(f"drain_seconds and finish_seconds must be ≥ 0, got {drain_seconds}, {finish_seconds}")
        self.pipeline = Pipeline(axes, prefix=prefix, limits=limits, input_health=input_health, monitors=monitors)
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
        self.inline_bytes = int(inline_bytes)
        # input side, under _in_lock (= the condition _cv): the queue, the token, the counters
        self._in_lock = threading.Lock()
        self._cv = threading.Condition(self._in_lock)
        self._queue: deque[tuple[str, bytes, float, int, int]] = deque()  # key, payload, t_recv, size, rx_ns
        self._busy = False  # one message at a time is being estimated (callback or estimator thread)
        self._running = False  # started and not stopping: messages may be estimated in the callback
        self._accepting = True
        self._stop_thread = False
        self.received = 0  # messages taken for estimation (in the callback or queued)
        self.inline = 0  # of them, estimated in the Zenoh callback
        self._bytes_in = 0
        self._bytes_out = 0
        self._refused: Counter[tuple[str, str]] = Counter()  # (reason, axis name or "") -> messages
        self.handled = 0  # messages taken by an estimating thread
        self.truth_blocks = 0
        self.publish_errors = 0
        self._encoded = [s for s in self.sinks if isinstance(s, EncodedSink)]
        self._plain = [s for s in self.sinks if not isinstance(s, EncodedSink)]
        self._health_offers = [s.offer_health for s in self.sinks if isinstance(s, HealthSink)]
        self._truth_offers = [s.offer_truth for s in self._plain if isinstance(s, TruthSink)]
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
        # process alarms (monitor.process_monitor): publishers, the sinks that take them
        self._alarm_pubs: dict[tuple[str, str], Any] = {}
        self._alarm_offers = [s.offer_alarm for s in self.sinks if isinstance(s, AlarmSink)]
        # the process monitors' views for the dashboard: made only when a sink takes them and monitors run
        self._view_offers = [s.offer_process_view for s in self.sinks if isinstance(s, ProcessViewSink)]
        self._queryable = None
        self._thread: threading.Thread | None = None
        self._started_mono = time.monotonic()
        self._started_wall = time.time()
        self.state = "new"
        self.saved_states: list[str] = []
        self.unsaved_states: list[str] = []  # axes whose state was not saved: learned from flagged input
        self.problems: list[str] = []  # what went wrong while stopping (empty: a clean stop)

    # ---- Zenoh side ----------------------------------------------------------------------------
    def _refuse(self, reason: str, key) -> None:
        ax = self.pipeline.axis_of_key(str(key))
        with self._in_lock:
            self._refused[(reason, ax.status.name if ax is not None else "")] += 1

    def _on_sample(self, sample) -> None:
        """Zenoh callback: size check; then estimate now (idle, small) or queue (bounded, counted)."""
        t = time.perf_counter()
        payload = sample.payload
        size = len(payload)
        if size > self.limits.max_message_bytes:  # before anything else: no copy of a huge payload
            self._refuse("too_large", sample.key_expr)
            return
        key = str(sample.key_expr)
        rx = time.time_ns()
        with self._cv:
            if not self._accepting:
                reason = "shutdown_discarded"
            elif not self._busy and not self._queue and self._running and size <= self.inline_bytes:
                self._busy = True  # the token: this thread estimates it now
                self.received += 1
                self.inline += 1
                self.handled += 1
                reason = None
            elif (len(self._queue) >= self.limits.queue_messages
                  or self._bytes_in - self._bytes_out + size > self.limits.queue_bytes):
                reason = "queue_full"
            else:
                self._queue.append((key, payload.to_bytes(), t, size, rx))
                self._bytes_in += size
                self.received += 1
                self._cv.notify()
                return
        if reason is not None:
            self._refuse(reason, key)
            return
        try:
            data = payload.to_bytes()
            self._guarded(key, data, t, time.perf_counter(), rx)
        finally:
            with self._cv:
                self._busy = False
                if self._queue or self._stop_thread:
                    self._cv.notify_all()

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

    def _publisher(self, key: str, high: bool = True):
        """A JSON publisher, congestion control DROP; ``high``: priority DATA_HIGH and express (the
        estimates), else DATA (the health reports)."""
        import zenoh

        return self.session.declare_publisher(
            key, encoding=zenoh.Encoding.APPLICATION_JSON, congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.DATA_HIGH if high else zenoh.Priority.DATA, express=high)

    def start(self) -> None:
        """Declare publishers, queryable and subscriber(s); start the estimator thread."""
        from feedio.transport import disturbance_key, health_key, samples_key, status_key, truth_key

        for key in self.axes:
            self._pubs[key] = self._publisher(disturbance_key(self.prefix, *key))
            self._health_pubs[key] = self._publisher(health_key(self.prefix, *key), high=False)
        if self.pipeline.process is not None:
            self._start_alarms()
        self._queryable = self.session.declare_queryable(status_key(self.prefix), self._on_query)
        self._thread = threading.Thread(target=self._run, name="estimator", daemon=True)
        self._thread.start()
        with self._cv:
            self._running = True
        self._subs.append(self.session.declare_subscriber(samples_key(self.prefix), self._on_sample))
        if self.record_truth:
            self._subs.append(self.session.declare_subscriber(truth_key(self.prefix), self._on_sample))
        self.state = "running"

    # ---- estimating ---------------------------------------------------------------------------
    def _run(self) -> None:
        """The estimator thread: the queue, in order, one message at a time (the token)."""
        cv = self._cv
        while True:
            with cv:
                while (self._busy or not self._queue) and not (self._stop_thread and not self._queue
                                                                and not self._busy):
                    cv.wait()
                if not self._queue:
                    return  # stopping, nothing queued, nothing in progress
                key, payload, t_recv, size, rx = self._queue.popleft()
                self._bytes_out += size
                self._busy = True
                self.handled += 1
            try:
                self._guarded(key, payload, t_recv, time.perf_counter(), rx)
            finally:
                with cv:
                    self._busy = False
                    cv.notify_all()

    def _guarded(self, key: str, payload: bytes, t_recv: float, t_start: float, rx_ns: int) -> None:
        try:
            self._process(key, payload, t_recv, t_start, rx_ns)
        except Exception:  # noqa: BLE001 - an estimating thread must survive anything
            self.pipeline.counters["internal_error"] += 1
            log.exception("internal error while handling a message (counted, continuing)")

    def handle(self, key: str, payload: bytes, t_recv: float) -> S.EstimateBlock | None:
        """Process one received message now, on this thread (tests; the monitor uses the callback and
        the estimator thread). Returns the estimate block (None: none)."""
        est = self._process(key, payload, t_recv, time.perf_counter(), time.time_ns())
        return None if est is None else est.block()

    def _process(self, key: str, payload: bytes, t_recv: float, t_start: float, rx_ns: int):
        """Decode → estimate → encode → publish → sinks (the token is held)."""
        p = self.pipeline
        if key.endswith("/truth"):
            self._handle_truth(key, payload, rx_ns)
            return None
        block = p.receive(key, payload)
        if block is None:
            return None
        t1 = time.perf_counter()
        ax, est, health, alarms = p.estimate(block)
        if ax is None:
            return None
        t2 = time.perf_counter()
        data = None
        if est is not None:
            data = est.json()
            t3 = time.perf_counter()
            try:
                self._pubs[ax.key].put(data)
            except Exception as exc:  # noqa: BLE001 - session closing, etc.
                self.publish_errors += 1
                p.burst(f"publish:{ax.status.name}", "publishing the estimate of %s failed: %s", ax.status.name,
                        str(exc))
            if alarms:  # right after the estimate: an alarm is what stops the feed
                self._publish_alarms(ax, alarms, rx_ns)
            t4 = time.perf_counter()
            ax.status.latency.record(t4 - t_recv)
        for sink in self._encoded:
            sink.offer_encoded(Tag.SAMPLES, payload, rx_ns)
            if data is not None:
                sink.offer_encoded(Tag.ESTIMATES, data, rx_ns)
        for sink in self._plain:
            sink.offer(block)
            if est is not None:
                sink.offer(est.block())
        if est is not None:
            ax.status.stages.record(t_start - t_recv, t1 - t_start, t2 - t1, t3 - t2, t4 - t3,
                                    time.perf_counter() - t4)
        if health:  # after the block's messages (the MCAP log keeps main's order), outside the stage times
            self._publish_health(ax, health)
        if self._view_offers and est is not None and p.process is not None:
            self._offer_view(ax)
        return est

    def _offer_view(self, ax: AxisRuntime) -> None:
        """The process monitors' view of an axis to the dashboard when one is due (at most every
        ``VIEW_INTERVAL_S`` s of data); a failure is counted and logged, never raised."""
        try:
            view = self.pipeline.process.take_view(ax.key)
        except Exception as exc:  # noqa: BLE001 - the dashboard must not stop the estimates
            ax.status.counters["process_view_error"] += 1
            self.pipeline.burst(f"view:{ax.status.name}", "axis %s: the process monitors' view failed: %s: %s",
                                ax.status.name, type(exc).__name__, str(exc))
            return
        if view is not None:
            for offer in self._view_offers:
                offer(view)

    def _start_alarms(self) -> None:
        """Alarm publishers (priority REAL_TIME, express) and the acknowledgement subscriber."""
        import zenoh

        from feedio.transport import ack_key, alarm_key

        for key in self.axes:
            self._alarm_pubs[key] = self.session.declare_publisher(
                alarm_key(self.prefix, *key), encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.REAL_TIME, express=True)
        self._subs.append(self.session.declare_subscriber(ack_key(self.prefix), self._on_ack))

    def _on_ack(self, sample) -> None:
        """``<prefix>/<machine>/<axis>/ack`` ``{"monitor": "impulse"|"tooth"|"envelope"}``: widen that monitor."""
        try:
            from feedio.transport import parse_key

            machine, axis, _ = parse_key(sample.key_expr, self.prefix)
            mon = self.pipeline.process.by_axis.get((machine, axis))
            payload = sample.payload.to_bytes()
            if mon is None or len(payload) > 4096:
                raise ValueError(f"no process monitor for {machine}/{axis}" if mon is None else "payload too large")
            import json

            # a factor set between two blocks (the estimator reads it once per block segment)
            mon.acknowledge(str(json.loads(payload)["monitor"]))
        except Exception as exc:  # noqa: BLE001 - a bad acknowledgement is refused and logged
            self.pipeline.counters["ack_refused"] += 1
            self.pipeline.burst("ack", "refusing an alarm acknowledgement on %s: %s", str(sample.key_expr), str(exc))

    def _put(self, pub, message, what: str, ax: AxisRuntime) -> None:
        """Publish one message of an axis; a failure (the session closing …) is counted and logged, never raised."""
        try:
            pub.put(S.encode(message))
        except Exception as exc:  # noqa: BLE001 - session closing, etc.
            self.publish_errors += 1
            self.pipeline.burst(f"publish_{what}:{ax.status.name}", f"publishing the {what} of %s failed: %s",
                                ax.status.name, str(exc))

    def _publish_alarms(self, ax: AxisRuntime, alarms: list, rx_ns: int) -> None:
        """Process alarms of an axis: on Zenoh (``<prefix>/<machine>/<axis>/alarm``) and to every sink that
        takes them (MCAP channel, Rerun event log)."""
        pub = self._alarm_pubs.get(ax.key)
        for a in alarms:
            self._put(pub, a, "alarm", ax)
            for offer in self._alarm_offers:
                offer(a, rx_ns)

    def _publish_health(self, ax: AxisRuntime, reports: list[S.Health]) -> None:
        """Health reports of an axis: on Zenoh (``<prefix>/<machine>/<axis>/health``) and to every sink
        that takes them (MCAP channel, Rerun event log)."""
        pub = self._health_pubs.get(ax.key)
        for h in reports:
            self._put(pub, h, "health", ax)
            for offer in self._health_offers:
                offer(h.machine, h.axis, h)

    def _handle_truth(self, key: str, payload: bytes, rx_ns: int) -> None:
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
        m, a = ax.model.machine, ax.model.axis
        for sink in self._encoded:
            sink.offer_encoded(Tag.TRUTH, payload, rx_ns, f"{m}\0{a}".encode())
        for offer in self._truth_offers:
            offer(m, a, block)

    # ---- shutdown ----------------------------------------------------------------------------
    def _problem(self, msg: str, *args: Any) -> None:
        text = msg % args if args else msg
        self.problems.append(text)
        log.error("%s", text)

    def _discard_queued(self) -> int:
        """Take every queued item off the queue and count it (per axis); returns how many."""
        with self._cv:
            items = list(self._queue)
            self._queue.clear()
            for item in items:
                self._bytes_out += item[3]
        for key, *_ in items:
            self._refuse("shutdown_discarded", key)
        return len(items)

    def _idle(self) -> bool:
        """True when the estimator thread has ended and no message is being estimated."""
        th = self._thread
        return (th is None or not th.is_alive()) and not self._busy

    def _wait_idle(self, seconds: float) -> bool:
        deadline = time.monotonic() + seconds
        th = self._thread
        if th is not None:
            th.join(max(0.0, deadline - time.monotonic()))
        with self._cv:
            while self._busy and time.monotonic() < deadline:
                self._cv.wait(max(0.0, deadline - time.monotonic()))
        return self._idle()

    def _stop_estimator(self) -> bool:
        """Stop estimating: drain for up to ``drain_seconds``, then discard the rest and wait for the
        message in progress up to ``finish_seconds``. True when nothing is being estimated any more."""
        th = self._thread
        with self._cv:
            self._running = False
            self._stop_thread = True
            self._cv.notify_all()
        if th is None or not th.is_alive():  # never started (or gone): what is queued will not be estimated
            n = self._discard_queued()
            if n:
                log.warning("%d queued message(s) discarded at stop (status: shutdown_discarded)", n)
            return self._wait_idle(self.finish_seconds)
        if self._wait_idle(self.drain_seconds):
            return True
        n = self._discard_queued()
        log.error("the estimator did not work off the input queue within %.3g s: %d queued message(s) discarded "
                  "(status: shutdown_discarded)", self.drain_seconds, n)
        return self._wait_idle(self.finish_seconds)  # the block in progress (at most max_block_samples samples)

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
                stopped = self._idle()
                self._problem("stopping the estimator thread failed: %s: %s", type(exc).__name__, exc)
            if not stopped:
                self._problem("the estimator thread did not stop (a block still in progress); tracker states are "
                              "NOT saved, the saved ones are left as they were")
            elif self._thread is not None:
                self._end_of_run()
            self._close_sinks(timeout)
            # never overwrite a state when start failed (no thread) or the estimator may still change it
            if self.state_store is not None and self._thread is not None and stopped:
                for ax in self.axes.values():
                    ih = self.pipeline.input_health[ax.key]
                    if ih.tainted:  # a state learned from a stream flagged bad is not saved over a good one
                        log.warning("tracker state of %s NOT saved: it learned %d samples from input the monitor "
                                    "flagged (%s); %s is left as it was", ax.status.name, ih.tainted,
                                    "; ".join(ih.reasons) or "see the health reports", self.state_store.path_for(ax))
                        self.unsaved_states.append(ax.status.name)
                        continue
                    try:
                        path = self.state_store.save(ax)
                        if path is None:
                            log.info("tracker state of %s not saved: it learned nothing", ax.status.name)
                        else:
                            self.saved_states.append(str(path))
                    except Exception as exc:  # noqa: BLE001 - OSError, a bad name, anything: say it, go on
                        self._problem("cannot save the tracker state of %s: %s: %s", ax.status.name,
                                      type(exc).__name__, exc)
            for obj in [*self._pubs.values(), *self._health_pubs.values(), *self._alarm_pubs.values(),
                        self._queryable]:
                try:
                    if obj is not None:
                        obj.undeclare()
                except Exception as exc:  # noqa: BLE001
                    log.warning("undeclaring a publisher/queryable failed: %s", exc)
            self._pubs.clear()
            self._health_pubs.clear()
            self._alarm_pubs.clear()
            self._queryable = None
        except BaseException as exc:  # noqa: BLE001 - even an interrupt must not leave "stopping" behind
            self._problem("shutdown interrupted: %s: %s", type(exc).__name__, exc)
            raise
        finally:
            self.state = "stopped"
        return self.problems

    def _end_of_run(self) -> None:
        """The wear monitor at the end of a run (this run is one part): the alarms go out like the others, before
        the sinks close; a history that cannot be saved is a problem (exit 1)."""
        try:
            when = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
            ends = self.pipeline.finish(f"live {when}", when)
        except Exception as exc:  # noqa: BLE001 - never stops the shutdown
            self._problem("the wear monitor failed at the end of the run: %s: %s", type(exc).__name__, exc)
            return
        rx_ns = time.time_ns()
        for key, alarms in ends.items():
            if alarms:
                self._publish_alarms(self.axes[key], alarms, rx_ns)
        wear = self.pipeline.process.wear if self.pipeline.process is not None else None
        if wear is not None and wear.error:
            self._problem("wear history %s NOT saved (%s): this run is not in it", wear.path, wear.error)

    def _close_sinks(self, timeout: float) -> None:
        """Close every sink side by side, all done by ``timeout`` s from now (a sink gives up on what it
        cannot finish by then, counted); then say what each did not write."""
        deadline = time.monotonic() + timeout
        for sink in self.sinks:
            try:
                if isinstance(sink, ClosingSink):  # (a sink of the plain protocol has close only)
                    sink.begin_close(timeout)
            except Exception as exc:  # noqa: BLE001
                self._problem("closing sink %s failed: %s: %s", getattr(sink, "name", sink), type(exc).__name__, exc)
        for sink in self.sinks:
            try:
                if not sink.close(max(0.0, deadline - time.monotonic())):
                    self._problem("sink %s did not finish within %.0f s", sink.name, timeout)
            except Exception as exc:  # noqa: BLE001
                self._problem("closing sink %s failed: %s: %s", getattr(sink, "name", sink), type(exc).__name__, exc)
                continue
            loss = sink_losses(sink.status())
            if loss:
                self._problem("%s", loss)

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
                                                 per_axis.get(ax.status.name), p.input_health[ax.key].status(),
                                                 p.process.by_axis[ax.key].status() if p.process is not None else None)
                for ax in self.axes.values()}
        all_lat = [ax.status.latency.values() for ax in self.axes.values()]
        lat = np.concatenate(all_lat) if all_lat else np.zeros(0)
        latency = Latency(count=int(lat.size))
        if lat.size:
            p50, p99 = np.percentile(lat, [50.0, 99.0])
            latency.p50, latency.p99 = round(float(p50), 1), round(float(p99), 1)
        all_st = [ax.status.stages.values() for ax in self.axes.values()]
        stages = StageRing.summarize(np.concatenate(all_st, axis=1) if all_st else np.zeros((6, 0)))
        pc = dict(p.counters)

        def axis_sum(reason: str) -> int:
            return sum(int(ax.status.counters.get(reason, 0)) for ax in self.axes.values())

        lim = self.limits
        return to_builtins(StatusDoc(
            monitor=MonitorInfo(
                version=__version__, pid=os.getpid(), host=socket.gethostname(), prefix=self.prefix,
                state=self.state, started_unix=self._started_wall,
                uptime_s=round(time.monotonic() - self._started_mono, 3), endpoints=self.endpoints,
            ),
            input=InputInfo(
                received=received, inline=self.inline, handled=self.handled, pending=len(self._queue),
                capacity=lim.queue_messages,
                pending_bytes=max(0, bytes_in - self._bytes_out), capacity_bytes=lim.queue_bytes,
                queue_full=int(totals["queue_full"]),
                too_large=int(totals["too_large"]) + axis_sum("too_large"),
                malformed=int(pc.get("malformed", 0)),
                key_mismatch=p.key_mismatch.to_dict(), key_mismatch_overflow=p.key_mismatch.overflow,
                key_mismatch_total=int(pc.get("key_mismatch", 0)) + axis_sum("key_mismatch"),
                no_model=p.no_model.to_dict(), no_model_overflow=p.no_model.overflow,
                no_model_blocks=int(pc.get("no_model_blocks", 0)),
                shutdown_discarded=int(totals["shutdown_discarded"]),
                truth_blocks=self.truth_blocks, malformed_truth=int(pc.get("malformed_truth", 0)),
                truth_no_model=int(pc.get("truth_no_model", 0)),
                publish_errors=self.publish_errors, internal_errors=int(pc.get("internal_error", 0)),
            ),
            limits={f: getattr(lim, f) for f in lim.__struct_fields__},
            status=Served(served=self.status_served, refused=self.status_refused),
            latency_us=latency,
            stages_us={k: Percentiles(**v) for k, v in stages.items()},
            axes=axes,
            sinks=[dict(s.status()) for s in self.sinks],
        ))
