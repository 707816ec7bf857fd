"""Replay an MCAP trial file on Zenoh with its original timing (``feedmon replay``).

What is published
-----------------
For every axis of the file (or the one chosen with ``axis=``):

* each :class:`~feedio.schema.SampleBlock` on ``<prefix>/<machine>/<axis>/samples``;
* each :class:`~feedio.schema.TruthBlock` (simulated trials) on
  ``<prefix>/<machine>/<axis>/truth``.

Payloads are the same JSON as in the file (``feedio.schema.encode``, encoding
``application/json``). With ``block=N`` the samples (and truth) are re-cut into
blocks of N samples; a block never spans a sequence gap of the recording.

Timing
------
A block is sent when its *last* sample would exist on the controller: at
``start + (t[-1] − t0) / rate`` on the monotonic clock, with ``t0`` the first
sample time of the file. Deadlines are absolute, so sleep jitter never
accumulates (no drift over long trials); a late block is sent at once and the
worst lateness is reported. ``rate=None`` (``--max``) sends as fast as the
transport accepts.

Looping (``loop=True`` forever, or ``loop=n`` passes): pass *k* shifts ``seq``
by k × (sample span) and ``t`` by k × (duration + Ts), so the monitor sees one
continuous stream instead of time and sequence numbers jumping backwards.

Congestion control: BLOCK
-------------------------
Publishers are declared with ``CongestionControl.BLOCK`` (reliable): when the
transmission queue towards a slow subscriber is full, ``put`` waits instead of
dropping. Replay exists to feed the monitor a *known* input; a silently dropped
block would show up as a GAP in the estimates and make runs irreproducible.
The price is that a stalled subscriber slows the replay down (visible as
lateness in :class:`ReplayStats`). A live controller bridge, which must keep
real time, should use DROP instead.

Start-up
--------
Zenoh declarations take a few milliseconds to propagate, and a publisher that
starts before the monitor would publish into the void.
``wait_for_subscriber`` seconds (CLI ``--wait``, default 10) are spent waiting
until a subscriber matches the samples key of every axis; the replay then
starts anyway (``ReplayStats.matched`` says whether one was found).
"""

from __future__ import annotations

import heapq
import itertools
import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import msgspec
import zenoh

from feedio import schema as S
from feedio.mcapio import iter_axes, iter_file, list_axes
from feedio.transport import DEFAULT_PREFIX, samples_key, truth_key
from kernels.errors import ParameterError

__all__ = ["ReplayStats", "replay", "scan_trial", "TrialScan"]

_KINDS = ("samples", "truth")


@dataclass
class ReplayStats:
    """Counts of one replay."""

    path: str
    axes: list[str] = field(default_factory=list)
    blocks: int = 0  # sample blocks published
    samples: int = 0  # samples published
    truth_blocks: int = 0
    truth_samples: int = 0
    passes: int = 0  # complete passes over the file
    duration: float = 0.0  # controller time covered (s), all passes
    wall_time: float = 0.0  # s, from the first deadline to the last put
    max_lateness: float = 0.0  # s, worst delay of a put after its deadline (timed replay)
    rate: float | None = 1.0  # None: as fast as possible
    matched: bool = False  # a subscriber matched before the replay started
    interrupted: bool = False  # stopped by Ctrl-C or stop event

    @property
    def speed(self) -> float:
        """Achieved controller-time / wall-time ratio."""
        return self.duration / self.wall_time if self.wall_time > 0 else math.inf


@dataclass
class TrialScan:
    """What one pass over the file contains (per axis ``machine/axis``)."""

    axes: list[str]
    samples: dict[str, int]
    first_seq: dict[str, int]
    end_seq: dict[str, int]  # last seq + 1
    t0: float  # first sample time of the file
    t_end: float  # last sample time of the file
    Ts: float  # median sampling period (for loop shifting)

    @property
    def total_samples(self) -> int:
        return sum(self.samples.values())

    @property
    def duration(self) -> float:
        return self.t_end - self.t0 + self.Ts


def scan_trial(path: str | os.PathLike, axis: str | None = None) -> TrialScan:
    """One decoding pass over the samples channels: axes, sample counts, seq range and time span."""
    path = os.fspath(path)
    axes = list_axes(path)
    if axis is not None:
        hits = [a for a in axes if axis in (a, a.split("/", 1)[1])]
        if not hits:
            raise ValueError(f"{path} has no axis {axis!r}; axes present: {', '.join(axes[:20]) or 'none'}")
        if len(hits) > 1:
            raise ValueError(f"{path}: axis {axis!r} is ambiguous ({', '.join(hits)}); give it as machine/axis")
        axes = hits
    if not axes:
        raise ValueError(f"{path} has no samples channel to replay")
    samples: dict[str, int] = dict.fromkeys(axes, 0)
    first: dict[str, int] = {}
    end: dict[str, int] = {}
    t0, t1 = math.inf, -math.inf
    dts: list[float] = []
    block_steps: list[float] = []  # one-sample blocks: time per sequence step between blocks
    prev: tuple[int, float] | None = None
    for name, _, _, b in iter_file(path, axes, ("samples",)):
        if name not in first:
            first[name] = b.seq
        samples[name] += len(b.t)
        end[name] = b.seq + len(b.t)
        t0 = min(t0, b.t[0])
        t1 = max(t1, b.t[-1])
        if len(dts) < 2000:
            dts.extend(y - x for x, y in zip(b.t, b.t[1:]) if y > x)
        if name == axes[0] and len(block_steps) < 2000:
            if prev is not None and b.t[0] > prev[1] and b.seq > prev[0]:
                block_steps.append((b.t[0] - prev[1]) / (b.seq - prev[0]))
            prev = (b.seq, b.t[0])
    empty = [a for a in axes if samples[a] == 0]
    if empty:
        raise ValueError(f"{path}: axis {empty[0]} has no samples")
    dts = dts or block_steps
    dts.sort()
    ts = dts[len(dts) // 2] if dts else 0.0
    return TrialScan(axes, samples, first, end, float(t0), float(t1), float(ts))


# ---- block manipulation ----------------------------------------------------------------------
def _concat(blocks: list[Any]) -> Any:
    """One block from several contiguous blocks of the same type/axis (optional columns filled with None)."""
    if len(blocks) == 1:
        return blocks[0]
    first = blocks[0]
    out: dict[str, Any] = {}
    for name in first.__struct_fields__:
        if name in ("machine", "axis", "seq"):
            out[name] = getattr(first, name)
            continue
        cols = [getattr(b, name) for b in blocks]
        if all(c is None for c in cols):
            out[name] = None
            continue
        fill = False if name == "glitch" else None
        merged: list = []
        for b, c in zip(blocks, cols):
            merged.extend(c if c is not None else [fill] * len(b.t))
        out[name] = merged
    return type(first)(**out)


def _slice(block: Any, i: int, j: int) -> Any:
    out: dict[str, Any] = {}
    for name in block.__struct_fields__:
        v = getattr(block, name)
        if name in ("machine", "axis"):
            out[name] = v
        elif name == "seq":
            out[name] = v + i
        else:
            out[name] = None if v is None else v[i:j]
    return type(block)(**out)


def _reblock(stream: Iterator[tuple[str, Any]], n: int) -> Iterator[tuple[str, Any]]:
    """Re-cut each kind of a ``(kind, block)`` stream into blocks of ``n`` samples (never across a seq gap)."""
    pending: dict[str, list[Any]] = {}
    count: dict[str, int] = {}
    end: dict[str, int] = {}

    def drain(kind: str, final: bool) -> Iterator[tuple[str, Any]]:
        blocks = pending.get(kind)
        if not blocks:
            return
        big = _concat(blocks)
        m = len(big.t)
        i = 0
        while m - i >= n:
            yield kind, _slice(big, i, i + n)
            i += n
        if final and i < m:
            yield kind, _slice(big, i, m)
            i = m
        pending[kind] = [_slice(big, i, m)] if i < m else []
        count[kind] = m - i

    for kind, block in stream:
        if kind in end and block.seq != end[kind]:
            yield from drain(kind, final=True)  # gap (or overlap): do not glue across it
        pending.setdefault(kind, []).append(block)
        count[kind] = count.get(kind, 0) + len(block.t)
        end[kind] = block.seq + len(block.t)
        if count[kind] >= n:
            yield from drain(kind, final=False)
    for kind in list(pending):
        yield from drain(kind, final=True)


def _shift(block: Any, dseq: int, dt: float) -> Any:
    if dseq == 0 and dt == 0.0:
        return block
    return msgspec.structs.replace(block, seq=block.seq + dseq, t=[x + dt for x in block.t])


def _pass_stream(path: str, scan: TrialScan, block: int | None, k: int,
                 kinds: tuple[str, ...] = _KINDS) -> Iterator[tuple[float, int, str, str, Any]]:
    """All blocks of pass ``k`` of every axis, merged by send time: ``(t_send, axis_index, axis, kind, block)``.
    One pass over the file feeds every axis (:func:`feedio.mcapio.iter_axes`), so the cost is
    linear in the file, whatever the number of axes."""
    streams = iter_axes(path, scan.axes, kinds=kinds)

    def one(idx: int, name: str) -> Iterator[tuple[float, int, int, str, str, Any]]:
        stream: Iterator[tuple[str, Any]] = ((kind, b) for kind, _, b in streams[name])
        if block:
            stream = _reblock(stream, block)
        span = scan.end_seq[name] - scan.first_seq[name]
        dt = k * scan.duration
        for j, (kind, b) in enumerate(stream):
            b = _shift(b, k * span, dt)
            yield float(b.t[-1]), idx, j, name, kind, b

    merged = heapq.merge(*(one(i, a) for i, a in enumerate(scan.axes)), key=lambda x: (x[0], x[1], x[2]))
    for t_send, idx, _, name, kind, b in merged:
        yield t_send, idx, name, kind, b


# ---- replay ----------------------------------------------------------------------------------
def _checked(rate, block, loop, progress) -> tuple[float | None, int | None]:
    """``(rate, passes)`` of :func:`replay`'s arguments (None: as fast as possible / forever), checked."""
    if rate is not None and math.isinf(rate):
        rate = None
    if rate is not None and not rate > 0:
        raise ParameterError(f"rate must be > 0 (or None: as fast as possible), got {rate}", "rate")
    if block is not None and block < 1:
        raise ParameterError(f"block must be at least 1 sample, got {block}", "block")
    if loop is True:
        passes: int | None = None
    elif loop is False:
        passes = 1
    else:
        passes = int(loop)
        if passes < 1:
            raise ParameterError(f"loop must be True/False or a number of passes ≥ 1, got {loop}", "loop")
    if progress is not None and not callable(progress):
        raise ParameterError(f"progress must be a callable progress(sent, total) or None, got {progress!r}",
                             "progress")
    return rate, passes


def _declare(session: zenoh.Session, scan, prefix: str, truth: bool):
    """The publishers of every axis' samples (and truth): ``({(axis, kind): publisher}, all declared)``."""
    pubs: dict[tuple[str, str], zenoh.Publisher] = {}
    declared: list[zenoh.Publisher] = []
    cc = zenoh.CongestionControl.BLOCK
    enc = zenoh.Encoding.APPLICATION_JSON
    for name in scan.axes:
        machine, ax = name.split("/", 1)
        pubs[(name, "samples")] = session.declare_publisher(
            samples_key(prefix, machine, ax), congestion_control=cc, encoding=enc,
            priority=zenoh.Priority.DATA_HIGH,
        )
        declared.append(pubs[(name, "samples")])
        if truth:
            pubs[(name, "truth")] = session.declare_publisher(
                truth_key(prefix, machine, ax), congestion_control=cc, encoding=enc,
            )
            declared.append(pubs[(name, "truth")])

    return pubs, declared


def _wait_for_subscribers(pubs, scan, truth: bool, wait: float, stop, stats: ReplayStats) -> None:
    """Wait up to ``wait`` s for a subscriber of every axis' samples (``stats.matched``), then briefly for
    the truth subscribers."""
    deadline = time.monotonic() + max(0.0, wait)
    sample_pubs = [pubs[(a, "samples")] for a in scan.axes]
    while True:
        stats.matched = all(p.matching_status.matching for p in sample_pubs)
        if stats.matched or time.monotonic() >= deadline or (stop is not None and stop.is_set()):
            break
        time.sleep(0.01)
    if stats.matched and truth:
        # truth subscribers are optional (a monitor records truth only with --record-truth), so do
        # not wait for them the full time; but a recorder that is there usually matches within
        # milliseconds of the samples subscriber: give it a moment before the first put
        truth_pubs = [pubs[(a, "truth")] for a in scan.axes]
        grace = min(deadline, time.monotonic() + 0.5)
        while not all(p.matching_status.matching for p in truth_pubs) and time.monotonic() < grace:
            time.sleep(0.01)


def replay(
    path: str | os.PathLike,
    session: zenoh.Session,
    *,
    rate: float | None = 1.0,
    block: int | None = None,
    loop: bool | int = False,
    prefix: str = DEFAULT_PREFIX,
    progress: Callable[[int, int | None], None] | None = None,
    axis: str | None = None,
    truth: bool = True,
    wait_for_subscriber: float = 0.0,
    stop: Any = None,
) -> ReplayStats:
    """Publish the sample (and truth) blocks of a trial file on ``session``.

    ``rate``: time scale (2.0 = twice as fast); ``None`` or ``math.inf`` = as fast as
    possible. ``block``: re-cut into blocks of this many samples (None: as recorded).
    ``loop``: False = one pass, True = forever, an int = that many passes.
    ``axis``: replay only this axis ("X" or "machine/X"). ``truth``: also publish
    TruthBlocks. ``wait_for_subscriber``: seconds to wait for a subscriber of every
    axis' samples key before starting. ``stop``: a ``threading.Event`` that ends the
    replay early. Ctrl-C also ends it; both set ``interrupted``.

    ``progress(sent, total)`` is called with the samples sent so far and the samples of the whole
    replay (None when looping forever): ``(0, total)`` when sending starts (after the wait for a
    subscriber), then after each sample block. It runs on the sending thread, so it must be quick
    (``feedmon replay`` draws its progress bar with it).

    Raises ``ValueError`` (incl. :class:`feedio.mcapio.TrialFileError`) for a bad
    file or arguments, ``OSError`` if it cannot be read.
    """
    path = os.fspath(path)
    rate, passes = _checked(rate, block, loop, progress)
    if not os.path.exists(path):
        raise FileNotFoundError(f"trial file {path!r} does not exist")

    scan = scan_trial(path, axis)
    stats = ReplayStats(path=path, axes=list(scan.axes), rate=rate)

    pubs, declared = _declare(session, scan, prefix, truth)
    kinds = _KINDS if truth else ("samples",)
    try:
        _wait_for_subscribers(pubs, scan, truth, wait_for_subscriber, stop, stats)

        total = None if passes is None else scan.total_samples * passes
        if progress is not None:
            progress(0, total)
        start = time.monotonic()
        last_put = start
        for k in itertools.count() if passes is None else range(passes):
            for t_send, _, name, kind, b in _pass_stream(path, scan, block, k, kinds):
                if stop is not None and stop.is_set():
                    stats.interrupted = True
                    break
                if rate is not None:
                    due = start + (t_send - scan.t0) / rate
                    wait = due - time.monotonic()
                    if wait > 0:
                        time.sleep(wait)
                pub = pubs.get((name, kind))
                if pub is None:
                    continue  # truth disabled
                pub.put(S.encode(b))
                last_put = time.monotonic()
                if rate is not None:
                    stats.max_lateness = max(stats.max_lateness, last_put - due)
                if kind == "samples":
                    stats.blocks += 1
                    stats.samples += len(b.t)
                    if progress is not None:
                        progress(stats.samples, total)
                else:
                    stats.truth_blocks += 1
                    stats.truth_samples += len(b.t)
            if stats.interrupted:
                break
            stats.passes += 1
            stats.duration += scan.duration
        stats.wall_time = last_put - start
    except KeyboardInterrupt:
        stats.interrupted = True
        stats.wall_time = time.monotonic() - start if "start" in locals() else 0.0
    finally:
        for p in declared:
            try:
                p.undeclare()
            except Exception:  # noqa: BLE001 - session may already be closed
                pass
    return stats
