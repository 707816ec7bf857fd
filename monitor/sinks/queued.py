"""``QueuedSink``: a writer on its own daemon thread behind a bounded queue.

The monitor's hot path (one KRLS-T update per sample at 333 Hz) must never wait
for a disk, a viewer or a network. It hands items to sinks with :meth:`offer`,
which never blocks: when the queue is full the item is dropped and counted.

A subclass implements :meth:`QueuedSink.handle` (write one item) and optionally
:meth:`~QueuedSink.handle_batch`, :meth:`~QueuedSink.start_worker`,
:meth:`~QueuedSink.tick` (periodic work such as flushing, called at least every
``tick_interval`` seconds, also when idle) and :meth:`~QueuedSink.finish`
(called once on the worker thread when the sink is closed, after the queue
has been drained). All of them run on the worker thread only, so a subclass
needs no locking of its own state.

Failure policy: an exception from a subclass hook never kills the thread. It
is counted (``failures``), remembered (``last_error``), logged once per burst
(the first failure after a success; the recovery is logged with the count),
and the sink's ``state`` is ``"failed"`` until a later item succeeds. The item
that failed is lost (it is not retried). ``failures`` and ``recoveries`` only ever
grow and ``last_error`` is kept after a recovery, so a failure stays visible (and a
test can wait on it) whatever the state is when one looks; ``failed_since`` is the
wall time the current failure began (None when ok).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Sequence
from typing import Any

__all__ = ["QueuedSink", "SinkStatus"]

log = logging.getLogger("monitor.sinks")

_STOP = object()


class SinkStatus(dict):
    """Plain ``dict`` snapshot of a sink's counters (JSON-serialisable)."""


class QueuedSink:
    """Bounded queue + daemon worker thread.

    Parameters
    ----------
    maxsize:
        queue capacity in items (blocks); ``offer`` drops when it is full.
    name:
        name used in logs, the thread name and :meth:`status`.
    tick_interval:
        the worker calls :meth:`tick` at least this often (seconds), also when idle.
    max_batch:
        at most this many queued items are passed to one :meth:`handle_batch` call.
    start:
        start the worker thread now (otherwise call :meth:`start`).
    """

    #: True for sinks whose items are buffered and made durable by :meth:`tick` (a flush):
    #: then only a successful tick clears the failed state
    recover_on_tick = False

    def __init__(
        self,
        maxsize: int = 1024,
        *,
        name: str | None = None,
        tick_interval: float = 0.1,
        max_batch: int = 256,
        start: bool = True,
    ) -> None:
        if maxsize < 1:
            raise ValueError(f"queue size must be at least 1, got {maxsize}")
        self.name = name or type(self).__name__
        self.maxsize = int(maxsize)
        self.tick_interval = float(tick_interval)
        self.max_batch = max(1, int(max_batch))
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=self.maxsize + 1)  # +1: room for the stop marker
        self._lock = threading.Lock()
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self.accepted = 0
        self.dropped = 0
        self.written = 0
        self.failures = 0
        self.last_error: str | None = None
        self.failed = False
        self.failed_since: float | None = None  # time.time() of the first failure of the current burst
        self.recoveries = 0  # failed -> ok transitions
        self.closed = False
        self._burst = 0  # failures in the current burst
        if start:
            self.start()

    # ---- producer side (any thread, never blocks) ----------------------------------------
    def offer(self, item: Any) -> bool:
        """Queue ``item`` for writing; never blocks. False (and ``dropped`` += 1) when full or closed."""
        if self._closing.is_set():
            with self._lock:
                self.dropped += 1
            return False
        # qsize() check keeps the last slot free for the stop marker
        if self._queue.qsize() >= self.maxsize:
            with self._lock:
                self.dropped += 1
            return False
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            with self._lock:
                self.dropped += 1
            return False
        with self._lock:
            self.accepted += 1
        return True

    @property
    def pending(self) -> int:
        """Items waiting in the queue."""
        return self._queue.qsize()

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def state(self) -> str:
        if self.closed:
            return "closed"
        if self._closing.is_set():
            return "closing"
        if self._thread is None:
            return "new"
        if self.failed:
            return "failed"
        return "ok"

    def status(self) -> SinkStatus:
        """Counters: name, state, accepted, dropped, written, failures, pending, last_error."""
        with self._lock:
            return SinkStatus(
                name=self.name,
                state=self.state,
                accepted=self.accepted,
                dropped=self.dropped,
                written=self.written,
                failures=self.failures,
                recoveries=self.recoveries,
                failed_since=self.failed_since,
                pending=self.pending,
                last_error=self.last_error,
                **self.extra_status(),
            )

    def start(self) -> None:
        """Start the worker thread (done by the constructor unless ``start=False``)."""
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name=f"sink-{self.name}", daemon=True)
        self._thread.start()

    def close(self, timeout: float | None = 10.0) -> bool:
        """Stop accepting, drain the queue, call :meth:`finish`, join the thread.

        Returns True when the worker finished within ``timeout`` seconds (False
        leaves a daemon thread still draining). Idempotent.
        """
        if self._thread is None:
            self.start()
        if not self._closing.is_set():
            self._closing.set()
            try:
                self._queue.put_nowait(_STOP)  # wakes the worker at once
            except queue.Full:  # pragma: no cover - a slot is reserved for it
                pass
        assert self._thread is not None
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- subclass hooks (worker thread) --------------------------------------------------
    def handle(self, item: Any) -> None:
        """Write one item. Override."""
        raise NotImplementedError

    def handle_batch(self, items: Sequence[Any]) -> None:
        """Write several items; default: :meth:`handle` each (failures counted per item)."""
        for item in items:
            self._guard(self.handle, item, count=True, durable=not self.recover_on_tick)

    def start_worker(self) -> None:
        """Called once on the worker thread before the first item (open files here)."""

    def tick(self, now: float) -> None:
        """Periodic work (``now`` = ``time.monotonic()``): flush, rotate, refresh."""

    def finish(self) -> None:
        """Called once on the worker thread after the queue was drained at close."""

    def extra_status(self) -> dict[str, Any]:
        """Extra fields for :meth:`status` (called from any thread; keep it cheap)."""
        return {}

    # ---- worker ------------------------------------------------------------------------------
    def _guard(self, fn, *args, count: bool = False, durable: bool = True) -> bool:
        """Run a hook; count and log failures; True on success.

        A success clears the failed state only when ``durable`` (for sinks with
        :attr:`recover_on_tick`, only the periodic :meth:`tick` — the flush — proves recovery:
        an item buffered in memory says nothing about a disk that is still full).
        """
        try:
            fn(*args)
        except Exception as exc:  # noqa: BLE001 - a sink must never kill the thread
            self._record_failure(exc)
            return False
        if count:
            with self._lock:
                self.written += 1
        if durable:
            self._record_success()
        return True

    def _record_failure(self, exc: BaseException) -> None:
        with self._lock:
            self.failures += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            if not self.failed:
                self.failed_since = time.time()
            self.failed = True
            self._burst += 1
            first = self._burst == 1
        if first:
            log.error("sink %s failed: %s (further failures counted until it recovers)", self.name,
                      self.last_error, exc_info=exc)

    def _record_success(self) -> None:
        if not self.failed:
            return
        with self._lock:
            burst, self._burst, self.failed = self._burst, 0, False
            self.failed_since = None
            self.recoveries += 1
        log.warning("sink %s recovered after %d failure(s)", self.name, burst)

    def _run(self) -> None:
        self._guard(self.start_worker)
        next_tick = time.monotonic() + self.tick_interval
        stop = False
        while not stop:
            timeout = max(0.0, next_tick - time.monotonic())
            items: list[Any] = []
            try:
                first = self._queue.get(timeout=timeout)
            except queue.Empty:
                stop = self._closing.is_set()  # stop marker could not be queued: still stop
            else:
                if first is _STOP:
                    stop = True
                else:
                    items.append(first)
                while len(items) < self.max_batch:
                    try:
                        nxt = self._queue.get_nowait()
                    except queue.Empty:
                        break
                    if nxt is _STOP:
                        stop = True
                        continue
                    items.append(nxt)
            if items:
                self._handle_items(items)
            now = time.monotonic()
            if now >= next_tick or stop:
                self._guard(self.tick, now)
                next_tick = now + self.tick_interval
            if stop:  # drain what is left (items offered before close)
                while True:
                    rest: list[Any] = []
                    while len(rest) < self.max_batch:
                        try:
                            nxt = self._queue.get_nowait()
                        except queue.Empty:
                            break
                        if nxt is not _STOP:
                            rest.append(nxt)
                    if not rest:
                        break
                    self._handle_items(rest)
        self._guard(self.tick, time.monotonic())
        self._guard(self.finish)
        self.closed = True

    def _handle_items(self, items: list[Any]) -> None:
        durable = not self.recover_on_tick
        if type(self).handle_batch is QueuedSink.handle_batch:
            for item in items:
                self._guard(self.handle, item, count=True, durable=durable)
            return
        if self._guard(self.handle_batch, items, durable=durable):
            with self._lock:
                self.written += len(items)
