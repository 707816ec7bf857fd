"""Drives that the rigid first-order model of method §1 does not describe: a test of identification's
honesty (scenario table ``[structure]`` and the Stribeck keys of ``[drive]``).

* **Stribeck friction**: ``T_f(v) = sign(v)·(F_c + F_s·exp(−(v/v_s)²))`` (``stribeck_force`` F_s over the
  Coulomb level F_c, fading with ``stribeck_speed`` v_s), on the true velocity, 0 inside the dead band.
* **Two-mass drive** (``kind = "two-mass"``): motor (J_m) and load (J_l = J − J_m) joined by a spring
  and a damper; the velocity loop measures and drives the motor, the disturbance force acts on the
  load, the damping B splits between them by their inertias::

      J_m v̇_m = F_m − k δ − c (v_m − v_l) − B_m v_m       F_m = u − T_f(v_m)
      J_l v̇_l = k δ + c (v_m − v_l) − B_l v_l − T_c       δ̇ = v_m − v_l,  ẋ_m = v_m

  with ``k = ω_r² J_m J_l / J``, ``c = 2 ζ ω_r J_m J_l / J`` (resonance ω_r = 2π·``resonance``, damping
  ratio ζ). ``F_m`` and ``T_c`` are held over each sample (ZOH), the friction evaluated at the sample
  instant: the exact discretisation ``s(k+1) = Φ s(k) + Γ_m F_m(k) + Γ_l T_c(k)`` (matrix exponential).
  Rigid (``kind = "rigid"``): ``s = [v, x]``, the plant of :func:`replay.simulator.closed_loop_zoh`.
* **Command delay** (``delay`` samples): the force asked for at sample k acts over
  ``[t_{k+delay}, t_{k+delay+1})`` (the model has it over ``[t_k, t_{k+1})``).
* **Encoder velocity** (``velocity = "encoder"``): the velocity the controller and the recorder see is
  the backward difference of the position quantised to ``encoder_resolution``, ``(q(x_k) − q(x_{k−1}))/Ts``
  (plus the white ``v_meas_std``): an average over the last interval, half a sample late.

The true β written with such a trial is the rigid equivalent's (J = J_m + J_l, B, the Coulomb level):
what an adequate identification of the rigid part should find — and what it should say it cannot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.linalg import expm

__all__ = ["Structure", "structure_of", "discretise", "closed_loop_radius", "structured_loop", "friction", "STRUCTURE_KINDS",
           "VELOCITY"]

STRUCTURE_KINDS = ("rigid", "two-mass")
VELOCITY = ("sensor", "encoder")


@dataclass(frozen=True)
class Structure:
    """The scenario's ``[structure]`` and Stribeck constants (SI)."""

    kind: str = "rigid"
    resonance: float = 50.0  # Hz
    resonance_damping: float = 0.05
    motor_share: float = 0.5
    delay: int = 0  # samples
    velocity: str = "sensor"
    encoder_resolution: float = 1e-8  # m
    stribeck_force: float = 0.0  # N
    stribeck_speed: float = 0.002  # m/s

    @property
    def rigid_model(self) -> bool:
        """True when the drive is the rigid first-order model of method §1 (the fast exact path)."""
        return (self.kind == "rigid" and self.delay == 0 and self.velocity == "sensor"
                and self.stribeck_force == 0.0)

    def describe(self) -> list[str]:
        out = []
        if self.kind == "two-mass":
            out.append(f"two-mass drive, resonance {self.resonance:g} Hz (ζ = {self.resonance_damping:g}), velocity "
                       f"measured at the motor ({100 * self.motor_share:.0f} % of the inertia)")
        if self.delay:
            out.append(f"the force acts {self.delay} sample(s) after it is commanded")
        if self.velocity == "encoder":
            out.append(f"velocity = backward difference of the encoder position ({self.encoder_resolution:g} m)")
        if self.stribeck_force:
            out.append(f"Stribeck friction: +{self.stribeck_force:g} N at standstill, fading over "
                       f"{self.stribeck_speed:g} m/s")
        return out


def structure_of(sc: dict) -> Structure:
    """The :class:`Structure` of a scenario dict (validated by :func:`replay.scenarios.check`)."""
    st = sc["structure"]
    d = sc["drive"]
    return Structure(kind=st["kind"], resonance=float(st["resonance"]), resonance_damping=float(st["resonance_damping"]),
                     motor_share=float(st["motor_share"]), delay=int(st["delay"]), velocity=st["velocity"],
                     encoder_resolution=float(st["encoder_resolution"]), stribeck_force=float(d["stribeck_force"]),
                     stribeck_speed=float(d["stribeck_speed"]))


def discretise(st: Structure, Ts: float, J: float, B: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Exact ZOH ``(Φ, Γ_m, Γ_l, n_states)`` of the plant; state ``[v_m, x_m]`` (rigid) or ``[v_m, v_l, δ, x_m]``;
    ``Γ_m`` for the motor force held, ``Γ_l`` for the disturbance force (its sign: it opposes motion)."""
    if st.kind == "rigid":
        A = np.array([[-B / J, 0.0], [1.0, 0.0]])
        G = np.array([[1.0 / J, -1.0 / J], [0.0, 0.0]])
    else:
        Jm = st.motor_share * J
        Jl = J - Jm
        w = 2.0 * math.pi * st.resonance
        k = w * w * Jm * Jl / J
        c = 2.0 * st.resonance_damping * w * Jm * Jl / J
        Bm, Bl = st.motor_share * B, (1.0 - st.motor_share) * B
        A = np.array([[-(c + Bm) / Jm, c / Jm, -k / Jm, 0.0],
                      [c / Jl, -(c + Bl) / Jl, k / Jl, 0.0],
                      [1.0, -1.0, 0.0, 0.0],
                      [1.0, 0.0, 0.0, 0.0]])
        G = np.array([[1.0 / Jm, 0.0], [0.0, -1.0 / Jl], [0.0, 0.0], [0.0, 0.0]])
    n = A.shape[0]
    M = np.zeros((n + 2, n + 2))
    M[:n, :n] = A * Ts
    M[:n, n:] = G * Ts
    E = expm(M)
    return E[:n, :n].copy(), E[:n, n].copy(), E[:n, n + 1].copy(), n


def closed_loop_radius(st: Structure, Ts: float, J: float, B: float, K: float) -> float:
    """Spectral radius of the linear closed loop ``u(k) = K (v_r − v_m(k))`` (friction off); ≥ 1: unstable.
    States: the plant's without the position (an integrator the loop does not see), the last position step
    when the velocity is the encoder's difference, the delay's held commands."""
    Phi, Gm, _, n = discretise(st, Ts, J, B)
    p = n - 1  # the position is the last state
    enc = st.velocity == "encoder"
    d = st.delay
    size = p + int(enc) + d
    M = np.zeros((size, size))
    gain = np.zeros(size)  # F(k) = gain · state when d = 0: the command from the measured velocity
    gain[p if enc else 0] = -K / Ts if enc else -K
    force = np.zeros(size) if d else gain  # the force acting now: the oldest held command, or the new one
    if d:
        force[p + int(enc)] = 1.0
    M[:p, :p] = Phi[:p, :p]
    M[:p] += np.outer(Gm[:p], force)
    if enc:  # d(k+1) = x(k+1) − x(k) = Φ[x, :p] s + Γ_m[x] F
        M[p, :p] = Phi[p, :p]
        M[p] += Gm[p] * force
    for j in range(d - 1):
        M[p + int(enc) + j, p + int(enc) + j + 1] = 1.0  # the queue moves on
    if d:
        M[size - 1] = gain  # the newest command joins the queue
    return float(np.max(np.abs(np.linalg.eigvals(M))))


@njit(cache=True)
def friction(v, omega, dp, dn, fs, vs):
    """The friction force (N, opposing motion) at velocity ``v``: Coulomb ``dp``/``dn`` beyond the dead band
    ``omega``, plus the Stribeck rise ``fs·exp(−(v/vs)²)`` (``fs = 0``: none); 0 inside the band. The one
    friction law of the simulated plants (:mod:`replay.simulator`)."""
    if v > omega:
        return dp + fs * math.exp(-(v / vs) ** 2) if fs != 0.0 else dp
    if v < -omega:
        return -(dn + fs * math.exp(-(v / vs) ** 2)) if fs != 0.0 else -dn
    return 0.0


def structured_loop(st: Structure, v_ref, tc, noise, Ts: float, J: float, B: float, K: float, dp: float, dn: float,
                    omega: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``v_true, v_meas, u, x`` per sample of the closed loop of a structured plant (module docstring): the
    velocity loop ``u = K (v_r − v_m)`` on the measured (motor) velocity, the force ``u − T_f`` held after
    ``delay`` samples, ``tc`` the disturbance force (N) on the load."""
    Phi, Gm, Gl, n = discretise(st, Ts, J, B)
    enc = st.encoder_resolution if st.velocity == "encoder" else 0.0
    return _loop_ts(np.ascontiguousarray(v_ref, dtype=np.float64), np.ascontiguousarray(tc, dtype=np.float64),
                    np.ascontiguousarray(noise, dtype=np.float64), Phi, Gm, Gl, float(K), float(dp), float(dn),
                    float(st.stribeck_force), float(st.stribeck_speed), float(omega), int(st.delay), float(enc), n,
                    float(Ts))


@njit(cache=True)
def _loop_ts(v_ref, tc, noise, Phi, Gm, Gl, K, dp, dn, fs, vs, omega, delay, enc, n_states, Ts):
    n = v_ref.size
    s = np.zeros(n_states)
    pos_i = n_states - 1
    v_true = np.empty(n)
    v_meas = np.empty(n)
    u_out = np.empty(n)
    x_out = np.empty(n)
    queue = np.zeros(max(delay, 1))
    q_prev = 0.0
    for k in range(n):
        v = s[0]
        x = s[pos_i]
        if enc > 0.0:
            q = enc * math.floor(x / enc + 0.5)
            vm = ((q - q_prev) / Ts if k > 0 else 0.0) + noise[k]
            q_prev = q
        else:
            vm = v + noise[k]
        uk = K * (v_ref[k] - vm)
        if delay > 0:
            applied = queue[0]
            for j in range(delay - 1):
                queue[j] = queue[j + 1]
            queue[delay - 1] = uk
        else:
            applied = uk
        tf = friction(v, omega, dp, dn, fs, vs)
        v_true[k] = v
        v_meas[k] = vm
        u_out[k] = uk
        x_out[k] = x
        s = Phi @ s + Gm * (applied - tf) + Gl * tc[k]
    return v_true, v_meas, u_out, x_out
