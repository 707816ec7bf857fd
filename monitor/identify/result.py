"""What one identification found (:class:`Identification`): the JSON document and the model file."""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field

import msgspec
import numpy as np

from kernels.adequacy import Adequacy
from kernels.low_speed import LowSpeedFriction
from kernels.noise import NoiseEstimate

from .. import online_settings as OS
from ..model_file import AxisModel, TrackerConfig, file_sha256
from .candidates import Candidate, MethodResult


@dataclass
class Identification:
    """Everything ``feedmon identify`` found on one axis of a trial."""

    trial_path: str
    machine: str
    axis: str
    form: str
    Ts: float
    period: float | None  # ψ of the periodic candidate(s) in play (the chosen one's when periodic)
    period_source: str  # given | spindle | detected | none
    period_suggested: float | None
    omega: float
    coulomb: bool
    coulomb_note: str
    rest: bool
    names: tuple[str, ...]  # spec β names (model file)
    loop_gain: float | None
    candidates: list[Candidate]
    chosen: Candidate | None
    ls: MethodResult
    pl: MethodResult | None
    model_result: MethodResult | None
    y: np.ndarray  # v_m(k+1), m/s
    t: np.ndarray  # time of y (s)
    refusal: str | None = None
    truth: dict | None = None
    truth_force: np.ndarray | None = None  # true disturbance force (N) aligned with y
    truth_f: np.ndarray | None = None  # true disturbance (m/s) aligned with y
    measured_force: np.ndarray | None = None  # e.g. dynamometer (N) aligned with y
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def chosen_method(self) -> str | None:
        return None if self.chosen is None else self.chosen.method

    @property
    def f(self) -> np.ndarray | None:
        """Disturbance estimate of the PL-LSSVM result (m/s)."""
        return None if self.pl is None else self.pl.f

    @property
    def f_force(self) -> np.ndarray | None:
        return None if self.pl is None else self.pl.f_force

    @property
    def hyperparameters(self) -> dict:
        return {} if self.pl is None else self.pl.candidate.hyperparameters
    spindle: dict | None = None  # {"teeth", "spindle_rpm"} when the trial's samples carry spindle data
    periods: list[float] = field(default_factory=list)  # every ψ in play (s; several when the spindle speed changes)
    low_speed: LowSpeedFriction | None = None  # the friction law near standstill (kernels.low_speed)
    min_speed: float = 0.0  # m/s: below it the friction departs from the law (the monitor learns β above it)
    checks: dict = field(default_factory=dict)  # what the data say beyond β (the JSON "checks")
    noise: NoiseEstimate | None = None  # the measurement noise in the written model's residual (kernels.noise)
    offset_separated: bool | None = None  # a process's mean force kept out of friction and offset
    adequacy: Adequacy | None = None  # does the rigid model explain the data (kernels.adequacy)
    delay: int = 0  # samples from a command to its force, modelled

    def to_json(self) -> dict:
        """The ``--json`` document (issue 10): exactly the keys form, Ts, chosen, period, candidates,
        ls, pl_lssvm, model, truth."""
        model = None
        if self.model_result is not None:
            c = self.model_result.candidate
            model = {"method": c.method, "beta": c.beta.tolist(), "beta_se": c.beta_se.tolist(),
                     "physical": c.physical,
                     "physical_se": {k: v for k, v in c.physical_se.items() if not k.startswith("_")}}
        return {
            "form": self.form,
            "Ts": self.Ts,
            "chosen": self.chosen_method,
            "period": {"value": self.period, "source": self.period_source, "suggested": self.period_suggested},
            "candidates": [c.summary() for c in self.candidates],
            "ls": self.ls.to_json(self.names, self.notes),
            "pl_lssvm": None if self.pl is None else self.pl.to_json(self.names, self.notes),
            "model": model,
            "truth": self.truth,
            "checks": self.checks,
        }

    def _tracker_kernel(self, chosen, psi) -> tuple[str, dict | None]:
        """The online tracker's kernel family and σ1, σ2, γ (issue 11: REML-tuned values track best).

        The tracker follows the evidence: the chosen candidate's kernel when it is a locally periodic one
        at the tracker's period ψ (its zero-mean form too — a disturbance without a slowly varying mean,
        so the tracker leaves slow forces to β, online as offline); when the chosen model is LS or of
        another kernel, the best tuned locally periodic candidate at ψ by evidence. ``("locally_periodic",
        None)`` (thesis values) when none was tuned. With spindle data the tracker runs the spindle-phase
        kernel: the tuned spindle-phase candidate's values when there is one (the speed changed)."""
        if self.spindle:
            spindle = [c for c in self.candidates if c.kernel == "spindle" and c.hyperparameters.get("tuned")]
            if spindle:
                return "spindle", max(spindle, key=lambda c: c.log_evidence).hyperparameters
        families = ("locally_periodic", "locally_periodic_zero_mean")
        if psi is not None:
            others = sorted((x for x in self.candidates if x is not chosen),
                            key=lambda x: -(x.log_evidence if x.log_evidence is not None else -math.inf))
            for cand in [chosen, *others]:
                hp = cand.hyperparameters
                if (cand.kernel in families and cand.period is not None
                        and abs(cand.period - psi) <= 1e-9 * psi and hp.get("tuned")
                        and all(hp.get(k) is not None for k in ("sigma1", "sigma2", "gamma"))):
                    return cand.kernel, hp
        return "locally_periodic", None

    def to_model(self, *, tracker: dict | None = None, feedmon_version: str = "", force: bool = False) -> AxisModel:
        """The axis model file for ``feedmon run``: β of the chosen candidate (of the best one by
        evidence when ``force`` and nothing is valid), the tracker defaults with ψ = the period."""
        res = self.model_result
        if res is None:
            raise ValueError(self.refusal or "no model to write")
        c = res.candidate
        if not c.valid and not force:
            raise ValueError(f"the {c.label} model is not valid: {c.why_not}")
        # the tracker's period: the chosen model's, else one the user gave (a period found in the data
        # whose candidates were not chosen is no reason to make the online kernel periodic)
        psi = c.period if c.period is not None else (self.period if self.period_source in ("given", "spindle") else None)
        family, tuned = self._tracker_kernel(c, psi)
        # issue 11: λ, M from measurements, σ1, σ2, γ from REML when tuned, the spindle-phase kernel when
        # the samples carry the spindle (monitor.online_settings.tracker_table, one definition)
        spindle = self.spindle if family != "spindle" else {**self.spindle, "per": tuned.get("per", "revolution")}
        cfg = OS.tracker_table(tuned=tuned, period=psi or 1.0, spindle=spindle)
        k = cfg["kernel"]
        if psi is None and not self.spindle:  # no periodic disturbance in play: a smooth, slowly varying one
            cfg["kernel"] = OS.SquaredExponentialKernel(lengthscale=k.sigma1)
        elif not self.spindle and family != "locally_periodic":
            cfg["kernel"] = OS.TRACKER_KERNELS[family](sigma1=k.sigma1, sigma2=k.sigma2, period=k.period)
        for key, value in (tracker or {}).items():  # explicit settings: kernel hyperparameters go into the kernel
            if key in cfg["kernel"].__struct_fields__:
                cfg["kernel"] = msgspec.structs.replace(cfg["kernel"], **{key: value})
            else:
                cfg[key] = value
        kernel = cfg["kernel"]
        ident = {"chosen": c.method, "kernel": c.kernel or "none", "period": c.period,
                 "period_source": self.period_source, "log_evidence": c.log_evidence}
        ident.update({k: v for k, v in c.hyperparameters.items() if isinstance(v, (int, float, bool))})
        if c.method == "pl_lssvm":
            ident["order"] = c.order
        if self.checks.get("offset_note"):
            ident["offset_note"] = self.checks["offset_note"]
        if self.adequacy is not None and not self.adequacy.adequate:
            ident["adequacy"] = f"the rigid model does not fit this drive: {self.adequacy.message}"
        candidates = [{"method": x.method, "kernel": x.kernel or "none", "period": x.period,
                       "log_evidence": x.log_evidence, "valid": x.valid, "why_not": x.why_not or ""}
                      | ({"per": x.hyperparameters.get("per", "revolution")} if x.kernel == "spindle" else {})
                      for x in self.candidates]
        warning = None if c.valid else f"written with --force although invalid: {c.why_not}"
        return AxisModel(
            machine=self.machine,
            axis=self.axis,
            form=self.form,
            Ts=self.Ts,
            beta=[float(b) for b in c.beta],
            beta_names=tuple(self.names),
            beta_se=[float(s) for s in c.beta_se],
            omega=self.omega,
            coulomb=self.coulomb,
            loop_gain=self.loop_gain,
            method="ls" if c.method == "ls" else "pl-lssvm",
            tracker=TrackerConfig(kernel=kernel, gamma=cfg["gamma"], forgetting=cfg["forgetting"],
                                  budget=int(cfg["budget"]), jitter=cfg["jitter"]),
            physical=dict(c.physical),
            physical_se={k: v for k, v in c.physical_se.items() if not k.startswith("_")},
            identification=ident,
            candidates=candidates,
            validity_warning=warning,
            noise=None if self.noise is None else float(self.noise.sigma_eps),
            offset_separated=self.offset_separated,
            delay=int(self.delay),
            # β learns only where the friction law holds (kernels.low_speed); every other setting its default
            online=OS.OnlineSettings(adaptation=OS.Adaptation(
                min_speed=float(self.min_speed))),
            provenance={
                "source": self.trial_path,
                "sha256": file_sha256(self.trial_path),
                "method": "ls" if c.method == "ls" else "pl-lssvm",
                "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                "feedmon_version": feedmon_version,
            },
        )


