"""Scenario constants (TOML under ``replay/scenarios/``) and reference trajectories.

A scenario is a nested dict: top-level ``form, machine, axis, rate, duration, block,
fine_rate`` and tables ``drive``, ``model``, ``noise``, ``trajectory``,
``disturbance``. Files may ``extends = "<other scenario>"``; the child's keys
override the parent's, table by table. Every constant can be changed with an
override TOML (``feedmon simulate … --config my.toml``) holding any subset of the
keys; a key that the scenario does not have is an error (catches typos).

Scenarios after the thesis (chapter 3):

* ``shaker-control``, ``shaker-constant``, ``shaker-sweep`` — case study 1: linear
  drive, identification trajectory with speed reversals (trapezoids of several
  amplitudes in both directions, then sinusoids of decreasing amplitude and rising
  frequency, after Erkorkmaz & Altintas), shaker at 55 Hz.
* ``milling-aircut``, ``milling-incdec``, ``milling-inc``, ``milling-dec`` — case
  study 2: CNC X axis, feed in one direction only with feed-rate steps; slotting
  7050 Al, 3000 rpm, 2 flutes, 16 mm, 1.5 mm depth (mechanistic force,
  :mod:`replay.cutting`).

Scenarios for a monitor in production (conditions change while it runs):

* ``milling-spindle-change`` — the spindle speed follows ``[spindle] schedule``
  (``[[t_s, rpm], …]``, ramps at ``accel`` rpm/s); the cutting force follows the
  integrated spindle angle; with ``feed = "per-tooth"`` the feed rate follows the
  speed so that the programmed feed per tooth holds.
* ``shaker-drift`` — viscous and Coulomb friction drift linearly over the trial
  (``[drive_drift]``).
* ``milling-payload`` — an inertia step at ``[drive_step] at`` (``[drive_step]``).
* ``shaker-step`` — a non-periodic force step on and off (disturbance ``kind = "step"``).

Drives the rigid first-order model does not describe (``[structure]``, Stribeck friction;
:mod:`replay.plant`), with the shaker's 55 Hz disturbance (the Stribeck drive: none):

* ``drive-stribeck`` — Coulomb friction 35 N rising to 50 N at standstill (Stribeck, 2 mm/s), slow
  trapezoids;
* ``two-mass`` — motor and load on a spring, 50 Hz resonance, velocity measured at the motor;
* ``command-delay`` — the force acts one sample after it is commanded;
* ``encoder-velocity`` — the velocity is the backward difference of the encoder position.

Process scenarios for a process monitor (:mod:`replay.process`; ``_process`` base: an NC program of
an approach, four feed sections and a retract with ``program_line`` and ``tool`` columns, 2 µm
runout, the per-tooth force model of :mod:`replay.cutting`, truth events on
``/<machine>/<axis>/truth/events``; ``docs/process-monitoring-scenarios.md``):

* ``milling-part`` — the nominal part (the program a part series repeats, :mod:`replay.parts`);
* ``milling-tooth-break`` — tooth 1 breaks at 9 s (its force share drops to 0, tooth 0 cuts
  the chip of both);
* ``milling-runout`` — the runout of tooth 0 grows by 2.5 µm/s from 4 s (the spindle-frequency
  component grows);
* ``milling-collision`` — a force pulse of 10× the cutting force over 6 ms at 8 s;
* ``milling-missing-cut`` — no stock from 11 s to 13 s inside a feed section (an air cut where
  the program cuts).

Drive constants that vary (``[drive_drift]``, ``[drive_step]``, in every scenario;
zero = constant) are evaluated at each sample time ``t_k`` and held over the
interval ``[t_k, t_k + Ts)``, like the controller output (:func:`drive_series`).
"""

from __future__ import annotations

import copy
import math
import tomllib
from importlib import resources
from pathlib import Path

import numpy as np

from feedio.limits import MAX_CONFIG_BYTES, SAMPLE_LIMITS, SPINDLE_RPM_MAX, read_capped
from feedio.mcapio import MAX_TRIAL_SAMPLES

_V_MAX = SAMPLE_LIMITS.v_max  # m/s

__all__ = [
    "SCENARIOS",
    "load_scenario",
    "merge",
    "describe",
    "drive_series",
    "spindle_profile",
    "reference_velocity",
    "engagement",
]

SCENARIOS = (
    "shaker-control",
    "shaker-constant",
    "shaker-sweep",
    "milling-aircut",
    "milling-incdec",
    "milling-inc",
    "milling-dec",
    "milling-spindle-change",
    "shaker-drift",
    "milling-payload",
    "shaker-step",
    "drive-stribeck",
    "two-mass",
    "command-delay",
    "encoder-velocity",
    "milling-part",
    "milling-tooth-break",
    "milling-runout",
    "milling-collision",
    "milling-missing-cut",
)

#: drive constants that may vary over a trial (``[drive_drift]``, ``[drive_step]``)
VARYING = ("inertia", "damping", "coulomb_pos", "coulomb_neg")
#: the most samples one simulated trial holds (at the controller rate, and at fine_rate with --fine): the
#: simulation keeps every sample in memory (~140 bytes each: 10 M ≈ 1.4 GB, 8 h at 333 Hz), and
#: ``read_trial`` (identify) reads no more
MAX_SIM_SAMPLES = MAX_TRIAL_SAMPLES


def describe() -> dict[str, str]:
    """The one-line description of every built-in scenario, in the order of :data:`SCENARIOS`."""
    return {name: str(_resolve(name).get("description", "")) for name in SCENARIOS}


def _read_builtin(name: str) -> dict:
    res = resources.files("replay").joinpath("scenarios", f"{name}.toml")
    try:
        text = res.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}") from None
    return tomllib.loads(text)


def merge(base: dict, override: dict, *, where: str = "", source: str = "override", strict: bool = True) -> dict:
    """Deep-merge ``override`` into a copy of ``base``; unknown keys raise ValueError when ``strict``."""
    out = copy.deepcopy(base)
    for key, value in override.items():
        path = f"{where}.{key}" if where else key
        if key not in out and not strict:
            out[key] = copy.deepcopy(value)
            continue
        if key not in out:
            known = ", ".join(sorted(k for k in out if k != "extends"))
            raise ValueError(f"{source}: unknown scenario key {path!r}; keys here: {known}")
        if isinstance(out[key], dict):
            if not isinstance(value, dict):
                raise ValueError(f"{source}: {path!r} must be a table")
            out[key] = merge(out[key], value, where=path, source=source, strict=strict)
        else:
            if isinstance(value, dict):
                raise ValueError(f"{source}: {path!r} is a value, not a table")
            out[key] = copy.deepcopy(value)
    return out


def _resolve(name: str, depth: int = 0) -> dict:
    if depth > 8:
        raise ValueError(f"scenario {name!r}: 'extends' chain too deep")
    raw = _read_builtin(name)
    parent = raw.pop("extends", None)
    if parent is None:
        return raw
    # a built-in child may add keys its parent lacks (e.g. the shaker constants)
    return merge(_resolve(parent, depth + 1), raw, source=f"scenario {name}", strict=False)


def load_scenario(name: str, config: str | Path | dict | None = None, *, duration: float | None = None) -> dict:
    """The constants of a built-in scenario, with an optional override (TOML path or dict).

    Returns a plain dict with ``name`` set; validated (:func:`check`).
    """
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}")
    sc = _resolve(name)
    if config is not None:
        if isinstance(config, dict):
            override, source = config, "config"
        else:
            path = Path(config)
            try:
                override = tomllib.loads(read_capped(path, MAX_CONFIG_BYTES, "scenario config").decode("utf-8"))
            except OSError as exc:
                raise OSError(f"cannot read scenario config {path}: {exc.strerror or exc}") from exc
            except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
                raise ValueError(f"scenario config {path} is not valid TOML: {exc}") from None
            source = str(path)
        override = dict(override)
        override.pop("extends", None)
        sc = merge(sc, override, source=source)
    if duration is not None:
        sc["duration"] = float(duration)
    sc["name"] = name
    check(sc)
    return sc


def _pos(sc: dict, path: str, *, allow_zero: bool = False) -> float:
    node = sc
    for part in path.split("."):
        node = node[part]
    ok = isinstance(node, (int, float)) and math.isfinite(node) and (node >= 0 if allow_zero else node > 0)
    if not ok:
        raise ValueError(f"scenario constant {path} must be a finite number {'≥' if allow_zero else '>'} 0, got {node!r}")
    return float(node)


def check(sc: dict) -> None:
    """Validate the numbers of a scenario (clear message naming the constant)."""
    if sc["form"] not in ("velocity-loop", "force-input"):
        raise ValueError(f"scenario constant form must be velocity-loop or force-input, got {sc['form']!r}")
    for p in ("rate", "duration", "fine_rate", "drive.inertia", "drive.damping", "drive.loop_gain", "drive.force_constant"):
        _pos(sc, p)
    for p in ("drive.coulomb_pos", "drive.coulomb_neg", "drive.omega", "noise.v_meas_std", "noise.dynamometer_std"):
        _pos(sc, p, allow_zero=True)
    if not 0.0 <= sc["noise"]["glitch_rate"] < 1.0:
        raise ValueError(f"noise.glitch_rate must be in [0, 1), got {sc['noise']['glitch_rate']!r}")
    if int(sc["block"]) != sc["block"] or sc["block"] < 1:
        raise ValueError(f"block must be a positive integer, got {sc['block']!r}")
    if sc["fine_rate"] < sc["rate"]:
        raise ValueError("fine_rate must be ≥ rate")
    if sc["duration"] * sc["rate"] < 10:
        raise ValueError(f"duration {sc['duration']} s is shorter than 10 samples")
    if sc["duration"] * sc["rate"] > MAX_SIM_SAMPLES:
        raise ValueError(f"duration {sc['duration']:g} s at rate {sc['rate']:g} Hz is {sc['duration'] * sc['rate']:.4g} "
                         f"samples, more than one simulated trial holds ({MAX_SIM_SAMPLES:,}: every sample is kept in "
                         f"memory); simulate at most {MAX_SIM_SAMPLES / sc['rate']:g} s at this rate")
    kind = sc["trajectory"]["kind"]
    if kind not in ("identification", "feed-steps"):
        raise ValueError(f"trajectory.kind must be identification or feed-steps, got {kind!r}")
    _pos(sc, "trajectory.accel")
    lists = ("amplitudes", "sine_amplitudes", "sine_frequencies") if kind == "identification" else ("levels",)
    for p in ("rest", "hold", "dwell") if kind == "identification" else ("lead_in", "lead_out"):
        _pos(sc, f"trajectory.{p}", allow_zero=True)
    if kind == "identification":
        _pos(sc, "trajectory.sine_cycles")
    for name in lists:
        values = sc["trajectory"][name]
        if not isinstance(values, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                   and math.isfinite(x) and (x > 0 if name == "sine_frequencies"
                                                                             else abs(x) <= _V_MAX) for x in values):
            raise ValueError(f"trajectory.{name} must be a list of finite numbers "
                             + {"sine_frequencies": "> 0 (Hz)", "levels": f"within ±{_V_MAX:g} (mm per tooth)"}.get(
                                 name, f"within ±{_V_MAX:g} m/s")
                             + f", got {values!r}")
    dk = sc["disturbance"]["kind"]
    if dk not in ("none", "shaker", "milling", "step"):
        raise ValueError(f"disturbance.kind must be none, shaker, milling or step, got {dk!r}")
    if dk == "step":
        _finite(sc, "disturbance.force")
    if dk in ("shaker", "step"):
        start, stop = _finite(sc, "disturbance.start"), _finite(sc, "disturbance.stop")
        if not 0.0 <= start <= stop <= 1.0:
            raise ValueError(f"disturbance.start and .stop are fractions of the duration with 0 ≤ start ≤ stop ≤ 1, "
                             f"got {start!r} and {stop!r}")
    _check_variation(sc)
    _check_structure(sc)
    if dk == "milling":
        _check_spindle(sc)
    if "process" in sc:
        from .process import check_process

        check_process(sc)


def _finite(sc: dict, path: str) -> float:
    node = sc
    for part in path.split("."):
        node = node[part]
    if isinstance(node, bool) or not isinstance(node, (int, float)) or not math.isfinite(node):
        raise ValueError(f"scenario constant {path} must be a finite number, got {node!r}")
    return float(node)


def _check_variation(sc: dict) -> None:
    """``[drive_drift]`` / ``[drive_step]``: relative changes keeping J, B > 0 and the friction ≥ 0."""
    at = _finite(sc, "drive_step.at")
    if not 0.0 <= at <= 1.0:
        raise ValueError(f"drive_step.at is a fraction of the duration in [0, 1], got {at!r}")
    for table in ("drive_drift", "drive_step"):
        unknown = set(sc[table]) - set(VARYING) - ({"at"} if table == "drive_step" else set())
        if unknown:
            raise ValueError(f"{table} has no constant {sorted(unknown)[0]!r}; it varies {', '.join(VARYING)}")
        for name in VARYING:
            rel = _finite(sc, f"{table}.{name}")
            positive = name in ("inertia", "damping")
            if rel < -1.0 or (positive and rel == -1.0):
                raise ValueError(
                    f"{table}.{name} = {rel!r} would make drive.{name} {'≤' if positive else '<'} 0 "
                    f"(a relative change must be {'>' if positive else '≥'} −1)"
                )


def _check_structure(sc: dict) -> None:
    """``[structure]`` and the Stribeck constants of ``[drive]`` (:mod:`replay.plant`)."""
    from .plant import STRUCTURE_KINDS, VELOCITY

    st = sc["structure"]
    if st["kind"] not in STRUCTURE_KINDS:
        raise ValueError(f"structure.kind must be one of {', '.join(STRUCTURE_KINDS)}, got {st['kind']!r}")
    if st["velocity"] not in VELOCITY:
        raise ValueError(f"structure.velocity must be one of {', '.join(VELOCITY)}, got {st['velocity']!r}")
    for p in ("structure.resonance", "structure.resonance_damping", "structure.encoder_resolution",
              "drive.stribeck_speed"):
        _pos(sc, p)
    _pos(sc, "drive.stribeck_force", allow_zero=True)
    share = _finite(sc, "structure.motor_share")
    if not 0.0 < share < 1.0:
        raise ValueError(f"structure.motor_share is the motor's share of the inertia, in (0, 1), got {share!r}")
    delay = st["delay"]
    if isinstance(delay, bool) or not isinstance(delay, int) or not 0 <= delay <= 16:
        raise ValueError(f"structure.delay must be a whole number of samples 0 … 16, got {delay!r}")
    if 2.0 * st["resonance"] * 1.0 / sc["rate"] >= 1.0 and st["kind"] == "two-mass":
        raise ValueError(f"structure.resonance {st['resonance']!r} Hz is at or above half the sample rate "
                         f"({sc['rate'] / 2:g} Hz): the loop at this rate cannot carry it; lower it")


def _check_spindle(sc: dict) -> None:
    d, sp = sc["disturbance"], sc["spindle"]
    rpm0 = _pos(sc, "disturbance.spindle_rpm", allow_zero=True)
    if rpm0 > SPINDLE_RPM_MAX:
        raise ValueError(f"disturbance.spindle_rpm must be ≤ {SPINDLE_RPM_MAX:g} rpm, got {rpm0!r}")
    _pos(sc, "spindle.accel", allow_zero=True)
    if sp["feed"] not in ("per-tooth", "rate"):
        raise ValueError(f"spindle.feed must be per-tooth or rate, got {sp['feed']!r}")
    sched = sp["schedule"]
    if not isinstance(sched, list):
        raise ValueError("spindle.schedule must be a list of [t_s, rpm] pairs")
    prev = -math.inf
    for i, item in enumerate(sched):
        ok = isinstance(item, list) and len(item) == 2 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in item
        )
        if not ok:
            raise ValueError(f"spindle.schedule[{i}] must be a pair [t_s, rpm] of finite numbers, got {item!r}")
        t_s, rpm = float(item[0]), float(item[1])
        if not (prev < t_s < sc["duration"]) or t_s < 0:
            raise ValueError(
                f"spindle.schedule[{i}]: time {t_s!r} s must be ≥ 0, after the previous entry and inside the trial "
                f"(duration {sc['duration']!r} s); shorten the schedule or lengthen the trial"
            )
        if not 0.0 < rpm <= SPINDLE_RPM_MAX:
            raise ValueError(f"spindle.schedule[{i}]: speed must be in (0, {SPINDLE_RPM_MAX:g}] rpm, got {rpm!r}")
        prev = t_s
    if sched and (rpm0 <= 0 or not d.get("cutting", True)):
        raise ValueError("spindle.schedule needs a turning spindle while cutting (disturbance.spindle_rpm > 0, "
                         "disturbance.cutting = true)")


def drive_series(sc: dict, t: np.ndarray) -> dict[str, np.ndarray]:
    """The drive constants at the sample times ``t`` (s): ``inertia`` (kg), ``damping`` (N·s/m),
    ``coulomb_pos``, ``coulomb_neg`` (N, magnitudes), each held over ``[t_k, t_k + Ts)``.

    ``value(t) = drive.value · (1 + drift · t/duration) · (1 + step · [t ≥ at·duration])``.
    """
    t = np.asarray(t, dtype=np.float64)
    T = float(sc["duration"])
    after = t >= float(sc["drive_step"]["at"]) * T
    out = {}
    for name in VARYING:
        drift = float(sc["drive_drift"][name])
        step = float(sc["drive_step"][name])
        value = np.full(t.shape, float(sc["drive"][name]))
        if drift:
            value = value * (1.0 + drift * t / T)
        if step:
            value = np.where(after, value * (1.0 + step), value)
        out[name] = value
    return out


def spindle_profile(sc: dict):
    """The spindle speed and angle over the trial (:class:`replay.cutting.SpindleProfile`),
    or None for scenarios without a spindle. ``disturbance.spindle_rpm`` until the first
    entry of ``spindle.schedule``, from angle ``disturbance.phase``."""
    from .cutting import SpindleProfile

    d = sc["disturbance"]
    if d["kind"] != "milling":
        return None
    rpm0 = float(d["spindle_rpm"]) if d.get("cutting", True) else 0.0
    sp = sc["spindle"]
    return SpindleProfile(rpm0, [tuple(x) for x in sp["schedule"]], accel=float(sp["accel"]), phase=float(d["phase"]))


# ---------------------------------------------------------------------------------------------
# trajectories (sampled at Ts; the velocity loop holds v_r over each interval)
# ---------------------------------------------------------------------------------------------
# Every part is cut at ``limit`` samples (the trial's length): the trial keeps only its first n samples,
# so a longer part changes nothing but would be allocated in full (a 1e6 s hold: ~24 GB).
def _ramp(v0: float, v1: float, accel: float, Ts: float, limit: int) -> np.ndarray:
    n = max(int(math.ceil(abs(v1 - v0) / (accel * Ts))), 1)
    return v0 + (v1 - v0) * np.arange(1, min(n, limit) + 1) / n


def _hold(v: float, seconds: float, Ts: float, limit: int) -> np.ndarray:
    return np.full(min(max(int(round(seconds / Ts)), 0), limit), float(v))


def _identification_cycle(tr: dict, Ts: float, limit: int) -> np.ndarray:
    parts = [np.zeros(0)]
    v = 0.0
    for amp in tr["amplitudes"]:
        for target in (amp, -amp, 0.0):
            parts.append(_ramp(v, target, tr["accel"], Ts, limit))
            v = target
            parts.append(_hold(v, tr["hold"] if target else tr["dwell"], Ts, limit))
    for amp, freq in zip(tr["sine_amplitudes"], tr["sine_frequencies"], strict=True):
        n = int(round(tr["sine_cycles"] / freq / Ts))
        k = np.arange(1, min(n, limit) + 1)
        parts.append(amp * np.sin(2 * np.pi * freq * k * Ts))
        parts.append(_hold(0.0, tr["dwell"], Ts, limit))
    return np.concatenate(parts)


def reference_velocity(sc: dict, n: int, Ts: float) -> np.ndarray:
    """Reference velocity v_r(k), k = 0…n−1 (m/s)."""
    tr = sc["trajectory"]
    if tr["kind"] == "identification":
        rest = _hold(0.0, tr["rest"], Ts, n)
        cycle = _identification_cycle(tr, Ts, n)
        if cycle.size == 0:  # no amplitudes, no sines, no dwell: the axis stays at rest
            cycle = np.zeros(1)
        reps = int(math.ceil(max(n - rest.size, 0) / cycle.size)) + 1
        v = np.concatenate([rest, np.tile(cycle, reps)])
        return v[:n].copy()
    # feed-steps: lead-in from rest, equal time per level, lead-out to rest
    tool_hz = sc["disturbance"]["spindle_rpm"] / 60.0 * sc["disturbance"]["teeth"]
    if tool_hz <= 0:  # air cut with the spindle off: feed rates as programmed for 3000 rpm
        tool_hz = 3000.0 / 60.0 * sc["disturbance"]["teeth"]
    feeds = [c * 1e-3 * tool_hz for c in tr["levels"]]  # mm/tooth → m/s
    accel = tr["accel"]
    t_levels = n * Ts - tr["lead_in"] - tr["lead_out"]
    if t_levels <= 0:
        raise ValueError("duration too short for trajectory.lead_in + lead_out")
    per = t_levels / len(feeds)
    parts = [_ramp(0.0, feeds[0], accel, Ts, n)]
    parts.append(_hold(feeds[0], tr["lead_in"] - parts[0].size * Ts, Ts, n))
    v = feeds[0]
    for i, f in enumerate(feeds):
        if i:
            parts.append(_ramp(v, f, accel, Ts, n))
            v = f
        start = sum(p.size for p in parts)
        end_level = int(round((tr["lead_in"] + per * (i + 1)) / Ts))
        parts.append(_hold(v, (end_level - start) * Ts, Ts, n))
    parts.append(_ramp(v, 0.0, accel, Ts, n))
    out = np.concatenate(parts)
    if out.size < n:
        out = np.concatenate([out, np.zeros(n - out.size)])
    out = out[:n].copy()
    spindle = sc.get("spindle", {})
    if spindle.get("schedule") and spindle.get("feed") == "per-tooth":
        # feed per revolution: the feed rate follows the spindle speed, the feed per tooth holds
        rpm0 = float(sc["disturbance"]["spindle_rpm"])
        out *= spindle_profile(sc).speed(np.arange(n) * Ts) / rpm0
    return out


def engagement(sc: dict, t: np.ndarray) -> np.ndarray:
    """Milling engagement 0…1 at times t: ramps up over ``entry`` s after ``lead_in``,
    down over ``entry`` s before the lead-out (tool entering / leaving the slot)."""
    d = sc["disturbance"]
    if not d.get("cutting", True):
        return np.zeros_like(t)
    t_in = sc["trajectory"]["lead_in"]
    t_out = sc["duration"] - sc["trajectory"]["lead_out"]
    entry = max(float(d["entry"]), 1e-9)
    up = np.clip((t - t_in) / entry, 0.0, 1.0)
    down = np.clip((t_out - t) / entry, 0.0, 1.0)
    return np.minimum(up, down)
