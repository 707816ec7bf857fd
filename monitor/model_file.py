"""The axis model file: what ``feedmon identify`` writes and ``feedmon run`` reads.

TOML, human-readable, versioned (``format_version``), never pickled. One file per axis.
Layout (version 2; version 1 files — without the uncertainty tables — are still read)::

    format_version = 2

    [axis]            machine, axis
    [model]           form, Ts (s), beta, beta_se, beta_names, omega (m/s), coulomb,
                      loop_gain (N·s/m, optional), method, noise (m/s, optional: the measurement
                      part of the one-step residual), offset_separated (optional: whether a
                      process's mean force is kept out of offset and friction; absent: unknown),
                      delay (samples, optional: the force acts this late; the first regressor
                      holds the command that far back, kernels.feed_drive.regressors)
    [physical]        inertia (kg), damping (N·s/m), coulomb (symmetric), coulomb_pos/neg (N),
                      offset (N) — or the ``…_over_gain`` ratios when K is unknown
    [physical_se]     their standard errors (same keys)
    [tracker]         kernel and exactly that kernel's keys (:data:`monitor.online_settings.TrackerKernel`:
                      sigma1 (s), sigma2, period (s) | lengthscale (s) | for kernel = "spindle", the
                      spindle-phase kernel, sigma1, sigma2, per, teeth, spindle_rpm), then gamma,
                      forgetting, budget, jitter, search — the online KRLS-T (method §6)
    [adaptation]      online β (optional; :class:`monitor.online_settings.Adaptation`)
    [health]          health thresholds (optional; :class:`monitor.online_settings.Health`)
    [identification]  chosen method, kernel, period, period_source, log_evidence and the
                      hyperparameters of the chosen model; order (lags of its likelihood);
                      offset_note, adequacy (what identify found, in words); self_check: what the
                      monitor over the identification trial said of this model (:mod:`monitor.self_check`)
    [[identification.candidates]]   method, kernel, period (s; ``per`` for a spindle-phase one),
                      log_evidence, valid, why_not — every candidate ``feedmon identify`` weighed
    [validity]        warning — only in a file written with ``identify --force`` although the model
                      is not valid; ``feedmon run`` refuses such a file (the reason is the warning)
    [provenance]      source, sha256, method, created, feedmon_version

Validation (:func:`load_model`) is one mechanism: the file is decoded into :class:`ModelFileV2`,
a tree of ``msgspec`` Structs whose every number carries its documented range
(``msgspec.Meta``); a wrong type, a value out of range, ``nan``/``inf`` (outside every range), an
unknown key or a missing one is a :class:`ModelFileError` naming the file, the key and the allowed
range; ``[tracker]`` is a tagged union on ``kernel`` (a key of another kernel is refused, naming the keys
the file's kernel takes). ``format_version`` must be the integer 1 or 2 (``true`` or ``1.0`` are refused). Then the
model itself must be one that can be right (:func:`kernels.feed_drive.validity_problems`: stable
pole, positive input gain, no Coulomb friction negative beyond its uncertainty), and ``beta`` must
match ``beta_names`` and the form. The ranges (generated from the Structs by :func:`ranges_table`)
admit every real drive — sample periods from 1 µs to 10 s, inertias from grams to hundreds of
tonnes, dictionaries up to 4096 elements (the KRLS-T state takes about 24·M² bytes, 0.4 GB at the
limit) — and refuse the absurd:

"""

from __future__ import annotations

import functools
import math
import operator
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import msgspec

from feedio.digest import file_sha256
from feedio.limits import MAX_CONFIG_BYTES, FileTooLarge, bounded_float, bounded_int, error_path, read_capped
from kernels.covariance import Kernel
from kernels.feed_drive import FORMS, beta_names, validity_problems

from . import online_settings as OS

__all__ = [
    "FORMAT_VERSION",
    "READABLE_VERSIONS",
    "ModelFileError",
    "TrackerConfig",
    "AxisModel",
    "ModelFileV2",
    "load_model",
    "save_model",
    "file_sha256",
    "ranges_table",
]

FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)


class ModelFileError(ValueError):
    """A model file that cannot be used; the message names the file and the key."""


# ---------------------------------------------------------------------------------------------
# the schema: every number with its range (one mechanism: msgspec.Meta)
# ---------------------------------------------------------------------------------------------
#: widest dead band Ω (m/s) a model may have (identify refuses a larger one before it runs)
OMEGA_MAX = 10.0

_Name = Annotated[str, msgspec.Meta(min_length=1, max_length=128, pattern=r"^[^/*$?#\s]+$",
                                    description="no whitespace or / * $ ? # (Zenoh key characters)")]
_Text = Annotated[str, msgspec.Meta(max_length=4096)]
_Short = Annotated[str, msgspec.Meta(max_length=64)]
_Coef = bounded_float(-1e12, 1e12)
_Se = bounded_float(0.0, 1e12)
_Value = bounded_float(-1e12, 1e12)
_Hyper = bounded_float(1e-9, 1e9)
_Opts = {"forbid_unknown_fields": True, "kw_only": True}


class _AxisT(msgspec.Struct, **_Opts):
    machine: _Name
    axis: _Name


class _ModelT(msgspec.Struct, **_Opts):
    form: Literal["velocity-loop", "force-input"]
    Ts: bounded_float(1e-6, 10.0, "s")
    beta: Annotated[list[_Coef], msgspec.Meta(min_length=2, max_length=6)]
    omega: bounded_float(0.0, OMEGA_MAX, "m/s")
    coulomb: bool
    beta_se: Annotated[list[_Se], msgspec.Meta(min_length=2, max_length=6)] | None = None
    beta_names: Annotated[list[_Short], msgspec.Meta(min_length=2, max_length=6)] | None = None
    loop_gain: bounded_float(0.0, 1e10, "N·s/m", open_low=True) | None = None
    method: _Short = "pl-lssvm"
    noise: bounded_float(0.0, 1e3, "m/s, std of the measurement part of the one-step residual", open_low=True) | None = None
    offset_separated: bool | None = None
    delay: bounded_int(0, 16, "samples from a force command to the force") | None = None


class _PhysicalT(msgspec.Struct, **_Opts):
    inertia: bounded_float(0.0, 1e9, "kg", open_low=True) | None = None
    damping: bounded_float(0.0, 1e12, "N·s/m", open_low=True) | None = None
    coulomb: bounded_float(-1e9, 1e9, "N") | None = None
    coulomb_pos: bounded_float(-1e9, 1e9, "N") | None = None
    coulomb_neg: bounded_float(-1e9, 1e9, "N") | None = None
    offset: bounded_float(-1e9, 1e9, "N") | None = None
    gain: bounded_float(0.0, 1e10, "N·s/m", open_low=True) | None = None  # version 1 files
    inertia_over_gain: bounded_float(0.0, 1e6, "s", open_low=True) | None = None
    damping_over_gain: bounded_float(0.0, 1e6, open_low=True) | None = None
    coulomb_over_gain: bounded_float(-1e6, 1e6, "m/s") | None = None
    coulomb_pos_over_gain: bounded_float(-1e6, 1e6, "m/s") | None = None
    coulomb_neg_over_gain: bounded_float(-1e6, 1e6, "m/s") | None = None
    offset_over_gain: bounded_float(-1e6, 1e6, "m/s") | None = None


class _PhysicalSeT(msgspec.Struct, **_Opts):
    inertia: _Se | None = None
    damping: _Se | None = None
    coulomb: _Se | None = None
    coulomb_pos: _Se | None = None
    coulomb_neg: _Se | None = None
    offset: _Se | None = None
    inertia_over_gain: _Se | None = None
    damping_over_gain: _Se | None = None
    coulomb_over_gain: _Se | None = None
    coulomb_pos_over_gain: _Se | None = None
    coulomb_neg_over_gain: _Se | None = None
    offset_over_gain: _Se | None = None


class _TrackerCommonT(msgspec.Struct, **_Opts):
    """The ``[tracker]`` keys of every kernel (λ, M, ε_j, γ, search)."""

    gamma: bounded_float(1e-4, 1e8)
    forgetting: bounded_float(0.5, 1.0) = OS.TRACKER_DEFAULTS["forgetting"]
    budget: bounded_int(*OS.BUDGET_RANGE, "dictionary elements") = OS.TRACKER_DEFAULTS["budget"]
    jitter: bounded_float(*OS.JITTER_RANGE) = OS.TRACKER_DEFAULTS["jitter"]
    search: bool = True


def _field_specs(struct: type) -> list[tuple]:
    return [(f.name, f.type) if f.required else (f.name, f.type, f.default) for f in msgspec.structs.fields(struct)]


def _tracker_table(kernel: type) -> type:
    """The ``[tracker]`` table of one kernel: its keys (a :data:`monitor.online_settings.TrackerKernel`
    member, tagged by ``kernel``) and the common ones (:class:`_TrackerCommonT`)."""
    tag = kernel.__struct_config__.tag
    return msgspec.defstruct(f"_Tracker_{tag}", _field_specs(kernel) + _field_specs(_TrackerCommonT),
                             tag_field="kernel", tag=tag, module=__name__, **_Opts)


#: the ``[tracker]`` table of each ``kernel`` string
_TRACKER_TABLES = {tag: _tracker_table(k) for tag, k in OS.TRACKER_KERNELS.items()}
_TrackerT = functools.reduce(operator.or_, _TRACKER_TABLES.values())


class _CandidateT(msgspec.Struct, **_Opts):
    method: Literal["ls", "pl_lssvm"]
    kernel: Literal["none", "squared_exponential", "locally_periodic", "locally_periodic_zero_mean", "spindle"] = "none"
    period: bounded_float(1e-6, 1e6, "s") | None = None
    per: Literal["revolution", "tooth"] | None = None  # spindle-phase candidate
    log_evidence: bounded_float(-1e15, 1e15) | None = None
    valid: bool = True
    why_not: _Text = ""


class _IdentificationT(msgspec.Struct, **_Opts):
    chosen: Literal["ls", "pl_lssvm"] | None = None
    kernel: Literal["none", "squared_exponential", "locally_periodic", "locally_periodic_zero_mean", "spindle"] | None = None
    period: bounded_float(1e-6, 1e6, "s") | None = None
    period_source: Literal["given", "spindle", "detected", "none"] | None = None
    log_evidence: bounded_float(-1e15, 1e15) | None = None
    log_likelihood: bounded_float(-1e15, 1e15) | None = None
    sigma1: _Hyper | None = None
    sigma2: _Hyper | None = None
    lengthscale: _Hyper | None = None
    gamma: _Hyper | None = None
    tuned: bool | None = None
    evaluations: bounded_int(0, 10**9) | None = None
    tune_seconds: bounded_float(0.0, 1e7, "s") | None = None
    segment: bounded_int(0, 10**9, "samples") | None = None
    order: bounded_int(0, 10**9, "lags of the likelihood (≥ samples − 1: exact)") | None = None
    offset_note: _Text | None = None
    adequacy: _Text | None = None
    self_check: _Text | None = None
    candidates: Annotated[list[_CandidateT], msgspec.Meta(max_length=64)] = []


class _ValidityT(msgspec.Struct, **_Opts):
    warning: _Text


class _ProvenanceT(msgspec.Struct, **_Opts):
    source: _Text = ""
    sha256: _Short = ""
    method: _Short = ""
    created: _Short = ""
    feedmon_version: _Short = ""


class ModelFileV2(msgspec.Struct, **_Opts):
    """The whole model file (versions 1 and 2)."""

    format_version: Literal[1, 2]
    axis: _AxisT
    model: _ModelT
    tracker: _TrackerT
    physical: _PhysicalT = msgspec.field(default_factory=_PhysicalT)
    physical_se: _PhysicalSeT = msgspec.field(default_factory=_PhysicalSeT)
    identification: _IdentificationT = msgspec.field(default_factory=_IdentificationT)
    validity: _ValidityT | None = None
    adaptation: OS.Adaptation = msgspec.field(default_factory=OS.Adaptation)
    health: OS.Health = msgspec.field(default_factory=OS.Health)
    provenance: _ProvenanceT = msgspec.field(default_factory=_ProvenanceT)


def _describe(t) -> str:
    """Allowed values of a msgspec type (for the ranges table and error messages)."""
    from msgspec import inspect as mi

    unit = ""
    if isinstance(t, mi.Metadata):
        unit = (t.extra_json_schema or {}).get("description", "")
        t = t.type
    if isinstance(t, mi.UnionType):
        parts = [_describe(x) for x in t.types if not isinstance(x, mi.NoneType)]
        return " or ".join(parts) + (" (optional)" if any(isinstance(x, mi.NoneType) for x in t.types) else "")
    if isinstance(t, (mi.FloatType, mi.IntType)):
        kind = "number" if isinstance(t, mi.FloatType) else "integer"
        lo = f"> {t.gt:g}" if t.gt is not None else (f"≥ {t.ge:g}" if t.ge is not None else "")
        hi = f"≤ {t.le:g}" if t.le is not None else ""
        return f"{kind} {lo}, {hi}".strip(", ") + (f" {unit}" if unit and unit != kind else "")
    if isinstance(t, mi.ListType):
        return f"list of {t.min_length}…{t.max_length} × {_describe(t.item_type)}"
    if isinstance(t, mi.LiteralType):
        return " / ".join(repr(v) if isinstance(v, str) else str(v) for v in t.values)
    if isinstance(t, mi.StrType):
        return f"text ≤ {t.max_length} characters" + (f", {unit}" if unit else "")
    if isinstance(t, mi.BoolType):
        return "true / false"
    if isinstance(t, mi.StructType):
        return "table"
    return type(t).__name__


def _union_fields(prefix: str, members: list[type]) -> list[tuple[str, str]]:
    """Rows of a tagged union of Structs: the tag's values, then each key with its range and, unless
    every member has it, the tags that take it (keys of some members first)."""
    tag_field = members[0].__struct_config__.tag_field
    tags = [m.__struct_config__.tag for m in members]
    seen: dict[str, dict[str, list[str]]] = {}  # key → range → tags
    for m, tag in zip(members, tags, strict=True):
        for key, allowed in _fields(prefix, m):
            seen.setdefault(key, {}).setdefault(allowed, []).append(tag)
    rows = [(f"{prefix}{tag_field}", " / ".join(map(repr, tags)))]
    for every in (False, True):
        for key, ranges in seen.items():
            if (sum(map(len, ranges.values())) == len(tags)) == every:
                rows.append((key, "; ".join(allowed if every and len(ranges) == 1 else
                                            f"{allowed} ({tag_field}: {', '.join(ts)})" for allowed, ts in ranges.items())))
    return rows


def _fields(prefix: str, struct_type) -> list[tuple[str, str]]:
    from msgspec import inspect as mi

    info = mi.type_info(struct_type)
    rows = []
    for f in info.fields:
        key = f"{prefix}{f.name}"
        t = f.type
        if isinstance(t, mi.UnionType) and all(isinstance(x, mi.StructType) for x in t.types):
            rows += _union_fields(f"{key}.", [x.cls for x in t.types])
            continue
        inner = t.types[0] if isinstance(t, mi.UnionType) and isinstance(t.types[0], mi.StructType) else t
        if isinstance(inner, mi.StructType):
            rows += _fields(f"{key}.", inner.cls)
        elif isinstance(inner, mi.ListType) and isinstance(inner.item_type, mi.StructType):
            rows += _fields(f"{key}[].", inner.item_type.cls)
        else:
            rows.append((key, _describe(t)))
    return rows


def ranges_table() -> str:
    """Markdown table of every key and its allowed values, generated from :class:`ModelFileV2`."""
    rows = _fields("", ModelFileV2)
    return "\n".join(["| key | allowed |", "|---|---|"] + [f"| `{k}` | {v} |" for k, v in rows])


_RANGES = dict(_fields("", ModelFileV2))
#: the ranges of each kernel's ``[tracker]`` keys (error messages name the range of the file's kernel)
_TRACKER_RANGES = {tag: dict(_fields("tracker.", t)) for tag, t in _TRACKER_TABLES.items()}
__doc__ = (__doc__ or "") + ranges_table() + "\n"


# ---------------------------------------------------------------------------------------------
# the model seen by the monitor
# ---------------------------------------------------------------------------------------------
@dataclass
class TrackerConfig:
    """KRLS-T hyperparameters for the online tracker (method §6), defaults after thesis Table 4.5."""

    #: the kernel and its hyperparameters, as the file's ``[tracker]`` holds them
    kernel: OS.TrackerKernel = field(default_factory=lambda: OS.LocallyPeriodicKernel(
        sigma1=OS.TRACKER_DEFAULTS["sigma1"], sigma2=OS.TRACKER_DEFAULTS["sigma2"], period=1 / 55))
    gamma: float = OS.TRACKER_DEFAULTS["gamma"]
    forgetting: float = OS.TRACKER_DEFAULTS["forgetting"]
    budget: int = OS.TRACKER_DEFAULTS["budget"]
    jitter: float = OS.TRACKER_DEFAULTS["jitter"]
    #: the monitor chooses the disturbance model online from the samples it sees (kernel family,
    #: period, σ1, σ2, γ, λ; :mod:`kernels.disturbance_search`), starting from the one above
    search: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.kernel, OS.TrackerKernel):
            raise TypeError(f"TrackerConfig.kernel must be one of {', '.join(OS.TRACKER_KERNELS)} kernels "
                            f"(monitor.online_settings.TrackerKernel), got {type(self.kernel).__name__}")

    def build_kernel(self) -> Kernel:
        """The kernel the online tracker runs (a time kernel or the spindle-phase kernel)."""
        return self.kernel.build()


def _layouts(form: str, coulomb: bool) -> list[tuple[str, ...]]:
    """The β layouts a model file may have: with the constant ``one`` (always for force-input)."""
    with_one = beta_names(form, coulomb, intercept=True)
    return [with_one] if form == "force-input" else [beta_names(form, coulomb, intercept=False), with_one]


@dataclass
class AxisModel:
    """Everything the monitor needs for one axis.

    ``beta_names`` defaults to the form's layout matching ``len(beta)``: the velocity-loop form may
    end with the constant column ``one`` (:attr:`intercept`), whose coefficient the online residual
    ``v(k) = v_m(k+1) − βᵀz(k)`` includes.
    """

    machine: str
    axis: str
    form: str
    Ts: float
    beta: list[float]
    omega: float
    coulomb: bool
    tracker: TrackerConfig
    loop_gain: float | None = None
    method: str = "pl-lssvm"
    physical: dict = field(default_factory=dict)
    identification: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    beta_names: tuple[str, ...] | None = None
    beta_se: list[float] | None = None
    physical_se: dict = field(default_factory=dict)
    candidates: list[dict] = field(default_factory=list)
    validity_warning: str | None = None
    online: OS.OnlineSettings = field(default_factory=OS.OnlineSettings)  # [adaptation], [health]
    noise: float | None = None  # m/s: std of the measurement part ε of v(k) = v_m(k+1) − βᵀz(k)
    offset_separated: bool | None = None  # a process's mean force kept out of friction/offset (None: unknown)
    delay: int = 0  # samples from a command to its force: z1(k) holds the command delay samples back

    def __post_init__(self) -> None:
        if self.form not in FORMS:
            raise ValueError(f"input form {self.form!r} is not known; use one of {', '.join(FORMS)}")
        layouts = _layouts(self.form, self.coulomb)
        if self.beta_names is None:
            match = [names for names in layouts if len(names) == len(self.beta)]
            if not match:
                raise ValueError(f"β has {len(self.beta)} entries; the {self.form} form with "
                                 f"coulomb={str(self.coulomb).lower()} needs {' or '.join(str(len(x)) for x in layouts)}")
            self.beta_names = match[0]
        else:
            self.beta_names = tuple(self.beta_names)
            if self.beta_names not in layouts:
                raise ValueError(f"beta_names {list(self.beta_names)} do not match the {self.form} form with "
                                 f"coulomb={str(self.coulomb).lower()} (expected {' or '.join(str(list(x)) for x in layouts)})")
            if len(self.beta) != len(self.beta_names):
                raise ValueError(f"β has {len(self.beta)} entries; the {self.form} form with "
                                 f"coulomb={str(self.coulomb).lower()} needs {' or '.join(str(len(x)) for x in layouts)} "
                                 f"(beta_names lists {len(self.beta_names)})")

    @property
    def intercept(self) -> bool:
        """True when β ends with the constant column ``one`` (force offset)."""
        return bool(self.beta_names) and self.beta_names[-1] == "one"

    @property
    def force_scalable(self) -> bool:
        """True when a disturbance can be published in newtons (method §6)."""
        return self.form == "force-input" or self.loop_gain is not None

    @property
    def force_gain(self) -> float | None:
        """``b = K_d/K`` (m/s per N) or None: ``F = −f / b``."""
        if self.form == "force-input":
            return self.beta[0]
        if self.loop_gain is not None:
            return self.beta[0] / self.loop_gain
        return None

    def validity_problems(self) -> list[str]:
        """Why this model cannot be right (:func:`kernels.feed_drive.validity_problems`)."""
        return validity_problems(self.form, self.beta, self.Ts, names=self.beta_names, gain=self.loop_gain,
                                 physical_se=self.physical_se)


def truth_model(meta, *, period: float = 1 / 55, budget: int = 50, forgetting: float = 0.996) -> AxisModel:
    """The model of a simulated trial with its TRUE β (``meta.truth`` of a
    :class:`~feedio.schema.TrialMeta` written by ``feedmon simulate``) and the thesis tracker
    hyperparameters (Table 4.5: σ1 = 1.2 s, σ2 = 0.495, γ = 5.85) at the disturbance period ``period``
    (s), dictionary budget ``budget`` and forgetting ``forgetting``: the monitor as it runs after a
    perfect identification (tests, benchmarks)."""
    truth = meta.truth
    if truth is None:
        raise ValueError(f"trial axis {meta.machine}/{meta.axis} carries no truth (only simulated trials do)")
    return AxisModel(
        machine=meta.machine, axis=meta.axis, form=meta.form, Ts=meta.Ts, beta=list(truth.beta), omega=truth.omega,
        coulomb=truth.coulomb, loop_gain=meta.loop_gain, method="truth",
        tracker=TrackerConfig(kernel=OS.LocallyPeriodicKernel(sigma1=1.2, sigma2=0.495, period=period),
                              gamma=5.85, forgetting=forgetting, budget=budget),
        provenance={"source": "simulated truth"},
    )


# ---------------------------------------------------------------------------------------------
# loading
# ---------------------------------------------------------------------------------------------
def load_model(path, *, allow_invalid: bool = False) -> AxisModel:
    """Read and validate a model file; errors name the file and the key (never executes anything).

    A model that cannot be right (:func:`kernels.feed_drive.validity_problems`) is refused unless
    ``allow_invalid`` (for inspection tools; ``feedmon run`` never sets it).
    """
    path = Path(path)
    try:
        raw = read_capped(path, MAX_CONFIG_BYTES, "model file")
    except FileTooLarge as exc:
        raise ModelFileError(str(exc)) from None
    except FileNotFoundError:
        raise ModelFileError(f"{path}: model file not found; create one with 'feedmon identify TRIAL.mcap -o {path}'") from None
    except OSError as exc:
        raise ModelFileError(f"{path}: cannot read the model file ({exc.strerror or exc})") from None
    try:
        doc = tomllib.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ModelFileError(f"{path}: not a valid TOML model file ({exc})") from None
    version = doc.get("format_version")
    if version is None:
        raise ModelFileError(f"{path}: key 'format_version': missing; is this a feedmon model file?")
    if isinstance(version, bool) or not isinstance(version, int) or version not in READABLE_VERSIONS:
        raise ModelFileError(f"{path}: key 'format_version': unknown version {version!r}; this feedmon reads "
                             f"the integers {', '.join(map(str, READABLE_VERSIONS))}")
    try:
        f = msgspec.convert(doc, ModelFileV2, strict=True)
    except msgspec.ValidationError as exc:
        raise _refusal(path, exc, doc) from None
    return _to_model(path, f, allow_invalid)


def _refusal(path: Path, exc: msgspec.ValidationError, doc: dict) -> ModelFileError:
    """The :class:`ModelFileError` of a schema violation: the file, the key and what is allowed there (in
    ``[tracker]``: what the file's kernel takes)."""
    path_, text = error_path(exc)
    key = path_.lstrip(".")
    tracker = doc.get("tracker")
    tag = tracker.get("kernel") if isinstance(tracker, dict) else None
    kernel = OS.TRACKER_KERNELS.get(tag) if isinstance(tag, str) else None
    name = text.split("`")[1] if "`" in text else "?"
    full = f"{key}.{name}" if key else name
    if text.startswith("Object contains unknown field"):
        if key == "tracker" and kernel is not None and any(name in k.__struct_fields__ for k in OS.TRACKER_KERNELS.values()):
            return ModelFileError(f"{path}: key '{full}': not a parameter of the {tag} kernel (it takes "
                                  f"{', '.join(kernel.__struct_fields__)})")
        return ModelFileError(f"{path}: key '{full}': unknown key (misspelt?); see the model-file keys in the README")
    if text.startswith("Object missing required field"):
        if key == "tracker" and kernel is not None and name in kernel.__struct_fields__:
            need = [f.name for f in msgspec.structs.fields(kernel) if f.required]
            return ModelFileError(f"{path}: key '{full}': missing; the {tag} kernel needs {', '.join(need)} "
                                  f"(allowed: {_TRACKER_RANGES[tag][full]})")
        return ModelFileError(f"{path}: key '{full}': missing; re-create the file with 'feedmon identify'")
    ranges = _TRACKER_RANGES.get(tag, _RANGES) if key.startswith("tracker.") and isinstance(tag, str) else _RANGES
    allowed = ranges.get(re.sub(r"\[\d+\]", "[]", key)) or ranges.get(re.sub(r"\[\d+\]$", "", key))
    hint = f" (allowed: {allowed})" if allowed else ""
    return ModelFileError(f"{path}: key '{key}': {text}{hint}")


def _to_model(path: Path, f: ModelFileV2, allow_invalid: bool) -> AxisModel:
    m, t = f.model, f.tracker
    kernel_type = OS.TRACKER_KERNELS[type(t).__struct_config__.tag]
    kernel = kernel_type(**{k: getattr(t, k) for k in kernel_type.__struct_fields__})
    physical = {k: v for k, v in msgspec.structs.asdict(f.physical).items() if v is not None}
    physical_se = {k: v for k, v in msgspec.structs.asdict(f.physical_se).items() if v is not None}
    ident = {k: v for k, v in msgspec.structs.asdict(f.identification).items()
             if v is not None and k != "candidates"}
    try:
        model = AxisModel(
            machine=f.axis.machine, axis=f.axis.axis, form=m.form, Ts=m.Ts, beta=list(m.beta), omega=m.omega,
            coulomb=m.coulomb, loop_gain=m.loop_gain, method=m.method,
            tracker=TrackerConfig(kernel=kernel, gamma=t.gamma, forgetting=t.forgetting, budget=t.budget,
                                  jitter=t.jitter, search=t.search),
            physical=physical, identification=ident,
            provenance={k: v for k, v in msgspec.structs.asdict(f.provenance).items() if v},
            beta_names=None if m.beta_names is None else tuple(m.beta_names), beta_se=m.beta_se,
            physical_se=physical_se,
            candidates=[msgspec.structs.asdict(c) for c in f.identification.candidates],
            validity_warning=None if f.validity is None else f.validity.warning,
            online=OS.OnlineSettings(adaptation=f.adaptation, health=f.health),
            noise=m.noise, offset_separated=m.offset_separated, delay=m.delay or 0,
        )
    except ValueError as exc:
        key = "model.beta_names" if str(exc).startswith("beta_names") else "model.beta"
        raise ModelFileError(f"{path}: key '{key}': {exc}") from None
    if m.beta_se is not None and len(m.beta_se) != len(m.beta):
        raise ModelFileError(f"{path}: key 'model.beta_se': has {len(m.beta_se)} entries, beta has {len(m.beta)}")
    if not allow_invalid:
        problems = model.validity_problems()
        if problems:
            forced = " (the file was written with 'identify --force')" if model.validity_warning else ""
            raise ModelFileError(f"{path}: key 'model.beta': the model cannot be right{forced}: " + "; ".join(problems))
        if model.validity_warning:
            raise ModelFileError(f"{path}: key 'validity.warning': {model.validity_warning}. Identify the axis again, "
                                 "or remove the [validity] table once you have checked the model by hand")
    return model


# ---------------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------------
def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"model files hold finite numbers only, got {value!r}")
        return repr(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
        return f'"{escaped}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if hasattr(value, "item"):  # numpy scalar
        return _toml_value(value.item())
    raise TypeError(f"cannot write {type(value).__name__} to a model file")


def _table(name: str, items: dict, comments: dict | None = None) -> list[str]:
    lines = [f"[{name}]"]
    for key, value in items.items():
        if value is None or isinstance(value, dict):
            continue
        note = (comments or {}).get(key)
        lines.append(f"{key} = {_toml_value(value)}" + (f"  # {note}" if note else ""))
    return lines + [""]


_UNITS = {
    "Ts": "s",
    "omega": "m/s, Coulomb dead band",
    "loop_gain": "N·s/m, velocity-loop gain K",
    "inertia": "kg",
    "damping": "N·s/m",
    "coulomb": "N, symmetric Coulomb friction (coulomb_pos + coulomb_neg)/2",
    "coulomb_pos": "N",
    "coulomb_neg": "N",
    "offset": "N",
    "inertia_over_gain": "s (J/K)",
    "damping_over_gain": "1 (B/K)",
    "coulomb_over_gain": "m/s",
    "coulomb_pos_over_gain": "m/s",
    "coulomb_neg_over_gain": "m/s",
    "offset_over_gain": "m/s",
    "sigma1": "s",
    "lengthscale": "s",
    "period": "s (ψ)",
    "budget": "KRLS-T dictionary size M",
    "spindle_rpm": "rpm, nominal: used without spindle data",
    "per": "revolution (2π: runout) | tooth (2π/teeth)",
    "search": "the monitor chooses the disturbance model online from the samples it sees, starting from this one",
    "noise": "m/s, std of the measurement part ε of the one-step residual (not of a disturbance)",
    "offset_separated": "true: a process's mean force is kept out of offset and friction; false: they hold it",
    "delay": "samples: the force acts this late; z1 = u(k−d), velocity-loop v_r(k−d) − v_m(k−d) + v_m(k)",
}

_IDENT_KEYS = [k for k in _IdentificationT.__struct_fields__ if k != "candidates"]
_PHYS_KEYS = set(_PhysicalT.__struct_fields__)


def save_model(model: AxisModel, path) -> Path:
    """Write ``model`` as a version-2 TOML model file (atomic replace). The file is read back through
    the validator before it replaces ``path`` (nothing that :func:`load_model` would refuse for its
    format is ever written)."""
    path = Path(path)
    tracker = {"kernel": model.tracker.kernel.kind, **msgspec.structs.asdict(model.tracker.kernel)}
    tracker.update(gamma=model.tracker.gamma, forgetting=model.tracker.forgetting, budget=model.tracker.budget,
                   jitter=model.tracker.jitter, search=model.tracker.search)
    ident = {k: model.identification.get(k) for k in _IDENT_KEYS}
    lines = [
        "# feedmon axis model (written by 'feedmon identify'; units SI)",
        f"format_version = {FORMAT_VERSION}",
        "",
        *_table("axis", {"machine": model.machine, "axis": model.axis}),
        *_table(
            "model",
            {
                "form": model.form,
                "Ts": float(model.Ts),
                "beta": [float(b) for b in model.beta],
                "beta_se": None if model.beta_se is None else [float(s) for s in model.beta_se],
                "beta_names": list(model.beta_names),
                "omega": float(model.omega),
                "coulomb": bool(model.coulomb),
                "loop_gain": None if model.loop_gain is None else float(model.loop_gain),
                "method": model.method,
                "noise": None if model.noise is None else float(model.noise),
                "offset_separated": model.offset_separated,
                "delay": model.delay or None,
            },
            {k: v for k, v in _UNITS.items() if k != "coulomb"} | {"coulomb": "Coulomb friction columns in β"},
        ),
        *_table("physical", {k: v for k, v in model.physical.items() if k in _PHYS_KEYS}, _UNITS),
        *_table("physical_se", {k: v for k, v in model.physical_se.items() if k in _PHYS_KEYS}),
        *_table("tracker", tracker, _UNITS),
        *_table("identification", ident, _UNITS),
    ]
    for cand in model.candidates:
        lines += [line.replace("[identification.candidates]", "[[identification.candidates]]")
                  for line in _table("identification.candidates", cand)]
    if model.validity_warning:
        lines += _table("validity", {"warning": model.validity_warning})
    lines += [line for name, items, notes in OS.model_tables(model.online) for line in _table(name, items, notes)]
    lines += _table("provenance", model.provenance)
    text = "\n".join(lines)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    try:
        load_model(tmp, allow_invalid=True)
    except ModelFileError as exc:
        tmp.unlink(missing_ok=True)
        raise ValueError(str(exc).replace(str(tmp), str(path))) from None
    tmp.replace(path)
    return path
