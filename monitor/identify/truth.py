"""Errors against the recorded truth of a simulated (or instrumented) trial, and against a published reference."""

from __future__ import annotations

import numpy as np

from kernels.feed_drive import (
    physical_to_beta,
)

from .result import Identification


def _aligned(truth, seq: np.ndarray, name: str) -> np.ndarray | None:
    """Truth column ``name`` at the samples ``seq`` (NaN where the truth has no value)."""
    col = getattr(truth, name, None)
    if col is None:
        return None
    out = np.full(seq.size, np.nan)
    pos = np.searchsorted(truth.seq, seq)
    ok = (pos < truth.seq.size) & (truth.seq[np.minimum(pos, truth.seq.size - 1)] == seq)
    out[ok] = col[pos[ok]]
    return out


def _corr(a, b) -> float | None:
    if a is None or b is None:
        return None
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.std(a[ok]) == 0 or np.std(b[ok]) == 0:
        return None
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def _true_physical(ident: Identification, truth_meta) -> dict:
    """The truth in the keys of :meth:`kernels.feed_drive.Physical.to_dict` (offset 0 in a simulation)."""
    p = dict(truth_meta.physical)
    out = {}
    scale = 1.0
    suffix = ""
    if ident.form == "velocity-loop" and ident.loop_gain is None:
        K = p.get("loop_gain")
        if not K:
            return {}
        scale, suffix = 1.0 / K, "_over_gain"
    for k in ("inertia", "damping"):
        if k in p:
            out[k + suffix] = p[k] * scale
    if ident.coulomb and "coulomb_pos" in p and "coulomb_neg" in p:
        out["coulomb_pos" + suffix] = p["coulomb_pos"] * scale
        out["coulomb_neg" + suffix] = p["coulomb_neg"] * scale
        out["coulomb" + suffix] = 0.5 * (p["coulomb_pos"] + p["coulomb_neg"]) * scale
        out["offset" + suffix] = 0.0
    return out


def _attach_truth(ident: Identification, trial) -> None:
    """Errors against the recorded truth (simulated trials, instrumented real ones) and against a
    published reference when the trial's provenance carries one (``reference_M``, ``reference_Fv``,
    ``reference_Fc``, ``reference_offset``)."""
    truth_meta = trial.meta.truth
    seq_k = trial.seq[:-1]  # z(k) rows: the disturbance of step k
    if trial.truth is not None:
        ident.truth_force = _aligned(trial.truth, seq_k, "force")
        ident.truth_f = _aligned(trial.truth, seq_k, "f")
        ident.measured_force = _aligned(trial.truth, seq_k, "dynamometer")
    doc: dict = {}
    results = {"ls": ident.ls, "pl_lssvm": ident.pl, "model": ident.model_result}
    if truth_meta is not None:
        phys_true = _true_physical(ident, truth_meta)
        doc["physical"] = phys_true
        doc["coulomb"] = truth_meta.coulomb
        p = truth_meta.physical
        try:
            true_beta = physical_to_beta(ident.form, ident.Ts, p["inertia"], p["damping"], gain=p.get("loop_gain"),
                                         coulomb_pos=p.get("coulomb_pos", 0.0), coulomb_neg=p.get("coulomb_neg", 0.0),
                                         coulomb=ident.coulomb, intercept=True)
        except (KeyError, ValueError):
            true_beta = None
        if true_beta is not None:
            doc["beta"] = true_beta.tolist()
        for key, res in results.items():
            if res is None:
                continue
            if true_beta is not None:
                n_cmp = 2 if not (ident.coulomb and truth_meta.coulomb) else true_beta.size - 1
                err = np.abs(res.beta[:n_cmp] - true_beta[:n_cmp])  # absolute where the true value is 0 (as below)
                rel = np.divide(err, np.abs(true_beta[:n_cmp]), out=err.copy(), where=true_beta[:n_cmp] != 0)
                doc[f"{key}_beta_rel_error"] = rel.tolist()
            errs = {}
            for name, value in res.physical.items():
                ref = phys_true.get(name)
                if ref is None:
                    continue
                errs[name] = abs(value - ref) / abs(ref) if ref else abs(value - ref)
            doc[f"{key}_physical_error"] = errs
    details = getattr(trial.meta.provenance, "details", {}) or {}
    ref_map = {"inertia": "reference_M", "damping": "reference_Fv", "coulomb": "reference_Fc", "offset": "reference_offset"}
    reference = {k: float(details[v]) for k, v in ref_map.items() if isinstance(details.get(v), (int, float))}
    if reference:
        doc["reference"] = reference
        for key, res in results.items():
            if res is None:
                continue
            doc[f"{key}_reference_error"] = {
                k: (res.physical[k] - r) / abs(r) if k != "offset" else res.physical[k] - r
                for k, r in reference.items() if k in res.physical}
    for key, res in results.items():
        if res is None or res.f is None:
            continue
        corr = _corr(res.f, ident.truth_f) if ident.truth_f is not None else _corr(res.f_force, ident.truth_force)
        if corr is not None:
            doc[f"{key}_disturbance_correlation"] = corr
        fc = _corr(res.f_force, ident.truth_force)
        if fc is not None:
            doc[f"{key}_force_correlation"] = fc
    model = ident.model_result
    if model is not None and model.f is not None:
        if "model_disturbance_correlation" in doc:
            doc["disturbance_correlation"] = doc["model_disturbance_correlation"]
        if "model_force_correlation" in doc:
            doc["force_correlation"] = doc["model_force_correlation"]
    ident.truth = doc or None

