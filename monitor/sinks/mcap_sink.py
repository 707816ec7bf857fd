"""``McapSink``: the monitor's MCAP log (samples + estimates of every axis, one file per run).

The file is written with :class:`feedio.mcapio.TrialWriter`, so a monitor log
*is* a trial file: same channels (``/<machine>/<axis>/samples|truth|disturbance``),
same JSON + ``jsonschema`` schemas, zstd chunks, one ``feedmon.trial`` metadata
record per axis. ``feedmon replay`` and :func:`feedio.mcapio.read_trial` read it.
Besides the block channels it writes ``/<machine>/<axis>/disturbance/scalars``: one
message of plain numbers per sample (:mod:`feedio.scalars`) that Foxglove and
``rerun mcap convert`` plot directly.

* Log times are wall-clock times (ns since the Unix epoch): a block's log time is the
  time it was handed to the sink (``offer(item, received_ns=...)`` gives the exact
  receive time; default ``time.time_ns()`` at the offer, right after estimation); the
  scalars of a block are stamped back from it by the controller-time differences
  of the samples, increasing per axis.
* Flushing: a chunk is closed and flushed to the OS at least every
  ``flush_seconds`` (default 0.5 s) of wall time while data arrives, so a crash
  loses about half a second.
* Rotation: with ``rotate_bytes`` and/or ``rotate_seconds`` the sink starts a
  new file when the current one reaches about that size (checked after each
  flush, so files overshoot by up to one chunk) or age. Files are then named
  ``<stem>-000.mcap``, ``<stem>-001.mcap``, ... next to ``path``; without
  rotation the first file is ``path`` itself. :attr:`McapSink.files` lists
  them; every file is complete and self-describing. With ``exclusive`` (the
  process sink of ``feedmon run``) every file is created exclusively: a name that
  exists already (another monitor's log, an older one) is skipped for the next
  number, so no file is ever overwritten or shared. Before a file is opened its directory is made again if it was
  removed, and its free space checked (``min_free_bytes``: ``degraded`` below).
* Failures: a block the writer refuses (an absurd value) is counted and the file goes on.
  A disk that refuses a flush (full, file too large) is counted each time; the bytes wait
  in memory (``pending_bytes`` in the status) and go out with the next flush that works,
  so nothing is lost when space comes back. When more than
  :data:`~feedio.mcapio.MAX_PENDING_BYTES` wait, or the writer failed in any other way,
  the file is given up — it ends on its last complete record, is listed in
  ``incomplete_files`` (finish it with ``feedmon recover``) and what never reached it is
  counted in ``messages_lost`` — and the next block opens a fresh file. A file removed
  or replaced by someone else while written (checked twice a second: the path no
  longer names the open file) is given up, listed in ``removed_files``, its items
  counted in ``removed``, and logging goes on in a new file. These counters
  never go back, and ``last_error`` keeps the last failure after a recovery.
* Accounting: an item is ``written`` once the chunk holding it reached the disk, so
  ``written`` is what the files hold (minus ``removed``); an item whose file was given
  up before that is ``lost``.
* Axes: a TrialWriter needs the :class:`~feedio.schema.TrialMeta` of every
  axis up front. Pass ``metas`` (the monitor knows Ts and form from its model
  files). A block of an axis without meta gets one from ``meta_factory``
  (default: Ts inferred from the block's sample times, form "velocity-loop",
  provenance ``source="live"``, flagged ``details={"inferred": True}``), and,
  if a file is already open, the sink rotates to a new file that declares it
  (TrialWriter cannot add an axis to an open file). Without ``metas`` the first
  file is opened ``discover_seconds`` (default 1 s) after the first block, with
  every axis seen by then, so a multi-axis run does not rotate at start-up.

Items: :class:`SampleBlock`, :class:`EstimateBlock`, ``(machine, axis, TruthBlock)``
(see :meth:`McapSink.offer_truth`) or :class:`Health` (:meth:`McapSink.offer_health`, channel
``/<machine>/<axis>/health``).

In its own process
------------------
The live monitor runs the MCAP log in a child process (:class:`McapProcessSink`), so that
decoding, pairing, JSON encoding, zstd compression and file I/O never hold the monitor's
interpreter lock. The monitor hands it the bytes it already has — each sample block as
received from Zenoh, each estimate block as published (``offer_encoded``) — no pickling, no
second encoding; its worker thread sends what gathered (about every 50 ms) in one write to a
pipe. The child decodes them (the schema checks again: what is logged went through the same
decoder as before) and runs a :class:`McapSink`, so the file is the same as with the sink
in-process. Wire format: frames ``tag (1 byte), received_ns (int64), head length (u32),
payload length (u32), head, payload`` back to back in one pipe message; tags ``S`` sample
block, ``E`` estimate block, ``T`` truth block (head ``machine\0axis``), ``H`` health report
(as published on ``<prefix>/<machine>/<axis>/health``); a pipe message
``Q`` finishes. The child reports its :meth:`McapSink.status` whenever it changes (at most every
``report_interval`` s) and once at the end; the parent's status merges it (files, failures,
drops, ``last_error`` ...). It ignores SIGINT/SIGTERM (the monitor stops it; if the monitor dies,
the pipe closes and it finishes the file anyway), logs like the monitor (same format) and runs
below the monitor, as the Rerun process (:func:`~monitor.sinks.child.background_priority`; default
``nice`` 10): the estimator gets the CPU first. The parent supervises it and replaces a
process that stalls or dies (:mod:`monitor.sinks.child`): what it had not written is counted
``lost``, its file is left ending on its last complete record, and the new process writes a new
file.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import signal
import struct
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from feedio import schema as S
from feedio.mcapio import TrialWriter
from feedio.scalars import HOLD_NS, ScalarsPairer, warm_up

from .child import STALL_SECONDS, ChildProcessSink, background_priority, check_priority, send_final, start_reporter
from .frames import Tag
from .queued import QueuedSink

__all__ = ["McapSink", "McapProcessSink", "infer_meta"]


def infer_meta(machine: str, axis: str, block: Any) -> S.TrialMeta:
    """A best-effort :class:`TrialMeta` for a live axis nobody declared."""
    from feedio import __version__

    ts = None
    t = list(getattr(block, "t", []) or [])
    if len(t) > 1:
        diffs = sorted(b - a for a, b in zip(t, t[1:]) if b > a)
        if diffs:
            ts = diffs[len(diffs) // 2]
    if ts is None or not math.isfinite(ts) or ts <= 0:
        ts = 1.0 / 333.0
    return S.TrialMeta(
        Ts=float(ts),
        form="velocity-loop",
        machine=machine,
        axis=axis,
        provenance=S.Provenance(
            source="live", tool="feedmon run", version=__version__,
            details={"inferred": True, "note": "TrialMeta inferred by McapSink: Ts from sample times, form assumed"},
        ),
        units=dict(S.UNITS),
        description="live monitor log (axis metadata inferred)",
    )


class McapSink(QueuedSink):
    """Queued MCAP writer. See the module docstring.

    Parameters
    ----------
    path:
        output file (``.mcap``); with rotation the counter is inserted before the suffix.
    rotate_bytes, rotate_seconds:
        start a new file at about this size / wall-clock age (None: never).
    metas:
        :class:`TrialMeta` of the axes expected (recommended: the first file is then created by the
        constructor, which raises ``OSError`` naming it when it cannot be).
    meta_factory:
        ``(machine, axis, block) -> TrialMeta`` for undeclared axes (default :func:`infer_meta`).
    flush_seconds:
        close and flush a chunk at least this often (wall clock).
    discover_seconds:
        without ``metas``: buffer this long before opening the first file.
    maxsize, max_bytes:
        queue capacity (blocks; bytes, None: blocks only).
    scalars:
        also write the per-sample ``disturbance/scalars`` channel (default True).
    max_pending_bytes:
        bytes kept in memory while the disk refuses them before a file is given up.
    min_free_bytes:
        when a new file is opened with less free space than this in its directory, the sink is
        ``degraded`` (and says so) until a later file finds enough (0: not checked).
    exclusive:
        create every file exclusively, skipping names that exist (``feedmon run``: a log never
        overwrites nor shares a file); False: ``path`` and its numbered names are overwritten.
    """

    recover_on_tick = True  # writes go to memory; only the flush proves the disk works
    counts_written = False  # an item is written when the chunk holding it is on disk (:meth:`_settle`)
    #: most names tried for one new file before giving up (other writers' files are skipped)
    MAX_NAME_TRIES = 10_000

    def __init__(
        self,
        path: str | os.PathLike,
        rotate_bytes: int | None = None,
        rotate_seconds: float | None = None,
        *,
        metas: S.TrialMeta | Sequence[S.TrialMeta] | None = None,
        meta_factory: Callable[[str, str, Any], S.TrialMeta] | None = None,
        flush_seconds: float = 0.5,
        discover_seconds: float = 1.0,
        maxsize: int = 4096,
        max_bytes: int | None = None,
        name: str = "mcap",
        scalars: bool = True,
        max_pending_bytes: int | None = None,
        min_free_bytes: int = 0,
        exclusive: bool = False,
    ) -> None:
        if rotate_bytes is not None and rotate_bytes <= 0:
            raise ValueError(f"rotate_bytes must be > 0, got {rotate_bytes}")
        if rotate_seconds is not None and rotate_seconds <= 0:
            raise ValueError(f"rotate_seconds must be > 0, got {rotate_seconds}")
        if not flush_seconds > 0:
            raise ValueError(f"flush_seconds must be > 0, got {flush_seconds}")
        self.path = Path(path)
        if not self.path.parent.is_dir():
            raise FileNotFoundError(f"directory of the MCAP log {str(self.path)!r} does not exist")
        self.rotate_bytes = rotate_bytes
        self.rotate_seconds = rotate_seconds
        self.flush_seconds = float(flush_seconds)
        self.min_free_bytes = int(min_free_bytes)
        self.exclusive = bool(exclusive)
        self.meta_factory = meta_factory or infer_meta
        ms = [metas] if isinstance(metas, S.TrialMeta) else list(metas or [])
        self._metas: dict[tuple[str, str], S.TrialMeta] = {(m.machine, m.axis): m for m in ms}
        self.files: list[str] = []
        self.incomplete_files: list[str] = []  # files given up (end on a complete record; feedmon recover)
        self.removed_files: list[str] = []  # files removed (or replaced) by someone else while written
        self.removed = 0  # items written to files that were then removed: gone from the disk
        self.messages_lost = 0  # MCAP messages accepted by a writer but never written to its file
        self.flush_failures = 0  # flushes the disk refused (each one also counted in ``failures``)
        self._writer: TrialWriter | None = None
        self._writer_kw = {} if max_pending_bytes is None else {"max_pending_bytes": int(max_pending_bytes)}
        self._marks: deque[int] = deque()  # per item in the current file not yet on disk: the writer's count after it
        self._file_written = 0  # items of the current file on disk
        self._opened_at = 0.0
        self._checked_at = 0.0  # time.monotonic() the file was last checked to be still there
        self._index = 0
        self._in_file = 0  # messages in the current file
        self.discover_seconds = float(discover_seconds)
        self._held: list[Any] = []  # blocks buffered while discovering axes (no metas given)
        self._held_since = 0.0
        self._pairer = ScalarsPairer() if scalars else None
        self.scalars_written = 0
        super().__init__(maxsize, name=name, tick_interval=min(0.1, self.flush_seconds / 2), max_bytes=max_bytes,
                         start=False)
        if self._metas:
            self._open()  # here, not on the worker: a log that cannot be created is an error of the caller
        self.start()

    # ---- producer helpers ----------------------------------------------------------------
    def offer(self, item: Any, received_ns: int | None = None, size: int = 0) -> bool:
        """Queue ``item``; ``received_ns`` = its receive time (ns since the epoch, default now); ``size``
        its bytes (against ``max_bytes``)."""
        return super().offer((item, time.time_ns() if received_ns is None else int(received_ns)), size)

    def offer_truth(self, machine: str, axis: str, block: S.TruthBlock, received_ns: int | None = None,
                    size: int = 0) -> bool:
        """Queue a :class:`TruthBlock` of ``machine/axis`` (truth blocks carry no axis)."""
        return self.offer((machine, axis, block), received_ns, size)

    def offer_health(self, machine: str, axis: str, report: S.Health, received_ns: int | None = None) -> bool:
        """Queue a :class:`Health` report (channel ``/<machine>/<axis>/health``; ``machine``/``axis`` are
        the report's own)."""
        return self.offer(report, received_ns)

    def offer_alarm(self, event: S.AlarmEvent, received_ns: int | None = None) -> bool:
        """Queue a process :class:`AlarmEvent` (channel ``/<machine>/<axis>/alarm``)."""
        return self.offer(event, received_ns)

    @property
    def rotating(self) -> bool:
        return self.rotate_bytes is not None or self.rotate_seconds is not None

    def extra_status(self) -> dict[str, Any]:
        w = self._writer
        return {"files": list(self.files), "current_file": self.files[-1] if w else None,
                "incomplete_files": list(self.incomplete_files), "removed_files": list(self.removed_files),
                "removed": self.removed, "messages_lost": self.messages_lost, "flush_failures": self.flush_failures,
                "pending_bytes": w.pending_bytes if w else 0, "scalars_written": self.scalars_written,
                "unflushed": len(self._marks) + len(self._held)}

    # ---- worker side -----------------------------------------------------------------------
    def _candidate(self) -> str:
        if not self.rotating and self._index == 0:
            return str(self.path)
        return str(self.path.with_name(f"{self.path.stem}-{self._index:03d}{self.path.suffix or '.mcap'}"))

    def _open(self) -> None:
        """Open the next file: the directory made again if it was removed; with :attr:`exclusive` a name
        nobody uses (created exclusively, so another process' file is never overwritten nor shared)."""
        d = self.path.parent
        if not d.is_dir():
            os.makedirs(d, exist_ok=True)  # OSError: counted by the caller (the item is lost)
            self.log.say(logging.WARNING, "directory %s was gone: made it again", str(d))
        self._check_space(d)
        for _ in range(self.MAX_NAME_TRIES):
            path = self._candidate()
            self._index += 1
            try:
                self._writer = TrialWriter(path, list(self._metas.values()), chunk_seconds=self.flush_seconds,
                                           start=time.time_ns(), exclusive=self.exclusive, **self._writer_kw)
                break
            except FileExistsError:
                continue
        else:
            raise FileExistsError(f"{self.MAX_NAME_TRIES} names after {self._candidate()} exist already next to "
                                  f"{self.path}")
        self._opened_at = time.monotonic()
        self._in_file = 0
        self._file_written = 0
        self.files.append(path)

    def _check_space(self, d: Path) -> None:
        if not self.min_free_bytes:
            return
        try:
            free = shutil.disk_usage(d).free
        except OSError:
            return
        if free < self.min_free_bytes:
            why = f"only {free / 2**20:.1f} MiB free in {d} (less than {self.min_free_bytes / 2**20:.0f} MiB)"
            if why != self.degraded:
                self.log.say(logging.WARNING, "%s", why)
            self.set_degraded(why)
        else:
            self.set_degraded(None)

    def _settle(self, w: TrialWriter) -> None:
        """Count the items of ``w`` whose chunks reached the disk as written."""
        on_disk, marks, n = w.messages_on_disk, self._marks, 0
        while marks and marks[0] <= on_disk:
            marks.popleft()
            n += 1
        self._file_written += n
        self.count_written(n)

    def _close_writer(self) -> None:
        w, self._writer = self._writer, None
        if w is None:
            return
        try:
            w.close()
        finally:
            self._account(w)

    def _account(self, w: TrialWriter) -> None:
        """Book a closed or given-up writer: its items on disk written, the others lost."""
        self._settle(w)
        self.count_lost(len(self._marks))
        self._marks.clear()
        if w.failed is not None and w.path not in self.incomplete_files:
            self.incomplete_files.append(w.path)
        self.messages_lost += w.messages_lost
        w.messages_lost = 0

    def _call(self, fn, *args):
        """Call the writer; if that left it failed, give the file up (the next block opens a new one)."""
        w = self._writer
        try:
            return fn(*args)
        except OSError:
            self.flush_failures += 1
            raise
        finally:
            if w is not None and w.failed is not None and self._writer is w:
                self._writer = None
                try:
                    w.close()
                finally:
                    self._account(w)

    def rotate(self) -> None:
        """Finish the current file and start the next one (worker thread only)."""
        self._close_writer()
        self._open()

    def start_worker(self) -> None:
        if self._metas and self._writer is None and not self.files:
            self._open()  # without metas the first file opens at the first block

    def _ensure_axis(self, machine: str, axis: str, block: Any) -> TrialWriter:
        key = (machine, axis)
        if key not in self._metas:
            meta = self.meta_factory(machine, axis, block)
            if (meta.machine, meta.axis) != key:
                raise ValueError(f"meta_factory returned meta of {meta.machine}/{meta.axis} for {machine}/{axis}")
            self._metas[key] = meta
            if self._writer is not None:
                self.rotate()
        if self._writer is None:
            self._open()
        assert self._writer is not None
        return self._writer

    def handle(self, entry: Any) -> None:
        item, _ = entry
        if self._writer is None and not self.files and self.discover_seconds > 0:
            key = self._axis_of(item)
            if key not in self._metas:
                self._metas[key] = self.meta_factory(key[0], key[1], item)
            if not self._held:
                self._held_since = time.monotonic()
            self._held.append(entry)
            return
        self._write_item(entry)

    def _write_item(self, entry: Any) -> None:
        """Write one item; it is written once its chunk is on disk (:meth:`_settle`), lost if its file
        is given up first."""
        w = self._write(entry)
        if self._writer is w and w.failed is None:
            self._marks.append(w.messages)
            self._in_file += 1
        else:  # the file was given up under it
            self.count_lost(1)

    @staticmethod
    def _axis_of(item: Any) -> tuple[str, str]:
        if isinstance(item, (S.SampleBlock, S.EstimateBlock, S.Health, S.AlarmEvent)):
            return item.machine, item.axis
        if isinstance(item, tuple) and len(item) == 3 and isinstance(item[2], S.TruthBlock):
            return str(item[0]), str(item[1])
        raise TypeError(
            f"McapSink accepts SampleBlock, EstimateBlock, Health or (machine, axis, TruthBlock), got {type(item).__name__}"
        )

    def _release(self) -> None:
        """Open the first file with every axis seen so far and write the held blocks."""
        held, self._held = self._held, []
        try:
            if self._writer is None:
                self._open()
        except Exception:
            self.count_lost(len(held))
            raise
        for entry in held:
            try:
                self._write_item(entry)
            except Exception as exc:  # noqa: BLE001 - counted like any other write failure
                self.count_lost(1)
                self._record_failure(exc)

    def _write(self, entry: Any) -> TrialWriter:
        """Write one item to its file; returns the writer it went to."""
        item, rx = entry
        if isinstance(item, S.SampleBlock):
            w = self._ensure_axis(item.machine, item.axis, item)
            self._call(lambda: w.write_samples(item, log_time=rx))
        elif isinstance(item, S.EstimateBlock):
            w = self._ensure_axis(item.machine, item.axis, item)
            self._call(lambda: w.write_estimates(item, log_time=rx))
            if self._pairer is not None:
                self._write_scalars(self._pairer.add_estimates(item, rx))
        elif isinstance(item, S.Health):
            w = self._ensure_axis(item.machine, item.axis, None)
            self._call(lambda: w.write_health(item, log_time=rx))
        elif isinstance(item, S.AlarmEvent):
            w = self._ensure_axis(item.machine, item.axis, None)
            self._call(lambda: w.write_alarm(item, log_time=rx))
        elif isinstance(item, tuple) and len(item) == 3 and isinstance(item[2], S.TruthBlock):
            machine, axis, block = item
            w = self._ensure_axis(machine, axis, block)
            self._call(lambda: w.write_truth(block, machine, axis, log_time=rx))
            if self._pairer is not None:
                self._write_scalars(self._pairer.add_truth(machine, axis, block))
        else:
            raise TypeError(
                f"McapSink accepts SampleBlock, EstimateBlock, Health or (machine, axis, TruthBlock), got {type(item).__name__}"
            )
        return w

    def _write_scalars(self, ready: list) -> None:
        for batch in ready:
            w = self._ensure_axis(batch.machine, batch.axis, None)
            self._call(w.write_scalars_batch, batch)
            self.scalars_written += len(batch)

    def _removed(self, w: TrialWriter) -> None:
        """The file was removed or replaced under the writer: what it held is gone; go on in a new one."""
        self._writer = None
        why = f"{w.path} was removed or replaced while being written"
        try:
            w.give_up(why)
        except OSError:
            pass
        finally:
            self._account(w)
        gone = self._file_written
        self.removed += gone
        self.removed_files.append(w.path)
        if w.path in self.incomplete_files:  # nothing to finish: it is gone
            self.incomplete_files.remove(w.path)
        self._record_failure(FileNotFoundError(why), f"FileNotFoundError: {why}; {gone} item(s) written to it are gone")
        self._open()  # the directory made again; an OSError here is counted by the worker, retried by the next item

    def tick(self, now: float) -> None:
        if self._held and now - self._held_since >= self.discover_seconds:
            self._release()
        if self._pairer is not None and self._writer is not None:
            self._write_scalars(self._pairer.expire(time.time_ns() - HOLD_NS))
        w = self._writer
        if w is None:
            return
        self._call(w.flush_if_due, now)
        if self._writer is not w:
            return  # given up
        self._settle(w)
        if now - self._checked_at >= self.flush_seconds:  # (one fstat and one stat, twice a second)
            self._checked_at = now
            if w.is_gone():
                self._removed(w)
                return
        if not self._in_file:
            return  # never rotate away from an empty file
        if self.rotate_seconds is not None and now - self._opened_at >= self.rotate_seconds:
            self.rotate()
            return
        if self.rotate_bytes is not None and w.bytes_on_disk >= self.rotate_bytes:
            self.rotate()

    def finish(self) -> None:
        if self._held:
            self._release()
        if self._pairer is not None:
            ready = self._pairer.drain()
            if ready:
                self._write_scalars(ready)
        if self._writer is None and not self.files and self._metas:
            self._open()  # a run without data still leaves a valid (empty) file
        w = self._writer
        if w is not None and w.is_gone():
            self._removed(w)
        self._close_writer()


# ==============================================================================================
# the MCAP log in a child process
# ==============================================================================================
_FRAME = struct.Struct("<cqII")  # tag, received_ns, head length, payload length
_SEND_BYTES = 8 * 2**20  # a pipe message holds the frames of up to about this many bytes


class McapProcessSink(ChildProcessSink):
    """A :class:`McapSink` run in a child process, fed with encoded messages (module docstring),
    supervised and replaced when it stalls or dies (:mod:`monitor.sinks.child`).

    Same arguments as :class:`McapSink` (``metas`` required: the child cannot ask for them),
    plus ``max_bytes`` (the queue's bound in payload bytes, besides ``maxsize`` items; the child's
    queue has the same bounds), ``start_timeout`` (s to wait for the child to start),
    ``stall_seconds`` (:data:`~monitor.sinks.child.STALL_SECONDS`), ``report_interval`` (s between
    the child's status reports) and ``priority`` ("idle" or "low",
    :func:`~monitor.sinks.child.background_priority`). :meth:`status` adds the children's
    counters: ``written`` (items on disk), ``lost``, ``failures`` (with undecodable frames),
    ``dropped`` (with the child's own queue drops), ``last_error``, ``state``, ``restarts`` and the
    MCAP fields (``files``, ``current_file``, ``incomplete_files``, ``removed_files``,
    ``removed``, ``messages_lost``, ``flush_failures``, ``pending_bytes``, ``scalars_written``).
    ``first_file`` is the file the first child opened.
    """

    summed_fields = ("removed", "messages_lost", "flush_failures", "scalars_written")
    incomplete_note = "it ends on its last complete record; feedmon recover finishes it"
    list_fields = ("files", "incomplete_files", "removed_files")
    finish_timeout = 120.0

    def __init__(self, path: str | os.PathLike, rotate_bytes: int | None = None, rotate_seconds: float | None = None,
                 *, metas: S.TrialMeta | Sequence[S.TrialMeta], flush_seconds: float = 0.5, maxsize: int = 4096,
                 max_bytes: int = 64 * 2**20, name: str = "mcap", scalars: bool = True,
                 max_pending_bytes: int | None = None, start_timeout: float = 60.0, report_interval: float = 0.5,
                 priority: str = "low", stall_seconds: float = STALL_SECONDS, min_free_bytes: int = 0) -> None:
        path = Path(path)
        if not path.parent.is_dir():
            raise FileNotFoundError(f"directory of the MCAP log {str(path)!r} does not exist")
        ms = [metas] if isinstance(metas, S.TrialMeta) else list(metas)
        if not ms:
            raise ValueError("McapProcessSink needs the TrialMeta of the axes")
        from monitor.status import log_format

        options = {"flush_seconds": float(flush_seconds), "maxsize": int(maxsize), "max_bytes": int(max_bytes),
                   "scalars": bool(scalars), "max_pending_bytes": max_pending_bytes,
                   "min_free_bytes": int(min_free_bytes), "exclusive": True}
        self._args = (os.fspath(path), rotate_bytes, rotate_seconds, [S.encode(m) for m in ms], options,
                      float(report_interval), log_format(), check_priority(priority))
        self.path = path
        hello = self._spawn(start_timeout, stall_seconds)
        self.first_file: str = (hello.get("files") or [os.fspath(path)])[0]
        super().__init__(maxsize, name=name, max_bytes=max_bytes)

    def _child_spec(self, restart: bool):
        return _child_main, "feedmon-mcap", self._args, "the MCAP logging process"

    def _where(self, hello: dict) -> str:
        return f", writing {hello['files'][0]}" if hello.get("files") else ""

    def _current_files(self, report: dict) -> list[str]:
        cur = report.get("current_file")
        return [cur] if cur else []

    # ---- producer side ---------------------------------------------------------------------
    def offer_encoded(self, tag: Tag, payload: bytes, received_ns: int, head: bytes = b"") -> bool:
        """Queue one encoded message: ``tag`` ``SAMPLES`` (a SampleBlock as received), ``ESTIMATES`` (an
        EstimateBlock as published), ``HEALTH`` (a Health report) or ``TRUTH`` (a TruthBlock, ``head`` =
        ``b"machine\\0axis"``);
        ``received_ns`` its log time (ns since the epoch). Refused and counted (``dropped``) when the
        queue holds ``maxsize`` items or ``max_bytes`` payload bytes."""
        return QueuedSink.offer(self, (tag, int(received_ns), head, payload), len(payload) + len(head))

    def offer(self, item: Any, received_ns: int | None = None) -> bool:
        """Queue a :class:`SampleBlock`, :class:`EstimateBlock` or :class:`Health` (encoded here)."""
        rx = time.time_ns() if received_ns is None else int(received_ns)
        if isinstance(item, S.SampleBlock):
            return self.offer_encoded(Tag.SAMPLES, S.encode(item), rx)
        if isinstance(item, S.EstimateBlock):
            return self.offer_encoded(Tag.ESTIMATES, S.encode(item), rx)
        if isinstance(item, S.Health):
            return self.offer_encoded(Tag.HEALTH, S.encode(item), rx)
        if isinstance(item, S.AlarmEvent):
            return self.offer_encoded(Tag.ALARM, S.encode(item), rx)
        raise TypeError(f"McapProcessSink accepts SampleBlock, EstimateBlock or Health, got {type(item).__name__}")

    def offer_truth(self, machine: str, axis: str, block: S.TruthBlock, received_ns: int | None = None) -> bool:
        """Queue a :class:`TruthBlock` of ``machine/axis``."""
        rx = time.time_ns() if received_ns is None else int(received_ns)
        return self.offer_encoded(Tag.TRUTH, S.encode(block), rx, f"{machine}\0{axis}".encode())

    def offer_health(self, machine: str, axis: str, report: S.Health, received_ns: int | None = None) -> bool:
        """Queue a :class:`Health` report (channel ``/<machine>/<axis>/health``; see
        :meth:`McapSink.offer_health`)."""
        return self.offer(report, received_ns)

    def offer_alarm(self, event: S.AlarmEvent, received_ns: int | None = None) -> bool:
        """Queue a process :class:`AlarmEvent` (channel ``/<machine>/<axis>/alarm``)."""
        return self.offer(event, received_ns)

    # ---- status ----------------------------------------------------------------------------
    def extra_status(self) -> dict[str, Any]:
        c, tot, lists = self.child_status, self._totals(), self._lists()
        incomplete = lists["incomplete_files"] + [f for f in self.incomplete_children
                                                  if f not in lists["incomplete_files"]]
        return {"files": lists["files"], "current_file": c.get("current_file"), "incomplete_files": incomplete,
                "removed_files": lists["removed_files"], **{k: tot[k] for k in self.summed_fields},
                "pending_bytes": int(c.get("pending_bytes", 0) or 0), "undecodable": tot["undecodable"]}

    # ---- worker side (a thread of the monitor process) ----------------------------------------
    def handle_batch(self, items: Sequence[Any]) -> None:
        parts: list[bytes] = []
        size = count = 0
        for tag, rx, head, payload in items:
            parts += (_FRAME.pack(tag, rx, len(head), len(payload)), head, payload)
            size += len(head) + len(payload) + _FRAME.size
            count += 1
            if size >= _SEND_BYTES:  # one pipe message of at most about this much
                self._send(b"".join(parts), count)
                parts, size, count = [], 0, 0
        if parts:
            self._send(b"".join(parts), count)


def _child_main(conn, path, rotate_bytes, rotate_seconds, metas, options, report_interval, log_format,
                priority) -> None:
    """The logging process: pipe → decode → :class:`McapSink`."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from monitor.status import install_log_format

    warm_up()  # (its compiled code loaded before the priority drops)
    background_priority(priority)

    install_log_format(log_format)
    try:
        sink = McapSink(path, rotate_bytes, rotate_seconds, metas=[S.decode_meta(m) for m in metas],
                        **{k: v for k, v in options.items() if v is not None})
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises
        conn.send_bytes(json.dumps({"error": f"{type(exc).__name__}: {exc}"}).encode())
        return
    conn.send_bytes(json.dumps({"files": sink.files}).encode())
    counts = {"undecodable": 0}
    reporter = start_reporter(conn, sink, report_interval, counts, "mcap-report")
    frame = _FRAME.size
    while True:
        try:
            msg = conn.recv_bytes()
        except (EOFError, OSError):  # the monitor is gone: finish the file anyway
            break
        if msg == Tag.QUIT:
            break
        view, pos, end = memoryview(msg), 0, len(msg)
        while pos < end:
            try:
                tag, rx, nh, npl = _FRAME.unpack_from(view, pos)
            except struct.error:
                counts["undecodable"] += 1
                break
            head = bytes(view[pos + frame:pos + frame + nh])
            payload = view[pos + frame + nh:pos + frame + nh + npl]
            pos += frame + nh + npl
            size = nh + npl
            try:
                if tag == Tag.SAMPLES:
                    sink.offer(S.decode_samples(payload), rx, size)
                elif tag == Tag.ESTIMATES:
                    sink.offer(S.decode_estimates(payload), rx, size)
                elif tag == Tag.TRUTH:
                    machine, axis = head.decode().split("\0", 1)
                    sink.offer_truth(machine, axis, S.decode_truth(payload), rx, size)
                elif tag == Tag.HEALTH:
                    sink.offer(S.decode_health(payload), rx, size)
                elif tag == Tag.ALARM:
                    sink.offer(S.decode_alarm(payload), rx, size)
                else:
                    counts["undecodable"] += 1
            except (S.SchemaError, ValueError):
                counts["undecodable"] += 1
    finished = sink.close(60.0)
    send_final(conn, sink, counts, reporter)
    if not finished:
        conn.close()
        os._exit(1)
