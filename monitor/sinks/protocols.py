"""What the daemon asks of a sink, as :class:`typing.Protocol` classes: a sink is any object with the
methods of :class:`Sink`; the optional capabilities are separate protocols, checked with ``isinstance``
once when the daemon starts (``runtime_checkable``: the check is on the method names)."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from .frames import Tag

__all__ = ["Sink", "EncodedSink", "HealthSink", "TruthSink", "AlarmSink", "ProcessViewSink", "ClosingSink"]


@runtime_checkable
class Sink(Protocol):
    """Takes the monitor's schema objects (``offer``: a SampleBlock, an EstimateBlock) without blocking."""

    name: str

    def offer(self, item: Any) -> bool: ...

    def close(self, timeout: float) -> bool: ...

    def status(self) -> dict[str, Any]: ...


@runtime_checkable
class EncodedSink(Protocol):
    """Takes messages already encoded (the bytes received and published), tagged with :class:`Tag`
    (``SAMPLES``, ``ESTIMATES``, ``TRUTH`` with ``head = b"machine\\0axis"``); the daemon then offers it no
    objects."""

    def offer_encoded(self, tag: Tag, payload: bytes, received_ns: int, head: bytes = b"") -> bool: ...


@runtime_checkable
class HealthSink(Protocol):
    """Takes the health reports of an axis."""

    def offer_health(self, machine: str, axis: str, report: Any) -> bool: ...


@runtime_checkable
class TruthSink(Protocol):
    """Takes the truth blocks of a simulated axis (a sink without ``offer_encoded``; an encoded sink gets
    them as ``Tag.TRUTH``)."""

    def offer_truth(self, machine: str, axis: str, block: Any) -> bool: ...


@runtime_checkable
class AlarmSink(Protocol):
    """Takes the process monitors' alarms (:class:`~feedio.schema.AlarmEvent`)."""

    def offer_alarm(self, event: Any, received_ns: int | None = None) -> bool: ...


@runtime_checkable
class ProcessViewSink(Protocol):
    """Takes the process monitors' views of an axis (:class:`~feedio.schema.ProcessView`: the dashboard's
    per-tooth panel and limits); the daemon makes them only when such a sink runs."""

    def offer_process_view(self, view: Any) -> bool: ...


@runtime_checkable
class ClosingSink(Protocol):
    """Closes in two steps, so that several sinks finish side by side: ``begin_close`` starts, ``close``
    waits."""

    def begin_close(self, timeout: float) -> None: ...
