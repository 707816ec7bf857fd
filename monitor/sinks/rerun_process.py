"""The Rerun sink in its own process, so Rerun's batching never holds the monitor's GIL.

Measured on the 2-core target at 333 Hz, one sample per message: with the in-process
:class:`~monitor.sinks.rerun_sink.RerunSink` the estimate latency p99 was 5.3 ms (max 29 ms),
without it 1.6 ms. :class:`RerunProcessSink` keeps the sink interface (bounded queue, never
blocks, counts drops) but its worker thread only writes each block's JSON bytes — the same
encoding as on Zenoh, no pickling — to a pipe; a child process decodes them and runs the
:class:`RerunSink` (``.rrd`` file and/or gRPC server, blueprint, PSD).

Wire format on the pipe (``Connection.send_bytes``): one tag byte, then the payload —
``S`` + SampleBlock JSON, ``E`` + EstimateBlock JSON, ``T`` + ``machine\\0axis\\0`` + TruthBlock
JSON, ``V`` + event JSON, ``H`` + health-report JSON, ``A`` + AlarmEvent JSON, ``P`` + ProcessView JSON,
``Q`` to finish (:class:`~monitor.sinks.frames.Tag`). The child answers once at
start (``{"server_uri": ...}`` or ``{"error": ...}``), then with its status whenever its counters
change (at most every ``report_interval`` s) and once at the end (``"final": true``): failures
inside the child count in the parent's ``failures``. It ignores SIGINT/SIGTERM (a service
manager signals the whole process group): it stops when told, or when the pipe closes because
the monitor died, and finishes the recording either way. It runs below the monitor
(:func:`~monitor.sinks.child.background_priority`, default ``nice`` 10), so the monitor's
estimator thread gets the CPU first.
"""

from __future__ import annotations

import json
import os
import signal
from typing import Any

import msgspec

from feedio import schema as S
from feedio.mcapio import held_bytes

from .child import STALL_SECONDS, ChildProcessSink, background_priority, check_priority, send_final, start_reporter
from .frames import Tag

__all__ = ["RerunProcessSink", "check_outputs"]


def check_outputs(rrd_path, serve_port) -> None:
    """Validate the Rerun outputs before anything starts (shared by both Rerun sinks)."""
    if rrd_path is not None:
        d = os.path.dirname(os.path.abspath(os.fspath(rrd_path)))
        if not os.path.isdir(d):
            raise FileNotFoundError(f"directory of the Rerun file {os.fspath(rrd_path)!r} does not exist")
    if serve_port is not None and not (0 < int(serve_port) < 65536):
        raise ValueError(f"serve_port must be a TCP port (1-65535), got {serve_port}")


class RerunProcessSink(ChildProcessSink):
    """A :class:`RerunSink` run in a child process (same arguments, same entities and blueprint),
    supervised and replaced when it stalls or dies (:mod:`monitor.sinks.child`; a new child writes
    a new file, ``<stem>-001.rrd``, … next to ``rrd_path``: :attr:`rrd_files`).

    Its :meth:`status` adds what went wrong inside the children to the sink's own counters: their
    ``failures`` and undecodable messages to ``failures``, their queue drops to ``dropped``, the
    blocks they recorded to ``written``, the blocks they could not record to ``lost``, the last error
    to ``last_error`` (a child reports every ``report_interval`` s while something changes, at
    least every heartbeat, and once more at the end).

    Parameters
    ----------
    rrd_path, serve_port, memory_limit, **rerun_options:
        as for :class:`~monitor.sinks.rerun_sink.RerunSink`.
    start_timeout:
        seconds to wait for the child to import Rerun and open its sinks.
    report_interval:
        seconds between the child's status reports.
    priority:
        "idle" or "low" (:func:`~monitor.sinks.child.background_priority`).
    stall_seconds:
        :data:`~monitor.sinks.child.STALL_SECONDS`.
    maxsize, max_bytes:
        the queue's bounds (items; bytes of the messages).
    """

    incomplete_note = "it has no footer: the viewer opens it as it is, 'rerun rrd optimize' writes it with one"

    def __init__(self, rrd_path=None, serve_port: int | None = None, memory_limit: str = "25%", *,
                 maxsize: int = 4096, max_bytes: int = 64 * 2**20, name: str = "rerun", start_timeout: float = 60.0,
                 report_interval: float = 0.5, priority: str = "low", stall_seconds: float = STALL_SECONDS,
                 **rerun_options) -> None:
        check_outputs(rrd_path, serve_port)
        self.rrd_path = None if rrd_path is None else os.fspath(rrd_path)
        self.rrd_files: list[str] = []
        self._opts = (serve_port, memory_limit, rerun_options, float(report_interval), check_priority(priority))
        hello = self._spawn(start_timeout, stall_seconds)
        self.server_uri: str | None = hello.get("server_uri")
        super().__init__(maxsize, name=name, max_bytes=max_bytes)

    def _child_spec(self, restart: bool):
        path = self.rrd_path
        if path is not None and restart:
            path = _next_free(path)
        if path is not None:
            self.rrd_files.append(path)
        return _child_main, "feedmon-rerun", (path, *self._opts), "the Rerun recording process"

    def _where(self, hello: dict) -> str:
        return f", writing {self.rrd_files[-1]}" if self.rrd_files else ""

    def _current_files(self, report: dict) -> list[str]:
        return self.rrd_files[-1:]

    # ---- producer side ---------------------------------------------------------------------
    def offer_truth(self, machine: str, axis: str, block: S.TruthBlock) -> bool:
        """Queue a :class:`TruthBlock` of ``machine/axis`` (plotted as the true force / dynamometer)."""
        return self.offer((machine, axis, block))

    def offer_alarm(self, event: S.AlarmEvent, received_ns: int | None = None) -> bool:
        """Queue a process alarm (an ERROR line in the event log and a marker on the force panel;
        :meth:`RerunSink.offer_alarm`)."""
        return self.offer(event)

    def offer_process_view(self, view: S.ProcessView) -> bool:
        """Queue a process monitors' view (:meth:`RerunSink.offer_process_view`)."""
        return self.offer(view)

    def offer_event(self, machine: str, axis: str, seq: int, t: float, level: str, text: str) -> bool:
        """Queue one line for the event log of ``machine/axis`` (see :meth:`RerunSink.offer_event`)."""
        return self.offer(("event", {"machine": machine, "axis": axis, "seq": int(seq), "t": float(t),
                                     "level": str(level), "text": str(text)}))

    def offer_health(self, machine: str, axis: str, health: dict[str, Any]) -> bool:
        """Queue a health report (see :meth:`RerunSink.offer_health`)."""
        if isinstance(health, msgspec.Struct):  # a feedio.schema.Health message
            health = msgspec.to_builtins(health)
        return self.offer(("health", {"machine": machine, "axis": axis, "health": dict(health)}))

    def offer(self, item: Any, size: int | None = None) -> bool:
        """Queue an item (``size`` bytes; default: a block's :func:`feedio.mcapio.held_bytes`, 1 KiB else)."""
        if size is None:
            size = held_bytes(item) if isinstance(item, msgspec.Struct) else 1024
        return super().offer(item, size)

    def extra_status(self) -> dict[str, Any]:
        return {"rrd_path": self.rrd_files[-1] if self.rrd_files else self.rrd_path, "rrd_files": list(self.rrd_files),
                "incomplete_files": list(self.incomplete_children), "server_uri": self.server_uri,
                **({"child": c} if (c := self.child_status or self.last_report) else {})}

    # ---- worker side (a thread of the monitor process) ----------------------------------------
    def handle(self, item: Any) -> None:
        self._send(self._wire(item), 1)

    @staticmethod
    def _wire(item: Any) -> bytes:
        if isinstance(item, S.SampleBlock):
            return Tag.SAMPLES + S.encode(item)
        if isinstance(item, S.EstimateBlock):
            return Tag.ESTIMATES + S.encode(item)
        if isinstance(item, S.AlarmEvent):
            return Tag.ALARM + S.encode(item)
        if isinstance(item, S.ProcessView):
            return Tag.PROCESS + S.encode(item)
        if isinstance(item, tuple) and len(item) == 3 and isinstance(item[2], S.TruthBlock):
            return Tag.TRUTH + f"{item[0]}\0{item[1]}\0".encode() + S.encode(item[2])
        if isinstance(item, tuple) and len(item) == 2 and item[0] in ("event", "health"):
            return (Tag.EVENT if item[0] == "event" else Tag.HEALTH) + json.dumps(item[1], allow_nan=False).encode()
        raise TypeError(f"RerunProcessSink accepts SampleBlock, EstimateBlock, (machine, axis, TruthBlock), "
                        f"AlarmEvent, ProcessView, events and health reports, got {type(item).__name__}")


def _next_free(path: str) -> str:
    """``<stem>-001<suffix>``, ``-002`` … next to ``path``: the first name no file has."""
    stem, suffix = os.path.splitext(path)
    for i in range(1, 10_000):
        candidate = f"{stem}-{i:03d}{suffix or '.rrd'}"
        if not os.path.exists(candidate):
            return candidate
    raise FileExistsError(f"9999 names after {path} exist already")


#: bytes of messages the recording process' own queue holds at most
CHILD_QUEUE_BYTES = 64 * 2**20


def _report_key(st: dict) -> tuple:
    """What makes the recording process report: its error counts and state, not every message written."""
    return st["failures"], st["dropped"], st["lost"], st["state"], st.get("broken"), st["undecodable"]


def _child_main(conn, rrd_path, serve_port, memory_limit, options, report_interval=0.5, priority="low") -> None:
    """The recording process: pipe → decode → :class:`RerunSink`."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from .rerun_sink import RerunSink  # (imports first: a process in SCHED_IDLE would take minutes on a busy machine)

    # a recording is background work: the estimator must win every contended core (before Rerun starts
    # its threads, which inherit it)
    background_priority(priority)
    try:
        sink = RerunSink(rrd_path, serve_port, memory_limit, max_bytes=CHILD_QUEUE_BYTES, **options)
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises
        conn.send_bytes(json.dumps({"error": f"{type(exc).__name__}: {exc}"}).encode())
        return
    conn.send_bytes(json.dumps({"server_uri": sink.server_uri}).encode())
    counts = {"undecodable": 0}
    reporter = start_reporter(conn, sink, report_interval, counts, "rerun-report", key=_report_key)
    while True:
        try:
            msg = conn.recv_bytes()
        except (EOFError, OSError):  # the monitor is gone: finish the recording anyway
            break
        tag, body = msg[:1], msg[1:]
        try:
            if tag == Tag.QUIT:
                break
            if tag == Tag.SAMPLES:
                sink.offer(S.decode_samples(body), len(body))
            elif tag == Tag.ESTIMATES:
                sink.offer(S.decode_estimates(body), len(body))
            elif tag == Tag.TRUTH:
                machine, axis, payload = body.split(b"\0", 2)
                sink.offer_truth(machine.decode(), axis.decode(), S.decode_truth(payload))
            elif tag == Tag.EVENT:
                e = json.loads(body)
                sink.offer_event(e["machine"], e["axis"], e["seq"], e["t"], e["level"], e["text"])
            elif tag == Tag.HEALTH:
                h = json.loads(body)
                sink.offer_health(h["machine"], h["axis"], h["health"])
            elif tag == Tag.ALARM:
                sink.offer_alarm(S.decode_alarm(body))
            elif tag == Tag.PROCESS:
                sink.offer_process_view(S.decode_process_view(body))
            else:
                counts["undecodable"] += 1
        except (S.SchemaError, ValueError, KeyError, TypeError):
            counts["undecodable"] += 1
    finished = sink.close(30.0)
    send_final(conn, sink, counts, reporter)
    if not finished or sink.broken:
        # Rerun's writer is stuck (e.g. the disk is full): its exit handlers would wait for ever
        conn.close()
        os._exit(1)
