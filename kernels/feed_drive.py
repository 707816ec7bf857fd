"""Feed-drive model: exact ZOH discretisation, PL-ARX regressors, β ↔ physical parameters,
their uncertainty and the validity rules of a model (method §1–2).

Plant ``J dω/dt = T − B ω − T_f(ω) − T_c(t)`` (thesis §2.1).

Two input forms:

* ``"velocity-loop"`` (thesis): ``T = K (v_r − v_m)`` held over ``Ts``;
  ``z(k) = [v_r(k), v_m(k), −σ_p(v_m(k)), −σ_n(v_m(k)) (, 1)]``,
  ``β = [K_d, p_d − K_d, b d_p, b d_n (, −b·offset)]``.
* ``"force-input"``: recorded force command ``u`` (N) held over ``Ts``;
  ``z(k) = [u(k), v_m(k), −σ_p, −σ_n, 1]``, ``β = [b, p_d, b d_p, b d_n, −b·offset]``.

with ``p_d = exp(−B Ts / J)``, ``b = K_d/K = (1 − p_d)/B`` and ``y(k) = v_m(k+1)``.
The constant column ``one`` (the force offset) always ends ``z`` in the force-input form and
may end it in the velocity-loop form (``intercept=True``; ``feedmon identify`` always keeps it,
so that a constant force — an offset, or the friction of a one-direction trial — does not bias
β); its physical value is ``offset = −β_one / b``.

Friction sign convention: ``T_f(v) = d_p + offset`` for ``v > Ω``, ``d_n + offset`` for
``v < −Ω`` and ``offset`` inside the dead band (signed forces; ``d_n < 0`` for friction that
opposes motion). :class:`Physical` reports the magnitudes ``coulomb_pos = d_p`` and
``coulomb_neg = −d_n`` (N), the symmetric Coulomb friction ``coulomb = (coulomb_pos +
coulomb_neg)/2`` and ``offset``.

Identifiable friction (:func:`friction_transform`). In motion only two friction levels are
seen, ``F(+) = d_p + offset`` and ``F(−) = d_n + offset``; the three numbers d_p, d_n, offset
are separated only by samples at rest (inside ±Ω). Identification therefore uses the columns

    −τ(v),  −|τ(v)|,  1          with coefficients  b·Fc,  b·a,  −b·offset

(``τ`` of method §1, ``Fc = (F(+) − F(−))/2`` the symmetric Coulomb friction, ``a`` the
asymmetry ``(coulomb_pos − coulomb_neg)/2``), mapped back to the spec's β by
``β(−σ_p) = b(Fc + a)``, ``β(−σ_n) = b(a − Fc)``. Without rest in the trial the ``−|τ|``
column is dropped (``a = 0``): the constant then holds the sum ``asymmetry + offset``
(the offset of the symmetric friction model, ``(F(+) + F(−))/2``) and
``coulomb_pos = coulomb_neg = coulomb``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

__all__ = [
    "FORMS",
    "Physical",
    "Regression",
    "coulomb_indicators",
    "regressors",
    "beta_names",
    "physical_to_beta",
    "beta_to_physical",
    "physical_covariance",
    "friction_transform",
    "rest_samples",
    "validity_problems",
    "check_validity",
    "predict_one_step",
    "simulate_free_run",
    "disturbance_to_force",
    "force_to_disturbance",
    "COULOMB_Z",
    "REST_MIN_SECONDS",
    "REST_MIN_SAMPLES",
]

FORMS = ("velocity-loop", "force-input")
#: a Coulomb friction is "negative beyond its uncertainty" when it is below −COULOMB_Z standard errors
COULOMB_Z = 2.0
#: a stretch inside the dead band counts as rest (not a pass through zero during a reversal) when it
#: lasts at least this long (s) and at least REST_MIN_SAMPLES samples
REST_MIN_SECONDS = 0.05
REST_MIN_SAMPLES = 10


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


def rest_samples(v, omega: float, Ts: float) -> int:
    """Samples of ``v`` at rest: inside ±Ω in runs of at least ``max(REST_MIN_SAMPLES,
    REST_MIN_SECONDS/Ts)`` consecutive samples. Passing through the dead band during a speed
    reversal (a few samples) is not rest: there the friction is changing sign, it says nothing
    about the force offset."""
    inside = np.abs(np.asarray(v, dtype=np.float64)) <= omega
    if not inside.any():
        return 0
    edges = np.diff(np.concatenate([[0], inside.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    runs = ends - starts
    need = max(REST_MIN_SAMPLES, int(math.ceil(REST_MIN_SECONDS / Ts)))
    return int(runs[runs >= need].sum())


@dataclass(frozen=True)
class Regression:
    """Linear regression data of the PL-ARX model: ``y = Z β + f + ε`` (eq. 2.5)."""

    Z: np.ndarray  # (N-1, m) regressors z(k)
    y: np.ndarray  # (N-1,) outputs y(k) = v_m(k+1), m/s
    names: tuple[str, ...]  # one per column of Z
    form: str
    coulomb: bool
    omega: float


def _intercept(form: str, intercept: bool | None) -> bool:
    return form == "force-input" if intercept is None else bool(intercept)


def beta_names(form: str, coulomb: bool = True, intercept: bool | None = None) -> tuple[str, ...]:
    """Column names of ``z(k)`` for ``form``; Coulomb columns dropped when ``coulomb`` is False;
    the constant ``one`` last when ``intercept`` (default: force-input only)."""
    _check_form(form)
    first = ("v_ref", "v_meas") if form == "velocity-loop" else ("u", "v_meas")
    names = first + (("-sigma_p", "-sigma_n") if coulomb else ())
    return names + (("one",) if _intercept(form, intercept) else ())


def regressors(
    form: str,
    v_meas,
    *,
    v_ref=None,
    u=None,
    omega: float = 0.0,
    coulomb: bool = True,
    intercept: bool | None = None,
    delay: int = 0,
) -> Regression:
    """Build ``Z`` and ``y`` of eq. 2.5–2.6 (method §2) from one trial.

    With ``delay`` d ≥ 1 (the force acts d samples after it is commanded) the first column carries the
    command d samples back: ``u(k−d)`` (force-input), ``v_r(k−d) − v_m(k−d) + v_m(k)`` (velocity-loop:
    ``β1·z1 + β2·v_m = K_d·(v_r − v_m)(k−d) + p_d·v_m(k)``, the same β); its first d rows have no such
    past and hold the undelayed command.

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
    intercept : bool, optional
        Append the constant column ``one`` (default: force-input form only).
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
    d = int(delay)
    if not 0 <= d <= 16:
        raise ValueError(f"delay must be a whole number of samples 0 … 16, got {delay!r}")
    first = first[:-1].copy()
    if d:
        command = first - vk if form == "velocity-loop" else first  # v_r − v_m, or u
        late = command.copy()
        late[d:] = command[:-d]
        first = late + vk if form == "velocity-loop" else late
    cols = [first, vk]
    if coulomb:
        sp, sn = coulomb_indicators(vk, omega)
        cols += [-sp, -sn]
    if _intercept(form, intercept):
        cols.append(np.ones_like(vk))
    Z = np.column_stack(cols)
    return Regression(Z=Z, y=v[1:].copy(), names=beta_names(form, coulomb, intercept), form=form, coulomb=coulomb,
                      omega=float(omega))


def friction_transform(names, rest: bool) -> tuple[np.ndarray, tuple[str, ...]]:
    """The identifiable friction parametrisation (module docstring): ``(T, id_names)`` with
    ``β = T θ`` and ``Z_id = Z T`` for the spec columns ``names``.

    ``−σ_p, −σ_n`` become ``−τ`` (coefficient b·Fc) and, when the trial has rest, ``−|τ|``
    (coefficient b·a); without rest ``a = 0`` is imposed (β(−σ_p) = −β(−σ_n)). Other columns are
    kept. Without Coulomb columns ``T`` is the identity.
    """
    names = tuple(names)
    m = len(names)
    if "-sigma_p" not in names:
        return np.eye(m), names
    ip, ineg = names.index("-sigma_p"), names.index("-sigma_n")
    cols, id_names = [], []
    for j, name in enumerate(names):
        if j == ineg:
            continue
        col = np.zeros(m)
        if j == ip:
            col[ip], col[ineg] = 1.0, -1.0  # −τ = −σ_p + σ_n
            cols.append(col)
            id_names.append("-tau")
            if rest:
                col = np.zeros(m)
                col[ip], col[ineg] = 1.0, 1.0  # −|τ| = −σ_p − σ_n
                cols.append(col)
                id_names.append("-abs_tau")
            continue
        col[j] = 1.0
        cols.append(col)
        id_names.append(name)
    return np.column_stack(cols), tuple(id_names)


@dataclass(frozen=True)
class Physical:
    """Physical parameters of one axis (SI units).

    ``inertia`` (kg for a linear axis), ``damping`` (N·s/m), ``coulomb`` the symmetric Coulomb
    friction ``(coulomb_pos + coulomb_neg)/2``, ``coulomb_pos`` / ``coulomb_neg`` (N,
    magnitudes opposing motion in each direction), ``offset`` (N, constant force, when the model
    has the ``one`` column). When the loop gain ``K`` is unknown (velocity-loop form), only the
    ratios to K are identifiable: ``inertia_over_gain`` (s), ``damping_over_gain`` (1),
    ``coulomb_over_gain`` … ``offset_over_gain`` (m/s); the absolute values are None.
    ``pole`` is the open-loop discrete pole ``p_d`` (not a physical key of :meth:`to_dict`).
    """

    form: str
    pole: float  # p_d
    gain: float | None = None  # K (N·s/m) when known
    inertia: float | None = None
    damping: float | None = None
    coulomb: float | None = None
    coulomb_pos: float | None = None
    coulomb_neg: float | None = None
    offset: float | None = None
    inertia_over_gain: float | None = None
    damping_over_gain: float | None = None
    coulomb_over_gain: float | None = None
    coulomb_pos_over_gain: float | None = None
    coulomb_neg_over_gain: float | None = None
    offset_over_gain: float | None = None

    def to_dict(self) -> dict:
        """The defined physical parameters (``None``, ``form``, ``pole`` and ``gain`` dropped)."""
        return {k: v for k, v in asdict(self).items() if v is not None and k not in ("form", "pole", "gain")}


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
    intercept: bool | None = None,
) -> np.ndarray:
    """Exact ZOH β of method §1–2 from physical parameters.

    ``p_d = exp(−B Ts/J)``, ``b = (1 − p_d)/B``, ``K_d = K b``;
    velocity-loop ``β = [K_d, p_d − K_d, b d_p, b d_n (, −b offset)]``,
    force-input ``β = [b, p_d, b d_p, b d_n, −b offset]``, with ``d_p = coulomb_pos``,
    ``d_n = −coulomb_neg``.
    """
    _check_form(form)
    if not (Ts > 0 and inertia > 0 and damping > 0):
        raise ValueError("Ts, inertia and damping must be positive")
    p_d = math.exp(-damping * Ts / inertia)
    b = (1.0 - p_d) / damping
    d_p, d_n = coulomb_pos, -coulomb_neg
    tail = [-b * offset] if _intercept(form, intercept) else []
    if form == "velocity-loop":
        if gain is None or not gain > 0:
            raise ValueError("the velocity-loop form needs the loop gain K > 0 (N·s/m)")
        K_d = gain * b
        beta = [K_d, p_d - K_d] + ([b * d_p, b * d_n] if coulomb else []) + tail
    else:
        beta = [b, p_d] + ([b * d_p, b * d_n] if coulomb else []) + tail
    return np.array(beta, dtype=np.float64)


def _pole_gain(form: str, beta: np.ndarray) -> tuple[float, float]:
    """``(p_d, β1)``: velocity-loop ``p_d = β1 + β2``, force-input ``p_d = β2``."""
    return (float(beta[0] + beta[1]) if form == "velocity-loop" else float(beta[1])), float(beta[0])


def _names_for(form: str, beta: np.ndarray, coulomb: bool, intercept: bool | None, names) -> tuple[str, ...]:
    if names is None:
        names = beta_names(form, coulomb, intercept)
        if beta.shape != (len(names),):
            raise ValueError(f"β for the {form} form {'with' if coulomb else 'without'} Coulomb columns"
                             f"{' and the constant column' if 'one' in names else ''} has {len(names)} entries, "
                             f"got {beta.shape}")
    names = tuple(names)
    if beta.shape != (len(names),):
        raise ValueError(f"β has {beta.shape} entries but {len(names)} names {names}")
    return names


def beta_to_physical(form: str, beta, Ts: float, *, gain: float | None = None, coulomb: bool = True,
                     intercept: bool | None = None, names=None) -> Physical:
    """Physical parameters from β (method §2, "Physical parameters from β").

    With ``b̃ = β1`` (force-input) or ``β1/K`` (velocity-loop with K; ``β1`` without K, giving the
    ``…_over_gain`` ratios): ``B = (1 − p_d)/b̃``, ``J = B Ts/(−ln p_d)``,
    ``coulomb_pos = β(−σ_p)/b̃``, ``coulomb_neg = −β(−σ_n)/b̃``, ``coulomb = (pos + neg)/2``,
    ``offset = −β(one)/b̃``. ``names`` (default :func:`beta_names`) locates the columns.

    Raises ``ValueError`` when β is not a stable, causal first-order drive (0 < p_d < 1, β1 > 0).
    """
    _check_form(form)
    beta = np.asarray(beta, dtype=np.float64)
    names = _names_for(form, beta, coulomb, intercept, names)
    p_d, b1 = _pole_gain(form, beta)
    if not (0.0 < p_d < 1.0) or not b1 > 0.0:
        raise ValueError(
            f"identified β gives pole p_d = {p_d:.6g} and input gain β1 = {b1:.6g}; a physical drive needs "
            "0 < p_d < 1 and β1 > 0 — check the input form, the sign of the command and the sample alignment"
        )
    known = form == "force-input" or gain is not None
    bt = b1 if form == "force-input" or gain is None else b1 / float(gain)
    log_term = -math.log(p_d)
    damping = (1.0 - p_d) / bt
    values = {"inertia": damping * Ts / log_term, "damping": damping}
    if "-sigma_p" in names:
        cp = float(beta[names.index("-sigma_p")]) / bt
        cn = -float(beta[names.index("-sigma_n")]) / bt
        values.update(coulomb=0.5 * (cp + cn), coulomb_pos=cp, coulomb_neg=cn)
    if "one" in names:
        values["offset"] = -float(beta[names.index("one")]) / bt
    if known:
        return Physical(form=form, pole=p_d, gain=None if gain is None else float(gain), **values)
    return Physical(form=form, pole=p_d, **{f"{k}_over_gain": v for k, v in values.items()})


def physical_covariance(form: str, beta, cov, Ts: float, *, gain: float | None = None, names=None,
                        coulomb: bool = True, intercept: bool | None = None) -> tuple[dict, dict]:
    """Physical parameters and their standard errors by the delta method.

    ``cov_φ = J cov_β Jᵀ`` with ``J = ∂φ/∂β`` from central differences (relative step 1e-6 of
    each β entry) of :func:`beta_to_physical`. Returns ``(physical, stderr)`` dicts with the keys
    of :meth:`Physical.to_dict`, plus ``"_cov"`` (the covariance matrix in key order) in the second.
    """
    beta = np.asarray(beta, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    kw = dict(gain=gain, names=names, coulomb=coulomb, intercept=intercept)
    phys = beta_to_physical(form, beta, Ts, **kw).to_dict()
    keys = list(phys)
    jac = np.zeros((len(keys), beta.size))
    for j in range(beta.size):
        h = 1e-6 * abs(beta[j]) if beta[j] != 0.0 else 1e-6 * float(np.max(np.abs(beta)))
        up, dn = beta.copy(), beta.copy()
        up[j] += h
        dn[j] -= h
        try:
            fu = beta_to_physical(form, up, Ts, **kw).to_dict()
            fd = beta_to_physical(form, dn, Ts, **kw).to_dict()
        except ValueError:  # at the edge of validity: one-sided
            fu, fd, h = beta_to_physical(form, up if beta[j] >= 0 else dn, Ts, **kw).to_dict(), phys, h / 2
        jac[:, j] = [(fu[k] - fd[k]) / (2.0 * h) for k in keys]
    c = jac @ cov @ jac.T
    se = {k: float(math.sqrt(max(c[i, i], 0.0))) for i, k in enumerate(keys)}
    se["_cov"] = c
    return phys, se


def validity_problems(form: str, beta, Ts: float, *, names=None, gain: float | None = None,
                      physical_se: dict | None = None, coulomb: bool = True,
                      intercept: bool | None = None) -> list[str]:
    """Why a model cannot be right (empty list: nothing found). The one check used by
    ``feedmon identify`` before writing and by the model-file loader before running.

    * discrete pole ``p_d ≥ 1`` (unstable/integrating drive) or ``p_d ≤ 0`` (no first-order
      drive: sampling too slow or wrong alignment);
    * input gain ``β1 ≤ 0`` (inertia or damping ≤ 0: wrong sign of the command or input form);
    * a Coulomb friction (symmetric, +, −) negative beyond its uncertainty:
      ``value < −COULOMB_Z · s.e.`` (s.e. from ``physical_se``, 0 when unknown).

    Each message names the cause and what to try.
    """
    _check_form(form)
    beta = np.asarray(beta, dtype=np.float64)
    names = _names_for(form, beta, coulomb, intercept, names)
    p_d, b1 = _pole_gain(form, beta)
    problems = []
    if not math.isfinite(p_d) or not math.isfinite(b1):
        return ["β has non-finite entries"]
    if p_d >= 1.0:
        problems.append(f"the discrete pole p_d = {p_d:.6g} is ≥ 1: the model drive would not come to rest "
                        "(unstable or integrating); the disturbance model has absorbed the damping — try another "
                        "--period, --method ls, or a trial with more varied motion")
    elif p_d <= 0.0:
        problems.append(f"the discrete pole p_d = {p_d:.6g} is ≤ 0: not a first-order drive at this sample rate — "
                        "check the sample alignment of command and velocity and the input form (--form)")
    if b1 <= 0.0:
        problems.append(f"the input gain β1 = {b1:.6g} is ≤ 0, so inertia and damping would be ≤ 0 — check the sign "
                        "of the command (v_ref or u), the input form (--form) and the sample alignment")
    if problems:
        return problems
    phys = beta_to_physical(form, beta, Ts, gain=gain, names=names).to_dict()
    se = physical_se or {}
    negative = []
    for key in ("coulomb", "coulomb_pos", "coulomb_neg"):
        for name in (key, f"{key}_over_gain"):
            value = phys.get(name)
            if value is None:
                continue
            s = float(se.get(name, 0.0) or 0.0)
            if value < -COULOMB_Z * s:
                negative.append(f"{name} = {value:.4g} ± {s:.2g}")
    if negative:
        problems.append("Coulomb friction negative beyond its uncertainty (" + ", ".join(negative) + "): the "
                        "disturbance model or a wrong dead band has taken the friction — try another --period, "
                        "--method ls, a larger --omega, or --no-coulomb")
    return problems


def check_validity(form: str, beta, Ts: float, **kw) -> None:
    """Raise ``ValueError`` with every problem of :func:`validity_problems` (nothing when valid)."""
    problems = validity_problems(form, beta, Ts, **kw)
    if problems:
        raise ValueError("the model cannot be right: " + "; ".join(problems))


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
    intercept: bool | None = None,
) -> np.ndarray:
    """Free-run simulation of an identified model: the model's own past velocity is fed back.

    ``v̂(k+1) = βᵀ z(v̂(k), e(k)) + f(k)`` with ``e`` = v_ref (velocity-loop) or u
    (force-input) and optional disturbance ``f`` (velocity units). Returns ``v̂``
    with ``v̂(0) = v0`` and the same length as ``exogenous``. ``intercept``: β ends with the
    constant column (default: force-input form only).
    """
    _check_form(form)
    beta = np.asarray(beta, dtype=np.float64)
    e = _finite_1d("exogenous input", exogenous)
    f = np.zeros_like(e) if disturbance is None else _finite_1d("disturbance", disturbance)
    const = beta[-1] if _intercept(form, intercept) else 0.0
    cp, cn = (float(beta[2]), float(beta[3])) if coulomb else (0.0, 0.0)
    return _free_run(float(beta[0]), float(beta[1]), cp, cn, float(const), float(v0), e, f, float(omega))


@njit(cache=True, nogil=True)
def _free_run(b1, b2, cp, cn, const, v0, e, f, omega):
    """The loop of :func:`simulate_free_run` (compiled: a record of any length)."""
    out = np.empty_like(e)
    out[0] = v0
    for k in range(e.size - 1):
        v = out[k]
        nxt = b1 * e[k] + b2 * v + const
        if v > omega:
            nxt -= cp
        elif v < -omega:
            nxt -= cn
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
