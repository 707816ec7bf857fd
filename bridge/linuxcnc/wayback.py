"""The way back: the monitor's outputs on Zenoh → the bridge's HAL pins, which the user wires.

Per axis the component (``[hal] component``, default ``feedmon``) has the output pins
``<component>.<axis>.<pin>``:

========================  =====  ==============================================================
``force``                 float  the filtered disturbance force (N) of the newest estimate row j
                                 (it describes sample j−1; :class:`~feedio.schema.EstimateBlock`)
``force-sigma``           float  its standard deviation (N)
``valid``                 bit    ``force`` is current: the row is learned (not REJECTED, GAP,
                                 WARMUP), the model scales to newtons, and a row came within
                                 ``[hal] stale_after`` s
``sample``                u32    the counter value (low 32 bits of ``seq``) of row j's sample:
                                 the newest sample the monitor has answered
``health``                s32    the last health report: −1 none yet, 0 ok, 1 warn, 2 alarm
``alarm``                 bit    raised while any alarm source says alarm (wire it to
                                 ``motion.feed-hold`` or ``motion.feed-inhibit``)
========================  =====  ==============================================================

Alarm sources (:data:`ALARM_SOURCES`): each is a Zenoh key per axis and a function deciding, from
one message, whether that source is in alarm (and which further pins it sets). The health reports
(``<prefix>/<machine>/<axis>/health``, ``state == "alarm"``) are the first; the process alarms
(``<prefix>/<machine>/<axis>/alarm``, any :class:`~feedio.schema.AlarmEvent`) hold the pin until an
operator acknowledges them (``<prefix>/<machine>/<axis>/ack``, ``feedmon alarm ack``); another source
plugs in with one more entry. A message that cannot be decoded, or is larger than :data:`MAX_REPORT_BYTES`, is
counted and changes nothing.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import NamedTuple

from feedio import schema as S
from feedio import transport as T

from .config import LINK_PINS, BridgeConfig

__all__ = ["AlarmSource", "ALARM_SOURCES", "WayBack", "HEALTH_CODES", "MAX_REPORT_BYTES"]

log = logging.getLogger("bridge.linuxcnc")

#: the ``health`` pin's values
HEALTH_CODES = {state: i for i, state in enumerate(S.HEALTH_STATES)}
#: a larger message from the monitor's side is refused unread (counted ``too_large``): the monitor's
#: estimate blocks are ~800 bytes per row, its health reports a few kB
MAX_REPORT_BYTES = 1 << 24
_NOT_LEARNED = S.REJECTED | S.GAP | S.WARMUP


class AlarmSource(NamedTuple):
    """``key(prefix, machine, axis)``: what to subscribe; ``decide(payload)``: ``(alarm, {pin: value})``
    from one message (raises ``ValueError`` for a message it cannot read)."""

    key: Callable[[str, str, str], str]
    decide: Callable[[bytes], tuple[bool, dict[str, int]]]
    #: a key whose messages clear the source (an alarm that latches until an operator acknowledges it)
    clear_key: Callable[[str, str, str], str] | None = None


def _health(payload: bytes) -> tuple[bool, dict[str, int]]:
    report = S.decode_health(payload)
    return report.state == "alarm", {"health": HEALTH_CODES[report.state]}


def _process(payload: bytes) -> tuple[bool, dict[str, int]]:
    S.decode_alarm(payload)  # a process alarm (collision, broken tooth, …): feed hold until acknowledged
    return True, {}


#: the alarm sources, by name: an axis' ``alarm`` pin is raised while any of them is in alarm
ALARM_SOURCES: dict[str, AlarmSource] = {
    "health": AlarmSource(T.health_key, _health),
    "process": AlarmSource(T.alarm_key, _process, T.ack_key),
}


class _Axis:
    def __init__(self) -> None:
        self.values: dict[str, float | int | bool] = {"force": 0.0, "force-sigma": 0.0, "valid": False, "sample": 0,
                                                      "health": -1, "alarm": False}
        self.alarms: dict[str, bool] = {}
        self.last = -math.inf  # CLOCK_MONOTONIC of the newest estimate row


class WayBack:
    """Pin values of every axis from the monitor's messages; ``send({pin: value})`` writes them."""

    def __init__(self, cfg: BridgeConfig, prefix: str, send: Callable[[dict], bool]) -> None:
        self.cfg, self.prefix, self.send = cfg, prefix, send
        self.axes = {axis: _Axis() for axis in cfg.axes}
        self.counters: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._subs: list = []

    def pins(self) -> list[tuple[str, str]]:
        """``[(pin, hal type)]`` of the component (pin names relative to it)."""
        return [(f"{axis}.{pin}", kind) for axis in self.axes for pin, kind in LINK_PINS.items()]

    def links(self) -> dict[str, str]:
        return {f"{axis}.{pin}": sig for axis, ax in self.cfg.axes.items() for pin, sig in ax.links.items()}

    def current(self) -> dict[str, float | int | bool]:
        """Every pin's value now (sent again after the helper restarted)."""
        with self._lock:
            return {f"{axis}.{k}": v for axis, ax in self.axes.items() for k, v in ax.values.items()}

    def alarm_state(self, axis: str) -> dict[str, bool]:
        """``{source: in alarm}`` of the sources that spoke for ``axis`` so far."""
        with self._lock:
            return dict(self.axes[axis].alarms)

    def subscribe(self, session) -> None:
        m = self.cfg.machine
        for axis in self.axes:
            self._subs.append(session.declare_subscriber(
                T.disturbance_key(self.prefix, m, axis), lambda s, a=axis: self.estimate(a, s.payload.to_bytes())))
            for name, src in ALARM_SOURCES.items():
                self._subs.append(session.declare_subscriber(
                    src.key(self.prefix, m, axis), lambda s, a=axis, n=name: self.alarm(a, n, s.payload.to_bytes())))
                if src.clear_key is not None:
                    self._subs.append(session.declare_subscriber(
                        src.clear_key(self.prefix, m, axis), lambda s, a=axis, n=name: self.clear(a, n)))

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._subs.clear()

    def _refuse(self, what: str, axis: str, exc: Exception) -> None:
        self.counters[f"malformed_{what}"] += 1
        if self.counters[f"malformed_{what}"] in (1, 10, 100, 1000):
            log.warning("ignoring a %s message for axis %s that cannot be read (%s): %s", what, axis,
                        f"{self.counters[f'malformed_{what}']} so far", exc)

    def estimate(self, axis: str, payload: bytes) -> None:
        """An estimate block: the pins show its newest row."""
        if len(payload) > MAX_REPORT_BYTES:
            self.counters["too_large"] += 1
            return
        try:
            blk = S.decode_estimates(payload)
        except S.SchemaError as exc:
            self._refuse("estimate", axis, exc)
            return
        force = blk.force[-1] if blk.force is not None else None
        var = blk.force_var[-1] if blk.force_var is not None else None
        ok = (force is not None and var is not None and math.isfinite(force) and math.isfinite(var) and var >= 0
              and not blk.flags[-1] & _NOT_LEARNED)
        with self._lock:
            ax = self.axes[axis]
            ax.last = time.monotonic()
            vals = {"sample": (blk.seq + len(blk) - 1) % (1 << 32), "valid": ok}
            if ok:
                vals.update({"force": float(force), "force-sigma": math.sqrt(var)})
            ax.values.update(vals)
            self.counters["estimates"] += 1
        self.send({f"{axis}.{k}": v for k, v in vals.items()})

    def alarm(self, axis: str, source: str, payload: bytes) -> None:
        """A message of an alarm source."""
        if len(payload) > MAX_REPORT_BYTES:
            self.counters["too_large"] += 1
            return
        try:
            raised, extra = ALARM_SOURCES[source].decide(payload)
        except (S.SchemaError, ValueError) as exc:
            self._refuse(source, axis, exc)
            return
        with self._lock:
            ax = self.axes[axis]
            ax.alarms[source] = raised
            vals = {**extra, "alarm": any(ax.alarms.values())}
            if vals["alarm"] != ax.values["alarm"]:
                log.warning("axis %s: alarm %s (%s)", axis, "RAISED" if vals["alarm"] else "cleared",
                            ", ".join(k for k, v in ax.alarms.items() if v) or source)
            ax.values.update(vals)
        self.send({f"{axis}.{k}": v for k, v in vals.items()})

    def clear(self, axis: str, source: str) -> None:
        """An operator acknowledged ``source``'s alarm on ``axis``: it no longer holds the ``alarm`` pin."""
        with self._lock:
            ax = self.axes[axis]
            if not ax.alarms.get(source):
                return
            ax.alarms[source] = False
            vals = {"alarm": any(ax.alarms.values())}
            if vals["alarm"] != ax.values["alarm"]:
                log.warning("axis %s: alarm cleared (%s acknowledged)", axis, source)
            ax.values.update(vals)
        self.send({f"{axis}.{k}": v for k, v in vals.items()})

    def tick(self, now: float) -> None:
        """``valid`` drops when no estimate came for ``stale_after`` s."""
        stale = {}
        with self._lock:
            for axis, ax in self.axes.items():
                if ax.values["valid"] and now - ax.last > self.cfg.hal.stale_after:
                    ax.values["valid"] = False
                    stale[f"{axis}.valid"] = False
        if stale:
            self.send(stale)
