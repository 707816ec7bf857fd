"""Every input limit of feedmon and its default, in one place.

Two kinds:

* **Contract bounds** (module constants): what a valid message may hold at all. The schema
  (:mod:`feedio.schema`) enforces them on decode and on construction, and writes them into the
  JSON Schemas it generates; they are not configurable because a bridge and a monitor must agree
  on them. Names are ``NAME_PATTERN`` (ASCII letters, digits, ``_ . -``; 1 … ``NAME_MAX_LEN``
  characters, not starting with ``.`` or ``-``): safe in Zenoh keys, file names, log lines and
  tables. ``0 ≤ seq`` and ``seq + len(block) − 1 ≤ SEQ_MAX = 2**53 − 1`` (every sequence number is
  exact as an int64 and as a float64). Controller time ``0 ≤ t ≤ T_MAX`` s (317 years; a larger
  time cannot be an MCAP log time, whose limit is 2**64 ns ≈ 1.8e10 s). A block holds at most
  ``BLOCK_SAMPLES_MAX`` samples (the top of the configurable ``max_block_samples`` range).
* **Resource limits** (:class:`InputLimits`, configurable: ``[run.limits]`` in the ``feedmon run
  --config`` file or ``--limit NAME=VALUE``): message size, block length, input queue, unknown
  axes, status queries. Each field documents its allowed range (``msgspec.Meta``), which decoding
  a config file checks.

Per-sample physical limits (:data:`PHYSICAL`, :data:`LIMITS`): a value beyond them is physically
absurd for a machine-tool axis; the estimator REJECTs that one sample (row emitted with NaN
estimates) and counts ``rejected_out_of_range``; the rest of the block is used.

What happens beyond each limit, and which status counter counts it, is in the README ("Input
limits"); ``tests/test_limits.py`` checks that table against this module.
"""

from __future__ import annotations

import re
from typing import Annotated, Any

import msgspec

__all__ = [
    "NAME_PATTERN",
    "NAME_RE",
    "NAME_MAX_LEN",
    "SEQ_MAX",
    "T_MAX",
    "BLOCK_SAMPLES_MAX",
    "PhysicalLimits",
    "PHYSICAL",
    "LIMITS",
    "InputLimits",
    "DEFAULT",
    "field_range",
    "range_text",
]

# ---- contract bounds (schema) ---------------------------------------------------------------
NAME_MAX_LEN = 64
#: machine and axis names (JSON Schema ``pattern``; anchored, so also valid as an ECMA regex)
NAME_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$"
NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")  # use with fullmatch (``$`` allows a final newline)
SEQ_MAX = 2**53 - 1
T_MAX = 1e10  # s
BLOCK_SAMPLES_MAX = 1_000_000


class PhysicalLimits(msgspec.Struct, frozen=True):
    """Per-sample magnitudes beyond which a value is absurd for a machine-tool axis (SI)."""

    v_max: float = 50.0  # |velocity| (m/s): v_ref, v_meas
    u_max: float = 1e7  # |force command| (N)
    t_max: float = T_MAX  # |controller time| (s)
    spindle_rpm_max: float = 200_000.0  # |spindle speed| (rpm): faster is unusable (the tracker falls back)


PHYSICAL = PhysicalLimits()
#: the estimator's view of :data:`PHYSICAL` (``monitor.estimator`` uses it)
LIMITS = {"v": PHYSICAL.v_max, "u": PHYSICAL.u_max, "t": PHYSICAL.t_max}


# ---- resource limits (configurable) ---------------------------------------------------------
def _int(lo: int, hi: int, doc: str) -> Any:
    return Annotated[int, msgspec.Meta(ge=lo, le=hi, description=doc)]


def _float(lo: float, hi: float, doc: str) -> Any:
    return Annotated[float, msgspec.Meta(ge=lo, le=hi, description=doc)]


class InputLimits(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Resource limits of the live monitor; defaults no real controller reaches.

    Beyond a limit the input is refused and counted, never a crash, a stall or unbounded memory.
    """

    max_message_bytes: _int(
        1024, 1 << 30,
        "largest message payload accepted (bytes); checked in the Zenoh callback before anything "
        "else; beyond: refused, counted too_large") = 4 << 20
    max_block_samples: _int(
        1, BLOCK_SAMPLES_MAX,
        "most samples in one block; beyond: the block is refused, counted too_large (bounds how "
        "long one message can hold the estimator, which all axes share)") = 10_000
    queue_messages: _int(
        1, 1_000_000,
        "input queue capacity (messages); when full: refused, counted queue_full") = 8192
    queue_bytes: _int(
        1024, 1 << 34,
        "input queue capacity (payload bytes); when full: refused, counted queue_full; "
        "must be >= max_message_bytes") = 64 << 20
    max_unknown_axes: _int(
        0, 100_000,
        "distinct axes without a model listed in the status (input.no_model); samples of further "
        "ones are counted in input.no_model_overflow") = 64
    status_rate: _float(
        0.1, 100_000.0,
        "status replies per second (token bucket); queries beyond: not answered, counted "
        "status.refused") = 50.0
    status_burst: _int(
        1, 1_000_000,
        "status replies allowed in a burst above status_rate") = 100
    status_refresh_s: _float(
        0.0, 60.0,
        "a status reply is at most this old (s): the document is rebuilt at most this often, on "
        "the query thread, never on the estimator thread") = 0.2

    @property
    def transport_max_message_bytes(self) -> int:
        """What the monitor's Zenoh links accept at all (2 × ``max_message_bytes`` + 64 KiB): a
        larger message is dropped by Zenoh before it is reassembled and is not counted; one between
        the two limits reaches the callback and is counted ``too_large``. Zenoh 1.10 applies its limit
        loosely (measured: after a first drop on a link, messages up to ~5x it were reassembled, 10x
        and 64x dropped), so memory stays bounded but the callback's exact limit is what counts."""
        return 2 * self.max_message_bytes + 65536

    def __post_init__(self) -> None:
        if self.queue_bytes < self.max_message_bytes:
            raise ValueError(f"queue_bytes ({self.queue_bytes}) must be >= max_message_bytes "
                             f"({self.max_message_bytes}), or a message of the largest allowed size could never "
                             "be queued")


DEFAULT = InputLimits()


def field_range(struct: type, name: str) -> tuple[float | None, float | None]:
    """``(minimum, maximum)`` of a numeric field of a msgspec Struct (None where unbounded or not numeric;
    an optional field ``X | None`` gives the range of ``X``)."""
    for f in msgspec.inspect.type_info(struct).fields:
        if f.name == name:
            t = f.type
            candidates = t.types if isinstance(t, msgspec.inspect.UnionType) else (t,)
            for c in candidates:
                c = c.type if isinstance(c, msgspec.inspect.Metadata) else c
                if isinstance(c, msgspec.inspect.IntType | msgspec.inspect.FloatType):
                    lo = c.ge if c.ge is not None else c.gt
                    hi = c.le if c.le is not None else c.lt
                    return lo, hi
            return None, None
    raise KeyError(f"{struct.__name__} has no field {name!r}")


def _num(v: float) -> str:
    return str(v) if isinstance(v, int) else f"{v:g}"


def range_text(struct: type, name: str) -> str | None:
    """The allowed range of a numeric field as text (``1024 ≤ queue_bytes ≤ 17179869184``), or the values of a
    choice (``mode one of peer, client``); None if unbounded."""
    for f in msgspec.inspect.type_info(struct).fields:
        if f.name == name:
            t = f.type
            for c in (t.types if isinstance(t, msgspec.inspect.UnionType) else (t,)):
                c = c.type if isinstance(c, msgspec.inspect.Metadata) else c
                if isinstance(c, msgspec.inspect.LiteralType):
                    return f"{name} one of {', '.join(map(str, c.values))}"
                if isinstance(c, msgspec.inspect.IntType | msgspec.inspect.FloatType):
                    lo = f"{_num(c.ge)} ≤ " if c.ge is not None else f"{_num(c.gt)} < " if c.gt is not None else ""
                    hi = f" ≤ {_num(c.le)}" if c.le is not None else f" < {_num(c.lt)}" if c.lt is not None else ""
                    return f"{lo}{name}{hi}" if lo or hi else None
            return None
    raise KeyError(f"{struct.__name__} has no field {name!r}")
