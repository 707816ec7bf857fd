"""The status document a monitor answers (``feedmon status --json``), as msgspec Structs: one typed
definition for the daemon that builds it (:meth:`monitor.daemon.Monitor.status`) and ``feedmon status``
that prints it (:func:`monitor.status.format_status`).

The JSON is the Structs' fields in their order (``msgspec.to_builtins``, then ``json.dumps`` as
before); the sections whose keys vary with the peer or the sink kind stay plain objects
(``limits``, a sink's status, an axis' health and input verdicts, counters by name). Every field
has a default so that a reader can take the document of another feedmon version, or of a hostile
peer, section by section (:func:`lenient`): a section of the wrong shape reads as its default.
"""

from __future__ import annotations

from typing import Any, TypeVar

import msgspec

__all__ = ["MonitorInfo", "InputInfo", "Served", "Latency", "Percentiles", "AxisModelRef", "AxisStateRef",
           "AxisReport", "StatusDoc", "lenient", "to_builtins"]

T = TypeVar("T")


class MonitorInfo(msgspec.Struct, kw_only=True):
    """``monitor``: which process, since when."""

    version: str | None = None
    pid: int | None = None
    host: str | None = None
    prefix: str | None = None
    state: str | None = None  #: starting | running | stopping | stopped
    started_unix: float | None = None  #: s since the Unix epoch
    uptime_s: float | None = None
    endpoints: list[str] = []


class InputInfo(msgspec.Struct, kw_only=True):
    """``input``: messages taken, queued and refused (by reason), over all axes."""

    received: int = 0
    inline: int = 0  #: of them, estimated in the Zenoh callback
    handled: int = 0
    pending: int = 0  #: messages in the input queue
    capacity: int = 0
    pending_bytes: int = 0
    capacity_bytes: int = 0
    queue_full: int = 0
    too_large: int = 0
    malformed: int = 0
    key_mismatch: dict[str, int] = {}  #: per key (bounded; the rest in ``key_mismatch_overflow``)
    key_mismatch_overflow: int = 0
    key_mismatch_total: int = 0
    no_model: dict[str, int] = {}  #: samples per axis without a model (bounded; the rest in the overflow)
    no_model_overflow: int = 0
    no_model_blocks: int = 0
    shutdown_discarded: int = 0
    truth_blocks: int = 0
    malformed_truth: int = 0
    truth_no_model: int = 0
    publish_errors: int = 0
    internal_errors: int = 0


class Served(msgspec.Struct, kw_only=True):
    """``status``: status queries answered and refused (rate limit)."""

    served: int = 0
    refused: int = 0


class Latency(msgspec.Struct, kw_only=True):
    """Latency from arrival to publish, µs (None before the first message)."""

    p50: float | None = None
    p99: float | None = None
    count: int = 0


class Percentiles(msgspec.Struct, kw_only=True):
    """One stage's time, µs (None before the first message)."""

    p50: float | None = None
    p99: float | None = None


class AxisLatency(msgspec.Struct, kw_only=True):
    """An axis' latency, µs, over the last ``window`` messages (``count`` in all)."""

    p50: float | None = None
    p99: float | None = None
    max: float | None = None
    count: int = 0
    window: int = 0


class AxisModelRef(msgspec.Struct, kw_only=True):
    """The model file an axis runs with."""

    path: str | None = None
    sha256: str | None = None


class AxisStateRef(msgspec.Struct, kw_only=True):
    """Where the axis' tracker state came from (fresh | restored | ignored | unreadable) and its file."""

    origin: str | None = None
    path: str | None = None


class AxisReport(msgspec.Struct, kw_only=True):
    """``axes[<machine>/<axis>]``: counts, latency, model, state, health and input verdicts of one axis."""

    machine: str | None = None
    axis: str | None = None
    samples_in: int = 0
    estimates_out: int = 0
    blocks: int = 0
    trained: int = 0
    gaps: int = 0
    missing_samples: int = 0
    stale: int = 0
    restarts: int = 0
    drops: dict[str, int] = {}  #: samples dropped, by reason (only reasons that occurred)
    dropped_total: int = 0
    counters: dict[str, int] = {}
    latency_us: AxisLatency = msgspec.field(default_factory=AxisLatency)
    stages_us: dict[str, Percentiles] = {}
    dict_size: int = 0
    last_seq: int | None = None
    last_t: float | None = None
    model: AxisModelRef = msgspec.field(default_factory=AxisModelRef)
    state: AxisStateRef = msgspec.field(default_factory=AxisStateRef)
    health: dict[str, Any] | None = None  #: the last health report, since when its state holds, changes
    input: dict[str, Any] | None = None  #: the input-health verdict (:meth:`monitor.input_health.InputHealth.status`)
    #: the process monitors' verdict (:meth:`monitor.process_monitor.monitor.AxisProcessMonitor.status`; None: off)
    process: dict[str, Any] | None = None


class StatusDoc(msgspec.Struct, kw_only=True):
    """The whole document."""

    monitor: MonitorInfo = msgspec.field(default_factory=MonitorInfo)
    input: InputInfo = msgspec.field(default_factory=InputInfo)
    limits: dict[str, Any] = {}  #: :class:`feedio.limits.InputLimits` in force
    status: Served = msgspec.field(default_factory=Served)
    latency_us: Latency = msgspec.field(default_factory=Latency)
    stages_us: dict[str, Percentiles] = {}
    axes: dict[str, AxisReport] = {}
    sinks: list[dict[str, Any]] = []  #: each sink's own status (keys vary with the kind of sink)


def _as_json_did(obj: Any) -> Any:
    """What ``json.dumps(default=str)`` made of a value msgspec does not know: a float subclass (a numpy
    float) stays a number, anything else becomes its text."""
    return float(obj) if isinstance(obj, float) else str(obj)


def to_builtins(doc: msgspec.Struct) -> dict[str, Any]:
    """The JSON-ready dict of a document, fields in order; the sinks' free-form sections come out as
    ``json.dumps(..., default=str)`` wrote them before the document was typed."""
    return msgspec.to_builtins(doc, enc_hook=_as_json_did)


def lenient(value: Any, type_: type[T]) -> T:
    """``value`` as ``type_`` if it has that shape, else ``type_()`` (every field at its default): how a
    reader takes a section of a document that may come from any peer."""
    try:
        return msgspec.convert(value, type_)
    except (msgspec.ValidationError, TypeError):
        return type_()
