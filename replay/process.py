"""Process events of a milling scenario with known truth: NC sections, tooth condition, collision, missing stock.

A scenario with a ``[process]`` table (``replay/scenarios/_process.toml`` and its children) is
cut by the per-tooth model (:func:`replay.cutting.feed_force_teeth`) and carries:

* ``program_line`` and ``tool`` columns from ``[program]``: the approach (lead-in) is line
  ``first_line``, feed level i of ``trajectory.levels`` line ``first_line + (i + 1)·line_step``,
  the retract (lead-out) the line after; each section starts at the sample where the ramp to its
  feed starts (:func:`replay.scenarios.reference_velocity`);
* a tooth condition (:class:`replay.cutting.ToothCondition`): per-tooth runout offsets that grow,
  chipped or broken teeth, a material factor on the cutting coefficients;
* collisions: a rectangular force pulse, resisting the feed, of ``factor`` × the cutting force (the
  mean magnitude of the simulated force over the 0.1 s before it) over ``width_s``, averaged
  exactly over each interval;
* missing stock: engagement 0 inside ``[start_s, stop_s)`` (an air cut where the program cuts);
* truth events (:class:`feedio.schema.TruthEvent`) at the time each of these begins, with the
  sample (seq) whose interval holds it and the spindle speed then (``detail.spindle_rpm``), so a
  monitor's detection delay can be scored in seconds and in spindle revolutions.

The runout event is the moment the chip imbalance between the teeth has grown by
``runout_event_fraction`` of the feed per tooth since the growth began,
``(Δh(t) − Δh(t_g)) / c(t) ≥ fraction`` with ``Δh = max_j h_j − min_j h_j`` the effective chips of
:func:`replay.cutting.tooth_chips`: the force of one tooth then differs from the other's by about
that fraction more (cutting force ∝ chip, edge forces aside).
"""

from __future__ import annotations

import math

import numpy as np

from feedio import schema as S

from .cutting import MillingTool, ToothCondition, tooth_chips

__all__ = ["has_process", "check_process", "tooth_condition", "program_columns", "missing_mask", "impulse_force",
           "truth_events", "MAX_EVENTS"]

#: most process events (breaks + impulses + missing sections) one scenario may list
MAX_EVENTS = 1000
#: window before a collision over which the cutting force it is scaled by is averaged (s)
IMPULSE_REFERENCE_S = 0.1
#: NC line numbers are HAL s32 values
_LINE_MAX = 2**31 - 1


def has_process(sc: dict) -> bool:
    return "process" in sc and sc["disturbance"]["kind"] == "milling"


def _num(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _rows(p: dict, key: str, width: int) -> list[list[float]]:
    rows = p[key]
    if not isinstance(rows, list) or len(rows) > MAX_EVENTS:
        raise ValueError(f"process.{key} must be a list of at most {MAX_EVENTS} entries")
    for i, row in enumerate(rows):
        if not (isinstance(row, list) and len(row) == width and all(_num(x) for x in row)):
            raise ValueError(f"process.{key}[{i}] must be a list of {width} finite numbers, got {row!r}")
    return rows


def check_process(sc: dict) -> None:
    """Validate ``[program]`` and ``[process]`` (ValueError naming the constant and its range)."""
    pr, p, T = sc["program"], sc["process"], float(sc["duration"])
    for key in ("tool", "first_line", "line_step"):
        v = pr[key]
        if isinstance(v, bool) or not isinstance(v, int) or not (0 if key == "tool" else 1) <= v <= _LINE_MAX:
            raise ValueError(f"program.{key} must be a whole number in {0 if key == 'tool' else 1} … {_LINE_MAX}, "
                             f"got {v!r}")
    last = pr["first_line"] + pr["line_step"] * (len(sc["trajectory"]["levels"]) + 1)
    if last > _LINE_MAX:
        raise ValueError(f"program: the retract line {last} is beyond {_LINE_MAX}; lower first_line or line_step")
    if not (_num(p["runout_event_fraction"]) and 0 < p["runout_event_fraction"] <= 10):
        raise ValueError(f"process.runout_event_fraction must be in (0, 10], got {p['runout_event_fraction']!r}")
    for i, (t_s, factor, width) in enumerate(_rows(p, "impulses", 3)):
        if not (0 <= t_s < T and 1 <= factor <= 50 and 1e-4 <= width <= 0.1):
            raise ValueError(f"process.impulses[{i}] = [t_s, factor, width_s] needs 0 ≤ t_s < duration ({T:g} s), "
                             f"factor in [1, 50] (× the cutting force) and width in [1e-4, 0.1] s, got "
                             f"{[t_s, factor, width]!r}")
    for i, (start, stop) in enumerate(_rows(p, "missing", 2)):
        if not 0 <= start < stop <= T:
            raise ValueError(f"process.missing[{i}] = [start_s, stop_s] needs 0 ≤ start < stop ≤ duration ({T:g} s), "
                             f"got {[start, stop]!r}")
    _rows(p, "breaks", 3)
    for i, (_, t_s, _) in enumerate(p["breaks"]):
        if not t_s < T:
            raise ValueError(f"process.breaks[{i}]: time {t_s!r} s is not inside the trial (duration {T:g} s)")
    tooth_condition(sc).check(int(sc["disturbance"]["teeth"]))


def tooth_condition(sc: dict) -> ToothCondition:
    p = sc["process"]
    for key in ("runout_offsets_m", "runout_growth_m_per_s"):
        if not (isinstance(p[key], list) and all(_num(x) for x in p[key])):
            raise ValueError(f"process.{key} must be a list of finite numbers (one per tooth), got {p[key]!r}")
    for key in ("material", "runout_growth_from_s"):
        if not _num(p[key]):
            raise ValueError(f"process.{key} must be a finite number, got {p[key]!r}")
    return ToothCondition(
        offsets_m=tuple(float(x) for x in p["runout_offsets_m"]),
        growth_m_per_s=tuple(float(x) for x in p["runout_growth_m_per_s"]),
        growth_from_s=float(p["runout_growth_from_s"]),
        breaks=tuple((int(a), float(b), float(c)) for a, b, c in _rows(p, "breaks", 3)),
        material=float(p["material"]),
    )


def section_starts(sc: dict, n: int, Ts: float) -> np.ndarray:
    """First sample of each section: approach, every feed level, retract (as the trajectory cuts them)."""
    tr = sc["trajectory"]
    levels = len(tr["levels"])
    per = (n * Ts - tr["lead_in"] - tr["lead_out"]) / levels
    starts = [0] + [int(round((tr["lead_in"] + per * i) / Ts)) for i in range(levels + 1)]
    return np.minimum(np.array(starts, dtype=np.int64), n)


def program_columns(sc: dict, n: int, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """``program_line`` and ``tool`` per sample (int64)."""
    pr = sc["program"]
    starts = section_starts(sc, n, Ts)
    section = np.searchsorted(starts, np.arange(n), side="right") - 1
    line = pr["first_line"] + pr["line_step"] * section
    return line.astype(np.int64), np.full(n, int(pr["tool"]), dtype=np.int64)


def missing_mask(sc: dict, t_mid: np.ndarray) -> np.ndarray:
    """1 where stock is present, 0 inside the ``process.missing`` windows (at interval mid-times ``t_mid``)."""
    mask = np.ones_like(t_mid)
    for start, stop in sc["process"]["missing"]:
        mask[(t_mid >= start) & (t_mid < stop)] = 0.0
    return mask


def impulse_force(sc: dict, cutting: np.ndarray, dt: float) -> tuple[np.ndarray, list[tuple[float, float, float]]]:
    """Collision pulses (N) on the grid of ``cutting`` (intervals of dt), and per pulse
    ``(t_s, peak N, cutting force N)``. The pulse of ``factor × F_cut`` covers ``[t_s, t_s + width_s)``,
    averaged exactly over each interval; ``F_cut`` is the mean of ``|cutting|`` over the
    :data:`IMPULSE_REFERENCE_S` before ``t_s`` (the magnitude: in partial immersion the feed force
    swings through zero and its plain mean can be ~0; the closed-form slot mean would not hold)."""
    out = np.zeros_like(cutting)
    info = []
    k = np.arange(cutting.size, dtype=np.float64)
    for t_s, factor, width in sc["process"]["impulses"]:
        i0 = int(t_s / dt)
        ref = cutting[max(0, i0 - max(1, int(round(IMPULSE_REFERENCE_S / dt)))):max(i0, 1)]
        f_cut = float(np.mean(np.abs(ref))) if ref.size else 0.0
        peak = factor * f_cut
        on, off = t_s / dt, (t_s + width) / dt
        out += peak * np.clip(np.minimum(k + 1.0, off) - np.maximum(k, on), 0.0, 1.0)
        info.append((float(t_s), float(peak), f_cut))
    return out, info


def _event(kind: str, t_s: float, Ts: float, n: int, value: float, **detail) -> S.TruthEvent:
    return S.TruthEvent(kind=kind, t_s=float(t_s), seq=min(int(math.floor(t_s / Ts + 1e-9)), n - 1), value=float(value),
                        detail=detail)


def _runout_event(sc: dict, tool: MillingTool, cond: ToothCondition, t: np.ndarray, feed_per_tooth: np.ndarray,
                  engaged: np.ndarray, Ts: float, n: int) -> list[S.TruthEvent]:
    p = sc["process"]
    if not any(p["runout_growth_m_per_s"]):
        return []
    t_g = float(p["runout_growth_from_s"])
    events = [_event("runout_growth", t_g, Ts, n, max(abs(x) for x in p["runout_growth_m_per_s"]),
                     rates_m_per_s=list(p["runout_growth_m_per_s"]))]
    frac = float(p["runout_event_fraction"])
    for k in np.flatnonzero((t >= t_g) & engaged & (feed_per_tooth > 0)):
        c = float(feed_per_tooth[k])
        now = tooth_chips(tool, cond, c, float(t[k]))
        then = tooth_chips(tool, cond, c, t_g)
        grown = ((now.max() - now.min()) - (then.max() - then.min())) / c
        if grown >= frac:
            events.append(_event("runout", float(t[k]), Ts, n, grown, fraction=frac, feed_per_tooth_mm=c))
            break
    return events


def truth_events(sc: dict, tool: MillingTool, t: np.ndarray, v_ref: np.ndarray, spindle_rpm: np.ndarray,
                 engaged: np.ndarray, impulses: list) -> list[S.TruthEvent]:
    """The scenario's truth events, in time order (sample times ``t``, feed ``v_ref`` m/s, spindle
    speed rpm and whether the tool is in the stock, per sample)."""
    n = t.size
    Ts = float(t[1] - t[0]) if n > 1 else 1.0 / sc["rate"]
    p = sc["process"]
    cond = tooth_condition(sc)
    teeth = int(sc["disturbance"]["teeth"])
    events = []
    for tooth, t_s, loss in sorted(p["breaks"], key=lambda b: b[1]):
        events.append(_event("tooth_break", t_s, Ts, n, int(tooth), tooth=int(tooth), loss_m=float(loss),
                             next_tooth=(int(tooth) - 1) % teeth))
    for t_s, peak, f_cut in impulses:
        events.append(_event("collision", t_s, Ts, n, peak, cutting_force_N=f_cut))
    for start, stop in p["missing"]:
        events.append(_event("missing_cut", start, Ts, n, stop - start, stop_s=float(stop)))
        events.append(_event("missing_cut_end", stop, Ts, n, stop - start, start_s=float(start)))
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(spindle_rpm > 0, v_ref * 1e3 / (spindle_rpm / 60.0 * teeth), 0.0)
    events += _runout_event(sc, tool, cond, t, c, engaged, Ts, n)
    for e in events:  # to score a delay in spindle revolutions: delay · n / 60
        e.detail["spindle_rpm"] = float(spindle_rpm[e.seq])
    events.sort(key=lambda e: (e.t_s, e.kind))
    return events
