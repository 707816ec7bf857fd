"""Sinks whose work runs in a spawned child process (the MCAP log, the Rerun recording): one
definition of the parent's side — start and handshake, the child's status reports over the pipe,
finishing — and of the child's status reporter.

Protocol: the parent spawns ``target(conn, *args)``; the child answers first with a JSON object
(``{"error": …}`` when it could not start), then sends JSON status reports whenever its status
changed, and a last one with ``"final": true`` after the parent's ``b"Q"``.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import threading
from collections.abc import Callable
from typing import Any, Literal, get_args

from .queued import QueuedSink

__all__ = ["ChildProcessSink", "start_reporter", "send_final", "background_priority", "leave_idle", "check_priority",
           "Priority", "PRIORITIES"]

#: how a sink's child process yields the CPU to the monitor (``feedmon run`` ``[run] sink_priority``)
Priority = Literal["idle", "low"]
PRIORITIES: tuple[str, ...] = get_args(Priority)


def check_priority(priority: str) -> str:
    """``priority`` when it is one of :data:`PRIORITIES`, else ``ValueError`` naming them."""
    if priority not in PRIORITIES:
        raise ValueError(f"sink priority must be one of {', '.join(PRIORITIES)}, got {priority!r}")
    return priority


def background_priority(priority: str) -> str:
    """Put the calling (child) process below the monitor before it starts any thread (threads inherit):
    ``"idle"`` — scheduling class ``SCHED_IDLE`` (Linux): it runs only on a core nothing else wants,
    and a waking estimator thread preempts it at once; ``"low"`` — ``nice`` 10 only: a share of the CPU
    under load, but it can hold a core for a scheduler slice while an estimate waits. Measured at
    333 Hz with both sinks on the 2-core machine (send → estimate p99, two runs each): low 1.82 /
    1.83 ms, idle 0.93 / 0.80 ms; no sink drops either way. Returns what was applied (``"low"`` where
    ``SCHED_IDLE`` is not available)."""
    check_priority(priority)
    try:
        os.nice(10)
    except OSError:
        pass
    if priority == "idle":
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
            return "idle"
        except (AttributeError, OSError):
            return "low"
    return "low"


def leave_idle(pid: int) -> int:
    """Move every thread of process ``pid`` out of ``SCHED_IDLE`` into the normal class (its ``nice`` 10
    kept: the ``"low"`` priority); returns how many threads were moved. Called when a sink is asked to
    finish: no estimate waits any more, and on a machine kept busy by other work an idle-class process
    would get no CPU at all and never finish its file (seen in CI: "sink mcap did not finish within
    30 s"). Linux only (``/proc``); elsewhere, or without permission, nothing is changed."""
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except (OSError, ValueError):
        return 0
    moved = 0
    for tid in tids:  # the policy is per thread: the child's writer threads were started in the idle class
        try:
            if os.sched_getscheduler(tid) == os.SCHED_IDLE:
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
                moved += 1
        except (AttributeError, OSError):
            pass
    return moved


class ChildProcessSink(QueuedSink):
    """A :class:`QueuedSink` whose worker thread feeds a child process over a pipe; ``child_status``
    holds the child's last report. Subclasses call :meth:`_spawn` before ``super().__init__``."""

    finish_timeout = 60.0  # s the parent waits for the child's final report

    def _spawn(self, target, name: str, args: tuple, start_timeout: float, what: str) -> dict[str, Any]:
        """Start ``target(conn, *args)`` in a spawned process and wait for its first message; raises
        ``OSError`` naming ``what`` when it does not come in ``start_timeout`` s or reports an error."""
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=True)
        self._proc = ctx.Process(target=target, name=name, daemon=True, args=(child, *args))
        self._proc.start()
        child.close()
        hello = self._receive(start_timeout)
        if hello is None or "error" in hello:
            self._proc.kill()
            why = "did not start in time" if hello is None else hello["error"]
            raise OSError(f"{what} {why}")
        self.child_status: dict[str, Any] = {}
        return hello

    def _receive(self, timeout: float) -> dict | None:
        try:
            if self._conn.poll(timeout):
                return json.loads(self._conn.recv_bytes())
        except (EOFError, OSError, ValueError):
            pass
        return None

    def _take_reports(self, timeout: float = 0.0) -> bool:
        """Read the child's status reports waiting on the pipe; True once the final one arrived."""
        while True:
            msg = self._receive(timeout)
            if msg is None:
                return False
            self.child_status = msg
            if msg.get("final"):
                return True

    def tick(self, now: float) -> None:
        self._take_reports()

    def finish(self) -> None:
        try:
            leave_idle(self._proc.pid)  # the queue must drain and the file close, however busy the machine
            self._conn.send_bytes(b"Q")
            self._take_reports(self.finish_timeout)
        finally:
            self._proc.join(10.0)
            if self._proc.is_alive():
                self._proc.kill()
            self._conn.close()


def _report(conn, sink, stop: threading.Event, interval: float, extra: dict,
            key: Callable[[dict], Any] | None) -> None:
    """Child thread: send the sink's status (with ``extra``) whenever ``key(status)`` changed (the
    whole status by default), at most every ``interval`` s."""
    last = None
    while not stop.wait(interval):
        st = {**sink.status(), **extra}
        text = json.dumps(st, default=str, sort_keys=True)
        k = text if key is None else key(st)
        if k != last:
            last = k
            try:
                conn.send_bytes(text.encode())
            except (OSError, ValueError):
                return


def start_reporter(conn, sink, interval: float, extra: dict, name: str,
                   key: Callable[[dict], Any] | None = None) -> tuple[threading.Event, threading.Thread]:
    """Start the child's status reporter thread; returns ``(stop, thread)`` for :func:`send_final`."""
    stop = threading.Event()
    thread = threading.Thread(target=_report, args=(conn, sink, stop, interval, extra, key), name=name, daemon=True)
    thread.start()
    return stop, thread


def send_final(conn, sink, extra: dict, reporter: tuple[threading.Event, threading.Thread]) -> None:
    """Child side, after the sink closed: stop the reporter and send the final status."""
    stop, thread = reporter
    stop.set()
    thread.join(5.0)
    try:
        conn.send_bytes(json.dumps({**sink.status(), **extra, "final": True}, default=str).encode())
    except (OSError, ValueError):
        pass
