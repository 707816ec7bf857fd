"""``QueuedSink``: a writer on its own daemon thread behind a bounded queue.

The monitor's hot path (one KRLS-T update per sample at 333 Hz) must never wait
for a disk, a viewer or a network. It hands items to sinks with :meth:`offer`,
which never blocks: when the queue is full (``maxsize`` items or ``max_bytes`` bytes)
the item is dropped and counted.

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

Accounting: every item offered is either refused (``dropped``: queue full, or closed) or
accepted; every accepted item ends ``written`` or ``lost`` (a hook that raised loses its
items; a subclass counts what it loses otherwise, e.g. an output given up), or is still
``pending``. By default an item is written when its hook returned; a sink whose writes are
made durable later (a flush) sets :attr:`QueuedSink.counts_written` False and counts
``written`` itself. So ``accepted = written + lost + pending``
(plus what a subclass holds between the two), and nothing goes missing without a count.

Failure policy: an exception from a subclass hook never kills the thread. It
is counted (``failures``), remembered (``last_error``), and the sink's ``state`` is
``"failed"`` until a later item succeeds. The item that failed is lost (counted, not
retried). ``failures`` and ``recoveries`` only ever grow and ``last_error`` is kept after a
recovery, so a failure stays visible (and a test can wait on it) whatever the state is when
one looks; ``failed_since`` is the wall time the current failure began (None when ok). A
subclass may also say the sink is ``"degraded"`` (:meth:`QueuedSink.set_degraded`: working,
but something is wrong, e.g. a child process late with its heartbeat).

Logging is rate-limited per sink (:class:`SinkLog`): the first failure is logged at once, one
line, with a traceback only for an unexpected kind of error (a bug, not a full disk); later
failures and recoveries within ``SinkLog.interval`` are counted and summed up in one line per
interval, so a flapping output never floods the log.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Sequence
from typing import Any

__all__ = ["QueuedSink", "SinkStatus", "SinkLog", "KNOWN_ERRORS"]

log = logging.getLogger("monitor.sinks")

#: errors of the outside world (disk, pipe, child process, time-outs): logged without a traceback
KNOWN_ERRORS: tuple[type[BaseException], ...] = (OSError, EOFError, TimeoutError)


class SinkStatus(dict):
    """Plain ``dict`` snapshot of a sink's counters (JSON-serialisable)."""


class SinkLog:
    """One sink's log lines, at most one every ``interval`` seconds after the first: failures and
    recoveries in between are counted and summed up in the next line (:meth:`flush`)."""

    interval = 30.0

    def __init__(self, name: str) -> None:
        self.name = name
        self._last = -float("inf")
        self._failures = 0  # not yet reported
        self._recoveries = 0
        self._events = 0  # other lines not yet said
        self._error: str | None = None
        self._text: str | None = None  # the last of those lines

    def _due(self) -> bool:
        return time.monotonic() - self._last >= self.interval

    def _emit(self, level: int, msg: str, *args: Any, exc: BaseException | None = None) -> None:
        self._last = time.monotonic()
        log.log(level, msg, *args, exc_info=exc)

    def failure(self, error: str, exc: BaseException | None, first: bool) -> None:
        """A failure (``first``: the sink was ok until now)."""
        self._error = error
        if first and self._due():
            known = exc is None or isinstance(exc, KNOWN_ERRORS)
            self._emit(logging.ERROR, "sink %s failed: %s (failures are counted; this log says more at most every "
                       "%.0f s)", self.name, error, self.interval, exc=None if known else exc)
            return
        self._failures += 1

    def recovery(self, burst: int) -> None:
        if self._due() and not self._failures:
            self._emit(logging.WARNING, "sink %s recovered after %d failure(s)", self.name, burst)
            return
        self._recoveries += 1

    def say(self, level: int, msg: str, *args: Any) -> None:
        """A line about a known condition (a child restarted, a directory made again): at once when due,
        else counted and summed up."""
        if self._due():
            self._emit(level, "sink %s: " + msg, self.name, *args)
        else:
            self._events += 1
            self._text = msg % args if args else msg

    def flush(self, state: str, final: bool = False) -> None:
        """Sum up what was counted since the last line, when the interval is over (worker thread);
        ``final`` (the sink closed): now, if a failure or an event was not said yet."""
        if not (self._failures or self._events) if final else \
                not ((self._failures or self._recoveries or self._events) and self._due()):
            return
        since = time.monotonic() - self._last
        self._emit(logging.WARNING if state in ("ok", "closed") and not self._failures else logging.ERROR,
                   "sink %s, since its last log line (%.0f s): %d more failure(s), %d recover(ies), %d other event(s); "
                   "state %s; last error: %s%s", self.name, since, self._failures, self._recoveries, self._events,
                   state, self._error, f"; last event: {self._text}" if self._text else "")
        self._failures = self._recoveries = self._events = 0
        self._text = None


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
    max_bytes:
        queue capacity in bytes (the ``size`` given to :meth:`offer`; None: items only).
    start:
        start the worker thread now (otherwise call :meth:`start`).
    """

    #: True for sinks whose items are buffered and made durable by :meth:`tick` (a flush):
    #: then only a successful tick clears the failed state
    recover_on_tick = False
    #: False for sinks that count ``written`` (and ``lost``) themselves, when an item is durable
    counts_written = True

    def __init__(
        self,
        maxsize: int = 1024,
        *,
        name: str | None = None,
        tick_interval: float = 0.1,
        max_batch: int = 256,
        batch_interval: float = 0.05,
        max_bytes: int | None = None,
        start: bool = True,
    ) -> None:
        if maxsize < 1:
            raise ValueError(f"queue size must be at least 1, got {maxsize}")
        if not batch_interval > 0:
            raise ValueError(f"batch_interval must be > 0 s, got {batch_interval}")
        if max_bytes is not None and max_bytes < 1:
            raise ValueError(f"max_bytes must be at least 1, got {max_bytes}")
        self.name = name or type(self).__name__
        self.maxsize = int(maxsize)
        self.max_bytes = None if max_bytes is None else int(max_bytes)
        self.tick_interval = float(tick_interval)
        self.max_batch = max(1, int(max_batch))
        self.batch_interval = float(batch_interval)
        self._items: deque[Any] = deque()
        self._sizes: deque[int] = deque()
        self._queued_bytes = 0
        self._wake = threading.Event()  # set by close() and by a full batch: the worker looks at once
        self._lock = threading.Lock()
        self._closing = threading.Event()
        self._deadline = float("inf")  # time.monotonic() by which close() wants the worker done
        self._thread: threading.Thread | None = None
        self.accepted = 0
        self.dropped = 0
        self.written = 0
        self.lost = 0
        self.failures = 0
        self.last_error: str | None = None
        self.failed = False
        self.failed_since: float | None = None  # time.time() of the first failure of the current burst
        self.recoveries = 0  # failed -> ok transitions
        self.degraded: str | None = None  # why the sink works but not as it should (None: it does)
        self.closed = False
        self.busy_since: float | None = None  # time.monotonic() the running hook started (None: idle)
        self._burst = 0  # failures in the current burst
        self.log = SinkLog(self.name)
        if start:
            self.start()

    # ---- producer side (any thread, never blocks) ----------------------------------------
    def offer(self, item: Any, size: int = 0) -> bool:
        """Queue ``item`` (``size`` bytes, counted against ``max_bytes``) for writing; never blocks,
        never wakes the worker (unless a batch is full). False (and ``dropped`` += 1) when full or
        closed."""
        with self._lock:
            if self._closing.is_set() or len(self._items) >= self.maxsize \
                    or (self.max_bytes is not None and self._queued_bytes + size > self.max_bytes):
                self.dropped += 1
                return False
            self._items.append(item)
            self._sizes.append(size)
            self._queued_bytes += size
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
        if self.degraded:
            return "degraded"
        return "ok"

    def status(self) -> SinkStatus:
        """Counters: name, state, accepted, dropped, written, lost, failures, pending, last_error, …"""
        with self._lock:
            return SinkStatus(
                name=self.name,
                state=self.state,
                accepted=self.accepted,
                dropped=self.dropped,
                written=self.written,
                lost=self.lost,
                failures=self.failures,
                recoveries=self.recoveries,
                failed_since=self.failed_since,
                degraded=self.degraded,
                pending=self.pending,
                queued_bytes=self._queued_bytes,
                last_error=self.last_error,
                **self.extra_status(),
            )

    def start(self) -> None:
        """Start the worker thread (done by the constructor unless ``start=False``)."""
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name=f"sink-{self.name}", daemon=True)
        self._thread.start()

    def begin_close(self, timeout: float | None = 10.0) -> None:
        """Stop accepting and let the worker drain and finish, done by ``timeout`` s from now (a
        subclass gives up on what it cannot finish by then, counted); returns at once. Closing
        several sinks: begin each, then :meth:`close` each, so they finish side by side."""
        if self._thread is None:
            self.start()
        with self._lock:
            if not self._closing.is_set():
                self._deadline = time.monotonic() + (float("inf") if timeout is None else max(0.0, timeout))
            self._closing.set()
        self._wake.set()

    def close(self, timeout: float | None = 10.0) -> bool:
        """Stop accepting, drain the queue, call :meth:`finish`, join the thread.

        Returns True when the worker finished within ``timeout`` seconds (False
        leaves a daemon thread still draining). Idempotent.
        """
        self.begin_close(timeout)
        assert self._thread is not None
        self._thread.join(None if timeout is None else max(0.0, self._deadline - time.monotonic()) + 0.5)
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
            self._one(item)

    def start_worker(self) -> None:
        """Called once on the worker thread before the first item (open files here)."""

    def tick(self, now: float) -> None:
        """Periodic work (``now`` = ``time.monotonic()``): flush, rotate, refresh."""

    def finish(self) -> None:
        """Called once on the worker thread after the queue was drained at close."""

    def extra_status(self) -> dict[str, Any]:
        """Extra fields for :meth:`status` (called from any thread; keep it cheap)."""
        return {}

    def set_degraded(self, why: str | None) -> None:
        """Say the sink works but not as it should (None: it does again); shown as state ``degraded``."""
        self.degraded = why

    def count_lost(self, n: int) -> None:
        """``n`` accepted items will never be written (any thread)."""
        if n > 0:
            with self._lock:
                self.lost += n

    def count_written(self, n: int) -> None:
        """``n`` accepted items are written (durable), for sinks that count themselves."""
        if n > 0:
            with self._lock:
                self.written += n

    # ---- worker ------------------------------------------------------------------------------
    def _one(self, item: Any) -> None:
        """One item through :meth:`handle`: written (when this class counts), or lost when it raised."""
        if not self._guard(self.handle, item, durable=not self.recover_on_tick):
            self.count_lost(1)
        elif self.counts_written:
            self.count_written(1)

    def _guard(self, fn, *args, durable: bool = True) -> bool:
        """Run a hook; count and log failures; True on success.

        A success clears the failed state only when ``durable`` (for sinks with
        :attr:`recover_on_tick`, only the periodic :meth:`tick` — the flush — proves recovery:
        an item buffered in memory says nothing about a disk that is still full).
        """
        self.busy_since = time.monotonic()
        try:
            fn(*args)
        except Exception as exc:  # noqa: BLE001 - a sink must never kill the thread
            self._record_failure(exc)
            return False
        finally:
            self.busy_since = None
        if durable:
            self._record_success()
        return True

    def _record_failure(self, exc: BaseException, error: str | None = None) -> None:
        with self._lock:
            self.failures += 1
            self.last_error = error or f"{type(exc).__name__}: {exc}"
            if not self.failed:
                self.failed_since = time.time()
            first = not self.failed
            self.failed = True
            self._burst += 1
        self.log.failure(self.last_error, exc, first)

    def _record_success(self) -> None:
        if not self.failed:
            return
        with self._lock:
            burst, self._burst, self.failed = self._burst, 0, False
            self.failed_since = None
            self.recoveries += 1
        self.log.recovery(burst)

    def _take(self) -> list[Any]:
        """Up to ``max_batch`` waiting items, oldest first."""
        items, sizes = self._items, self._sizes
        with self._lock:
            n = min(len(items), self.max_batch)
            self._queued_bytes -= sum(sizes.popleft() for _ in range(n))
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
                self.log.flush(self.state)
                next_tick = now + self.tick_interval
            if stop:
                break
        self._guard(self.tick, time.monotonic())
        self._guard(self.finish)
        self.closed = True
        self.log.flush(self.state, final=True)  # a failure not said yet is said now

    def _handle_items(self, items: list[Any]) -> None:
        durable = not self.recover_on_tick
        if type(self).handle_batch is QueuedSink.handle_batch:
            for item in items:
                self._one(item)
            return
        if not self._guard(self.handle_batch, items, durable=durable):
            self.count_lost(len(items))
        elif self.counts_written:
            self.count_written(len(items))
