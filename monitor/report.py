"""Thesis-style identification report: PNG figures (thesis Figures 4.1–4.7) and a markdown summary.

Figure layout, one PNG per trial axis (``<axis>-identification.png``):
(a) measured vs predicted velocity (PL-LSSVM, ``Zβ + f``), (b) prediction error,
(c) identified disturbance vs the measured or true force (in N when the model
scales, else normalised), (d) power spectral density of the prediction error,
LS vs PL-LSSVM (``scipy.signal.welch``).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["write_report", "summary_table"]


def _fmt(x, digits=6) -> str:
    if x is None:
        return "—"
    if isinstance(x, float):
        if not math.isfinite(x):
            return str(x)
        return f"{x:.{digits}g}"
    return str(x)


_PHYS_ROWS = [
    ("inertia", "J (kg)"),
    ("damping", "B (N·s/m)"),
    ("coulomb_pos", "Coulomb + (N)"),
    ("coulomb_neg", "Coulomb − (N)"),
    ("offset", "offset (N)"),
    ("inertia_over_gain", "J/K (s)"),
    ("damping_over_gain", "B/K"),
    ("coulomb_pos_over_gain", "Coulomb +/K (m/s)"),
    ("coulomb_neg_over_gain", "Coulomb −/K (m/s)"),
]


def summary_table(ident) -> list[list[str]]:
    """Rows of the thesis Table 4.2-shaped summary: parameter, LS (± s.e.), PL-LSSVM, truth."""
    truth_beta = (ident.truth or {}).get("beta")
    truth_phys = (ident.truth or {}).get("physical", {})
    rows = []
    for i, name in enumerate(ident.names):
        ls = f"{ident.ls.beta[i]:.6g} ± {ident.ls.stderr[i]:.2g}"
        tb = truth_beta[i] if truth_beta is not None and i < len(truth_beta) and len(truth_beta) == len(ident.names) else None
        rows.append([f"β{i + 1} ({name})", ls, f"{ident.pl.beta[i]:.6g}", _fmt(tb)])
    for key, label in _PHYS_ROWS:
        a, b = ident.ls.physical.get(key), ident.pl.physical.get(key)
        if a is None and b is None:
            continue
        rows.append([label, _fmt(a), _fmt(b), _fmt(truth_phys.get(key))])
    rows.append(["one-step RMSE (m/s)", _fmt(ident.ls.rmse, 4), _fmt(ident.pl.rmse, 4), ""])
    rows.append(["free-run RMSE (m/s)", _fmt(ident.ls.rmse_free_run, 4), _fmt(ident.pl.rmse_free_run, 4), ""])
    if ident.truth and "ls_beta_rel_error" in ident.truth:
        ls_err = max(ident.truth["ls_beta_rel_error"][:2])
        pl_err = max(ident.truth["pl_lssvm_beta_rel_error"][:2])
        rows.append(["max rel. error β1, β2 vs truth", f"{ls_err:.3%}", f"{pl_err:.3%}", ""])
    return rows


def _psd(x: np.ndarray, fs: float):
    from scipy.signal import welch

    nperseg = int(min(1024, max(16, x.size // 8)))
    return welch(x, fs=fs, nperseg=nperseg)


def write_report(ident, out_dir) -> list[Path]:
    """Write the figure and ``<axis>-identification.md`` into ``out_dir``; returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{ident.machine}-{ident.axis}-identification"
    t = ident.t - ident.t[0]
    fs = 1.0 / ident.Ts

    fig, ax = plt.subplots(4, 1, figsize=(10, 12), constrained_layout=True)
    ax[0].plot(t, ident.y, lw=0.8, label="measured $v_m$")
    ax[0].plot(t, ident.pl.prediction, lw=0.8, ls="--", label="PL-LSSVM $\\beta^T z + f$")
    ax[0].set(ylabel="velocity (m/s)", title="(a) measured vs predicted velocity")
    ax[0].legend(loc="upper right")

    ax[1].plot(t, ident.y - ident.pl.prediction, lw=0.6, color="C3")
    ax[1].set(ylabel="error (m/s)", title="(b) PL-LSSVM prediction error $y - \\hat y$")

    ref, ref_label = None, None
    if ident.measured_force is not None and np.isfinite(ident.measured_force).any():
        ref, ref_label = ident.measured_force, "measured force (dynamometer)"
    elif ident.truth_force is not None and np.isfinite(ident.truth_force).any():
        ref, ref_label = ident.truth_force, "true disturbance force"
    if ident.f_force is not None:
        est, unit = ident.f_force, "N"
        if ref is not None and ref is ident.measured_force:
            ref = -ref  # a dynamometer measures the reaction: T_c = −F_dyn
        ax[2].set_ylabel("force (N)")
    else:
        est, unit = ident.f, "m/s"
        ax[2].set_ylabel("disturbance (normalised)")
    if ref is not None:
        ref_c = ref - np.nanmean(ref)
        if ident.f_force is None:  # no scale: normalise both
            est = est / (np.nanstd(est) or 1.0)
            ref_c = ref_c / (np.nanstd(ref_c) or 1.0)
        ax[2].plot(t, ref_c, lw=0.8, color="0.4", label=ref_label + " (mean removed)")
    ax[2].plot(t, est, lw=0.8, color="C2", label=f"PL-LSSVM disturbance ({unit})")
    ax[2].set(title="(c) identified disturbance")
    ax[2].legend(loc="upper right")

    for res, color in ((ident.ls, "C0"), (ident.pl, "C1")):
        f, p = _psd(ident.y - res.prediction, fs)
        ax[3].semilogy(f, p, lw=0.9, color=color, label=res.name)
    for k in (1, 2):
        fk = k / ident.period
        if fk < fs / 2:
            ax[3].axvline(fk, color="0.7", lw=0.6, ls=":")
    ax[3].set(xlabel="frequency (Hz)", ylabel="PSD ((m/s)²/Hz)", title="(d) PSD of the prediction error")
    ax[3].legend(loc="upper right")
    for a in ax[:3]:
        a.set_xlabel("time (s)")
    fig.suptitle(f"{ident.machine}/{ident.axis}: {Path(ident.trial_path).name} — {ident.form}, ψ = {ident.period:.5g} s")
    png = out / f"{stem}.png"
    fig.savefig(png, dpi=110)
    plt.close(fig)

    rows = summary_table(ident)
    hp = ident.hyperparameters
    md = [
        f"# Identification of {ident.machine}/{ident.axis}",
        "",
        f"Trial `{ident.trial_path}`, form **{ident.form}**, Ts = {ident.Ts:.6g} s, ψ = {ident.period:.6g} s "
        f"({ident.period_source}), Ω = {ident.omega:.3g} m/s. {ident.coulomb_note}.",
        "",
        f"PL-LSSVM hyperparameters: σ1 = {hp['sigma1']:.4g} s, σ2 = {hp['sigma2']:.4g}, γ = {hp['gamma']:.4g}"
        + (" (tuned by maximum likelihood" if hp.get("tuned") else " (given")
        + (f", log-likelihood {hp['log_likelihood']:.6g})" if hp.get("log_likelihood") is not None else ")"),
        "",
        "| parameter | LS (± s.e.) | PL-LSSVM | truth |",
        "|---|---|---|---|",
        *["| " + " | ".join(r) + " |" for r in rows],
        "",
        *[f"* {n}" for n in ident.notes],
        "",
        f"![identification]({png.name})",
        "",
    ]
    md_path = out / f"{stem}.md"
    md_path.write_text("\n".join(md), encoding="utf-8")
    return [png, md_path]
