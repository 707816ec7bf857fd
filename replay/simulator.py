"""Closed-loop feed-drive simulator with known truth (method §1).

Plant ``J dv/dt = T − B v − T_f(v) − T_c(t)``, velocity P loop ``T = K (v_r − v_m)``
held over ``Ts`` (ZOH), Coulomb friction ``T_f = d_p`` for ``v > Ω``, ``−d_n`` for
``v < −Ω``, 0 inside the dead band, acting on the **true** velocity; the controller
and the model see the **measured** velocity ``v_m = v + noise``.

The drive constants may vary over the trial (``[drive_drift]``, ``[drive_step]`` of the
scenario): ``J(k), B(k), d_p(k), d_n(k)`` are evaluated at the sample time ``t_k`` and
held over ``[t_k, t_k + Ts)`` in both paths (:func:`replay.scenarios.drive_series`); the
truth channel records them per sample.

Default path (exact): the plant is advanced with the exact ZOH solution over each
``Ts``, with the friction evaluated at the sample instant and the disturbance force
averaged over the interval (both held, like the controller output). Without noise the
recorded data then satisfy the PL-ARX model of method §2 exactly with the β(k) of
``kernels.feed_drive.physical_to_beta`` at the constants of sample k, and
``f(k) = −b(k)·T_c(k)`` (``force_to_disturbance``). ``TrialTruth.beta`` is β(0).

``fine=True``: the plant is integrated at ``fine_rate`` (10 kHz; ``n_sub =
round(fine_rate·Ts)`` exact-ZOH substeps per controller period) with the friction on
the continuous true velocity and the disturbance averaged per substep; the controller
still runs at ``Ts``. The recorded velocity is the 10 kHz measurement, anti-alias
filtered (zero-phase FIR, ``scipy.signal.decimate``) and decimated to ``Ts``, as the
thesis data were recorded. β from ``physical_to_beta`` is then the nominal truth,
no longer exact.

Stability: the linear closed loop over one ``Ts`` has the pole ``p_d − K_d`` with
``p_d = exp(−B Ts/J)``, ``K_d = K (1 − p_d)/B`` (method §1; in the fine path the same
pole results from ``n_sub`` substeps, ``p_d = exp(−B h/J)^n_sub``). A configuration with
``|p_d − K_d| ≥ 1`` at any sample is refused before anything is simulated
(:class:`UnstableLoopError`, naming the pole and the stable gain range
``0 < K < B (1 + p_d)/(1 − p_d)``). A simulation that still produces a non-finite or
physically absurd sample (:data:`PLAUSIBLE`) raises :class:`SimulationError`; nothing is
written.

Recording glitch (thesis §4.2.2): with probability ``glitch_rate`` per sample the
recorder repeats the previous ``v_meas`` (the loop is not affected); glitched samples
are flagged in the truth channel.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from feedio import schema as S
from feedio.limits import SPINDLE_RPM_MAX
from kernels.errors import ParameterError
from kernels.feed_drive import beta_names, force_to_disturbance, physical_to_beta

from . import process as P
from . import scenarios as SC
from .cutting import MillingTool, SpindleProfile, feed_force, feed_force_teeth
from .plant import closed_loop_radius, friction, structure_of, structured_loop

__all__ = [
    "SimResult",
    "SimulationError",
    "UnstableLoopError",
    "PLAUSIBLE",
    "simulate",
    "simulate_scenario",
    "write_trial",
    "true_beta",
    "drive_constants",
    "closed_loop_pole",
    "stable_gain_limit",
    "check_closed_loop",
    "closed_loop_zoh",
]

# independent random streams (changing one source of randomness leaves the others alone)
_STREAM_NOISE, _STREAM_GLITCH, _STREAM_DYN, _STREAM_FINE = 1, 2, 3, 4

#: Plausibility limits of a simulated sample (column → (largest magnitude, unit)). A feed drive
#: moving faster than 100 m/s or pushing more than 10 MN is a simulation gone wrong, not a trial.
PLAUSIBLE = {
    "v_ref": (100.0, "m/s"),
    "v_meas": (100.0, "m/s"),
    "v_true": (100.0, "m/s"),
    "u": (1e7, "N"),
    "position": (1e6, "m"),
    "force": (1e7, "N"),
    "dynamometer": (1e7, "N"),
    "spindle_rpm": (SPINDLE_RPM_MAX, "rpm"),
    "spindle_angle": (1e12, "rad"),
}


class SimulationError(ValueError):
    """A scenario cannot be simulated into a trial (the message names the cause and the fix)."""


class UnstableLoopError(SimulationError):
    """The discrete closed loop ``p_d − K_d`` of a configuration lies outside the unit circle."""


@dataclass
class SimResult:
    """A simulated trial: recorded signals, ground truth and metadata (SI units)."""

    meta: S.TrialMeta
    t: np.ndarray
    v_ref: np.ndarray
    v_meas: np.ndarray  # as recorded (glitches included)
    u: np.ndarray  # force command K (v_r − v_m), N
    current: np.ndarray  # u / force_constant, A
    position: np.ndarray  # m
    spindle_rpm: np.ndarray | None
    force: np.ndarray  # true disturbance force T_c held over each interval, N
    f: np.ndarray  # −b(k)·T_c(k), m/s
    v_true: np.ndarray
    glitch: np.ndarray  # bool
    dynamometer: np.ndarray | None
    inertia: np.ndarray  # J(k), kg, held over [t_k, t_k + Ts)
    damping: np.ndarray  # B(k), N·s/m
    coulomb_pos: np.ndarray  # d_p(k), N
    coulomb_neg: np.ndarray  # magnitude of d_n(k), N
    spindle_angle: np.ndarray | None = None  # θ(t_k), rad, unwrapped (milling)
    block: int = 100
    program_line: np.ndarray | None = None  # NC line per sample (process scenarios, replay.process)
    tool: np.ndarray | None = None  # tool number per sample
    tooth_force: np.ndarray | None = None  # (n, teeth) each tooth's share of ``force`` (N; process scenarios)
    events: list = dataclasses.field(default_factory=list)  # known process events (feedio.schema.TruthEvent)

    @property
    def beta(self) -> np.ndarray:
        """β at the first sample (``TrialMeta.truth.beta``)."""
        return np.asarray(self.meta.truth.beta)

    def beta_series(self) -> np.ndarray:
        """The true β(k) of every sample, shape ``(n, len(beta))`` (``physical_to_beta`` per sample)."""
        truth = self.meta.truth
        return _beta_series(self.meta.form, self.meta.Ts, self.meta.loop_gain, self.drive(), truth.coulomb)

    def drive(self) -> dict[str, np.ndarray]:
        """The true drive constants per sample (``inertia``, ``damping``, ``coulomb_pos``, ``coulomb_neg``)."""
        return {name: getattr(self, name) for name in SC.VARYING}

    def __len__(self) -> int:
        return int(self.t.size)


def drive_constants(sc: dict) -> dict:
    """The nominal drive constants of a scenario (``[drive]``; SI)."""
    d = sc["drive"]
    return {
        "inertia": float(d["inertia"]),
        "damping": float(d["damping"]),
        "loop_gain": float(d["loop_gain"]),
        "coulomb_pos": float(d["coulomb_pos"]),
        "coulomb_neg": float(d["coulomb_neg"]),
    }


def true_beta(sc: dict) -> np.ndarray:
    """Exact ZOH β of the scenario's nominal constants (``physical_to_beta``; the only formula)."""
    p = drive_constants(sc)
    return physical_to_beta(
        sc["form"], 1.0 / sc["rate"], p["inertia"], p["damping"], gain=p["loop_gain"],
        coulomb_pos=p["coulomb_pos"], coulomb_neg=p["coulomb_neg"], coulomb=bool(sc["model"]["coulomb"]),
    )


def _beta_runs(form: str, Ts: float, K: float, par: dict, coulomb: bool):
    """β and the force-to-disturbance factor ``−b`` (``f = −b·T_c``) per run of samples with the
    same drive constants, from ``physical_to_beta`` / ``force_to_disturbance`` (one call per run:
    one for a constant drive, two for a step). Returns ``betas (runs, m), minus_b (runs,), run``
    with ``run[k]`` the run of sample k."""
    cols = [np.asarray(par[name], dtype=np.float64) for name in SC.VARYING]
    changed = np.zeros(cols[0].size, dtype=bool)
    for c in cols:
        changed[1:] |= c[1:] != c[:-1]
    run = np.cumsum(changed)
    starts = np.concatenate([[0], np.flatnonzero(changed)])
    betas = np.array([
        physical_to_beta(form, Ts, cols[0][k], cols[1][k], gain=K, coulomb_pos=cols[2][k], coulomb_neg=cols[3][k],
                         coulomb=coulomb)
        for k in starts
    ])
    minus_b = np.array([force_to_disturbance(form, beta, 1.0, gain=K) for beta in betas])
    return betas, minus_b, run


def _beta_series(form: str, Ts: float, K: float, par: dict, coulomb: bool) -> np.ndarray:
    """β(k) of every sample, shape ``(n, m)``."""
    betas, _, run = _beta_runs(form, Ts, K, par, coulomb)
    return betas[run]


# ---------------------------------------------------------------------------------------------
# closed-loop stability (method §1)
# ---------------------------------------------------------------------------------------------
def closed_loop_pole(Ts: float, inertia, damping, loop_gain: float, *, n_sub: int = 1) -> np.ndarray:
    """Discrete closed-loop pole ``p_d − K_d`` over one controller period ``Ts`` (method §1).

    ``p_d = exp(−B Ts/J)``, ``K_d = K (1 − p_d)/B``. With ``n_sub`` > 1 the pole of the fine
    path: the plant advanced by ``n_sub`` exact substeps of ``h = Ts/n_sub`` under the held
    command, ``p_d = exp(−B h/J)^n_sub`` (the same number up to rounding).
    """
    J = np.asarray(inertia, dtype=np.float64)
    B = np.asarray(damping, dtype=np.float64)
    p_h = np.exp(-B * (Ts / n_sub) / J)
    p_d = p_h**n_sub
    return p_d - loop_gain * (1.0 - p_d) / B


def stable_gain_limit(Ts: float, inertia: float, damping: float) -> float:
    """Largest stable loop gain (N·s/m): ``|p_d − K_d| < 1  ⇔  0 < K < B (1 + p_d)/(1 − p_d)``
    (≈ 2J/Ts when ``B Ts ≪ J``)."""
    p_d = math.exp(-damping * Ts / inertia)
    return damping * (1.0 + p_d) / (1.0 - p_d)


def check_closed_loop(Ts: float, inertia, damping, loop_gain: float, *, t=None, n_sub: int = 1) -> np.ndarray:
    """Refuse a closed loop with a pole ``|p_d − K_d| ≥ 1`` at any sample (:class:`UnstableLoopError`).

    ``inertia``, ``damping`` scalars or per-sample arrays (``t`` the sample times, for the
    message). Returns the poles. The message names the pole, where, the path and what to change:
    the stable gain range for that J, B, Ts, the inertia or the rate that makes the gain stable.
    """
    J = np.atleast_1d(np.asarray(inertia, dtype=np.float64))
    B = np.atleast_1d(np.asarray(damping, dtype=np.float64))
    for name, value in (("inertia", J), ("damping", B), ("loop_gain", np.atleast_1d(float(loop_gain))),
                        ("Ts", np.atleast_1d(float(Ts)))):
        if not np.all((value > 0) & np.isfinite(value)):
            raise SimulationError(f"the closed loop needs a finite {name} > 0, got {value[~((value > 0) & np.isfinite(value))][0]!r}")
    pole = closed_loop_pole(Ts, J, B, loop_gain, n_sub=n_sub)
    bad = np.flatnonzero(~(np.abs(pole) < 1.0))
    if bad.size == 0:
        return pole
    k = int(bad[0])
    Jk, Bk = float(J[k if J.size > 1 else 0]), float(B[k if B.size > 1 else 0])
    K = float(loop_gain)
    path = ("exact-ZOH loop" if n_sub == 1 else
            f"10 kHz fine path ({n_sub} substeps of {Ts / n_sub * 1e6:.4g} µs per Ts)")
    varies = J.size > 1 and (np.any(J != J[0]) or np.any(B != B[0]))
    where = "" if t is None or np.size(t) <= 1 else (
        f" from t = {float(np.asarray(t)[k]):.6g} s (sample {k}{'; the drive constants vary over this trial' if varies else ''})"
    )
    k_max = stable_gain_limit(Ts, Jk, Bk)
    fixes = [f"a loop gain in 0 < drive.loop_gain < {k_max:.6g} N·s/m (stable for this J, B, Ts)"]
    ln = math.log1p(2.0 * Bk / (K - Bk)) if K > Bk else 0.0  # log((K + B)/(K − B)), exact for K ≫ B
    if ln > 0.0:
        fixes.append(f"an inertia > {Bk * Ts / ln:.6g} kg for this gain and damping")
        fixes.append(f"rate > {Bk / (Jk * ln):.6g} Hz")
    raise UnstableLoopError(
        f"unstable closed loop: the discrete pole p_d − K_d = {float(pole[k]):.6g} (|·| ≥ 1) of the "
        f"{path}{where} with J = {Jk:.6g} kg, B = {Bk:.6g} N·s/m, K = {K:.6g} N·s/m, Ts = {Ts:.6g} s "
        f"(p_d = exp(−B Ts/J), K_d = K(1 − p_d)/B) diverges; nothing simulated. Change the scenario: "
        + "; or ".join(fixes)
    )


# ---------------------------------------------------------------------------------------------
# plant loops
# ---------------------------------------------------------------------------------------------
@njit(cache=True)
def _zoh_loop(v_ref, tc, noise, Ts, J, B, K, dp, dn, omega, v0, pos0):
    n = v_ref.size
    v_true = np.empty(n)
    v_ctrl = np.empty(n)
    u = np.empty(n)
    x = np.empty(n)
    v = v0
    pos = pos0
    Jc = -1.0
    Bc = -1.0
    pd = b = gx = p = 0.0
    for k in range(n):
        if J[k] != Jc or B[k] != Bc:  # constants changed: new exact-ZOH coefficients
            Jc = J[k]
            Bc = B[k]
            p = -Bc / Jc
            pd = math.exp(p * Ts)  # p_d
            b = (1.0 - pd) / Bc  # b = K_d/K
            gx = (pd - 1.0) / p  # ∫0^Ts e^{pτ} dτ
        vm = v + noise[k]
        uk = K * (v_ref[k] - vm)
        tf = friction(v, omega, dp[k], dn[k], 0.0, 1.0)
        v_true[k] = v
        v_ctrl[k] = vm
        u[k] = uk
        x[k] = pos
        force = uk - tf - tc[k]
        vss = force / Bc
        pos += vss * Ts + (v - vss) * gx
        v = pd * v + b * force
    return v_true, v_ctrl, u, x, v, pos


def _per_sample(value, n: int, name: str) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 0:
        return np.full(n, float(a))
    if a.shape != (n,):
        raise ValueError(f"{name} has shape {a.shape}; give one value or one per sample ({n})")
    return np.ascontiguousarray(a)


def closed_loop_zoh(v_ref, tc, noise, Ts, J, B, K, dp, dn, omega, v0=0.0, pos0=0.0):
    """Exact ZOH closed loop of method §1, starting from the state ``(v0, pos0)``.

    ``v_ref`` (m/s), ``tc`` disturbance force (N) and measurement ``noise`` (m/s) per sample;
    the drive constants ``J`` (kg), ``B`` (N·s/m), ``dp``, ``dn`` (N, magnitudes) one value or
    one per sample (held over ``[t_k, t_k + Ts)``), loop gain ``K`` (N·s/m), dead band ``omega``.
    Returns ``v_true, v_ctrl (= v_meas), u (N), x (m)`` per sample and the state after the last
    sample, ``v_end, pos_end``, so a long stream can be generated in chunks (the soak benchmark).
    Raises :class:`UnstableLoopError` when the closed loop is unstable.
    """
    v_ref = np.ascontiguousarray(v_ref, dtype=np.float64)
    n = v_ref.size
    J, B, dp, dn = (_per_sample(a, n, name) for a, name in ((J, "J"), (B, "B"), (dp, "dp"), (dn, "dn")))
    check_closed_loop(Ts, J, B, K)
    return _zoh_loop(v_ref, np.ascontiguousarray(tc, dtype=np.float64), np.ascontiguousarray(noise, dtype=np.float64),
                     float(Ts), J, B, float(K), dp, dn, float(omega), float(v0), float(pos0))


@njit(cache=True)
def _loop_fine(v_ref, tc_fine, noise, noise_fine, Ts, n_sub, J, B, K, dp, dn, omega):
    n = v_ref.size
    h = Ts / n_sub
    v_true = np.empty(n)
    v_ctrl = np.empty(n)
    u = np.empty(n)
    x = np.empty(n)
    v_fine = np.empty(n * n_sub)
    x_fine = np.empty(n * n_sub)
    v = 0.0
    pos = 0.0
    Jc = -1.0
    Bc = -1.0
    pd = b = gx = p = 0.0
    for k in range(n):
        if J[k] != Jc or B[k] != Bc:  # constants changed: new exact-ZOH substep coefficients
            Jc = J[k]
            Bc = B[k]
            p = -Bc / Jc
            pd = math.exp(p * h)
            b = (1.0 - pd) / Bc
            gx = (pd - 1.0) / p
        vm = v + noise[k]
        uk = K * (v_ref[k] - vm)
        v_true[k] = v
        v_ctrl[k] = vm
        u[k] = uk
        x[k] = pos
        for m in range(n_sub):
            i = k * n_sub + m
            v_fine[i] = v + noise_fine[i]
            x_fine[i] = pos
            tf = friction(v, omega, dp[k], dn[k], 0.0, 1.0)
            force = uk - tf - tc_fine[i]
            vss = force / Bc
            pos += vss * h + (v - vss) * gx
            v = pd * v + b * force
    return v_true, v_ctrl, u, x, v_fine, x_fine


# ---------------------------------------------------------------------------------------------
# disturbances (interval averages)
# ---------------------------------------------------------------------------------------------
@njit(cache=True)
def _shaker_kernel(n, dt, sub, w, ph, h2, ph2, profile, a0, a1, sweep_period, t_on, t_off):
    out = np.zeros(n)
    for k in range(n):
        acc = 0.0
        for i in range(sub):
            t = (k + (i + 0.5) / sub) * dt
            if t < t_on or t >= t_off:
                continue
            if profile == 0:
                amp = a0
            else:
                amp = a0 + (a1 - a0) * 0.5 * (1.0 - math.cos(2.0 * math.pi * t / sweep_period))
            x = w * t + ph
            acc += amp * (math.sin(x) + h2 * math.sin(2.0 * x + ph2))
        out[k] = acc / sub
    return out


def _shaker_force(d: dict, dt: float, n: int, duration: float) -> np.ndarray:
    """Shaker force (N, positive opposes positive motion) averaged over intervals of dt:
    ``A(t)·[sin(ωt + φ) + h2·sin(2(ωt + φ) + φ2)]`` while on (``start``…``stop`` fractions
    of the duration: abrupt switching), ``A`` constant or swept ``A0 + (A1 − A0)(1 − cos 2πt/T)/2``."""
    if d["profile"] not in ("constant", "sweep"):
        raise ValueError(f"disturbance.profile must be constant or sweep, got {d['profile']!r}")
    sub = max(1, int(math.ceil(16 * dt * d["frequency"] / (1.0 / 333.0) / 55.0)))  # ~16 points per 3 ms at 55 Hz
    return _shaker_kernel(
        n, dt, sub, 2 * math.pi * d["frequency"], math.radians(d["phase"]), float(d["harmonic2"]),
        math.radians(d["harmonic2_phase"]), 0 if d["profile"] == "constant" else 1,
        float(d["amplitude"]), float(d["amplitude_max"]), float(d["sweep_period"]),
        float(d["start"]) * duration, float(d["stop"]) * duration,
    )


def _milling_tool(d: dict) -> MillingTool:
    keys = ("spindle_rpm", "teeth", "diameter", "depth", "Ktc", "Krc", "Kte", "Kre", "runout",
            "runout_angle", "start_angle", "exit_angle", "phase", "angle_step")
    return MillingTool(**{k: d[k] for k in keys})


def _step_force(d: dict, dt: float, n: int, duration: float) -> np.ndarray:
    """Force step ``F`` (N) on from ``start·duration`` to ``stop·duration`` (abrupt), averaged
    exactly over each interval of dt (an interval the edge cuts holds the covered fraction)."""
    k = np.arange(n, dtype=np.float64)  # interval k is [k, k + 1] in units of dt (exact integers)
    on, off = float(d["start"]) * duration / dt, float(d["stop"]) * duration / dt
    covered = np.clip(np.minimum(k + 1.0, off) - np.maximum(k, on), 0.0, 1.0)
    return float(d["force"]) * covered


def _process_force(sc: dict, v_ref: np.ndarray, Ts: float, n_sub: int, spindle: SpindleProfile | None,
                   out: dict) -> np.ndarray:
    """Milling force of a process scenario (:mod:`replay.process`) per interval of Ts/n_sub (N): the
    per-tooth model with the tooth condition, missing stock and collision pulses; ``out`` receives
    each tooth's share per sample (``tooth_force``, averaged to Ts) and the pulses (``impulses``)."""
    n = v_ref.size * n_sub
    dt = Ts / n_sub
    t_mid = (np.arange(n) + 0.5) * dt
    engage = SC.engagement(sc, t_mid) * P.missing_mask(sc, t_mid)
    tc, teeth = feed_force_teeth(_milling_tool(sc["disturbance"]), 0.0, dt, np.repeat(v_ref, n_sub), engage,
                                 spindle=spindle, condition=P.tooth_condition(sc))
    pulses, out["impulses"] = P.impulse_force(sc, tc, dt)
    out["tooth_force"] = teeth.reshape(v_ref.size, n_sub, -1).mean(axis=1)
    return tc + pulses


def _disturbance(sc: dict, v_ref: np.ndarray, Ts: float, n_sub: int, spindle: SpindleProfile | None,
                 process: dict | None = None) -> np.ndarray:
    """Disturbance force per interval of Ts/n_sub (N); a process scenario's extras go to ``process``."""
    d = sc["disturbance"]
    n = v_ref.size * n_sub
    dt = Ts / n_sub
    if d["kind"] == "none":
        return np.zeros(n)
    if d["kind"] == "shaker":
        return _shaker_force(d, dt, n, sc["duration"])
    if d["kind"] == "step":
        return _step_force(d, dt, n, sc["duration"])
    if not d["cutting"]:
        return np.zeros(n)
    if P.has_process(sc):
        return _process_force(sc, v_ref, Ts, n_sub, spindle, {} if process is None else process)
    tool = _milling_tool(d)
    feed = np.repeat(v_ref, n_sub)  # programmed feed rate → feed per tooth at the spindle speed (replay.cutting)
    t_mid = (np.arange(n) + 0.5) * dt
    return feed_force(tool, 0.0, dt, feed, SC.engagement(sc, t_mid), spindle=spindle)


def _structured(sc: dict, st, v_ref, tc, noise, Ts: float, par: dict, K: float, omega: float, fine: bool):
    """The closed loop of a drive beyond the rigid model (:mod:`replay.plant`): constant drive constants,
    the exact path; refused when unstable."""
    if fine:
        raise ParameterError("fine=True simulates the rigid drive only; a [structure] or Stribeck friction runs on "
                             "the exact path (fine=False)", "fine")
    const = {name: float(par[name][0]) for name in SC.VARYING}
    if any(np.any(par[name] != const[name]) for name in SC.VARYING):
        raise SimulationError("drive_drift and drive_step need the rigid drive; set them to 0 with a [structure] "
                              "or Stribeck friction")
    radius = closed_loop_radius(st, Ts, const["inertia"], const["damping"], K)
    if not radius < 1.0:
        raise UnstableLoopError(f"unstable closed loop: {'; '.join(st.describe()) or 'the drive'} with J = "
                                f"{const['inertia']:.6g} kg, B = {const['damping']:.6g} N·s/m, K = {K:.6g} N·s/m, "
                                f"Ts = {Ts:.6g} s has a pole of magnitude {radius:.4g} ≥ 1; nothing simulated. Lower "
                                "drive.loop_gain, or raise structure.resonance (two-mass)")
    return structured_loop(st, v_ref, tc, noise, Ts, const["inertia"], const["damping"], K, const["coulomb_pos"],
                           const["coulomb_neg"], omega)


def _check_plausible(columns: dict, dt: float, path: str) -> None:
    """Refuse a simulated trial holding a non-finite or absurd sample (:data:`PLAUSIBLE`);
    sample k of every column is at ``t = k·dt``."""
    for name, values in columns.items():
        if values is None:
            continue
        limit, unit = PLAUSIBLE[name]
        bad = np.flatnonzero(~(np.abs(values) <= limit))
        if bad.size:
            k = int(bad[0])
            raise SimulationError(
                f"the {path} simulation produced {name} = {float(values[k])!r} {unit} at t = {k * dt:.6g} s "
                f"(sample {k}; {bad.size} sample(s) non-finite or beyond ±{limit:g} {unit}), which no feed drive "
                "does; nothing written. Check the drive constants (inertia, damping, loop_gain), the disturbance "
                "amplitude and the trajectory of the scenario"
            )


# ---------------------------------------------------------------------------------------------
# simulate
# ---------------------------------------------------------------------------------------------
def _trial_meta(sc: dict, *, Ts: float, seed: int, fine: bool, created: str | None, structure, par: dict, K: float, omega: float,
                spindle, betas: np.ndarray, coulomb: bool) -> S.TrialMeta:
    """The metadata of a simulated trial: provenance, and the truth (β at t = 0, the physical constants,
    the scenario) that ``identify`` and the tests score against."""
    from feedio import __version__

    d = sc["disturbance"]
    milling = d["kind"] == "milling"
    physical = {name: float(par[name][0]) for name in SC.VARYING}  # the values at t = 0
    physical["loop_gain"] = K
    physical["force_constant"] = float(sc["drive"]["force_constant"])
    details = {"fine": bool(fine), "path": "fine 10 kHz + AA decimation" if fine else "exact ZOH"}
    if not structure.rigid_model:
        details["beyond_the_model"] = structure.describe()  # the truth's β is the rigid equivalent's
    varying = [name for name in SC.VARYING if np.any(par[name] != par[name][0])]
    if varying:
        details["time_varying"] = varying  # the truth channel holds their values per sample
    return S.TrialMeta(
        Ts=Ts,
        form=sc["form"],
        machine=sc["machine"],
        axis=sc["axis"],
        units=dict(S.UNITS),
        spindle_rpm=(float(spindle.rpm[0]) if spindle.constant else None) if spindle is not None else None,
        teeth=int(d["teeth"]) if milling else None,
        loop_gain=K,
        provenance=S.Provenance(
            source="simulated",
            tool="feedmon simulate",
            version=__version__,
            seed=int(seed),
            scenario=sc["name"],
            created=created,
            details=details,
        ),
        truth=S.TrialTruth(
            beta=[float(b) for b in betas[0]],
            omega=omega,
            coulomb=coulomb,
            physical=physical,
            scenario=sc,
            beta_names=list(beta_names(sc["form"], coulomb)),
        ),
        description=sc["description"],
    )


def simulate(sc: dict, *, seed: int = 0, fine: bool = False, created: str | None = None) -> SimResult:
    """Simulate a scenario dict (from :func:`replay.scenarios.load_scenario`).

    Raises :class:`UnstableLoopError` before simulating when the closed loop is unstable at
    any sample, and :class:`SimulationError` when a sample comes out non-finite or absurd.
    """
    SC.check(sc)
    if not (isinstance(seed, int) and seed >= 0):
        raise ValueError(f"seed must be an integer ≥ 0, got {seed!r}")
    Ts = 1.0 / sc["rate"]
    n = int(round(sc["duration"] * sc["rate"]))
    t = np.arange(n) * Ts
    dc = drive_constants(sc)
    K = dc["loop_gain"]
    par = SC.drive_series(sc, t)  # J(k), B(k), d_p(k), d_n(k)
    J, B, dp, dn = (par[name] for name in SC.VARYING)
    omega = float(sc["drive"]["omega"])
    n_sub = 1
    if fine:
        n_sub = int(round(sc["fine_rate"] * Ts))
        if n_sub < 2:
            raise ValueError(f"fine_rate {sc['fine_rate']} Hz gives {n_sub} substeps per Ts; need ≥ 2")
        if n * n_sub > SC.MAX_SIM_SAMPLES:
            raise ParameterError(f"fine=True: {n} samples × {n_sub} substeps at fine_rate {sc['fine_rate']:g} Hz are "
                                 f"more than one simulated trial holds ({SC.MAX_SIM_SAMPLES:,} samples, every one kept "
                                 f"in memory); simulate at most {SC.MAX_SIM_SAMPLES / n_sub / sc['rate']:g} s with "
                                 "fine=True, or lower fine_rate", "fine")
    check_closed_loop(Ts, J, B, K, t=t, n_sub=n_sub)

    nz = sc["noise"]
    spindle = SC.spindle_profile(sc)
    v_ref = SC.reference_velocity(sc, n, Ts)
    noise = np.random.default_rng([seed, _STREAM_NOISE]).normal(0.0, nz["v_meas_std"], n) if nz["v_meas_std"] > 0 else np.zeros(n)

    structure = structure_of(sc)
    proc: dict = {}
    if not structure.rigid_model:
        tc = _disturbance(sc, v_ref, Ts, 1, spindle, proc)
        v_true, v_ctrl, u, x = _structured(sc, structure, v_ref, tc, noise, Ts, par, K, omega, fine)
        v_rec = v_ctrl.copy()
        pos = x
    elif not fine:
        tc = _disturbance(sc, v_ref, Ts, 1, spindle, proc)
        v_true, v_ctrl, u, x, _, _ = _zoh_loop(v_ref, tc, noise, Ts, J, B, K, dp, dn, omega, 0.0, 0.0)
        v_rec = v_ctrl.copy()
        pos = x
    else:
        from scipy.signal import decimate

        tc_fine = _disturbance(sc, v_ref, Ts, n_sub, spindle, proc)
        noise_fine = (
            np.random.default_rng([seed, _STREAM_FINE]).normal(0.0, nz["v_meas_std"], n * n_sub)
            if nz["v_meas_std"] > 0 else np.zeros(n * n_sub)
        )
        v_true, v_ctrl, u, x, v_fine, x_fine = _loop_fine(
            v_ref, tc_fine, noise, noise_fine, Ts, n_sub, J, B, K, dp, dn, omega
        )
        _check_plausible({"v_true": v_fine, "position": x_fine}, Ts / n_sub, "fine-path")
        v_rec = decimate(v_fine, n_sub, ftype="fir", zero_phase=True)[:n]
        pos = decimate(x_fine, n_sub, ftype="fir", zero_phase=True)[:n]
        tc = tc_fine.reshape(n, n_sub).mean(axis=1)

    # recording glitch: repeat the previous recorded value
    glitch = np.zeros(n, dtype=bool)
    if nz["glitch_rate"] > 0:
        glitch[1:] = np.random.default_rng([seed, _STREAM_GLITCH]).random(n - 1) < nz["glitch_rate"]
        for k in np.flatnonzero(glitch):
            v_rec[k] = v_rec[k - 1]

    coulomb = bool(sc["model"]["coulomb"])
    betas, minus_b, run = _beta_runs(sc["form"], Ts, K, par, coulomb)
    f = tc * (minus_b[0] if minus_b.size == 1 else minus_b[run])  # f(k) = −b(k)·T_c(k) (force_to_disturbance)
    d = sc["disturbance"]
    dyn = None
    if d["kind"] != "none":
        dyn = 0.0 - tc  # the force on the table in the +axis direction (no negative zeros)
        if nz["dynamometer_std"] > 0:
            dyn = dyn + np.random.default_rng([seed, _STREAM_DYN]).normal(0.0, nz["dynamometer_std"], n)
    rpm = angle = None
    if spindle is not None:
        rpm, angle = spindle.speed(t), spindle.angle(t)
    _check_plausible(
        {"force": tc, "dynamometer": dyn, "v_ref": v_ref, "spindle_rpm": rpm, "spindle_angle": angle,
         "v_true": v_true, "v_meas": v_rec, "u": u, "position": pos},
        Ts, "fine-path" if fine else "exact-ZOH",
    )

    meta = _trial_meta(sc, Ts=Ts, seed=seed, fine=fine, created=created, structure=structure, par=par, K=K, omega=omega,
                       spindle=spindle, betas=betas, coulomb=coulomb)
    res = SimResult(
        meta=meta, t=t, v_ref=v_ref, v_meas=v_rec, u=u, current=u / sc["drive"]["force_constant"],
        position=pos, spindle_rpm=rpm, force=tc, f=f, v_true=v_true, glitch=glitch,
        dynamometer=dyn, inertia=J, damping=B, coulomb_pos=dp, coulomb_neg=dn, spindle_angle=angle,
        block=int(sc["block"]),
    )
    if P.has_process(sc):
        _add_process(res, sc, proc, Ts)
    return res


def _add_process(res: SimResult, sc: dict, proc: dict, Ts: float) -> None:
    """The NC context columns, each tooth's force and the truth events of a process scenario."""
    n = len(res)
    res.program_line, res.tool = P.program_columns(sc, n, Ts)
    if not sc["disturbance"]["cutting"]:
        return
    res.tooth_force = proc["tooth_force"]
    engaged = (SC.engagement(sc, res.t) * P.missing_mask(sc, res.t)) > 0
    res.events = P.truth_events(sc, _milling_tool(sc["disturbance"]), res.t, res.v_ref, res.spindle_rpm, engaged,
                                proc["impulses"])


def simulate_scenario(name: str, *, seed: int = 0, duration: float | None = None, config=None,
                      fine: bool = False, created: str | None = None) -> SimResult:
    """Load a built-in scenario (with optional override TOML/dict) and simulate it."""
    return simulate(SC.load_scenario(name, config, duration=duration), seed=seed, fine=fine, created=created)


def write_trial(res: SimResult, path, *, block: int | None = None) -> None:
    """Write a simulated trial (samples + truth) to an MCAP trial file."""
    from feedio.mcapio import write_arrays

    write_arrays(
        path, res.meta,
        dict(t=res.t, v_ref=res.v_ref, v_meas=res.v_meas, u=res.u, current=res.current,
             position=res.position, spindle_rpm=res.spindle_rpm, spindle_angle=res.spindle_angle,
             **({} if res.program_line is None else {"program_line": res.program_line, "tool": res.tool})),
        dict(t=res.t, force=res.force, f=res.f, dynamometer=res.dynamometer, v_true=res.v_true,
             glitch=res.glitch, inertia=res.inertia, damping=res.damping, coulomb_pos=res.coulomb_pos,
             coulomb_neg=res.coulomb_neg),
        block=int(block or res.block), events=res.events,
    )
