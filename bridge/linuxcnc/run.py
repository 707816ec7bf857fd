"""``feedmon bridge linuxcnc``: HAL sampler → SampleBlocks on Zenoh (and/or a trial file), and back.

The loop: attach to HAL through the helper (:mod:`bridge.linuxcnc.helper`), check the wiring once
per HAL session (:mod:`bridge.linuxcnc.wiring`), then map every FIFO read into runs of samples
(:mod:`bridge.linuxcnc.mapper`) and send them as blocks of at most ``[publish] block`` samples; a
shorter block leaves when its first sample has waited ``[publish] max_delay`` s. When HAL goes away
(LinuxCNC stopped) the bridge says so, waits and attaches again; the monitor then sees a new session.
The way back (:mod:`bridge.linuxcnc.wayback`) runs on Zenoh's threads beside it.

Latency of one sample to the monitor: the helper's poll (``[hal] poll``, 0.5 ms) plus the block's
wait (none with ``block = 1``) plus mapping and one Zenoh put (tens of µs).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass

import numpy as np
import zenoh

from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import TrialWriter

from .config import BridgeConfig
from .helper import Frame, HalHelper, HalUnavailable
from .mapper import Mapper, Run
from .wayback import WayBack
from .wiring import check_wiring, read_wiring

__all__ = ["Outlet", "blocks_of", "trial_metas", "run_bridge"]

log = logging.getLogger("bridge.linuxcnc")

JSON = zenoh.Encoding.APPLICATION_JSON
#: SampleBlock fields of the mapped axis fields (the rest keep their name)
_FIELD = {"spindle_revs": "spindle_angle", "spindle_speed": "spindle_rpm"}


def blocks_of(cfg: BridgeConfig, run: Run) -> list[S.SampleBlock]:
    """One :class:`~feedio.schema.SampleBlock` per axis of ``run`` (a column an axis lacks: absent;
    ``v_ref``, which the schema requires, all null when the axis has none)."""
    n, t = len(run), run.t.tolist()
    ctx = {name: run.cols[name].tolist() for name in cfg.context()}
    out = []
    for axis, ax in cfg.axes.items():
        cols = {_FIELD.get(f, f): run.cols[f"{axis}.{f}"].tolist() for f in (*ax.pins(), "v_meas")
                if f"{axis}.{f}" in run.cols}
        cols.setdefault("v_ref", [None] * n)
        out.append(S.SampleBlock(machine=cfg.machine, axis=axis, seq=run.seq0, t=t, **cols, **ctx))
    return out


def trial_metas(cfg: BridgeConfig, *, tool: str, version: str) -> list[S.TrialMeta]:
    """The :class:`~feedio.schema.TrialMeta` of each axis of a recording."""
    out = []
    for axis, ax in cfg.axes.items():
        fields = {_FIELD.get(f, f) for f in (*ax.pins(), "v_meas", "v_ref", *cfg.context())}
        out.append(S.TrialMeta(
            Ts=cfg.servo_period, form=ax.resolved_form, machine=cfg.machine, axis=axis,
            provenance=S.Provenance(source="linuxcnc", tool=tool, version=version,
                                    details={"sampler": cfg.sampler, "columns": list(cfg.columns)}),
            units={k: v for k, v in S.UNITS.items() if k in fields or k == "t"},
            description=f"HAL sampler.{cfg.sampler} recorded by the LinuxCNC bridge"))
    return out


class Outlet:
    """Runs → blocks of at most ``block`` samples → Zenoh publishers and/or a trial writer."""

    def __init__(self, cfg: BridgeConfig, publishers: dict | None, writer: TrialWriter | None) -> None:
        self.cfg, self.publishers, self.writer = cfg, publishers, writer
        self.block, self.max_delay = cfg.publish.block, cfg.publish.max_delay
        self._pending: Run | None = None
        self._since = 0.0  # when the pending run's first sample arrived
        self.counters: Counter[str] = Counter()
        self.first_t: float | None = None
        self.last_t: float | None = None

    def add(self, runs: list[Run], now: float) -> None:
        for run in runs:
            if self._pending is not None and run.seq0 != self._pending.end:
                self.flush()
            if self._pending is None and len(run) == self.block:  # as it came: no waiting, no cutting
                self._emit(run)
                continue
            if self._pending is None:
                self._pending, self._since = run, now
            else:
                self._pending = self._pending.join(run)
            n = len(self._pending) // self.block * self.block
            for i in range(0, n, self.block):
                self._emit(self._pending.cut(i, i + self.block))
            if n:
                rest = self._pending.cut(n, len(self._pending))
                self._pending, self._since = (rest, now) if len(rest) else (None, now)

    def due(self, now: float) -> float:
        """Send the pending samples when they have waited ``max_delay``; the seconds until they will."""
        if self._pending is None:
            return self.max_delay or 0.05
        left = self._since + self.max_delay - now
        if left <= 0:
            self.flush()
            return self.max_delay or 0.05
        return left

    def flush(self) -> None:
        if self._pending is not None:
            self._emit(self._pending)
            self._pending = None

    def _emit(self, run: Run) -> None:
        for blk in blocks_of(self.cfg, run):
            data = S.encode(blk)
            if self.publishers is not None:
                try:
                    self.publishers[blk.axis].put(data)
                except Exception as exc:  # noqa: BLE001 - Zenoh errors are plain exceptions; a session closing
                    self.counters["publish_errors"] += 1
                    log.warning("publishing samples of %s failed: %s", blk.axis, exc)
            if self.writer is not None:
                self.writer.write_samples(blk)
            self.counters["messages"] += 1
        self.counters["samples"] += len(run)
        self.first_t = float(run.t[0]) if self.first_t is None else self.first_t
        self.last_t = float(run.t[-1])


@dataclass
class _Said:
    """What was logged already (a burst of the same problem is one line)."""

    waiting: bool = False
    gaps: int = 0
    nonfinite: dict | None = None


def _log_news(mapper: Mapper, said: _Said, overruns: int, before_gaps: int, before_missing: int) -> None:
    if mapper.gaps > before_gaps:
        log.warning("gap: %d sample(s) not delivered by sampler.%d (FIFO overruns since attached: %d; the bridge "
                    "read too late, or the sampler was disabled); the monitor sees the gap",
                    mapper.missing - before_missing, mapper.cfg.sampler, overruns)
    seen = said.nonfinite or {}
    for pin, k in mapper.nonfinite.items():
        if seen.get(pin, 0) == 0 or k >= 10 * seen[pin]:
            log.warning("%s gave %d non-finite value(s) so far: those samples go out as null (the monitor "
                        "rejects them)", pin, k)
            seen[pin] = k
    said.nonfinite = seen


def _attach(cfg: BridgeConfig, wayback: WayBack, said: _Said) -> HalHelper | None:
    """A started helper, or None while HAL is not there (said once)."""
    helper = HalHelper(cfg, wayback.pins(), wayback.links())
    try:
        helper.start()
    except HalUnavailable as exc:
        helper.close()
        if not said.waiting:
            log.warning("waiting for HAL: %s", exc)
            said.waiting = True
        return None
    said.waiting = False
    return helper


def run_bridge(cfg: BridgeConfig, *, session=None, prefix: str = T.DEFAULT_PREFIX, writer: TrialWriter | None = None,
               duration: float | None = None, stop: threading.Event | None = None) -> dict:
    """Run until ``stop`` is set (or ``duration`` s of samples went out); returns the counters.
    Raises :class:`~bridge.linuxcnc.config.ConfigError` when HAL is not wired as ``cfg`` says,
    :class:`~bridge.linuxcnc.helper.HalError` when the helper cannot run."""
    stop = stop or threading.Event()
    publishers = None if session is None else {  # block rather than drop: a late bridge shows as a FIFO gap
        axis: session.declare_publisher(T.samples_key(prefix, cfg.machine, axis), encoding=JSON, express=True,
                                        congestion_control=zenoh.CongestionControl.BLOCK,
                                        priority=zenoh.Priority.DATA_HIGH) for axis in cfg.axes}
    outlet, mapper, said = Outlet(cfg, publishers, writer), Mapper(cfg), _Said()
    helper: HalHelper | None = None
    wayback = WayBack(cfg, prefix, lambda values: helper.set_pins(values) if helper is not None else False)
    if session is not None:
        wayback.subscribe(session)
    hal_session, attaches = None, 0
    try:
        while not stop.is_set():
            helper = _attach(cfg, wayback, said)
            if helper is None:
                stop.wait(cfg.hal.retry)
                continue
            try:
                if helper.hello.session != hal_session:
                    check_wiring(cfg, helper.hello.types, read_wiring(cfg))
                    mapper.new_session()
                    hal_session = helper.hello.session
                attaches += 1
                log.info("attached to sampler.%d (HAL session %d, FIFO depth %d, columns %s, %d stale sample(s) "
                         "discarded; HAL helper pid %d)", cfg.sampler, hal_session, helper.hello.maxdepth,
                         helper.hello.types, helper.hello.stale, helper.hello.pid)
                helper.set_pins(wayback.current())
                _pump(helper, mapper, outlet, wayback, said, stop, duration)
            except HalUnavailable as exc:
                log.warning("HAL went away: %s; attaching again when it is back", exc)
            finally:
                outlet.flush()
                h, helper = helper, None
                h.set_pins({f"{axis}.valid": False for axis in cfg.axes})  # the signals keep what the pins last had
                h.close()
    finally:
        wayback.close()
        for pub in (publishers or {}).values():
            pub.undeclare()
    return {**outlet.counters, "gaps": mapper.gaps, "missing_samples": mapper.missing, "held": mapper.held,
            "sessions": mapper.sessions,
            "attaches": attaches, "nonfinite": dict(mapper.nonfinite), **wayback.counters}


def _pump(helper: HalHelper, mapper: Mapper, outlet: Outlet, wayback: WayBack, said: _Said,
          stop: threading.Event, duration: float | None) -> None:
    wait = outlet.due(time.monotonic())
    while not stop.is_set():
        item = helper.read(min(wait, 0.05))
        if isinstance(item, Frame):  # behind? then every frame already there is mapped at once
            frames, ended = [item], None
            try:
                while len(frames) < 256 and isinstance(more := helper.read(0.0), Frame):
                    frames.append(more)
            except HalUnavailable as exc:  # the frames read before go out first
                ended = exc
            rows = frames[0].rows if len(frames) == 1 else np.concatenate([f.rows for f in frames])
            gaps, missing = mapper.gaps, mapper.missing
            outlet.add(mapper.map(rows, frames[-1].t_read), time.monotonic())
            if mapper.gaps > gaps or mapper.nonfinite:
                _log_news(mapper, said, frames[-1].overruns - helper.hello.overruns, gaps, missing)
            if ended is not None:
                raise ended
        now = time.monotonic()
        wait = outlet.due(now)
        wayback.tick(now)
        if duration is not None and outlet.first_t is not None and outlet.last_t - outlet.first_t >= duration:
            stop.set()
