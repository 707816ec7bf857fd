"""Mechanistic milling force in the feed direction (Altintas, *Manufacturing Automation*, ch. 2).

Flat end mill, ``N_t`` teeth, spindle speed ``n(t)`` (rev/s), axial depth ``a`` (mm),
feed per tooth ``c = feed / (n(t)·N_t)`` (mm) from the programmed feed. Tooth ``j``
is at immersion angle ``φ_j = θ(t) + 2π j/N_t`` with the spindle angle
``θ(t) = θ0 + 2π ∫_0^t n dτ`` (``2π n t + θ0`` at constant speed; :class:`SpindleProfile`
for speed changes), measured from the +y axis, clockwise, feed along +x; it cuts while
``φ_st ≤ φ_j ≤ φ_ex`` (slotting: 0…π) with chip thickness

    h_j = max(0, (c + r_j − r_{j−1}) · sin φ_j),   r_j = ρ cos(λ − 2π j/N_t)

(radial runout ρ at angle λ: one tooth takes a thicker chip than the other, so the
spindle frequency appears beside the tooth-passing frequency). Tangential and
radial forces with cutting and edge coefficients,

    F_t = K_tc a h + K_te a,   F_r = K_rc a h + K_re a   (only while h > 0),

give the force on the tool in x: ``F_x = −F_t cos φ − F_r sin φ``. The force that
resists the feed motion of the table is ``−F_x`` (mean for a slot:
``N_t a c K_rc/4 + N_t a K_re/π``, growing with the feed rate).

Forces are evaluated at a fine angular step (default 0.5° of spindle rotation) and
averaged over each output interval — exactly what a force held over one sample
(ZOH) sees. No helix (flat-end, helix-free approximation), no tool deflection,
no regeneration.

Tooth condition (:class:`ToothCondition`, :func:`feed_force_teeth`): per-tooth radial
offsets ``r_j(t)`` (the ρ cos model above plus an offset per tooth that may grow linearly,
minus the radius a chipped or broken tooth lost) and a material factor on all four
coefficients. The chip of tooth j is cut from the surface the teeth before it left
(Kline & DeVor's runout model; the tooth before j is j + 1, which is 2π/N_t ahead),

    h_j = max(0, min_{k=1…N_t} (k c + r_j − r_{j+k})) · sin φ_j,

which is ``(c + r_j − r_{j+1}) sin φ`` while every tooth cuts; a tooth b that lost more
radius than its chip cuts nothing and the tooth after it, b − 1, takes ``2c + r_{b−1} − r_{b+1}``.
(:func:`feed_force` takes ``r_{j−1}``: the same tooth for the 2-tooth tools of the scenarios.)
The radii are taken at the current time for all teeth (quasi-static: the first
revolution after a step change is approximated).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

__all__ = ["MillingTool", "SpindleProfile", "ToothCondition", "feed_force", "feed_force_teeth", "tooth_chips",
           "mean_feed_force", "once_per_rev_amplitude"]


@dataclass(frozen=True)
class MillingTool:
    """Tool, cut and material constants (units: mm, N, rpm, degrees).

    Defaults: 16 mm 2-flute flat end mill, 3000 rpm, slotting 7050-T7451 aluminium
    at 1.5 mm depth; cutting coefficients of the order reported for 7050/7075 Al
    (K_tc ≈ 700–800 N/mm², K_rc ≈ 200–300 N/mm², K_te, K_re ≈ 20–30 N/mm).
    """

    spindle_rpm: float = 3000.0
    teeth: int = 2
    diameter: float = 16.0  # mm (documents the tool; forces do not depend on it without helix)
    depth: float = 1.5  # axial depth of cut a, mm
    Ktc: float = 750.0  # N/mm²
    Krc: float = 250.0  # N/mm²
    Kte: float = 25.0  # N/mm
    Kre: float = 25.0  # N/mm
    runout: float = 0.004  # radial runout ρ, mm
    runout_angle: float = 0.0  # λ, degrees
    start_angle: float = 0.0  # φ_st, degrees (slot: 0)
    exit_angle: float = 180.0  # φ_ex, degrees (slot: 180)
    phase: float = 0.0  # θ0, spindle angle at t = 0, degrees
    angle_step: float = 0.5  # degrees of spindle rotation per force evaluation

    def __post_init__(self):
        for name in ("spindle_rpm", "depth", "angle_step", "diameter"):
            if not getattr(self, name) > 0:
                raise ValueError(f"milling constant {name} must be > 0, got {getattr(self, name)!r}")
        if int(self.teeth) != self.teeth or self.teeth < 1:
            raise ValueError(f"milling constant teeth must be a positive integer, got {self.teeth!r}")
        for name in ("Ktc", "Krc", "Kte", "Kre", "runout"):
            if getattr(self, name) < 0:
                raise ValueError(f"milling constant {name} must be ≥ 0, got {getattr(self, name)!r}")
        if not 0.0 <= self.start_angle < self.exit_angle <= 360.0:
            raise ValueError("milling immersion needs 0 ≤ start_angle < exit_angle ≤ 360 degrees")

    @property
    def spindle_hz(self) -> float:
        return self.spindle_rpm / 60.0

    @property
    def tooth_hz(self) -> float:
        """Tooth-passing frequency (Hz)."""
        return self.spindle_hz * self.teeth

    def feed_per_tooth(self, feed) -> np.ndarray:
        """Feed per tooth c (mm) from the feed rate (m/s): ``c = feed / (n N_t)``."""
        return np.asarray(feed, dtype=np.float64) * 1e3 / (self.spindle_hz * self.teeth)

    def to_dict(self) -> dict:
        return asdict(self)


class SpindleProfile:
    """Spindle speed over time, piecewise linear in rpm, and its unwrapped angle.

    Built from an initial speed ``rpm0`` and a schedule of speed commands ``[(t_s, rpm), …]``
    (times in s, strictly increasing): from ``t_s`` the spindle moves to the commanded speed
    at the constant acceleration ``accel`` (rpm/s; 0 = an instantaneous step). A command that
    arrives while a ramp is still running starts from the speed reached. The angle is the
    exact integral of the speed,

        θ(t) = θ0 + (2π/60) ∫_0^t n(τ) dτ   (rad, n in rpm),

    so the tool's angle, hence the cutting force, is continuous through every change.
    Knots ``(t_i, n_i, θ_i)``; between knots ``n`` is linear and ``θ`` quadratic; before the
    first and after the last knot the speed is held.
    """

    def __init__(self, rpm0: float, schedule=(), *, accel: float = 0.0, phase: float = 0.0):
        if not (math.isfinite(rpm0) and rpm0 >= 0):
            raise ValueError(f"spindle speed must be a finite number ≥ 0 rpm, got {rpm0!r}")
        if not (math.isfinite(accel) and accel >= 0):
            raise ValueError(f"spindle acceleration must be a finite number ≥ 0 rpm/s, got {accel!r}")
        kt, kn = [0.0], [float(rpm0)]
        prev = -math.inf
        for t_s, rpm in schedule:
            t_s, rpm = float(t_s), float(rpm)
            if not (math.isfinite(t_s) and t_s >= 0 and t_s > prev):
                raise ValueError(f"spindle schedule times must be finite, ≥ 0 s and increasing; got {t_s!r} after {prev!r}")
            if not (math.isfinite(rpm) and rpm >= 0):
                raise ValueError(f"spindle schedule speeds must be finite numbers ≥ 0 rpm, got {rpm!r}")
            prev = t_s
            if t_s < kt[-1]:  # the previous ramp is still running at t_s: cut it there
                cur = float(np.interp(t_s, kt, kn))
                while kt[-1] > t_s:
                    kt.pop()
                    kn.pop()
                kt.append(t_s)
                kn.append(cur)
            else:
                cur = kn[-1]
                if t_s > kt[-1]:
                    kt.append(t_s)
                    kn.append(cur)
            if rpm != cur:  # ramp (or step, accel = 0) to the commanded speed
                kt.append(t_s + (abs(rpm - cur) / accel if accel > 0 else 0.0))
                kn.append(rpm)
        self.t = np.array(kt)
        self.rpm = np.array(kn)
        rev_s = self.rpm / 60.0
        self.theta = math.radians(phase) + np.concatenate(
            [[0.0], np.cumsum(2.0 * math.pi * 0.5 * (rev_s[1:] + rev_s[:-1]) * np.diff(self.t))]
        )

    @property
    def constant(self) -> bool:
        return self.t.size == 1

    @property
    def max_rpm(self) -> float:
        return float(self.rpm.max())

    def _segment(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        i = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, self.t.size - 1)
        tau = t - self.t[i]
        nxt = np.minimum(i + 1, self.t.size - 1)
        span = self.t[nxt] - self.t[i]
        slope = np.where((span > 0) & (tau >= 0), (self.rpm[nxt] - self.rpm[i]) / np.where(span > 0, span, 1.0), 0.0)
        return i, tau, slope  # before t = 0 the speed rpm0 is held

    def speed(self, t) -> np.ndarray:
        """Spindle speed n(t) (rpm)."""
        t = np.asarray(t, dtype=np.float64)
        i, tau, slope = self._segment(t)
        return self.rpm[i] + slope * tau

    def angle(self, t) -> np.ndarray:
        """Unwrapped spindle angle θ(t) (rad); θ0 = ``phase`` at t = 0."""
        t = np.asarray(t, dtype=np.float64)
        i, tau, slope = self._segment(t)
        return self.theta[i] + (2.0 * math.pi / 60.0) * (self.rpm[i] * tau + 0.5 * slope * tau * tau)


@njit(cache=True)
def _spindle_at(t, seg, kt, kn, kth):
    """(n, θ, seg) at time t ≥ the previous call's (knots ``kt, kn, kth`` of :class:`SpindleProfile`)."""
    last = kt.size - 1
    while seg < last and t >= kt[seg + 1]:
        seg += 1
    tau = t - kt[seg]
    slope = 0.0
    if seg < last and kt[seg + 1] > kt[seg] and tau >= 0.0:
        slope = (kn[seg + 1] - kn[seg]) / (kt[seg + 1] - kt[seg])
    rpm = kn[seg] + slope * tau
    theta = kth[seg] + (2.0 * math.pi / 60.0) * (kn[seg] * tau + 0.5 * slope * tau * tau)
    return rpm, theta, seg


@njit(cache=True)
def _feed_force(t0, dt, feed, engage, kt, kn, kth, rpm_max, teeth, a, Ktc, Krc, Kte, Kre, dr, phi_st, phi_ex, step):
    n = feed.size
    out = np.zeros(n)
    two_pi = 2.0 * math.pi
    rad_per_rev_min = two_pi / 60.0
    # sub-points per interval from the angular step at the highest speed
    m = int(math.ceil(two_pi * rpm_max / 60.0 * dt / step))
    if m < 1:
        m = 1
    pitch = two_pi / teeth
    last = kt.size - 1
    seg = np.int64(0)                           # not a literal 0: one compiled _spindle_at
    for k in range(n):
        if engage[k] == 0.0:
            continue
        t_start = t0 + k * dt
        while seg < last and t_start >= kt[seg + 1]:
            seg += 1
        # constant speed over the whole interval (the usual case): θ linear in t, one chip load
        steady = (seg == last or kt[seg + 1] >= t_start + dt) and (seg == last or kn[seg + 1] == kn[seg])
        rpm = kn[seg]
        ck = feed[k] * 1e3 / (rpm / 60.0 * teeth) if rpm > 0.0 else 0.0  # feed per tooth c = feed/(n N_t), mm
        acc = 0.0
        for i in range(m):
            t = t0 + (k + (i + 0.5) / m) * dt
            if steady:
                theta = kth[seg] + rad_per_rev_min * rpm * (t - kt[seg])
            else:
                rpm, theta, seg = _spindle_at(t, seg, kt, kn, kth)
                ck = feed[k] * 1e3 / (rpm / 60.0 * teeth) if rpm > 0.0 else 0.0
            if rpm <= 0.0:
                continue
            for j in range(teeth):
                phi = (theta + j * pitch) % two_pi
                if phi < phi_st or phi > phi_ex:
                    continue
                s = math.sin(phi)
                h = (ck + dr[j]) * s
                if h <= 0.0:
                    continue
                ft = Ktc * a * h + Kte * a
                fr = Krc * a * h + Kre * a
                acc += ft * math.cos(phi) + fr * s  # −F_x, the force resisting the feed
        out[k] = engage[k] * acc / m
    return out


def feed_force(tool: MillingTool, t0: float, dt: float, feed, engage=None, spindle: SpindleProfile | None = None) -> np.ndarray:
    """Feed-direction force resisting the motion (N), averaged over each interval.

    Interval ``k`` is ``[t0 + k dt, t0 + (k+1) dt]``; ``feed`` (m/s, ≥ 0, one value per
    interval) gives the feed per tooth ``c = feed/(n(t) N_t)`` at the spindle speed of each
    force evaluation; ``engage`` (0…1 per interval, default 1) scales the force (radial
    immersion growing at the workpiece entry, 0 = not cutting). ``spindle`` gives the speed
    and angle over time (default: constant ``tool.spindle_rpm`` from angle ``tool.phase``);
    the tooth angles follow its integrated angle, so tooth passing and runout follow every
    speed change without a jump.
    """
    feed = np.maximum(np.asarray(feed, dtype=np.float64), 0.0)
    eng = np.ones_like(feed) if engage is None else np.asarray(engage, dtype=np.float64)
    if eng.shape != feed.shape:
        raise ValueError(f"engage has {eng.size} values, feed has {feed.size}")
    sp = SpindleProfile(tool.spindle_rpm, phase=tool.phase) if spindle is None else spindle
    teeth = int(tool.teeth)
    lam = math.radians(tool.runout_angle)
    r = np.array([tool.runout * math.cos(lam - 2 * math.pi * j / teeth) for j in range(teeth)])
    dr = r - np.roll(r, 1)  # r_j − r_{j−1}
    return _feed_force(
        float(t0), float(dt), feed, eng, sp.t, sp.rpm, sp.theta, sp.max_rpm, teeth, tool.depth,
        tool.Ktc, tool.Krc, tool.Kte, tool.Kre, dr,
        math.radians(tool.start_angle), math.radians(tool.exit_angle), math.radians(tool.angle_step),
    )


def mean_feed_force(tool: MillingTool, feed: float) -> float:
    """Closed-form mean slotting force resisting the feed (N) without runout: ``N a c K_rc/4 + N a K_re/π``."""
    c = float(tool.feed_per_tooth(feed))
    return tool.teeth * tool.depth * (c * tool.Krc / 4.0 + tool.Kre / math.pi)


# ---------------------------------------------------------------------------------------------
# tooth condition: per-tooth runout that grows, chipped / broken teeth, material
# ---------------------------------------------------------------------------------------------
#: most teeth a tool may have in the per-tooth model (indexable face mills go to ~20)
MAX_TEETH = 64


@dataclass(frozen=True)
class ToothCondition:
    """What happens to the teeth of a :class:`MillingTool` during a cut (SI: m, s).

    ``offsets_m`` radial offset per tooth added to the tool's ρ cos(λ − 2πj/N_t) runout
    (m; empty = none); ``growth_m_per_s`` their growth rate per tooth (m/s) from
    ``growth_from_s`` on, ``r_j(t) = r_j + e_j + g_j·max(0, t − t_g)``; ``breaks`` tuples
    ``(tooth, t_s, loss_m)``: from ``t_s`` tooth ``tooth`` is ``loss_m`` shorter (chipped;
    more than its chip: broken, it cuts nothing); ``material`` multiplies K_tc, K_rc, K_te,
    K_re (harder stock > 1; tool wear too).
    """

    offsets_m: tuple = ()
    growth_m_per_s: tuple = ()
    growth_from_s: float = 0.0
    breaks: tuple = ()
    material: float = 1.0

    def check(self, teeth: int) -> None:
        """ValueError naming the constant when it does not fit a tool of ``teeth`` teeth."""
        if not 1 <= teeth <= MAX_TEETH:
            raise ValueError(f"the per-tooth model takes 1 … {MAX_TEETH} teeth, got {teeth}")
        for name in ("offsets_m", "growth_m_per_s"):
            values = getattr(self, name)
            if len(values) not in (0, teeth) or not all(math.isfinite(x) and abs(x) <= 1e-3 for x in values):
                raise ValueError(f"{name} needs one value per tooth ({teeth}), each within ±1e-3 "
                                 f"({'m' if name == 'offsets_m' else 'm/s'}), got {list(values)!r}")
        if not (math.isfinite(self.growth_from_s) and self.growth_from_s >= 0):
            raise ValueError(f"growth_from_s must be a finite time ≥ 0 s, got {self.growth_from_s!r}")
        if not (math.isfinite(self.material) and 0.1 <= self.material <= 10.0):
            raise ValueError(f"material factor must be in [0.1, 10], got {self.material!r}")
        for item in self.breaks:
            tooth, t_s, loss = item
            if int(tooth) != tooth or not 0 <= tooth < teeth:
                raise ValueError(f"breaks: tooth {tooth!r} is not one of the tool's teeth 0 … {teeth - 1}")
            if not (math.isfinite(t_s) and t_s >= 0 and math.isfinite(loss) and 0 < loss <= 0.01):
                raise ValueError(f"breaks: ({tooth}, {t_s!r} s, {loss!r} m) needs a time ≥ 0 s and a loss in (0, 0.01] m")

    def arrays(self, tool: MillingTool):
        """Kernel inputs in the tool's units (mm): base radius r_j, growth (mm/s), break times
        (s, +inf: never) and losses (mm) per tooth, and the coefficients × material."""
        teeth = int(tool.teeth)
        self.check(teeth)
        lam = math.radians(tool.runout_angle)
        r = np.array([tool.runout * math.cos(lam - 2 * math.pi * j / teeth) for j in range(teeth)])
        if self.offsets_m:
            r = r + 1e3 * np.asarray(self.offsets_m, dtype=np.float64)
        g = 1e3 * np.asarray(self.growth_m_per_s, dtype=np.float64) if self.growth_m_per_s else np.zeros(teeth)
        t_break = np.full(teeth, np.inf)
        loss = np.zeros(teeth)
        for tooth, t_s, loss_m in sorted(self.breaks, key=lambda b: b[1]):
            t_break[int(tooth)] = min(t_break[int(tooth)], float(t_s))
            loss[int(tooth)] += 1e3 * float(loss_m)  # two events on one tooth: the losses add (at the first time)
        k = float(self.material)
        return r, g, t_break, loss, (tool.Ktc * k, tool.Krc * k, tool.Kte * k, tool.Kre * k)


@njit(cache=True)
def _chips(c, r, g, t, t_g, t_break, loss, out):
    """Effective chip factors ``max(0, min_k (k c + r_j − r_{j+k}))`` (mm) of every tooth at time t
    into ``out`` (the sin φ comes later)."""
    teeth = r.size
    grow = t - t_g if t > t_g else 0.0
    for j in range(teeth):
        rj = r[j] + g[j] * grow - (loss[j] if t >= t_break[j] else 0.0)
        best = 1e300
        for k in range(1, teeth + 1):
            i = (j + k) % teeth  # the tooth k pitches ahead cut this spot k·(pitch time) earlier
            ri = r[i] + g[i] * grow - (loss[i] if t >= t_break[i] else 0.0)
            v = k * c + rj - ri
            if v < best:
                best = v
        out[j] = best if best > 0.0 else 0.0


@njit(cache=True)
def _feed_force_teeth(t0, dt, feed, engage, kt, kn, kth, rpm_max, a, Ktc, Krc, Kte, Kre, r, g, t_g, t_break, loss,
                      phi_st, phi_ex, step):
    n = feed.size
    teeth = r.size
    out = np.zeros(n)
    per = np.zeros((n, teeth))
    chip = np.zeros(teeth)
    acc = np.zeros(teeth)
    two_pi = 2.0 * math.pi
    m = int(math.ceil(two_pi * rpm_max / 60.0 * dt / step))
    if m < 1:
        m = 1
    pitch = two_pi / teeth
    seg = 0
    for k in range(n):
        if engage[k] == 0.0:
            continue
        acc[:] = 0.0
        for i in range(m):
            t = t0 + (k + (i + 0.5) / m) * dt
            rpm, theta, seg = _spindle_at(t, seg, kt, kn, kth)
            if rpm <= 0.0:
                continue
            c = feed[k] * 1e3 / (rpm / 60.0 * teeth)  # feed per tooth, mm
            _chips(c, r, g, t, t_g, t_break, loss, chip)
            for j in range(teeth):
                phi = (theta + j * pitch) % two_pi
                if phi < phi_st or phi > phi_ex:
                    continue
                s = math.sin(phi)
                h = chip[j] * s
                if h <= 0.0:
                    continue
                acc[j] += (Ktc * a * h + Kte * a) * math.cos(phi) + (Krc * a * h + Kre * a) * s
        total = 0.0
        for j in range(teeth):
            per[k, j] = engage[k] * acc[j] / m
            total += acc[j]
        out[k] = engage[k] * total / m
    return out, per


def feed_force_teeth(tool: MillingTool, t0: float, dt: float, feed, engage=None, spindle: SpindleProfile | None = None,
                     condition: ToothCondition | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`feed_force` with a :class:`ToothCondition`: the force resisting the feed (N) per
    interval and each tooth's share of it, shape ``(n, N_t)`` (rows sum to the force)."""
    feed = np.maximum(np.asarray(feed, dtype=np.float64), 0.0)
    eng = np.ones_like(feed) if engage is None else np.asarray(engage, dtype=np.float64)
    if eng.shape != feed.shape:
        raise ValueError(f"engage has {eng.size} values, feed has {feed.size}")
    sp = SpindleProfile(tool.spindle_rpm, phase=tool.phase) if spindle is None else spindle
    r, g, t_break, loss, (Ktc, Krc, Kte, Kre) = (condition or ToothCondition()).arrays(tool)
    return _feed_force_teeth(
        float(t0), float(dt), feed, eng, sp.t, sp.rpm, sp.theta, sp.max_rpm, tool.depth, Ktc, Krc, Kte, Kre,
        r, g, float((condition or ToothCondition()).growth_from_s), t_break, loss,
        math.radians(tool.start_angle), math.radians(tool.exit_angle), math.radians(tool.angle_step),
    )


def tooth_chips(tool: MillingTool, condition: ToothCondition, c: float, t: float) -> np.ndarray:
    """Effective chip ``max(0, min_k (k c + r_j − r_{j+k}))`` (mm) of every tooth at time t (s)
    for the feed per tooth c (mm): what each tooth cuts, before the sin φ."""
    r, g, t_break, loss, _ = condition.arrays(tool)
    out = np.zeros(r.size)
    _chips(float(c), r, g, float(t), float(condition.growth_from_s), t_break, loss, out)
    return out


def once_per_rev_amplitude(tool: MillingTool, chip_difference: float) -> float:
    """Amplitude (N) of the spindle-frequency line of the slotting force resisting the feed of a
    2-tooth tool whose teeth cut chips ``c ± Δc/2`` (``chip_difference`` = Δc, mm):

        X_1 = (a Δc / 2π) ∫_0^π (K_tc sin φ cos φ + K_rc sin² φ) e^{−iφ} dφ,   2|X_1| = (2 a Δc / 3π) √(K_tc² + 4 K_rc²)

    (the edge forces are alike for both teeth and only feed the tooth-passing harmonics).
    With runout ρ at λ = 0: Δc = 2 (r_0 − r_1) = 4ρ."""
    if tool.teeth != 2 or tool.start_angle != 0.0 or tool.exit_angle != 180.0:
        raise ValueError("the closed form is for a 2-tooth tool slotting (0 … 180 degrees)")
    return 2.0 * tool.depth * abs(chip_difference) / (3.0 * math.pi) * math.hypot(tool.Ktc, 2.0 * tool.Krc)
