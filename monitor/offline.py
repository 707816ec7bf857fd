"""The offline twin of the monitor (``feedmon run --from``): a recorded trial through the same
:class:`~monitor.pipeline.Pipeline`, as fast as the machine goes."""

from __future__ import annotations

import heapq
import math
import os
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from functools import partial
from typing import Any

import msgspec

from feedio.limits import DEFAULT, InputLimits

from .axes import AxisRuntime
from .pipeline import Pipeline

__all__ = ["OfflineResult", "run_offline"]


@dataclass
class OfflineResult:
    output: str
    samples: int
    estimates: int
    truth_blocks: int
    seconds: float
    axes: list[str]
    skipped_axes: list[str]

    @property
    def rate(self) -> float:
        return self.samples / self.seconds if self.seconds > 0 else math.inf


def _merged_blocks(path: str, axes: list[str]) -> Iterator[tuple[str, str, int, Any]]:
    """``(axis_name, kind, log_time, block)`` of several axes merged by the time of their last
    sample, from one pass over the file (:func:`feedio.mcapio.iter_axes`)."""
    from feedio.mcapio import iter_axes

    streams = iter_axes(path, axes, kinds=("samples", "truth"))

    def one(idx: int, name: str):
        for j, (kind, lt, b) in enumerate(streams[name]):
            yield float(b.t[-1]), idx, j, name, kind, lt, b

    for _, _, _, name, kind, lt, b in heapq.merge(*(one(i, a) for i, a in enumerate(axes)),
                                                  key=lambda x: (x[0], x[1], x[2])):
        yield name, kind, lt, b


def run_offline(trial: str | os.PathLike, output: str | os.PathLike,
                axes: dict[tuple[str, str], AxisRuntime], *, limits: InputLimits = DEFAULT) -> OfflineResult:
    """Estimate a recorded trial without Zenoh, as fast as the machine goes.

    Every samples block of the axes that have a model goes through the same
    :class:`Pipeline` as in the live monitor; samples and estimates are written
    with :class:`~feedio.mcapio.TrialWriter` (the writer of the MCAP sink) and the
    truth blocks are copied through, each with the log time its input block had (the
    estimates of a block get the log time of its samples), and so do the per-sample
    ``disturbance/scalars`` (:class:`~feedio.scalars.ScalarsPairer`, stamped from those
    log times). The trial's own metadata (with its truth and start time) is kept, with the
    model file and hash added to the provenance details. Chunks follow controller time
    only, so the same input gives the same bytes.
    """
    from feedio.mcapio import TrialWriter, _Open
    from feedio.scalars import ScalarsPairer

    trial, output = os.fspath(trial), os.fspath(output)
    if os.path.abspath(trial) == os.path.abspath(output):
        raise ValueError(f"output {output!r} would overwrite the input trial")
    with _Open(trial) as f:
        present = f.axes()
        metas = {key: f.meta(*key) for key in present if key in axes}
        starts = {f.start_ns(*key) for key in metas}
        has_truth = {(m, a) for (m, a) in metas if f"/{m}/{a}/truth" in f.channels}
    missing = [f"{m}/{a}" for (m, a) in axes if (m, a) not in present]
    if missing:
        raise ValueError(f"{trial} has no axis {', '.join(missing)} (axes present: "
                         f"{', '.join(f'{m}/{a}' for m, a in present) or 'none'}); check the --model files")
    skipped = [f"{m}/{a}" for (m, a) in present if (m, a) not in axes]
    out_metas = []
    for key, meta in metas.items():
        ax = axes[key]
        if ax.model.form != meta.form:
            raise ValueError(f"axis {key[0]}/{key[1]}: model form {ax.model.form!r} but the trial is {meta.form!r}")
        details = dict(meta.provenance.details)
        details.update(estimated_by="feedmon run --from", model_file=ax.status.model_path,
                       model_sha256=ax.status.model_sha256, tracker_state=ax.status.state)
        out_metas.append(msgspec.structs.replace(meta, provenance=msgspec.structs.replace(meta.provenance,
                                                                                           details=details)))
    pipe = Pipeline(axes, limits=limits)
    names = [f"{m}/{a}" for (m, a) in metas]
    pairer = ScalarsPairer(expect_truth=has_truth)
    start = min((s for s in starts if s is not None), default=0)  # files without one: log times as they were
    samples = estimates = truth = 0
    t0 = time.perf_counter()
    with TrialWriter(output, out_metas, start=start) as w, _WriterThread(w) as out:
        for name, kind, lt, block in _prefetch(_merged_blocks(trial, names)):
            if kind == "truth":
                m, a = name.split("/", 1)
                out.put(partial(w.write_truth, block, m, a, log_time=lt))
                if (m, a) in has_truth:
                    out.put(_scalars, w, pairer.add_truth, m, a, block)
                truth += 1
                continue
            samples += len(block.t)
            ax, est = pipe.estimate(block)
            if ax is None:  # refused (too long): counted, not copied, as live
                continue
            out.put(partial(w.write_samples, block, log_time=lt))
            if est is not None:
                out.put(partial(w.write_estimates, est, log_time=lt))
                out.put(_scalars, w, pairer.add_estimates, est, lt)
                estimates += len(est.t)
        out.put(_scalars, w, pairer.drain)
    seconds = time.perf_counter() - t0
    return OfflineResult(output, samples, estimates, truth, seconds, names, skipped)


def _scalars(w, pair, *args) -> None:
    """On the writer thread: feed the pairer (``pair(*args)``) and write the scalars that became
    complete (grouped per axis, order kept)."""
    for batch in pair(*args):
        w.write_scalars_batch(batch)


def _prefetch(items: Iterator, depth: int = 64) -> Iterator:
    """Iterate ``items`` on a second thread (MCAP reading, zstd decompression and JSON decoding
    overlap with the estimation); exceptions are re-raised here, order is kept."""
    q: queue.Queue = queue.Queue(maxsize=depth)
    done = object()
    stop = threading.Event()

    def run() -> None:
        try:
            for item in items:
                if stop.is_set():
                    return
                q.put((None, item))
        except BaseException as exc:  # noqa: BLE001 - re-raised in the consumer
            q.put((exc, None))
        q.put((None, done))

    th = threading.Thread(target=run, name="offline-reader", daemon=True)
    th.start()
    try:
        while True:
            exc, item = q.get()
            if exc is not None:
                raise exc
            if item is done:
                return
            yield item
    finally:
        stop.set()
        while th.is_alive():  # unblock a producer waiting on a full queue
            try:
                q.get_nowait()
            except queue.Empty:
                th.join(0.01)


class _WriterThread:
    """Runs the MCAP writes of :func:`run_offline` on a second thread, in order.

    The tracker loop (``@njit(nogil=True)``) and zstd compression both release the GIL, so
    estimating and encoding/compressing/writing overlap on two cores; one thread and a FIFO
    keep the output byte-identical to writing inline. A write error is raised in the caller.
    """

    def __init__(self, writer, depth: int = 256) -> None:
        self._q: queue.Queue = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="offline-writer", daemon=True)

    def __enter__(self) -> _WriterThread:
        self._thread.start()
        return self

    def put(self, fn, *args) -> None:
        if self._error is not None:
            raise self._error
        self._q.put((fn, args))

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            if self._error is None:
                try:
                    item[0](*item[1])
                except BaseException as exc:  # noqa: BLE001 - re-raised in the caller
                    self._error = exc

    def __exit__(self, *exc) -> None:
        self._q.put(None)
        self._thread.join()
        if self._error is not None and exc[0] is None:
            raise self._error

