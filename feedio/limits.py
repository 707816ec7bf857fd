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

Per-sample physical limits (:data:`SAMPLE_LIMITS`, :data:`LIMITS`): a value beyond them is physically
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
    "SPINDLE_RPM_MAX",
    "MAX_CONFIG_BYTES",
    "SAMPLE_LIMITS",
    "LIMITS",
    "InputLimits",
    "DEFAULT",
    "field_range",
    "range_text",
    "explain",
    "error_path",
    "bounded_int",
    "bounded_float",
]

# ---- contract bounds (schema) ---------------------------------------------------------------
NAME_MAX_LEN = 64
#: machine and axis names (JSON Schema ``pattern``; anchored, so also valid as an ECMA regex)
NAME_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$"
NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")  # use with fullmatch (``$`` allows a final newline)
SEQ_MAX = 2**53 - 1
T_MAX = 1e10  # s
BLOCK_SAMPLES_MAX = 1_000_000
#: fastest spindle (rpm) a model may name, a scenario may command and a sample may carry; a faster sample
#: speed is unusable (the spindle tracker falls back to the model's nominal speed), an imported one refused
SPINDLE_RPM_MAX = 100_000.0


class PhysicalLimits(msgspec.Struct, frozen=True):
    """Per-sample magnitudes beyond which a value is absurd for a machine-tool axis (SI)."""

    v_max: float = 50.0  # |velocity| (m/s): v_ref, v_meas
    u_max: float = 1e7  # |force command| (N)
    t_max: float = T_MAX  # |controller time| (s)
    spindle_rpm_max: float = SPINDLE_RPM_MAX  # |spindle speed| (rpm): faster is unusable (the tracker falls back)


SAMPLE_LIMITS = PhysicalLimits()
#: the estimator's view of :data:`SAMPLE_LIMITS` (``monitor.estimator`` uses it)
LIMITS = {"v": SAMPLE_LIMITS.v_max, "u": SAMPLE_LIMITS.u_max, "t": SAMPLE_LIMITS.t_max}


#: largest config file (``feedmon run --config``, the LinuxCNC bridge's, a scenario's ``--config``) and
#: model file, bytes
MAX_CONFIG_BYTES = 1 << 20


class FileTooLarge(ValueError):
    """A file read with :func:`read_capped` holds more than its limit."""


def read_capped(path, limit: int, what: str) -> bytes:
    """The bytes of ``path``, at most ``limit``: reads ``limit + 1`` bytes, never the whole of a larger file
    (its size on disk is not trusted: a FIFO or a device has none). :class:`FileTooLarge` names the file,
    what it should be and the limit; ``OSError`` (``FileNotFoundError``…) as ``open`` raises it."""
    with open(path, "rb") as fh:
        data = fh.read(limit + 1)
    if len(data) > limit:
        raise FileTooLarge(f"{path}: larger than the limit of a {what}: at most {limit} bytes")
    return data


# ---- resource limits (configurable) ---------------------------------------------------------
def bounded_int(lo: int, hi: int, doc: str = "") -> Any:
    """An int field in ``[lo, hi]`` described by ``doc``: the one way a settings Struct gives a range, from
    which :func:`range_text`, :func:`explain` and the generated tables read it."""
    return Annotated[int, msgspec.Meta(ge=lo, le=hi, description=doc)]


def bounded_float(lo: float, hi: float, doc: str = "", *, open_low: bool = False) -> Any:
    """A float field in ``[lo, hi]`` (``(lo, hi]`` when ``open_low``) described by ``doc``; NaN and ±inf are
    outside (see :func:`bounded_int`)."""
    meta = msgspec.Meta(gt=lo, le=hi, description=doc) if open_low else msgspec.Meta(ge=lo, le=hi, description=doc)
    return Annotated[float, meta]


class InputLimits(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Resource limits of the live monitor; defaults no real controller reaches.

    Beyond a limit the input is refused and counted, never a crash, a stall or unbounded memory.
    """

    max_message_bytes: bounded_int(
        1024, 1 << 30,
        "largest message payload accepted (bytes); checked in the Zenoh callback before anything "
        "else; beyond: refused, counted too_large") = 4 << 20
    max_block_samples: bounded_int(
        1, BLOCK_SAMPLES_MAX,
        "most samples in one block; beyond: the block is refused, counted too_large (bounds how "
        "long one message can hold the estimator, which all axes share)") = 10_000
    queue_messages: bounded_int(
        1, 1_000_000,
        "input queue capacity (messages); when full: refused, counted queue_full") = 8192
    queue_bytes: bounded_int(
        1024, 1 << 34,
        "input queue capacity (payload bytes); when full: refused, counted queue_full; "
        "must be >= max_message_bytes") = 64 << 20
    max_unknown_axes: bounded_int(
        0, 100_000,
        "distinct axes without a model listed in the status (input.no_model); samples of further "
        "ones are counted in input.no_model_overflow") = 64
    status_rate: bounded_float(
        0.1, 100_000.0,
        "status replies per second (token bucket); queries beyond: not answered, counted "
        "status.refused") = 50.0
    status_burst: bounded_int(
        1, 1_000_000,
        "status replies allowed in a burst above status_rate") = 100
    status_refresh_s: bounded_float(
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


# ---- error explanation (every msgspec-validated settings file and option) --------------------
_AT = re.compile(r"^(?P<msg>.*?)(?: - at `\$(?P<path>[^`]*)`)?$", re.S)


def _struct_in(t: Any) -> type | None:
    """The Struct class a field type holds (itself, behind ``Annotated``, or in an optional union)."""
    t = t.type if isinstance(t, msgspec.inspect.Metadata) else t
    if isinstance(t, msgspec.inspect.StructType):
        return t.cls
    if isinstance(t, msgspec.inspect.UnionType):
        found = [s for s in map(_struct_in, t.types) if s is not None]
        return found[0] if len(found) == 1 else None
    return None


def _walk(root: type, path: str) -> tuple[type | None, str | None]:
    """``(Struct holding the last key, last key)`` of a msgspec error path such as ``.run.limits.queue_bytes``,
    ``.axes[...].scale`` (a table of Structs) or ``.steps[1].mode`` (a list of them); ``(Struct, None)`` for a
    path naming a Struct itself, ``(None, None)`` for one that leaves the Structs."""
    t: Any = root
    ft: Any = None
    name: str | None = None
    for key, _ in re.findall(r"\.([^.\[]+)|\[(\d+|\.\.\.)\]", path):
        if key:
            if name is not None:  # a key inside a value that is not a Struct
                return None, None
            fields = {f.name: f.type for f in msgspec.inspect.type_info(t).fields}
            if key not in fields:
                return None, None
            ft = fields[key]
        elif name is not None:  # an element of a list of numbers: the key is still the list's
            continue
        else:  # an element of a table or a list of Structs
            inner = ft.type if isinstance(ft, msgspec.inspect.Metadata) else ft
            ft = getattr(inner, "value_type", None) or getattr(inner, "item_type", None)
            if ft is None:
                return None, None
        nxt = _struct_in(ft)
        inner = ft.type if isinstance(ft, msgspec.inspect.Metadata) else ft
        element = getattr(inner, "value_type", None) or getattr(inner, "item_type", None)
        if nxt is not None:
            t, name = nxt, None
        elif key and element is not None and _struct_in(element) is not None:
            name = None  # a table or list of Structs: an element follows
        elif key:
            name = key
        else:
            return None, None
    return t, name


def error_path(exc: msgspec.ValidationError) -> tuple[str, str]:
    """``(path, message)`` of a msgspec validation error: ``(".tracker.gamma", "Expected `float` >= 0.0001")``;
    the path is ``""`` for the document itself."""
    m = _AT.match(str(exc))
    return m.group("path") or "", m.group("msg")


def explain(exc: msgspec.ValidationError, root: type) -> tuple[str, str]:
    """``(key, message)`` of a validation error of ``root`` (a msgspec Struct): the dotted key
    (``run.limits.queue_bytes``; ``(top level)``) and msgspec's message with the allowed range of the key
    (:func:`range_text`) or, for an unknown key, the keys known there — what a user needs to fix it."""
    path, msg = error_path(exc)
    key = path.lstrip(".") or "(top level)"
    struct, name = _walk(root, path)
    if struct is not None and name is not None:
        allowed = range_text(struct, name)
        if allowed:
            msg += f" (allowed: {allowed})"
    elif struct is not None and "unknown field" in msg:
        msg += f"; known keys here: {', '.join(struct.__struct_fields__)}"
    return key, msg
