"""Validity rules 2 and 3 and the choice among the candidates (docs/method.md §8, "Validity")."""

from __future__ import annotations

import math

from .candidates import BIAS_SHARE, BIAS_Z, EFFICIENCY_KEYS, SUGGEST_MARGIN, Candidate


def _efficiency_check(cand: Candidate, ls: Candidate) -> str | None:
    """Validity rule 2 (module docstring): None, or why the candidate determines β worse than LS."""
    worse = []
    for key in EFFICIENCY_KEYS:
        for name in (key, f"{key}_over_gain"):
            a, b = cand.physical_se.get(name), ls.physical_se.get(name)
            if a is None or b is None:
                continue
            if a > b:
                worse.append(f"{name} ± {a:.3g} vs ± {b:.3g}")
    if not worse:
        return None
    return ("the disturbance model competes with the drive's regressors: it determines "
            + ", ".join(worse) + " (LS) — worse than least squares, so this trial does not separate its "
            "disturbance from the drive's parameters")


def _bias_check(cand: Candidate, witnesses: list[Candidate]) -> str | None:
    """Validity rule 3 (module docstring): None, or why one of ``witnesses`` (candidates that determine
    the parameters at least as well as LS: rule 2 holds for them) explains the data far better and shows
    ``cand``'s parameters to be biased by the disturbance it leaves out."""
    for other in witnesses:
        margin = other.log_evidence - cand.log_evidence
        if other is cand or not margin > SUGGEST_MARGIN:
            continue
        for key in EFFICIENCY_KEYS:
            for name in (key, f"{key}_over_gain"):
                a, b = cand.physical.get(name), other.physical.get(name)
                sa, sb = cand.physical_se.get(name), other.physical_se.get(name)
                if None in (a, b, sa, sb) or not all(map(math.isfinite, (a, b, sa, sb))):
                    continue
                z = abs(a - b) / math.hypot(sa, sb) if sa > 0 or sb > 0 else math.inf
                if z > BIAS_Z and abs(a - b) > BIAS_SHARE * abs(b):
                    return (f"biased by the disturbance it leaves out: {other.label} explains the data far better "
                            f"(log evidence {margin:+.0f}) and puts {name} at {b:.4g} ± {sb:.2g}, {z:.1f} s.e. from "
                            f"this model's {a:.4g} ± {sa:.2g}")
    return None




def _invalidate(cand: Candidate, why: str | None) -> None:
    """Mark ``cand`` invalid for ``why`` (kept after any earlier reason); nothing when ``why`` is None."""
    if why:
        cand.valid = False
        cand.why_not = why if cand.why_not is None else f"{cand.why_not}; {why}"


def _choose(candidates: list[Candidate], method: str) -> tuple[Candidate | None, str | None, Candidate | None,
                                                               Candidate | None]:
    """Step 7: ``(chosen, refusal, pl_best, written)`` — the valid candidate of ``method``'s pool with the
    highest evidence (None, with the refusal saying why, when none is valid), the best PL-LSSVM candidate
    (the best valid one, else the best; for the report), and the candidate written to the model file (the
    chosen one, else, for ``--force``, the best of the pool)."""
    pool = {"auto": candidates, "ls": candidates[:1], "pl-lssvm": candidates[1:]}[method]
    valid = [c for c in pool if c.valid]
    chosen = max(valid, key=lambda c: c.log_evidence) if valid else None
    refusal = None
    if chosen is None:
        best = max(pool, key=lambda c: c.log_evidence) if pool else None
        what = {"auto": "no candidate", "ls": "the LS model", "pl-lssvm": "no PL-LSSVM candidate"}[method]
        refusal = f"{what} is a valid model of this drive" + (f": {best.label}: {best.why_not}" if best else "")
        ls = candidates[0]
        if method == "auto" and best is not None and best is not ls:  # its advice may name LS: say why LS is not
            refusal += f"; {ls.label}: {ls.why_not}"
    pl_pool = [c for c in candidates if c.method == "pl_lssvm"]
    pl_best = None
    if pl_pool:
        pl_valid = [c for c in pl_pool if c.valid]
        pl_best = max(pl_valid or pl_pool, key=lambda c: c.log_evidence)
    written = chosen if chosen is not None else (max(pool, key=lambda c: c.log_evidence) if pool else None)
    return chosen, refusal, pl_best, written


