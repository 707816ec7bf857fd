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
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

__all__ = ["MillingTool", "SpindleProfile", "feed_force", "mean_feed_force"]


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
    seg = 0
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
