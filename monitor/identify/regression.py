"""The regression all candidates share: the dead band from the measurement noise, the friction columns,
and — where a process acts — the columns that keep its mean force out of friction and offset
(docs/method.md §8, "Friction", "Noise and dead band", "A process's mean force").

Steps (:func:`build_regression`):

1. a first dead band from the velocity's second differences (:func:`dead_band`), the friction
   columns, least squares;
2. the measurement noise in that residual (:func:`kernels.noise.white_noise`, with the LS pole), and
   the dead band from it: ``Ω = max(3 σ_n, 0.5 % of max|v|)`` — a disturbance does not widen it; the
   friction columns again when Ω moved;
3. where a process acts (:func:`kernels.process.process_mask` on the LS residual; a spindle at rest
   is no cut): when the axis also moves without it long enough, the columns ``p``, ``p·v_m`` (and
   ``−p·τ`` with the Coulomb columns), ``p`` = 1 where the process acts, take the process's mean force
   and the part of it that follows the feed or the direction of motion; friction, damping and offset
   are then those of the process-free motion. They are nuisance parameters: not part of β.
   Without enough process-free motion the mean force cannot be told from friction and offset: said
   so, and the model file records ``offset_separated = false``;
4. the friction near standstill (:mod:`kernels.low_speed`): the speed above which the friction law
   holds, chosen from the data (eq. LS3). When the friction *rises* above the law below it (a Stribeck
   rise), the samples below it are left out of the batch fit — the hump meets the peak acceleration of
   every slow reversal and bends J, B and Fc (simulated Stribeck drive: damping −16 %). A departure
   *below* the law (a gradual onset, presliding: the real EMPS drive) bends them little, and the
   published EMPS values are fitted on those samples: they stay in, and the departure is reported.
   Either way the monitor learns β only above ``min_speed``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from kernels.errors import ParameterError
from kernels.feed_drive import friction_transform, regressors, rest_samples
from kernels.low_speed import LowSpeedCut, LowSpeedFriction, law_holds_above, low_speed_friction
from kernels.noise import NoiseEstimate, white_noise
from kernels.process import ProcessMask, process_mask

from ..model_file import OMEGA_MAX
from .candidates import MIN_REST_SAMPLES, MIN_REVERSAL_SAMPLES

__all__ = ["Regression", "build_regression", "dead_band", "NOISE_FACTOR", "FLOOR_SHARE", "MIN_SPLIT_SECONDS",
           "NUISANCE"]

#: the dead band is this many times the measurement noise σ_n …
NOISE_FACTOR = 3.0
#: … and at least this share of the peak speed (a smooth filtered velocity has next to no noise, yet its
#: samples at rest must fall inside the band)
FLOOR_SHARE = 0.005
#: the process must act, and the axis move without it, at least this long (s; and 50 samples) for the
#: process's mean force to be separated from friction and offset
MIN_SPLIT_SECONDS = 0.25
MIN_SPLIT_SAMPLES = 50
#: names of the nuisance columns (p: 1 where the process acts)
NUISANCE = ("process", "process*v_meas", "process*-tau")


def dead_band(v_meas: np.ndarray) -> float:
    """A first Coulomb dead band Ω (m/s), before any model: the larger of 3× the velocity noise from second
    differences, ``σ ≈ 1.4826·MAD(Δ²v)/√6`` (white noise: Var Δ²v = 6σ²), and 0.5 % of the peak speed.
    A disturbance in the velocity inflates that noise; :func:`build_regression` replaces it by the noise of
    the model's residual."""
    v = np.asarray(v_meas, dtype=np.float64)
    d2 = np.diff(v, 2)
    if d2.size == 0:
        return 0.0
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return max(NOISE_FACTOR * 1.4826 * mad / math.sqrt(6.0), FLOOR_SHARE * float(np.max(np.abs(v))))


@dataclass
class Regression:
    """The regression of one trial (``Z_id θ``, ``β = T θ``; the nuisance entries of θ map to no β)."""

    names: tuple[str, ...]  # spec β names (model file)
    T: np.ndarray  # (len(names), len(id_names))
    Z_id: np.ndarray
    id_names: tuple[str, ...]
    y: np.ndarray
    Z_spec: np.ndarray  # the spec regressors z(k) (the monitor's)
    omega: float
    coulomb: bool
    coulomb_note: str
    rest: bool
    noise: NoiseEstimate | None
    process: ProcessMask | None
    nuisance: tuple[str, ...] = ()
    offset_separated: bool | None = None
    offset_note: str = ""
    ls_theta: np.ndarray | None = None
    low_speed: LowSpeedFriction | None = None  # the strongest departure from the law near standstill (LS1, LS2)
    cut: LowSpeedCut | None = None  # the speed above which the law holds (LS3), None: down to the dead band
    keep: np.ndarray | None = None  # the samples in the batch fit (None: all); a Stribeck rise is left out
    delay: int = 0  # samples from a command to its force (kernels.feed_drive.regressors)

    @property
    def min_speed(self) -> float:
        """The speed (m/s) below which the friction departs from the law: the monitor learns β above it."""
        speed = self.low_speed.min_speed if self.low_speed is not None else 0.0
        return max(speed, self.cut.speed if self.cut is not None and self.cut.rise else 0.0)

    @property
    def pole(self) -> float:
        return float(self.noise.pole) if self.noise is not None else math.nan


def _friction_columns(v: np.ndarray, Ts: float, omega_used: float, coulomb: bool | None) -> tuple[bool, str, bool]:
    """Whether the Coulomb columns are kept (``coulomb``, or when the trial reverses direction beyond ±Ω),
    the note saying why, and whether the trial rests (the Coulomb asymmetry can then be told from the
    offset: :func:`kernels.feed_drive.friction_transform`)."""
    n_pos = int(np.sum(v[:-1] > omega_used))
    n_neg = int(np.sum(v[:-1] < -omega_used))
    reversal = n_pos >= MIN_REVERSAL_SAMPLES and n_neg >= MIN_REVERSAL_SAMPLES
    if coulomb is None:
        coulomb_used = reversal
        coulomb_note = ("Coulomb columns kept (trial reverses direction)" if reversal else
                        f"Coulomb columns dropped: no speed reversal ({n_pos} samples above +Ω, {n_neg} below −Ω); "
                        "the constant column holds the friction of the direction of motion")
    else:
        coulomb_used = bool(coulomb)
        coulomb_note = "Coulomb columns " + ("kept" if coulomb_used else "dropped") + " as requested"
        if coulomb_used and not reversal:
            empty = "-sigma_n" if n_neg < MIN_REVERSAL_SAMPLES else "-sigma_p"
            raise ParameterError(f"coulomb=True: the trial has no speed reversal ({n_pos} samples above +Ω, {n_neg} "
                                 f"below −Ω), so the Coulomb column {empty!r} cannot be identified; use coulomb=False "
                                 "(or None: identify chooses) or record a trial with reversals", "coulomb")
    rest = coulomb_used and rest_samples(v[:-1], omega_used, Ts) >= MIN_REST_SAMPLES
    return coulomb_used, coulomb_note, rest


def _least_squares(form, v, exo, omega, coulomb, rest, Ts, delay):
    """The spec regression, its identifiable form and the LS residual, pole and noise (steps 1–2)."""
    kw = {"v_ref": exo} if form == "velocity-loop" else {"u": exo}
    reg = regressors(form, v, omega=omega, coulomb=coulomb, intercept=True, delay=delay, **kw)
    T, id_names = friction_transform(reg.names, rest)
    Z_id = reg.Z @ T
    theta = np.linalg.lstsq(Z_id, reg.y, rcond=None)[0]
    beta = T @ theta
    resid = reg.y - Z_id @ theta
    pole = float(beta[0] + beta[1]) if form == "velocity-loop" else float(beta[1])
    try:
        noise = white_noise(resid, pole=min(max(pole, -0.999), 1.0))
    except ParameterError:  # too short a record, or nothing but lines: no noise level to go by
        noise = None
    return reg, T, Z_id, id_names, theta, resid, noise


def build_regression(form: str, v: np.ndarray, exo: np.ndarray, Ts: float, *, omega: float | None,
                     coulomb: bool | None, spindle_rpm: np.ndarray | None, notes: list[str],
                     delay: int = 0) -> Regression:
    """Steps 1–4 of the module docstring. ``omega``/``coulomb`` given by the user are kept; ``delay``: the
    command acts that many samples late (:func:`kernels.feed_drive.regressors`; the first ``delay`` samples,
    which have no such past, are left out of the fit)."""
    omega_used = dead_band(v) if omega is None else float(omega)
    if not (math.isfinite(omega_used) and 0 <= omega_used <= OMEGA_MAX):
        raise ParameterError(f"omega must be a dead band 0 … {OMEGA_MAX:g} m/s, got {omega!r}", "omega")
    coulomb_used, coulomb_note, rest = _friction_columns(v, Ts, omega_used, coulomb)
    reg, T, Z_id, id_names, theta, resid, noise = _least_squares(form, v, exo, omega_used, coulomb_used, rest, Ts, delay)
    if omega is None and noise is not None:
        better = max(NOISE_FACTOR * noise.sigma_n, FLOOR_SHARE * float(np.max(np.abs(v))))
        if better <= OMEGA_MAX and not math.isclose(better, omega_used, rel_tol=1e-9):
            omega_used = better
            coulomb_used, coulomb_note, rest = _friction_columns(v, Ts, omega_used, coulomb)
            reg, T, Z_id, id_names, theta, resid, noise = _least_squares(form, v, exo, omega_used, coulomb_used,
                                                                         rest, Ts, delay)
    if not coulomb_used and coulomb is None:
        notes.append(coulomb_note)
    if coulomb_used and not rest:
        notes.append("the trial has no rest (only passes through ±Ω during reversals): the Coulomb asymmetry "
                     "cannot be told from the force offset — coulomb_pos = coulomb_neg = the symmetric Coulomb "
                     "friction, and offset holds asymmetry + offset")
    out = Regression(names=reg.names, T=T, Z_id=Z_id, id_names=id_names, y=reg.y, Z_spec=reg.Z, omega=omega_used,
                     coulomb=coulomb_used, coulomb_note=coulomb_note, rest=rest, noise=noise, process=None,
                     ls_theta=theta)
    out.delay = int(delay)
    if noise is not None:
        _separate_process(out, v, resid, Ts, spindle_rpm, notes)
    _low_speed(out, v)
    if delay:
        keep = np.ones(out.y.size, dtype=bool) if out.keep is None else out.keep
        keep[:delay] = False
        out.keep = keep
    return out


def _add_nuisance(reg: Regression, cols: list[np.ndarray], names: list[str]) -> None:
    reg.Z_id = np.column_stack([reg.Z_id, *cols])
    reg.id_names = reg.id_names + tuple(names)
    reg.T = np.column_stack([reg.T, np.zeros((reg.T.shape[0], len(cols)))])
    reg.nuisance = reg.nuisance + tuple(names)


def _low_speed(reg: Regression, v: np.ndarray) -> None:
    """Step 4: the low-speed check on the LS residual (process columns in) and the speed above which the law
    holds; the samples of a Stribeck rise below it left out of the fit."""
    theta = np.linalg.lstsq(reg.Z_id, reg.y, rcond=None)[0]
    err = reg.y - reg.Z_id @ theta
    reg.low_speed = low_speed_friction(reg.Z_id, err, v[:-1], reg.omega)
    if reg.low_speed is None or not reg.low_speed.significant:
        return
    reg.cut = law_holds_above(reg.Z_id, reg.y, v[:-1], reg.omega)
    if reg.cut is not None and reg.cut.rise:
        reg.keep = ~((np.abs(v[:-1]) > reg.omega) & (np.abs(v[:-1]) < reg.cut.speed))


def _separate_process(reg: Regression, v: np.ndarray, resid: np.ndarray, Ts: float, spindle_rpm, notes) -> None:
    """Step 3: the process mask, and the nuisance columns when the process-free motion can carry friction and
    offset (``reg`` is extended in place)."""
    idle = None
    if spindle_rpm is not None:
        rpm = np.asarray(spindle_rpm[:-1], dtype=np.float64)
        idle = np.isfinite(rpm) & (rpm == 0.0)  # a spindle at rest cuts nothing
    mask = process_mask(resid, reg.noise.sigma_n, reg.noise.pole, Ts, idle=idle)
    reg.process = mask
    moving = np.abs(v[:-1]) > reg.omega
    free, acting = mask.counts(moving)
    need = max(MIN_SPLIT_SAMPLES, int(math.ceil(MIN_SPLIT_SECONDS / Ts)))
    if acting < need:
        reg.offset_separated = True
        reg.offset_note = "no process force found in the residual: friction and offset are the drive's"
        return
    share = f"a process acts in {100 * acting / max(free + acting, 1):.0f} % of the motion"
    if free < need:
        reg.offset_separated = False
        reg.offset_note = (f"{share}, and the axis moves without it for only {free * Ts:.2g} s: the process's mean "
                           "force cannot be told from friction and offset (an axis that never moves without it: a "
                           "constant force along the feed looks like Coulomb friction), so they hold it — record "
                           f"motion without the process (≥ {MIN_SPLIT_SECONDS:g} s, e.g. an air cut before the cut) "
                           "to separate them")
        notes.append(reg.offset_note)
        return
    p = mask.active.astype(np.float64)
    cols = [p, p * v[:-1]]
    names = list(NUISANCE[:2])
    if reg.coulomb:
        cols.append(p * reg.Z_id[:, reg.id_names.index("-tau")])
        names.append(NUISANCE[2])
    _add_nuisance(reg, cols, names)
    reg.offset_separated = True
    reg.offset_note = (f"{share}; its mean force (and the part that follows the feed"
                       + (" and the direction" if reg.coulomb else "") + f") is kept apart: friction, damping and "
                       f"offset are those of the {free * Ts:.3g} s of motion without it")
    notes.append(reg.offset_note)
