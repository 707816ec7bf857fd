"""Sinks whose work runs in a spawned child process (the MCAP log, the Rerun recording): one
definition of the parent's side — start and handshake, the child's status reports over the pipe,
supervision and restart, finishing — and of the child's status reporter.

Protocol: the parent spawns ``target(conn, *args)``; the child answers first with a JSON object
(``{"error": …}`` when it could not start), then sends JSON status reports whenever its status
changed and at least every ``heartbeat`` seconds, and a last one with ``"final": true`` after the
parent's :attr:`~monitor.sinks.frames.Tag.QUIT`.

Supervision (the parent's worker thread, :meth:`ChildProcessSink.tick` and every send): the
child is taken for **stalled** when no report came for ``stall_seconds`` (stopped, hung), when it
reports its writer busy in one call for that long (stuck I/O), or when the pipe stayed full that
long (the parent never blocks on it: sends are non-blocking with a deadline) — unless it is only
**starved** of CPU (a thread runnable, less than half a core got since it was last on time: a host
kept busy by other work), which is ``degraded`` and waited for up to :data:`STARVED_STALLS` stall
periods: a replacement would be as starved, and killing it would lose what it holds;
for **dead** when its process ended or the pipe broke. Either way it is killed, what it did not
write is counted (every item sent to it and not reported written, lost or dropped by it, is
``lost``), its file is listed as incomplete (it ends on its last complete record: ``feedmon
recover`` finishes it) and a new child is started with a new file — at once, then after 1, 2,
4 … 60 s while it keeps failing. The sink's state is ``failed`` from then until the new child
reports a write (``degraded`` while a heartbeat is late: the child is moved out of
``SCHED_IDLE`` first, in case it was only starved of CPU). Closing (:meth:`ChildProcessSink.finish`)
asks the child to finish and waits until the deadline :meth:`QueuedSink.begin_close` set; then
it is killed and what it had not written is counted: a stop never waits for a child for longer.
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import multiprocessing.process
import os
import select
import socket
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any, Literal, get_args

from .frames import Tag
from .queued import QueuedSink

__all__ = ["ChildProcessSink", "ChildGone", "cpu_state", "STARVED_STALLS", "start_reporter", "send_final", "background_priority", "leave_idle",
           "check_priority", "Priority", "PRIORITIES", "STALL_SECONDS"]

#: how a sink's child process yields the CPU to the monitor (``feedmon run`` ``[run] sink_priority``)
Priority = Literal["idle", "low"]
PRIORITIES: tuple[str, ...] = get_args(Priority)
#: default seconds without a word from a sink's child (or with its writer stuck, or its pipe full)
#: before it is taken for stalled, killed and replaced (``feedmon run`` ``[run] sink_stall_seconds``)
STALL_SECONDS = 10.0
#: a child starved of CPU is waited for this many ``stall_seconds`` before it is replaced all the same (an
#: endless loop on a host kept busy looks starved too: this bounds it)
STARVED_STALLS = 6
#: the child reports at least this often (s), changed or not: its heartbeat
HEARTBEAT_SECONDS = 0.5
#: seconds of silence, of a full pipe or of a writer busy in one call after which a child is ``degraded``
LATE_SECONDS = 2.0
#: longest wait before restarting a child that keeps failing (s)
MAX_BACKOFF = 60.0
#: counters a child reports that add up over its generations
_COUNTED = ("written", "lost", "dropped", "failures", "undecodable")


def check_priority(priority: str) -> str:
    """``priority`` when it is one of :data:`PRIORITIES`, else ``ValueError`` naming them."""
    if priority not in PRIORITIES:
        raise ValueError(f"sink priority must be one of {', '.join(PRIORITIES)}, got {priority!r}")
    return priority


def background_priority(priority: str) -> str:
    """Put the calling (child) process below the monitor before it starts any thread (threads inherit):
    ``"idle"`` — scheduling class ``SCHED_IDLE`` (Linux): it runs only on a core nothing else wants,
    and a waking estimator thread preempts it at once; ``"low"`` (the default) — ``nice`` 10 only: a
    share of the CPU under load, but it can hold a core for a scheduler slice while an estimate waits.
    ``"low"`` is the default because a log must keep up on a host kept busy by other work, where an
    idle-class child gets no CPU at all and is replaced as stalled, losing messages; ``"idle"`` buys
    about 1 ms of estimate latency at p99 on a quiet host (docs/design-decisions.md). Returns what was applied (``"low"`` where
    ``SCHED_IDLE`` is not available). Called after the child's imports: a process in ``SCHED_IDLE``
    on a busy machine would take minutes to import Rerun."""
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
    finish (no estimate waits any more: on a machine kept busy by other work an idle-class process
    would get no CPU at all and never finish its file — seen in CI: "sink mcap did not finish within
    30 s") and when a child is late with its heartbeat (before it is taken for stalled). Linux only
    (``/proc``); elsewhere, or without permission, nothing is changed."""
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


def _cpu_seconds(pid: int) -> float:
    """CPU seconds process ``pid`` has used, all its threads (``utime + stime`` of ``/proc/<pid>/stat``)."""
    with open(f"/proc/{pid}/stat", "rb") as fh:
        stat = fh.read()
    fields = stat[stat.rindex(b")") + 2:].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_state(pid: int) -> tuple[float, bool] | None:
    """``(CPU seconds process pid has used, whether one of its threads is runnable)`` from ``/proc``;
    ``None`` where that cannot be read (not Linux, the process gone). A stopped (``T``), blocked
    (``D``) or sleeping (``S``) process is not runnable; a starved one is (``R``), most of the time."""
    try:
        cpu = _cpu_seconds(pid)
        for tid in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{tid}/stat", "rb") as fh:
                task = fh.read()
            if task[task.rindex(b")") + 2:task.rindex(b")") + 3] == b"R":
                return cpu, True
        return cpu, False
    except (OSError, ValueError, IndexError):
        return None


class ChildGone(ConnectionError):
    """The child process is dead, stalled or not running (its items are counted lost)."""


class _PipeWriter:
    """Writes messages to the child in :class:`multiprocessing.connection.Connection`'s framing (a
    signed 32-bit big-endian length, then the bytes; what the child's ``recv_bytes`` reads) without
    ever blocking past a deadline: non-blocking sends on the parent's end of the socket pair
    (``MSG_DONTWAIT``, per call: the end stays blocking for the reports read from it)."""

    def __init__(self, conn) -> None:
        self._sock = socket.socket(fileno=os.dup(conn.fileno()))

    def send(self, data: bytes, deadline: float, on_wait: Callable[[float], None] | None = None) -> None:
        """Send one message by ``deadline`` (``time.monotonic()``); :class:`ChildGone` when the child
        is gone or did not take it in time (a message cut short: the stream is then unusable).
        ``on_wait(seconds waited)`` is called about every 0.25 s while the pipe is full."""
        t0 = time.monotonic()
        if len(data) > 0x7FFFFFFF:
            raise ValueError(f"a message to a child process has at most 2**31 − 1 bytes, got {len(data)}")
        for part in (struct.pack("!i", len(data)), data):
            view, pos = memoryview(part), 0
            while pos < len(view):
                try:
                    pos += self._sock.send(view[pos:], socket.MSG_DONTWAIT)
                    continue
                except BlockingIOError:
                    pass
                except OSError as exc:
                    raise ChildGone(f"the pipe to it broke ({type(exc).__name__}: {exc})") from None
                now = time.monotonic()
                if now >= deadline:
                    raise ChildGone(f"it took no data for {now - t0:.0f} s: its pipe stayed full")
                if select.select([], [self._sock], [], min(deadline - now, 0.25))[1] == [] and on_wait is not None:
                    on_wait(time.monotonic() - t0)

    def close(self) -> None:
        self._sock.close()


class _Gen:
    """One child process: its process, pipe, what was sent to it and what it last reported."""

    def __init__(self, proc, conn, hello: dict) -> None:
        self.proc, self.conn, self.hello = proc, conn, hello
        self.writer = _PipeWriter(conn)
        self.sent = 0  # items sent to it whole
        self.report: dict[str, Any] = {}
        self.last_msg = time.monotonic()
        self.started = self.last_msg
        self.final = False
        self.on_time = (self.last_msg, 0.0)  # (time.monotonic(), its CPU seconds) when it was last on time

    def mark_on_time(self, now: float) -> None:
        """Remember its CPU time now, while it is on time (every tick: one read of its ``stat``, not of its threads)."""
        try:
            self.on_time = (now, _cpu_seconds(self.proc.pid))
        except (OSError, ValueError, IndexError):
            pass

    def starved(self, now: float) -> str | None:
        """Why this child counts as starved of CPU rather than stalled (None: it does not): a thread of it
        is runnable and it got less than half a core since it was last on time."""
        state = cpu_state(self.proc.pid)
        if state is None or not state[1]:
            return None
        t0, cpu0 = self.on_time
        share = (state[0] - cpu0) / max(now - t0, 1e-3)
        return f"starved of CPU ({share:.0%} of a core in {now - t0:.0f} s)" if share < 0.5 else None


class ChildProcessSink(QueuedSink):
    """A :class:`QueuedSink` whose worker thread feeds a child process over a pipe, supervises it and
    replaces it when it stalls or dies (module docstring); ``child_status`` holds the current child's
    last report. A subclass implements :meth:`_child_spec` (what to start) and calls :meth:`_spawn`
    before ``super().__init__``; its :meth:`handle_batch` sends through :meth:`_send`."""

    recover_on_tick = True  # a write the child reports, not a send, clears the failed state
    counts_written = False  # the child says what it wrote
    finish_timeout = 60.0  # s the parent waits for the child's final report at most
    #: further counters of the child's reports that add up over its generations
    summed_fields: tuple[str, ...] = ()
    #: lists of the child's reports (files …) that add up over its generations
    list_fields: tuple[str, ...] = ()
    #: what a file a killed child was writing is like, and how to finish it (for the log and the status)
    incomplete_note = "it ends where the process was killed"

    # ---- start -----------------------------------------------------------------------------------
    def _child_spec(self, restart: bool) -> tuple[Callable, str, tuple, str]:
        """``(target, process name, args, what)`` of the next child (``what`` names it in messages);
        ``restart``: it replaces one that failed."""
        raise NotImplementedError

    def _spawn(self, start_timeout: float, stall_seconds: float = STALL_SECONDS) -> dict[str, Any]:
        """Start the first child and wait for its first message; raises ``OSError`` naming it when it
        does not come in ``start_timeout`` s or reports an error."""
        if not stall_seconds > 2 * HEARTBEAT_SECONDS:
            raise ValueError(f"stall_seconds must be > {2 * HEARTBEAT_SECONDS} s (twice the heartbeat), got "
                             f"{stall_seconds!r}")
        self.start_timeout, self.stall_seconds = float(start_timeout), float(stall_seconds)
        self.restarts = 0
        self.idle_left = 0  # times a late child was moved out of SCHED_IDLE (leave_idle)
        self.incomplete_children: list[str] = []  # files of children killed or dead (end on a complete record)
        self._past: Counter[str] = Counter()  # counters of the children that ended
        self._past_lists: dict[str, list] = {k: [] for k in self.list_fields}
        self._gen: _Gen | None = None
        self.last_report: dict[str, Any] = {}  # the last report of the last child that ended
        self._backoff = 0.0
        self._restart_at = 0.0
        self._await_write: int | None = None  # after a failure: the child's written count a write must pass
        self._closing_restart = False  # a restart was tried while closing (one at most)
        self._gen = self._launch(restart=False, deadline=time.monotonic() + self.start_timeout)
        return self._gen.hello

    def _launch(self, restart: bool, deadline: float) -> _Gen:
        """Start a child; wait for its first message until ``deadline``; ``OSError`` when it does not come."""
        target, name, args, what = self._child_spec(restart)
        self._what = what
        ctx = multiprocessing.get_context("spawn")
        conn, child = ctx.Pipe(duplex=True)
        proc = ctx.Process(target=target, name=name, daemon=True, args=(child, *args))
        proc.start()
        child.close()
        hello = None
        # (the deadline of a close begun meanwhile counts too: a stop never waits for a slow start)
        while hello is None and time.monotonic() < min(deadline, getattr(self, "_deadline", deadline)) \
                and proc.is_alive():
            hello = _receive(conn, 0.1)
        if hello is None:
            hello = _receive(conn, 0.0)
        if hello is None or "error" in hello:
            ended = None if proc.is_alive() else proc.exitcode
            _kill(proc)
            conn.close()
            if hello is not None:
                why = hello["error"]
            elif ended is not None:
                why = f"ended at start (exit code {ended})"
            elif getattr(self, "_closing", None) is not None and self._closing.is_set():
                why = "did not start before the deadline of the stop"
            else:
                why = (f"did not start in {self.start_timeout:g} s (start_timeout; a machine this busy, or a slow "
                       "first import)")
            raise OSError(f"{what} {why}")
        gen = _Gen(proc, conn, hello)
        self.child_status: dict[str, Any] = {}
        return gen

    # ---- the parent's status of the children -----------------------------------------------------
    @property
    def _proc(self):
        """The current child's process (None while none runs)."""
        return None if self._gen is None else self._gen.proc

    def _totals(self) -> Counter:
        tot = Counter(self._past)
        c = self.child_status
        for k in (*_COUNTED, *self.summed_fields):
            tot[k] += int(c.get(k, 0) or 0)
        return tot

    def _lists(self) -> dict[str, list]:
        """The :attr:`list_fields` of every child so far (the current one's last report included)."""
        c = self.child_status
        return {k: [*v, *(c.get(k) or [])] for k, v in self._past_lists.items()}

    def status(self):
        st = super().status()
        tot, c = self._totals(), self.child_status
        st["offered"] = st["accepted"] + st["dropped"]
        st["written"] = tot["written"]
        st["lost"] += tot["lost"]
        st["dropped"] += tot["dropped"]
        st["failures"] += tot["failures"] + tot["undecodable"]
        st["pending"] += int(c.get("pending", 0) or 0)
        gen = self._gen
        if gen is not None:  # sent, and not yet reported written, lost or dropped
            st["in_child"] = max(0, gen.sent - sum(int(c.get(k, 0) or 0) for k in _COUNTED if k != "failures"))
        if c.get("last_error") and (c.get("state") == "failed" or not st["last_error"]):
            st["last_error"] = f"{self._what}: {c['last_error']}"  # (the child's own, e.g. a full disk)
        if c.get("state") == "failed" and st["state"] in ("ok", "degraded"):
            st["state"] = "failed"
        elif c.get("state") == "degraded" and st["state"] == "ok":
            st["state"] = "degraded"
            st["degraded"] = c.get("degraded")
        st["restarts"] = self.restarts
        st["incomplete_note"] = self.incomplete_note
        st["process_alive"] = gen is not None and gen.proc.is_alive()
        st["pid"] = None if gen is None else gen.proc.pid
        return st

    # ---- the worker: sending ---------------------------------------------------------------------
    def _live(self) -> _Gen:
        """The running child, started again when it is time; :class:`ChildGone` while there is none."""
        gen = self._gen
        if gen is None:
            if self._closing.is_set():
                if self._closing_restart:
                    raise ChildGone(f"{self._what} is not running (it could not be started again before the stop)")
                self._closing_restart = True  # once, at once: what is still queued may yet be written
                return self._restart()
            if time.monotonic() < self._restart_at:
                raise ChildGone(f"{self._what} is not running (restarting in "
                                f"{self._restart_at - time.monotonic():.0f} s)")
            gen = self._restart()
        return gen

    def _send(self, data: bytes, items: int) -> bool:
        """Send one message holding ``items`` items to the child; False when it could not take it (the
        items counted lost, the failure recorded, the child replaced)."""
        try:
            gen = self._live()
            # a stall: ChildGone after stall_seconds; at close: after the deadline of the stop
            gen.writer.send(data, min(self._deadline, time.monotonic() + STARVED_STALLS * self.stall_seconds),
                            lambda waited: self._waiting(gen, waited))
        except ChildGone as exc:
            self.count_lost(items)
            if self._gen is not None:
                self._replace(f"{self._what} stalled or died: {exc}")
            else:
                self._record_failure(exc, str(exc))
            return False
        gen.sent += items
        return True

    # ---- the worker: supervision -------------------------------------------------------------------
    def _take_reports(self, gen: _Gen, timeout: float = 0.0) -> bool:
        """Read the child's status reports waiting on the pipe; True once the final one arrived."""
        while True:
            msg = _receive(gen.conn, timeout)
            if msg is None:
                return gen.final
            gen.last_msg = time.monotonic()
            gen.report = self.child_status = msg
            if msg.get("final"):
                gen.final = True
                return True

    def _late(self, gen: _Gen, why: str) -> None:
        """The child is late (``why``): ``degraded``, and out of ``SCHED_IDLE`` (starved of CPU? it gets its
        share before it is taken for stalled)."""
        if self.degraded is None:
            self.idle_left += 1  # (counted before the move: who sees the child moved sees the count)
            leave_idle(gen.proc.pid)
        self.set_degraded(f"{self._what} is late: {why}")

    def _waiting(self, gen: _Gen, waited: float) -> None:
        """While a send waits on a full pipe: keep reading the child's reports; late after a while, gone
        after ``stall_seconds`` (or more, while it is only starved of CPU)."""
        self._take_reports(gen)
        if waited > self._late_after:
            starved = self._starved(gen, waited)
            if waited > self.stall_seconds and starved is None:
                raise ChildGone(f"it took no data for {waited:.0f} s: its pipe stayed full")
            self._late(gen, f"its pipe has been full for {waited:.1f} s" + (f", {starved}" if starved else ""))

    def _starved(self, gen: _Gen, late: float) -> str | None:
        """Why ``gen``, late by ``late`` s, is only starved of CPU (kept, up to :data:`STARVED_STALLS` stall
        periods), or None: it is stalled."""
        if late > STARVED_STALLS * self.stall_seconds:
            return None
        return gen.starved(time.monotonic())

    @property
    def _late_after(self) -> float:
        """Seconds of silence (or of a full pipe) after which the child is ``degraded``."""
        return min(LATE_SECONDS, self.stall_seconds / 2)

    def tick(self, now: float) -> None:
        gen = self._gen
        if gen is None:
            if not self._closing.is_set() and now >= self._restart_at:
                self._restart()
            return
        self._take_reports(gen)
        quiet = time.monotonic() - gen.last_msg
        stuck = float(gen.report.get("stuck_s") or 0.0)
        late = max(quiet, stuck)
        starved = self._starved(gen, late) if late > self.stall_seconds else None
        if not gen.proc.is_alive():
            self._replace(f"{self._what} died (exit code {gen.proc.exitcode})")
        elif quiet > self.stall_seconds and starved is None:
            self._replace(f"{self._what} stalled: no word from it for {quiet:.0f} s")
        elif stuck > self.stall_seconds and starved is None:
            self._replace(f"{self._what} stalled: its writer has been busy in one call for {stuck:.0f} s")
        elif late > self._late_after:
            self._late(gen, f"no word from it for {quiet:.1f} s, its writer busy in one call for {stuck:.1f} s"
                       + (f", {starved}" if starved else ""))
        else:
            gen.mark_on_time(now)
            self.set_degraded(None)
            if now - gen.started > MAX_BACKOFF:
                self._backoff = 0.0

    def _record_success(self) -> None:
        # ok again only once the child wrote something after the failure
        if self._await_write is not None:
            written = self._totals()["written"]
            if written <= self._await_write:
                return
            self._await_write = None
        super()._record_success()

    def _record_failure(self, exc: BaseException, error: str | None = None) -> None:
        self._await_write = self._totals()["written"]
        super()._record_failure(exc, error)

    def _retire(self, gen: _Gen, kill: bool) -> int:
        """End ``gen`` (killed when ``kill``), fold its counters into the past ones, count what it did not
        write; returns how many items that is."""
        if kill:
            _kill(gen.proc)
        else:
            gen.proc.join(5.0)
            if gen.proc.is_alive():
                _kill(gen.proc)
        self._take_reports(gen)  # what it said before it went is still in the pipe
        c = gen.report
        for k in (*_COUNTED, *self.summed_fields):
            self._past[k] += int(c.get(k, 0) or 0)
        for k, v in self._past_lists.items():
            v += c.get(k) or []
        accounted = sum(int(c.get(k, 0) or 0) for k in _COUNTED if k != "failures")
        missing = max(0, gen.sent - accounted)
        self.count_lost(missing)
        if not gen.final:
            self.incomplete_children += [f for f in self._current_files(c) if f not in self.incomplete_children]
        gen.writer.close()
        gen.conn.close()
        if self._gen is gen:
            self._gen = None
            self.child_status = {}  # (its counters are in the past ones now)
        self.last_report = c
        return missing

    def _replace(self, why: str) -> None:
        """The child stalled or died: kill it, count its losses, restart it now or after the back-off."""
        gen = self._gen
        files = self._current_files(gen.report) if gen is not None else []
        lost = self._retire(gen, kill=True) if gen is not None else 0
        self._restart_at = time.monotonic() + self._backoff
        self._backoff = min(MAX_BACKOFF, max(1.0, 2 * self._backoff))
        where = f" ({', '.join(files)}: {self.incomplete_note})" if files else ""
        self._record_failure(ChildGone(why), f"{why}: killed it, counted the {lost} item(s) sent to it and not written "
                                               f"as lost{where}, starting a new one")

    def _restart(self) -> _Gen | None:
        """Start a new child (counted in ``restarts``); on failure back off and raise :class:`ChildGone`."""
        try:
            gen = self._launch(restart=True, deadline=min(self._deadline, time.monotonic() + self.start_timeout))
        except OSError as exc:
            self._restart_at = time.monotonic() + self._backoff
            self._backoff = min(MAX_BACKOFF, max(1.0, 2 * self._backoff))
            raise ChildGone(f"could not be started again: {exc}") from None
        self._gen = gen
        self.restarts += 1
        self.log.say(logging.WARNING, "started %s again (restart %d)%s", self._what, self.restarts, self._where(gen.hello))
        return gen

    def _where(self, hello: dict) -> str:
        """`` writing <file>`` of a child's first message (for the log)."""
        return ""

    def _current_files(self, report: dict) -> list[str]:
        """The file(s) a child was writing when it ended (incomplete unless it finished)."""
        return []

    # ---- closing --------------------------------------------------------------------------------
    def finish(self) -> None:
        """Ask the child to finish (``Q``) and wait for its final report — until the deadline of the close,
        or until it stalls (silent, or its writer stuck, for ``stall_seconds``): then kill it and count what
        it had not written."""
        gen = self._gen
        if gen is None:
            return
        deadline = min(self._deadline, time.monotonic() + self.finish_timeout)
        leave_idle(gen.proc.pid)  # the queue must drain and the file close, however busy the machine
        why = None
        try:
            gen.writer.send(Tag.QUIT, min(deadline, time.monotonic() + self.stall_seconds))
            while not self._take_reports(gen, 0.1) and gen.proc.is_alive():
                quiet, stuck = time.monotonic() - gen.last_msg, float(gen.report.get("stuck_s") or 0.0)
                if time.monotonic() >= deadline:
                    why = f"did not finish by the deadline of the stop (no word for {quiet:.0f} s)"
                elif max(quiet, stuck) > self.stall_seconds and self._starved(gen, max(quiet, stuck)) is None:
                    why = f"stalled while finishing (no word for {quiet:.0f} s, its writer busy for {stuck:.0f} s)"
                if why:
                    break
        except ChildGone as exc:
            why = f"stalled or died while finishing: {exc}"
        if gen.final:
            self._retire(gen, kill=False)
            return
        why = why or f"ended without its final report (exit code {gen.proc.exitcode})"
        lost = self._retire(gen, kill=True)
        self._record_failure(ChildGone(why), f"{self._what} {why}: killed it, counted the {lost} item(s) sent to it "
                                               "and not written as lost")


def _receive(conn, timeout: float) -> dict | None:
    try:
        if conn.poll(timeout):
            return json.loads(conn.recv_bytes())
    except (EOFError, OSError, ValueError):
        pass
    return None


def _kill(proc) -> None:
    """SIGKILL (a stopped process dies too) and reap; a process that cannot die at once (uninterruptible
    I/O) is left to the kernel and forgotten by ``multiprocessing``, whose exit handler would otherwise
    wait for it for ever."""
    try:
        proc.kill()
    except (OSError, ValueError, AttributeError):
        pass
    proc.join(2.0)
    if proc.is_alive():
        multiprocessing.process._children.discard(proc)  # noqa: SLF001 - see the docstring


def _report(conn, sink, stop: threading.Event, interval: float, extra: dict,
            key: Callable[[dict], Any] | None) -> None:
    """Child thread: send the sink's status (with ``extra`` and ``stuck_s``, how long its worker has been in
    one call) whenever ``key(status)`` changed (the whole status by default), at most every ``interval``
    s, and at least every :data:`HEARTBEAT_SECONDS` (the heartbeat the parent watches)."""
    last, sent = None, 0.0
    while not stop.wait(min(interval, HEARTBEAT_SECONDS)):
        busy = sink.busy_since
        st = {**sink.status(), **extra, "stuck_s": 0.0 if busy is None else round(time.monotonic() - busy, 3)}
        text = json.dumps(st, default=str, sort_keys=True)
        k = text if key is None else key(st)
        now = time.monotonic()
        if k != last or now - sent >= HEARTBEAT_SECONDS:
            last, sent = k, now
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
