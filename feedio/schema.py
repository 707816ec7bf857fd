"""One schema for everything feedmon sends or stores: samples, truth, estimates, trial metadata.

The same JSON encoding (``msgspec.json``) is used on Zenoh and inside MCAP trial
files, and the JSON Schemas stored on every MCAP channel are generated from the
Structs below (:func:`json_schema`), so there is one source.

Conventions
-----------
* SI units everywhere: s, m, m/s, N, A, rpm for spindle speed.
* Columnar blocks: a controller streams samples in blocks; one sample is a block
  of length 1. ``seq`` is the sequence number of the first sample of the block;
  sample ``i`` of the block has sequence number ``seq + i``.
* Every per-sample column has the length of ``t``; blocks are never empty.
  This is checked on decode (``__post_init__``) and on construction, and the
  error names the field and both lengths.

Bounds (:mod:`feedio.limits`, checked on decode and on construction)
----------------------------------------------------------------------
* ``machine`` and ``axis`` match ``NAME_PATTERN`` = ``^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$``:
  1 to 64 ASCII letters, digits, ``_``, ``.``, ``-`` (not starting with ``.`` or ``-``).
  Such a name is safe in a Zenoh key, a file name, a log line and a table.
* ``0 ≤ seq`` and ``seq + len(block) − 1 ≤ SEQ_MAX = 2**53 − 1``: every sequence number of
  every sample is exact as an int64 and as a float64.
* Controller time ``0 ≤ t ≤ T_MAX = 1e10`` s and finite: every time is a valid MCAP log time
  (ns since 0 in a uint64), so no sink ever sees a time it cannot store.
* A block holds 1 … ``BLOCK_SAMPLES_MAX`` = 1 000 000 samples (the monitor's configurable
  ``max_block_samples``, default 10 000, is tighter).

Non-finite values
-----------------
JSON has no NaN; ``msgspec`` writes NaN/±inf as ``null``. Measured columns are
therefore typed ``list[float | None]``: a ``null`` is one missing or non-finite
sample (a dropped encoder read, a NaN from the controller). It decodes to
``None`` and becomes ``NaN`` in the NumPy arrays of :mod:`feedio.mcapio`, so
the monitor can reject that one sample (flag ``REJECTED``) instead of losing
the whole block. ``t`` is strictly ``list[float]`` within the bounds below: a
sample without a (possible) time cannot be placed, so a block with a ``null`` or
out-of-range time is rejected as a whole.

Unknown fields
--------------
All Structs are ``forbid_unknown_fields=True``. A misspelt optional column
(``"curent"``) would otherwise decode silently as "absent" and the data would
be lost without a word; here it is an error naming the field. Schema evolution
goes through new optional fields with defaults, and every MCAP channel carries
the JSON Schema it was written with.
"""

from __future__ import annotations

import math
from operator import attrgetter
from typing import Annotated, Any, Literal

import msgspec

from feedio.limits import BLOCK_SAMPLES_MAX, NAME_MAX_LEN, NAME_PATTERN, NAME_RE, SEQ_MAX, T_MAX
from kernels.flags import ADAPTATION_MODES, EstimateFlag

__all__ = [
    "SchemaError",
    "SEQ_MAX",
    "T_MAX",
    "NAME_PATTERN",
    "check_name",
    "SampleBlock",
    "SAMPLE_COLUMNS",
    "CONTEXT_COLUMNS",
    "TruthBlock",
    "EstimateBlock",
    "DisturbanceScalars",
    "Health",
    "HEALTH_STATES",
    "REASONS_MAX",
    "REASON_CHARS_MAX",
    "decode_health",
    "Provenance",
    "TrialTruth",
    "TrialMeta",
    "EstimateFlag",
    "STALE",
    "GAP",
    "REJECTED",
    "WARMUP",
    "REDUCED",
    "FLAG_NAMES",
    "flag_names",
    "encode",
    "decode",
    "decode_samples",
    "decode_estimates",
    "decode_truth",
    "decode_meta",
    "json_schema",
    "JSON_SCHEMAS",
    "SCHEMA_NAMES",
    "UNITS",
]

# ---- flags of EstimateBlock.flags (bitmask) -------------------------------------------------
# One definition: kernels.flags.EstimateFlag (an IntFlag; what each bit means is in
# kernels.flags.DESCRIPTIONS and the README). The names below are that IntFlag's members.
STALE = EstimateFlag.STALE  # repeated v_meas while the axis moves: predicted, not learned from
GAP = EstimateFlag.GAP  # the chain restarts: samples missing, time backwards, or a new bridge session
REJECTED = EstimateFlag.REJECTED  # non-finite or absurd value: NaN estimates, tracker not updated
WARMUP = EstimateFlag.WARMUP  # chain (re)start, or fewer samples learned than the budget M
REDUCED = EstimateFlag.REDUCED  # KRLS-T reduced update (the newest sample not added to the dictionary)
FLAG_NAMES = {flag: flag.name for flag in EstimateFlag}


def flag_names(flags: int) -> list[str]:
    """Names of the bits set in ``flags`` (unknown bits are ignored)."""
    return [flag.name for flag in EstimateFlag if int(flags) & flag]


class SchemaError(ValueError):
    """A message does not follow the feedmon schema (says which field and why)."""


Positive = Annotated[float, msgspec.Meta(gt=0.0)]
Column = list[float | None]  # measured column: null = missing / non-finite sample
#: a context column (NC program line, tool number: HAL s32 values), null = not known for that sample
Context = list[Annotated[int, msgspec.Meta(ge=-(2**31), le=2**31 - 1)] | None]
Form = Literal["velocity-loop", "force-input"]
#: machine / axis name (see "Bounds" above). The pattern is checked in ``__post_init__`` (one
#: compiled ``fullmatch``, also for constructed objects) and stated in the JSON Schema.
Name = Annotated[str, msgspec.Meta(min_length=1, max_length=NAME_MAX_LEN, extra_json_schema={"pattern": NAME_PATTERN},
                                   description="1-64 ASCII letters, digits, '_', '.', '-' (not first: '.', '-')")]
#: sequence number of the first sample of a block; seq + len - 1 <= SEQ_MAX too
Seq = Annotated[int, msgspec.Meta(ge=0, le=SEQ_MAX, description=f"0 <= seq and seq + len(t) - 1 <= {SEQ_MAX} (2**53 - 1)")]
#: controller time (s) of every sample
Times = Annotated[list[Annotated[float, msgspec.Meta(ge=0.0, le=T_MAX)]],
                  msgspec.Meta(min_length=1, max_length=BLOCK_SAMPLES_MAX,
                               description=f"controller time (s), 0 <= t <= {T_MAX:g}; 1 to {BLOCK_SAMPLES_MAX} samples")]

_STRUCT_OPTS = dict(forbid_unknown_fields=True, omit_defaults=True)


def check_name(value: str, what: str) -> str:
    """``value`` if it is a valid machine/axis name, else ``ValueError`` naming ``what`` and the rule."""
    if not isinstance(value, str) or NAME_RE.fullmatch(value) is None:
        shown = repr(value[:80]) + ("…" if isinstance(value, str) and len(value) > 80 else "")
        raise ValueError(f"{what} {shown} is not a valid name: 1-{NAME_MAX_LEN} ASCII letters, digits, "
                         "'_', '.' or '-', not starting with '.' or '-'")
    return value


class _Columns:
    """Names of per-sample columns and a getter of all of them at once (one C call per block:
    :func:`_check_columns` runs on every message, the estimates of one sample included)."""

    __slots__ = ("names", "get")

    def __init__(self, *names: str) -> None:
        self.names = names
        get = attrgetter(*names)
        self.get = get if len(names) > 1 else lambda obj: (get(obj),)


def _check_columns(obj: msgspec.Struct, columns: _Columns) -> None:
    """Common block checks: 1 … BLOCK_SAMPLES_MAX samples, every column as long as ``t``, times in
    [0, T_MAX], sequence numbers within [0, SEQ_MAX], valid names. Runs on every decoded message:
    kept to a few C-level calls on the good path (``sum`` is NaN/inf for any non-finite time,
    after which ``min``/``max`` are exact)."""
    t = obj.t
    n = len(t)
    if not 0 < n <= BLOCK_SAMPLES_MAX:
        raise ValueError(f"{type(obj).__name__} has {n} samples in 't'; a block holds 1 to {BLOCK_SAMPLES_MAX}")
    for name, col in zip(columns.names, columns.get(obj)):
        if col is not None and len(col) != n:
            raise ValueError(f"{type(obj).__name__} field '{name}' has {len(col)} values but 't' has {n}; "
                             "every column must have one value per sample")
    seq = obj.seq
    if type(seq) is not int or seq < 0 or seq + n - 1 > SEQ_MAX:  # bool is not a sequence number either
        raise ValueError(f"{type(obj).__name__} field 'seq': sequence number {seq!r} with {n} samples is out of "
                         f"range: need 0 <= seq and seq + {n} - 1 <= SEQ_MAX = {SEQ_MAX} (2**53 - 1)")
    if not (math.isfinite(sum(t)) and min(t) >= 0.0 and max(t) <= T_MAX):
        i, ti = next((i, x) for i, x in enumerate(t) if not 0.0 <= x <= T_MAX)
        raise ValueError(f"{type(obj).__name__} field 't' has {ti!r} at index {i}; controller time must be "
                         f"finite, 0 <= t <= {T_MAX:g} s")
    machine = getattr(obj, "machine", None)
    if machine is not None and not (machine in _GOOD_NAMES and obj.axis in _GOOD_NAMES):
        for what in ("machine", "axis"):
            value = check_name(getattr(obj, what), f"{type(obj).__name__} field '{what}'")
            if len(_GOOD_NAMES) < 4096:  # bounded: names a peer invents only cost the regex
                _GOOD_NAMES.add(value)


#: names already seen to match NAME_PATTERN (a set lookup instead of a regex per message)
_GOOD_NAMES: set[str] = set()
#: the columns each block checks against ``t``, in the order the errors name them
_SAMPLE_COLUMNS = _Columns("v_ref", "v_meas", "u", "current", "position", "spindle_rpm", "spindle_angle",
                           "program_line", "tool")
_TRUTH_COLUMNS = _Columns("force", "f", "dynamometer", "v_true", "glitch", "inertia", "damping", "coulomb_pos",
                          "coulomb_neg")
_ESTIMATE_COLUMNS = _Columns("v_meas", "v_pred", "residual", "f", "f_var", "f_next", "f_next_var", "dict_size",
                             "removed", "flags", "force", "force_var", "force_next", "program_line", "tool")


class SampleBlock(msgspec.Struct, **_STRUCT_OPTS):
    """A block of controller samples of one axis (topic ``<machine>/<axis>/samples``).

    ``t`` controller time (s), ``v_ref`` reference velocity (m/s), ``v_meas`` measured
    velocity (m/s); optional ``u`` force command (N), ``current`` motor current (A),
    ``position`` (m), ``spindle_rpm`` (rpm); context ``program_line`` (the NC program line the
    controller executes, e.g. LinuxCNC ``motion.program-line``) and ``tool`` (tool number), integers
    −2**31 … 2**31 − 1, carried unchanged to the estimate rows. ``None`` inside a column = missing sample.
    """

    machine: Name
    axis: Name
    seq: Seq
    t: Times
    v_ref: Column
    v_meas: Column
    u: Column | None = None
    current: Column | None = None
    position: Column | None = None
    spindle_rpm: Column | None = None
    spindle_angle: Column | None = None  # rad, unwrapped spindle angle, finite
    program_line: Context | None = None
    tool: Context | None = None

    def __post_init__(self) -> None:
        _check_columns(self, _SAMPLE_COLUMNS)

    def __len__(self) -> int:
        return len(self.t)

    def validate(self) -> SampleBlock:
        """Re-run the checks (after in-place edits); returns ``self``; raises :class:`SchemaError`."""
        try:
            self.__post_init__()
        except ValueError as exc:
            raise SchemaError(str(exc)) from None
        return self


#: the per-sample columns of a :class:`SampleBlock` (all fields but machine, axis, seq), in order
SAMPLE_COLUMNS = tuple(f for f in SampleBlock.__struct_fields__ if f not in ("machine", "axis", "seq"))
#: the context columns: in a sample block and, for the same samples, in its estimate block
CONTEXT_COLUMNS = ("program_line", "tool")


class TruthBlock(msgspec.Struct, **_STRUCT_OPTS):
    """Ground truth of a simulated (or instrumented) trial (topic ``<machine>/<axis>/truth``).

    ``force`` the true disturbance force acting on the drive (N; ``T_c`` of method §1,
    positive opposes positive motion), ``f`` the same in the model's velocity units
    (m/s, ``f = −b·T_c`` via ``force_to_disturbance``), optional ``dynamometer`` the
    force a dynamometer on the table measured (N, machine axis direction, with sensor
    noise), ``v_true`` the true velocity (m/s), ``glitch`` True where the recorded
    ``v_meas`` repeats the previous value (recording glitch).
    """

    seq: Seq
    t: Times
    force: Column
    f: Column
    dynamometer: Column | None = None
    v_true: Column | None = None
    glitch: list[bool] | None = None
    inertia: Column | None = None  # kg, true J(t) (held over the sample interval)
    damping: Column | None = None  # N·s/m, true B(t)
    coulomb_pos: Column | None = None  # N, true Coulomb friction magnitude for v > Ω
    coulomb_neg: Column | None = None  # N, true Coulomb friction magnitude for v < −Ω

    def __post_init__(self) -> None:
        _check_columns(self, _TRUTH_COLUMNS)

    def __len__(self) -> int:
        return len(self.t)


class EstimateBlock(msgspec.Struct, **_STRUCT_OPTS):
    """Monitor output for one axis (topic ``<machine>/<axis>/disturbance``).

    Velocity units: ``v_meas``, ``v_pred`` (one-step prediction), ``residual``,
    ``f`` (filtered disturbance) and ``f_next`` (one-step-ahead prediction) in m/s,
    variances in (m/s)². Force units (N, N²) only when the model can scale
    (force-input form, or velocity-loop with known K); otherwise ``None``.
    ``dict_size`` KRLS-T dictionary size, ``removed`` index of the pruned element
    (-1 none), ``flags`` bitmask of :class:`EstimateFlag` (STALE, GAP, REJECTED, WARMUP, REDUCED).
    ``program_line``, ``tool``: the context columns of the sample each row was emitted for
    (present when the sample block had them).
    """

    machine: Name
    axis: Name
    seq: Seq
    t: Times
    v_meas: Column
    v_pred: Column
    residual: Column
    f: Column
    f_var: Column
    f_next: Column
    f_next_var: Column
    dict_size: list[int]
    removed: list[int]
    flags: list[int]
    force: Column | None = None
    force_var: Column | None = None
    force_next: Column | None = None
    program_line: Context | None = None
    tool: Context | None = None

    def __post_init__(self) -> None:
        _check_columns(self, _ESTIMATE_COLUMNS)

    def __len__(self) -> int:
        return len(self.t)


class DisturbanceScalars(msgspec.Struct, **_STRUCT_OPTS):
    """One sample's disturbance estimate as plain numbers (MCAP channel
    ``/<machine>/<axis>/disturbance/scalars``), for tools that plot one time series per field
    (Foxglove's Plot panel, ``rerun mcap convert``).

    Message k describes sample k (sequence number ``seq``, controller time ``t`` in s) and its
    log time is the wall-clock time of that sample. ``f``, ``f_sd`` (m/s) and ``force``,
    ``force_sd`` (N) are the filtered disturbance of sample k and its standard deviation, taken
    from the estimate row of sample k+1 (the filtered values of row j describe sample j−1);
    ``f_next`` (m/s), ``force_next`` (N) are the one-step-ahead prediction for sample k made when
    sample k arrived (row k); ``v_meas`` (m/s) and ``flags`` (STALE 1, GAP 2, REJECTED 4,
    WARMUP 8, REDUCED 16) are row k's. ``truth_force`` (N), ``truth_f`` (m/s) and
    ``dynamometer`` (N) are the recorded truth of sample k. A value that is missing (no force
    scaling, a rejected sample, no later row, no truth) is left out of the message, never
    written as null or NaN.
    """

    t: float
    seq: int
    flags: int
    v_meas: float | None = None
    f: float | None = None
    f_sd: float | None = None
    f_next: float | None = None
    force: float | None = None
    force_sd: float | None = None
    force_next: float | None = None
    truth_force: float | None = None
    truth_f: float | None = None
    dynamometer: float | None = None


#: health states of :class:`Health`, in increasing severity
HEALTH_STATES = ("ok", "warn", "alarm")
#: bounds of a :class:`Health` report's ``reasons``
REASONS_MAX, REASON_CHARS_MAX = 32, 500
_Value = Annotated[float, msgspec.Meta(description="SI value; null: not given (see reasons)")] | None
_SE = Annotated[float, msgspec.Meta(ge=0.0, description="standard error, same unit; null: not given")] | None


class Health(msgspec.Struct, forbid_unknown_fields=True):
    """Health report of one axis (topic ``<machine>/<axis>/health``, MCAP channel
    ``/<machine>/<axis>/health``), about once a second of data time (issue 11).

    ``seq``, ``t``: the sample the report was made at (sequence number, controller time s).
    ``state``: ``ok``, ``warn`` or ``alarm`` (the worst of the model-validity test on the
    normalised innovations and the drift test of each physical parameter against the model file);
    ``reasons``: why (one line each), and which values are not given and why.
    The online physical parameters with their standard errors (delta method): ``inertia`` (kg),
    ``damping`` (N·s/m), ``coulomb`` (N, mean of ``coulomb_pos`` and ``coulomb_neg``, the
    magnitudes for v > Ω and v < −Ω) and ``offset`` (N, the constant force); ``null`` when it
    cannot be given (adaptation off, a column the model does not have, absolute values of a
    velocity-loop model without the loop gain K) — the reasons say which. ``nu2``: mean squared
    normalised innovation over the report's window (1 when the model explains the data; null
    when nothing was learned); ``adaptation``: the mode β ran in (``off``, ``track``, ``apply``).
    Unlike the blocks, absent values are written as ``null`` (never left out).
    """

    machine: Name
    axis: Name
    seq: Seq
    t: Annotated[float, msgspec.Meta(ge=0.0, le=T_MAX, description=f"controller time (s), 0 <= t <= {T_MAX:g}")]
    state: Literal["ok", "warn", "alarm"]
    reasons: Annotated[list[Annotated[str, msgspec.Meta(max_length=REASON_CHARS_MAX)]],
                       msgspec.Meta(max_length=REASONS_MAX)] = []
    inertia: _Value = None
    inertia_se: _SE = None
    damping: _Value = None
    damping_se: _SE = None
    coulomb: _Value = None
    coulomb_se: _SE = None
    coulomb_pos: _Value = None
    coulomb_pos_se: _SE = None
    coulomb_neg: _Value = None
    coulomb_neg_se: _SE = None
    offset: _Value = None
    offset_se: _SE = None
    nu2: Annotated[float, msgspec.Meta(ge=0.0)] | None = None
    adaptation: Literal[ADAPTATION_MODES] = "track"

    def __post_init__(self) -> None:
        check_name(self.machine, "Health field 'machine'")
        check_name(self.axis, "Health field 'axis'")
        if not (math.isfinite(self.t) and 0.0 <= self.t <= T_MAX):
            raise ValueError(f"Health field 't' is {self.t!r}; controller time must be finite, 0 <= t <= {T_MAX:g} s")
        for name in _HEALTH_NUMBERS:
            value = getattr(self, name)
            if value is not None and not math.isfinite(value):
                raise ValueError(f"Health field '{name}' is {value!r}; give a finite number or null")


#: the optional numbers of a Health report (each finite or null), from its field list
_HEALTH_NUMBERS = tuple(f for f in Health.__struct_fields__
                        if f not in ("machine", "axis", "seq", "t", "state", "reasons", "adaptation"))


def decode_health(data: bytes | str, *, what: str = "health report") -> Health:
    """Decode a :class:`Health` report (names, bounds and finiteness checked)."""
    return decode(data, Health, what=what)


class Provenance(msgspec.Struct, **_STRUCT_OPTS):
    """Where a trial came from. ``created`` is only set when the caller gives it
    (simulated trials stay byte-identical for the same seed)."""

    source: str  # "simulated", "emps", "csv", ...
    tool: str  # e.g. "feedmon simulate"
    version: str
    seed: int | None = None
    scenario: str | None = None
    created: str | None = None
    details: dict[str, Any] = {}


class TrialTruth(msgspec.Struct, **_STRUCT_OPTS):
    """Known truth of a simulated trial.

    ``beta`` the exact ZOH β (``kernels.feed_drive.physical_to_beta``), ``omega`` the
    Coulomb dead band Ω (m/s), ``coulomb`` whether the Coulomb columns belong to the
    model (False for trials without speed reversal), ``physical``: inertia (kg),
    damping (N·s/m), coulomb_pos / coulomb_neg (N), loop_gain (N·s/m);
    ``scenario`` all scenario constants used.
    """

    beta: list[float]
    omega: float
    coulomb: bool
    physical: dict[str, float]
    scenario: dict[str, Any] = {}
    beta_names: list[str] = []


UNITS = {
    "t": "s",
    "v_ref": "m/s",
    "v_meas": "m/s",
    "u": "N",
    "current": "A",
    "position": "m",
    "spindle_rpm": "rpm",
    "spindle_angle": "rad",
    "program_line": "NC line",
    "tool": "tool number",
}


class TrialMeta(msgspec.Struct, **_STRUCT_OPTS):
    """Metadata of one axis of a trial (MCAP metadata record ``feedmon.trial``)."""

    Ts: Positive
    form: Form
    machine: Name
    axis: Name
    provenance: Provenance
    units: dict[str, str] = {}
    spindle_rpm: float | None = None
    teeth: int | None = None
    loop_gain: float | None = None
    truth: TrialTruth | None = None
    description: str = ""

    def __post_init__(self) -> None:
        check_name(self.machine, "TrialMeta field 'machine'")
        check_name(self.axis, "TrialMeta field 'axis'")


# ---- encode / decode --------------------------------------------------------------------------
_encoder = msgspec.json.Encoder()
_decoders: dict[type, msgspec.json.Decoder] = {}


def encode(obj: msgspec.Struct) -> bytes:
    """JSON bytes of a message (NaN/inf written as null)."""
    return _encoder.encode(obj)


def decode(data: bytes | str, type_: type, *, what: str = "message"):
    """Decode and validate ``data`` as ``type_``; raises :class:`SchemaError` naming ``what``."""
    dec = _decoders.get(type_)
    if dec is None:
        dec = _decoders[type_] = msgspec.json.Decoder(type_)
    try:
        return dec.decode(data)
    except msgspec.ValidationError as exc:
        raise SchemaError(f"{what} is not a valid {type_.__name__}: {exc}") from None
    except msgspec.DecodeError as exc:
        raise SchemaError(f"{what} is not valid JSON: {exc}") from None
    except UnicodeDecodeError as exc:  # msgspec raises it for invalid UTF-8 inside a string
        raise SchemaError(f"{what} is not valid JSON: not UTF-8 text ({exc.reason} at byte {exc.start})") from None


def decode_samples(data: bytes | str, *, what: str = "sample block") -> SampleBlock:
    """Decode a :class:`SampleBlock` (lengths, types and names checked)."""
    return decode(data, SampleBlock, what=what)


def decode_truth(data: bytes | str, *, what: str = "truth block") -> TruthBlock:
    return decode(data, TruthBlock, what=what)


def decode_estimates(data: bytes | str, *, what: str = "estimate block") -> EstimateBlock:
    return decode(data, EstimateBlock, what=what)


def decode_meta(data: bytes | str, *, what: str = "trial metadata") -> TrialMeta:
    return decode(data, TrialMeta, what=what)


# ---- JSON Schemas (draft 2020-12), generated from the Structs ---------------------------------
SCHEMA_NAMES = {
    SampleBlock: "feedmon.SampleBlock",
    TruthBlock: "feedmon.TruthBlock",
    EstimateBlock: "feedmon.EstimateBlock",
    DisturbanceScalars: "feedmon.DisturbanceScalars",
    Health: "feedmon.Health",
    TrialMeta: "feedmon.TrialMeta",
}


def json_schema(type_: type) -> dict:
    """JSON Schema (draft 2020-12) of a message type, generated by ``msgspec.json.schema``.

    Self-contained: the top level is the object schema itself plus ``$defs`` for nested
    types, with ``$schema`` and ``$id`` set. (Length equality of the columns is a
    cross-field rule JSON Schema cannot state; it is documented in ``description``.)
    """
    raw = msgspec.json.schema(type_)
    defs = dict(raw.get("$defs", {}))
    name = type_.__name__
    top = dict(defs.pop(name)) if raw.get("$ref") == f"#/$defs/{name}" else dict(raw)
    out = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"https://feedmon.invalid/schemas/{SCHEMA_NAMES.get(type_, name)}.json",
    }
    out.update(top)
    if type_ in (SampleBlock, TruthBlock, EstimateBlock):  # the columnar blocks
        out["description"] = (
            (out.get("description", "") + "\n\n").lstrip()
            + "Every per-sample array has the same length as 't' (at least 1); null = missing sample."
        )
    if defs:
        out["$defs"] = defs
    return out


JSON_SCHEMAS = {SCHEMA_NAMES[t]: json_schema(t) for t in SCHEMA_NAMES}


# ---- process alarms ----------------------------------------------------------------------------
#: kinds of :class:`AlarmEvent` (what the process monitors of :mod:`monitor.process_monitor` detect)
ALARM_KINDS = ("collision", "overload", "broken_tooth", "runout", "missing_cut", "over_band", "wear")
#: bound of :attr:`AlarmEvent.detail`
ALARM_DETAIL_CHARS_MAX = 500
#: the process monitors an alarm can be acknowledged for (each widens its own band)
ALARM_MONITORS = ("impulse", "tooth", "envelope")
_Newton = Annotated[float, msgspec.Meta(description="N (for 'wear': the unit the detail names)")]


class AlarmEvent(msgspec.Struct, forbid_unknown_fields=True):
    """A process alarm of one axis (topic ``<machine>/<axis>/alarm``, MCAP channel ``/<machine>/<axis>/alarm``).

    ``kind`` what was detected (:data:`ALARM_KINDS`), ``monitor`` the monitor that judged it (e.g.
    ``impulse``, ``tooth``, ``envelope``, ``wear``), ``seq``/``t`` the estimate row (sequence number,
    controller time s) it was decided on, ``program_line``/``tool`` that row's context (null: not known),
    ``value`` the measured quantity and ``limit`` the limit it crossed (N), ``sigma`` the standard
    deviation the limit was judged with (N; null: an absolute limit), ``detail`` one line for people.
    """

    machine: Name
    axis: Name
    seq: Seq
    t: Annotated[float, msgspec.Meta(ge=0.0, le=T_MAX, description=f"controller time (s), 0 <= t <= {T_MAX:g}")]
    kind: Literal["collision", "overload", "broken_tooth", "runout", "missing_cut", "over_band", "wear"]
    monitor: Annotated[str, msgspec.Meta(min_length=1, max_length=64)]
    value: _Newton
    limit: _Newton
    sigma: Annotated[float, msgspec.Meta(ge=0.0)] | None = None
    program_line: Annotated[int, msgspec.Meta(ge=-(2**31), le=2**31 - 1)] | None = None
    tool: Annotated[int, msgspec.Meta(ge=-(2**31), le=2**31 - 1)] | None = None
    detail: Annotated[str, msgspec.Meta(max_length=ALARM_DETAIL_CHARS_MAX)] = ""

    def __post_init__(self) -> None:
        check_name(self.machine, "AlarmEvent field 'machine'")
        check_name(self.axis, "AlarmEvent field 'axis'")
        if not (math.isfinite(self.t) and 0.0 <= self.t <= T_MAX):
            raise ValueError(f"AlarmEvent field 't' is {self.t!r}; controller time must be finite, 0 <= t <= {T_MAX:g} s")
        for name in ("value", "limit", "sigma"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"AlarmEvent field '{name}' is {v!r}; give a finite number")


def decode_alarm(data: bytes | str, *, what: str = "alarm event") -> AlarmEvent:
    """Decode an :class:`AlarmEvent` (names, bounds and finiteness checked)."""
    return decode(data, AlarmEvent, what=what)


__all__ += ["AlarmEvent", "ALARM_KINDS", "ALARM_MONITORS", "decode_alarm"]
SCHEMA_NAMES[AlarmEvent] = "feedmon.AlarmEvent"
JSON_SCHEMAS[SCHEMA_NAMES[AlarmEvent]] = json_schema(AlarmEvent)


# ---- truth events of simulated process scenarios (appended: replay/process.py writes them) -----
#: most characters of a truth event's kind
TRUTH_KIND_MAX_LEN = 64


class TruthEvent(msgspec.Struct, **_STRUCT_OPTS):
    """A known process event of a simulated trial (topic ``<machine>/<axis>/truth/events``).

    ``kind`` what happened (``tooth_break``, ``runout_growth``, ``runout``, ``collision``,
    ``missing_cut``, ``missing_cut_end``, ``part``), ``t_s`` when (controller time, s), ``seq``
    the sample whose interval ``[t_k, t_k + Ts)`` holds it, ``value`` the event's number (tooth
    index, peak force in N, duration in s, chip-imbalance fraction, part index: see ``kind`` in
    ``docs/process-monitoring-scenarios.md``), ``detail`` further constants. A monitor's delay
    is its alarm time minus ``t_s``.
    """

    kind: Annotated[str, msgspec.Meta(min_length=1, max_length=TRUTH_KIND_MAX_LEN)]
    t_s: Annotated[float, msgspec.Meta(ge=0.0, le=T_MAX)]
    seq: Seq
    value: float
    detail: dict[str, Any] = {}


def decode_truth_event(data: bytes | str, *, what: str = "truth event") -> TruthEvent:
    return decode(data, TruthEvent, what=what)


SCHEMA_NAMES[TruthEvent] = "feedmon.TruthEvent"
JSON_SCHEMAS[SCHEMA_NAMES[TruthEvent]] = json_schema(TruthEvent)
__all__ += ["TruthEvent", "decode_truth_event", "TRUTH_KIND_MAX_LEN"]


# ---- the process monitors' view for the dashboard (appended: monitor/process_monitor makes it) -----
#: most teeth and angle bins of a :class:`ToothView` (the ranges of ``[monitors.tooth]``)
TEETH_MAX = 32
PROFILE_BINS_MAX = 720
#: revolutions a :class:`ToothView`'s profile and peaks average: one revolution has a few samples (6.7 at 333 Hz
#: and 3000 rpm) for 36 angle bins
TOOTH_VIEW_REVOLUTIONS = 10
_N = Annotated[float | None, msgspec.Meta(description="N; null: none")]


class ToothView(msgspec.Struct, forbid_unknown_fields=True):
    """The last revolutions per tooth: ``seq``/``t`` of the row that ended the last one, ``profile`` the mean
    force per spindle-angle bin over the last :data:`TOOTH_VIEW_REVOLUTIONS` (bin ``b`` covers
    ``[b, b + 1)·360°/bins``), ``peaks`` their mean peak force per tooth, ``a0`` the mean force and ``a1`` the
    once-per-revolution amplitude of the last (N); ``a1_broken``/``a1_runout`` the values of A1 above which the
    tooth monitor calls a broken tooth / runout (null while it learns)."""

    seq: Seq
    t: Annotated[float, msgspec.Meta(ge=0.0, le=T_MAX)]
    profile: Annotated[list[float | None], msgspec.Meta(min_length=1, max_length=PROFILE_BINS_MAX)]
    peaks: Annotated[list[float | None], msgspec.Meta(min_length=1, max_length=TEETH_MAX)]
    a0: _N = None
    a1: _N = None
    a1_broken: _N = None
    a1_runout: _N = None


class ProcessView(msgspec.Struct, forbid_unknown_fields=True):
    """What the process monitors of one axis judge against at row ``seq`` (time ``t``, s), for the dashboard
    (the Rerun recording process; not published, not logged): ``collision_low``/``collision_high`` the force
    range the collision test passes, ``overload`` its limit on ``|F|``, ``band_low``/``band_high`` the reference
    envelope (N; null: that monitor has none here), ``tooth`` the last revolution when one ended since the
    previous view."""

    machine: Name
    axis: Name
    seq: Seq
    t: Annotated[float, msgspec.Meta(ge=0.0, le=T_MAX)]
    collision_low: _N = None
    collision_high: _N = None
    overload: _N = None
    band_low: _N = None
    band_high: _N = None
    tooth: ToothView | None = None


def decode_process_view(data: bytes | str, *, what: str = "process view") -> ProcessView:
    return decode(data, ProcessView, what=what)


__all__ += ["ProcessView", "ToothView", "decode_process_view", "TEETH_MAX", "PROFILE_BINS_MAX",
            "TOOTH_VIEW_REVOLUTIONS"]
