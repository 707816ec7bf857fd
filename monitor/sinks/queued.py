"""``QueuedSink``: a writer on its own daemon thread behind a bounded queue.

The monitor's hot path (one KRLS-T update per sample at 333 Hz) must never wait
for a disk, a viewer or a network. It hands items to sinks with :meth:`offer`,
which never blocks: when the queue is full the item is dropped and counted.

``offer`` does not wake the worker: it appends to a deque (a few hundred ns, no
condition variable, no thread switch on the hot path). The worker takes what has
gathered every ``batch_interval`` seconds (default 50 ms), or at once when
``max_batch`` items wait or the sink is closed, so a sink costs the estimating
thread no context switch per message and competes for the interpreter lock in a
few short bursts per second instead of once per message (measured: 50 ms instead of 10 ms took
~10 % off the monitor's median latency at 333 Hz).

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
import threading
import time
from collections import deque
from collections.abc import Sequence
from typing import Any

__all__ = ["QueuedSink", "SinkStatus"]

log = logging.getLogger("monitor.sinks")


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
        at most this many queued items are passed to one :meth:`handle_batch` call; this many
        waiting items wake the worker before ``batch_interval`` is over.
    batch_interval:
        the worker takes the items that gathered at least this often (seconds).
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
        batch_interval: float = 0.05,
        start: bool = True,
    ) -> None:
        if maxsize < 1:
            raise ValueError(f"queue size must be at least 1, got {maxsize}")
        if not batch_interval > 0:
            raise ValueError(f"batch_interval must be > 0 s, got {batch_interval}")
        self.name = name or type(self).__name__
        self.maxsize = int(maxsize)
        self.tick_interval = float(tick_interval)
        self.max_batch = max(1, int(max_batch))
        self.batch_interval = float(batch_interval)
        self._items: deque[Any] = deque()
        self._wake = threading.Event()  # set by close() and by a full batch: the worker looks at once
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
        """Queue ``item`` for writing; never blocks, never wakes the worker (unless a batch is
        full). False (and ``dropped`` += 1) when full or closed."""
        with self._lock:
            if self._closing.is_set() or len(self._items) >= self.maxsize:
                self.dropped += 1
                return False
            self._items.append(item)
            self.accepted += 1
            full = len(self._items) >= self.max_batch
        if full:
            self._wake.set()
        return True

    @property
    def pending(self) -> int:
        """Items waiting in the queue."""
        return len(self._items)

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
        with self._lock:
            self._closing.set()
        self._wake.set()
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

    def _take(self) -> list[Any]:
        """Up to ``max_batch`` waiting items, oldest first."""
        items = self._items
        with self._lock:
            n = min(len(items), self.max_batch)
            return [items.popleft() for _ in range(n)]

    def _run(self) -> None:
        self._guard(self.start_worker)
        next_tick = time.monotonic() + self.tick_interval
        while True:
            stop = self._closing.is_set()  # read first: what was offered before close is drained below
            if not stop:
                self._wake.wait(max(0.0, min(self.batch_interval, next_tick - time.monotonic())))
                self._wake.clear()
            while True:
                items = self._take()
                if not items:
                    break
                self._handle_items(items)
                if not stop and len(items) < self.max_batch:
                    break
            now = time.monotonic()
            if now >= next_tick or stop:
                self._guard(self.tick, now)
                next_tick = now + self.tick_interval
            if stop:
                break
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
