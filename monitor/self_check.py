"""Self-check of an identified model: the monitor run over the very trial it was identified on.

``feedmon identify`` chooses among batch candidates (LS, PL-LSSVM with kernels in time and, when the
spindle speed changes, the spindle-phase kernel). Their standard errors say how well the data
determine β *if the candidate's disturbance model is right*; they cannot show a bias that the
candidate's own model hides. The online monitor estimates β
with a different disturbance model — the tracker's kernel — and tests the drift of each physical
parameter against the model file (:mod:`kernels.health`). Run over the identification trial itself
(or the window identified), with the model just identified, it must find nothing: the data are the
same. A drift warning or alarm there means the identified values and the tracker's view of the same
data disagree by more than the health thresholds (≥ 6 standard errors *and* ≥ 3 %): at least one
of them is biased, and the model file should not be used as a reference for drift without checking
it. Measured: a milling trial whose spindle goes 3000 → 2400 → 3600 rpm, identified before the
spindle-phase candidate existed — every batch candidate found an inertia of 770–1110 kg at ± 7–11
kg (truth 1500 kg), the monitor over the same trial 1530 kg: alarm from 5 s (now: 1502 ± 2.9 kg,
ok). ``DATA_EMPS.mat`` without a period was flagged (damping +21 %) until the online β learned
only above the drive's low-speed friction departure (:mod:`kernels.low_speed`). Still flagged: the
EMPS pulses identified on themselves (README, self-check).

The check is what ``feedmon run --from`` does (:class:`~monitor.estimator.AxisEstimator`, the
model file's own tracker, adaptation and health settings, adaptation *track* when the file says
*off*, so that β is estimated), without writing anything.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import msgspec

from feedio.schema import SAMPLE_COLUMNS

__all__ = ["SelfCheck", "self_check"]


@dataclass
class SelfCheck:
    """Outcome of :func:`self_check`: ``state`` the worst health state over the trial (ok | warn |
    alarm), ``reports`` and ``flagged`` (warn or alarm) counts, ``reasons`` the first reason of each
    kind (one per parameter, the innovation test), ``online`` the last report's physical values
    ``{name: (value, standard error)}`` (SI; None when not given)."""

    state: str
    reports: int
    flagged: int
    reasons: list[str] = field(default_factory=list)
    online: dict[str, tuple[float | None, float | None]] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.state == "ok"

    def summary(self) -> str:
        """One line for the terminal and the model file."""
        if self.reports == 0 and not self.reasons:
            return "not run: the trial gave no health report (too short for one)"
        if self.ok:
            return f"ok: the monitor over this trial with this model raised nothing ({self.reports} health reports)"
        return (f"{self.state}: the monitor over this very trial with this model disagrees with it in "
                f"{self.flagged} of {self.reports} health reports — " + "; ".join(self.reasons)
                + " — the identified values or the tracker's are biased on these data; check them before "
                "using the file as the reference for drift")

    def to_json(self) -> dict:
        return {"state": self.state, "reports": self.reports, "flagged": self.flagged, "reasons": self.reasons,
                "online": {k: {"value": v, "se": s} for k, (v, s) in self.online.items()},
                "summary": self.summary()}


def _kind(reason: str) -> str:
    """What a health reason is about: the parameter of a drift, else the text before the first ':'."""
    head = reason.split(" drift ", 1)[0] if " drift " in reason else reason.split(":", 1)[0]
    return head.strip()


def _within(block, lo: int, hi: int):
    """The part of a sample block with ``lo ≤ seq ≤ hi`` (None when nothing is left)."""
    a, b = max(lo - block.seq, 0), min(hi - block.seq + 1, len(block))
    if a >= b:
        return None
    if (a, b) == (0, len(block)):
        return block
    cols = {k: getattr(block, k)[a:b] for k in SAMPLE_COLUMNS if getattr(block, k) is not None}
    return msgspec.structs.replace(block, seq=block.seq + a, **cols)


def self_check(trial_path: str, model, seq_range: tuple[int, int] | None = None) -> SelfCheck:
    """Run ``model`` (:class:`~monitor.model_file.AxisModel`) over the sample blocks of its axis in
    ``trial_path`` (an MCAP trial, as ``feedmon run --from`` reads it) — only the samples with
    ``seq_range[0] ≤ seq ≤ seq_range[1]`` when given (the window identified) — and collect the health
    reports."""
    from feedio.mcapio import iter_axes
    from feedio.schema import HEALTH_STATES

    from .estimator import AxisEstimator, TrackerBreakdown

    if model.online.adaptation.mode == "off":  # β must be estimated to be compared
        online = msgspec.structs.replace(model.online,
                                         adaptation=msgspec.structs.replace(model.online.adaptation, mode="track"))
        model = dataclasses.replace(model, online=online)
    est = AxisEstimator(model)
    name = f"{model.machine}/{model.axis}"
    reports = []
    breakdowns: list[str] = []
    blocks = iter_axes(trial_path, [name], kinds=("samples",))[name]
    try:
        for _, _, block in blocks:
            if seq_range is not None:
                if block.seq > seq_range[1]:  # past the window: the rest of a long record is not read
                    break
                block = _within(block, *seq_range)
                if block is None:
                    continue
            try:
                est.process_rows(block)
            except TrackerBreakdown as exc:  # the monitor would drop the block and start over: so does the check
                breakdowns.append(str(exc))
            reports += est.take_health()
    finally:
        blocks.close()
    flagged = [h for h in reports if h.state != "ok"]
    worst = max((h.state for h in flagged), key=HEALTH_STATES.index, default="ok")
    reasons: dict[str, str] = {}                   # the first reason of each kind, in order
    if breakdowns:  # the tracker cannot run this model on these data: the strongest finding there is
        worst = "alarm"
        reasons["breakdown"] = f"the tracker broke down {len(breakdowns)} time(s): {breakdowns[0]}"
    for r in (r for h in flagged for r in h.reasons if " drift " in r or r.startswith("innovation")):
        reasons.setdefault(_kind(r), r)
    last = reports[-1] if reports else None
    online = {} if last is None else {k: (getattr(last, k), getattr(last, f"{k}_se"))
                                      for k in ("inertia", "damping", "coulomb", "offset")}
    return SelfCheck(worst, len(reports), len(flagged), list(reasons.values()), online)
