"""Identification report: PNG figure (thesis Figures 4.1–4.7) and a markdown summary (issue 10 item 7).

Figure, one PNG per trial axis (``<machine>-<axis>-identification.png``):
(a) measured vs predicted velocity of the written model, (b) its prediction error,
(c) identified disturbance vs the measured or true force — estimate and reference both with their
mean removed (a disturbance's mean cannot be told from the force offset, so only the variation is
compared), in N when the model scales and is valid, otherwise both normalised (an invalid model's
force scale means nothing), (d) power spectral density of the prediction error, LS vs PL-LSSVM
(``scipy.signal.welch``) with the harmonics ``h/ψ`` of the period marked and labelled (and, when the
spindle speed changes, the fundamental of every other speed in play, dotted).

The markdown names the chosen model, lists every candidate with its evidence and validity, the
parameters with their standard errors (undetermined ones flagged), the errors against the truth or a
published reference when known, and the disturbance correlation.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["write_report", "summary_table", "summary_columns", "candidate_rows", "format_value"]


def _fmt(x, digits=6) -> str:
    if x is None:
        return "—"
    if isinstance(x, float):
        if not math.isfinite(x):
            return str(x)
        return f"{x:.{digits}g}"
    return str(x)


def format_value(value, se, *, vif=None, digits: int = 5) -> str:
    """``value ± se``; ``not determined (value ± se)`` when the relative s.e. is above
    :data:`monitor.identify.UNDETERMINED_RSE`; ``(competes, VIF v)`` appended when the disturbance model
    inflates its variance more than :data:`monitor.identify.VIF_FLAG`."""
    from .identify import UNDETERMINED_RSE, VIF_FLAG

    if value is None:
        return "—"
    if se is None:
        return _fmt(value, digits)
    text = f"{value:.{digits}g} ± {se:.2g}"
    if not (se <= UNDETERMINED_RSE * abs(value)):
        text = f"not determined ({text})"
    if vif is not None and vif > VIF_FLAG:
        text += f" (competes with the disturbance, VIF {vif:.0f})"
    return text


_PHYS_ROWS = [
    ("inertia", "J (kg)"),
    ("damping", "B (N·s/m)"),
    ("coulomb", "Coulomb, symmetric (N)"),
    ("coulomb_pos", "Coulomb + (N)"),
    ("coulomb_neg", "Coulomb − (N)"),
    ("offset", "offset (N)"),
    ("inertia_over_gain", "J/K (s)"),
    ("damping_over_gain", "B/K"),
    ("coulomb_over_gain", "Coulomb/K, symmetric (m/s)"),
    ("coulomb_pos_over_gain", "Coulomb +/K (m/s)"),
    ("coulomb_neg_over_gain", "Coulomb −/K (m/s)"),
    ("offset_over_gain", "offset/K (m/s)"),
]


def summary_columns(ident) -> list[str]:
    """Headers of :func:`summary_table`. A column whose candidate is not valid says so: its numbers are that
    model's reading of the data, not the drive's (the candidates table says why)."""
    def head(label: str, cand) -> str:
        return label if cand.valid else f"{label} — NOT VALID (see candidates)"

    pl = ident.pl
    return ["parameter", head("LS", ident.ls.candidate),
            "PL-LSSVM" if pl is None else head(f"PL-LSSVM ({pl.candidate.label[10:]})", pl.candidate),
            "truth / reference"]


def summary_table(ident) -> list[list[str]]:
    """Rows: parameter, LS (± s.e.), PL-LSSVM (± s.e.), truth."""
    truth = ident.truth or {}
    truth_beta = truth.get("beta")
    truth_phys = dict(truth.get("reference", {}))
    truth_phys.update(truth.get("physical", {}))
    pl = ident.pl
    rows = []
    for i, name in enumerate(ident.names):
        tb = truth_beta[i] if truth_beta is not None and len(truth_beta) == len(ident.names) else None
        rows.append([f"β{i + 1} ({name})", format_value(ident.ls.beta[i], ident.ls.stderr[i]),
                     "—" if pl is None else format_value(pl.beta[i], pl.stderr[i]), _fmt(tb)])
    for key, label in _PHYS_ROWS:
        a = ident.ls.physical.get(key)
        b = None if pl is None else pl.physical.get(key)
        if a is None and b is None:
            continue
        rows.append([label, format_value(a, ident.ls.physical_se.get(key)),
                     "—" if pl is None else format_value(b, pl.physical_se.get(key), vif=pl.candidate.vif.get(key)),
                     _fmt(truth_phys.get(key))])
    rows.append(["log evidence", _fmt(ident.ls.candidate.log_evidence, 8),
                 "—" if pl is None else _fmt(pl.candidate.log_evidence, 8), ""])
    rows.append(["one-step RMSE (m/s)", _fmt(ident.ls.rmse, 4), "—" if pl is None else _fmt(pl.rmse, 4), ""])
    rows.append(["free-run RMSE (m/s)", _fmt(ident.ls.rmse_free_run, 4),
                 "—" if pl is None else _fmt(pl.rmse_free_run, 4), ""])
    return rows


def _hyper_text(c) -> str:
    h = c.hyperparameters
    parts = []
    for key, sym in (("sigma1", "σ1"), ("sigma2", "σ2"), ("lengthscale", "ℓ"), ("gamma", "γ")):
        if h.get(key) is not None:
            parts.append(f"{sym} = {h[key]:.3g}")
    if h.get("on_bound"):
        parts.append("on bound: " + ", ".join(f"{k} ({v})" for k, v in h["on_bound"].items()))
    if c.method != "ls" and not h.get("tuned", False):
        parts.append("not tuned")
    return ", ".join(parts) or "—"


def candidate_rows(ident) -> list[list[str]]:
    """Rows: candidate, hyperparameters, log evidence, valid, chosen / why not."""
    rows = []
    for c in ident.candidates:
        mark = "◀ chosen" if c is ident.chosen else (c.why_not or ("" if c.eligible else "not a choice: " + c.notes[-1]))
        rows.append([c.label, _hyper_text(c), f"{c.log_evidence:.6g}", "yes" if c.valid else "no", mark])
    return rows


def _psd(x: np.ndarray, fs: float):
    from scipy.signal import welch

    nperseg = int(min(4096, max(16, x.size // 8)))
    return welch(np.where(np.isfinite(x), x, 0.0), fs=fs, nperseg=nperseg)  # samples left out of the fit: 0


def _reference(ident):
    if ident.measured_force is not None and np.isfinite(ident.measured_force).any():
        return -ident.measured_force, "measured force (dynamometer, reaction sign)"
    if ident.truth_force is not None and np.isfinite(ident.truth_force).any():
        return ident.truth_force, "true disturbance force"
    return None, None


#: the most samples drawn in a time plot of the report (a longer record: every k-th)
PLOT_POINTS = 100_000


def write_report(ident, out_dir, self_check: dict | None = None) -> list[Path]:
    """Write the figure and ``<machine>-<axis>-identification.md`` into ``out_dir``; returns the paths.
    ``self_check``: the JSON of :func:`monitor.self_check.self_check` for the written model (a section of
    the summary)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{ident.machine}-{ident.axis}-identification"
    t = ident.t - ident.t[0]
    fs = 1.0 / ident.Ts
    model = ident.model_result if ident.model_result is not None else ident.ls
    chosen = model.candidate
    model_label = chosen.label + ("" if chosen.valid else " — NOT VALID")

    k = slice(None, None, max(1, t.size // PLOT_POINTS))  # a long record: every k-th sample in the time plots
    t = t[k]
    fig, ax = plt.subplots(4, 1, figsize=(11, 13), constrained_layout=True)
    ax[0].plot(t, ident.y[k], lw=0.8, label="measured $v_m$")
    ax[0].plot(t, model.prediction[k], lw=0.8, ls="--", label=f"{model.name}: one-step prediction")
    ax[0].set(ylabel="velocity (m/s)", title=f"(a) measured vs predicted velocity — {model_label}")
    ax[0].legend(loc="upper right")

    ax[1].plot(t, (ident.y - model.prediction)[k], lw=0.6, color="C3")
    ax[1].set(ylabel="error (m/s)", title=f"(b) prediction error $y - \\hat y$ ({model.name})")

    dist = model if model.f is not None else ident.pl
    ref, ref_label = _reference(ident)
    if dist is None or dist.f is None:
        ax[2].text(0.5, 0.5, "no disturbance model (LS)", ha="center", va="center", transform=ax[2].transAxes)
        ax[2].set(title="(c) identified disturbance")
    else:
        newtons = dist.f_force is not None and dist.candidate.valid
        est = (dist.f_force if newtons else dist.f)[k]
        est = est - np.nanmean(est)
        ref_c = None if ref is None else ref[k] - np.nanmean(ref[k])
        if newtons:
            ax[2].set_ylabel("force (N), mean removed")
        else:
            est = est / (np.nanstd(est) or 1.0)
            if ref_c is not None:
                ref_c = ref_c / (np.nanstd(ref_c) or 1.0)
            why = "model not valid" if not dist.candidate.valid else "no force scale (loop gain unknown)"
            ax[2].set_ylabel(f"normalised ({why})")
        if ref_c is not None:
            ax[2].plot(t, ref_c, lw=2.0, color="0.6", label=ref_label + " (mean removed)")
        ax[2].plot(t, est, lw=0.7, color="C2", alpha=0.9, label=f"{dist.candidate.label} (mean removed)")
        corr = (ident.truth or {}).get("pl_lssvm_disturbance_correlation" if dist is ident.pl else "disturbance_correlation")
        whose = "" if dist is model else " of the best PL-LSSVM candidate (not the written model)"
        ax[2].set(title="(c) identified disturbance" + whose
                  + (f" — correlation with the reference {corr:.4f}" if corr else ""))
        ax[2].legend(loc="upper right")

    results = [ident.ls] + ([ident.pl] if ident.pl is not None else [])
    for res, color in zip(results, ("C0", "C1")):
        f, p = _psd(ident.y - res.prediction, fs)
        ax[3].semilogy(f, p, lw=0.9, color=color, label=res.candidate.label)
    psi = ident.period
    if psi is not None:
        harmonics = [h / psi for h in range(1, 6) if h / psi < fs / 2]
        for h, fk in enumerate(harmonics, start=1):
            ax[3].axvline(fk, color="k", lw=1.0, ls="--", alpha=0.6, zorder=0)
            ax[3].annotate(f"{h}/ψ" if h > 1 else "1/ψ", (fk, 1.0), xycoords=("data", "axes fraction"),
                           xytext=(3, -12), textcoords="offset points", fontsize=8)
        others = [q for q in ident.periods if abs(q - psi) > 1e-3 * psi and 1.0 / q < fs / 2]
        for i, q in enumerate(sorted(others)):  # the spindle's other speeds in the trial: their fundamentals
            ax[3].axvline(1.0 / q, color="0.4", lw=1.0, ls=":", alpha=0.8, zorder=0)
            ax[3].annotate(f"{60.0 / q:.0f} rpm", (1.0 / q, 0.93 - 0.07 * (i % 3)), xycoords=("data", "axes fraction"),
                           xytext=(3, -12), textcoords="offset points", fontsize=8, color="0.3")
        if harmonics and harmonics[-1] < fs / 20:
            ax[3].set_xscale("log")
    ax[3].set(xlabel="frequency (Hz)", ylabel="PSD ((m/s)²/Hz)", title="(d) PSD of the prediction error")
    ax[3].legend(loc="lower left")
    for a in ax[:3]:
        a.set_xlabel("time (s)")
    psi_text = "none" if psi is None else f"{psi:.5g} s ({ident.period_source})"
    fig.suptitle(f"{ident.machine}/{ident.axis}: {Path(ident.trial_path).name} — {ident.form}, ψ = {psi_text}; "
                 f"written: {model_label}")
    png = out / f"{stem}.png"
    fig.savefig(png, dpi=100)
    plt.close(fig)

    md_path = out / f"{stem}.md"
    md_path.write_text(_markdown(ident, png.name, self_check), encoding="utf-8")
    return [png, md_path]


def _checks_section(ident) -> list[str]:
    """What the data say beyond β (the JSON ``checks``): noise, the process, the friction near standstill,
    whether the rigid model fits."""
    checks = ident.checks or {}
    out = []
    noise = checks.get("noise")
    if noise:
        out.append(f"* measurement noise: σ_n = {noise['sigma_n']:.3g} m/s on the velocity, σ_ε = "
                   f"{noise['sigma_eps']:.3g} ± {noise['se_eps']:.2g} m/s in the one-step residual")
    if checks.get("offset_note"):
        state = {True: "kept out of friction and offset", False: "NOT separated from friction and offset"}.get(
            checks.get("offset_separated"), "unknown")
        out.append(f"* a process's mean force: {state} — {checks['offset_note']}")
    if checks.get("left_out"):
        out.append(f"* {checks['left_out']} samples below {checks['law_holds_above']['speed']:.3g} m/s left out of "
                   "the fit (the friction rises above the law there)")
    adequacy = checks.get("adequacy")
    if adequacy:
        out.append("* the rigid model fits the data" if adequacy["adequate"] else
                   f"* **the rigid model does not fit**: {adequacy['message']}")
    if checks.get("delay"):
        out.append(f"* modelled: the force acts {checks['delay']} sample(s) after the command")
    return ["## What else the data say", "", *out, ""] if out else []


def _markdown(ident, png_name: str, self_check: dict | None = None) -> str:
    truth = ident.truth or {}
    psi_text = "none" if ident.period is None else f"{ident.period:.6g} s ({ident.period_source})"
    if ident.period_suggested is not None:
        psi_text += f"; the data prefer ψ = {ident.period_suggested:.6g} s"
    chosen = ident.chosen
    lines = [
        f"# Identification of {ident.machine}/{ident.axis}",
        "",
        f"Trial `{ident.trial_path}`, form **{ident.form}**, Ts = {ident.Ts:.6g} s, ψ = {psi_text}, "
        f"Ω = {ident.omega:.3g} m/s. {ident.coulomb_note}.",
        "",
        (f"**Chosen model: {chosen.label}** (log evidence {chosen.log_evidence:.6g})." if chosen is not None else
         f"**No valid model**: {ident.refusal}."),
        "",
        "## Candidates",
        "",
        "Evidence: restricted marginal likelihood at the tuned hyperparameters minus ½ k log(N − p) for the "
        "k hyperparameters fitted to the data.",
        "",
        "| candidate | hyperparameters | log evidence | valid | |",
        "|---|---|---|---|---|",
        *["| " + " | ".join(r) + " |" for r in candidate_rows(ident)],
        "",
        "## Parameters (± standard error)",
        "",
        "| " + " | ".join(summary_columns(ident)) + " |",
        "|---|---|---|---|",
        *["| " + " | ".join(r) + " |" for r in summary_table(ident)],
        "",
    ]
    errs = []
    for key, label in (("ls", "LS"), ("pl_lssvm", "PL-LSSVM"), ("model", "written model")):
        for kind, what in (("physical_error", "truth"), ("reference_error", "published reference")):
            e = truth.get(f"{key}_{kind}")
            if e:
                parts = [f"{k} {v:+.2f} N" if k == "offset" and kind == "reference_error" else
                         (f"{k} {v:.2%}" if kind == "physical_error" else f"{k} {v:+.2%}") for k, v in e.items()]
                errs.append(f"* {label} vs {what}: " + ", ".join(parts))
    for key, label in (("disturbance_correlation", "written model"), ("pl_lssvm_disturbance_correlation", "PL-LSSVM")):
        if truth.get(key) is not None:
            errs.append(f"* disturbance correlation with the truth ({label}): {truth[key]:.4f}")
    if errs:
        lines += ["## Against the truth", "", *errs, ""]
    lines += _checks_section(ident)
    if self_check is not None:
        lines += ["## Self-check", "", "The monitor (`feedmon run --from`) with the written model over this trial: "
                  + self_check["summary"] + ".", ""]
    notes = ident.notes + [n for c in ident.candidates for n in c.notes]
    if notes:
        lines += ["## Notes", "", *[f"* {n}" for n in notes], ""]
    lines += [f"![identification]({png_name})", ""]
    return "\n".join(lines)
