"""Closed-loop feed-drive simulator with known truth (method §1).

Plant ``J dv/dt = T − B v − T_f(v) − T_c(t)``, velocity P loop ``T = K (v_r − v_m)``
held over ``Ts`` (ZOH), Coulomb friction ``T_f = d_p`` for ``v > Ω``, ``−d_n`` for
``v < −Ω``, 0 inside the dead band, acting on the **true** velocity; the controller
and the model see the **measured** velocity ``v_m = v + noise``.

Default path (exact): the plant is advanced with the exact ZOH solution over each
``Ts``, with the friction evaluated at the sample instant and the disturbance force
averaged over the interval (both held, like the controller output). Without noise the
recorded data then satisfy the PL-ARX model of method §2 exactly with the β of
``kernels.feed_drive.physical_to_beta`` — the recorded truth — and
``f(k) = −b·T_c(k)`` (``force_to_disturbance``).

``fine=True``: the plant is integrated at ``fine_rate`` (10 kHz; ``n_sub =
round(fine_rate·Ts)`` exact-ZOH substeps per controller period) with the friction on
the continuous true velocity and the disturbance averaged per substep; the controller
still runs at ``Ts``. The recorded velocity is the 10 kHz measurement, anti-alias
filtered (zero-phase FIR, ``scipy.signal.decimate``) and decimated to ``Ts``, as the
thesis data were recorded. β from ``physical_to_beta`` is then the nominal truth,
no longer exact.

Recording glitch (thesis §4.2.2): with probability ``glitch_rate`` per sample the
recorder repeats the previous ``v_meas`` (the loop is not affected); glitched samples
are flagged in the truth channel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from feedio import schema as S
from kernels.feed_drive import beta_names, force_to_disturbance, physical_to_beta

from . import scenarios as SC
from .cutting import MillingTool, feed_force

__all__ = ["SimResult", "simulate", "simulate_scenario", "write_trial", "true_beta", "drive_constants"]

# independent random streams (changing one source of randomness leaves the others alone)
_STREAM_NOISE, _STREAM_GLITCH, _STREAM_DYN, _STREAM_FINE = 1, 2, 3, 4


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
    f: np.ndarray  # −b·T_c, m/s
    v_true: np.ndarray
    glitch: np.ndarray  # bool
    dynamometer: np.ndarray | None
    block: int = 100

    @property
    def beta(self) -> np.ndarray:
        return np.asarray(self.meta.truth.beta)

    def __len__(self) -> int:
        return int(self.t.size)


def drive_constants(sc: dict) -> dict:
    d = sc["drive"]
    return {
        "inertia": float(d["inertia"]),
        "damping": float(d["damping"]),
        "loop_gain": float(d["loop_gain"]),
        "coulomb_pos": float(d["coulomb_pos"]),
        "coulomb_neg": float(d["coulomb_neg"]),
    }


def true_beta(sc: dict) -> np.ndarray:
    """Exact ZOH β of the scenario (``physical_to_beta``; the only formula)."""
    p = drive_constants(sc)
    return physical_to_beta(
        sc["form"], 1.0 / sc["rate"], p["inertia"], p["damping"], gain=p["loop_gain"],
        coulomb_pos=p["coulomb_pos"], coulomb_neg=p["coulomb_neg"], coulomb=bool(sc["model"]["coulomb"]),
    )


# ---------------------------------------------------------------------------------------------
# plant loops
# ---------------------------------------------------------------------------------------------
@njit(cache=True)
def closed_loop_zoh(v_ref, tc, noise, Ts, J, B, K, dp, dn, omega, v0=0.0, pos0=0.0):
    """Exact ZOH closed loop of method §1, starting from the state ``(v0, pos0)``.

    ``v_ref`` (m/s), ``tc`` disturbance force (N) and measurement ``noise`` (m/s) per sample.
    Returns ``v_true, v_ctrl (= v_meas), u (N), x (m)`` per sample and the state after the last
    sample, ``v_end, pos_end``, so a long stream can be generated in chunks (the soak benchmark).
    """
    n = v_ref.size
    p = -B / J
    pd = math.exp(p * Ts)
    b = (1.0 - pd) / B
    gx = (pd - 1.0) / p  # ∫0^Ts e^{pτ} dτ
    v_true = np.empty(n)
    v_ctrl = np.empty(n)
    u = np.empty(n)
    x = np.empty(n)
    v = v0
    pos = pos0
    for k in range(n):
        vm = v + noise[k]
        uk = K * (v_ref[k] - vm)
        if v > omega:
            tf = dp
        elif v < -omega:
            tf = -dn
        else:
            tf = 0.0
        v_true[k] = v
        v_ctrl[k] = vm
        u[k] = uk
        x[k] = pos
        force = uk - tf - tc[k]
        vss = force / B
        pos += vss * Ts + (v - vss) * gx
        v = pd * v + b * force
    return v_true, v_ctrl, u, x, v, pos


@njit(cache=True)
def _loop_fine(v_ref, tc_fine, noise, noise_fine, Ts, n_sub, J, B, K, dp, dn, omega):
    n = v_ref.size
    h = Ts / n_sub
    p = -B / J
    pd = math.exp(p * h)
    b = (1.0 - pd) / B
    gx = (pd - 1.0) / p
    v_true = np.empty(n)
    v_ctrl = np.empty(n)
    u = np.empty(n)
    x = np.empty(n)
    v_fine = np.empty(n * n_sub)
    x_fine = np.empty(n * n_sub)
    v = 0.0
    pos = 0.0
    for k in range(n):
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
            if v > omega:
                tf = dp
            elif v < -omega:
                tf = -dn
            else:
                tf = 0.0
            force = uk - tf - tc_fine[i]
            vss = force / B
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


def _disturbance(sc: dict, v_ref: np.ndarray, Ts: float, n_sub: int) -> np.ndarray:
    """Disturbance force per interval of Ts/n_sub (N)."""
    d = sc["disturbance"]
    n = v_ref.size * n_sub
    dt = Ts / n_sub
    if d["kind"] == "none":
        return np.zeros(n)
    if d["kind"] == "shaker":
        return _shaker_force(d, dt, n, sc["duration"])
    if not d["cutting"]:
        return np.zeros(n)
    tool = _milling_tool(d)
    feed = np.repeat(v_ref, n_sub)  # programmed feed per tooth (see replay.cutting)
    t_mid = (np.arange(n) + 0.5) * dt
    return feed_force(tool, 0.0, dt, feed, SC.engagement(sc, t_mid))


# ---------------------------------------------------------------------------------------------
# simulate
# ---------------------------------------------------------------------------------------------
def simulate(sc: dict, *, seed: int = 0, fine: bool = False, created: str | None = None) -> SimResult:
    """Simulate a scenario dict (from :func:`replay.scenarios.load_scenario`)."""
    from feedio import __version__

    SC.check(sc)
    if not (isinstance(seed, int) and seed >= 0):
        raise ValueError(f"seed must be an integer ≥ 0, got {seed!r}")
    Ts = 1.0 / sc["rate"]
    n = int(round(sc["duration"] * sc["rate"]))
    t = np.arange(n) * Ts
    dc = drive_constants(sc)
    J, B, K = dc["inertia"], dc["damping"], dc["loop_gain"]
    dp, dn = dc["coulomb_pos"], dc["coulomb_neg"]
    omega = float(sc["drive"]["omega"])
    nz = sc["noise"]
    v_ref = SC.reference_velocity(sc, n, Ts)
    noise = np.random.default_rng([seed, _STREAM_NOISE]).normal(0.0, nz["v_meas_std"], n) if nz["v_meas_std"] > 0 else np.zeros(n)

    if not fine:
        tc = _disturbance(sc, v_ref, Ts, 1)
        v_true, v_ctrl, u, x, _, _ = closed_loop_zoh(v_ref, tc, noise, Ts, J, B, K, dp, dn, omega)
        v_rec = v_ctrl.copy()
        pos = x
    else:
        from scipy.signal import decimate

        n_sub = int(round(sc["fine_rate"] * Ts))
        if n_sub < 2:
            raise ValueError(f"fine_rate {sc['fine_rate']} Hz gives {n_sub} substeps per Ts; need ≥ 2")
        tc_fine = _disturbance(sc, v_ref, Ts, n_sub)
        noise_fine = (
            np.random.default_rng([seed, _STREAM_FINE]).normal(0.0, nz["v_meas_std"], n * n_sub)
            if nz["v_meas_std"] > 0 else np.zeros(n * n_sub)
        )
        v_true, v_ctrl, u, x, v_fine, x_fine = _loop_fine(
            v_ref, tc_fine, noise, noise_fine, Ts, n_sub, J, B, K, dp, dn, omega
        )
        v_rec = decimate(v_fine, n_sub, ftype="fir", zero_phase=True)[:n]
        pos = decimate(x_fine, n_sub, ftype="fir", zero_phase=True)[:n]
        tc = tc_fine.reshape(n, n_sub).mean(axis=1)

    # recording glitch: repeat the previous recorded value
    glitch = np.zeros(n, dtype=bool)
    if nz["glitch_rate"] > 0:
        glitch[1:] = np.random.default_rng([seed, _STREAM_GLITCH]).random(n - 1) < nz["glitch_rate"]
        for k in np.flatnonzero(glitch):
            v_rec[k] = v_rec[k - 1]

    beta = true_beta(sc)
    coulomb = bool(sc["model"]["coulomb"])
    f = force_to_disturbance(sc["form"], beta, tc, gain=K)
    d = sc["disturbance"]
    milling = d["kind"] == "milling"
    dyn = None
    if milling or d["kind"] == "shaker":
        dyn = 0.0 - tc  # the force on the table in the +axis direction (no negative zeros)
        if nz["dynamometer_std"] > 0:
            dyn = dyn + np.random.default_rng([seed, _STREAM_DYN]).normal(0.0, nz["dynamometer_std"], n)
    rpm = float(d["spindle_rpm"]) if milling and d.get("cutting", True) else (0.0 if milling else None)
    spindle = np.full(n, rpm) if rpm is not None else None

    physical = dict(dc)
    physical["force_constant"] = float(sc["drive"]["force_constant"])
    meta = S.TrialMeta(
        Ts=Ts,
        form=sc["form"],
        machine=sc["machine"],
        axis=sc["axis"],
        units=dict(S.UNITS),
        spindle_rpm=rpm,
        teeth=int(d["teeth"]) if milling else None,
        loop_gain=K,
        provenance=S.Provenance(
            source="simulated",
            tool="feedmon simulate",
            version=__version__,
            seed=int(seed),
            scenario=sc["name"],
            created=created,
            details={"fine": bool(fine), "path": "fine 10 kHz + AA decimation" if fine else "exact ZOH"},
        ),
        truth=S.TrialTruth(
            beta=[float(b) for b in beta],
            omega=omega,
            coulomb=coulomb,
            physical=physical,
            scenario=sc,
            beta_names=list(beta_names(sc["form"], coulomb)),
        ),
        description=sc["description"],
    )
    return SimResult(
        meta=meta, t=t, v_ref=v_ref, v_meas=v_rec, u=u, current=u / sc["drive"]["force_constant"],
        position=pos, spindle_rpm=spindle, force=tc, f=f, v_true=v_true, glitch=glitch,
        dynamometer=dyn, block=int(sc["block"]),
    )


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
             position=res.position, spindle_rpm=res.spindle_rpm),
        dict(t=res.t, force=res.force, f=res.f, dynamometer=res.dynamometer, v_true=res.v_true,
             glitch=res.glitch),
        block=int(block or res.block),
    )
