"""Feed-drive model: exact ZOH discretisation, PL-ARX regressors, β ↔ physical parameters.

Method §1–2 (thesis §2.1, eq. 2.5–2.7). Plant ``J dω/dt = T − B ω − T_f(ω) − T_c(t)``.

Two input forms:

* ``"velocity-loop"`` (thesis): ``T = K (v_r − v_m)`` held over ``Ts``;
  ``z(k) = [v_r(k), v_m(k), −σ_p(v_m(k)), −σ_n(v_m(k))]``,
  ``β = [K_d, p_d − K_d, (K_d/K) d_p, (K_d/K) d_n]``.
* ``"force-input"``: recorded force command ``u`` (N) held over ``Ts``;
  ``z(k) = [u(k), v_m(k), −σ_p, −σ_n, 1]``, ``β = [b, p_d, b d_p, b d_n, −b·offset]``.

with ``p_d = exp(−B Ts / J)``, ``b = K_d/K = (1 − p_d)/B`` and ``y(k) = v_m(k+1)``.

Friction sign convention: ``T_f(v) = d_p`` for ``v > Ω`` and ``d_n`` for
``v < −Ω`` (signed forces; ``d_n < 0`` for friction that opposes motion).
:class:`Physical` reports the magnitudes ``coulomb_pos = d_p`` and
``coulomb_neg = −d_n`` (N) of the friction opposing motion in each direction.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

__all__ = [
    "FORMS",
    "Physical",
    "Regression",
    "coulomb_indicators",
    "regressors",
    "beta_names",
    "physical_to_beta",
    "beta_to_physical",
    "predict_one_step",
    "simulate_free_run",
    "disturbance_to_force",
    "force_to_disturbance",
]

FORMS = ("velocity-loop", "force-input")


def _check_form(form: str) -> str:
    if form not in FORMS:
        raise ValueError(f"input form {form!r} is not known; use one of {', '.join(FORMS)}")
    return form


def _finite_1d(name: str, values) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array of samples, got shape {a.shape}")
    bad = np.flatnonzero(~np.isfinite(a))
    if bad.size:
        raise ValueError(
            f"{name} has {bad.size} non-finite value(s), first at sample {bad[0]}; "
            "remove or interpolate them before identification"
        )
    return a


def coulomb_indicators(v, omega: float) -> tuple[np.ndarray, np.ndarray]:
    """``σ_p(v), σ_n(v)`` of thesis eq. 2.7 with dead band Ω (method §1).

    ``τ(v) = +1 if v > Ω, −1 if v < −Ω, 0 otherwise``;
    ``σ_p = 1 where τ = +1``, ``σ_n = 1 where τ = −1``.
    """
    v = np.asarray(v, dtype=np.float64)
    return (v > omega).astype(np.float64), (v < -omega).astype(np.float64)


@dataclass(frozen=True)
class Regression:
    """Linear regression data of the PL-ARX model: ``y = Z β + f + ε`` (eq. 2.5)."""

    Z: np.ndarray  # (N-1, m) regressors z(k)
    y: np.ndarray  # (N-1,) outputs y(k) = v_m(k+1), m/s
    names: tuple[str, ...]  # one per column of Z
    form: str
    coulomb: bool
    omega: float


def beta_names(form: str, coulomb: bool = True) -> tuple[str, ...]:
    """Column names of ``z(k)`` for ``form``; Coulomb columns dropped when ``coulomb`` is False."""
    _check_form(form)
    first = ("v_ref", "v_meas") if form == "velocity-loop" else ("u", "v_meas")
    names = first + (("-sigma_p", "-sigma_n") if coulomb else ())
    return names + (("one",) if form == "force-input" else ())


def regressors(
    form: str,
    v_meas,
    *,
    v_ref=None,
    u=None,
    omega: float = 0.0,
    coulomb: bool = True,
) -> Regression:
    """Build ``Z`` and ``y`` of eq. 2.5–2.6 (method §2) from one trial.

    Parameters
    ----------
    form : "velocity-loop" or "force-input"
    v_meas : array (N,)
        Measured velocity v_m (m/s).
    v_ref : array (N,), velocity-loop form
        Reference velocity v_r (m/s).
    u : array (N,), force-input form
        Force command (N).
    omega : float
        Coulomb dead band Ω (m/s).
    coulomb : bool
        Keep the two Coulomb columns (drop them for trials without speed reversal).
    """
    _check_form(form)
    v = _finite_1d("v_meas", v_meas)
    if form == "velocity-loop":
        if v_ref is None:
            raise ValueError("the velocity-loop form needs v_ref (reference velocity, m/s)")
        first = _finite_1d("v_ref", v_ref)
        first_name = "v_ref"
    else:
        if u is None:
            raise ValueError("the force-input form needs u (force command, N)")
        first = _finite_1d("u", u)
        first_name = "u"
    if first.shape != v.shape:
        raise ValueError(f"{first_name} has {first.size} samples but v_meas has {v.size}; they must align")
    if not (math.isfinite(omega) and omega >= 0.0):
        raise ValueError(f"dead band omega must be a finite number ≥ 0 (m/s), got {omega!r}")
    if v.size < 3:
        raise ValueError(f"a trial needs at least 3 samples, got {v.size}")
    vk = v[:-1]
    cols = [first[:-1], vk]
    if coulomb:
        sp, sn = coulomb_indicators(vk, omega)
        cols += [-sp, -sn]
    if form == "force-input":
        cols.append(np.ones_like(vk))
    Z = np.column_stack(cols)
    return Regression(Z=Z, y=v[1:].copy(), names=beta_names(form, coulomb), form=form, coulomb=coulomb, omega=float(omega))


@dataclass(frozen=True)
class Physical:
    """Physical parameters of one axis (SI units).

    ``inertia`` (kg for a linear axis), ``damping`` (N·s/m), ``coulomb_pos`` and
    ``coulomb_neg`` (N, magnitudes opposing motion), ``offset`` (N, force-input form).
    When the loop gain ``K`` is unknown (velocity-loop form), only the ratios
    ``inertia_over_gain`` (s) and ``damping_over_gain`` (dimensionless) — and the
    Coulomb terms over gain (m/s) — are identifiable; the absolute values are None.
    """

    form: str
    pole: float  # p_d
    gain: float | None = None  # K (N·s/m) when known
    inertia: float | None = None
    damping: float | None = None
    coulomb_pos: float | None = None
    coulomb_neg: float | None = None
    offset: float | None = None
    inertia_over_gain: float | None = None
    damping_over_gain: float | None = None
    coulomb_pos_over_gain: float | None = None
    coulomb_neg_over_gain: float | None = None

    def to_dict(self) -> dict:
        """Only the defined fields (``None`` dropped)."""
        return {k: v for k, v in asdict(self).items() if v is not None}


def physical_to_beta(
    form: str,
    Ts: float,
    inertia: float,
    damping: float,
    *,
    gain: float | None = None,
    coulomb_pos: float = 0.0,
    coulomb_neg: float = 0.0,
    offset: float = 0.0,
    coulomb: bool = True,
) -> np.ndarray:
    """Exact ZOH β of method §1–2 from physical parameters.

    ``p_d = exp(−B Ts/J)``, ``b = (1 − p_d)/B``, ``K_d = K b``;
    velocity-loop ``β = [K_d, p_d − K_d, b d_p, b d_n]``,
    force-input ``β = [b, p_d, b d_p, b d_n, −b offset]``, with ``d_p = coulomb_pos``,
    ``d_n = −coulomb_neg``.
    """
    _check_form(form)
    if not (Ts > 0 and inertia > 0 and damping > 0):
        raise ValueError("Ts, inertia and damping must be positive")
    p_d = math.exp(-damping * Ts / inertia)
    b = (1.0 - p_d) / damping
    d_p, d_n = coulomb_pos, -coulomb_neg
    if form == "velocity-loop":
        if gain is None or not gain > 0:
            raise ValueError("the velocity-loop form needs the loop gain K > 0 (N·s/m)")
        K_d = gain * b
        beta = [K_d, p_d - K_d] + ([b * d_p, b * d_n] if coulomb else [])
    else:
        beta = [b, p_d] + ([b * d_p, b * d_n] if coulomb else []) + [-b * offset]
    return np.array(beta, dtype=np.float64)


def beta_to_physical(form: str, beta, Ts: float, *, gain: float | None = None, coulomb: bool = True) -> Physical:
    """Physical parameters from β (method §2, "Physical parameters from β").

    velocity-loop: ``p_d = β1 + β2``, ``B = K(1 − p_d)/β1``, ``J = B Ts/(−ln p_d)``,
    ``d_p = β3 K/β1``, ``d_n = β4 K/β1``; without ``K`` only ``J/K`` and ``B/K``.
    force-input: ``p_d = β2``, ``B = (1 − p_d)/β1``, ``J = B Ts/(−ln p_d)``,
    ``d_p = β3/β1``, ``d_n = β4/β1``, ``offset = −β5/β1``.

    Raises ``ValueError`` when β is not a stable, causal first-order drive (0 < p_d < 1, β1 > 0).
    """
    _check_form(form)
    beta = np.asarray(beta, dtype=np.float64)
    expected = len(beta_names(form, coulomb))
    if beta.shape != (expected,):
        raise ValueError(f"β for the {form} form {'with' if coulomb else 'without'} Coulomb columns has {expected} entries, got {beta.shape}")
    b1 = beta[0]
    p_d = beta[0] + beta[1] if form == "velocity-loop" else beta[1]
    if not (0.0 < p_d < 1.0) or not b1 > 0.0:
        raise ValueError(
            f"identified β gives pole p_d = {p_d:.6g} and input gain β1 = {b1:.6g}; a physical drive needs "
            "0 < p_d < 1 and β1 > 0 — check the input form, the sign of the command and the sample alignment"
        )
    b1, p_d = float(b1), float(p_d)
    log_term = -math.log(p_d)
    dp_scaled = float(beta[2]) / b1 if coulomb else None  # d_p / K (velocity-loop) or d_p (force-input)
    dn_scaled = float(beta[3]) / b1 if coulomb else None
    if form == "force-input":
        damping = (1.0 - p_d) / b1
        return Physical(
            form=form,
            pole=p_d,
            inertia=damping * Ts / log_term,
            damping=damping,
            coulomb_pos=dp_scaled,
            coulomb_neg=None if dn_scaled is None else -dn_scaled,
            offset=-float(beta[-1]) / b1,
        )
    damping_over_gain = (1.0 - p_d) / b1
    inertia_over_gain = damping_over_gain * Ts / log_term
    if gain is None:
        return Physical(
            form=form,
            pole=p_d,
            inertia_over_gain=inertia_over_gain,
            damping_over_gain=damping_over_gain,
            coulomb_pos_over_gain=dp_scaled,
            coulomb_neg_over_gain=None if dn_scaled is None else -dn_scaled,
        )
    return Physical(
        form=form,
        pole=p_d,
        gain=float(gain),
        inertia=inertia_over_gain * gain,
        damping=damping_over_gain * gain,
        coulomb_pos=None if dp_scaled is None else dp_scaled * gain,
        coulomb_neg=None if dn_scaled is None else -dn_scaled * gain,
        inertia_over_gain=inertia_over_gain,
        damping_over_gain=damping_over_gain,
    )


def predict_one_step(beta, reg: Regression) -> np.ndarray:
    """One-step prediction ``ŷ(k) = βᵀ z(k)`` (m/s), aligned with ``reg.y``."""
    return reg.Z @ np.asarray(beta, dtype=np.float64)


def simulate_free_run(
    form: str,
    beta,
    v0: float,
    exogenous,
    *,
    omega: float = 0.0,
    coulomb: bool = True,
    disturbance=None,
) -> np.ndarray:
    """Free-run simulation of an identified model: the model's own past velocity is fed back.

    ``v̂(k+1) = βᵀ z(v̂(k), e(k)) + f(k)`` with ``e`` = v_ref (velocity-loop) or u
    (force-input) and optional disturbance ``f`` (velocity units). Returns ``v̂``
    with ``v̂(0) = v0`` and the same length as ``exogenous``.
    """
    _check_form(form)
    beta = np.asarray(beta, dtype=np.float64)
    e = _finite_1d("exogenous input", exogenous)
    f = np.zeros_like(e) if disturbance is None else _finite_1d("disturbance", disturbance)
    out = np.empty_like(e)
    out[0] = v0
    const = beta[-1] if form == "force-input" else 0.0
    for k in range(e.size - 1):
        v = out[k]
        nxt = beta[0] * e[k] + beta[1] * v + const
        if coulomb:
            nxt -= beta[2] * (v > omega) + beta[3] * (v < -omega)
        out[k + 1] = nxt + f[k]
    return out


def _force_gain(form: str, beta, gain: float | None) -> float:
    """``b = K_d/K`` (m/s per N per step): the factor from a force to its velocity effect."""
    b1 = float(np.asarray(beta)[0])
    if form == "force-input":
        return b1
    if gain is None:
        raise ValueError("converting a velocity-loop disturbance to newtons needs the loop gain K")
    return b1 / gain


def disturbance_to_force(form: str, beta, f, *, gain: float | None = None) -> np.ndarray:
    """Disturbance force (N) from ``f`` (m/s): ``T_c = −f K/K_d`` or ``F_c = −f/b`` (method §6)."""
    return -np.asarray(f, dtype=np.float64) / _force_gain(_check_form(form), beta, gain)


def force_to_disturbance(form: str, beta, force, *, gain: float | None = None) -> np.ndarray:
    """Inverse of :func:`disturbance_to_force`: ``f = −b F`` (m/s)."""
    return -np.asarray(force, dtype=np.float64) * _force_gain(_check_form(form), beta, gain)
