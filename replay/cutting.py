"""Mechanistic milling force in the feed direction (Altintas, *Manufacturing Automation*, ch. 2).

Flat end mill, ``N_t`` teeth, spindle speed ``n`` (rev/s), axial depth ``a`` (mm),
feed per tooth ``c = feed / (n·N_t)`` (mm) from the programmed feed. Tooth ``j``
is at immersion angle ``φ_j = 2π n t + θ0 + 2π j/N_t`` (measured from the +y axis,
clockwise; feed along +x); it cuts while ``φ_st ≤ φ_j ≤ φ_ex`` (slotting: 0…π)
with chip thickness

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

__all__ = ["MillingTool", "feed_force", "mean_feed_force"]


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
        return self.spindle_hz * self.teeth

    def feed_per_tooth(self, feed) -> np.ndarray:
        """Feed per tooth c (mm) from the feed rate (m/s): ``c = feed / (n N_t)``."""
        return np.asarray(feed, dtype=np.float64) * 1e3 / (self.spindle_hz * self.teeth)

    def to_dict(self) -> dict:
        return asdict(self)


@njit(cache=True)
def _feed_force(t0, dt, c, engage, n_rev_s, teeth, a, Ktc, Krc, Kte, Kre, dr, phi_st, phi_ex, theta0, step):
    n = c.size
    out = np.zeros(n)
    two_pi = 2.0 * math.pi
    # sub-points per interval from the angular step
    m = int(math.ceil(two_pi * n_rev_s * dt / step))
    if m < 1:
        m = 1
    pitch = two_pi / teeth
    for k in range(n):
        if engage[k] == 0.0:
            continue
        ck = c[k]
        acc = 0.0
        for i in range(m):
            t = t0 + (k + (i + 0.5) / m) * dt
            theta = two_pi * n_rev_s * t + theta0
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


def feed_force(tool: MillingTool, t0: float, dt: float, feed, engage=None) -> np.ndarray:
    """Feed-direction force resisting the motion (N), averaged over each interval.

    Interval ``k`` is ``[t0 + k dt, t0 + (k+1) dt]``; ``feed`` (m/s, ≥ 0, one value per
    interval) gives the feed per tooth; ``engage`` (0…1 per interval, default 1) scales
    the force (radial immersion growing at the workpiece entry, 0 = not cutting).
    """
    c = tool.feed_per_tooth(np.maximum(np.asarray(feed, dtype=np.float64), 0.0))
    eng = np.ones_like(c) if engage is None else np.asarray(engage, dtype=np.float64)
    if eng.shape != c.shape:
        raise ValueError(f"engage has {eng.size} values, feed has {c.size}")
    teeth = int(tool.teeth)
    lam = math.radians(tool.runout_angle)
    r = np.array([tool.runout * math.cos(lam - 2 * math.pi * j / teeth) for j in range(teeth)])
    dr = r - np.roll(r, 1)  # r_j − r_{j−1}
    return _feed_force(
        float(t0), float(dt), c, eng, tool.spindle_hz, teeth, tool.depth,
        tool.Ktc, tool.Krc, tool.Kte, tool.Kre, dr,
        math.radians(tool.start_angle), math.radians(tool.exit_angle), math.radians(tool.phase),
        math.radians(tool.angle_step),
    )


def mean_feed_force(tool: MillingTool, feed: float) -> float:
    """Closed-form mean slotting force resisting the feed (N) without runout: ``N a c K_rc/4 + N a K_re/π``."""
    c = float(tool.feed_per_tooth(feed))
    return tool.teeth * tool.depth * (c * tool.Krc / 4.0 + tool.Kre / math.pi)
