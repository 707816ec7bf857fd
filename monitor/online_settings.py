"""The online settings of an axis beyond β: tracker kernel choice and defaults, β adaptation, health.

They live in the model file (``[tracker]``: the kernel and its hyperparameters, λ, budget,
jitter; ``[adaptation]``; ``[health]``) and ``feedmon run --config`` may override any of them for
every axis (``[run.tracker]``, ``[run.adaptation]``, ``[run.health]``). Each setting has a
documented range (msgspec ``Meta``, checked when a file is read: an error names the file, the
key and the range) and says what it trades; README "Online β and health" has the table.

Tracker kernels (method §5, §6):

* the time kernel ``LocallyPeriodic(σ1, σ2, ψ)`` on ``x = t`` (``[tracker] kernel =
  "locally_periodic"``, ``period`` ψ in s) — a fixed disturbance period;
* the spindle-phase kernel (``kernel = "spindle"``) on ``x = (t, θ)``, θ the spindle angle
  (rad): ``SquaredExponential(σ1, dims=0) × Periodic(σ2, P, dims=1)`` with ``P = 2π`` (``per =
  "revolution"``: runout, the default) or ``2π/teeth`` (``per = "tooth"``). With
  ``θ = 2π·n/60·t`` it *is* the time kernel with ``ψ = 60/n`` (per revolution), so σ1, σ2
  mean the same in both; a change of spindle speed needs no new model. ``spindle_rpm`` (the
  identification trial's median speed) is the nominal speed used when samples carry no
  spindle data (the fallback, counted ``spindle_fallback``: then it is exactly the time kernel
  with ψ = 60/``spindle_rpm``).

Defaults from measurements (``benchmarks/tracker_defaults.py``, ``benchmarks/online_checks.py``):
λ = 0.998 at 333 Hz (memory ≈ 1.5 s: less lag at disturbance edges than the thesis' 0.996
without losing steady-cutting accuracy), M = 100; σ1, σ2, γ the REML-tuned values of
identification when it tuned them (``feedmon identify --tune``), else the thesis' Table 4.5.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import msgspec

from feedio.limits import SPINDLE_RPM_MAX, bounded_float, bounded_int, explain, field_range
from kernels.beta_tracker import MIN_SPEED_MAX
from kernels.covariance import Kernel, LocallyPeriodic, Periodic, SquaredExponential, ZeroMeanLocallyPeriodic
from kernels.disturbance_search import SIGMA1_RANGE, TrackerChoice
from kernels.errors import ParameterError
from kernels.flags import ADAPTATION_MODES
from kernels.health import HEALTH_RANGES, HealthConfig
from kernels.spindle_phase import spindle_phase_kernel

__all__ = ["TRACKER_DEFAULTS", "BUDGET_RANGE", "JITTER_RANGE", "SPINDLE", "PER", "TrackerKernel", "TRACKER_KERNELS",
           "SquaredExponentialKernel", "LocallyPeriodicKernel", "ZeroMeanLocallyPeriodicKernel", "PeriodicKernel",
           "SpindleKernel", "Adaptation", "Health", "OnlineSettings", "TrackerOverride", "AdaptationOverride",
           "HealthOverride", "tracker_table", "choice_of", "parse_model_tables", "model_tables", "apply_overrides"]

#: online KRLS-T defaults: thesis Table 4.5 kernel (σ1 s, σ2, γ) with the measured λ and M
TRACKER_DEFAULTS = {"sigma1": 1.2, "sigma2": 0.495, "gamma": 5.85, "forgetting": 0.998, "budget": 100,
                    "jitter": 1e-6}
#: dictionary size M, for the model file's ``[tracker]`` and ``[run.tracker]`` alike: the step costs ∝ M²
#: (M = 400: ~70 µs; 2000: ~1.8 ms, real time at 333 Hz only; 4096 ran at 94 samples/s), and below 4 the
#: tracker holds too little of the disturbance to follow it
BUDGET_RANGE = (4, 2000)
#: jitter ε_j on K_D's diagonal (normalised kernel), for both files: below ~1e-9 Q ≈ K_D⁻¹ is lost to
#: roundoff (ε_j = 0, 1e-12 and 1e-10 broke down on simulated drives, :meth:`kernels.krlst.KRLST.breakdown`)
JITTER_RANGE = (1e-8, 0.1)
SPINDLE = "spindle"
PER = ("revolution", "tooth")

_OPTS = dict(frozen=True, forbid_unknown_fields=True, kw_only=True)

_Seconds = bounded_float(1e-6, 1e6, "s")
_Sigma2 = bounded_float(1e-3, 1e3)


class _TrackerKernel(msgspec.Struct, tag_field="kernel", **_OPTS):
    """A ``[tracker]`` kernel: the ``kernel`` key of the file is the tag, the fields are exactly that
    kernel's keys (a key of another kernel is refused when the file is read)."""

    @property
    def kind(self) -> str:
        """The ``kernel`` string of the model file."""
        return type(self).__struct_config__.tag

    def build(self) -> Kernel:
        """The :class:`kernels.covariance.Kernel` the online tracker runs."""
        raise NotImplementedError


class SquaredExponentialKernel(_TrackerKernel, tag="squared_exponential"):
    """A smooth, slowly varying disturbance: ``SquaredExponential(ℓ)`` on time."""

    lengthscale: _Seconds

    def build(self) -> Kernel:
        return SquaredExponential(self.lengthscale)


class LocallyPeriodicKernel(_TrackerKernel, tag="locally_periodic"):
    """``LocallyPeriodic(σ1, σ2, ψ)`` on time (method §5): a fixed disturbance period ψ."""

    sigma1: _Seconds
    sigma2: _Sigma2
    period: _Seconds

    def build(self) -> Kernel:
        return LocallyPeriodic(self.sigma1, self.sigma2, self.period)


class ZeroMeanLocallyPeriodicKernel(_TrackerKernel, tag="locally_periodic_zero_mean"):
    """The locally periodic kernel without its slowly varying mean (:class:`kernels.covariance.ZeroMeanLocallyPeriodic`)."""

    sigma1: _Seconds
    sigma2: _Sigma2
    period: _Seconds

    def build(self) -> Kernel:
        return ZeroMeanLocallyPeriodic(self.sigma1, self.sigma2, self.period)


class PeriodicKernel(_TrackerKernel, tag="periodic"):
    """``Periodic(σ2, ψ)`` on time: a period that never decorrelates."""

    sigma2: _Sigma2
    period: _Seconds

    def build(self) -> Kernel:
        return Periodic(self.sigma2, self.period)


class SpindleKernel(_TrackerKernel, tag=SPINDLE, kw_only=True):
    """The spindle-phase kernel of ``[tracker] kernel = "spindle"`` (see the module docstring)."""

    sigma1: bounded_float(1e-6, 1e4, "s")  # length scale of the slow (time) factor
    sigma2: _Sigma2  # smoothness of the periodic factor (as in the time kernel)
    per: Literal["revolution", "tooth"] = "revolution"
    teeth: bounded_int(1, 1000, "cutting edges of the tool") = 1
    spindle_rpm: bounded_float(0.0, SPINDLE_RPM_MAX, "rpm, nominal: the fallback without spindle data", open_low=True)

    @property
    def period(self) -> float:
        """Period of the periodic factor in spindle angle (rad): 2π per revolution, 2π/teeth per tooth."""
        return 2.0 * math.pi / (self.teeth if self.per == "tooth" else 1)

    def build(self) -> Kernel:
        return spindle_phase_kernel(self.sigma1, self.sigma2, self.period)


#: the ``[tracker]`` kernel of a model file, one Struct per ``kernel`` string (a msgspec tagged union)
TrackerKernel = (SquaredExponentialKernel | LocallyPeriodicKernel | ZeroMeanLocallyPeriodicKernel | PeriodicKernel
                 | SpindleKernel)
#: the kernel Struct of each ``kernel`` string
TRACKER_KERNELS = {k.__struct_config__.tag: k for k in TrackerKernel.__args__}


def choice_of(tracker) -> TrackerChoice:
    """The :class:`~kernels.disturbance_search.TrackerChoice` a model file's ``[tracker]`` starts the
    online search from (a :class:`monitor.model_file.TrackerConfig`). A pure periodic kernel is the
    locally periodic one with the longest σ1 the search allows."""
    k = tracker.kernel
    common = dict(gamma=float(tracker.gamma), forgetting=float(tracker.forgetting))
    if isinstance(k, SpindleKernel):
        return TrackerChoice("spindle", sigma1=k.sigma1, sigma2=k.sigma2,
                             teeth=k.teeth if k.per == "tooth" else 1, **common)
    if isinstance(k, LocallyPeriodicKernel | ZeroMeanLocallyPeriodicKernel):
        return TrackerChoice("periodic", sigma1=float(k.sigma1), sigma2=float(k.sigma2),
                             period=float(k.period), zero_mean=isinstance(k, ZeroMeanLocallyPeriodicKernel), **common)
    if isinstance(k, PeriodicKernel):
        return TrackerChoice("periodic", sigma1=SIGMA1_RANGE[1], sigma2=float(k.sigma2),
                             period=float(k.period), **common)
    return TrackerChoice("time", sigma1=float(k.lengthscale), **common)


def tracker_table(*, tuned: dict | None, period: float, spindle: dict | None) -> dict:
    """The ``[tracker]`` settings ``feedmon identify`` writes: λ, M, jitter from
    :data:`TRACKER_DEFAULTS`; σ1, σ2, γ the REML-tuned values when identification tuned them, else
    the thesis'; the spindle-phase kernel when the trial has spindle data (``spindle``: ``teeth``,
    the median ``spindle_rpm`` and ``per``, default "revolution"), else the time kernel with ψ = ``period`` (s). Returns the
    kernel (a :data:`TrackerKernel`) under ``"kernel"`` and the scalar settings."""
    cfg = dict(TRACKER_DEFAULTS)
    if tuned:
        cfg.update({k: float(tuned[k]) for k in ("sigma1", "sigma2", "gamma")})
    if spindle:
        kernel = SpindleKernel(sigma1=cfg["sigma1"], sigma2=cfg["sigma2"], per=spindle.get("per", "revolution"),
                               teeth=int(spindle.get("teeth") or 1), spindle_rpm=float(spindle["spindle_rpm"]))
    else:
        kernel = LocallyPeriodicKernel(sigma1=cfg["sigma1"], sigma2=cfg["sigma2"], period=float(period))
    return {"kernel": kernel, "gamma": cfg["gamma"], "forgetting": cfg["forgetting"], "budget": int(cfg["budget"]),
            "jitter": cfg["jitter"]}


class Adaptation(msgspec.Struct, **_OPTS):
    """``[adaptation]``: online β (method "Online β and health"; :mod:`kernels.beta_tracker`)."""

    #: off: β stays the model file's, nothing estimated (cheapest); track (default): β̂ and its
    #: covariance are estimated and reported (health, drift alarms), the disturbance uses the
    #: model file's β; apply: the disturbance uses β̂ (unbiased under drift, but β̂ may take up
    #: a disturbance that moves with the motion)
    mode: Literal[ADAPTATION_MODES] = "track"
    #: T_β of the friction parameters (damping, Coulomb, offset), s of learning samples: a drift of ṙ
    #: per second lags by ≈ 1.5 ṙ·T_β; standard errors ∝ 1/√T_β
    memory: bounded_float(0.5, 3600.0, "s, β memory T_β of damping, Coulomb, offset (drift lag vs noise)") = 5.0
    #: T_J, the inertia's: excited only while the axis accelerates, so it needs a longer memory to
    #: rest on several accelerations (a payload step is followed within ≈ 2 T_J)
    inertia_memory: bounded_float(0.5, 3600.0, "s, β memory T_J of the inertia (step lag vs noise)") = 10.0
    #: ρ, relative drift allowance of the prior P₀ (bounds P; larger: faster start, farther wander
    #: of weakly determined parameters)
    allowance: bounded_float(0.01, 10.0, "relative drift allowance ρ of the prior") = 0.3
    #: Huber threshold (standard deviations): smaller bounds outliers harder, larger is more efficient
    huber: bounded_float(1.0, 100.0, "Huber threshold c (standard deviations)") = 3.0
    #: the model's one-step velocity prediction as instrument of v_m (removes the closed-loop noise bias)
    instrument: bool = True
    #: |ν| beyond which a sample teaches nothing (None: off; delays learning after a real step)
    reject: bounded_float(1.0, 1000.0, "standard deviations, > huber; none = off") | None = None
    #: s after a rejected sample that teach nothing either
    hold: bounded_float(0.0, 60.0, "s after a rejected sample") = 0.0
    #: m/s: β learns only above this speed, where the model's friction law holds (written by
    #: ``feedmon identify`` from its low-speed friction check, :mod:`kernels.low_speed`; 0: down to Ω)
    min_speed: bounded_float(0.0, MIN_SPEED_MAX, "m/s, β learns only above (friction law holds)") = 0.0

    def __post_init__(self) -> None:
        if self.reject is not None and not self.reject > self.huber:
            raise ValueError(f"adaptation.reject = {self.reject!r} must be larger than adaptation.huber = {self.huber!r}")


_H = HealthConfig()


def _health_field(name: str) -> Any:
    """The msgspec field type of a ``[health]`` setting, from its range in :data:`kernels.health.HEALTH_RANGES`."""
    lo, hi, open_low, doc = HEALTH_RANGES[name]
    return bounded_float(lo, hi, doc, open_low=open_low)


class Health(msgspec.Struct, **_OPTS):
    """``[health]``: the health verdict (:mod:`kernels.health`; what each trades is documented there)."""

    period: bounded_float(0.1, 60.0, "s of data time between two health reports") = 1.0
    tau: _health_field("tau") = _H.tau
    clip: _health_field("clip") = _H.clip
    warn: _health_field("warn") = _H.warn
    alarm: _health_field("alarm") = _H.alarm
    clear: _health_field("clear") = _H.clear
    persist: _health_field("persist") = _H.persist
    hold: _health_field("hold") = _H.hold
    z_warn: _health_field("z_warn") = _H.z_warn
    z_alarm: _health_field("z_alarm") = _H.z_alarm
    z_clear: _health_field("z_clear") = _H.z_clear
    rel_warn: _health_field("rel_warn") = _H.rel_warn
    rel_alarm: _health_field("rel_alarm") = _H.rel_alarm
    kappa: _health_field("kappa") = _H.kappa
    warmup: _health_field("warmup") = _H.warmup

    def __post_init__(self) -> None:
        try:
            self.config()
        except ValueError as exc:
            raise ValueError(str(exc).replace("health setting ", "health.")) from None

    def config(self) -> HealthConfig:
        """The :class:`kernels.health.HealthConfig` (cross-field rules checked)."""
        d = msgspec.structs.asdict(self)
        d.pop("period")
        return HealthConfig(**d).validate()


class OnlineSettings(msgspec.Struct, **_OPTS):
    """``[adaptation]`` and ``[health]`` of one axis (``AxisModel.online``)."""

    adaptation: Adaptation = Adaptation()
    health: Health = Health()


def _override_of(struct: type) -> type:
    """A Struct with the fields of ``struct``, each optional (None: keep the model file's value)."""
    fields = []
    for f in msgspec.structs.fields(struct):
        fields.append((f.name, f.type | None, None))
    return msgspec.defstruct(f"{struct.__name__}Override", fields, **_OPTS, module=__name__)


class TrackerOverride(msgspec.Struct, **_OPTS):
    """``[run.tracker]``: tracker settings for every axis instead of the model files' (None: keep).

    ``forgetting`` λ (memory ≈ Ts/(1 − λ): shorter follows disturbance edges, longer averages
    steady cutting), ``budget`` M (cost ∝ M², more detail), ``jitter`` ε_j (numerical floor),
    ``sigma1`` (s), ``sigma2``, ``gamma`` (kernel hyperparameters, method §5; γ = signal/noise)."""

    forgetting: bounded_float(0.5, 1.0, "λ per sample", open_low=True) | None = None
    budget: bounded_int(*BUDGET_RANGE, "dictionary size M") \
        | None = None
    jitter: bounded_float(*JITTER_RANGE, "ε_j") | None = None
    sigma1: bounded_float(0.0, 1e4, "s", open_low=True) | None = None
    sigma2: bounded_float(0.0, 1e3, "", open_low=True) | None = None
    gamma: bounded_float(0.0, 1e12, "γ", open_low=True) | None = None
    search: bool | None = None


#: ``[run.adaptation]``: the fields of :class:`Adaptation`, each optional (None: the model file's)
AdaptationOverride = _override_of(Adaptation)
#: ``[run.health]``: the fields of :class:`Health`, each optional (None: the model file's)
HealthOverride = _override_of(Health)


def _convert(table: Any, struct: type, where: str, name: str):
    """``table`` as ``struct``; ``ValueError`` "<where>: key '<name>.<field>': <problem> (allowed: <range>)"
    (:func:`feedio.limits.explain`)."""
    try:
        return msgspec.convert(table, struct)
    except msgspec.ValidationError as exc:
        key, msg = explain(exc, struct)
        key = name if key == "(top level)" else f"{name}.{key}"
        raise ValueError(f"{where}: key '{key}': {msg}") from None
    except ValueError as exc:  # a cross-field rule in __post_init__
        raise ValueError(f"{where}: key '{name}': {exc}") from None


def parse_model_tables(doc: dict, path) -> OnlineSettings:
    """``[adaptation]`` and ``[health]`` of a model file (optional tables; defaults when absent).
    ``ValueError`` naming the file, the key and the allowed range."""
    out = {}
    for name, struct in (("adaptation", Adaptation), ("health", Health)):
        table = doc.get(name, {})
        if not isinstance(table, dict):
            raise ValueError(f"{path}: key '{name}': must be a table [{name}], got {type(table).__name__}")
        out[name] = _convert(table, struct, str(path), name)
    return OnlineSettings(**out)


#: the comment written next to each setting in a model file: unit and what it trades
def _span(struct: type, name: str) -> str:
    """``lo … hi`` of a field's range (:func:`feedio.limits.field_range`), for the comments a model file
    carries beside its settings."""
    lo, hi = field_range(struct, name)
    return f"{lo:g} … {hi:g}"


COMMENTS = {
    "adaptation": {
        "mode": "off | track (β estimated, disturbance with the file's β) | apply (disturbance with online β)",
        "memory": "s of learning samples, damping, Coulomb, offset: drift lag ≈ 1.5 × rate × memory vs. noise "
                  f"∝ 1/√memory ({_span(Adaptation, 'memory')})",
        "inertia_memory": "s of learning samples, inertia (excited only while accelerating): step lag vs. noise "
                          f"({_span(Adaptation, 'inertia_memory')})",
        "allowance": f"relative drift the prior allows ({_span(Adaptation, 'allowance')}): bounds the covariance of β",
        "huber": f"standard deviations ({_span(Adaptation, 'huber')}): a sample's largest influence",
        "instrument": "model's velocity prediction as instrument of v_m (closed-loop noise bias)",
        "reject": "standard deviations (> huber): larger innovations teach nothing; absent = off",
        "hold": f"s after a rejected sample that teach nothing ({_span(Adaptation, 'hold')})",
        "min_speed": f"m/s: β learns only above it, where the friction law holds ({_span(Adaptation, 'min_speed')}; identify's "
                     "low-speed check)",
    },
    "health": {
        "period": f"s of data time between two health reports ({_span(Health, 'period')})",
        "tau": f"s, EWMA of ν² ({_span(Health, 'tau')}): detection delay vs. noise",
        "clip": f"|ν| clip, standard deviations ({_span(Health, 'clip')}): one outlier's weight",
        "warn": "EWMA of ν² for warn (clear < warn < alarm < clip²): false alarms vs. detection",
        "alarm": "EWMA of ν² for alarm",
        "clear": "EWMA of ν² below which warn clears (> 1): hysteresis",
        "persist": f"s above a level before it counts ({_span(Health, 'persist')}): bursts vs. delay",
        "hold": f"s below a level before it clears ({_span(Health, 'hold')}): flapping vs. staying up",
        "z_warn": "drift: standard errors for warn (> z_clear)",
        "z_alarm": "drift: standard errors for alarm (≥ z_warn)",
        "z_clear": "drift: standard errors below which warn clears",
        "rel_warn": "drift: relative change for warn (practical significance)",
        "rel_alarm": "drift: relative change for alarm (≥ rel_warn)",
        "kappa": f"a parameter is tested once its s.e. ≤ kappa × prior s.e. ({_span(Health, 'kappa')}]",
        "warmup": f"s of innovations ignored after the start ({_span(Health, 'warmup')})",
    },
}


def model_tables(settings: OnlineSettings) -> list[tuple[str, dict, dict]]:
    """The ``[adaptation]`` and ``[health]`` tables to write into a model file: ``(name, values,
    comments)`` (:data:`COMMENTS`)."""
    return [(name, msgspec.to_builtins(getattr(settings, name)), COMMENTS[name]) for name in ("adaptation", "health")]


def _merged(current, override) -> Any:
    given = {k: v for k, v in msgspec.structs.asdict(override).items() if v is not None}
    if not given:
        return current
    return msgspec.convert({**msgspec.to_builtins(current), **given}, type(current))


def apply_overrides(model, tracker: TrackerOverride | None = None, adaptation=None, health=None):
    """``model`` (an :class:`~monitor.model_file.AxisModel`) with the overrides applied (``feedmon run --config``)
    (a copy; None or empty overrides: the model itself). ``ValueError`` when the result breaks a
    cross-field rule (e.g. health.clear < warn < alarm), naming the setting
    (a :class:`~kernels.errors.ParameterError` naming ``adaptation`` or ``health``)."""
    import copy

    def given(o) -> bool:
        return o is not None and any(v is not None for v in msgspec.structs.asdict(o).values())

    if not any(given(o) for o in (tracker, adaptation, health)):
        return model
    m = copy.deepcopy(model)
    if tracker is not None:
        t = m.tracker
        for k in ("forgetting", "budget", "jitter", "gamma", "search"):
            v = getattr(tracker, k)
            if v is not None:
                setattr(t, k, v)
        sigmas = {k: float(v) for k in ("sigma1", "sigma2")  # a kernel without σ1 (σ2) keeps none
                  if (v := getattr(tracker, k)) is not None and k in t.kernel.__struct_fields__}
        if sigmas:
            t.kernel = msgspec.structs.replace(t.kernel, **sigmas)
        t.kernel.build()  # ValueError: a value the kernel refuses
    online = getattr(m, "online", None) or OnlineSettings()
    try:
        online = OnlineSettings(adaptation=_merged(online.adaptation, adaptation) if adaptation is not None
                                else online.adaptation,
                                health=_merged(online.health, health) if health is not None else online.health)
    except (msgspec.ValidationError, ValueError) as exc:
        names = tuple(name for name, o in (("adaptation", adaptation), ("health", health)) if given(o))
        names = names or ("adaptation", "health")
        raise ParameterError(f"the {'/'.join(names)} overrides for {m.machine}/{m.axis}: {exc}", *names) from None
    m.online = online
    return m
